//! The user-facing command line, a drop-in for eProsima's `MicroXRCEAgent` v2.4.3:
//! `xrce-agent <transport> <options>` with the same transports, option names, defaults and
//! value forms (`-p8888` as well as `-p 8888`), plus this agent's own options. What the
//! reference offers but this agent does not (the CED middleware, its P2P mode, CAN FD) is
//! refused with a clear message and exit status 2, like any other usage error.

use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};

/// What this build is (written by `build.rs`).
pub mod build {
    include!(concat!(env!("OUT_DIR"), "/version.rs"));
}

/// DDS-XRCE agent: lets XRCE clients (Micro XRCE-DDS, micro-ROS, PX4) join a DDS data space.
///
/// Either one transport (`xrce-agent udp4 -p 8888`, as MicroXRCEAgent) or a gateway of
/// several from a file (`xrce-agent --config gateway.toml`).
#[derive(Debug, Parser)]
#[command(
    name = "xrce-agent",
    version = build::SHORT_VERSION,
    long_version = build::LONG_VERSION,
    args_conflicts_with_subcommands = true
)]
pub struct Cli {
    /// Run a gateway: one DDS worker and one front-end process per `[[frontend]]` of this
    /// TOML file (see deploy/gateway.example.toml).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// With --config: check the file, print what it would run, and exit (0 when valid).
    #[arg(long, requires = "config")]
    pub check: bool,
    /// With --config: run only this process of the gateway, in the foreground (`worker`, or
    /// a front-end's name), for deployments that run each process as a systemd unit.
    #[arg(long, requires = "config", value_name = "NAME")]
    pub process: Option<String>,
    /// The transport to serve, or an internal role.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// What to run.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Serve clients over UDP/IPv4.
    Udp4(UdpArgs),
    /// Serve clients over UDP/IPv6.
    Udp6(UdpArgs),
    /// Serve clients over TCP/IPv4.
    Tcp4(TcpArgs),
    /// Serve clients over TCP/IPv6.
    #[command(alias = "tpc6")]
    Tcp6(TcpArgs),
    /// Serve clients on a serial device.
    Serial(SerialArgs),
    /// Serve clients on several serial devices.
    Multiserial(MultiserialArgs),
    /// Open a pseudoterminal and serve the client that opens it.
    Pseudoterminal(PtyArgs),
    /// CAN FD (not supported by this agent).
    Canfd(CanfdArgs),
    /// Show the live sessions and processes of a running agent (from its metrics endpoint
    /// or the status reports of the agents on this machine).
    Status(crate::status_view::StatusArgs),
    /// Internal: remove a stopped instance's session store once no restart can take its
    /// sessions over (left behind by a stopping supervisor).
    #[command(hide = true)]
    Sweep(crate::sweep::SweepArgs),
    /// Internal: write the man pages, the shell completions or the command-line reference
    /// (for packages and docs/).
    #[command(hide = true)]
    Generate(GenerateArgs),
    /// Internal: run the DDS worker (started by the supervisor).
    #[command(hide = true)]
    DdsWorker(xrce_dds_worker::cli::WorkerArgs),
    /// Internal: run a front-end (started by the supervisor).
    #[command(hide = true)]
    Frontend(xrce_frontend::cli::FrontendArgs),
    /// Internal: run a front-end and the DDS worker in one process (started by the
    /// supervisor with `--single-process`).
    #[command(hide = true)]
    SingleProcess(crate::in_process::SingleProcessArgs),
}

/// What to generate.
#[derive(Debug, clap::Args)]
pub struct GenerateArgs {
    /// Which.
    #[command(subcommand)]
    pub what: Generated,
}

/// The documents `xrce-agent generate` writes.
#[derive(Debug, clap::Subcommand)]
pub enum Generated {
    /// Man pages, `xrce-agent.1` and one per subcommand, into DIR.
    Man {
        /// Where to write them.
        dir: PathBuf,
    },
    /// The completion script of SHELL on standard output.
    Completions {
        /// bash, zsh, fish, elvish or powershell.
        shell: clap_complete::Shell,
    },
    /// The command-line reference (Markdown, `docs/cli.md`) on standard output.
    Reference,
    /// The gateway file reference (Markdown, `docs/gateway.md`) on standard output.
    GatewayReference,
}

