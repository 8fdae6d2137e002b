//! Checking a gateway file's text into a [`Gateway`]: the TOML decoded into its sections, each
//! setting checked with the command line's own rules (`crate::settings`), every front-end
//! checked against its transport and against the front-ends before it. Every error names the
//! key, the front-end and the line.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::ops::Range;
use std::path::{Path, PathBuf};

use toml::Spanned;
use xrce_common::session::admission::KeyArg;
use xrce_frontend::cli::{AdmissionArgs, TransportKind};
use xrce_frontend::transport::registry::{Medium, TRANSPORTS};

use super::{
    AgentSection, ConfigError, File, FrontendSection, Gateway, GatewayFrontend, MetricsSection,
    ProcessCount, WorkerSection,
};
use crate::cli::FrontendPlan;
use crate::settings;

/// Checks a gateway file's text (`path` names it in errors and anchors relative paths).
pub fn parse(path: &Path, text: &str) -> Result<Gateway, ConfigError> {
    let c = Checker { path, text };
    let file = c.decode()?;
    check_agent(&c, &file.agent)?;
    let worker = check_worker(&c, &file.worker)?;
    let metrics = metrics_listen(&c, &file.metrics)?;
    if file.frontend.is_empty() {
        return Err(c.err(
            0..0,
            "no [[frontend]]: a gateway serves at least one transport",
        ));
    }
    let mut taken = Taken::default();
    let frontends = file
        .frontend
        .iter()
        .enumerate()
        .map(|(index, section)| taken.frontend(&c, index, section))
        .collect::<Result<_, _>>()?;
    Ok(Gateway {
        path: path.to_path_buf(),
        agent: file.agent,
        worker,
        frontends,
        metrics,
    })
}

/// `[agent]`: each value within its setting's bounds.
fn check_agent(c: &Checker<'_>, agent: &AgentSection) -> Result<(), ConfigError> {
    if let Some(v) = &agent.verbose {
        settings::check_verbose(*v.get_ref())
            .map_err(|e| c.err(v.span(), format!("agent.verbose {e}")))?;
    }
    if let Some(m) = &agent.memory_limit_mib {
        settings::check_memory_limit_mib(*m.get_ref())
            .map_err(|e| c.err(m.span(), format!("agent.memory_limit_mib {e}")))?;
    }
    if let Some(i) = &agent.instance {
        settings::check_instance(i)
            .map_err(|e| c.err(c.key("agent", "instance"), format!("agent.instance {e}")))?;
    }
    Ok(())
}

/// `[worker]`: each value within its setting's bounds; the references file loaded and the
/// type-hash folders resolved against the file's directory (what the worker is given).
fn check_worker(c: &Checker<'_>, w: &WorkerSection) -> Result<WorkerSection, ConfigError> {
    let in_worker = |key: &str, e: String| c.err(c.key("worker", key), format!("worker.{key} {e}"));
    if let Some(g) = w.frontend_grace {
        settings::check_frontend_grace(g).map_err(|e| in_worker("frontend_grace", e))?;
    }
    if let Some(n) = w.max_domains {
        settings::check_max_domains(n).map_err(|e| in_worker("max_domains", e))?;
    }
    for (key, value) in [
        (
            "max_entities_per_client",
            w.max_entities_per_client.map(|v| v as u64),
        ),
        ("max_entities", w.max_entities.map(|v| v as u64)),
        (
            "max_samples_per_endpoint",
            w.max_samples_per_endpoint.map(u64::from),
        ),
        (
            "max_instances_per_endpoint",
            w.max_instances_per_endpoint.map(u64::from),
        ),
        ("max_samples_per_client", w.max_samples_per_client),
        ("max_samples", w.max_samples),
    ] {
        if value == Some(0) {
            return Err(in_worker(key, "must be at least 1".into()));
        }
    }
    if let Some(d) = &w.domains {
        settings::parse_domains(d).map_err(|e| in_worker("domains", e.to_string()))?;
    }
    if let Some(m) = &w.middleware {
        crate::cli::backend_for(m, w.dds_backend).map_err(|e| {
            c.err(
                c.key("worker", "middleware"),
                format!("worker.middleware: {e}"),
            )
        })?;
    }
    let base = c.path.parent().unwrap_or(Path::new("."));
    let mut worker = w.clone();
    worker.zenoh_type_hashes = w.zenoh_type_hashes.iter().map(|p| base.join(p)).collect();
    if let Some(r) = &w.refs {
        let resolved = base.join(r.get_ref());
        if let Err(e) = xrce_dds_worker::references::References::load(&resolved) {
            return Err(c.err(r.span(), format!("worker.refs: {e}")));
        }
        worker.refs = Some(Spanned::new(r.span(), resolved));
    }
    Ok(worker)
}

