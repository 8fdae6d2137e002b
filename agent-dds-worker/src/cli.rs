//! Command-line settings of the worker, shared by `xrce-dds-worker` and `xrce-agent dds-worker`.

use std::net::IpAddr;

use crate::backend::ports::ReservedPorts;
use crate::backend::{BackendKind, DdsConfig};
use crate::domains::{DomainPolicy, DomainSet};
use crate::process::WorkerProcess;
use crate::worker::WorkerConfig;

/// The environment variables a worker reads settings from when its command line does not
/// give them. A supervisor passes every setting on the command line
/// ([`WorkerArgs::to_args`]) and removes these from its worker's environment, so that what it
/// decided is what the worker runs with, whatever the worker inherited.
pub const SETTINGS_ENV: [&str; 20] = [
    "XRCE_INSTANCE",
    "XRCE_DDS_INTERFACES",
    "XRCE_DDS_BACKEND",
    "XRCE_REFS",
    "XRCE_ROS_GRAPH",
    "XRCE_ROS_DISTRO",
    "XRCE_SHARE_WRITERS",
    "XRCE_FRONTEND_GRACE",
    "XRCE_DOMAINS",
    "XRCE_MAX_DOMAINS",
    "XRCE_RESERVED_PORTS",
    "XRCE_ZENOH_TYPE_HASHES",
    "XRCE_LOCAL_DELIVERY",
    "XRCE_MAX_ENTITIES_PER_CLIENT",
    "XRCE_MAX_ENTITIES",
    "XRCE_MAX_SAMPLES_PER_ENDPOINT",
    "XRCE_MAX_INSTANCES_PER_ENDPOINT",
    "XRCE_MAX_SAMPLES_PER_CLIENT",
    "XRCE_MAX_SAMPLES",
    "XRCE_LOG",
];

/// What clients may make the worker hold ([`crate::bounds`]), each unset for its default:
/// the same options on the worker's command line and the agent's (a gateway file's
/// `[worker]` keys of the same names, with `_`).
#[derive(Debug, Clone, Default, PartialEq, Eq, clap::Args)]
pub struct BoundsArgs {
    /// DDS entities of one client (default 1,024); one more is refused with
    /// STATUS_ERR_RESOURCES.
    #[arg(long = "max-entities-per-client", env = "XRCE_MAX_ENTITIES_PER_CLIENT", value_name = "N", value_parser = at_least_one::<usize>)]
    pub max_entities_per_client: Option<usize>,
    /// DDS entities of every client together (default 32,768).
    #[arg(long = "max-entities", env = "XRCE_MAX_ENTITIES", value_name = "N", value_parser = at_least_one::<usize>)]
    pub max_entities: Option<usize>,
    /// Samples one DDS reader's or writer's cache may keep (default 4,096): a deeper
    /// history, KEEP_ALL and unlimited resource limits are clamped to it.
    #[arg(long = "max-samples-per-endpoint", env = "XRCE_MAX_SAMPLES_PER_ENDPOINT", value_name = "N", value_parser = at_least_one::<u32>)]
    pub max_samples_per_endpoint: Option<u32>,
    /// Instances one endpoint of a keyed topic may keep (default 1,024).
    #[arg(long = "max-instances-per-endpoint", env = "XRCE_MAX_INSTANCES_PER_ENDPOINT", value_name = "N", value_parser = at_least_one::<u32>)]
    pub max_instances_per_endpoint: Option<u32>,
    /// Samples the endpoints of one client may keep together (default 65,536).
    #[arg(long = "max-samples-per-client", env = "XRCE_MAX_SAMPLES_PER_CLIENT", value_name = "N", value_parser = at_least_one::<u64>)]
    pub max_samples_per_client: Option<u64>,
    /// Samples the endpoints of every client may keep together (default 1,048,576).
    #[arg(long = "max-samples", env = "XRCE_MAX_SAMPLES", value_name = "N", value_parser = at_least_one::<u64>)]
    pub max_samples: Option<u64>,
}

