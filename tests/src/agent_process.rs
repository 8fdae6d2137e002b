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
    /// What it printed (stdout and stderr), when started with [`AgentProcess::launch`].
    output: Option<AgentOutput>,
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

    /// How many lines contain `needle`.
    pub fn count(&self, needle: &str) -> usize {
        self.lines
            .0
            .lock()
            .map(|v| v.iter().filter(|l| l.contains(needle)).count())
            .unwrap_or(0)
    }
}

impl AgentProcess {
    /// Starts `xrce-agent <args>` (DDS pinned to loopback, instance `tag`-based) and waits
    /// until it reports ready (every front-end serving), up to 30 s. Its output is collected
    /// ([`Self::output`]). `None` if it exited first.
    pub fn launch(tag: &str, args: &[&str]) -> Option<Self> {
        Self::launch_with_env(tag, args, &[])
    }

    /// [`Self::launch`] with extra environment variables.
    pub fn launch_with_env(tag: &str, args: &[&str], env: &[(&str, &str)]) -> Option<Self> {
        let instance = unique_instance(tag);
        let mut full: Vec<&str> = args.to_vec();
        full.extend(["--dds-interface", "127.0.0.1", "--instance", &instance]);
        let (ip, port) = ip_and_port(args);
        Self::spawn_collected(&full, instance.clone(), "agent ready", ip, port, env)
    }

    /// Starts `xrce-agent <args>` exactly as given (a gateway file names its instance and
    /// pins DDS itself) and waits up to 30 s for a log line containing `ready`.
    pub fn launch_raw(
        args: &[&str],
        instance: String,
        ready: &str,
        ip: std::net::IpAddr,
        port: u16,
    ) -> Option<Self> {
        Self::spawn_collected(args, instance, ready, ip, port, &[])
    }

    fn spawn_collected(
        args: &[&str],
        instance: String,
        ready: &str,
        ip: std::net::IpAddr,
        port: u16,
        env: &[(&str, &str)],
    ) -> Option<Self> {
        let (child, output) = spawn_agent(args, env);
        let mut agent = AgentProcess {
            child,
            port,
            instance,
            ip,
            output: Some(output.clone()),
        };
        let end = Instant::now() + Duration::from_secs(30);
        while Instant::now() < end {
            if output
                .wait_for(0, ready, Duration::from_millis(100))
                .is_some()
            {
                return Some(agent);
            }
            if let Ok(Some(_)) = agent.child.try_wait() {
                return None;
            }
        }
        None
    }

    /// The agent's collected output.
    pub fn output(&self) -> &AgentOutput {
        self.output
            .as_ref()
            .expect("output is collected for every agent started here")
    }

    /// Starts an agent on a free port.
    pub fn start(tag: &str) -> Self {
        Self::start_with_env(tag, &[])
    }

    /// Starts an agent on a free port with extra environment variables.
    pub fn start_with_env(tag: &str, env: &[(&str, &str)]) -> Self {
        // A port found free can be taken by another process before the agent binds it
        // (tests run in parallel): then the agent exits at once, and another port is tried.
        for _ in 0..5 {
            let port = free_udp_port();
            let instance = unique_instance(tag);
            if let Some(a) =
                Self::try_start(([127, 0, 0, 1], port).into(), Some(instance), &[], env)
            {
                return a;
            }
        }
        panic!("the agent did not start on any of 5 free ports");
    }

    /// Starts an agent bound to `addr`; without `instance` it picks its default name
    /// (`udp4-<port>-<hash of what it serves and its network namespace>`).
    pub fn start_on(addr: SocketAddr, instance: Option<String>) -> Self {
        Self::start_with(addr, instance, &[])
    }

    /// Starts an agent bound to `addr` with extra command-line arguments.
    pub fn start_with(addr: SocketAddr, instance: Option<String>, extra: &[&str]) -> Self {
        Self::try_start(addr, instance, extra, &[]).expect("the agent did not answer a ping")
    }

    /// Starts an agent; `None` if it exits or does not answer a ping within 20 s.
    fn try_start(
        addr: SocketAddr,
        instance: Option<String>,
        extra: &[&str],
        env: &[(&str, &str)],
    ) -> Option<Self> {
        let port = addr.port();
        let mut args = vec![
            "udp4".to_string(),
            "-p".into(),
            port.to_string(),
            "--bind".into(),
            addr.ip().to_string(),
        ];
        args.extend(["--dds-interface".to_string(), "127.0.0.1".into()]);
        if let Some(i) = &instance {
            args.extend(["--instance".to_string(), i.clone()]);
        }
        args.extend(extra.iter().map(|a| a.to_string()));
        let (child, output) = spawn_agent(&args, env);
        // The agent's own default: derived from what it serves (and the namespace).
        let instance = instance.unwrap_or_else(|| {
            xrce_ipc::derived_instance(
                &format!("udp4-{port}"),
                &SocketAddr::new(addr.ip(), port).to_string(),
            )
        });
        let mut agent = AgentProcess {
            child,
            port,
            instance,
            ip: addr.ip(),
            output: Some(output),
        };
        let end = Instant::now() + Duration::from_secs(20);
        while Instant::now() < end {
            if agent.ping(Duration::from_millis(200)) {
                return Some(agent);
            }
            if let Ok(Some(_)) = agent.child.try_wait() {
                return None;
            }
        }
        None
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