/// `[metrics] listen`: an address and port, if given.
fn metrics_listen(
    c: &Checker<'_>,
    metrics: &MetricsSection,
) -> Result<Option<SocketAddr>, ConfigError> {
    let Some(l) = &metrics.listen else {
        return Ok(None);
    };
    l.get_ref().parse::<SocketAddr>().map(Some).map_err(|_| {
        c.err(
            l.span(),
            format!(
                "metrics.listen {:?} is not an address and port (e.g. \"127.0.0.1:9464\" or \"[::1]:9464\")",
                l.get_ref()
            ),
        )
    })
}

/// What the front-ends checked so far hold, which a later one may not take again: ids,
/// names, ports (with their protocol and address) and serial devices, each with the number
/// of the front-end that holds it.
#[derive(Default)]
struct Taken {
    ids: HashMap<u32, usize>,
    names: HashMap<String, usize>,
    ports: HashMap<(bool, u16, IpAddr), usize>,
    devices: HashMap<PathBuf, usize>,
}

/// Errors about one `[[frontend]]`, named by its number and transport.
struct InFrontend<'a> {
    c: &'a Checker<'a>,
    /// 1-based place in the file.
    n: usize,
    kind: TransportKind,
    /// The whole table, for a key that is missing.
    table: Range<usize>,
}

impl InFrontend<'_> {
    fn err(&self, key: &str, span: Range<usize>, what: &str) -> ConfigError {
        self.c.err(
            span,
            format!("frontend {} ({}): `{key}` {what}", self.n, self.kind.name()),
        )
    }

    /// `value` of `key` when it is at least 1, `default` when it is left out.
    fn at_least_one(
        &self,
        value: &Option<Spanned<usize>>,
        key: &str,
        default: usize,
    ) -> Result<usize, ConfigError> {
        match value {
            Some(m) if *m.get_ref() == 0 => Err(self.err(key, m.span(), "must be at least 1")),
            Some(m) => Ok(*m.get_ref()),
            None => Ok(default),
        }
    }
}

impl Taken {
    /// Checks the `index`th `[[frontend]]` against its transport and the ones before it.
    fn frontend(
        &mut self,
        c: &Checker<'_>,
        index: usize,
        section: &Spanned<FrontendSection>,
    ) -> Result<GatewayFrontend, ConfigError> {
        let f = section.get_ref();
        let n = index + 1;
        let kind = TransportKind::by_name(f.transport.get_ref()).ok_or_else(|| {
            c.err(
                f.transport.span(),
                format!(
                    "frontend {n}: transport {:?} is not one of {}",
                    f.transport.get_ref(),
                    TRANSPORTS.map(|t| t.name).join(", ")
                ),
            )
        })?;
        let at = InFrontend {
            c,
            n,
            kind,
            table: section.span(),
        };
        refuse_keys_of_other_transports(&at, f)?;
        let plan = match kind.medium() {
            Medium::Datagrams | Medium::Streams => self.ip_plan(&at, f)?,
            Medium::SerialLines => self.serial_plan(&at, f)?,
            Medium::Pseudoterminal => FrontendPlan::Pty {
                baudrate: f.baudrate.as_ref().map_or(115_200, |b| *b.get_ref()),
            },
        };
        let id = f.id.as_ref().map_or(index as u32, |i| *i.get_ref());
        if let Some(other) = self.ids.insert(id, n) {
            let span = f.id.as_ref().map_or(at.table.clone(), Spanned::span);
            return Err(at.err("id", span, &format!("{id} is also frontend {other}'s")));
        }
        let name = self.name(&at, f, id)?;
        let client_dead_time = match &f.client_dead_time {
            Some(d) => Some(
                settings::check_client_dead_time(*d.get_ref())
                    .map_err(|e| at.err("client_dead_time", d.span(), &e))?,
            ),
            None => None,
        };
        let dialect = match &f.dialect {
            Some(d) => Some(d.get_ref().parse().map_err(|_: String| {
                at.err("dialect", d.span(), "must be \"spec\" or \"eprosima\"")
            })?),
            None => None,
        };
        Ok(GatewayFrontend {
            name,
            id,
            plan,
            discovery: f.discovery.as_ref().map(|d| *d.get_ref()),
            client_dead_time,
            dialect,
            admission: admission(&at, f)?,
        })
    }

