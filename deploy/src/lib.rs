//! The supervisor of an XRCE agent instance: starts the DDS worker and the front-ends,
//! restarts a child that dies (with back-off), forwards SIGINT/SIGTERM for a clean stop and
//! removes shared-memory leftovers of children that died hard.
#![deny(unsafe_code)]
// What is `pub` is the crate's API, documented; an item only the crate uses says so (`pub(crate)`).
#![warn(unreachable_pub, missing_docs)]

use std::os::fd::{AsRawFd, OwnedFd, RawFd};
use std::path::PathBuf;
use std::process::{Child, Command};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub mod cli;
pub mod docs;
pub mod gateway;
pub mod group;
pub mod in_process;
pub mod metrics;
pub mod plan;
pub mod readiness;
pub mod settings;
pub mod shared_port;
pub mod status_view;
pub mod sweep;
#[allow(unsafe_code)]
mod sys;

pub use sys::high_fd;
use sys::wait_signal;

use nix::sys::signal::{kill, SigSet, Signal};
use nix::unistd::Pid;
use xrce_ipc::status::{self, ChildStatus, ProcessReport, Reporter, Watchdog};

/// One child process the supervisor keeps alive.
#[derive(Debug, Clone)]
pub struct ChildSpec {
    /// Name for logs.
    pub name: String,
    /// Program path.
    pub program: PathBuf,
    /// Arguments.
    pub args: Vec<String>,
    /// Extra environment.
    pub env: Vec<(String, String)>,
    /// Variables removed from the environment it inherits (a front-end's settings travel as
    /// arguments: [`xrce_frontend::cli::SETTINGS_ENV`]).
    pub env_remove: Vec<String>,
    /// Descriptors the child gets at fixed numbers: (the supervisor's descriptor, its number
    /// in the child). The supervisor keeps them open, so a restarted child gets them again
    /// (a pseudoterminal keeps its path across front-end restarts).
    pub fds: Vec<(Arc<OwnedFd>, RawFd)>,
    /// `worker` or `frontend` (for status reports and metrics).
    pub role: String,
    /// The stem of the status report it writes (`worker`, `frontend-<id>`): a report that
    /// stops changing means a wedged loop, and the child is killed and restarted.
    pub report: Option<String>,
}

/// Where the supervisor reads its children's status reports and writes its own.
#[derive(Debug, Clone)]
pub struct Monitoring {
    /// The instance's status directory.
    pub dir: PathBuf,
    /// A child whose report is older than this is killed and restarted (never: `None`).
    pub stale_after: Option<Duration>,
    /// A child whose private resident memory (RssAnon: heap and stacks, not the shared
    /// memory between the processes) exceeds this many bytes is killed and restarted (its
    /// sessions survive: the worker's are replayed to its successor, a front-end's are handed
    /// over); never: `None`.
    pub memory_limit: Option<u64>,
}

/// Share of the memory limit (per mille) at which a child is warned about, once per life.
pub const MEMORY_WARN_PERMILLE: u64 = 800;

#[derive(Debug)]
struct Supervised {
    spec: ChildSpec,
    child: Option<Child>,
    started: Instant,
    backoff: Duration,
    restart_at: Option<Instant>,
    restarts: u64,
    watchdog_kills: u64,
    memory_kills: u64,
    /// Whether this life of the child was already logged as near its memory limit.
    memory_warned: bool,
    /// Whether this life of the child was already sent SIGKILL (by the watchdog or the
    /// memory check): it is not killed, nor counted, again before it is reaped.
    killed: bool,
    /// The `updated_unix_ms` of its last report, and when (on the supervisor's monotonic
    /// clock) that value was first seen: a wall-clock step cannot make a child look wedged.
    last_report: Option<(u64, Instant)>,
}

impl Supervised {
    /// A child just started for the first time.
    fn started(spec: ChildSpec, child: Child) -> Self {
        Supervised {
            spec,
            child: Some(child),
            started: Instant::now(),
            backoff: MIN_BACKOFF,
            restart_at: None,
            restarts: 0,
            watchdog_kills: 0,
            memory_kills: 0,
            memory_warned: false,
            killed: false,
            last_report: None,
        }
    }

    fn status(&self, now: Instant) -> ChildStatus {
        ChildStatus {
            name: self.spec.name.clone(),
            role: self.spec.role.clone(),
            pid: self.child.as_ref().map(Child::id),
            uptime_seconds: if self.child.is_some() {
                (now.duration_since(self.started).as_secs_f64() * 1000.0).round() / 1000.0
            } else {
                0.0
            },
            restarts: self.restarts,
            watchdog_kills: self.watchdog_kills,
            memory_kills: self.memory_kills,
        }
    }

