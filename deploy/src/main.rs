//! `xrce-agent`: the user-facing command, a drop-in for eProsima's `MicroXRCEAgent`
//! (`xrce-agent udp4 -p 8888`). It supervises one DDS worker and one front-end, which are
//! this same executable started with the hidden `dds-worker` and `frontend` subcommands, so
//! one binary is all a user needs.

use std::net::IpAddr;

use clap::{Args, Parser, Subcommand};
use xrce_agent::{supervise, verbosity_filter, ChildSpec};

/// DDS-XRCE agent: lets XRCE clients (Micro XRCE-DDS, micro-ROS, PX4) join a DDS data space.
#[derive(Debug, Parser)]
#[command(name = "xrce-agent", version)]
struct Cli {
    #[command(subcommand)]
    transport: Transport,
}

#[derive(Debug, Subcommand)]
enum Transport {
    /// Serve clients over UDP/IPv4.
    Udp4(Common),
    /// Serve clients over UDP/IPv6.
    Udp6(Common),
    /// Internal: run the DDS worker (started by the supervisor).
    #[command(hide = true)]
    DdsWorker(xrce_dds_worker::cli::WorkerArgs),
    /// Internal: run a front-end (started by the supervisor).
    #[command(hide = true)]
    Frontend(xrce_frontend::cli::FrontendArgs),
}

