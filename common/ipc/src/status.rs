//! Status reports: what each process of an agent instance is doing, for `xrce-agent status`,
//! the metrics endpoint and the watchdog.
//!
//! Every process rewrites its own JSON report in the instance's status directory (in the
//! private runtime directory, `<runtime>/<instance>/status/`: see [`crate::runtime_dir`])
//! about every [`REPORT_PERIOD`], from its event loop: written to a new private temporary
//! file and renamed, so a reader never sees half a report, and a report that stops changing
//! means a wedged loop (the supervisor restarts that process). Readers take the reports of
//! live processes only (a process killed hard leaves its file), and only regular files of
//! their own user, opened without following links: a report is never taken from a file
//! another user planted.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

/// How often a process rewrites its report.
pub const REPORT_PERIOD: Duration = Duration::from_secs(1);
/// A report older than this belongs to a process whose loop is stuck.
pub const STALE_AFTER: Duration = Duration::from_secs(30);
/// Overrides the directory of the reports (tests, or a system without `/dev/shm`).
pub const STATUS_DIR_ENV: &str = crate::runtime_dir::STATUS_DIR_ENV;
/// Largest report read (a front-end with tens of thousands of sessions writes megabytes).
pub const MAX_REPORT_BYTES: u64 = 64 << 20;

/// One process's report.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ProcessReport {
    /// Its name in the group: `worker`, `supervisor` or the front-end's name.
    pub name: String,
    /// `worker`, `frontend` or `supervisor`.
    pub role: String,
    /// Its process id.
    pub pid: u32,
    /// When it started, in milliseconds since the Unix epoch.
    pub started_unix_ms: u64,
    /// When it started, in clock ticks after boot as /proc says (0: unknown): tells this
    /// process from a later one the system gave the same pid, whatever the wall clock did.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub start_ticks: u64,
    /// When it wrote this report, in milliseconds since the Unix epoch.
    pub updated_unix_ms: u64,
    /// User and system CPU time it used, in seconds.
    pub cpu_seconds: f64,
    /// Its resident memory, in bytes.
    pub resident_bytes: u64,
    /// What a front-end serves, if it is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frontend: Option<FrontendStatus>,
    /// What the worker holds, if it is the worker.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub worker: Option<WorkerStatus>,
    /// The supervisor's children, if it is the supervisor.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub children: Vec<ChildStatus>,
}

impl ProcessReport {
    /// The front-end whose process this worker runs inside (`xrce-agent --single-process`),
    /// among `all` the reports of its agent: the process's CPU and memory are that
    /// front-end's, counted once.
    pub fn runs_inside<'a>(&self, all: &'a [ProcessReport]) -> Option<&'a ProcessReport> {
        self.worker.as_ref()?;
        all.iter()
            .find(|p| p.pid == self.pid && p.frontend.is_some())
    }
}

/// A front-end's part of its report.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FrontendStatus {
    /// Its id within the instance.
    pub id: u32,
    /// The transport (`udp4`, `tcp6`, `serial`, ...).
    pub transport: String,
    /// What it serves: an address and port, or devices.
    pub serving: String,
    /// Whether it has seen a worker generation (see `generation` for whether that worker
    /// still runs).
    pub connected: bool,
    /// The worker generation it serves, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub generation: Option<u32>,
    /// Counters (names as the metrics name them, without the `xrce_` prefix).
    pub counters: BTreeMap<String, u64>,
    /// Dropped input and output, by reason.
    pub dropped: BTreeMap<String, u64>,
    /// The live sessions.
    pub sessions: Vec<SessionStatus>,
}

/// One session of a front-end.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SessionStatus {
    /// The client key, as the client's code writes it (`0xAAAABBBB`).
    pub client_key: String,
    /// The session id.
    pub session_id: u8,
    /// Where the client is: an address and port, or a device and serial address.
    pub peer: String,
    /// `spec` or `eprosima`.
    pub dialect: String,
    /// Seconds since the session was created.
    pub age_seconds: f64,
    /// Seconds since the client was last heard.
    pub last_heard_seconds: f64,
    /// Whether its connection or device is gone (the session waits for it).
    pub detached: bool,
    /// Its XRCE objects (participants, topics, publishers, writers, ...).
    pub entities: u64,
    /// Messages received from it.
    pub messages_in: u64,
    /// Samples it wrote.
    pub samples_in: u64,
    /// Samples delivered to it.
    pub samples_out: u64,
    /// Its messages and replies lost (not refusals for room, which the client resends).
    pub dropped: u64,
}

/// The worker's part of its report.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WorkerStatus {
    /// Its generation id.
    pub generation: u32,
    /// Its DDS entities by kind (`participant`, `topic`, `writer`, ...).
    pub entities: BTreeMap<String, u64>,
    /// Front-ends it answers.
    pub frontends: u64,
    /// Samples written to DDS.
    pub samples_written: u64,
    /// Samples taken from DDS readers and sent to front-ends.
    pub samples_taken: u64,
    /// Refused or failed work, by reason.
    pub dropped: BTreeMap<String, u64>,
}

