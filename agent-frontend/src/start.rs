//! The front-end process's start-up: logging, faults, limits, then the transport its
//! settings name, opened by its module, served by the event loop until SIGINT/SIGTERM. The
//! settings themselves are [`crate::cli`]'s; the transports know nothing of either.

use std::io::Write;

use xrce_common::session::agent::AgentConfig;

use crate::cli::FrontendArgs;
use crate::event_loop::OnServing;
use crate::relay::Relay;
use crate::transport::discovery::Discovery;
use crate::transport::registry::Medium;
use crate::transport::tcp::TcpConfig;
use crate::transport::{multiserial, pty, tcp, udp, Transport};
use crate::worker_side::{ShmSide, WorkerSide};

/// Once serving: writes "READY" to the descriptor named by `XRCE_READY_FD`, if any (the
/// supervisor waits on it before it reports the agent ready), and tells systemd when the
/// front-end runs as a unit of its own (`NOTIFY_SOCKET`).
fn readiness_reporter() -> OnServing {
    let pipe = std::env::var("XRCE_READY_FD")
        .ok()
        .and_then(|v| v.parse::<i32>().ok())
        .and_then(|fd| match crate::sys::owned_fd::inherited(fd) {
            Ok(f) => Some(f),
            Err(e) => {
                tracing::warn!(error = %e, "XRCE_READY_FD");
                None
            }
        });
    Box::new(move || {
        if let Some(mut file) = pipe {
            if let Err(e) = file.write_all(b"READY\n") {
                tracing::debug!(error = %e, "readiness report");
            }
        }
        if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
            tracing::warn!(error = %e, "sd_notify failed");
        }
    })
}

/// Raises the open-file limit to the hard limit: every TCP connection is a descriptor, and
/// so is every stored session.
fn raise_fd_limit() {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    if let Ok((soft, hard)) = getrlimit(Resource::RLIMIT_NOFILE) {
        if soft < hard {
            match setrlimit(Resource::RLIMIT_NOFILE, hard, hard) {
                Ok(()) => tracing::debug!(from = soft, to = hard, "open-file limit raised"),
                Err(e) => tracing::warn!(error = %e, soft, "could not raise the open-file limit"),
            }
        }
    }
}

/// Runs a front-end until SIGINT/SIGTERM, with its worker in its own process.
pub fn run(args: FrontendArgs) -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&args.log).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    xrce_common::fault::install_and_log("frontend")?;
    run_with(&args, |args, incarnation| {
        let (link, inbox) =
            crate::relay::link::open(&args.instance, args.frontend_id, incarnation)?;
        Ok((link, ShmSide::new(inbox)))
    })
}

/// Opens the worker side of a front-end: given its settings and its process's incarnation,
/// the link the relay sends through and the side the event loop waits on.
pub trait OpenWorker<W: WorkerSide>:
    FnOnce(&FrontendArgs, u16) -> anyhow::Result<(W::Link, W)>
{
}

impl<W: WorkerSide, F: FnOnce(&FrontendArgs, u16) -> anyhow::Result<(W::Link, W)>> OpenWorker<W>
    for F
{
}

/// Runs a front-end until SIGINT/SIGTERM, with the worker side `open_worker` opens (logging
/// and faults are the caller's).
pub fn run_with<W: WorkerSide>(
    args: &FrontendArgs,
    open_worker: impl OpenWorker<W>,
) -> anyhow::Result<()> {
    let config = args.agent_config()?;
    // Every TCP connection is a descriptor, and so is every stored session's state file.
    raise_fd_limit();
    let on_serving = Some(readiness_reporter());
    open_and_serve(args, config, on_serving, open_worker)
}