/// Options every transport takes.
#[derive(Debug, Clone, Args)]
pub struct Common {
    /// Verbosity 0 (off) … 6 (a hex dump of every message); 4 = info (the default), 5 adds
    /// per-message debug logs. Given, it wins over the XRCE_LOG environment variable.
    #[arg(short = 'v', long = "verbose", value_parser = crate::settings::parse_verbose)]
    pub verbose: Option<u8>,
    /// Middleware: `dds` (DDS, through `--dds-backend`) or `zenoh` (a ROS 2 graph on
    /// rmw_zenoh: its keys, attachments and liveliness tokens; the session connects to a
    /// Zenoh router at tcp/localhost:7447 unless `ZENOH_SESSION_CONFIG_URI` or
    /// `ZENOH_CONFIG_OVERRIDE` say otherwise). MicroXRCEAgent's `ced` and `rtps` are refused.
    #[arg(short = 'm', long = "middleware", default_value = "dds")]
    pub middleware: String,
    /// With `-m zenoh`: where the RIHS01 type hashes of rmw_zenoh's keys are looked up, before
    /// `AMENT_PREFIX_PATH` and the built-in table of ROS 2 Jazzy's common interfaces: ROS
    /// installations (`/opt/ros/jazzy` or its `share` folder) and tables (`pkg/msg/Type
    /// RIHS01_...` lines); comma-separated.
    #[arg(long = "zenoh-type-hashes", value_delimiter = ',', value_name = "PATH")]
    pub zenoh_type_hashes: Vec<PathBuf>,
    /// References file: Fast DDS XML profiles that clients may create by reference.
    #[arg(short = 'r', long = "refs")]
    pub refs: Option<PathBuf>,
    /// Answer multicast discovery (group 239.255.0.2) on this port (7400 if given alone).
    #[arg(short = 'd', long = "discovery", num_args = 0..=1, default_missing_value = "7400")]
    pub discovery: Option<u16>,
    /// P2P port of the CED middleware (not supported by this agent).
    #[arg(short = 'P', long = "p2p")]
    pub p2p: Option<u16>,
    /// Restrict DDS to these local addresses (comma-separated); default: every interface.
    #[arg(
        long = "dds-interface",
        env = "XRCE_DDS_INTERFACES",
        value_delimiter = ','
    )]
    pub dds_interfaces: Vec<IpAddr>,
    /// Instance name shared by the agent's processes (default: derived from what the agent
    /// serves and its network namespace, so that the same command line finds the sessions
    /// its predecessor stored).
    #[arg(long, env = "XRCE_INSTANCE")]
    pub instance: Option<String>,
    /// Start without the sessions a previous agent of this instance stored (by default a
    /// restarted agent takes them over and its clients go on).
    #[arg(long = "discard-sessions", env = "XRCE_DISCARD_SESSIONS", action = clap::ArgAction::SetTrue, value_parser = clap::builder::FalseyValueParser::new())]
    pub discard_sessions: bool,
    /// Run the front-end and the DDS worker in one process (still under this supervisor):
    /// no process hop per sample, which on a small gateway costs most of its CPU. A crash
    /// then takes both down; the restarted process takes the sessions over and re-creates
    /// their DDS entities, as after a worker crash.
    #[arg(long = "single-process", env = "XRCE_SINGLE_PROCESS", action = clap::ArgAction::SetTrue, value_parser = clap::builder::FalseyValueParser::new())]
    pub single_process: bool,
    /// Protocol dialect for every session: `spec` or `eprosima` (default: per session, from
    /// the client's vendor id).
    #[arg(long, env = "XRCE_DIALECT")]
    pub dialect: Option<xrce_common::wire::Dialect>,
    /// Seconds of silence after which a client's session and entities are deleted; silent
    /// clients are probed with GET_INFO first (one that answers keeps its session). 0 keeps
    /// them for ever, like MicroXRCEAgent; the default, six hours, ends the sessions of
    /// clients gone for good.
    #[arg(
        long = "client-dead-time",
        env = "XRCE_CLIENT_DEAD_TIME",
        default_value_t = xrce_frontend::cli::DEFAULT_CLIENT_DEAD_TIME
    )]
    pub client_dead_time: f64,
    /// Announce XRCE participants named like ROS 2 nodes that have an endpoint on a ROS topic
    /// (`rt/`, `rq/`, `rr/`: micro-ROS) on `ros_discovery_info`, so `ros2 node list` shows
    /// them: `true` (default) or `false`.
    #[arg(long = "ros-graph", env = "XRCE_ROS_GRAPH", default_value_t = true, action = clap::ArgAction::Set)]
    pub ros_graph: bool,
    /// Map the XRCE data writers of one domain, topic, type and QoS onto shared DDS writers,
    /// one per 32 clients (volatile, shared-ownership writers only): `true` or `false`
    /// (default). Scales to thousands of clients publishing on one topic; DDS readers then
    /// see one writer per group of clients.
    #[arg(long = "share-writers", env = "XRCE_SHARE_WRITERS", default_value_t = false, action = clap::ArgAction::Set)]
    pub share_writers: bool,
    /// The ROS 2 distribution whose `ros_discovery_info` layout the graph is published in
    /// (`humble` has 24-octet GIDs, `iron` and later 16): default `ROS_DISTRO` as a sourced
    /// ROS 2 shell sets it, else jazzy.
    #[arg(long = "ros-distro", env = "XRCE_ROS_DISTRO", value_enum)]
    pub ros_distro: Option<xrce_dds_worker::ros_graph::RosDistro>,
    /// Domain ids clients may use, e.g. `0-10,42`; a participant in another gets
    /// STATUS_ERR_DENIED. Default: any, but at most `--max-domains` at once.
    #[arg(long = "domains", env = "XRCE_DOMAINS", value_name = "LIST")]
    pub domains: Option<String>,
    /// Most distinct DDS domains in use at once (each costs the worker a DDS participant and
    /// its threads, released with its last user); one more gets STATUS_ERR_RESOURCES.
    /// Default 8, or no cap with `--domains`.
    #[arg(long = "max-domains", env = "XRCE_MAX_DOMAINS", value_name = "N")]
    pub max_domains: Option<u16>,
    /// The DDS implementation of the worker: `cyclone` (Cyclone DDS, the default in builds
    /// with the `cyclone` feature, which is on by default) or `rustdds`.
    #[arg(long = "dds-backend", env = "XRCE_DDS_BACKEND", value_enum)]
    pub dds_backend: Option<xrce_dds_worker::backend::BackendKind>,
    /// Serve Prometheus metrics at http://ADDR:PORT/metrics and the live status (JSON) at
    /// /status, e.g. 127.0.0.1:9464; off by default.
    #[arg(long = "metrics", value_name = "ADDR:PORT")]
    pub metrics: Option<SocketAddr>,
    /// Restart any process of the agent (the DDS worker, a front-end) whose private resident
    /// memory (RssAnon: heap and stacks, not the shared memory between the processes)
    /// exceeds this many MiB; its clients' sessions survive the restart. Checked every
    /// second, warned about at 80 %; off by default.
    #[arg(
        long = "memory-limit",
        env = "XRCE_MEMORY_LIMIT",
        value_name = "MIB",
        value_parser = crate::settings::parse_memory_limit_mib
    )]
    pub memory_limit: Option<u64>,
    /// Seconds the DDS entities of a front-end whose process is gone are kept for it to
    /// come back (default 30), 0 to 86400.
    #[arg(
        long = "frontend-grace",
        env = "XRCE_FRONTEND_GRACE",
        value_name = "SECONDS"
    )]
    pub frontend_grace: Option<f64>,
    /// Which clients may open sessions, and their quotas.
    #[command(flatten)]
    pub admission: xrce_frontend::cli::AdmissionArgs,
    /// What clients may make the DDS worker hold.
    #[command(flatten)]
    pub bounds: xrce_dds_worker::cli::BoundsArgs,
}