    /// Kills the child if its private resident memory (`resident_of` its pid) exceeds `limit` bytes,
    /// so that it is restarted; warns once per life when it comes near. Whether it killed.
    fn check_memory(&mut self, limit: u64, resident_of: impl Fn(u32) -> Option<u64>) -> bool {
        let Some(child) = self.child.as_ref().filter(|_| !self.killed) else {
            return false;
        };
        let pid = child.id();
        let Some(resident) = resident_of(pid) else {
            return false;
        };
        let mib = |b: u64| (b as f64 / 1_048_576.0 * 10.0).round() / 10.0;
        if resident > limit {
            tracing::error!(
                name = %self.spec.name,
                pid,
                resident_mib = mib(resident),
                limit_mib = mib(limit),
                "child's private resident memory is over the memory limit; killing it to restart it"
            );
            self.memory_kills += 1;
            self.killed = true;
            let _ = kill(Pid::from_raw(pid as i32), Signal::SIGKILL);
            return true;
        }
        if !self.memory_warned && resident >= limit / 1000 * MEMORY_WARN_PERMILLE {
            self.memory_warned = true;
            tracing::warn!(
                name = %self.spec.name,
                pid,
                resident_mib = mib(resident),
                limit_mib = mib(limit),
                "child's private resident memory is near the memory limit (it is restarted beyond it)"
            );
        }
        false
    }

    /// Whether its loop stopped reporting: its report (of this very process) has not changed
    /// for `stale_after`, or it never wrote one in `stale_after` since it started (stuck
    /// before its loop ran) while reports can be written (the supervisor's own is there).
    fn is_wedged(
        &mut self,
        now: Instant,
        reports: &[ProcessReport],
        stale_after: Duration,
    ) -> bool {
        let Some(child) = self.child.as_ref().filter(|_| self.spec.report.is_some()) else {
            self.last_report = None;
            return false;
        };
        let Some(r) = reports.iter().find(|r| r.pid == child.id()) else {
            let reports_work = reports.iter().any(|r| r.role == "supervisor");
            return reports_work && now.duration_since(self.started) > stale_after;
        };
        match self.last_report {
            Some((updated, since)) if updated == r.updated_unix_ms => {
                now.duration_since(since) > stale_after
            }
            _ => {
                self.last_report = Some((r.updated_unix_ms, now));
                false
            }
        }
    }
}

/// Back-off after the first crash; doubles up to [`MAX_BACKOFF`].
pub const MIN_BACKOFF: Duration = Duration::from_millis(50);
/// Longest wait before a restart.
pub const MAX_BACKOFF: Duration = Duration::from_secs(5);
/// A child that ran this long is healthy again: its back-off resets.
pub const STABLE_AFTER: Duration = Duration::from_secs(10);
/// How long children get to stop after SIGTERM before SIGKILL.
pub const STOP_GRACE: Duration = Duration::from_secs(5);

/// The command that starts `spec`'s child (its descriptors aside).
fn command(spec: &ChildSpec) -> Command {
    let mut cmd = Command::new(&spec.program);
    cmd.args(&spec.args);
    // Readiness and the watchdog reach systemd through the supervisor (NotifyAccess=main).
    cmd.env_remove("NOTIFY_SOCKET");
    cmd.env_remove("WATCHDOG_USEC");
    cmd.env_remove("WATCHDOG_PID");
    for k in &spec.env_remove {
        cmd.env_remove(k);
    }
    for (k, v) in &spec.env {
        cmd.env(k, v);
    }
    cmd
}

fn spawn(spec: &ChildSpec) -> std::io::Result<Child> {
    let mut cmd = command(spec);
    let fds: Vec<(RawFd, RawFd)> = spec
        .fds
        .iter()
        .map(|(fd, number)| (fd.as_raw_fd(), *number))
        .collect();
    sys::prepare_child(&mut cmd, fds);
    cmd.spawn()
}

