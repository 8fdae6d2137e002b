//! `xrce-agent`: the user-facing command, a drop-in for eProsima's `MicroXRCEAgent`
//! (`xrce-agent udp4 -p 8888`, `xrce-agent serial --dev /dev/ttyACM0 -b 921600`, ...). It
//! supervises one DDS worker and one front-end, which are this same executable started with
//! the hidden `dds-worker` and `frontend` subcommands, so one binary is all a user needs.

use std::process::ExitCode;
use std::sync::Arc;

use clap::Parser;
use xrce_agent::cli::{check_supported, plan, Cli, Command, Common, FrontendPlan, Unsupported};
use xrce_agent::{readiness, supervise, verbosity_filter, ChildSpec};

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.downcast_ref::<Unsupported>().is_some() => {
            eprintln!("xrce-agent: {e}");
            ExitCode::from(2)
        }
        Err(e) => {
            eprintln!("Error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    let Some((frontend, common)) = plan(&cli.command)? else {
        return match cli.command {
            Command::DdsWorker(args) => xrce_dds_worker::cli::run(args),
            Command::Frontend(args) => xrce_frontend::cli::run(args),
            _ => Ok(()),
        };
    };
    check_supported(&common)?;
    // An explicit -v wins over XRCE_LOG (the systemd units set it), which wins over the default.
    let filter = match common.verbose {
        Some(v) => verbosity_filter(v).to_string(),
        None => std::env::var("XRCE_LOG")
            .unwrap_or_else(|_| verbosity_filter(xrce_agent::cli::DEFAULT_VERBOSITY).to_string()),
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&filter).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    // By default every agent is its own instance (two agents on one port, bound to different
    // addresses or in different network namespaces, must not share their IPC).
    let stem = format!("{}-", frontend.label());
    let instance = common
        .instance
        .clone()
        .unwrap_or_else(|| format!("{stem}{}", std::process::id()));
    if !xrce_common::ipc::shm::valid_instance(&instance) {
        anyhow::bail!("instance name {instance:?} must be 1-32 characters of [A-Za-z0-9_-]");
    }
    preflight(&frontend)?;
    let exe =
        std::env::current_exe().map_err(|e| anyhow::anyhow!("locating this executable: {e}"))?;
    let env = child_env(&common, &instance, &filter)?;
    let mut frontend_args = vec!["frontend".to_string(), "--frontend-id".into(), "0".into()];
    frontend_args.extend(frontend.frontend_args());
    if let Some(port) = common.discovery {
        if frontend.kind().is_ip() {
            frontend_args.extend(["--discovery".into(), port.to_string()]);
        } else {
            tracing::warn!(
                transport = frontend.kind().name(),
                "-d/--discovery is not supported on this transport (UDP and TCP only); ignored"
            );
        }
    }
    let mut frontend_fds = Vec::new();
    // The supervisor owns the pseudoterminal, so its path survives front-end restarts.
    let _pty_master = if let FrontendPlan::Pty { baudrate } = frontend {
        let pty = xrce_frontend::transport::pty::open(baudrate)
            .map_err(|e| anyhow::anyhow!("opening a pseudoterminal: {e}"))?;
        let path = pty.slave_path.display().to_string();
        // Also in the reference's words ("dev: ..."), which scripts look for.
        println!("Pseudoterminal opened at {path} (dev: {path})");
        tracing::info!(%path, "pseudoterminal opened; clients open this path as their serial port");
        let master = Arc::new(xrce_agent::high_fd(&pty.master)?);
        frontend_fds.push((master.clone(), 3));
        frontend_args.extend(["--pty-fd".into(), "3".into(), "--pty-path".into(), path]);
        Some(master)
    } else {
        None
    };
    let (ready_read, ready_write) = readiness::pipe()?;
    frontend_fds.push((Arc::new(ready_write), readiness::READY_FD));
    let mut frontend_env = env.clone();
    frontend_env.push(("XRCE_READY_FD".into(), readiness::READY_FD.to_string()));
    let frontend_name = "xrce-frontend-0".to_string();
    let specs = vec![
        ChildSpec {
            name: "xrce-dds-worker".into(),
            program: exe.clone(),
            args: vec!["dds-worker".into()],
            env,
            fds: Vec::new(),
        },
        ChildSpec {
            name: frontend_name.clone(),
            program: exe,
            args: frontend_args,
            env: frontend_env,
            fds: frontend_fds,
        },
    ];
    tracing::info!(transport = frontend.kind().name(), plan = ?frontend, %instance, "xrce-agent starting");
    let explicit_instance = common.instance.is_some();
    let cleanup = |last: bool| {
        if !last && !explicit_instance {
            // Leftovers of earlier agents on this transport that died without cleaning up.
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
    // Ready once every front-end reports that it serves (to systemd too, if present).
    let report_ready = move || {
        readiness::watch(
            vec![(frontend_name, ready_read)],
            std::time::Duration::from_secs(30),
            || {
                tracing::info!("agent ready");
                if let Err(e) = readiness::notify_systemd("READY=1") {
                    tracing::warn!(error = %e, "sd_notify failed");
                }
            },
        );
    };
    supervise(specs, cleanup, report_ready)?;
    Ok(())
}

/// Fails early and clearly if the port is taken, instead of a crash loop in the child.
fn preflight(frontend: &FrontendPlan) -> anyhow::Result<()> {
    use xrce_frontend::cli::TransportKind as K;
    if let FrontendPlan::Ip { kind, listen, .. } = frontend {
        match kind {
            K::Udp4 | K::Udp6 => drop(
                std::net::UdpSocket::bind(listen)
                    .map_err(|e| anyhow::anyhow!("cannot bind UDP {listen}: {e}"))?,
            ),
            _ => drop(
                std::net::TcpListener::bind(listen)
                    .map_err(|e| anyhow::anyhow!("cannot listen on TCP {listen}: {e}"))?,
            ),
        }
    }
    Ok(())
}

/// The environment every child gets: instance, logging and the worker's settings.
fn child_env(
    common: &Common,
    instance: &str,
    filter: &str,
) -> anyhow::Result<Vec<(String, String)>> {
    let mut env = vec![
        ("XRCE_INSTANCE".to_string(), instance.to_string()),
        ("XRCE_LOG".to_string(), filter.to_string()),
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
    Ok(env)
}
