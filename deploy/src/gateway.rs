//! The gateway configuration file (`xrce-agent --config FILE`): one DDS worker and one
//! front-end process per `[[frontend]]`, each its own transport and interface.
//!
//! ```toml
//! [agent]
//! instance = "gw"                  # optional: shared-memory name of the agent's processes
//! verbose = 4                      # optional, like -v
//! memory_limit_mib = 512           # optional, like --memory-limit (per process)
//! discard_sessions = false         # optional, like --discard-sessions
//!
//! [worker]
//! refs = "profiles.xml"            # optional, like -r
//! dds_interfaces = ["127.0.0.1"]   # optional, like --dds-interface
//! ros_graph = true                 # optional
//! share_writers = false            # optional
//! ros_distro = "humble"            # optional: the graph's layout (default ROS_DISTRO, else jazzy)
//! domains = "0-10,42"              # optional: the domain ids clients may use (default: any)
//! max_domains = 8                  # optional: most domains in use at once (default 8, or
//!                                  #   none with `domains`)
//! dds_backend = "cyclone"          # optional, like --dds-backend (cyclone, the default, or rustdds)
//! middleware = "dds"               # optional, like -m: dds, or zenoh (an rmw_zenoh graph)
//! zenoh_type_hashes = ["/opt/ros/jazzy"]  # optional, like --zenoh-type-hashes
//! frontend_grace = 30              # optional: seconds a gone front-end's clients are kept
//! max_entities_per_client = 1024   # optional: DDS entities of one client
//! max_samples_per_client = 65536   # optional: samples one client's DDS caches may keep
//!
//! [[frontend]]
//! name = "ethernet"                # optional, unique (default: transport and id)
//! id = 0                           # optional, unique (default: its place in the file)
//! transport = "udp4"               # udp4 udp6 tcp4 tcp6 serial multiserial pseudoterminal
//! port = 8888                      # udp and tcp
//! bind = "0.0.0.0"                 # optional, udp and tcp
//! discovery = 7400                 # optional, udp and tcp
//! max_connections = 2000           # optional, tcp
//! client_dead_time = 21600.0       # optional, seconds (any transport; 0: never)
//! dialect = "eprosima"             # optional: spec or eprosima (any transport)
//! allow_keys = ["0xAAAABBBB"]      # optional: only these client keys (default: any)
//! allow_roaming = false            # optional: sessions follow clients to new endpoints
//! max_objects_per_client = 1024    # optional
//! max_client_messages_per_second = 0  # optional, 0 = no bound
//! max_client_bytes_per_second = 0     # optional, 0 = no bound
//! memory_budget_mib = 64           # optional: what clients may make it hold (any transport)
//! max_sessions = 8192              # optional
//! max_sessions_per_address = 2048  # optional (a serial line is one address)
//! new_sessions_per_second = 1000   # optional, per address; 0: no limit
//! max_connections_per_address = 256  # optional, tcp
//! tcp_idle_timeout = 300           # optional, tcp, seconds, 0 = none
//! closed_session_grace = 60        # optional, tcp, seconds, 0 = keep for ever
//!
//! [[frontend]]
//! transport = "serial"
//! device = "/dev/ttyACM0"
//! baudrate = 921600                # optional, serial transports (default 115200)
//! flow_control = false             # optional, serial transports
//!
//! [[frontend]]
//! transport = "multiserial"
//! devices = ["/dev/ttyUSB0", "/dev/ttyUSB1"]
//! ```
//!
//! Every error names the key, the front-end and the line.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::ops::Range;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use toml::Spanned;
use xrce_common::session::admission::KeyArg;
use xrce_frontend::cli::{AdmissionArgs, TransportKind};
use xrce_frontend::transport::registry::{Medium, TRANSPORTS};

use crate::cli::FrontendPlan;
use crate::settings;

/// A gateway file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    agent: AgentSection,
    #[serde(default)]
    worker: WorkerSection,
    #[serde(default)]
    metrics: MetricsSection,
    #[serde(default)]
    frontend: Vec<Spanned<FrontendSection>>,
}

/// `[metrics]`: the Prometheus endpoint (off unless `listen` is set).
#[derive(Debug, Default, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct MetricsSection {
    /// Address and port of `/metrics` and `/status`, like `--metrics`.
    listen: Option<Spanned<String>>,
}

