//! The processes of one agent: a DDS worker and one or more front-ends, described either by
//! a MicroXRCEAgent command line (one front-end) or by a gateway file (several), then run
//! under the supervisor ([`Group::supervise`]) or one at a time in the foreground for
//! systemd units of their own ([`Group::exec_one`]).

use std::sync::Arc;
use std::time::Duration;
use xrce_dds_worker::backend::ports::ReservedPorts;
use xrce_dds_worker::backend::BackendKind;
use xrce_dds_worker::cli::{WorkerArgs, SETTINGS_ENV as WORKER_SETTINGS_ENV};

use xrce_frontend::cli::{FrontendArgs, SETTINGS_ENV};
use xrce_frontend::session_store;
use xrce_frontend::transport::registry::Medium;

use crate::cli::{FrontendPlan, DEFAULT_VERBOSITY};
use crate::plan::{AgentPlan, FrontendSpec, WorkerPlan};
use crate::{readiness, supervise, verbosity_filter, ChildSpec};
use xrce_ipc::{runtime_dir, status};

/// One front-end of the group.
#[derive(Debug, Clone)]
pub struct FrontendLaunch {
    /// Name for logs and readiness (and `--process`).
    pub name: String,
    /// Its id within the instance.
    pub id: u32,
    /// What it serves.
    pub plan: FrontendPlan,
    /// Its settings (the pty's or the shared socket's descriptor aside, set when the
    /// supervisor opens them).
    pub settings: FrontendArgs,
    /// Which of the processes serving its UDP port it is, of how many, if several do
    /// ([`crate::shared_port`]).
    pub share: Option<PortShare>,
}

/// One process of several that serve a UDP port: its place among them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PortShare {
    /// Its number, from 0: the socket it serves is the one bound in this place.
    pub member: u16,
    /// How many serve the port.
    pub members: u16,
}

/// Whether `name` is an instance name of the kind agents before derived names used: `stem`
/// followed by a process id (at most 7 digits, Linux's largest pid being 4,194,304), not
/// `stem` followed by the 8 hexadecimal digits of a derived name.
fn is_legacy_instance(name: &str, stem: &str) -> bool {
    name.strip_prefix(stem)
        .is_some_and(|pid| (1..=7).contains(&pid.len()) && pid.bytes().all(|b| b.is_ascii_digit()))
}

/// Longest the supervisor waits for a shared UDP port to be free before binding its
/// sockets (after [`PREDECESSOR_WAIT`] for the previous agent's processes).
const SHARED_PORT_WAIT: Duration = Duration::from_secs(2);

/// Longest a new supervisor waits for the processes of the previous agent of its instance.
pub const PREDECESSOR_WAIT: Duration = Duration::from_secs(10);

/// The processes of one agent instance and their settings.
#[derive(Debug, Clone)]
pub struct Group {
    /// Shared-memory name of the instance.
    pub instance: String,
    /// Given by the user (else derived, and leftovers of dead agents with the same stem are
    /// removed at start).
    pub explicit_instance: bool,
    /// Prefix of derived instance names (`udp4-8888-`, `gw-`).
    pub stem: String,
    /// Log filter of every process.
    pub filter: String,
    /// The worker's settings.
    pub worker: WorkerArgs,
    /// The front-ends.
    pub frontends: Vec<FrontendLaunch>,
    /// Where the metrics endpoint is served, if anywhere.
    pub metrics: Option<std::net::SocketAddr>,
    /// Private resident memory (bytes, RssAnon) beyond which a process is restarted, if any.
    pub memory_limit: Option<u64>,
    /// Start without the sessions a previous agent of the instance stored.
    pub discard_sessions: bool,
    /// The front-end and the worker in one process ([`crate::in_process`]).
    pub single_process: bool,
}

