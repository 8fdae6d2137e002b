//! A running `xrce-agent` under test: started with DDS pinned to loopback, its output
//! collected, stopped on drop.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use xrce_common::session::client::ClientEvent;

use crate::*;

/// A running `xrce-agent` with DDS pinned to loopback. Stopped (SIGTERM) on drop.
#[derive(Debug)]
pub struct AgentProcess {
    child: Child,
    /// The UDP or TCP port it serves (0 for serial transports).
    pub port: u16,
    /// Its instance name.
    pub instance: String,
    ip: std::net::IpAddr,
    /// What it printed (stdout and stderr).
    output: AgentOutput,
}

/// `line` without ANSI escape sequences (`ESC [ ... letter`).
fn strip_ansi(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for d in chars.by_ref() {
                if d.is_ascii_alphabetic() {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// The lines an agent printed, collected by reader threads (and echoed to the test's
/// stderr), so tests can wait for a log line instead of sleeping.
#[derive(Debug, Clone, Default)]
pub struct AgentOutput {
    lines: std::sync::Arc<(std::sync::Mutex<Vec<String>>, std::sync::Condvar)>,
}

impl AgentOutput {
    fn collect(&self, pipe: impl std::io::Read + Send + 'static, echo: bool) {
        let lines = self.lines.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(pipe).lines() {
                let Ok(line) = line else { return };
                if echo {
                    eprintln!("{line}");
                }
                // Matched without the terminal colours.
                let line = strip_ansi(&line);
                let (m, cv) = &*lines;
                if let Ok(mut v) = m.lock() {
                    v.push(line);
                }
                cv.notify_all();
            }
        });
    }

    /// The first line (from line `from` on) containing `needle`, waiting up to `d`; returns
    /// its index and text.
    pub fn wait_for(&self, from: usize, needle: &str, d: Duration) -> Option<(usize, String)> {
        let end = Instant::now() + d;
        let (m, cv) = &*self.lines;
        let mut v = m.lock().ok()?;
        loop {
            if let Some((i, l)) = v
                .iter()
                .enumerate()
                .skip(from)
                .find(|(_, l)| l.contains(needle))
            {
                return Some((i, l.clone()));
            }
            let left = end.checked_duration_since(Instant::now())?;
            v = cv.wait_timeout(v, left).ok()?.0;
        }
    }

    /// How many lines were printed so far.
    pub fn len(&self) -> usize {
        self.lines.0.lock().map(|v| v.len()).unwrap_or(0)
    }

    /// Whether nothing was printed yet.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether at least `n` lines contain `needle`, waiting up to `d` for them ([`LOG_WAIT`]): a log line
    /// reaches the test through the process's pipe and a reader thread, after the effect the
    /// test saw (a closed connection, a refused sample), so counting at once races it.
    pub fn logged(&self, needle: &str, n: usize, d: Duration) -> bool {
        let end = Instant::now() + d;
        let (m, cv) = &*self.lines;
        let Ok(mut v) = m.lock() else {
            return false;
        };
        loop {
            if v.iter().filter(|l| l.contains(needle)).count() >= n {
                return true;
            }
            let Some(left) = end.checked_duration_since(Instant::now()) else {
                return false;
            };
            match cv.wait_timeout(v, left) {
                Ok((guard, _)) => v = guard,
                Err(_) => return false,
            }
        }
    }

    /// How many lines contain `needle` (now: see [`logged`](AgentOutput::logged)).
    pub fn count(&self, needle: &str) -> usize {
        self.lines
            .0
            .lock()
            .map(|v| v.iter().filter(|l| l.contains(needle)).count())
            .unwrap_or(0)
    }
}

/// What an agent under test serves, and so how the test knows it is ready.
#[derive(Debug, Clone)]
enum Serves {
    /// `udp4` on a free loopback port (another one when a parallel test takes it first);
    /// ready when it answers a ping.
    FreeUdpPort,
    /// `udp4` bound to this address; ready when it answers a ping.
    Udp(SocketAddr),
    /// This command line, DDS pinned to loopback and the instance added; ready when it logs
    /// `agent ready`. Its address is read from `-p` / `--bind`.
    CommandLine(Vec<String>),
    /// This command line with nothing added (a gateway file pins DDS and names its
    /// instance); ready when it logs `ready`; serving `addr` (port 0: nothing to ping).
    Exactly {
        args: Vec<String>,
        ready: String,
        addr: SocketAddr,
    },
}

/// An agent a test is about to start: what it serves, its instance, its options and
/// environment ([`AgentProcess::builder`], [`AgentProcess::at`], [`AgentProcess::exactly`]),
/// then [`start`](AgentBuilder::start) or [`launch`](AgentBuilder::launch). Every agent of
/// the suite starts through [`AgentBuilder::launch`].
#[derive(Debug, Clone)]
#[must_use]
pub struct AgentBuilder {
    tag: String,
    serves: Serves,
    /// Named by the test; otherwise a unique one from `tag` (or, for [`Serves::Udp`], the
    /// agent's own default).
    instance: Option<String>,
    extra: Vec<String>,
    env: Vec<(String, String)>,
}

impl AgentProcess {
    /// An agent serving `udp4` on a free loopback port, DDS pinned to loopback, in an
    /// instance of its own named after `tag`; ready when it answers a ping.
    pub fn builder(tag: &str) -> AgentBuilder {
        AgentBuilder {
            tag: tag.to_string(),
            serves: Serves::FreeUdpPort,
            instance: None,
            extra: Vec::new(),
            env: Vec::new(),
        }
    }

    /// An agent serving `udp4` bound to `addr`, in the agent's own default instance (derived
    /// from what it serves, so an agent started again at `addr` is its predecessor's
    /// successor) unless [`AgentBuilder::instance`] names one.
    pub fn at(addr: SocketAddr) -> AgentBuilder {
        AgentBuilder {
            serves: Serves::Udp(addr),
            ..Self::builder("at")
        }
    }

    /// `xrce-agent <args>` exactly as given (a gateway file names its `instance` and pins DDS
    /// itself), ready when it logs a line containing `ready`, serving `addr`.
    pub fn exactly(args: &[&str], ready: &str, addr: SocketAddr, instance: &str) -> AgentBuilder {
        AgentBuilder {
            serves: Serves::Exactly {
                args: args.iter().map(|a| a.to_string()).collect(),
                ready: ready.to_string(),
                addr,
            },
            instance: Some(instance.to_string()),
            ..Self::builder("exactly")
        }
    }
}

impl AgentBuilder {
    /// `xrce-agent <args>` (DDS pinned to loopback and the instance added), ready when it
    /// logs `agent ready` (every front-end serving), instead of `udp4` on a free port.
    pub fn command_line(mut self, args: &[&str]) -> Self {
        self.serves = Serves::CommandLine(args.iter().map(|a| a.to_string()).collect());
        self
    }

    /// In the instance `name`.
    pub fn instance(mut self, name: impl Into<String>) -> Self {
        self.instance = Some(name.into());
        self
    }

    /// With these options after the others.
    pub fn extra(mut self, args: &[&str]) -> Self {
        self.extra.extend(args.iter().map(|a| a.to_string()));
        self
    }

    /// With these environment variables.
    pub fn env(mut self, env: &[(&str, &str)]) -> Self {
        self.env
            .extend(env.iter().map(|(k, v)| (k.to_string(), v.to_string())));
        self
    }

    /// Starts it; panics unless it becomes ready. On a free port, up to 5 ports are tried: one
    /// found free can be taken by another test before the agent binds it, and then the agent
    /// exits at once.
    pub fn start(self) -> AgentProcess {
        let tries = if matches!(self.serves, Serves::FreeUdpPort) {
            5
        } else {
            1
        };
        for _ in 0..tries {
            if let Some(agent) = self.clone().launch() {
                return agent;
            }
        }
        panic!("the agent ({:?}) did not become ready", self.serves);
    }

    /// Starts it and waits until it is ready (a ping answered within 20 s, or its ready line
    /// within 30 s); `None` if it exited or was not ready by then. Its output is collected
    /// ([`AgentProcess::output`]).
    pub fn launch(self) -> Option<AgentProcess> {
        let (mut args, instance, addr, ready) = match self.serves {
            Serves::FreeUdpPort => {
                let addr = SocketAddr::from(([127, 0, 0, 1], free_udp_port()));
                let instance = self.instance.unwrap_or_else(|| unique_instance(&self.tag));
                (udp_arguments(addr, Some(&instance)), instance, addr, None)
            }
            Serves::Udp(addr) => {
                let args = udp_arguments(addr, self.instance.as_deref());
                // The agent's own default: derived from what it serves (and the namespace).
                let instance = self.instance.unwrap_or_else(|| {
                    xrce_ipc::derived_instance(&format!("udp4-{}", addr.port()), &addr.to_string())
                });
                (args, instance, addr, None)
            }
            Serves::CommandLine(mut args) => {
                let instance = self.instance.unwrap_or_else(|| unique_instance(&self.tag));
                let (ip, port) = ip_and_port(&args);
                args.extend(["--dds-interface".into(), "127.0.0.1".into()]);
                args.extend(["--instance".into(), instance.clone()]);
                let ready = Some("agent ready".to_string());
                (args, instance, SocketAddr::new(ip, port), ready)
            }
            Serves::Exactly { args, ready, addr } => {
                let instance = self.instance.unwrap_or_default();
                (args, instance, addr, Some(ready))
            }
        };
        args.extend(self.extra);
        let env: Vec<(&str, &str)> = self
            .env
            .iter()
            .map(|(k, v)| (k.as_str(), v.as_str()))
            .collect();
        let (child, output) = spawn_agent(&args, &env);
        let mut agent = AgentProcess {
            child,
            port: addr.port(),
            instance,
            ip: addr.ip(),
            output: output.clone(),
        };
        let (end, step) = match ready {
            Some(_) => (Instant::now() + Duration::from_secs(30), 100),
            None => (Instant::now() + Duration::from_secs(20), 200),
        };
        while Instant::now() < end {
            let is_ready = match &ready {
                Some(line) => output
                    .wait_for(0, line, Duration::from_millis(step))
                    .is_some(),
                None => agent.ping(Duration::from_millis(step)),
            };
            if is_ready {
                return Some(agent);
            }
            if let Ok(Some(_)) = agent.child.try_wait() {
                return None;
            }
        }
        None
    }
}

/// `udp4` bound to `addr`, DDS pinned to loopback, in `instance` if given.
fn udp_arguments(addr: SocketAddr, instance: Option<&str>) -> Vec<String> {
    let mut args: Vec<String> = vec![
        "udp4".into(),
        "-p".into(),
        addr.port().to_string(),
        "--bind".into(),
        addr.ip().to_string(),
        "--dds-interface".into(),
        "127.0.0.1".into(),
    ];
    if let Some(i) = instance {
        args.extend(["--instance".into(), i.to_string()]);
    }
    args
}

impl AgentProcess {
    /// The agent's collected output.
    pub fn output(&self) -> &AgentOutput {
        &self.output
    }

    /// Pings the agent (GET_INFO without a session) until it answers INFO, up to `d`.
    pub fn ping(&self, d: Duration) -> bool {
        let mut c = TestClient::new(self.addr(), *b"PING");
        let end = Instant::now() + d;
        while Instant::now() < end {
            c.client.ping();
            let answered = c.run_until(Duration::from_millis(100), |c| {
                c.events.iter().any(|e| matches!(e, ClientEvent::Info(_)))
            });
            if answered {
                return true;
            }
        }
        false
    }

    /// The supervisor's process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The agent's instance name.
    pub fn instance(&self) -> &str {
        &self.instance
    }

    /// The agent's address.
    pub fn addr(&self) -> SocketAddr {
        SocketAddr::new(self.ip, self.port)
    }

    /// Pids of the agent's children started with this subcommand (`dds-worker`, `frontend`).
    pub fn child_pids(&self, subcommand: &str) -> Vec<i32> {
        let parent = self.child.id().to_string();
        let mut out = Vec::new();
        for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
            let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else {
                continue;
            };
            let stat = std::fs::read_to_string(e.path().join("stat")).unwrap_or_default();
            // Fields after the command name: state, ppid, ...
            let ppid = stat
                .rsplit_once(')')
                .and_then(|(_, rest)| rest.split_whitespace().nth(1).map(str::to_string));
            if ppid.as_deref() != Some(parent.as_str()) {
                continue;
            }
            let cmdline = std::fs::read(e.path().join("cmdline")).unwrap_or_default();
            if cmdline.split(|b| *b == 0).nth(1) == Some(subcommand.as_bytes()) {
                out.push(pid);
            }
        }
        out
    }

    /// The pid of the child started with `subcommand` whose command line contains `needle`
    /// (a front-end by its transport or port, say).
    pub fn child_pid_with(&self, subcommand: &str, needle: &str) -> Option<i32> {
        self.child_pids(subcommand).into_iter().find(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline"))
                .map(|c| {
                    String::from_utf8_lossy(&c)
                        .replace('\0', " ")
                        .contains(needle)
                })
                .unwrap_or(false)
        })
    }

    /// Sends SIGTERM and waits; returns whether it exited cleanly (code 0). For one process
    /// of a group (`--process`), whose instance's files belong to the group.
    pub fn stop_process(mut self) -> bool {
        self.terminate()
    }

    /// Sends SIGTERM and waits; returns whether it exited cleanly (code 0) and left no
    /// shared-memory files or status reports behind. The stored sessions are removed after
    /// it (an agent keeps them for the next agent of its instance; a test's agent has none).
    pub fn stop(self) -> bool {
        let instance = self.instance.clone();
        let clean = self.stop_keeping_sessions();
        let _ = std::fs::remove_dir_all(xrce_ipc::status::sessions_dir(&instance));
        if let Some(dir) = xrce_ipc::status::sessions_dir(&instance).parent() {
            let _ = std::fs::remove_dir(dir);
        }
        clean
    }

    /// [`Self::stop`] as an operator's `systemctl stop` before a start: the stored sessions
    /// stay for the next agent of the instance.
    pub fn stop_keeping_sessions(mut self) -> bool {
        let clean = self.terminate();
        let left = xrce_ipc::shm::instance_files(&self.instance);
        assert!(
            left.is_empty(),
            "stale shared-memory files after stop: {left:?}"
        );
        let status = xrce_ipc::status::status_dir(&self.instance);
        assert!(
            !status.exists(),
            "status reports left after stop in {}",
            status.display()
        );
        clean
    }

    fn terminate(&mut self) -> bool {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(self.child.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
        let deadline = Instant::now() + Duration::from_secs(15);
        loop {
            match self.child.try_wait() {
                Ok(Some(s)) => return s.success(),
                Ok(None) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(20))
                }
                _ => {
                    let _ = self.child.kill();
                    let _ = self.child.wait();
                    return false;
                }
            }
        }
    }
}