impl Common {
    /// The options as an empty command line gives them: each from its environment
    /// variable, else its default. What a gateway file's left-out keys take, so that a
    /// setting means the same from a file as on a command line.
    pub fn from_environment() -> anyhow::Result<Self> {
        #[derive(Parser)]
        #[command(name = "xrce-agent")]
        struct Empty {
            #[command(flatten)]
            common: Common,
        }
        Empty::try_parse_from(["xrce-agent"])
            .map(|e| e.common)
            .map_err(|e| {
                let rendered = e.render().to_string();
                let why = rendered.lines().next().unwrap_or_default().to_string();
                anyhow::anyhow!(
                    "an environment variable of the agent's settings is refused: {}",
                    why.trim_start_matches("error: ")
                )
            })
    }
}

pub use crate::settings::MAX_MEMORY_LIMIT_MIB;

/// Options of the UDP transports.
#[derive(Debug, Clone, Args)]
pub struct UdpArgs {
    /// The address and port.
    #[command(flatten)]
    pub ip: IpArgs,
    /// Front-end processes that serve the port, 1-64, or `auto` (one per four cores, at most
    /// 8). Each client is served by one of them, chosen by its source address (a client
    /// whose port changes stays where its session is; clients of one address share one).
    #[arg(long = "processes", value_name = "N", default_value = "1", value_parser = crate::settings::parse_processes)]
    pub processes: u16,
}

