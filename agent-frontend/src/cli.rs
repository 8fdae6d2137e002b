//! Command-line settings of a front-end, shared by `xrce-frontend` and `xrce-agent frontend`
//! (its start-up, which reads them, is [`crate::start`]).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use xrce_common::session::admission::{Admission, KeyArg, RateQuota};
use xrce_common::session::agent::AgentConfig;
use xrce_common::session::budget::{self, BudgetSplit, Limits};
use xrce_common::wire::Dialect;

use crate::transport::multiserial::LineDevice;
use crate::transport::serial::TtyConfig;
use crate::transport::tcp::TcpConfig;

pub use crate::transport::registry::TransportKind;

/// The environment variables a front-end reads settings from when its command line does not
/// give them. A supervisor passes every setting on the command line and removes these from
/// its front-ends' environment, so that a setting it left unset (a dialect chosen per
/// session) is not decided by a variable it inherited.
pub const SETTINGS_ENV: [&str; 5] = [
    "XRCE_INSTANCE",
    "XRCE_KEEP_SESSIONS",
    "XRCE_LOG",
    "XRCE_DIALECT",
    "XRCE_CLIENT_DEAD_TIME",
];

/// The supervisor hands a front-end process its settings as this type
/// ([`FrontendArgs::to_args`]); adding a setting is a field here (the compiler then asks for
/// its argument in `to_args`).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct FrontendArgs {
    /// Agent instance name (all processes of one agent share it).
    #[arg(long, env = "XRCE_INSTANCE", default_value = "default")]
    pub instance: String,
    /// This front-end's id within the instance (unique per front-end).
    #[arg(long, default_value_t = 0)]
    pub frontend_id: u32,
    /// Its name in status reports, metrics and logs (default: `frontend-<id>`).
    #[arg(long)]
    pub name: Option<String>,
    /// Keep the sessions where a restarted front-end takes them over (`true`, the default),
    /// or not (`false`: a front-end crash ends its clients' sessions).
    #[arg(long, env = "XRCE_KEEP_SESSIONS", default_value_t = true, action = clap::ArgAction::Set)]
    pub keep_sessions: bool,
    /// The transport served.
    #[arg(long, value_enum, default_value = "udp4")]
    pub transport: TransportKind,
    /// Address and port served by udp4/udp6/tcp4/tcp6, e.g. `0.0.0.0:8888` or `[::]:8888`.
    #[arg(long, visible_alias = "udp")]
    pub listen: Option<SocketAddr>,
    /// Serial device (serial: one; multiserial: repeat the option, one per device).
    #[arg(long = "device")]
    pub devices: Vec<PathBuf>,
    /// Baud rate of the serial devices (any rate; non-standard ones are set as custom rates).
    #[arg(long, default_value_t = 115_200)]
    pub baudrate: u32,
    /// RTS/CTS hardware flow control on the serial devices.
    #[arg(long)]
    pub flow_control: bool,
    /// pseudoterminal: serve the pty master the parent left open at this descriptor
    /// (without it, a new pseudoterminal is opened and its path printed).
    #[arg(long, requires = "pty_path")]
    pub pty_fd: Option<i32>,
    /// The slave path of the pty at `--pty-fd` (for logs).
    #[arg(long)]
    pub pty_path: Option<PathBuf>,
    /// udp4/udp6: serve the socket the parent bound and left open at this descriptor, on
    /// `--listen`'s port (one of the sockets of a port several front-ends share, which the
    /// supervisor keeps: a restarted front-end gets the same one and its clients' datagrams
    /// wait in it meanwhile), instead of binding `--listen`.
    #[arg(long)]
    pub socket_fd: Option<i32>,
    /// Answer multicast discovery (239.255.0.2) on this port.
    #[arg(long)]
    pub discovery: Option<u16>,
    /// TCP connections served at once; more are refused with a log line.
    #[arg(long, default_value_t = TcpConfig::default().max_connections)]
    pub max_connections: usize,
    /// Bytes buffered for a TCP client that does not read before its connection is closed.
    #[arg(long, default_value_t = TcpConfig::default().send_buffer)]
    pub tcp_send_buffer: usize,
    /// Log filter (tracing syntax), e.g. `info` or `xrce_common=debug`.
    #[arg(long, env = "XRCE_LOG", default_value = "info")]
    pub log: String,
    /// Protocol dialect for every session (`spec` or `eprosima`); by default chosen per session
    /// from the client's vendor id.
    #[arg(long, env = "XRCE_DIALECT")]
    pub dialect: Option<Dialect>,
    /// Seconds of silence after which a client's session and its DDS entities are deleted
    /// (probed with GET_INFO from a quarter of it on: a client that answers keeps its
    /// session); 0 keeps silent sessions for ever (as MicroXRCEAgent). Clients built with
    /// hard liveliness use their own timeout. The default, six hours, lets sessions of
    /// clients gone for good (and their entities, replayed to every new worker) end.
    #[arg(long, env = "XRCE_CLIENT_DEAD_TIME", default_value_t = DEFAULT_CLIENT_DEAD_TIME)]
    pub client_dead_time: f64,
    /// Which clients may open sessions, and their quotas.
    #[command(flatten)]
    pub admission: AdmissionArgs,
}