    /// A UDP or TCP front-end's port, address and connection bound; no two front-ends of
    /// one protocol on one port with overlapping addresses.
    fn ip_plan(
        &mut self,
        at: &InFrontend<'_>,
        f: &FrontendSection,
    ) -> Result<FrontendPlan, ConfigError> {
        let kind = at.kind;
        let is_tcp = kind.medium() == Medium::Streams;
        let port = f
            .port
            .as_ref()
            .ok_or_else(|| at.err("port", at.table.clone(), "is required"))?;
        if *port.get_ref() == 0 {
            return Err(at.err("port", port.span(), "must be 1 to 65535"));
        }
        if let Some(d) = f.discovery.as_ref().filter(|d| *d.get_ref() == 0) {
            return Err(at.err("discovery", d.span(), "must be 1 to 65535"));
        }
        let v6 = kind.is_ipv6();
        let bind = match &f.bind {
            Some(b) if b.get_ref().is_ipv6() != v6 => {
                return Err(at.err(
                    "bind",
                    b.span(),
                    &format!("{} is not an address of {}", b.get_ref(), kind.name()),
                ));
            }
            Some(b) => *b.get_ref(),
            None if v6 => IpAddr::V6(Ipv6Addr::UNSPECIFIED),
            None => IpAddr::V4(Ipv4Addr::UNSPECIFIED),
        };
        let max_connections = match &f.max_connections {
            Some(m) if *m.get_ref() == 0 => {
                return Err(at.err("max_connections", m.span(), "must be at least 1"))
            }
            Some(m) => *m.get_ref(),
            None => xrce_frontend::transport::tcp::TcpConfig::default().max_connections,
        };
        let p = *port.get_ref();
        let clash = self
            .ports
            .iter()
            .find(|(&(tcp, q, addr), _)| tcp == is_tcp && q == p && overlaps(addr, bind));
        if let Some((_, other)) = clash {
            return Err(at.err(
                "port",
                port.span(),
                &format!("{p} is also served by frontend {other}"),
            ));
        }
        self.ports.insert((is_tcp, p, bind), at.n);
        let processes = match &f.processes {
            None => 1,
            Some(v) => {
                let parsed: Result<u16, String> = match v.get_ref() {
                    ProcessCount::Word(w) => settings::parse_processes(w),
                    ProcessCount::Count(n) => u16::try_from(*n)
                        .map_err(|_| {
                            format!(
                                "must be 1 to {}, got {n}",
                                crate::shared_port::MAX_PROCESSES
                            )
                        })
                        .and_then(settings::check_processes),
                };
                parsed.map_err(|e| at.err("processes", v.span(), &e))?
            }
        };
        Ok(FrontendPlan::Ip {
            kind,
            listen: SocketAddr::new(bind, p),
            max_connections: if is_tcp { max_connections } else { 0 },
            processes,
        })
    }