/// The address and port of the UDP and TCP transports.
#[derive(Debug, Clone, Args)]
pub struct IpArgs {
    /// Port to listen on.
    #[arg(short = 'p', long = "port")]
    pub port: u16,
    /// Address to bind (default: every interface).
    #[arg(long)]
    pub bind: Option<IpAddr>,
    /// The options every transport has.
    #[command(flatten)]
    pub common: Common,
}

/// Options of the TCP transports.
#[derive(Debug, Clone, Args)]
pub struct TcpArgs {
    /// The address and port.
    #[command(flatten)]
    pub ip: IpArgs,
    /// Connections served at once; more are refused with a log line.
    #[arg(long = "max-connections", default_value_t = 2_000)]
    pub max_connections: usize,
}

/// Options of the serial transport.
#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("device").required(true).args(["dev", "file"])))]
pub struct SerialArgs {
    /// The serial device, e.g. /dev/ttyACM0.
    #[arg(short = 'D', long = "dev")]
    pub dev: Option<PathBuf>,
    /// A file whose first line is the device path.
    #[arg(short = 'f', long = "file")]
    pub file: Option<PathBuf>,
    /// Baud rate: any standard rate up to 4000000, or another value as a custom rate.
    #[arg(short = 'b', long = "baudrate", default_value_t = 115_200)]
    pub baudrate: u32,
    /// RTS/CTS hardware flow control.
    #[arg(long = "flow-control")]
    pub flow_control: bool,
    /// The options every transport has.
    #[command(flatten)]
    pub common: Common,
}

/// Options of the multiserial transport.
#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("devices").required(true).args(["devs", "file"])))]
pub struct MultiserialArgs {
    /// The serial devices, space-separated in one argument: "/dev/ttyUSB0 /dev/ttyUSB1".
    #[arg(short = 'D', long = "devs")]
    pub devs: Option<String>,
    /// A file with one device path a line.
    #[arg(short = 'f', long = "file")]
    pub file: Option<PathBuf>,
    /// Baud rate of every device.
    #[arg(short = 'b', long = "baudrate", default_value_t = 115_200)]
    pub baudrate: u32,
    /// RTS/CTS hardware flow control on every device.
    #[arg(long = "flow-control")]
    pub flow_control: bool,
    /// The options every transport has.
    #[command(flatten)]
    pub common: Common,
}

/// Options of the pseudoterminal transport.
#[derive(Debug, Clone, Args)]
pub struct PtyArgs {
    /// Baud rate (a pseudoterminal ignores it).
    #[arg(short = 'b', long = "baudrate", default_value_t = 115_200)]
    pub baudrate: u32,
    /// The options every transport has.
    #[command(flatten)]
    pub common: Common,
}

/// Options of the CAN FD transport (refused).
#[derive(Debug, Clone, Args)]
pub struct CanfdArgs {
    /// CAN interface.
    #[arg(short = 'D', long = "dev")]
    pub dev: Option<String>,
    /// CAN id (hex).
    #[arg(short = 'I', long = "id")]
    pub id: Option<String>,
    /// The options every transport has.
    #[command(flatten)]
    pub common: Common,
}

/// Verbosity without `-v` (and without XRCE_LOG), as MicroXRCEAgent's.
pub const DEFAULT_VERBOSITY: u8 = 4;

/// A usage error with the reference's exit status (2).
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Unsupported(pub String);

/// What one front-end serves, decided from the command line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FrontendPlan {
    /// UDP or TCP at an address.
    Ip {
        /// `udp4`, `udp6`, `tcp4` or `tcp6`.
        kind: xrce_frontend::cli::TransportKind,
        /// Where.
        listen: SocketAddr,
        /// TCP connections served at once.
        max_connections: usize,
        /// UDP: front-end processes that share the port (1 for TCP).
        processes: u16,
    },
    /// Serial devices (one for `serial`).
    Serial {
        /// `serial` or `multiserial`.
        kind: xrce_frontend::cli::TransportKind,
        /// The devices.
        devices: Vec<PathBuf>,
        /// Their baud rate.
        baudrate: u32,
        /// RTS/CTS.
        flow_control: bool,
    },
    /// A pseudoterminal the supervisor opens.
    Pty {
        /// Its baud rate.
        baudrate: u32,
    },
}