/// A whole number of at least 1 (a bound of 0 would refuse everything).
fn at_least_one<T: std::str::FromStr + PartialOrd + From<u8>>(s: &str) -> Result<T, String> {
    match s.parse::<T>() {
        Ok(n) if n >= T::from(1) => Ok(n),
        _ => Err(format!("{s:?} is not a whole number of at least 1")),
    }
}

impl BoundsArgs {
    /// These bounds, each unset one taken from `fallback`.
    pub fn or(&self, fallback: &BoundsArgs) -> BoundsArgs {
        BoundsArgs {
            max_entities_per_client: self
                .max_entities_per_client
                .or(fallback.max_entities_per_client),
            max_entities: self.max_entities.or(fallback.max_entities),
            max_samples_per_endpoint: self
                .max_samples_per_endpoint
                .or(fallback.max_samples_per_endpoint),
            max_instances_per_endpoint: self
                .max_instances_per_endpoint
                .or(fallback.max_instances_per_endpoint),
            max_samples_per_client: self
                .max_samples_per_client
                .or(fallback.max_samples_per_client),
            max_samples: self.max_samples.or(fallback.max_samples),
        }
    }

    /// The worker's bounds: the defaults with the ones given here.
    pub fn bounds(&self) -> crate::bounds::WorkerBounds {
        let d = crate::bounds::WorkerBounds::default();
        let count = |v: Option<u32>, d: i32| v.map_or(d, |v| i32::try_from(v).unwrap_or(i32::MAX));
        crate::bounds::WorkerBounds {
            samples_per_endpoint: count(self.max_samples_per_endpoint, d.samples_per_endpoint),
            instances_per_endpoint: count(
                self.max_instances_per_endpoint,
                d.instances_per_endpoint,
            ),
            samples_per_client: self.max_samples_per_client.unwrap_or(d.samples_per_client),
            samples_total: self.max_samples.unwrap_or(d.samples_total),
            entities_per_client: self
                .max_entities_per_client
                .unwrap_or(d.entities_per_client),
            entities_total: self.max_entities.unwrap_or(d.entities_total),
        }
    }

    /// The given ones as `--option=value` arguments.
    fn to_args(&self, out: &mut Vec<String>) {
        let BoundsArgs {
            max_entities_per_client,
            max_entities,
            max_samples_per_endpoint,
            max_instances_per_endpoint,
            max_samples_per_client,
            max_samples,
        } = self;
        let mut arg = |k: &str, v: Option<String>| {
            if let Some(v) = v {
                out.push(format!("{k}={v}"));
            }
        };
        arg(
            "--max-entities-per-client",
            max_entities_per_client.map(|v| v.to_string()),
        );
        arg("--max-entities", max_entities.map(|v| v.to_string()));
        arg(
            "--max-samples-per-endpoint",
            max_samples_per_endpoint.map(|v| v.to_string()),
        );
        arg(
            "--max-instances-per-endpoint",
            max_instances_per_endpoint.map(|v| v.to_string()),
        );
        arg(
            "--max-samples-per-client",
            max_samples_per_client.map(|v| v.to_string()),
        );
        arg("--max-samples", max_samples.map(|v| v.to_string()));
    }
}