    /// A serial front-end's devices (`device` for serial, `devices` for multiserial), none
    /// named twice in the file.
    fn serial_plan(
        &mut self,
        at: &InFrontend<'_>,
        f: &FrontendSection,
    ) -> Result<FrontendPlan, ConfigError> {
        let one = at.kind.spec().one_device;
        let list: Vec<(PathBuf, Range<usize>)> = match (one, &f.device, &f.devices) {
            (true, Some(d), None) => vec![(d.get_ref().clone(), d.span())],
            (true, _, Some(d)) => {
                return Err(at.err(
                    "devices",
                    d.span(),
                    "is for multiserial; serial takes `device`",
                ))
            }
            (true, None, None) => return Err(at.err("device", at.table.clone(), "is required")),
            (_, Some(d), _) => {
                return Err(at.err(
                    "device",
                    d.span(),
                    "is for serial; multiserial takes `devices`",
                ))
            }
            (_, None, Some(d)) if d.get_ref().is_empty() => {
                return Err(at.err("devices", d.span(), "names no device"))
            }
            (_, None, Some(d)) => d.get_ref().iter().map(|p| (p.clone(), d.span())).collect(),
            (_, None, None) => return Err(at.err("devices", at.table.clone(), "is required")),
        };
        for (dev, span) in &list {
            if let Some(other) = self.devices.insert(dev.clone(), at.n) {
                let whom = if other == at.n {
                    "twice here".to_string()
                } else {
                    format!("by frontend {other} too")
                };
                return Err(at.err(
                    "device",
                    span.clone(),
                    &format!("{} is named {whom}", dev.display()),
                ));
            }
        }
        Ok(FrontendPlan::Serial {
            kind: at.kind,
            devices: list.into_iter().map(|(p, _)| p).collect(),
            baudrate: f.baudrate.as_ref().map_or(115_200, |b| *b.get_ref()),
            flow_control: f.flow_control.as_ref().is_some_and(|b| *b.get_ref()),
        })
    }

    /// The front-end's name (default: transport and id): a word of at most 48 characters,
    /// not another process's and not another front-end's.
    fn name(
        &mut self,
        at: &InFrontend<'_>,
        f: &FrontendSection,
        id: u32,
    ) -> Result<String, ConfigError> {
        let name = f.name.as_ref().map_or_else(
            || format!("{}-{id}", at.kind.name()),
            |s| s.get_ref().clone(),
        );
        let span = f.name.as_ref().map_or(at.table.clone(), Spanned::span);
        if name.is_empty()
            || name.len() > 48
            || !name
                .chars()
                .all(|ch| ch.is_ascii_alphanumeric() || ch == '-' || ch == '_')
        {
            return Err(at.err("name", span, "must be 1-48 characters of [A-Za-z0-9_-]"));
        }
        if ["worker", "metrics", "supervisor"].contains(&name.as_str()) {
            return Err(at.err(
                "name",
                span,
                &format!("{name:?} names another process of the agent (for --process)"),
            ));
        }
        if let Some(other) = self.names.insert(name.clone(), at.n) {
            return Err(at.err(
                "name",
                span,
                &format!("{name:?} is also frontend {other}'s"),
            ));
        }
        Ok(name)
    }
}