impl FrontendPlan {
    /// The transport's name.
    pub fn kind(&self) -> xrce_frontend::cli::TransportKind {
        match self {
            FrontendPlan::Ip { kind, .. } | FrontendPlan::Serial { kind, .. } => *kind,
            FrontendPlan::Pty { .. } => xrce_frontend::cli::TransportKind::Pseudoterminal,
        }
    }

    /// What it serves, for people (`tcp4 on 0.0.0.0:8888`, `serial /dev/ttyACM0 at 921600
    /// baud`).
    pub fn describe(&self) -> String {
        match self {
            FrontendPlan::Ip {
                kind,
                listen,
                processes,
                ..
            } if *processes > 1 => format!("{} on {listen} ({processes} processes)", kind.name()),
            FrontendPlan::Ip { kind, listen, .. } => format!("{} on {listen}", kind.name()),
            FrontendPlan::Serial {
                kind,
                devices,
                baudrate,
                flow_control,
            } => {
                let list: Vec<String> = devices.iter().map(|d| d.display().to_string()).collect();
                format!(
                    "{} {} at {baudrate} baud{}",
                    kind.name(),
                    list.join(" "),
                    if *flow_control { " with RTS/CTS" } else { "" }
                )
            }
            FrontendPlan::Pty { .. } => "pseudoterminal".into(),
        }
    }

    /// What it serves, for the derived instance name: the address and port, or the devices.
    /// A pseudoterminal is a new one at every start, which no client of a previous agent
    /// can reach: its agent's instance is its own (the process id).
    pub fn identity(&self) -> String {
        match self {
            FrontendPlan::Ip { listen, .. } => listen.to_string(),
            FrontendPlan::Serial { devices, .. } => devices
                .iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(" "),
            _ => format!("pid {}", std::process::id()),
        }
    }

    /// A short label for instance names and logs (`udp4-8888`, `serial`).
    pub fn label(&self) -> String {
        match self {
            FrontendPlan::Ip { kind, listen, .. } => format!("{}-{}", kind.name(), listen.port()),
            other => other.kind().name().to_string(),
        }
    }

    /// Sets what a front-end serves in its settings (the pty descriptor, if any, is set by
    /// the supervisor when it opens the pseudoterminal).
    pub fn apply_to(&self, s: &mut xrce_frontend::cli::FrontendArgs) {
        s.transport = self.kind();
        match self {
            FrontendPlan::Ip {
                listen,
                max_connections,
                ..
            } => {
                s.listen = Some(*listen);
                s.max_connections = *max_connections;
            }
            FrontendPlan::Serial {
                devices,
                baudrate,
                flow_control,
                ..
            } => {
                s.devices = devices.clone();
                s.baudrate = *baudrate;
                s.flow_control = *flow_control;
            }
            FrontendPlan::Pty { baudrate } => s.baudrate = *baudrate,
        }
    }
}

/// The worker's backend a middleware (`-m`) and `--dds-backend` name together: `zenoh` is
/// the Zenoh backend (with `--dds-backend` absent or `zenoh`), `dds` the DDS backend
/// `--dds-backend` names (or the default).
pub fn backend_for(
    middleware: &str,
    dds_backend: Option<xrce_dds_worker::backend::BackendKind>,
) -> Result<Option<xrce_dds_worker::backend::BackendKind>, Unsupported> {
    use xrce_dds_worker::backend::BackendKind;
    match (middleware, dds_backend) {
        ("dds", b) => Ok(b),
        ("zenoh", None | Some(BackendKind::Zenoh)) => Ok(Some(BackendKind::Zenoh)),
        ("zenoh", Some(b)) => Err(Unsupported(format!(
            "middleware 'zenoh' and the DDS backend '{}' contradict each other: give one",
            b.as_str()
        ))),
        (m @ ("ced" | "rtps"), _) => Err(Unsupported(format!(
            "middleware '{m}' is not supported by this agent: it serves DDS (-m dds) and Zenoh \
             (-m zenoh)"
        ))),
        (m, _) => Err(Unsupported(format!(
            "unknown middleware '{m}' (MicroXRCEAgent knows dds, ced and rtps; this agent \
             serves dds and zenoh)"
        ))),
    }
}