/// A child as the supervisor sees it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ChildStatus {
    /// Its name in the group.
    pub name: String,
    /// `worker` or `frontend`.
    pub role: String,
    /// Its process id, while it runs.
    pub pid: Option<u32>,
    /// Seconds since it was (re)started.
    pub uptime_seconds: f64,
    /// How often it was restarted.
    pub restarts: u64,
    /// How often it was killed for not reporting (a wedged loop).
    pub watchdog_kills: u64,
    /// How often it was killed for resident memory over the configured limit.
    #[serde(default)]
    pub memory_kills: u64,
}

/// Milliseconds since the Unix epoch.
pub fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The status directory of an instance (a path: nothing is created or checked; see
/// [`crate::runtime_dir::status_dir`]).
pub fn status_dir(instance: &str) -> PathBuf {
    crate::runtime_dir::status_dir(instance)
}

/// Creates or checks the status directory of an instance (private, ours).
pub fn ensure_status_dir(instance: &str) -> Result<PathBuf, crate::runtime_dir::RuntimeDirError> {
    crate::runtime_dir::ensure_status_dir(instance)
}

/// Where the front-ends of an instance keep their sessions for a successor (see the
/// front-end's session store): `<runtime>/<instance>/sessions/` (`XRCE_SESSION_DIR` moves
/// it to `$XRCE_SESSION_DIR/xrce-sessions-<instance>/`). The supervisor empties it when the
/// agent starts and stops. A path: nothing is created or checked.
pub fn sessions_dir(instance: &str) -> PathBuf {
    crate::runtime_dir::sessions_dir(instance)
}

/// The status directories of every instance of this user on this machine (in the runtime
/// directory), with their instance names; empty when the runtime directory is missing or
/// cannot be trusted ([`crate::runtime_dir::list_instances`] says why).
pub fn instance_dirs() -> Vec<(String, PathBuf)> {
    match crate::runtime_dir::list_instances() {
        Ok(v) => v,
        Err(e) => {
            tracing::warn!(error = %e, "cannot list the agents of this user");
            Vec::new()
        }
    }
}

/// This process's CPU time (seconds) and resident memory (bytes), when /proc tells.
pub fn own_usage() -> (f64, u64) {
    let Ok(me) = procfs::process::Process::myself() else {
        return (0.0, 0);
    };
    let Ok(stat) = me.stat() else {
        return (0.0, 0);
    };
    let ticks = procfs::ticks_per_second().max(1) as f64;
    let cpu = (stat.utime + stat.stime) as f64 / ticks;
    let rss = stat.rss * procfs::page_size();
    (cpu, rss)
}

/// The resident private memory (bytes: RssAnon, its heap and stacks) of process `pid`, when
/// /proc tells. Unlike the whole resident set it leaves out the shared-memory segments
/// between the agent's processes (bounded by construction, and counted again in every
/// process that touches them) and mapped files.
pub fn private_resident_bytes_of(pid: u32) -> Option<u64> {
    let status = procfs::process::Process::new(pid as i32)
        .and_then(|p| p.status())
        .ok()?;
    Some(status.rssanon?.saturating_mul(1024))
}

/// Whether a process is alive (its /proc entry exists and is no zombie).
pub fn is_alive(pid: u32) -> bool {
    match procfs::process::Process::new(pid as i32).and_then(|p| p.stat()) {
        Ok(s) => s.state != 'Z' && s.state != 'X',
        Err(_) => false,
    }
}

/// Whether the process that wrote `r` still runs: its pid is alive, no zombie, and started at
/// the clock tick the report says (a pid the system gave to another process since does not
/// pass for it; ticks after boot do not move with the wall clock).
pub fn report_is_live(r: &ProcessReport) -> bool {
    let Ok(stat) = procfs::process::Process::new(r.pid as i32).and_then(|p| p.stat()) else {
        return false;
    };
    if stat.state == 'Z' || stat.state == 'X' {
        return false;
    }
    r.start_ticks == 0 || stat.starttime == r.start_ticks
}

/// This process's start, in clock ticks after boot (0 when /proc does not tell).
pub fn own_start_ticks() -> u64 {
    procfs::process::Process::myself()
        .and_then(|p| p.stat())
        .map_or(0, |s| s.starttime)
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

/// Writes the report of process `file_stem` atomically into `dir` (created 0700 if
/// missing; if there, it must be a real directory of ours that only we can change): to a new
/// 0600 temporary file (`O_EXCL | O_NOFOLLOW`), then renamed into place.
pub fn write_report(dir: &Path, file_stem: &str, report: &ProcessReport) -> std::io::Result<()> {
    crate::runtime_dir::prepare_dir_for_writing(dir).map_err(std::io::Error::other)?;
    let json = serde_json::to_vec(report).map_err(std::io::Error::other)?;
    let tmp = dir.join(format!(".{file_stem}.{}.tmp", std::process::id()));
    crate::runtime_dir::write_atomically(&dir.join(format!("{file_stem}.json")), &tmp, &json)
        .map_err(std::io::Error::other)
}

/// Removes the report of process `file_stem` (on a clean exit).
pub fn remove_report(dir: &Path, file_stem: &str) {
    let _ = std::fs::remove_file(dir.join(format!("{file_stem}.json")));
}

/// The report in `path`, if it is a regular file of ours (opened without following links)
/// holding one; `Err` says why a file there was not trusted.
fn read_report(path: &Path) -> Result<Option<ProcessReport>, crate::runtime_dir::RuntimeDirError> {
    let bytes = crate::runtime_dir::read_owned(path, MAX_REPORT_BYTES)?;
    Ok(serde_json::from_slice::<ProcessReport>(&bytes).ok())
}

/// Removes the reports in `dir` of processes that are gone (killed hard, they leave theirs),
/// and anything else in it that is no live report of ours (unlinking never follows a link).
pub fn remove_dead_reports(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let path = e.path();
        let dead = read_report(&path)
            .ok()
            .flatten()
            .is_none_or(|r| !report_is_live(&r));
        if dead {
            let _ = std::fs::remove_file(&path);
        }
    }
}

/// The reports in `dir` of processes that are alive, sorted by name. Unreadable files are
/// skipped; so are files that are not regular files of this user (links are not followed),
/// which are counted in one warning.
pub fn read_reports(dir: &Path) -> Vec<ProcessReport> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut untrusted = Vec::new();
    let mut out: Vec<ProcessReport> = entries
        .flatten()
        .filter(|e| e.path().extension().is_some_and(|x| x == "json"))
        .filter_map(|e| match read_report(&e.path()) {
            Ok(r) => r,
            Err(err) => {
                if err.is_untrusted() {
                    untrusted.push(err.to_string());
                }
                None
            }
        })
        .filter(report_is_live)
        .collect();
    if !untrusted.is_empty() {
        tracing::warn!(dir = %dir.display(), ignored = untrusted.len(), first = %untrusted[0], "status files that are not this user's regular files were ignored");
    }
    out.sort_by(|a, b| (role_rank(&a.role), &a.name).cmp(&(role_rank(&b.role), &b.name)));
    out
}