/// Keys that do not apply to the front-end's transport are mistakes, not silently ignored.
fn refuse_keys_of_other_transports(
    at: &InFrontend<'_>,
    f: &FrontendSection,
) -> Result<(), ConfigError> {
    let ip_only = [
        ("port", f.port.as_ref().map(Spanned::span)),
        ("bind", f.bind.as_ref().map(Spanned::span)),
        ("discovery", f.discovery.as_ref().map(Spanned::span)),
    ];
    let serial_only = [
        ("device", f.device.as_ref().map(Spanned::span)),
        ("devices", f.devices.as_ref().map(Spanned::span)),
        ("flow_control", f.flow_control.as_ref().map(Spanned::span)),
        ("baudrate", f.baudrate.as_ref().map(Spanned::span)),
    ];
    let (foreign, only) = if at.kind.is_ip() {
        // A pseudoterminal takes `baudrate` too, so it is an IP transport's mistake only.
        (&serial_only[..], "applies to serial transports only")
    } else {
        (&ip_only[..], "applies to udp and tcp only")
    };
    if let Some((key, Some(span))) = foreign.iter().find(|(_, s)| s.is_some()) {
        return Err(at.err(key, span.clone(), only));
    }
    if let (false, Some(m)) = (at.kind.medium() == Medium::Streams, &f.max_connections) {
        return Err(at.err("max_connections", m.span(), "applies to tcp only"));
    }
    if let (false, Some(p)) = (at.kind.medium() == Medium::Datagrams, &f.processes) {
        return Err(at.err(
            "processes",
            p.span(),
            "applies to udp only (a TCP, serial or pseudoterminal front-end is one process)",
        ));
    }
    Ok(())
}

/// The front-end's allow-list, roaming and quotas (left-out keys take the options'
/// defaults).
fn admission(at: &InFrontend<'_>, f: &FrontendSection) -> Result<AdmissionArgs, ConfigError> {
    let mut allow_keys = Vec::new();
    if let Some(keys) = &f.allow_keys {
        if keys.get_ref().is_empty() {
            return Err(at.err(
                "allow_keys",
                keys.span(),
                "names no key (leave it out to admit every key)",
            ));
        }
        for k in keys.get_ref() {
            let key = k
                .parse::<KeyArg>()
                .map_err(|e| at.err("allow_keys", keys.span(), &e.to_string()))?;
            allow_keys.push(key);
        }
    }
    let d = AdmissionArgs::default();
    Ok(AdmissionArgs {
        allow_keys,
        allow_roaming: f.allow_roaming.unwrap_or(false),
        max_objects_per_client: at.at_least_one(
            &f.max_objects_per_client,
            "max_objects_per_client",
            xrce_common::session::graph::MAX_OBJECTS,
        )?,
        max_client_messages_per_second: f.max_client_messages_per_second.unwrap_or(0),
        max_client_bytes_per_second: f.max_client_bytes_per_second.unwrap_or(0),
        memory_budget_mib: at.at_least_one(
            &f.memory_budget_mib,
            "memory_budget_mib",
            d.memory_budget_mib,
        )?,
        max_sessions: at.at_least_one(&f.max_sessions, "max_sessions", d.max_sessions)?,
        max_sessions_per_address: at.at_least_one(
            &f.max_sessions_per_address,
            "max_sessions_per_address",
            d.max_sessions_per_address,
        )?,
        new_sessions_per_second: f
            .new_sessions_per_second
            .unwrap_or(d.new_sessions_per_second),
        max_connections_per_address: at.at_least_one(
            &f.max_connections_per_address,
            "max_connections_per_address",
            d.max_connections_per_address,
        )?,
        tcp_idle_timeout: f.tcp_idle_timeout.unwrap_or(d.tcp_idle_timeout),
        closed_session_grace: f.closed_session_grace.unwrap_or(d.closed_session_grace),
    })
}

/// The 1-based line of a byte offset.
fn line_of(text: &str, offset: usize) -> usize {
    text.get(..offset.min(text.len()))
        .map_or(1, |t| t.bytes().filter(|b| *b == b'\n').count() + 1)
}

struct Checker<'a> {
    path: &'a Path,
    text: &'a str,
}

impl Checker<'_> {
    /// Where `key` of `[table]` is written (its line), for values checked after parsing.
    fn key(&self, table: &str, key: &str) -> Range<usize> {
        let mut offset = 0;
        let mut in_table = false;
        for line in self.text.split_inclusive('\n') {
            let t = line.trim();
            if t.starts_with('[') {
                in_table = t.trim_matches(|c| c == '[' || c == ']').trim() == table;
            } else if in_table
                && t.strip_prefix(key)
                    .is_some_and(|rest| rest.trim_start().starts_with('='))
            {
                return offset..offset + line.len();
            }
            offset += line.len();
        }
        0..0
    }

    fn err(&self, span: Range<usize>, message: impl Into<String>) -> ConfigError {
        ConfigError {
            path: self.path.display().to_string(),
            line: line_of(self.text, span.start),
            message: message.into(),
        }
    }
}