/// Refuses what the reference offers and this agent does not.
pub fn check_supported(common: &Common) -> Result<(), Unsupported> {
    backend_for(&common.middleware, common.dds_backend)?;
    if common.p2p.is_some() {
        return Err(Unsupported(
            "-P/--p2p is a mode of the CED middleware, which this agent does not have".into(),
        ));
    }
    Ok(())
}

fn ip_plan(
    kind: xrce_frontend::cli::TransportKind,
    a: &IpArgs,
    v6: bool,
    max_connections: usize,
    processes: u16,
) -> FrontendPlan {
    let bind = a.bind.unwrap_or(if v6 {
        IpAddr::V6(Ipv6Addr::UNSPECIFIED)
    } else {
        IpAddr::V4(Ipv4Addr::UNSPECIFIED)
    });
    FrontendPlan::Ip {
        kind,
        listen: SocketAddr::new(bind, a.port),
        max_connections,
        processes,
    }
}

/// Device paths from a file: one a line, blank lines and `#` comments skipped.
fn devices_from_file(file: &Path, first_only: bool) -> anyhow::Result<Vec<PathBuf>> {
    let text = std::fs::read_to_string(file)
        .map_err(|e| anyhow::anyhow!("reading the device file {}: {e}", file.display()))?;
    let mut out: Vec<PathBuf> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(PathBuf::from)
        .collect();
    if first_only {
        out.truncate(1);
    }
    if out.is_empty() {
        anyhow::bail!("the device file {} names no device", file.display());
    }
    Ok(out)
}