/// Opens the transport `args` names (each medium's module opens its own from the settings
/// that concern it) and serves it.
fn open_and_serve<W: WorkerSide>(
    args: &FrontendArgs,
    config: AgentConfig,
    on_serving: Option<OnServing>,
    open_worker: impl OpenWorker<W>,
) -> anyhow::Result<()> {
    let w = open_worker;
    match args.transport.medium() {
        Medium::Datagrams => {
            let t = match args.socket_fd {
                Some(fd) => udp::inherited(fd, args.listen_addr()?)?,
                None => udp::open(args.listen_addr()?)?,
            };
            serve(t, args, config, on_serving, w)
        }
        Medium::Streams => {
            let tcp = TcpConfig {
                max_connections: args.max_connections.max(1),
                max_per_address: args.admission.max_connections_per_address,
                idle_timeout: (args.admission.tcp_idle_timeout > 0)
                    .then(|| std::time::Duration::from_secs(args.admission.tcp_idle_timeout)),
                send_buffer: args.tcp_send_buffer.max(1024),
                // Half the session core's share of --memory-budget: the connections' buffers
                // hold what the core would otherwise (messages on their way in and out).
                memory_budget: config.limits.memory_budget / 2,
                ..TcpConfig::default()
            };
            let mut config = config;
            config.limits.memory_budget -= tcp.memory_budget;
            serve(
                tcp::open(args.listen_addr()?, tcp)?,
                args,
                config,
                on_serving,
                w,
            )
        }
        Medium::SerialLines => {
            let lines = args.serial_lines()?;
            let t = multiserial::open(args.transport.name(), lines, args.baudrate);
            serve(t, args, config, on_serving, w)
        }
        Medium::Pseudoterminal => {
            let inherited = args
                .pty_fd
                .map(|fd| (fd, args.pty_path.clone().unwrap_or_default()));
            let t = pty::open_transport(inherited, args.baudrate)?;
            serve(t, args, config, on_serving, w)
        }
    }
}

/// A random seed for the epochs of clients' streams ([`AgentConfig::epoch_seed`]): from the
/// system's generator, else (logged) the clock mixed with the process id, which still
/// differs from one process to the next.
fn epoch_seed() -> u64 {
    let mut bytes = [0u8; 8];
    match getrandom::getrandom(&mut bytes) {
        Ok(()) => u64::from_le_bytes(bytes),
        Err(e) => {
            tracing::warn!(error = %e, "no random bytes for the epochs of clients' streams; using the clock");
            let nanos = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64);
            nanos ^ u64::from(std::process::id()).rotate_left(32)
        }
    }
}

/// Serves clients over `transport`, opened from `args`: connects to the worker
/// and runs the event loop until SIGINT/SIGTERM.
fn serve<T: Transport, W: WorkerSide>(
    transport: T,
    args: &FrontendArgs,
    config: AgentConfig,
    on_serving: Option<OnServing>,
    open_worker: impl OpenWorker<W>,
) -> anyhow::Result<()> {
    let discovery = match args.discovery {
        Some(port) => {
            let served = args.listen.map(|a| a.ip());
            Some(
                Discovery::new(port, served, config.vendor_id, transport.locators())
                    .map_err(|e| anyhow::anyhow!("discovery on port {port}: {e}"))?,
            )
        }
        None => None,
    };
    let incarnation = crate::session_store::next_incarnation(&args.instance, args.frontend_id);
    let (link, worker) = open_worker(args, incarnation)?;
    // The epochs of clients' streams this process issues are its own: a successor draws
    // other ones, so a position the worker kept of this process's runs is never taken
    // for one of its own.
    let config = AgentConfig {
        epoch_seed: epoch_seed(),
        ..config
    };
    let mut relay = Relay::new(args.frontend_id, incarnation, link);
    relay.set_max_objects_per_client(args.admission.max_objects_per_client);
    relay.set_memory_budget(args.admission.budget_split());
    if let Some(keys) = &config.admission.allowed_keys {
        tracing::info!(keys = keys.len(), "only listed client keys are admitted");
    }
    let who = crate::status::Identity {
        name: args
            .name
            .clone()
            .unwrap_or_else(|| format!("frontend-{}", args.frontend_id)),
        id: args.frontend_id,
    };
    let place = crate::event_loop::Placement {
        instance: args.instance.clone(),
        keep_sessions: args.keep_sessions,
    };
    let serving = crate::event_loop::Serving {
        transport,
        relay,
        worker,
        config,
        discovery,
        on_serving,
    };
    crate::event_loop::run(&place, who, serving)
}
