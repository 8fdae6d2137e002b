//! The agent under test: started (any command, `{port}` replaced) and stopped by the
//! generator, and its resource use read from /proc over its whole process tree.

use std::net::UdpSocket;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// The agent under test, started by the generator and stopped when dropped.
pub struct AgentUnderTest {
    child: Child,
    /// Where our agent writes its processes' status reports (`XRCE_STATUS_DIR`): read for
    /// its drop counters at the end of a run. Other agents ignore the variable.
    status_dir: std::path::PathBuf,
}

impl AgentUnderTest {
    /// Starts `cmd` (`{port}` replaced) with a shell.
    pub fn start(cmd: &str, port: u16) -> Result<Self, String> {
        let line = cmd.replace("{port}", &port.to_string());
        eprintln!("starting agent: {line}");
        let status_dir =
            std::env::temp_dir().join(format!("xrce-loadgen-status-{}-{port}", std::process::id()));
        let child = Command::new("sh")
            .arg("-c")
            .arg(format!("exec {line}"))
            .env(xrce_ipc::status::STATUS_DIR_ENV, &status_dir)
            .spawn()
            .map_err(|e| format!("starting {line:?}: {e}"))?;
        Ok(AgentUnderTest { child, status_dir })
    }

    /// What our agent's processes counted as dropped (summed by reason over the worker and
    /// the front-ends) and the front-ends' other counters, from status reports written after
    /// `since_unix_ms` (waits up to 3 s for them); None for an agent that writes none.
    pub fn counters(&self, since_unix_ms: u64) -> Option<AgentCounters> {
        use xrce_ipc::status::read_reports;
        let end = Instant::now() + Duration::from_secs(3);
        loop {
            let reports = read_reports(&self.status_dir);
            let fresh = !reports.is_empty()
                && reports
                    .iter()
                    .filter(|r| r.frontend.is_some() || r.worker.is_some())
                    .all(|r| r.updated_unix_ms >= since_unix_ms);
            if fresh || Instant::now() >= end {
                if reports.is_empty() {
                    return None;
                }
                let mut c = AgentCounters::default();
                for r in &reports {
                    let maps = [
                        r.frontend.as_ref().map(|f| (&f.dropped, Some(&f.counters))),
                        r.worker.as_ref().map(|w| (&w.dropped, None)),
                    ];
                    for (dropped, counters) in maps.into_iter().flatten() {
                        for (k, v) in dropped {
                            *c.dropped.entry(k.clone()).or_default() += v;
                        }
                        for (k, v) in counters.into_iter().flatten() {
                            *c.frontend.entry(k.clone()).or_default() += v;
                        }
                    }
                }
                c.stale = !fresh;
                return Some(c);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// CPU seconds and summed peak RSS (KiB) of the agent and every descendant.
    /// The agent's process id (the root of its process tree).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Resource use of the agent's process tree now.
    pub fn usage(&self) -> Option<ProcUsage> {
        proc_usage(self.child.id())
    }

    /// Resource use once the agent has finished starting: an agent answers a ping from its
    /// front-end while its DDS worker may still be starting (spawning, creating its
    /// participant), so a baseline taken then would charge that start to the sessions. Waits
    /// until the process count holds and the resident size moves by less than 256 KiB over
    /// 300 ms, at most `limit`.
    pub fn settled_usage(&self, limit: Duration) -> Option<ProcUsage> {
        let end = Instant::now() + limit;
        let mut last = self.usage()?;
        loop {
            std::thread::sleep(Duration::from_millis(300));
            let now = self.usage()?;
            let steady =
                now.processes == last.processes && now.rss_kib.abs_diff(last.rss_kib) < 256;
            if steady || Instant::now() >= end {
                return Some(now);
            }
            last = now;
        }
    }
}

/// Counters our agent reported about a run.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct AgentCounters {
    /// Drops by reason, summed over the worker and front-ends.
    pub dropped: std::collections::BTreeMap<String, u64>,
    /// The front-ends' other counters, summed (retransmissions, reads paused, ...).
    pub frontend: std::collections::BTreeMap<String, u64>,
    /// Some report was older than the end of the run (a process stopped reporting).
    pub stale: bool,
}

impl Drop for AgentUnderTest {
    fn drop(&mut self) {
        let pid = self.child.id() as i32;
        // SIGINT first (agents clean up), then give them 5 s.
        let _ = Command::new("kill")
            .args(["-INT", &pid.to_string()])
            .status();
        let end = Instant::now() + Duration::from_secs(5);
        let mut exited = false;
        while !exited && Instant::now() < end {
            exited = matches!(self.child.try_wait(), Ok(Some(_)));
            if !exited {
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        if !exited {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
        let _ = std::fs::remove_dir_all(&self.status_dir);
    }
}

/// Resource use of a process tree, summed, and per process.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ProcUsage {
    /// User plus system CPU seconds.
    pub cpu_seconds: f64,
    /// Sum of the processes' resident set sizes now, KiB.
    pub rss_kib: u64,
    /// Sum of the processes' peak resident set sizes, KiB.
    pub peak_rss_kib: u64,
    /// Processes counted.
    pub processes: usize,
    /// Threads of all the processes.
    pub threads: u64,
    /// Open file descriptors of all the processes.
    pub fds: u64,
    /// Each process of the tree.
    pub each: Vec<ProcOne>,
}

/// Resource use of one process.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ProcOne {
    /// Process id.
    pub pid: u32,
    /// The command name (`comm`) and, for our agent, its subcommand.
    pub name: String,
    /// User plus system CPU seconds (over the measured period where reported as such).
    pub cpu_seconds: f64,
    /// Resident set size now, KiB.
    pub rss_kib: u64,
    /// Peak resident set size, KiB.
    pub peak_rss_kib: u64,
    /// Threads.
    pub threads: u64,
    /// Open file descriptors.
    pub fds: u64,
}

/// Reads /proc for `root` and its descendants.
pub fn proc_usage(root: u32) -> Option<ProcUsage> {
    let ticks = 100.0; // USER_HZ on Linux
    let mut parents: Vec<(u32, u32)> = Vec::new();
    for e in std::fs::read_dir("/proc").ok()?.flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        let after = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
        let ppid = after.split_whitespace().nth(1).and_then(|v| v.parse().ok());
        if let Some(ppid) = ppid {
            parents.push((pid, ppid));
        }
    }
    let mut tree = vec![root];
    let mut i = 0;
    while i < tree.len() {
        let p = tree[i];
        tree.extend(parents.iter().filter(|(_, pp)| *pp == p).map(|(c, _)| *c));
        i += 1;
    }
    let mut u = ProcUsage::default();
    for pid in &tree {
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        let (before, after) = stat.rsplit_once(')').unwrap_or(("", ""));
        let f: Vec<&str> = after.split_whitespace().collect();
        // Fields after the command: state(0) ppid(1) ... utime(11) stime(12).
        let t = |k: usize| f.get(k).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        let mut one = ProcOne {
            pid: *pid,
            name: before
                .split_once('(')
                .map_or(String::new(), |(_, n)| n.to_string()),
            cpu_seconds: (t(11) + t(12)) / ticks,
            ..Default::default()
        };
        // Our agent's processes share one executable: its first argument (the transport or
        // `dds-worker`, `frontend`) tells them apart.
        if let Ok(cmdline) = std::fs::read(format!("/proc/{pid}/cmdline")) {
            if let Some(arg) = cmdline
                .split(|b| *b == 0)
                .nth(1)
                .filter(|a| !a.is_empty() && !a.starts_with(b"-"))
            {
                one.name = format!("{} {}", one.name, String::from_utf8_lossy(arg));
            }
        }
        if let Ok(status) = std::fs::read_to_string(format!("/proc/{pid}/status")) {
            let field = |name: &str| {
                status
                    .lines()
                    .find_map(|l| l.strip_prefix(name))
                    .and_then(|v| v.split_whitespace().next())
                    .and_then(|v| v.parse::<u64>().ok())
                    .unwrap_or(0)
            };
            one.peak_rss_kib = field("VmHWM:");
            one.rss_kib = field("VmRSS:");
            one.threads = field("Threads:");
        }
        one.fds = std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count() as u64);
        u.cpu_seconds += one.cpu_seconds;
        u.rss_kib += one.rss_kib;
        u.peak_rss_kib += one.peak_rss_kib;
        u.threads += one.threads;
        u.fds += one.fds;
        u.processes += 1;
        u.each.push(one);
    }
    Some(u)
}

/// Waits until something answers an XRCE ping on `port` (giving up early if the agent we
/// started exited).
pub fn wait_for_agent(port: u16, limit: Duration, agent: &mut Option<AgentUnderTest>) -> bool {
    let Ok(socket) = UdpSocket::bind("127.0.0.1:0") else {
        return false;
    };
    if socket.connect(("127.0.0.1", port)).is_err()
        || socket
            .set_read_timeout(Some(Duration::from_millis(100)))
            .is_err()
    {
        return false;
    }
    // GET_INFO without a session, as eProsima's ping sends it.
    let ping = [
        0x80, 0x00, 0x00, 0x00, 0x02, 0x01, 0x08, 0x00, 0x00, 0x01, 0xFF, 0xFD, 0x02, 0x00, 0x00,
        0x00,
    ];
    let end = Instant::now() + limit;
    let mut buf = [0u8; 512];
    while Instant::now() < end {
        if let Some(a) = agent.as_mut() {
            if let Ok(Some(status)) = a.child.try_wait() {
                eprintln!("the agent exited before answering: {status}");
                return false;
            }
        }
        let _ = socket.send(&ping);
        if let Ok(n) = socket.recv(&mut buf) {
            if n > 4 && buf[4] == 0x06 {
                return true;
            }
        }
    }
    false
}

/// Pings the agent over TCP (GET_INFO without a session, length-prefixed) until it answers
/// INFO or `limit` passes.
pub fn wait_for_tcp_agent(port: u16, limit: Duration, agent: &mut Option<AgentUnderTest>) -> bool {
    use std::io::{Read, Write};
    let ping = [
        16, 0, 0x80, 0x00, 0x00, 0x00, 0x02, 0x01, 0x08, 0x00, 0x00, 0x01, 0xFF, 0xFD, 0x02, 0x00,
        0x00, 0x00,
    ];
    let end = Instant::now() + limit;
    while Instant::now() < end {
        if let Some(a) = agent.as_mut() {
            if let Ok(Some(status)) = a.child.try_wait() {
                eprintln!("the agent exited before answering: {status}");
                return false;
            }
        }
        let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", port)) else {
            std::thread::sleep(Duration::from_millis(50));
            continue;
        };
        let _ = s.set_read_timeout(Some(Duration::from_millis(500)));
        let mut buf = [0u8; 64];
        if s.write_all(&ping).is_ok() && s.read(&mut buf).is_ok_and(|n| n > 6 && buf[6] == 0x06) {
            return true;
        }
    }
    false
}