#[derive(Debug, Args)]
struct Common {
    /// UDP port to listen on.
    #[arg(short = 'p', long = "port")]
    port: u16,
    /// Verbosity 0 (off) … 6 (trace); 4 = info, 5 adds per-message debug logs.
    #[arg(short = 'v', long = "verbose", default_value_t = 4, value_parser = clap::value_parser!(u8).range(0..=6))]
    verbose: u8,
    /// Middleware (accepted for compatibility; only `dds` exists here).
    #[arg(short = 'm', long = "middleware", default_value = "dds", value_parser = ["dds"])]
    middleware: String,
    /// References file: Fast DDS XML profiles that clients may create by reference.
    #[arg(short = 'r', long = "refs")]
    refs: Option<std::path::PathBuf>,
    /// Address to bind (default: all interfaces).
    #[arg(long)]
    bind: Option<IpAddr>,
    /// Restrict DDS to these local addresses (comma-separated); default: every interface.
    #[arg(
        long = "dds-interface",
        env = "XRCE_DDS_INTERFACES",
        value_delimiter = ','
    )]
    dds_interfaces: Vec<IpAddr>,
    /// Instance name shared by the agent's processes (default: derived from transport and port).
    #[arg(long, env = "XRCE_INSTANCE")]
    instance: Option<String>,
    /// Protocol dialect for every session: `spec` or `eprosima` (default: per session, from
    /// the client's vendor id).
    #[arg(long, env = "XRCE_DIALECT")]
    dialect: Option<xrce_common::wire::Dialect>,
    /// Seconds of silence after which a client's session and entities are deleted; silent
    /// clients are probed with GET_INFO first. 0 (default) keeps them, like MicroXRCEAgent.
    #[arg(
        long = "client-dead-time",
        env = "XRCE_CLIENT_DEAD_TIME",
        default_value_t = 0.0
    )]
    client_dead_time: f64,
    /// Announce XRCE participants named like ROS 2 nodes that have an endpoint on a ROS topic
    /// (`rt/`, `rq/`, `rr/`: micro-ROS) on `ros_discovery_info`, so `ros2 node list` shows
    /// them: `true` (default) or `false`.
    #[arg(long = "ros-graph", env = "XRCE_ROS_GRAPH", default_value_t = true, action = clap::ArgAction::Set)]
    ros_graph: bool,
    /// Map the XRCE data writers of one domain, topic, type and QoS onto shared DDS writers,
    /// one per 32 clients (volatile, shared-ownership writers only): `true` or `false`
    /// (default). Scales to thousands of clients publishing on one topic; DDS readers then
    /// see one writer per group of clients.
    #[arg(long = "share-writers", env = "XRCE_SHARE_WRITERS", default_value_t = false, action = clap::ArgAction::Set)]
    share_writers: bool,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let (common, v6) = match cli.transport {
        Transport::Udp4(ref c) => (c, false),
        Transport::Udp6(ref c) => (c, true),
        Transport::DdsWorker(args) => return xrce_dds_worker::cli::run(args),
        Transport::Frontend(args) => return xrce_frontend::cli::run(args),
    };
    let filter =
        std::env::var("XRCE_LOG").unwrap_or_else(|_| verbosity_filter(common.verbose).to_string());
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&filter).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    // By default every agent is its own instance (two agents on one port, bound to different
    // addresses or in different network namespaces, must not share their IPC).
    let stem = format!("{}-{}-", if v6 { "udp6" } else { "udp4" }, common.port);
    let instance = common
        .instance
        .clone()
        .unwrap_or_else(|| format!("{stem}{}", std::process::id()));
    if !xrce_common::ipc::shm::valid_instance(&instance) {
        anyhow::bail!("instance name {instance:?} must be 1-32 characters of [A-Za-z0-9_-]");
    }
    let bind: IpAddr = common.bind.unwrap_or(if v6 {
        IpAddr::V6(std::net::Ipv6Addr::UNSPECIFIED)
    } else {
        IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED)
    });
    let udp = std::net::SocketAddr::new(bind, common.port);
    // Fail early and clearly if the port is taken, instead of a crash loop in the child.
    drop(
        std::net::UdpSocket::bind(udp)
            .map_err(|e| anyhow::anyhow!("cannot bind UDP {udp}: {e}"))?,
    );
    let exe =
        std::env::current_exe().map_err(|e| anyhow::anyhow!("locating this executable: {e}"))?;
    let mut env = vec![
        ("XRCE_INSTANCE".to_string(), instance.clone()),
        ("XRCE_LOG".to_string(), filter.clone()),
    ];
    if let Some(path) = &common.refs {
        // Refuse a bad file here, with a clear message, rather than in a worker crash loop.
        let refs = xrce_dds_worker::references::References::load(path)?;
        let absolute = std::fs::canonicalize(path).unwrap_or_else(|_| path.clone());
        tracing::info!(path = %absolute.display(), profiles = refs.len(), "references file");
        env.push(("XRCE_REFS".into(), absolute.display().to_string()));
    }
    if let Some(d) = common.dialect {
        env.push((
            "XRCE_DIALECT".into(),
            if d == xrce_common::wire::Dialect::Spec {
                "spec"
            } else {
                "eprosima"
            }
            .into(),
        ));
    }
    if !(common.client_dead_time.is_finite()
        && (0.0..=31_536_000.0).contains(&common.client_dead_time))
    {
        anyhow::bail!("--client-dead-time must be 0 to 31536000 seconds (a year)");
    }
    env.push((
        "XRCE_CLIENT_DEAD_TIME".into(),
        common.client_dead_time.to_string(),
    ));
    env.push(("XRCE_ROS_GRAPH".into(), common.ros_graph.to_string()));
    env.push((
        "XRCE_SHARE_WRITERS".into(),
        common.share_writers.to_string(),
    ));
    if !common.dds_interfaces.is_empty() {
        let list: Vec<String> = common
            .dds_interfaces
            .iter()
            .map(ToString::to_string)
            .collect();
        env.push(("XRCE_DDS_INTERFACES".into(), list.join(",")));
    }
    let specs = vec![
        ChildSpec {
            name: "xrce-dds-worker".into(),
            program: exe.clone(),
            args: vec!["dds-worker".into()],
            env: env.clone(),
        },
        ChildSpec {
            name: "xrce-frontend-0".into(),
            program: exe,
            args: vec![
                "frontend".into(),
                "--frontend-id".into(),
                "0".into(),
                "--udp".into(),
                udp.to_string(),
            ],
            env,
        },
    ];
    tracing::info!(%udp, %instance, "xrce-agent starting");
    let explicit_instance = common.instance.is_some();
    let cleanup = |last: bool| {
        if !last && !explicit_instance {
            // Leftovers of earlier agents on this port that died without cleaning up.
            for dead in xrce_common::ipc::shm::dead_instances(&stem) {
                if let Ok(n) = xrce_common::ipc::shm::IpcNode::new(&dead, "xrce-agent") {
                    drop(n);
                }
                xrce_common::ipc::shm::remove_instance_leftovers(&dead);
                tracing::info!(instance = %dead, "removed shared memory of a dead agent");
            }
        }
        // Creating a node removes what dead nodes of this instance left in shared memory.
        match xrce_common::ipc::shm::IpcNode::new(&instance, "xrce-agent") {
            Ok(n) => drop(n),
            Err(e) => tracing::warn!(error = %e, "shared-memory cleanup failed"),
        }
        if last {
            xrce_common::ipc::shm::remove_instance_leftovers(&instance);
        }
    };
    // Report readiness once the front-end answers an XRCE ping (to systemd too, if present).
    let probe = xrce_agent::readiness::probe_address(udp);
    let report_ready = move || {
        std::thread::spawn(move || {
            if xrce_agent::readiness::wait_until_serving(probe, std::time::Duration::from_secs(30))
            {
                tracing::info!(%probe, "agent ready");
                if let Err(e) = xrce_agent::readiness::notify_systemd("READY=1") {
                    tracing::warn!(error = %e, "sd_notify failed");
                }
            } else {
                tracing::warn!(%probe, "the front-end did not answer a ping within 30 s");
            }
        });
    };
    supervise(specs, cleanup, report_ready)?;
    Ok(())
}