fn role_rank(role: &str) -> u8 {
    match role {
        "supervisor" => 0,
        "worker" => 1,
        _ => 2,
    }
}

/// Rewrites one process's report every [`REPORT_PERIOD`] from its loop.
#[derive(Debug)]
pub struct Reporter {
    dir: PathBuf,
    /// The instance whose status directory (and the directories above it) is created or
    /// checked before the first report, if the reporter was made for an instance.
    instance: Option<String>,
    file_stem: String,
    started_unix_ms: u64,
    next: std::time::Instant,
    failed: bool,
}

impl Reporter {
    /// Reports of process `file_stem` of `instance`.
    pub fn new(instance: &str, file_stem: &str) -> Self {
        let mut r = Self::at(status_dir(instance), file_stem);
        r.instance = Some(instance.to_string());
        r
    }

    /// Reports of process `file_stem` in directory `dir`.
    pub fn at(dir: PathBuf, file_stem: &str) -> Self {
        Reporter {
            dir,
            instance: None,
            file_stem: file_stem.to_string(),
            started_unix_ms: unix_ms(),
            next: std::time::Instant::now(),
            failed: false,
        }
    }

    /// When the next report is due.
    pub fn due(&self) -> std::time::Instant {
        self.next
    }

    /// Writes a report built by `build` if one is due (the process fields are filled in
    /// here); returns whether it wrote one.
    pub fn maybe_write(
        &mut self,
        now: std::time::Instant,
        build: impl FnOnce() -> ProcessReport,
    ) -> bool {
        if now < self.next {
            return false;
        }
        self.next = now + REPORT_PERIOD;
        let mut report = build();
        report.pid = std::process::id();
        report.started_unix_ms = self.started_unix_ms;
        report.start_ticks = own_start_ticks();
        report.updated_unix_ms = unix_ms();
        let (cpu, rss) = own_usage();
        report.cpu_seconds = cpu;
        report.resident_bytes = rss;
        let prepared = match &self.instance {
            Some(instance) => ensure_status_dir(instance)
                .map(drop)
                .map_err(std::io::Error::other),
            None => Ok(()),
        };
        match prepared.and_then(|()| write_report(&self.dir, &self.file_stem, &report)) {
            Ok(()) => {
                // The directory stays prepared; only its last component is checked again.
                self.instance = None;
                if self.failed {
                    tracing::info!(dir = %self.dir.display(), "status reports written again");
                    self.failed = false;
                }
            }
            Err(e) => {
                if !self.failed {
                    tracing::warn!(dir = %self.dir.display(), error = %e, "cannot write the status report; `xrce-agent status` and the metrics will miss this process");
                    self.failed = true;
                }
            }
        }
        true
    }