/// `[agent]`: the group as a whole.
#[derive(Debug, Default, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentSection {
    /// Shared-memory name of the agent's processes (default: `gw-<pid>`).
    pub instance: Option<String>,
    /// Verbosity 0..6, like `-v`.
    pub verbose: Option<Spanned<u8>>,
    /// Private resident memory (MiB) beyond which a process is restarted, like
    /// `--memory-limit`.
    pub memory_limit_mib: Option<Spanned<u64>>,
    /// Start without the sessions a previous agent of the instance stored, like
    /// `--discard-sessions`.
    pub discard_sessions: Option<bool>,
}

/// `[worker]`: the DDS side.
#[derive(Debug, Default, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorkerSection {
    /// References file (Fast DDS XML profiles), like `-r`; relative to the gateway file.
    pub refs: Option<Spanned<PathBuf>>,
    /// Local addresses DDS is restricted to, like `--dds-interface`.
    #[serde(default)]
    pub dds_interfaces: Vec<IpAddr>,
    /// Announce micro-ROS nodes on `ros_discovery_info` (default true).
    pub ros_graph: Option<bool>,
    /// Map many clients' writers onto shared DDS writers (default false).
    pub share_writers: Option<bool>,
    /// The DDS implementation, like `--dds-backend` (`rustdds` or `cyclone`).
    pub dds_backend: Option<xrce_dds_worker::backend::BackendKind>,
    /// The middleware, like `-m`: `dds` or `zenoh`.
    pub middleware: Option<String>,
    /// Where rmw_zenoh's type hashes are looked up, like `--zenoh-type-hashes`; relative
    /// paths against the file's directory.
    #[serde(default)]
    pub zenoh_type_hashes: Vec<PathBuf>,
    /// Seconds a gone front-end's entities are kept for it to come back (default 30).
    pub frontend_grace: Option<f64>,
    /// The ROS 2 distribution of the graph's layout, like `--ros-distro`.
    pub ros_distro: Option<String>,
    /// Domain ids clients may use, like `--domains` (`"0-10,42"`).
    pub domains: Option<String>,
    /// Most distinct domains in use at once, like `--max-domains`.
    pub max_domains: Option<u16>,
    /// DDS entities of one client, like `--max-entities-per-client`.
    pub max_entities_per_client: Option<usize>,
    /// DDS entities of every client, like `--max-entities`.
    pub max_entities: Option<usize>,
    /// Samples one endpoint's cache may keep, like `--max-samples-per-endpoint`.
    pub max_samples_per_endpoint: Option<u32>,
    /// Instances one endpoint may keep, like `--max-instances-per-endpoint`.
    pub max_instances_per_endpoint: Option<u32>,
    /// Samples one client's endpoints may keep, like `--max-samples-per-client`.
    pub max_samples_per_client: Option<u64>,
    /// Samples every client's endpoints may keep, like `--max-samples`.
    pub max_samples: Option<u64>,
}

impl WorkerSection {
    /// The worker's bounds the file gives.
    pub fn bounds(&self) -> xrce_dds_worker::cli::BoundsArgs {
        xrce_dds_worker::cli::BoundsArgs {
            max_entities_per_client: self.max_entities_per_client,
            max_entities: self.max_entities,
            max_samples_per_endpoint: self.max_samples_per_endpoint,
            max_instances_per_endpoint: self.max_instances_per_endpoint,
            max_samples_per_client: self.max_samples_per_client,
            max_samples: self.max_samples,
        }
    }
}