/// Settings of a DDS worker process. The supervisor hands its worker the settings as this
/// type ([`WorkerArgs::to_args`]); adding a setting is a field here (the compiler then asks
/// for its argument in `to_args`).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct WorkerArgs {
    /// Agent instance name (all processes of one agent share it).
    #[arg(long, env = "XRCE_INSTANCE", default_value = "default")]
    pub instance: String,
    /// Restrict DDS to these local addresses (comma-separated or repeated); default: all.
    #[arg(
        long = "dds-interface",
        env = "XRCE_DDS_INTERFACES",
        value_delimiter = ','
    )]
    pub dds_interfaces: Vec<IpAddr>,
    /// The DDS implementation: `cyclone` (Cyclone DDS, the default in builds with the
    /// `cyclone` feature) or `rustdds` (the default without it).
    #[arg(long = "dds-backend", env = "XRCE_DDS_BACKEND", value_enum, default_value_t = BackendKind::default())]
    pub dds_backend: BackendKind,
    /// References file: Fast DDS XML profiles that clients may create by reference.
    #[arg(short = 'r', long = "refs", env = "XRCE_REFS")]
    pub refs: Option<std::path::PathBuf>,
    /// Announce XRCE participants named like ROS 2 nodes that have an endpoint on a ROS topic
    /// (`rt/`, `rq/`, `rr/`: micro-ROS) on `ros_discovery_info`, so ROS 2 tools list them.
    #[arg(long = "ros-graph", env = "XRCE_ROS_GRAPH", default_value_t = true, action = clap::ArgAction::Set)]
    pub ros_graph: bool,
    /// The ROS 2 distribution whose `ros_discovery_info` layout the graph is published in:
    /// `humble` (24-octet GIDs) or `iron`, `jazzy`, `kilted`, `rolling` (16-octet GIDs).
    /// Without it, `ROS_DISTRO` as a sourced ROS 2 shell sets it; else jazzy.
    #[arg(
        long = "ros-distro",
        env = "XRCE_ROS_DISTRO",
        value_enum,
        ignore_case = true
    )]
    pub ros_distro: Option<crate::ros_graph::RosDistro>,
    /// Map the XRCE data writers of one domain, topic, type and QoS onto shared DDS writers,
    /// one per 32 clients, each keeping 32 times the clients' history depth (volatile,
    /// shared-ownership writers only): thousands of clients publishing on one topic then
    /// cost a few DDS writers. DDS readers see one writer per group instead of one per
    /// client (one GUID, no per-client liveliness).
    #[arg(long = "share-writers", env = "XRCE_SHARE_WRITERS", default_value_t = false, action = clap::ArgAction::Set)]
    pub share_writers: bool,
    /// Seconds the entities of a front-end whose process is gone are kept for it to come
    /// back, before they are deleted.
    #[arg(
        long = "frontend-grace",
        env = "XRCE_FRONTEND_GRACE",
        default_value_t = 30.0
    )]
    pub frontend_grace: f64,
    /// The DDS domain ids clients may use: ids and ranges, comma-separated (e.g.
    /// `0-10,42`); a participant in another domain is refused with STATUS_ERR_DENIED.
    /// Without it any domain id is allowed, but at most `--max-domains` at once.
    #[arg(long = "domains", env = "XRCE_DOMAINS")]
    pub domains: Option<DomainSet>,
    /// Most distinct DDS domains in use at once (each costs DDS participants, threads and
    /// sockets); a participant in one more is refused with STATUS_ERR_RESOURCES. Default:
    /// 8 without `--domains`, no cap with it.
    #[arg(
        long = "max-domains",
        env = "XRCE_MAX_DOMAINS",
        value_parser = clap::value_parser!(u16).range(1..=i64::from(crate::domains::DOMAIN_COUNT))
    )]
    pub max_domains: Option<u16>,
    /// The UDP ports the agent's front-ends serve (comma-separated): DDS leaves them to the
    /// front-ends, moving off a well-known DDS port such as 7401. The supervisor sets it.
    #[arg(
        long = "reserved-ports",
        env = "XRCE_RESERVED_PORTS",
        default_value = ""
    )]
    pub reserved_ports: ReservedPorts,
    /// With `--dds-backend zenoh` (`-m zenoh`): where the RIHS01 type hashes rmw_zenoh puts
    /// in its keys are looked up, before `AMENT_PREFIX_PATH` and the built-in table of ROS 2
    /// Jazzy's common interfaces: ROS installations (an install prefix such as
    /// `/opt/ros/jazzy`, or its `share` folder) and tables (`pkg/msg/Type RIHS01_...` lines);
    /// comma-separated or repeated.
    #[arg(
        long = "zenoh-type-hashes",
        env = "XRCE_ZENOH_TYPE_HASHES",
        value_delimiter = ','
    )]
    pub zenoh_type_hashes: Vec<std::path::PathBuf>,
    /// With RustDDS: deliver the agent's own samples to its own readers inside the worker
    /// (`false`: through UDP loopback, as RustDDS does between processes; to measure the
    /// difference, or to rule the in-process delivery out when looking for a fault).
    #[arg(
        long = "local-delivery",
        env = "XRCE_LOCAL_DELIVERY",
        default_value_t = true,
        action = clap::ArgAction::Set,
        value_parser = local_delivery
    )]
    pub local_delivery: bool,
    /// The DDS domain of a participant created in domain 255, "the agent's default". Without
    /// it, `XRCE_DOMAIN_ID_OVERRIDE` (as MicroXRCEAgent), else `ROS_DOMAIN_ID`, else 0.
    #[arg(
        long = "default-domain",
        value_parser = clap::value_parser!(u16).range(0..=i64::from(crate::domains::MAX_DOMAIN_ID))
    )]
    pub default_domain: Option<u16>,
    /// What clients may make the worker hold.
    #[command(flatten)]
    pub bounds: BoundsArgs,
    /// Log filter (tracing syntax), e.g. `info` or `xrce_dds_worker=debug`.
    #[arg(long, env = "XRCE_LOG", default_value = "info,rustdds=error")]
    pub log: String,
}