impl Drop for AgentProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            self.terminate();
        }
    }
}

/// How long a test waits for a log line the agent prints after an effect the test saw.
pub const LOG_WAIT: Duration = Duration::from_secs(5);

/// Runs `cmd` (its output piped) to its end and returns what it printed; panics if it
/// takes longer than `d` (it is killed then), so that a hang fails instead of blocking.
pub fn output_within(cmd: &mut Command, d: Duration) -> std::process::Output {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start the command");
    let read = |pipe: Option<Box<dyn std::io::Read + Send>>| {
        std::thread::spawn(move || {
            let mut buf = Vec::new();
            if let Some(mut p) = pipe {
                let _ = p.read_to_end(&mut buf);
            }
            buf
        })
    };
    let out = read(child.stdout.take().map(|p| Box::new(p) as _));
    let err = read(child.stderr.take().map(|p| Box::new(p) as _));
    let end = Instant::now() + d;
    let status = loop {
        if let Ok(Some(s)) = child.try_wait() {
            break s;
        }
        if Instant::now() >= end {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{cmd:?} did not finish within {d:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    std::process::Output {
        status,
        stdout: out.join().unwrap_or_default(),
        stderr: err.join().unwrap_or_default(),
    }
}

/// SIGKILLs a process.
pub fn sigkill(pid: i32) {
    let _ = nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(pid),
        nix::sys::signal::Signal::SIGKILL,
    );
}

/// Starts `xrce-agent` with `args` and `env` (its log level from `XRCE_TEST_LOG`, `info` by
/// default). Its output is collected (and echoed into the test's captured output, shown if
/// the test fails), so a passing suite prints nothing of its agents' logs.
fn spawn_agent(args: &[impl AsRef<std::ffi::OsStr>], env: &[(&str, &str)]) -> (Child, AgentOutput) {
    let mut child = Command::new(binaries().join("xrce-agent"))
        .args(args)
        .env(
            "XRCE_LOG",
            std::env::var("XRCE_TEST_LOG").unwrap_or_else(|_| "info".into()),
        )
        .envs(env.iter().copied())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start xrce-agent");
    let output = AgentOutput::default();
    if let Some(out) = child.stdout.take() {
        output.collect(out, true);
    }
    if let Some(err) = child.stderr.take() {
        output.collect(err, true);
    }
    (child, output)
}