/// One `[[frontend]]` as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct FrontendSection {
    name: Option<Spanned<String>>,
    id: Option<Spanned<u32>>,
    transport: Spanned<String>,
    port: Option<Spanned<u16>>,
    bind: Option<Spanned<IpAddr>>,
    discovery: Option<Spanned<u16>>,
    max_connections: Option<Spanned<usize>>,
    device: Option<Spanned<PathBuf>>,
    devices: Option<Spanned<Vec<PathBuf>>>,
    baudrate: Option<Spanned<u32>>,
    flow_control: Option<Spanned<bool>>,
    client_dead_time: Option<Spanned<f64>>,
    dialect: Option<Spanned<String>>,
    allow_keys: Option<Spanned<Vec<String>>>,
    allow_roaming: Option<bool>,
    max_objects_per_client: Option<Spanned<usize>>,
    max_client_messages_per_second: Option<u32>,
    max_client_bytes_per_second: Option<u64>,
    memory_budget_mib: Option<Spanned<usize>>,
    max_sessions: Option<Spanned<usize>>,
    max_sessions_per_address: Option<Spanned<usize>>,
    new_sessions_per_second: Option<u32>,
    max_connections_per_address: Option<Spanned<usize>>,
    tcp_idle_timeout: Option<u64>,
    closed_session_grace: Option<u64>,
}

/// One front-end of a checked gateway.
#[derive(Debug, Clone, PartialEq)]
pub struct GatewayFrontend {
    /// Unique name (for logs, readiness and `--process`).
    pub name: String,
    /// Unique front-end id (the worker keys its entities by it).
    pub id: u32,
    /// What it serves.
    pub plan: FrontendPlan,
    /// Answer multicast discovery on this port.
    pub discovery: Option<u16>,
    /// Seconds of silence before a client's session is deleted (0 = never); `None`: as
    /// `--client-dead-time` left out.
    pub client_dead_time: Option<f64>,
    /// Forced protocol dialect.
    pub dialect: Option<xrce_common::wire::Dialect>,
    /// Allow-list, roaming and quotas of its clients.
    pub admission: AdmissionArgs,
}

/// A checked gateway file.
#[derive(Debug, Clone)]
pub struct Gateway {
    /// Where it was read from.
    pub path: PathBuf,
    /// `[agent]`.
    pub agent: AgentSection,
    /// `[worker]`, with `refs` resolved against the file's directory.
    pub worker: WorkerSection,
    /// The front-ends, in file order.
    pub frontends: Vec<GatewayFrontend>,
    /// `[metrics] listen`: where the metrics endpoint is served, if anywhere.
    pub metrics: Option<SocketAddr>,
}

/// Why a gateway file is refused.
#[derive(Debug, thiserror::Error)]
#[error("{path}:{line}: {message}")]
pub struct ConfigError {
    /// The file.
    pub path: String,
    /// 1-based line of the offending key (or its table).
    pub line: usize,
    /// What is wrong, naming the key.
    pub message: String,
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

/// Reads and checks a gateway file.
pub fn load(path: &Path) -> Result<Gateway, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
        path: path.display().to_string(),
        line: 0,
        message: format!("cannot read it: {e}"),
    })?;
    parse(path, &text)
}