impl WorkerArgs {
    /// Every setting as an empty command line gives them: the environment variables the
    /// worker reads ([`SETTINGS_ENV`]) included. Where a supervisor's own configuration (a
    /// gateway file) leaves a setting unset, this is where it comes from. A variable with a
    /// value the worker refuses is an error, not a fallback to the built-in defaults: among
    /// them are the ones that confine DDS (`XRCE_DDS_INTERFACES`, `XRCE_DOMAINS`), which must
    /// never be dropped silently.
    pub fn from_environment() -> anyhow::Result<Self> {
        xrce_ipc::settings::from_environment("dds-worker").map_err(|e| {
            let rendered = e.render().to_string();
            let why = rendered.lines().next().unwrap_or_default();
            anyhow::anyhow!(
                "an environment variable of the DDS worker's settings ({}) is refused: {}",
                SETTINGS_ENV.join(", "),
                why.trim_start_matches("error: ")
            )
        })
    }

    /// Every setting at its built-in default, whatever the environment says.
    pub fn built_in() -> Self {
        xrce_ipc::settings::built_in("dds-worker")
    }

    /// These settings as the worker's command line (what the supervisor runs it with):
    /// every field, so that the process gets exactly what its supervisor decided.
    pub fn to_args(&self) -> Vec<String> {
        let WorkerArgs {
            instance,
            dds_interfaces,
            dds_backend,
            refs,
            ros_graph,
            ros_distro,
            share_writers,
            frontend_grace,
            domains,
            max_domains,
            reserved_ports,
            zenoh_type_hashes,
            local_delivery,
            default_domain,
            bounds,
            log,
        } = self;
        // `--key=value`: a value that starts with `-` (`-1`, an instance `-gw`) stays a value.
        let mut a: Vec<String> = Vec::new();
        let mut arg = |k: &str, v: String| a.push(format!("{k}={v}"));
        arg("--instance", instance.clone());
        arg("--dds-backend", dds_backend.as_str().to_string());
        arg("--ros-graph", ros_graph.to_string());
        arg("--share-writers", share_writers.to_string());
        arg("--frontend-grace", frontend_grace.to_string());
        arg("--log", log.clone());
        if !dds_interfaces.is_empty() {
            let list: Vec<String> = dds_interfaces.iter().map(ToString::to_string).collect();
            arg("--dds-interface", list.join(","));
        }
        if let Some(r) = refs {
            arg("--refs", r.display().to_string());
        }
        if let Some(d) = ros_distro {
            arg("--ros-distro", d.to_string());
        }
        if let Some(d) = domains {
            arg("--domains", d.to_string());
        }
        if let Some(n) = max_domains {
            arg("--max-domains", n.to_string());
        }
        arg("--reserved-ports", reserved_ports.to_string());
        arg("--local-delivery", local_delivery.to_string());
        if let Some(d) = default_domain {
            arg("--default-domain", d.to_string());
        }
        if !zenoh_type_hashes.is_empty() {
            let list: Vec<String> = zenoh_type_hashes
                .iter()
                .map(|p| p.display().to_string())
                .collect();
            arg("--zenoh-type-hashes", list.join(","));
        }
        bounds.to_args(&mut a);
        a
    }
}

