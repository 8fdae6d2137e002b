//! The gateway configuration file (`xrce-agent --config FILE`): one DDS worker and one
//! front-end process per `[[frontend]]`, each its own transport and interface.
//!
//! ```toml
//! [agent]
//! instance = "gw"                  # optional: shared-memory name of the agent's processes
//! verbose = 4                      # optional, like -v
//! memory_limit_mib = 512           # optional, like --memory-limit (per process)
//! discard_sessions = false         # optional, like --discard-sessions
//! single_process = false           # optional, like --single-process (one front-end only)
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

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};

use serde::Deserialize;
use toml::Spanned;
use xrce_frontend::cli::AdmissionArgs;

use crate::cli::FrontendPlan;

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
    /// The front-end and the worker in one process, like `--single-process` (a file with
    /// one front-end only).
    pub single_process: Option<bool>,
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

/// `processes` as written: a count or a word (`auto`).
#[derive(Debug, Clone, Deserialize)]
#[serde(untagged, expecting = "a count 1-64 or \"auto\"")]
enum ProcessCount {
    Count(i64),
    Word(String),
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
    processes: Option<Spanned<ProcessCount>>,
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

/// Reads and checks a gateway file.
pub fn load(path: &Path) -> Result<Gateway, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
        path: path.display().to_string(),
        line: 0,
        message: format!("cannot read it: {e}"),
    })?;
    parse(path, &text)
}

pub use check::parse;

mod check;
mod keys;
pub use keys::{reference, KeyDoc, KEYS};

#[cfg(test)]
mod tests;