/// The log filter: `-v` (or the file's `verbose`) first, then XRCE_LOG, then the default.
///
/// RustDDS 0.15's writers warn "No locators" for every discovery message to the participant's
/// own built-in readers: a participant discovers itself ("is myself, but some reflection is
/// good"), the proxies of its own readers get only loopback locators, which RustDDS keeps
/// for peers it has confirmed on this host, and it never confirms itself. Nothing is lost
/// (a participant needs no copy of its own announcements), but it is about 3,500 lines per
/// test run, so that target is kept at `error` unless the filter names it.
pub fn log_filter(verbose: Option<u8>) -> String {
    let filter = match verbose {
        Some(v) => verbosity_filter(v).to_string(),
        None => std::env::var("XRCE_LOG")
            .unwrap_or_else(|_| verbosity_filter(DEFAULT_VERBOSITY).to_string()),
    };
    if filter.contains(RUSTDDS_WRITER) || filter.trim() == "off" {
        filter
    } else {
        format!("{filter},{RUSTDDS_WRITER}=error")
    }
}

/// The tracing target of RustDDS's transient "No locators" warnings.
const RUSTDDS_WRITER: &str = "rustdds::rtps::writer";

/// Sets up the supervisor's logging with `filter` ([`log_filter`]): once, in `main`.
pub fn init_logging(filter: &str) {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(filter).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
}

/// What the supervisor decided for its worker: `base` (the worker's settings from the
/// environment) with the plan's on top, each checked now with a clear message rather than in
/// a worker crash loop, and the UDP ports the front-ends serve reserved from DDS.
fn worker_settings(
    mut base: WorkerArgs,
    plan: &WorkerPlan,
    frontends: &[FrontendSpec],
) -> anyhow::Result<WorkerArgs> {
    // An unknown ROS_DISTRO would stop the worker.
    let (distro, _) = xrce_dds_worker::ros_graph::RosDistro::resolve(
        plan.ros_distro,
        std::env::var_os("ROS_DISTRO").as_deref(),
    )?;
    base.ros_distro = Some(distro);
    // So would a ROS_DOMAIN_ID that is no domain id; the worker gets the domain decided.
    base.default_domain = Some(xrce_dds_worker::cli::resolve_default_domain(
        base.default_domain,
        |v| std::env::var_os(v),
    )?);
    if plan.domains.is_some() {
        base.domains = plan.domains.clone();
    }
    if plan.max_domains.is_some() {
        base.max_domains = plan.max_domains;
    }
    if let Some(b) = plan.backend {
        if !b.is_built() {
            anyhow::bail!(
                "this build has no {} DDS backend: build xrce-agent with its default features \
                 (needs cmake and libclang: deploy/build-deps), or use --dds-backend rustdds",
                b.as_str()
            );
        }
        base.dds_backend = b;
    }
    if !plan.dds_interfaces.is_empty() {
        base.dds_interfaces = plan.dds_interfaces.clone();
    }
    if let Some(grace) = plan.frontend_grace {
        base.frontend_grace = grace;
    }
    if !plan.zenoh_type_hashes.is_empty() {
        base.zenoh_type_hashes = plan.zenoh_type_hashes.clone();
    }
    if base.dds_backend == BackendKind::Zenoh {
        xrce_dds_worker::backend::check_zenoh(&base.zenoh_type_hashes)?;
    }
    // The UDP ports the front-ends serve: DDS leaves them alone (a well-known DDS port,
    // such as RTI's default XRCE port 7401, domain 0's user multicast port, is moved off);
    // one it cannot leave, a domain's discovery multicast port, costs that domain only (the
    // worker warns at start and refuses the domain's participants).
    let udp_ports: Vec<u16> = frontends
        .iter()
        .filter_map(|f| match &f.plan {
            FrontendPlan::Ip { kind, listen, .. } if kind.medium() == Medium::Datagrams => {
                Some(listen.port())
            }
            _ => None,
        })
        .collect();
    let dds = xrce_dds_worker::backend::DdsConfig {
        interfaces: base.dds_interfaces.clone(),
        reserved_ports: ReservedPorts::new(udp_ports.iter().copied()),
        ..Default::default()
    };
    base.reserved_ports = dds.reserved_ports.clone();
    if !base.dds_interfaces.is_empty() {
        // The worker refuses to run unconfined; refused here too, before any process starts.
        xrce_dds_worker::backend::check_config(base.dds_backend, &dds)?;
    }
    if let Some(path) = &plan.refs {
        // Refuse a bad file here, with a clear message, rather than in a worker crash loop.
        let refs = xrce_dds_worker::references::References::load(path)?;
        let absolute = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        tracing::info!(path = %absolute.display(), profiles = refs.len(), "references file");
        base.refs = Some(absolute);
    }
    base.ros_graph = plan.ros_graph;
    base.share_writers = plan.share_writers;
    base.bounds = plan.bounds.or(&base.bounds);
    Ok(base)
}