/// The domain of "the agent's default" (domain id 255): `given` (`--default-domain`), else
/// the environment's `XRCE_DOMAIN_ID_OVERRIDE` (MicroXRCEAgent's variable), else
/// `ROS_DOMAIN_ID` (ROS 2's, what micro-ROS users set), else 0. A variable set but blank is
/// unset (as ROS 2 reads `ROS_DOMAIN_ID`); one that is no DDS domain id is refused here, at
/// start, rather than at a client's first participant.
pub fn resolve_default_domain(
    given: Option<u16>,
    env: impl Fn(&str) -> Option<std::ffi::OsString>,
) -> anyhow::Result<u16> {
    if let Some(d) = given {
        return Ok(d);
    }
    for var in ["XRCE_DOMAIN_ID_OVERRIDE", "ROS_DOMAIN_ID"] {
        let Some(v) = env(var) else { continue };
        let text = v.to_string_lossy();
        if text.trim().is_empty() {
            continue;
        }
        return text
            .trim()
            .parse::<u16>()
            .ok()
            .filter(|d| *d <= crate::domains::MAX_DOMAIN_ID)
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "{var}={text:?} is not a DDS domain id (0 to {})",
                    crate::domains::MAX_DOMAIN_ID
                )
            });
    }
    Ok(0)
}

/// `--local-delivery`'s parser: a boolean as clap reads one (`off`, `0`, `false`, `no` are
/// false), blank meaning the default (on), so that `XRCE_LOCAL_DELIVERY=` stops nothing.
fn local_delivery(s: &str) -> Result<bool, String> {
    use clap::builder::TypedValueParser;
    if s.trim().is_empty() {
        return Ok(true);
    }
    clap::builder::BoolishValueParser::new()
        .parse_ref(
            &clap::Command::new("xrce-dds-worker"),
            None,
            std::ffi::OsStr::new(s.trim()),
        )
        .map_err(|_| format!("{s:?} is not on or off (true, false, 1, 0, yes, no)"))
}

/// Runs a worker until SIGINT/SIGTERM.
pub fn run(args: WorkerArgs) -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&args.log).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    xrce_common::fault::install_and_log("worker")?;
    let (config, ros_distro) = configure(args)?;
    let mut process = WorkerProcess::start(config)?;
    process.worker_mut().set_ros_distro(ros_distro);
    // Under systemd (a unit of its own), the worker is ready once it serves.
    if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
        tracing::warn!(error = %e, "sd_notify failed");
    }
    process.run()
}