/// Who may hold a session and how much each client may do: options of the front-end, also
/// taken by `xrce-agent` (which passes them on) and set per front-end in a gateway file.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct AdmissionArgs {
    /// Client keys that may create a session, comma-separated, 8 hexadecimal digits each as
    /// the client's code writes them (e.g. 0xAAAABBBB), each optionally bound to the network
    /// its client must come from (0xAAAABBBB@192.168.1.0/24); other keys, and bound keys
    /// from elsewhere or from a serial line, are refused with STATUS_ERR_DENIED. Default:
    /// every key.
    #[arg(long = "allow-keys", value_delimiter = ',', value_name = "KEYS")]
    pub allow_keys: Vec<KeyArg>,
    /// Let a session follow its client to another source address or connection without a new
    /// CREATE_CLIENT (clients behind a NAT that changes their port). Without it, messages
    /// that name a session from an endpoint other than the session's are dropped (counted).
    #[arg(long = "allow-roaming")]
    pub allow_roaming: bool,
    /// Most objects one client may create (each is a DDS entity); more get
    /// STATUS_ERR_RESOURCES.
    #[arg(long = "max-objects-per-client", value_name = "N", default_value_t = xrce_common::session::graph::MAX_OBJECTS, value_parser = at_least_one)]
    pub max_objects_per_client: usize,
    /// Most messages a second one client may send (a second's worth in a burst); beyond,
    /// its messages are dropped: reliable ones are sent again by the client, so it is
    /// slowed, best-effort ones are lost. 0: no bound.
    #[arg(
        long = "max-client-messages-per-second",
        value_name = "N",
        default_value_t = 0
    )]
    pub max_client_messages_per_second: u32,
    /// Most bytes a second one client may send, as for messages. 0: no bound.
    #[arg(
        long = "max-client-bytes-per-second",
        value_name = "N",
        default_value_t = 0
    )]
    pub max_client_bytes_per_second: u64,
    /// Memory the front-end may hold for its clients, in MiB: unfinished fragments, early
    /// reliable messages, output waiting for or unacknowledged by clients. Shared fairly
    /// between source addresses, then between each address's sessions; over it, the
    /// heaviest holders are refused first (reliable input unacknowledged, so it comes again).
    #[arg(long = "memory-budget", value_name = "MIB", default_value_t = DEFAULT_MEMORY_BUDGET_MIB, value_parser = at_least_one)]
    pub memory_budget_mib: usize,
    /// Most sessions of one front-end; a new one beyond evicts the most silent session
    /// without objects of the address with the most sessions, or is refused with
    /// STATUS_ERR_RESOURCES.
    #[arg(long = "max-sessions", value_name = "N", default_value_t = budget::DEFAULT_MAX_SESSIONS, value_parser = at_least_one)]
    pub max_sessions: usize,
    /// Most sessions from one source address (a serial line counts as one address).
    #[arg(long = "max-sessions-per-address", value_name = "N", default_value_t = budget::DEFAULT_MAX_SESSIONS_PER_ORIGIN, value_parser = at_least_one)]
    pub max_sessions_per_address: usize,
    /// New sessions one source address may start per second (a second's worth at once);
    /// beyond, its CREATE_CLIENTs go unanswered until the rate falls (the client retries).
    /// 0: no limit.
    #[arg(long = "new-sessions-per-second", value_name = "N", default_value_t = budget::DEFAULT_NEW_SESSIONS_PER_SECOND)]
    pub new_sessions_per_second: u32,
    /// TCP: most connections from one source address; more are closed as they arrive.
    #[arg(long = "max-connections-per-address", value_name = "N", default_value_t = DEFAULT_TCP_PER_ADDRESS, value_parser = at_least_one)]
    pub max_connections_per_address: usize,
    /// TCP: seconds a connection may pass with nothing received and nothing sent before
    /// it is closed (its session then waits out `--closed-session-grace`). 0: no limit.
    #[arg(long = "tcp-idle-timeout", value_name = "SECONDS", default_value_t = DEFAULT_TCP_IDLE_SECS)]
    pub tcp_idle_timeout: u64,
    /// Seconds the session of a client whose TCP connection closed waits for it to connect
    /// again before the session and its DDS entities are deleted. 0: kept for ever.
    #[arg(long = "closed-session-grace", value_name = "SECONDS", default_value_t = DEFAULT_CLOSED_GRACE_SECS)]
    pub closed_session_grace: u64,
}