impl Group {
    /// The processes `plan` describes, once it is checked ([`AgentPlan::check`]) and the
    /// worker's settings are decided (`worker_settings`). Logging is the caller's to set
    /// up first ([`init_logging`] with [`log_filter`] of the plan's verbosity).
    pub fn new(plan: AgentPlan) -> anyhow::Result<Self> {
        plan.check()?;
        let filter = log_filter(plan.verbose);
        let instance = plan.instance().to_string();
        let mut worker = worker_settings(
            WorkerArgs::from_environment()?,
            &plan.worker,
            &plan.frontends,
        )?;
        worker.instance = instance.clone();
        worker.log = filter.clone();
        let mut frontends = Vec::new();
        for f in &plan.frontends {
            let mut settings = f.settings();
            settings.instance = instance.clone();
            settings.log = filter.clone();
            if settings.discovery.is_some() && !f.plan.kind().is_ip() {
                tracing::warn!(
                    transport = f.plan.kind().name(),
                    "-d/--discovery is not supported on this transport (UDP and TCP only); ignored"
                );
                settings.discovery = None;
            }
            let members = f.processes();
            if members > 1 && settings.admission.allow_roaming {
                tracing::warn!(
                    frontend = %f.name,
                    "--allow-roaming with several processes on a port: a session follows its \
                     client to a new port of its address, not to another address (served by \
                     whichever process that address is steered to, where the client creates \
                     its session again)"
                );
            }
            for member in 0..members {
                // Checked by `plan.check()` above.
                let Some((id, name)) = f.process(member) else {
                    anyhow::bail!("front-end {}: process {member} has no id", f.name);
                };
                let mut settings = settings.clone();
                settings.frontend_id = id;
                settings.name = Some(name.clone());
                if member > 0 {
                    // One multicast discovery answer per port is enough.
                    settings.discovery = None;
                }
                frontends.push(FrontendLaunch {
                    name,
                    id,
                    plan: f.plan.clone(),
                    settings,
                    share: (members > 1).then_some(PortShare { member, members }),
                });
            }
        }
        Ok(Group {
            instance,
            explicit_instance: plan.instance.is_some(),
            stem: plan.stem,
            filter,
            worker,
            frontends,
            metrics: plan.metrics,
            memory_limit: plan.memory_limit_mib.map(|mib| mib << 20),
            discard_sessions: plan.discard_sessions,
            single_process: plan.single_process,
        })
    }

    /// Fails early and clearly if a port is taken, instead of a crash loop in a child.
    fn preflight(&self) -> anyhow::Result<()> {
        for f in self.frontends.iter().filter(|f| f.share.is_none()) {
            if let FrontendPlan::Ip { kind, listen, .. } = &f.plan {
                match kind.medium() {
                    Medium::Datagrams => drop(std::net::UdpSocket::bind(listen).map_err(|e| {
                        anyhow::anyhow!("front-end {}: cannot bind UDP {listen}: {e}", f.name)
                    })?),
                    _ => drop(std::net::TcpListener::bind(listen).map_err(|e| {
                        anyhow::anyhow!("front-end {}: cannot listen on TCP {listen}: {e}", f.name)
                    })?),
                }
            }
        }
        Ok(())
    }