/// The worker's configuration from its settings (the references file read, the ROS
/// distribution and default domain resolved from the environment, the open-file limit
/// raised), and the ROS distribution its graph is published in; logged.
pub fn configure(args: WorkerArgs) -> anyhow::Result<(WorkerConfig, crate::ros_graph::RosDistro)> {
    // Before anything starts: a ROS_DISTRO the agent does not know stops it here.
    let (ros_distro, distro_source) = crate::ros_graph::RosDistro::resolve(
        args.ros_distro,
        std::env::var_os("ROS_DISTRO").as_deref(),
    )?;
    let default_domain = resolve_default_domain(args.default_domain, |v| std::env::var_os(v))?;
    raise_fd_limit();
    let references = match &args.refs {
        Some(path) => {
            let refs = crate::references::References::load(path)?;
            tracing::info!(path = %path.display(), profiles = refs.len(), "references loaded");
            refs
        }
        None => Default::default(),
    };
    let domains = DomainPolicy::from_options(args.domains, args.max_domains.map(usize::from));
    tracing::info!(
        domains = %domains.allowed.as_ref().map_or("any".to_string(), ToString::to_string),
        max_in_use = ?domains.max_in_use,
        "DDS domains clients may use"
    );
    let config = WorkerConfig {
        instance: args.instance,
        backend: args.dds_backend,
        dds: DdsConfig {
            interfaces: args.dds_interfaces,
            reserved_ports: args.reserved_ports,
            zenoh: crate::backend::ZenohSettings {
                type_hashes: args.zenoh_type_hashes,
            },
            rustdds_loopback: !args.local_delivery,
        },
        references,
        ros_graph: args.ros_graph,
        share_writers: args.share_writers,
        frontend_grace: std::time::Duration::from_secs_f64(if args.frontend_grace.is_finite() {
            args.frontend_grace.clamp(0.0, 86_400.0)
        } else {
            30.0
        }),
        domains,
        bounds: args.bounds.bounds(),
        default_domain,
    };
    if args.ros_graph {
        tracing::info!(
            distro = %ros_distro,
            from = ?distro_source,
            gid_octets = ros_distro.gid_layout().octets(),
            "ROS 2 graph layout"
        );
    }
    Ok((config, ros_distro))
}