/// Runs the children until SIGINT or SIGTERM; returns the signal that stopped it.
///
/// `cleanup(final)` runs before the children start (`false`) and after they all stopped
/// (`true`); `on_started` runs once they are started, with the stop signals blocked. With
/// `monitoring`, the supervisor writes its own status report (its children, their restarts)
/// every second and restarts a child whose report went stale; it pings systemd's watchdog
/// from its loop when the unit sets one.
pub fn supervise(
    specs: Vec<ChildSpec>,
    cleanup: impl Fn(bool),
    on_started: impl FnOnce(),
    monitoring: Option<Monitoring>,
) -> anyhow::Result<Signal> {
    let mut set = SigSet::empty();
    set.add(Signal::SIGINT);
    set.add(Signal::SIGTERM);
    set.add(Signal::SIGCHLD);
    set.thread_block()?;
    cleanup(false);
    let mut children: Vec<Supervised> = Vec::new();
    for spec in specs {
        let child = spawn(&spec).map_err(|e| {
            anyhow::anyhow!("starting {} ({}): {e}", spec.name, spec.program.display())
        })?;
        tracing::info!(name = %spec.name, pid = child.id(), "started");
        children.push(Supervised::started(spec, child));
    }
    // Runs with SIGINT/SIGTERM blocked, so threads it starts leave them to this loop.
    on_started();
    let mut reporter = monitoring
        .as_ref()
        .map(|m| Reporter::at(m.dir.clone(), "supervisor"));
    let mut watchdog = Watchdog::from_env();
    loop {
        let now = Instant::now();
        if let Some(r) = reporter.as_mut() {
            let children_now: Vec<ChildStatus> = children.iter().map(|c| c.status(now)).collect();
            r.maybe_write(now, || ProcessReport {
                name: "supervisor".into(),
                role: "supervisor".into(),
                children: children_now,
                ..Default::default()
            });
        }
        watchdog.maybe_ping(now);
        let next = children.iter().filter_map(|c| c.restart_at).min();
        let timeout = next.map_or(Duration::from_secs(1), |t| {
            t.saturating_duration_since(now)
                .max(Duration::from_millis(1))
                .min(Duration::from_secs(1))
        });
        if let Some(s @ (Signal::SIGINT | Signal::SIGTERM)) = wait_signal(&set, timeout) {
            tracing::info!(signal = ?s, "stopping");
            stop_all(&mut children);
            if let Some(r) = &reporter {
                r.remove();
            }
            cleanup(true);
            return Ok(s);
        }
        let now = Instant::now();
        if let Some(m) = &monitoring {
            if let Some(after) = m.stale_after {
                let reports = status::read_reports(&m.dir);
                for c in &mut children {
                    if c.killed || !c.is_wedged(now, &reports, after) {
                        continue;
                    }
                    if let Some(child) = &c.child {
                        tracing::error!(name = %c.spec.name, pid = child.id(), stale_after = ?after, "child stopped reporting (its event loop is stuck); killing it to restart it");
                        c.watchdog_kills += 1;
                        c.killed = true;
                        // Once per wedge: its exit is reaped below and it is restarted.
                        c.last_report = None;
                        let _ = kill(Pid::from_raw(child.id() as i32), Signal::SIGKILL);
                    }
                }
            }
            if let Some(limit) = m.memory_limit {
                for c in &mut children {
                    c.check_memory(limit, status::private_resident_bytes_of);
                }
            }
        }
        for c in &mut children {
            if let Some(child) = c.child.as_mut() {
                if let Ok(Some(status)) = child.try_wait() {
                    if now.duration_since(c.started) >= STABLE_AFTER {
                        c.backoff = MIN_BACKOFF;
                    }
                    tracing::warn!(name = %c.spec.name, %status, restart_in = ?c.backoff, "child exited; restarting");
                    c.child = None;
                    c.restart_at = Some(now + c.backoff);
                    c.backoff = (c.backoff * 2).min(MAX_BACKOFF);
                }
            }
            if c.child.is_none() && c.restart_at.is_some_and(|t| t <= now) {
                c.restart_at = None;
                match spawn(&c.spec) {
                    Ok(child) => {
                        c.restarts += 1;
                        tracing::info!(name = %c.spec.name, pid = child.id(), restarts = c.restarts, "restarted");
                        c.child = Some(child);
                        c.started = now;
                        c.memory_warned = false;
                        c.killed = false;
                    }
                    Err(e) => {
                        tracing::error!(name = %c.spec.name, error = %e, "restart failed");
                        c.restart_at = Some(now + c.backoff);
                        c.backoff = (c.backoff * 2).min(MAX_BACKOFF);
                    }
                }
            }
        }
    }
}