/// Default `--client-dead-time`: six hours.
pub const DEFAULT_CLIENT_DEAD_TIME: f64 = 21_600.0;
/// Default `--memory-budget` in MiB.
pub const DEFAULT_MEMORY_BUDGET_MIB: usize = budget::DEFAULT_MEMORY_BUDGET >> 20;
/// Default `--max-connections-per-address`.
pub const DEFAULT_TCP_PER_ADDRESS: usize = 256;
/// Default `--tcp-idle-timeout`.
pub const DEFAULT_TCP_IDLE_SECS: u64 = 300;
/// Default `--closed-session-grace`.
pub const DEFAULT_CLOSED_GRACE_SECS: u64 = 60;

impl Default for AdmissionArgs {
    fn default() -> Self {
        AdmissionArgs {
            allow_keys: Vec::new(),
            allow_roaming: false,
            max_objects_per_client: xrce_common::session::graph::MAX_OBJECTS,
            max_client_messages_per_second: 0,
            max_client_bytes_per_second: 0,
            memory_budget_mib: DEFAULT_MEMORY_BUDGET_MIB,
            max_sessions: budget::DEFAULT_MAX_SESSIONS,
            max_sessions_per_address: budget::DEFAULT_MAX_SESSIONS_PER_ORIGIN,
            new_sessions_per_second: budget::DEFAULT_NEW_SESSIONS_PER_SECOND,
            max_connections_per_address: DEFAULT_TCP_PER_ADDRESS,
            tcp_idle_timeout: DEFAULT_TCP_IDLE_SECS,
            closed_session_grace: DEFAULT_CLOSED_GRACE_SECS,
        }
    }
}

/// A count of at least 1.
fn at_least_one(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("{s:?} is not a number of at least 1")),
    }
}

impl AdmissionArgs {
    /// The session core's admission settings.
    pub fn admission(&self) -> Admission {
        Admission {
            allowed_keys: Admission::allow_list(&self.allow_keys),
            allow_roaming: self.allow_roaming,
            rate: RateQuota {
                messages_per_second: (self.max_client_messages_per_second > 0)
                    .then_some(self.max_client_messages_per_second),
                bytes_per_second: (self.max_client_bytes_per_second > 0)
                    .then_some(self.max_client_bytes_per_second),
            },
        }
    }

    /// The same settings as front-end arguments (only those not at their default).
    pub fn to_args(&self) -> Vec<String> {
        let mut a = Vec::new();
        if !self.allow_keys.is_empty() {
            let keys: Vec<String> = self.allow_keys.iter().map(KeyArg::to_string).collect();
            a.extend(["--allow-keys".to_string(), keys.join(",")]);
        }
        if self.allow_roaming {
            a.push("--allow-roaming".into());
        }
        if self.max_objects_per_client != xrce_common::session::graph::MAX_OBJECTS {
            a.extend([
                "--max-objects-per-client".into(),
                self.max_objects_per_client.to_string(),
            ]);
        }
        if self.max_client_messages_per_second > 0 {
            a.extend([
                "--max-client-messages-per-second".into(),
                self.max_client_messages_per_second.to_string(),
            ]);
        }
        if self.max_client_bytes_per_second > 0 {
            a.extend([
                "--max-client-bytes-per-second".into(),
                self.max_client_bytes_per_second.to_string(),
            ]);
        }
        let d = AdmissionArgs::default();
        let limits = [
            (
                "--memory-budget",
                self.memory_budget_mib as u64,
                d.memory_budget_mib as u64,
            ),
            (
                "--max-sessions",
                self.max_sessions as u64,
                d.max_sessions as u64,
            ),
            (
                "--max-sessions-per-address",
                self.max_sessions_per_address as u64,
                d.max_sessions_per_address as u64,
            ),
            (
                "--new-sessions-per-second",
                u64::from(self.new_sessions_per_second),
                u64::from(d.new_sessions_per_second),
            ),
            (
                "--max-connections-per-address",
                self.max_connections_per_address as u64,
                d.max_connections_per_address as u64,
            ),
            (
                "--tcp-idle-timeout",
                self.tcp_idle_timeout,
                d.tcp_idle_timeout,
            ),
            (
                "--closed-session-grace",
                self.closed_session_grace,
                d.closed_session_grace,
            ),
        ];
        for (flag, value, default) in limits {
            if value != default {
                a.extend([flag.to_string(), value.to_string()]);
            }
        }
        a
    }