    /// Removes the report (clean exit).
    pub fn remove(&self) {
        remove_report(&self.dir, &self.file_stem);
    }
}

/// systemd's watchdog: when the unit sets `WatchdogSec` (and so `WATCHDOG_USEC` for this
/// process), [`Watchdog::maybe_ping`] from the event loop sends `WATCHDOG=1` at half the
/// period, so a loop that stops turning gets the process restarted.
#[derive(Debug)]
pub struct Watchdog {
    period: Option<Duration>,
    next: std::time::Instant,
}

impl Watchdog {
    /// The watchdog systemd set for this process, if any.
    pub fn from_env() -> Self {
        let period = sd_notify::watchdog_enabled().map(|d| (d / 2).max(Duration::from_millis(10)));
        if let Some(p) = period {
            tracing::info!(
                ping_every_ms = p.as_millis() as u64,
                "systemd watchdog enabled"
            );
        }
        Watchdog {
            period,
            next: std::time::Instant::now(),
        }
    }

    /// When the next ping is due (never without a watchdog).
    pub fn due(&self) -> Option<std::time::Instant> {
        self.period.map(|_| self.next)
    }

    /// Pings if a ping is due.
    pub fn maybe_ping(&mut self, now: std::time::Instant) {
        let Some(period) = self.period else {
            return;
        };
        if now < self.next {
            return;
        }
        self.next = now + period;
        if let Err(e) = sd_notify::notify(&[sd_notify::NotifyState::Watchdog]) {
            tracing::warn!(error = %e, "systemd watchdog ping failed");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_round_trips_and_dead_processes_are_left_out() {
        let dir = std::env::temp_dir().join(format!("xrce-status-test-{}", std::process::id()));
        let mut r = ProcessReport {
            name: "udp".into(),
            role: "frontend".into(),
            pid: std::process::id(),
            frontend: Some(FrontendStatus {
                id: 3,
                transport: "udp4".into(),
                sessions: vec![SessionStatus {
                    client_key: "0xAAAABBBB".into(),
                    samples_in: 7,
                    ..Default::default()
                }],
                ..Default::default()
            }),
            ..Default::default()
        };
        write_report(&dir, "frontend-udp", &r).expect("write");
        assert_eq!(read_reports(&dir), vec![r.clone()]);
        // Started at this process's start: it is this process.
        r.start_ticks = own_start_ticks();
        assert!(r.start_ticks > 0, "/proc tells a process's start");
        write_report(&dir, "frontend-udp", &r).expect("write");
        assert_eq!(read_reports(&dir), vec![r.clone()]);
        // A report of another process that had this pid before.
        let mut reused = r.clone();
        reused.start_ticks -= 1;
        write_report(&dir, "frontend-udp", &reused).expect("write");
        assert!(
            read_reports(&dir).is_empty(),
            "a reused pid passed for its old process"
        );
        // A process that is gone (pid 0 is never a user process).
        r.pid = 0;
        write_report(&dir, "frontend-udp", &r).expect("write");
        assert!(read_reports(&dir).is_empty());
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn reports_are_private_and_planted_ones_are_not_read() {
        use std::os::unix::fs::{MetadataExt, PermissionsExt};
        let dir = std::env::temp_dir().join(format!("xrce-status-priv-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let r = ProcessReport {
            name: "w".into(),
            role: "worker".into(),
            pid: std::process::id(),
            ..Default::default()
        };
        write_report(&dir, "worker", &r).expect("write");
        let mode = |p: &Path| std::fs::symlink_metadata(p).expect("exists").mode() & 0o7777;
        assert_eq!(mode(&dir), 0o700);
        assert_eq!(mode(&dir.join("worker.json")), 0o600);
        // A link to a live report elsewhere is not taken for one.
        let elsewhere = dir.with_extension("elsewhere");
        std::fs::copy(dir.join("worker.json"), &elsewhere).expect("copy");
        std::os::unix::fs::symlink(&elsewhere, dir.join("planted.json")).expect("link");
        assert_eq!(read_reports(&dir), vec![r.clone()]);
        // Nor is a directory made loose since.
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o777)).expect("chmod");
        assert!(write_report(&dir, "worker", &r).is_err());
        let _ = std::fs::remove_file(elsewhere);
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn own_usage_is_measured() {
        let (_, rss) = own_usage();
        assert!(rss > 0, "resident memory of a running process");
    }
}