    /// Runs every process under the supervisor until SIGINT or SIGTERM.
    ///
    /// First, before anything of the instance is read or removed, it takes the instance's
    /// lock (`<runtime>/<instance>/agent.lock`, see [`runtime_dir`]): a second supervisor of
    /// the same instance is refused and leaves the first one's sessions alone. The lock's
    /// descriptor is close-on-exec: no child holds it, so a supervisor killed hard is
    /// replaced at once even while its children still stop. Then it checks the instance's
    /// private directories and shared memory (refusing planted ones, clearly, rather than
    /// letting the children fail over and over).
    pub fn supervise(self) -> anyhow::Result<()> {
        let lock = runtime_dir::lock_instance(&self.instance)?;
        self.wait_for_predecessor();
        // What dead nodes of the last run left under its names is cleaned up (creating a
        // node does), then this run draws names of its own: names seen in /dev/shm before
        // are no use for planting files (docs/security.md).
        if let Err(e) = xrce_ipc::shm::IpcNode::new(&self.instance, "xrce-agent") {
            tracing::debug!(error = %e, "the last run's shared memory was not cleaned up");
        }
        runtime_dir::renew_secret(&self.instance, runtime_dir::SHM_TOKEN)?;
        if self.discard_sessions {
            let n = runtime_dir::clear_sessions(&self.instance);
            tracing::info!(
                kept_by_live_front_ends = n,
                "stored sessions discarded (--discard-sessions)"
            );
        }
        let checked = status::ensure_status_dir(&self.instance)
            .map_err(anyhow::Error::from)
            .and_then(|_| {
                drop(xrce_ipc::shm::IpcNode::new(&self.instance, "xrce-agent")?);
                self.preflight()
            });
        if let Err(e) = checked {
            runtime_dir::remove_instance_dir(&self.instance, lock);
            return Err(e);
        }
        let exe = std::env::current_exe()
            .map_err(|e| anyhow::anyhow!("locating this executable: {e}"))?;
        // One process with both halves, or the worker of its own.
        let mut specs = Vec::new();
        (!self.single_process).then(|| {
            specs.push(ChildSpec {
                name: "xrce-dds-worker".into(),
                program: exe.clone(),
                args: std::iter::once("dds-worker".to_string())
                    .chain(self.worker.to_args())
                    .collect(),
                env: Vec::new(),
                env_remove: WORKER_SETTINGS_ENV.map(String::from).to_vec(),
                fds: Vec::new(),
                role: "worker".into(),
                report: Some("worker".into()),
            })
        });
        // Kept open for the group's life, as the ptys below: the members of a shared UDP
        // port and their order stay as they were bound, so each client stays with its
        // front-end, and a restarted front-end gets its socket back.
        let shared = match self.bind_shared_ports() {
            Ok(shared) => shared,
            Err(e) => {
                runtime_dir::remove_instance_dir(&self.instance, lock);
                return Err(e);
            }
        };
        let mut ready = Vec::new();
        // Kept open for the group's life: a restarted front-end gets the same pty.
        let mut ptys = Vec::new();
        for f in &self.frontends {
            let mut settings = f.settings.clone();
            let mut fds = Vec::new();
            if let Some(socket) = shared.get(&f.id) {
                fds.push((socket.clone(), 3));
                settings.socket_fd = Some(3);
            }
            if let FrontendPlan::Pty { baudrate } = f.plan {
                let pty = xrce_frontend::transport::pty::open(baudrate)
                    .map_err(|e| anyhow::anyhow!("opening a pseudoterminal: {e}"))?;
                let path = pty.slave_path.display().to_string();
                // Also in the reference's words ("dev: ..."), which scripts look for.
                println!("Pseudoterminal opened at {path} (dev: {path})");
                tracing::info!(frontend = %f.name, %path, "pseudoterminal opened; clients open this path as their serial port");
                let master = Arc::new(crate::high_fd(&pty.master)?);
                fds.push((master.clone(), 3));
                ptys.push(master);
                settings.pty_fd = Some(3);
                settings.pty_path = Some(path.into());
            }
            let (read, write) = readiness::pipe()?;
            fds.push((Arc::new(write), readiness::READY_FD));
            ready.push((f.name.clone(), read));
            let env = vec![("XRCE_READY_FD".into(), readiness::READY_FD.to_string())];
            let (args, env_remove) = if self.single_process {
                (
                    crate::in_process::command_line(&self.worker.to_args(), &settings.to_args()),
                    SETTINGS_ENV
                        .into_iter()
                        .chain(WORKER_SETTINGS_ENV)
                        .map(String::from)
                        .collect(),
                )
            } else {
                (
                    std::iter::once("frontend".to_string())
                        .chain(settings.to_args())
                        .collect(),
                    SETTINGS_ENV.map(String::from).to_vec(),
                )
            };
            specs.push(ChildSpec {
                name: format!("xrce-frontend-{}", f.name),
                program: exe.clone(),
                args,
                env,
                env_remove,
                fds,
                role: "frontend".into(),
                report: Some(format!("frontend-{}", f.id)),
            });
        }
        let plans: Vec<String> = self
            .frontends
            .iter()
            .map(|f| format!("{}: {}", f.name, f.plan.describe()))
            .collect();
        tracing::info!(instance = %self.instance, frontends = ?plans, "xrce-agent starting");
        let (instance, stem, explicit) = (
            self.instance.clone(),
            self.stem.clone(),
            self.explicit_instance,
        );
        let status_dir = status::status_dir(&self.instance);
        let dir = status_dir.clone();
        // Released (and its file removed) by the last cleanup.
        let lock = std::sync::Mutex::new(Some(lock));
        let cleanup = move |last: bool| {
            // Sessions are handed from a front-end to its restarted successor; a new agent
            // (and a stopped one) has none. (A store whose front-end still runs, a child of
            // a supervisor killed hard that is still stopping, is kept.)
            if !last {
                status::remove_dead_reports(&dir);
                if !explicit {
                    // Directories of agents of earlier versions with this stem, named by
                    // their pid, all dead (their lock is free and they left no live
                    // report). Not other derived names: those are other agents (another
                    // address, another namespace), whose stored sessions stay for them.
                    for (name, d) in status::instance_dirs() {
                        if is_legacy_instance(&name, &stem)
                            && name != instance
                            && status::read_reports(&d).is_empty()
                        {
                            runtime_dir::remove_instance_if_unlocked(&name);
                        }
                    }
                }
            }
            if !last && !explicit {
                // Leftovers of earlier agents with this stem that died without cleaning up.
                for dead in xrce_ipc::shm::dead_instances(&stem)
                    .into_iter()
                    .filter(|d| *d != instance && is_legacy_instance(d, &stem))
                {
                    if let Ok(n) = xrce_ipc::shm::IpcNode::new(&dead, "xrce-agent") {
                        drop(n);
                    }
                    xrce_ipc::shm::remove_instance_leftovers(&dead);
                    runtime_dir::remove_instance_if_unlocked(&dead);
                    tracing::info!(instance = %dead, "removed shared memory of a dead agent");
                }
            }
            // Creating a node removes what dead nodes of this instance left in shared memory.
            match xrce_ipc::shm::IpcNode::new(&instance, "xrce-agent") {
                Ok(n) => drop(n),
                Err(e) => tracing::warn!(error = %e, "shared-memory cleanup failed"),
            }
            if last {
                xrce_ipc::shm::remove_instance_leftovers(&instance);
                // The sessions stay for the next agent of this instance (a restart, an
                // upgrade): its front-ends take them over. The rest goes; a sweeper left
                // behind removes the sessions too once no restart can take them over.
                if session_store::inspect(&instance).clients > 0 {
                    crate::sweep::leave_sweeper(&instance);
                }
                let held = lock
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .take();
                match held {
                    Some(l) => runtime_dir::remove_instance_dir(&instance, l),
                    None => {
                        let _ = std::fs::remove_dir_all(&dir);
                    }
                }
            } else {
                // Stores that stopped agents of this user left, past their adoption window.
                crate::sweep::sweep(Some(&instance));
            }
        };
        // Ready once every front-end reports that it serves (to systemd too, if present).
        let swept = self.instance.clone();
        let report_ready = move || {
            // Then every minute (a thread started with the stop signals blocked).
            let spawned = std::thread::Builder::new()
                .name("sweep".into())
                .spawn(move || loop {
                    std::thread::sleep(crate::sweep::SWEEP_PERIOD);
                    crate::sweep::sweep(Some(&swept));
                });
            if let Err(e) = spawned {
                tracing::debug!(error = %e, "no periodic sweep");
            }
            readiness::watch(ready, Duration::from_secs(30), || {
                tracing::info!("agent ready");
                if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
                    tracing::warn!(error = %e, "sd_notify failed");
                }
            });
        };
        if let Some(listen) = self.metrics {
            // The stop signals are blocked before the server's thread exists, so they reach
            // the supervisor's loop and not that thread (whose default action would kill
            // the process without stopping the children).
            let mut set = nix::sys::signal::SigSet::empty();
            set.add(nix::sys::signal::Signal::SIGINT);
            set.add(nix::sys::signal::Signal::SIGTERM);
            set.add(nix::sys::signal::Signal::SIGCHLD);
            set.thread_block()?;
            // Bound before the children start: a taken port fails the start, clearly.
            crate::metrics::serve(listen, &self.instance)?;
        }
        let monitoring = crate::Monitoring {
            dir: status_dir,
            stale_after: stall_timeout()?,
            memory_limit: self.memory_limit,
        };
        if let Some(limit) = self.memory_limit {
            if status::private_resident_bytes_of(std::process::id()).is_none() {
                tracing::warn!(
                    "this kernel does not report private resident memory (RssAnon, Linux 4.5 \
                     and later): the memory limit cannot be kept"
                );
            }
            tracing::info!(
                limit_mib = limit >> 20,
                "each process is restarted beyond this private resident memory (RssAnon)"
            );
        }
        supervise(specs, cleanup, report_ready, Some(monitoring))?;
        drop((ptys, shared));
        Ok(())
    }

    /// The sockets of each UDP port several front-end processes serve
    /// ([`crate::shared_port::bind`]), by the id of the process each is for.
    fn bind_shared_ports(
        &self,
    ) -> anyhow::Result<std::collections::HashMap<u32, Arc<std::os::fd::OwnedFd>>> {
        let mut by_id = std::collections::HashMap::new();
        for f in &self.frontends {
            let (Some(share), FrontendPlan::Ip { listen, .. }) = (f.share, &f.plan) else {
                continue;
            };
            if share.member != 0 {
                continue;
            }
            let sockets = crate::shared_port::bind(*listen, share.members, SHARED_PORT_WAIT)?;
            let members = self
                .frontends
                .iter()
                .filter(|m| matches!(&m.plan, FrontendPlan::Ip { listen: l, .. } if l == listen))
                .filter_map(|m| m.share.map(|s| (s.member, m.id)));
            for (member, id) in members {
                let socket = sockets
                    .get(usize::from(member))
                    .ok_or_else(|| anyhow::anyhow!("{listen}: no socket for process {member}"))?;
                by_id.insert(id, Arc::new(crate::high_fd(socket)?));
            }
            tracing::info!(frontend = %f.name, %listen, processes = share.members, "UDP port served by several front-end processes, each client by the one its source address hashes to");
        }
        Ok(by_id)
    }

    /// Waits (at most [`PREDECESSOR_WAIT`]) until no process of a previous agent of this
    /// instance is alive: a supervisor killed hard leaves its children stopping (they
    /// finish handing their operations to DDS first), and the new children must find their
    /// session stores and ports free rather than fail and be restarted with back-off.
    fn wait_for_predecessor(&self) {
        let dir = status::status_dir(&self.instance);
        let live = || {
            status::read_reports(&dir)
                .into_iter()
                .filter(status::report_is_live)
                .filter(|r| r.pid != std::process::id())
                .map(|r| r.name)
                .collect::<Vec<_>>()
        };
        let first = live();
        if first.is_empty() {
            return;
        }
        tracing::info!(processes = ?first, "processes of the previous agent of this instance are still stopping; waiting for them");
        // Front-ends whose supervisor died hold their ports for this one: they may go now.
        if let Err(e) = runtime_dir::announce_successor(&self.instance) {
            tracing::debug!(error = %e, "successor marker not written: the old front-ends go after their hold");
        }
        let end = std::time::Instant::now() + PREDECESSOR_WAIT;
        let mut gone = false;
        while !gone && std::time::Instant::now() < end {
            std::thread::sleep(Duration::from_millis(10));
            gone = live().is_empty();
        }
        runtime_dir::clear_successor(&self.instance);
        if !gone {
            tracing::warn!(processes = ?live(), "processes of the previous agent still run; starting anyway (the new ones retry until they are gone)");
        }
    }

    /// Replaces this process with one of the group's (`worker`, or a front-end by name), for
    /// a systemd unit per process: same settings, readiness straight to systemd.
    pub fn exec_one(self, name: &str) -> anyhow::Result<()> {
        use std::os::unix::process::CommandExt;
        if !self.explicit_instance {
            anyhow::bail!(
                "--process needs an instance name ([agent] instance in the file, or XRCE_INSTANCE): the processes of separate units must agree on it"
            );
        }
        let exe = std::env::current_exe()
            .map_err(|e| anyhow::anyhow!("locating this executable: {e}"))?;
        if name == "metrics" {
            let listen = self.metrics.ok_or_else(|| {
                anyhow::anyhow!("--process metrics needs [metrics] listen in the file")
            })?;
            return serve_metrics_alone(listen, &self.instance);
        }
        let mut cmd = std::process::Command::new(exe);
        if name == "worker" && self.single_process {
            anyhow::bail!(
                "no process \"worker\": with single_process the worker runs in the front-end's process"
            );
        }
        if name == "worker" {
            cmd.arg("dds-worker").args(self.worker.to_args());
            for k in WORKER_SETTINGS_ENV {
                cmd.env_remove(k);
            }
        } else {
            let f = self
                .frontends
                .iter()
                .find(|f| f.name == name)
                .ok_or_else(|| {
                    let names: Vec<&str> = self.frontends.iter().map(|f| f.name.as_str()).collect();
                    anyhow::anyhow!(
                        "no process {name:?}: the file has `worker` and the front-ends {names:?}"
                    )
                })?;
            if f.share.is_some() {
                anyhow::bail!(
                    "{name} is one of the processes sharing a UDP port (`processes`): they run \
                     under the supervisor, which keeps their sockets; with a unit per process, \
                     give each front-end a port of its own"
                );
            }
            if self.single_process {
                cmd.args(crate::in_process::command_line(
                    &self.worker.to_args(),
                    &f.settings.to_args(),
                ));
                for k in WORKER_SETTINGS_ENV {
                    cmd.env_remove(k);
                }
            } else {
                cmd.arg("frontend").args(f.settings.to_args());
            }
            for k in SETTINGS_ENV {
                cmd.env_remove(k);
            }
        }
        if self.memory_limit.is_some() {
            tracing::warn!(
                process = name,
                "the memory limit is kept by the supervisor, which does not run here: give the \
                 unit MemoryMax= instead (systemd restarts it, its sessions survive)"
            );
        }
        tracing::info!(process = name, instance = %self.instance, "starting");
        Err(anyhow::anyhow!("starting {name}: {}", cmd.exec()))
    }
}