/// The key a value error is about, as the file spells it (`frontend[0].port`), without the
/// parts `toml::Spanned` adds to the path.
fn key_path(path: &serde_path_to_error::Path) -> String {
    use serde_path_to_error::Segment;
    let mut out = String::new();
    for segment in path.iter() {
        match segment {
            Segment::Seq { index } => out.push_str(&format!("[{index}]")),
            Segment::Map { key } | Segment::Enum { variant: key } => {
                if key.starts_with("$__serde_spanned") {
                    continue;
                }
                if !out.is_empty() {
                    out.push('.');
                }
                out.push_str(key);
            }
            Segment::Unknown => {}
        }
    }
    out
}

/// What went wrong with the value of `key`, in the words of the file
/// (`frontend[0].port: expected a port number 1-65535, got "not a number"`), from serde's
/// message (`invalid type: string "not a number", expected u16`). Messages of another shape
/// (an unknown or missing key) are kept, after the key's path.
fn describe_value_error(key: &str, message: &str) -> String {
    let leaf = key.rsplit('.').next().unwrap_or(key);
    let got_expected = message
        .strip_prefix("invalid type: ")
        .or_else(|| message.strip_prefix("invalid value: "))
        .and_then(|m| m.rsplit_once(", expected "));
    let Some((got, expected)) = got_expected else {
        return if key.is_empty() {
            message.to_string()
        } else {
            format!("{key}: {message}")
        };
    };
    let got = got
        .strip_prefix("string ")
        .or_else(|| got.strip_prefix("integer "))
        .or_else(|| got.strip_prefix("floating point "))
        .or_else(|| got.strip_prefix("boolean "))
        .unwrap_or(got)
        .trim_matches('`');
    let expected = match (leaf, expected) {
        ("port" | "discovery", _) => "a port number 1-65535",
        (_, "u8") => "a whole number 0-255",
        (_, "u16") => "a whole number 0-65535",
        (_, "u32") => "a whole number 0-4294967295",
        (_, "u64" | "usize") => "a whole number (0 or more)",
        (_, "f64") => "a number",
        (_, "a boolean") => "true or false",
        (_, "a sequence") => "a list ([...])",
        (_, other) => other,
    };
    format!("{key}: expected {expected}, got {got}")
}

/// Whether sockets bound to `a` and `b` (same port and protocol) would collide: the same
/// address, a wildcard of the same family, or the IPv6 wildcard (dual-stack) with anything.
fn overlaps(a: IpAddr, b: IpAddr) -> bool {
    let v6_any = |x: IpAddr| x.is_ipv6() && x.is_unspecified();
    a == b
        || (a.is_ipv6() == b.is_ipv6() && (a.is_unspecified() || b.is_unspecified()))
        || v6_any(a)
        || v6_any(b)
}

impl Checker<'_> {
    /// The text parsed and decoded into its sections; a syntax error, an unknown key or a
    /// value of the wrong type names its key and line.
    fn decode(&self) -> Result<File, ConfigError> {
        let syntax = |e: toml::de::Error| ConfigError {
            path: self.path.display().to_string(),
            line: e.span().map_or(0, |s| line_of(self.text, s.start)),
            message: e.message().to_string(),
        };
        let document = toml::Deserializer::parse(self.text).map_err(syntax)?;
        serde_path_to_error::deserialize(document).map_err(|e| {
            let key = key_path(e.path());
            let e = e.into_inner();
            ConfigError {
                path: self.path.display().to_string(),
                line: e.span().map_or(0, |s| line_of(self.text, s.start)),
                message: describe_value_error(&key, e.message()),
            }
        })
    }
}