/// The front-end plan and the common options of a transport command; `None` for the
/// internal roles.
pub fn plan(command: &Command) -> anyhow::Result<Option<(FrontendPlan, Common)>> {
    use xrce_frontend::cli::TransportKind as K;
    Ok(Some(match command {
        Command::Udp4(a) => (
            ip_plan(K::Udp4, &a.ip, false, 0, a.processes),
            a.ip.common.clone(),
        ),
        Command::Udp6(a) => (
            ip_plan(K::Udp6, &a.ip, true, 0, a.processes),
            a.ip.common.clone(),
        ),
        Command::Tcp4(a) => (
            ip_plan(K::Tcp4, &a.ip, false, a.max_connections, 1),
            a.ip.common.clone(),
        ),
        Command::Tcp6(a) => (
            ip_plan(K::Tcp6, &a.ip, true, a.max_connections, 1),
            a.ip.common.clone(),
        ),
        Command::Serial(a) => {
            let devices = match (&a.dev, &a.file) {
                (Some(d), _) => vec![d.clone()],
                (None, Some(f)) => devices_from_file(f, true)?,
                (None, None) => anyhow::bail!("serial needs --dev DEVICE or --file FILE"),
            };
            (
                FrontendPlan::Serial {
                    kind: K::Serial,
                    devices,
                    baudrate: a.baudrate,
                    flow_control: a.flow_control,
                },
                a.common.clone(),
            )
        }
        Command::Multiserial(a) => {
            let devices = match (&a.devs, &a.file) {
                (Some(d), _) => d.split_whitespace().map(PathBuf::from).collect(),
                (None, Some(f)) => devices_from_file(f, false)?,
                (None, None) => {
                    anyhow::bail!("multiserial needs --devs \"DEV1 DEV2\" or --file FILE")
                }
            };
            if devices.is_empty() {
                anyhow::bail!("multiserial: --devs names no device");
            }
            let mut seen = std::collections::HashSet::new();
            if let Some(d) = devices.iter().find(|d| !seen.insert(*d)) {
                anyhow::bail!("multiserial: {} is named twice", d.display());
            }
            (
                FrontendPlan::Serial {
                    kind: K::Multiserial,
                    devices,
                    baudrate: a.baudrate,
                    flow_control: a.flow_control,
                },
                a.common.clone(),
            )
        }
        Command::Pseudoterminal(a) => (
            FrontendPlan::Pty {
                baudrate: a.baudrate,
            },
            a.common.clone(),
        ),
        Command::Canfd(a) => {
            check_supported(&a.common)?;
            return Err(Unsupported(
                "the canfd transport is not supported by this agent (UDP, TCP, serial, multiserial and pseudoterminal are)".into(),
            )
            .into());
        }
        Command::DdsWorker(_)
        | Command::Frontend(_)
        | Command::SingleProcess(_)
        | Command::Status(_)
        | Command::Sweep(_)
        | Command::Generate(_) => return Ok(None),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_frontend::cli::TransportKind as K;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("xrce-agent").chain(args.iter().copied()))
    }

    /// `--version` says the version, the commit and the backends built in; `-V` the first
    /// two on one line.
    #[test]
    fn the_version_names_the_commit_and_the_backends() {
        use clap::CommandFactory;
        let command = Cli::command();
        let long = command.render_long_version();
        let lines: Vec<&str> = long.lines().collect();
        assert_eq!(
            lines.first().copied(),
            Some(concat!("xrce-agent ", env!("CARGO_PKG_VERSION")))
        );
        assert!(lines.iter().any(|l| l.starts_with("commit: ")), "{long}");
        let backends = if cfg!(feature = "cyclone") {
            "DDS backends: cyclone"
        } else {
            "DDS backends: rustdds"
        };
        assert!(lines.iter().any(|l| l.starts_with(backends)), "{long}");
        let middlewares = if cfg!(feature = "zenoh") {
            "middlewares: dds, zenoh"
        } else {
            "middlewares: dds ("
        };
        assert!(lines.iter().any(|l| l.starts_with(middlewares)), "{long}");
        let short = command.render_version();
        assert_eq!(short.lines().count(), 1, "{short}");
        assert!(short.starts_with(concat!("xrce-agent ", env!("CARGO_PKG_VERSION"), " (")));
    }

    fn planned(args: &[&str]) -> FrontendPlan {
        let cli = parse(args).expect("parses");
        plan(cli.command.as_ref().expect("a command"))
            .expect("plan")
            .expect("a transport")
            .0
    }

    #[test]
    fn reference_command_lines_parse_unchanged() {
        assert_eq!(
            planned(&["udp4", "-p", "8888"]),
            FrontendPlan::Ip {
                kind: K::Udp4,
                listen: "0.0.0.0:8888".parse().expect("addr"),
                max_connections: 0,
                processes: 1
            }
        );
        assert_eq!(
            planned(&["udp4", "-p", "8888", "--processes", "3"]),
            FrontendPlan::Ip {
                kind: K::Udp4,
                listen: "0.0.0.0:8888".parse().expect("addr"),
                max_connections: 0,
                processes: 3
            }
        );
        assert!(parse(&["udp4", "-p", "8888", "--processes", "0"]).is_err());
        assert!(parse(&["tcp4", "-p", "8888", "--processes", "2"]).is_err());
        // Values glued to their flag, and verbosity.
        assert_eq!(
            planned(&["tcp6", "-p8888", "-v6"]),
            FrontendPlan::Ip {
                kind: K::Tcp6,
                listen: "[::]:8888".parse().expect("addr"),
                max_connections: 2_000,
                processes: 1
            }
        );
        // The reference's misspelling in its usage line.
        assert_eq!(planned(&["tpc6", "-p", "1"]).kind(), K::Tcp6);
        assert_eq!(
            planned(&["serial", "--dev", "/dev/ttyACM0", "-b", "921600"]),
            FrontendPlan::Serial {
                kind: K::Serial,
                devices: vec!["/dev/ttyACM0".into()],
                baudrate: 921_600,
                flow_control: false
            }
        );
        assert_eq!(
            planned(&["serial", "-D/dev/ttyUSB0"]),
            FrontendPlan::Serial {
                kind: K::Serial,
                devices: vec!["/dev/ttyUSB0".into()],
                baudrate: 115_200,
                flow_control: false
            }
        );
        assert_eq!(
            planned(&["multiserial", "--devs", "/dev/a /dev/b", "-b", "57600"]),
            FrontendPlan::Serial {
                kind: K::Multiserial,
                devices: vec!["/dev/a".into(), "/dev/b".into()],
                baudrate: 57_600,
                flow_control: false
            }
        );
        assert_eq!(
            planned(&["pseudoterminal", "-b", "115200"]),
            FrontendPlan::Pty { baudrate: 115_200 }
        );
    }

    #[test]
    fn discovery_takes_an_optional_port() {
        let cli = parse(&["udp4", "-p", "8888", "-d"]).expect("parses");
        let (_, common) = plan(cli.command.as_ref().expect("a command"))
            .expect("plan")
            .expect("transport");
        assert_eq!(common.discovery, Some(7400));
        let cli = parse(&["udp4", "-d", "7500", "-p", "8888"]).expect("parses");
        let (_, common) = plan(cli.command.as_ref().expect("a command"))
            .expect("plan")
            .expect("transport");
        assert_eq!(common.discovery, Some(7500));
        let cli = parse(&["udp4", "-p", "8888"]).expect("parses");
        let (_, common) = plan(cli.command.as_ref().expect("a command"))
            .expect("plan")
            .expect("transport");
        assert_eq!(common.discovery, None);
    }

    #[test]
    fn device_files_name_the_devices() {
        let dir = std::env::temp_dir().join(format!("xrce-cli-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let f = dir.join("devs");
        std::fs::write(&f, "/dev/ttyUSB0\n\n# spare\n/dev/ttyUSB1\n").expect("write");
        let path = f.display().to_string();
        assert_eq!(
            planned(&["serial", "-f", &path]),
            FrontendPlan::Serial {
                kind: K::Serial,
                devices: vec!["/dev/ttyUSB0".into()],
                baudrate: 115_200,
                flow_control: false
            }
        );
        match planned(&["multiserial", "-f", &path, "--flow-control"]) {
            FrontendPlan::Serial {
                devices,
                flow_control,
                ..
            } => {
                assert_eq!(devices.len(), 2);
                assert!(flow_control);
            }
            other => panic!("{other:?}"),
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn middleware_zenoh_chooses_the_zenoh_backend() {
        use xrce_dds_worker::backend::BackendKind;
        assert_eq!(backend_for("zenoh", None), Ok(Some(BackendKind::Zenoh)));
        assert_eq!(
            backend_for("zenoh", Some(BackendKind::Zenoh)),
            Ok(Some(BackendKind::Zenoh))
        );
        assert!(backend_for("zenoh", Some(BackendKind::Cyclone)).is_err());
        assert_eq!(backend_for("dds", None), Ok(None));
        assert_eq!(
            backend_for("dds", Some(BackendKind::Rustdds)),
            Ok(Some(BackendKind::Rustdds))
        );
        let e = backend_for("mqtt", None).expect_err("unknown");
        assert!(e.to_string().contains("dds and zenoh"), "{e}");
        let cli = parse(&[
            "udp4",
            "-p",
            "1",
            "-m",
            "zenoh",
            "--zenoh-type-hashes",
            "/a,/b",
        ])
        .expect("parses");
        let (_, common) = plan(cli.command.as_ref().expect("a command"))
            .expect("plan")
            .expect("transport");
        assert!(check_supported(&common).is_ok());
        assert_eq!(common.zenoh_type_hashes.len(), 2);
    }

    #[test]
    fn what_this_agent_lacks_is_refused() {
        for args in [
            &["udp4", "-p", "1", "-m", "ced"][..],
            &["udp4", "-p", "1", "-m", "rtps"],
            &["udp4", "-p", "1", "-P", "2020"],
        ] {
            let cli = parse(args).expect("parses");
            let (_, common) = plan(cli.command.as_ref().expect("a command"))
                .expect("plan")
                .expect("transport");
            assert!(check_supported(&common).is_err(), "{args:?}");
        }
        let cli = parse(&["canfd", "-D", "can0", "-I", "1"]).expect("parses");
        let e = plan(cli.command.as_ref().expect("a command")).expect_err("refused");
        assert!(e.downcast_ref::<Unsupported>().is_some());
        // Usage errors: clap's exit status is 2 as well.
        let e = parse(&["serial"]).expect_err("a device is required");
        assert_eq!(e.exit_code(), 2);
        let e = parse(&["udp4"]).expect_err("a port is required");
        assert_eq!(e.exit_code(), 2);
        let cli = parse(&["multiserial", "--devs", "/dev/a /dev/a"]).expect("parses");
        assert!(plan(cli.command.as_ref().expect("a command")).is_err());
        for bad in ["0", "-1", "lots", "1048577"] {
            let e = parse(&["udp4", "-p", "1", "--memory-limit", bad]).expect_err(bad);
            assert_eq!(e.exit_code(), 2, "{bad}");
        }
    }

    #[test]
    fn the_memory_limit_is_in_mib() {
        let cli = parse(&["tcp4", "-p", "1", "--memory-limit", "256"]).expect("parses");
        let (_, common) = plan(cli.command.as_ref().expect("a command"))
            .expect("plan")
            .expect("transport");
        assert_eq!(common.memory_limit, Some(256));
    }
}