/// Raises the open-file limit to its hard limit: RustDDS holds about two descriptors per
/// data writer or reader (its notification channels), so a worker serving 1,000 clients
/// needs over 2,000, beyond the usual soft limit of 1,024.
fn raise_fd_limit() {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    match getrlimit(Resource::RLIMIT_NOFILE) {
        Ok((soft, hard)) if soft < hard => match setrlimit(Resource::RLIMIT_NOFILE, hard, hard) {
            Ok(()) => tracing::info!(from = soft, to = hard, "open-file limit raised"),
            Err(e) => tracing::warn!(soft, hard, error = %e, "could not raise the open-file limit"),
        },
        Ok((soft, _)) => tracing::debug!(limit = soft, "open-file limit"),
        Err(e) => tracing::warn!(error = %e, "could not read the open-file limit"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: WorkerArgs,
    }

    /// The supervisor's settings reach the worker exactly: every field through `to_args`
    /// and back, from the built-in defaults and with every optional setting given.
    #[test]
    fn settings_survive_the_command_line() {
        let parse = |args: Vec<String>| {
            Cli::try_parse_from(std::iter::once("w".to_string()).chain(args))
                .expect("the worker parses its own command line")
                .args
        };
        let built_in = WorkerArgs::built_in();
        assert_eq!(parse(built_in.to_args()), built_in);
        assert!(built_in.ros_graph && !built_in.share_writers);
        assert!(built_in.reserved_ports.is_empty());
        let every = WorkerArgs {
            instance: "gw-1234abcd".into(),
            dds_interfaces: vec!["127.0.0.1".parse().expect("address")],
            dds_backend: BackendKind::Rustdds,
            refs: Some("/etc/xrce-agent/refs.xml".into()),
            ros_graph: false,
            ros_distro: Some(crate::ros_graph::RosDistro::Humble),
            share_writers: true,
            frontend_grace: 2.5,
            domains: Some("0-10,42".parse().expect("domains")),
            max_domains: Some(4),
            reserved_ports: ReservedPorts::new([7401, 8888]),
            zenoh_type_hashes: vec!["/opt/ros/jazzy".into(), "/etc/xrce-agent/hashes.tsv".into()],
            local_delivery: false,
            default_domain: Some(45),
            bounds: BoundsArgs {
                max_entities_per_client: Some(10),
                max_entities: Some(100),
                max_samples_per_endpoint: Some(64),
                max_instances_per_endpoint: Some(8),
                max_samples_per_client: Some(1000),
                max_samples: Some(10_000),
            },
            log: "debug".into(),
        };
        assert_eq!(parse(every.to_args()), every);
        // Values that start with `-` stay values.
        let dashed = WorkerArgs {
            instance: "-gw".into(),
            frontend_grace: -1.0,
            ..every
        };
        assert_eq!(parse(dashed.to_args()), dashed);
    }

    #[test]
    fn the_default_domain_is_the_option_then_the_variables_then_zero() {
        use std::ffi::OsString;
        let env = |vars: &'static [(&'static str, &'static str)]| {
            move |name: &str| {
                vars.iter()
                    .find(|(n, _)| *n == name)
                    .map(|(_, v)| OsString::from(v))
            }
        };
        assert_eq!(resolve_default_domain(None, env(&[])).ok(), Some(0));
        assert_eq!(
            resolve_default_domain(None, env(&[("ROS_DOMAIN_ID", " 65 ")])).ok(),
            Some(65)
        );
        let both = env(&[("XRCE_DOMAIN_ID_OVERRIDE", "66"), ("ROS_DOMAIN_ID", "67")]);
        assert_eq!(resolve_default_domain(None, both).ok(), Some(66));
        assert_eq!(resolve_default_domain(Some(1), both).ok(), Some(1));
        // Blank is unset (as ROS 2 reads it).
        let blank = env(&[("XRCE_DOMAIN_ID_OVERRIDE", " "), ("ROS_DOMAIN_ID", "")]);
        assert_eq!(resolve_default_domain(None, blank).ok(), Some(0));
        for bad in ["233", "-1", "x"] {
            let vars: &'static [(&'static str, &'static str)] = match bad {
                "233" => &[("ROS_DOMAIN_ID", "233")],
                "-1" => &[("XRCE_DOMAIN_ID_OVERRIDE", "-1")],
                _ => &[("ROS_DOMAIN_ID", "x")],
            };
            let err = resolve_default_domain(None, env(vars)).expect_err(bad);
            assert!(err.to_string().contains("not a DDS domain id"), "{err}");
        }
        // The option takes DDS's domain ids only.
        assert!(Cli::try_parse_from(["w", "--default-domain", "233"]).is_err());
        let cli = Cli::try_parse_from(["w", "--default-domain", "232", "--local-delivery", "off"])
            .expect("valid");
        assert_eq!(cli.args.default_domain, Some(232));
        assert!(!cli.args.local_delivery);
        assert_eq!(local_delivery(""), Ok(true));
        assert_eq!(local_delivery("no"), Ok(false));
        assert!(local_delivery("maybe").is_err());
    }

    #[test]
    fn the_domain_options_are_parsed_into_the_policy() {
        let cli = Cli::try_parse_from(["w", "--domains", "0-10,42", "--max-domains", "4"])
            .expect("valid options");
        let policy = DomainPolicy::from_options(
            cli.args.domains.clone(),
            cli.args.max_domains.map(usize::from),
        );
        assert_eq!(policy.max_in_use, Some(4));
        assert!(policy
            .allowed
            .as_ref()
            .is_some_and(|a| a.contains(42) && !a.contains(11)));
        let cli = Cli::try_parse_from(["w"]).expect("no options");
        assert_eq!(
            DomainPolicy::from_options(cli.args.domains, cli.args.max_domains.map(usize::from)),
            DomainPolicy::default()
        );
        // --ros-distro: the names ROS_DISTRO uses; another is refused, naming them.
        let cli = Cli::try_parse_from(["w", "--ros-distro", "humble"]).expect("valid");
        assert_eq!(
            cli.args.ros_distro,
            Some(crate::ros_graph::RosDistro::Humble)
        );
        let err = Cli::try_parse_from(["w", "--ros-distro", "foxy"]).expect_err("unknown");
        assert!(
            err.to_string()
                .contains("humble, iron, jazzy, kilted, rolling"),
            "{err}"
        );
        for bad in [
            &["w", "--domains", "0-300"][..],
            &["w", "--domains", "x"],
            &["w", "--max-domains", "0"],
            &["w", "--max-domains", "234"],
        ] {
            assert!(Cli::try_parse_from(bad).is_err(), "{bad:?}");
        }
    }
}