/// `--process metrics`: the metrics endpoint alone in the foreground, for deployments that
/// run each process as a unit of its own (the reports are read from the shared status
/// directory), until SIGINT or SIGTERM.
fn serve_metrics_alone(listen: std::net::SocketAddr, instance: &str) -> anyhow::Result<()> {
    use nix::sys::signal::{SigSet, Signal};
    let mut set = SigSet::empty();
    set.add(Signal::SIGINT);
    set.add(Signal::SIGTERM);
    set.thread_block()?;
    crate::metrics::serve(listen, instance)?;
    if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Ready]) {
        tracing::warn!(error = %e, "sd_notify failed");
    }
    let signal = set.wait()?;
    tracing::info!(?signal, "stopping");
    Ok(())
}

/// How long a child may go without reporting before it is killed and restarted:
/// `XRCE_STALL_TIMEOUT` seconds (0 turns the check off), else [`status::STALE_AFTER`].
fn stall_timeout() -> anyhow::Result<Option<Duration>> {
    match std::env::var("XRCE_STALL_TIMEOUT") {
        Err(_) => Ok(Some(status::STALE_AFTER)),
        Ok(v) => match v.trim().parse::<f64>() {
            Ok(0.0) => Ok(None),
            Ok(s) if s.is_finite() && (2.0..=86_400.0).contains(&s) => {
                Ok(Some(Duration::from_secs_f64(s)))
            }
            _ => anyhow::bail!(
                "XRCE_STALL_TIMEOUT={v:?}: seconds from 2 to 86400, or 0 for no stall check"
            ),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the supervisor decides for its worker reaches it as arguments that override
    /// whatever the worker's environment says: the front-ends' UDP ports reserved from DDS,
    /// the resolved ROS distribution, the checked domain list.
    #[test]
    fn the_workers_settings_are_decided_by_the_supervisor() {
        let udp = FrontendPlan::Ip {
            kind: xrce_frontend::cli::TransportKind::Udp4,
            listen: "127.0.0.1:7401".parse().expect("address"),
            max_connections: 0,
            processes: 1,
        };
        let tcp = FrontendPlan::Ip {
            kind: xrce_frontend::cli::TransportKind::Tcp4,
            listen: "127.0.0.1:8888".parse().expect("address"),
            max_connections: 10,
            processes: 1,
        };
        let spec = |plan: FrontendPlan| FrontendSpec {
            name: "f".into(),
            id: 0,
            plan,
            discovery: None,
            client_dead_time: 0.0,
            dialect: None,
            admission: Default::default(),
        };
        let plan = WorkerPlan {
            refs: None,
            dds_interfaces: vec!["127.0.0.1".parse().expect("address")],
            ros_graph: false,
            share_writers: true,
            backend: Some(BackendKind::Rustdds),
            zenoh_type_hashes: vec![],
            frontend_grace: Some(2.5),
            ros_distro: Some(xrce_dds_worker::ros_graph::RosDistro::Humble),
            domains: Some("0-3".parse().expect("domains")),
            max_domains: Some(2),
            bounds: Default::default(),
        };
        let worker = worker_settings(WorkerArgs::built_in(), &plan, &[spec(udp), spec(tcp)])
            .expect("valid settings");
        // Only the datagram front-end's port: DDS never binds TCP.
        assert_eq!(worker.reserved_ports, ReservedPorts::new([7401]));
        assert_eq!(
            worker.ros_distro,
            Some(xrce_dds_worker::ros_graph::RosDistro::Humble)
        );
        assert_eq!(worker.domains, Some("0-3".parse().expect("domains")));
        assert_eq!(worker.max_domains, Some(2));
        assert_eq!(worker.dds_backend, BackendKind::Rustdds);
        assert!(!worker.ros_graph && worker.share_writers);
        let args = worker.to_args();
        assert!(
            args.contains(&"--reserved-ports=7401".to_string()),
            "{args:?}"
        );
        assert_eq!(worker.frontend_grace, 2.5);
        // The default domain is decided here too (the worker's environment aside).
        assert!(worker.default_domain.is_some());
    }

    #[test]
    fn only_pid_named_instances_count_as_leftovers_of_earlier_versions() {
        assert!(is_legacy_instance("udp4-8888-12345", "udp4-8888-"));
        assert!(is_legacy_instance("udp4-8888-4194304", "udp4-8888-"));
        // Derived names: 8 hexadecimal digits, all-decimal ones included.
        assert!(!is_legacy_instance("udp4-8888-1a2b3c4d", "udp4-8888-"));
        assert!(!is_legacy_instance("udp4-8888-12345678", "udp4-8888-"));
        assert!(!is_legacy_instance("udp4-8888-", "udp4-8888-"));
        assert!(!is_legacy_instance("gw-abc", "gw-"));
    }
}