/// Checks a gateway file's text (`path` names it in errors and anchors relative paths).
pub fn parse(path: &Path, text: &str) -> Result<Gateway, ConfigError> {
    let c = Checker { path, text };
    let syntax = |e: toml::de::Error| ConfigError {
        path: path.display().to_string(),
        line: e.span().map_or(0, |s| line_of(text, s.start)),
        message: e.message().to_string(),
    };
    let document = toml::Deserializer::parse(text).map_err(syntax)?;
    let file: File = serde_path_to_error::deserialize(document).map_err(|e| {
        let key = key_path(e.path());
        let e = e.into_inner();
        ConfigError {
            path: path.display().to_string(),
            line: e.span().map_or(0, |s| line_of(text, s.start)),
            message: describe_value_error(&key, e.message()),
        }
    })?;
    if let Some(v) = &file.agent.verbose {
        settings::check_verbose(*v.get_ref())
            .map_err(|e| c.err(v.span(), format!("agent.verbose {e}")))?;
    }
    if let Some(g) = file.worker.frontend_grace {
        settings::check_frontend_grace(g).map_err(|e| {
            c.err(
                c.key("worker", "frontend_grace"),
                format!("worker.frontend_grace {e}"),
            )
        })?;
    }
    if let Some(n) = file.worker.max_domains {
        settings::check_max_domains(n).map_err(|e| {
            c.err(
                c.key("worker", "max_domains"),
                format!("worker.max_domains {e}"),
            )
        })?;
    }
    let w = &file.worker;
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
            return Err(c.err(
                c.key("worker", key),
                format!("worker.{key} must be at least 1"),
            ));
        }
    }
    if let Some(d) = &file.worker.domains {
        settings::parse_domains(d)
            .map_err(|e| c.err(c.key("worker", "domains"), format!("worker.domains {e}")))?;
    }
    if let Some(m) = &file.agent.memory_limit_mib {
        settings::check_memory_limit_mib(*m.get_ref())
            .map_err(|e| c.err(m.span(), format!("agent.memory_limit_mib {e}")))?;
    }
    if let Some(i) = &file.agent.instance {
        settings::check_instance(i)
            .map_err(|e| c.err(c.key("agent", "instance"), format!("agent.instance {e}")))?;
    }
    let mut worker = file.worker.clone();
    if let Some(m) = &file.worker.middleware {
        crate::cli::backend_for(m, file.worker.dds_backend).map_err(|e| {
            c.err(
                c.key("worker", "middleware"),
                format!("worker.middleware: {e}"),
            )
        })?;
    }
    let base = path.parent().unwrap_or(Path::new("."));
    worker.zenoh_type_hashes = file
        .worker
        .zenoh_type_hashes
        .iter()
        .map(|p| base.join(p))
        .collect();
    if let Some(r) = &file.worker.refs {
        let base = path.parent().unwrap_or(Path::new("."));
        let resolved = base.join(r.get_ref());
        if let Err(e) = xrce_dds_worker::references::References::load(&resolved) {
            return Err(c.err(r.span(), format!("worker.refs: {e}")));
        }
        worker.refs = Some(Spanned::new(r.span(), resolved));
    }
    let metrics = match &file.metrics.listen {
        Some(l) => Some(l.get_ref().parse::<SocketAddr>().map_err(|_| {
            c.err(
                l.span(),
                format!(
                    "metrics.listen {:?} is not an address and port (e.g. \"127.0.0.1:9464\" or \"[::1]:9464\")",
                    l.get_ref()
                ),
            )
        })?),
        None => None,
    };
    if file.frontend.is_empty() {
        return Err(c.err(
            0..0,
            "no [[frontend]]: a gateway serves at least one transport",
        ));
    }
    let mut frontends = Vec::new();
    let mut ids: HashMap<u32, usize> = HashMap::new();
    let mut names: HashMap<String, usize> = HashMap::new();
    let mut ports: HashMap<(bool, u16, IpAddr), usize> = HashMap::new();
    let mut devices: HashMap<PathBuf, usize> = HashMap::new();
    for (index, section) in file.frontend.iter().enumerate() {
        let table = section.span();
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
        let here = |key: &str, span: Range<usize>, what: &str| {
            c.err(
                span,
                format!("frontend {n} ({}): `{key}` {what}", kind.name()),
            )
        };
        // Keys that do not apply to the transport are mistakes, not silently ignored.
        let ip_only = [
            ("port", f.port.as_ref().map(Spanned::span)),
            ("bind", f.bind.as_ref().map(Spanned::span)),
            ("discovery", f.discovery.as_ref().map(Spanned::span)),
        ];
        let serial_only = [
            ("device", f.device.as_ref().map(Spanned::span)),
            ("devices", f.devices.as_ref().map(Spanned::span)),
            ("flow_control", f.flow_control.as_ref().map(Spanned::span)),
        ];
        if kind.is_ip() {
            for (key, span) in serial_only {
                if let Some(s) = span {
                    return Err(here(key, s, "applies to serial transports only"));
                }
            }
            if let Some(b) = &f.baudrate {
                return Err(here(
                    "baudrate",
                    b.span(),
                    "applies to serial transports only",
                ));
            }
        } else {
            for (key, span) in ip_only {
                if let Some(s) = span {
                    return Err(here(key, s, "applies to udp and tcp only"));
                }
            }
        }
        let is_tcp = kind.medium() == Medium::Streams;
        if let (false, Some(m)) = (is_tcp, &f.max_connections) {
            return Err(here("max_connections", m.span(), "applies to tcp only"));
        }
        let plan = match kind.medium() {
            Medium::Datagrams | Medium::Streams => {
                let port = f
                    .port
                    .as_ref()
                    .ok_or_else(|| here("port", table.clone(), "is required"))?;
                if *port.get_ref() == 0 {
                    return Err(here("port", port.span(), "must be 1 to 65535"));
                }
                if let Some(d) = f.discovery.as_ref().filter(|d| *d.get_ref() == 0) {
                    return Err(here("discovery", d.span(), "must be 1 to 65535"));
                }
                let v6 = kind.is_ipv6();
                let bind = match &f.bind {
                    Some(b) => {
                        if b.get_ref().is_ipv6() != v6 {
                            return Err(here(
                                "bind",
                                b.span(),
                                &format!("{} is not an address of {}", b.get_ref(), kind.name()),
                            ));
                        }
                        *b.get_ref()
                    }
                    None if v6 => IpAddr::V6(Ipv6Addr::UNSPECIFIED),
                    None => IpAddr::V4(Ipv4Addr::UNSPECIFIED),
                };
                let max_connections = match &f.max_connections {
                    Some(m) if *m.get_ref() == 0 => {
                        return Err(here("max_connections", m.span(), "must be at least 1"))
                    }
                    Some(m) => *m.get_ref(),
                    None => xrce_frontend::transport::tcp::TcpConfig::default().max_connections,
                };
                // Two front-ends on one port: same protocol and overlapping addresses.
                for (&(tcp, p, addr), &other) in &ports {
                    if tcp == is_tcp && p == *port.get_ref() && overlaps(addr, bind) {
                        return Err(here(
                            "port",
                            port.span(),
                            &format!("{} is also served by frontend {other}", port.get_ref()),
                        ));
                    }
                }
                ports.insert((is_tcp, *port.get_ref(), bind), n);
                FrontendPlan::Ip {
                    kind,
                    listen: SocketAddr::new(bind, *port.get_ref()),
                    max_connections: if is_tcp { max_connections } else { 0 },
                }
            }
            Medium::SerialLines => {
                let one = kind.spec().one_device;
                let list: Vec<(PathBuf, Range<usize>)> = match (one, &f.device, &f.devices) {
                    (true, Some(d), None) => vec![(d.get_ref().clone(), d.span())],
                    (true, _, Some(d)) => {
                        return Err(here(
                            "devices",
                            d.span(),
                            "is for multiserial; serial takes `device`",
                        ))
                    }
                    (true, None, None) => return Err(here("device", table.clone(), "is required")),
                    (_, Some(d), _) => {
                        return Err(here(
                            "device",
                            d.span(),
                            "is for serial; multiserial takes `devices`",
                        ))
                    }
                    (_, None, Some(d)) if d.get_ref().is_empty() => {
                        return Err(here("devices", d.span(), "names no device"))
                    }
                    (_, None, Some(d)) => {
                        d.get_ref().iter().map(|p| (p.clone(), d.span())).collect()
                    }
                    (_, None, None) => return Err(here("devices", table.clone(), "is required")),
                };
                for (dev, span) in &list {
                    if let Some(other) = devices.insert(dev.clone(), n) {
                        let whom = if other == n {
                            "twice here".to_string()
                        } else {
                            format!("by frontend {other} too")
                        };
                        return Err(here(
                            "device",
                            span.clone(),
                            &format!("{} is named {whom}", dev.display()),
                        ));
                    }
                }
                FrontendPlan::Serial {
                    kind,
                    devices: list.into_iter().map(|(p, _)| p).collect(),
                    baudrate: f.baudrate.as_ref().map_or(115_200, |b| *b.get_ref()),
                    flow_control: f.flow_control.as_ref().is_some_and(|b| *b.get_ref()),
                }
            }
            Medium::Pseudoterminal => FrontendPlan::Pty {
                baudrate: f.baudrate.as_ref().map_or(115_200, |b| *b.get_ref()),
            },
        };
        let id = f.id.as_ref().map_or(index as u32, |i| *i.get_ref());
        if let Some(other) = ids.insert(id, n) {
            let span = f.id.as_ref().map_or(table.clone(), Spanned::span);
            return Err(here(
                "id",
                span,
                &format!("{id} is also frontend {other}'s"),
            ));
        }
        let name = f
            .name
            .as_ref()
            .map_or_else(|| format!("{}-{id}", kind.name()), |s| s.get_ref().clone());
        if name.is_empty()
            || name.len() > 48
            || !name
                .chars()
                .all(|ch| ch.is_ascii_alphanumeric() || ch == '-' || ch == '_')
        {
            let span = f.name.as_ref().map_or(table.clone(), Spanned::span);
            return Err(here(
                "name",
                span,
                "must be 1-48 characters of [A-Za-z0-9_-]",
            ));
        }
        if ["worker", "metrics", "supervisor"].contains(&name.as_str()) {
            let span = f.name.as_ref().map_or(table.clone(), Spanned::span);
            return Err(here(
                "name",
                span,
                &format!("{name:?} names another process of the agent (for --process)"),
            ));
        }
        if let Some(other) = names.insert(name.clone(), n) {
            let span = f.name.as_ref().map_or(table.clone(), Spanned::span);
            return Err(here(
                "name",
                span,
                &format!("{name:?} is also frontend {other}'s"),
            ));
        }
        let client_dead_time = match &f.client_dead_time {
            Some(d) => Some(
                settings::check_client_dead_time(*d.get_ref())
                    .map_err(|e| here("client_dead_time", d.span(), &e))?,
            ),
            None => None,
        };
        let dialect = match &f.dialect {
            Some(d) => Some(d.get_ref().parse().map_err(|_: String| {
                here("dialect", d.span(), "must be \"spec\" or \"eprosima\"")
            })?),
            None => None,
        };
        let mut allow_keys = Vec::new();
        if let Some(keys) = &f.allow_keys {
            if keys.get_ref().is_empty() {
                return Err(here(
                    "allow_keys",
                    keys.span(),
                    "names no key (leave it out to admit every key)",
                ));
            }
            for k in keys.get_ref() {
                let key = k
                    .parse::<KeyArg>()
                    .map_err(|e| here("allow_keys", keys.span(), &e.to_string()))?;
                allow_keys.push(key);
            }
        }
        let max_objects_per_client = match &f.max_objects_per_client {
            Some(m) if *m.get_ref() == 0 => {
                return Err(here(
                    "max_objects_per_client",
                    m.span(),
                    "must be at least 1",
                ))
            }
            Some(m) => *m.get_ref(),
            None => xrce_common::session::graph::MAX_OBJECTS,
        };
        let d = AdmissionArgs::default();
        let at_least_one = |v: &Option<Spanned<usize>>, key: &str, default: usize| match v {
            Some(m) if *m.get_ref() == 0 => Err(here(key, m.span(), "must be at least 1")),
            Some(m) => Ok(*m.get_ref()),
            None => Ok(default),
        };
        let admission = AdmissionArgs {
            allow_keys,
            allow_roaming: f.allow_roaming.unwrap_or(false),
            max_objects_per_client,
            max_client_messages_per_second: f.max_client_messages_per_second.unwrap_or(0),
            max_client_bytes_per_second: f.max_client_bytes_per_second.unwrap_or(0),
            memory_budget_mib: at_least_one(
                &f.memory_budget_mib,
                "memory_budget_mib",
                d.memory_budget_mib,
            )?,
            max_sessions: at_least_one(&f.max_sessions, "max_sessions", d.max_sessions)?,
            max_sessions_per_address: at_least_one(
                &f.max_sessions_per_address,
                "max_sessions_per_address",
                d.max_sessions_per_address,
            )?,
            new_sessions_per_second: f
                .new_sessions_per_second
                .unwrap_or(d.new_sessions_per_second),
            max_connections_per_address: at_least_one(
                &f.max_connections_per_address,
                "max_connections_per_address",
                d.max_connections_per_address,
            )?,
            tcp_idle_timeout: f.tcp_idle_timeout.unwrap_or(d.tcp_idle_timeout),
            closed_session_grace: f.closed_session_grace.unwrap_or(d.closed_session_grace),
        };
        frontends.push(GatewayFrontend {
            name,
            id,
            plan,
            discovery: f.discovery.as_ref().map(|d| *d.get_ref()),
            client_dead_time,
            dialect,
            admission,
        });
    }
    Ok(Gateway {
        path: path.to_path_buf(),
        agent: file.agent,
        worker,
        frontends,
        metrics,
    })
}

mod keys;
pub use keys::{reference, KeyDoc, KEYS};

#[cfg(test)]
mod tests;