    /// How `--memory-budget` is split between the parts of the front-end.
    pub fn budget_split(&self) -> BudgetSplit {
        BudgetSplit::of(self.memory_budget_mib.saturating_mul(1 << 20))
    }

    /// The session core's limits.
    pub fn limits(&self) -> Limits {
        Limits {
            memory_budget: self.budget_split().core,
            max_sessions_per_origin: self.max_sessions_per_address,
            new_sessions_per_second: self.new_sessions_per_second,
            detached_grace: (self.closed_session_grace > 0)
                .then(|| Duration::from_secs(self.closed_session_grace.min(31_536_000))),
            ..Limits::default()
        }
    }
}

impl FrontendArgs {
    /// Every setting at its default, as an empty command line gives them: the environment
    /// variables the front-end reads ([`SETTINGS_ENV`]) included, unless one of them has a
    /// value it refuses (then it is ignored, with a warning: a supervisor that decides the
    /// settings must not stop on them).
    pub fn defaults() -> Self {
        xrce_ipc::settings::from_environment("frontend").unwrap_or_else(|e| {
            tracing::warn!(error = %e.kind(), "a front-end setting's environment variable is refused; the built-in defaults apply");
            Self::built_in()
        })
    }

    /// Every setting at its built-in default, whatever the environment says.
    pub fn built_in() -> Self {
        xrce_ipc::settings::built_in("frontend")
    }

    /// These settings as the front-end's command line (what the supervisor runs it with):
    /// every field, so that the process gets exactly what its supervisor decided whatever
    /// its environment says.
    pub fn to_args(&self) -> Vec<String> {
        let FrontendArgs {
            instance,
            frontend_id,
            name,
            keep_sessions,
            transport,
            listen,
            devices,
            baudrate,
            flow_control,
            pty_fd,
            pty_path,
            socket_fd,
            discovery,
            max_connections,
            tcp_send_buffer,
            log,
            dialect,
            client_dead_time,
            admission,
        } = self;
        // `--key=value`: a value that starts with `-` (an instance or name `-gw`) stays a
        // value.
        let mut a: Vec<String> = Vec::new();
        let mut arg = |k: &str, v: String| a.push(format!("{k}={v}"));
        arg("--instance", instance.clone());
        arg("--frontend-id", frontend_id.to_string());
        arg("--keep-sessions", keep_sessions.to_string());
        arg("--transport", transport.name().to_string());
        arg("--baudrate", baudrate.to_string());
        arg("--max-connections", max_connections.to_string());
        arg("--tcp-send-buffer", tcp_send_buffer.to_string());
        arg("--log", log.clone());
        arg("--client-dead-time", client_dead_time.to_string());
        if let Some(n) = name {
            arg("--name", n.clone());
        }
        if let Some(l) = listen {
            arg("--listen", l.to_string());
        }
        for d in devices {
            arg("--device", d.display().to_string());
        }
        if let Some(fd) = pty_fd {
            arg("--pty-fd", fd.to_string());
        }
        if let Some(p) = pty_path {
            arg("--pty-path", p.display().to_string());
        }
        if let Some(fd) = socket_fd {
            arg("--socket-fd", fd.to_string());
        }
        if let Some(port) = discovery {
            arg("--discovery", port.to_string());
        }
        if let Some(d) = dialect {
            let name = match d {
                Dialect::Spec => "spec",
                Dialect::Eprosima => "eprosima",
            };
            arg("--dialect", name.to_string());
        }
        if *flow_control {
            a.push("--flow-control".into());
        }
        a.extend(admission.to_args());
        a
    }