fn stop_all(children: &mut [Supervised]) {
    for c in children.iter() {
        if let Some(child) = &c.child {
            let _ = kill(Pid::from_raw(child.id() as i32), Signal::SIGTERM);
        }
    }
    let deadline = Instant::now() + STOP_GRACE;
    for c in children.iter_mut() {
        if let Some(child) = c.child.as_mut() {
            loop {
                match child.try_wait() {
                    Ok(Some(_)) | Err(_) => break,
                    Ok(None) if Instant::now() >= deadline => {
                        tracing::warn!(name = %c.spec.name, "did not stop in time; killing");
                        let _ = child.kill();
                        let _ = child.wait();
                        break;
                    }
                    Ok(None) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
        }
        c.child = None;
    }
}

/// Maps the reference agent's `-v` levels (0 off … 6 trace) to a log filter.
pub fn verbosity_filter(v: u8) -> &'static str {
    // RustDDS is chatty at info; its warnings show from level 5 on.
    match v {
        0 => "off",
        1 | 2 => "error,rustdds=off",
        3 => "warn,rustdds=error",
        4 => "info,rustdds=error",
        5 => "debug,rustdds=warn",
        // Every XRCE message in and out as hex (the core logs them at trace), without the
        // trace of the DDS stack underneath.
        _ => "trace,rustdds=warn,iceoryx2=info,mio=info",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sleeper() -> Supervised {
        let spec = ChildSpec {
            name: "sleeper".into(),
            program: "sleep".into(),
            args: vec!["30".into()],
            env: Vec::new(),
            env_remove: Vec::new(),
            fds: Vec::new(),
            role: "worker".into(),
            report: None,
        };
        let child = spawn(&spec).expect("sleep runs");
        Supervised::started(spec, child)
    }

    /// A front-end's settings travel as arguments: the variables they would otherwise come
    /// from are removed from what it inherits, and never added back.
    #[test]
    fn a_child_loses_the_variables_it_must_not_inherit() {
        let spec = ChildSpec {
            name: "frontend".into(),
            program: "true".into(),
            args: Vec::new(),
            env: vec![("XRCE_READY_FD".into(), "4".into())],
            env_remove: xrce_frontend::cli::SETTINGS_ENV.map(String::from).to_vec(),
            fds: Vec::new(),
            role: "frontend".into(),
            report: None,
        };
        let cmd = command(&spec);
        let envs: Vec<(String, Option<String>)> = cmd
            .get_envs()
            .map(|(k, v)| {
                let text = |s: &std::ffi::OsStr| s.to_string_lossy().into_owned();
                (text(k), v.map(text))
            })
            .collect();
        for k in xrce_frontend::cli::SETTINGS_ENV {
            assert!(
                envs.contains(&(k.to_string(), None)),
                "{k} removed: {envs:?}"
            );
        }
        assert!(envs.contains(&("XRCE_READY_FD".into(), Some("4".into()))));
    }

    fn exited_within(c: &mut Supervised, d: Duration) -> bool {
        let end = Instant::now() + d;
        while Instant::now() < end {
            if let Some(Ok(Some(_))) = c.child.as_mut().map(Child::try_wait) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        false
    }

    #[test]
    fn a_child_over_the_memory_limit_is_killed_once_and_counted() {
        let mut c = sleeper();
        let pid = c.child.as_ref().map(Child::id).expect("pid");
        // Its real private resident memory can be read.
        assert!(status::private_resident_bytes_of(pid).is_some_and(|b| b > 0));
        assert!(!c.check_memory(100 << 20, |_| Some(79 << 20)));
        assert!(!c.memory_warned, "79 % is not near yet");
        assert!(!c.check_memory(100 << 20, |_| Some(80 << 20)));
        assert!(c.memory_warned, "80 % is warned about");
        assert!(
            !c.check_memory(100 << 20, |_| Some(100 << 20)),
            "at the limit is within it"
        );
        assert!(!exited_within(&mut c, Duration::from_millis(200)));
        assert!(c.check_memory(100 << 20, |p| (p == pid).then_some((100 << 20) + 1)));
        assert_eq!(c.status(Instant::now()).memory_kills, 1);
        // Until it is reaped, it is not killed or counted again.
        assert!(!c.check_memory(100 << 20, |_| Some(200 << 20)));
        assert_eq!(c.status(Instant::now()).memory_kills, 1);
        assert!(exited_within(&mut c, Duration::from_secs(5)), "killed");
    }

    #[test]
    fn a_child_whose_memory_cannot_be_read_is_left_alone() {
        let mut c = sleeper();
        assert!(!c.check_memory(1, |_| None));
        assert!(!exited_within(&mut c, Duration::from_millis(200)));
        assert_eq!(c.memory_kills, 0);
        if let Some(child) = c.child.as_mut() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}