    /// The session-core settings these arguments ask for.
    pub fn agent_config(&self) -> anyhow::Result<AgentConfig> {
        let dead = self.client_dead_time;
        // At most a year: longer is "never" in practice, and keeps Instant arithmetic safe.
        if !(dead.is_finite() && (0.0..=31_536_000.0).contains(&dead)) {
            anyhow::bail!("--client-dead-time must be 0 to 31536000 seconds, got {dead}");
        }
        Ok(AgentConfig {
            dialect: self.dialect,
            client_dead_time: (dead > 0.0).then(|| Duration::from_secs_f64(dead.max(0.1))),
            admission: self.admission.admission(),
            max_clients: self.admission.max_sessions,
            limits: self.admission.limits(),
            ..AgentConfig::default()
        })
    }

    /// The address an IP transport serves.
    pub(crate) fn listen_addr(&self) -> anyhow::Result<SocketAddr> {
        self.listen.ok_or_else(|| {
            anyhow::anyhow!(
                "--listen ADDRESS:PORT is needed for {}",
                self.transport.name()
            )
        })
    }

    /// The serial devices, checked for the transport.
    pub(crate) fn serial_lines(&self) -> anyhow::Result<Vec<LineDevice>> {
        let name = self.transport.name();
        match (self.transport.spec().one_device, self.devices.len()) {
            (true, 1) | (false, 1..) => {}
            (true, n) => anyhow::bail!("{name} serves exactly one --device, got {n}"),
            (false, _) => anyhow::bail!("{name} needs at least one --device"),
        }
        if self.devices.len() > u16::MAX as usize {
            anyhow::bail!("at most 65535 devices");
        }
        Ok(self
            .devices
            .iter()
            .map(|path| {
                LineDevice::Tty(TtyConfig {
                    path: path.clone(),
                    baudrate: self.baudrate,
                    flow_control: self.flow_control,
                })
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{Args, FromArgMatches};

    fn parse(args: &[String]) -> FrontendArgs {
        let command = FrontendArgs::augment_args(clap::Command::new("frontend"));
        let matches = command
            .try_get_matches_from(std::iter::once("frontend".to_string()).chain(args.to_vec()))
            .expect("the arguments parse");
        FrontendArgs::from_arg_matches(&matches).expect("the settings")
    }

    /// What the supervisor decides is what the process gets: every setting, off its default,
    /// survives `to_args` and the front-end's parsing.
    #[test]
    fn settings_survive_their_command_line() {
        let mut s = FrontendArgs::built_in();
        assert_eq!(s.instance, "default");
        assert!(s.keep_sessions);
        assert_eq!(
            (s.dialect, s.client_dead_time),
            (None, DEFAULT_CLIENT_DEAD_TIME)
        );
        assert_eq!(parse(&s.to_args()), s, "the defaults");
        s.instance = "gw-1234abcd".into();
        s.frontend_id = 7;
        s.name = Some("radio".into());
        s.keep_sessions = false;
        s.transport = TransportKind::Multiserial;
        s.listen = Some("[::1]:8890".parse().expect("address"));
        s.devices = vec!["/dev/ttyACM0".into(), "/dev/ttyUSB1".into()];
        s.baudrate = 921_600;
        s.flow_control = true;
        s.pty_fd = Some(3);
        s.pty_path = Some("/dev/pts/9".into());
        s.socket_fd = Some(4);
        s.discovery = Some(7400);
        s.max_connections = 12;
        s.tcp_send_buffer = 4096;
        s.log = "debug".into();
        s.dialect = Some(Dialect::Spec);
        s.client_dead_time = 2.5;
        s.admission.allow_keys = vec!["0xAAAABBBB".parse().expect("key")];
        s.admission.allow_roaming = true;
        s.admission.max_objects_per_client = 33;
        s.admission.max_client_messages_per_second = 40;
        s.admission.max_client_bytes_per_second = 3000;
        s.admission.memory_budget_mib = 48;
        s.admission.max_sessions = 9;
        s.admission.max_sessions_per_address = 4;
        s.admission.max_connections_per_address = 5;
        s.admission.tcp_idle_timeout = 60;
        s.admission.closed_session_grace = 30;
        assert_eq!(parse(&s.to_args()), s);
    }
}
