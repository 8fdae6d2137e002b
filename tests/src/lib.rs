//! End-to-end test harness: real agent processes on loopback, a Rust XRCE client built on
//! `xrce_common`'s client state machine, and Cyclone DDS (Python, pinned) as the independent
//! DDS peer. Everything stays on 127.0.0.1: the agent's DDS is pinned with
//! `--dds-interface 127.0.0.1`, Cyclone with `python/cyclonedds-loopback.xml`.

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::mpsc;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

pub mod link;
pub use link::{Link, PtyPair, SharedLine};
use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind, stream_id, ClientKey, DataDeliveryControl, ObjectId, ObjectVariant,
    ReadSpecification, Representation, RequestId, VariantExtra,
};

/// The Cyclone DDS release the tests pin.
pub const CYCLONEDDS_VERSION: &str = "11.0.1";

/// The workspace root.
pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace")
        .to_path_buf()
}

/// The target directory the tests run from (…/target).
fn target_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("CARGO_TARGET_DIR") {
        return PathBuf::from(d);
    }
    workspace().join("target")
}

/// The DDS backend the agents under test use (`XRCE_DDS_BACKEND`, default `cyclone`, the
/// agent's own default).
pub fn dds_backend() -> String {
    std::env::var("XRCE_DDS_BACKEND").unwrap_or_else(|_| "cyclone".into())
}

/// Builds the agent's binaries once per test process; returns their directory.
pub fn binaries() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let release = std::env::var("XRCE_TEST_RELEASE").is_ok();
        let mut cmd = Command::new(cargo);
        cmd.current_dir(workspace()).args([
            "build",
            "--bins",
            "-p",
            "xrce-agent",
            "-p",
            "xrce-frontend",
            "-p",
            "xrce-dds-worker",
            // Faults injected on purpose when XRCE_FAULT names one (tests/fault-check.sh);
            // inert otherwise. Release builds of the agent never have this feature.
            "--features",
            "xrce-agent/fault-injection,xrce-frontend/fault-injection,xrce-dds-worker/fault-injection",
        ]);
        if release {
            cmd.arg("--release");
        }
        // Built with their default features: both DDS backends. XRCE_DDS_BACKEND=rustdds runs
        // the suite against RustDDS (the agents inherit the variable).
        let st = cmd.status().expect("run cargo build");
        assert!(st.success(), "building the agent binaries failed");
        target_dir().join(if release { "release" } else { "debug" })
    })
}

/// The address and port named by `-p PORT` / `--bind ADDR` in an agent command line
/// (loopback and 0 when absent).
fn ip_and_port(args: &[&str]) -> (std::net::IpAddr, u16) {
    let mut ip: std::net::IpAddr = [127, 0, 0, 1].into();
    let mut port = 0;
    for w in args.windows(2) {
        match w[0] {
            "-p" | "--port" => port = w[1].parse().unwrap_or(0),
            "--bind" => ip = w[1].parse().unwrap_or(ip),
            _ => {}
        }
    }
    (ip, port)
}

/// A port free for both TCP and UDP on 127.0.0.1, below every DDS port (RTPS puts domain
/// `d` at 7400 + 250 d and up) and so below the kernel's ephemeral range too.
///
/// A port the kernel hands out for `bind(0)` would be fine but for two things: between the
/// test learning it and the agent binding it, any client socket of any test running in
/// parallel (the load generator opens hundreds) may be given the same ephemeral port; and a
/// port of the DDS range may be the one a DDS participant of another test's domain wants
/// next. Ports from 2000 to 7399 are neither, so only another test choosing the same one
/// could race, and the candidates are spread by process id and a counter.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let (low, high) = (FREE_PORTS.start, FREE_PORTS.end);
    let span = high - low;
    let seed = std::process::id().wrapping_mul(2_654_435_761);
    for _ in 0..span {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let port = (low + seed.wrapping_add(n.wrapping_mul(7919)) % span) as u16;
        let udp = UdpSocket::bind(("127.0.0.1", port));
        let tcp = std::net::TcpListener::bind(("127.0.0.1", port));
        if udp.is_ok() && tcp.is_ok() {
            return port;
        }
    }
    panic!("no free port in {FREE_PORTS:?}")
}

/// Where [`free_port`] looks: above the well-known ports, below RTPS's first (7400).
pub const FREE_PORTS: std::ops::Range<u32> = 2_000..7_400;

/// A free TCP port on 127.0.0.1 (see [`free_port`]).
pub fn free_tcp_port() -> u16 {
    free_port()
}

/// A free UDP port on 127.0.0.1 (see [`free_port`]).
pub fn free_udp_port() -> u16 {
    free_port()
}

/// A unique instance name for this test process.
pub fn unique_instance(tag: &str) -> String {
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "t{}-{}-{}",
        std::process::id() % 100_000,
        tag,
        N.fetch_add(1, Ordering::Relaxed)
    )
}

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
        let full: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        let mut child = Command::new(binaries().join("xrce-agent"))
            .args(&full)
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
        let mut child = Command::new(binaries().join("xrce-agent"))
            .args(&args)
            .env(
                "XRCE_LOG",
                std::env::var("XRCE_TEST_LOG").unwrap_or_else(|_| "info".into()),
            )
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start xrce-agent");
        // Collected (and echoed into the test's captured output, shown if it fails), so a
        // passing suite prints nothing of its agents' logs.
        let output = AgentOutput::default();
        if let Some(out) = child.stdout.take() {
            output.collect(out, true);
        }
        if let Some(err) = child.stderr.take() {
            output.collect(err, true);
        }
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

/// The HelloWorld sample of the eProsima examples: `unsigned long index; string message;`
/// in little-endian CDR.
pub fn hello_world(index: u32, message: &str) -> Vec<u8> {
    let mut v = index.to_le_bytes().to_vec();
    v.extend_from_slice(&(message.len() as u32 + 1).to_le_bytes());
    v.extend_from_slice(message.as_bytes());
    v.push(0);
    v
}

/// The HelloWorld sample in big-endian CDR (what a big-endian microcontroller writes).
pub fn hello_world_be(index: u32, message: &str) -> Vec<u8> {
    let mut v = index.to_be_bytes().to_vec();
    v.extend_from_slice(&(message.len() as u32 + 1).to_be_bytes());
    v.extend_from_slice(message.as_bytes());
    v.push(0);
    v
}

/// Decodes a HelloWorld sample (little-endian CDR).
pub fn parse_hello_world(b: &[u8]) -> Option<(u32, String)> {
    let index = u32::from_le_bytes(b.get(0..4)?.try_into().ok()?);
    let len = u32::from_le_bytes(b.get(4..8)?.try_into().ok()?) as usize;
    let s = b.get(8..8 + len.checked_sub(1)?)?;
    Some((index, String::from_utf8(s.to_vec()).ok()?))
}

/// XML of the reference client's HelloWorld examples.
pub mod xml {
    /// Participant.
    pub const PARTICIPANT: &str =
        "<dds><participant><rtps><name>default_xrce_participant</name></rtps></participant></dds>";
    /// Topic.
    pub const TOPIC: &str =
        "<dds><topic><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic></dds>";
    /// Data writer.
    pub const WRITER: &str = "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic></data_writer></dds>";
    /// Data reader (reliable, so the tests can demand every sample).
    pub const READER: &str = "<dds><data_reader><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic><qos><reliability><kind>RELIABLE</kind></reliability></qos></data_reader></dds>";
    /// The adder service (requests `{a, b}` on `rq/addRequest`, replies `{sum}` on
    /// `rr/addReply`) as a requester or replier: `{e}` is `requester` or `replier`.
    pub const ADDER_SERVICE: &str = "<dds><{e} profile_name=\"adder\" service_name=\"/add\" \
        request_type=\"AddRequest\" reply_type=\"AddReply\">\
        <request_topic_name>rq/addRequest</request_topic_name>\
        <reply_topic_name>rr/addReply</reply_topic_name></{e}></dds>";
}

/// An adder request (`a`, `b`, little endian) as a requester writes it.
pub fn adder_request(a: u32, b: u32) -> Vec<u8> {
    [a.to_le_bytes(), b.to_le_bytes()].concat()
}

/// An unlimited READ_DATA on the built-in reliable stream, samples as plain data.
pub fn unlimited_reliable_read() -> ReadSpecification {
    ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        data_format: 0,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// A Rust XRCE client over a [`Link`] (UDP, TCP or a serial line), driving `xrce_common`'s
/// client state machine.
#[derive(Debug)]
pub struct TestClient {
    /// The protocol state.
    pub client: Client,
    /// How it reaches the agent.
    pub link: Link,
    /// Events received and not yet consumed.
    pub events: Vec<ClientEvent>,
    /// Messages sent so far.
    pub sent: u64,
    buf: Vec<u8>,
}

impl TestClient {
    /// A client with `key`, talking to `agent`.
    pub fn new(agent: SocketAddr, key: [u8; 4]) -> Self {
        Self::with_config(agent, ClientConfig::new(ClientKey(key)))
    }

    /// A client with its own settings (byte order, liveliness, ...), talking to `agent`.
    pub fn with_config(agent: SocketAddr, config: ClientConfig) -> Self {
        Self::on_link(Link::udp(agent), config)
    }

    /// A client with `key` on a TCP connection to `agent`.
    pub fn tcp(agent: SocketAddr, key: [u8; 4]) -> Self {
        let link = Link::tcp(agent).expect("TCP connection to the agent");
        Self::on_link(link, ClientConfig::new(ClientKey(key)))
    }

    /// A client with `key` at `address` on a serial line.
    pub fn serial(line: std::fs::File, address: u8, key: [u8; 4]) -> Self {
        Self::on_link(
            Link::serial(line, address),
            ClientConfig::new(ClientKey(key)),
        )
    }

    /// A client on any link.
    pub fn on_link(link: Link, config: ClientConfig) -> Self {
        TestClient {
            client: Client::new(config),
            link,
            events: Vec::new(),
            sent: 0,
            buf: vec![0; 65_536],
        }
    }

    /// Runs the protocol for up to `d`, or until `done` says so.
    pub fn run_until(&mut self, d: Duration, mut done: impl FnMut(&mut Self) -> bool) -> bool {
        let end = Instant::now() + d;
        loop {
            self.step();
            if done(self) {
                return true;
            }
            if Instant::now() >= end {
                return false;
            }
        }
    }

    /// One round: flush, receive what arrived (up to 5 ms), fire timers.
    pub fn step(&mut self) {
        while let Some(t) = self.client.poll_transmit() {
            self.sent += u64::from(self.link.send(&t));
        }
        for m in self.link.receive(Duration::from_millis(5), &mut self.buf) {
            self.client.handle_datagram(Instant::now(), &m);
        }
        self.client.handle_timeout(Instant::now());
        while let Some(e) = self.client.poll_event() {
            self.events.push(e);
        }
        while let Some(t) = self.client.poll_transmit() {
            self.sent += u64::from(self.link.send(&t));
        }
    }

    /// Opens the session; panics if the agent does not accept it within `d`.
    pub fn connect(&mut self, d: Duration) {
        self.client.connect(Instant::now());
        let ok = self.run_until(d, |c| c.client.is_connected());
        assert!(ok, "session not established: {:?}", self.events);
    }

    /// Creates an object and waits for its STATUS; returns the status value.
    pub fn create(&mut self, id: ObjectId, kind: u8, xml: &str, extra: VariantExtra) -> u8 {
        self.create_as(id, kind, Representation::Xml(xml.into()), extra)
    }

    /// Creates an object from any representation and waits for its STATUS.
    pub fn create_as(
        &mut self,
        id: ObjectId,
        kind: u8,
        representation: Representation,
        extra: VariantExtra,
    ) -> u8 {
        let variant = ObjectVariant {
            kind,
            representation,
            extra,
        };
        let req = self
            .client
            .create(Instant::now(), id, variant, false, true)
            .expect("create");
        self.wait_status(req, Duration::from_secs(20))
    }

    /// Waits for the STATUS of `req`.
    pub fn wait_status(&mut self, req: RequestId, d: Duration) -> u8 {
        let mut found = None;
        self.run_until(d, |c| {
            if let Some(i) = c
                .events
                .iter()
                .position(|e| matches!(e, ClientEvent::Status(s) if s.related.request_id == req))
            {
                if let ClientEvent::Status(s) = c.events.remove(i) {
                    found = Some(s.result.status);
                }
                return true;
            }
            false
        });
        found.unwrap_or_else(|| panic!("no STATUS for request {req:?}"))
    }

    /// Creates the HelloWorld chain participant (in `domain`) → topic → `group` (publisher
    /// or subscriber) → `endpoint` (writer or reader), asserting every STATUS is OK; returns
    /// the endpoint id.
    pub fn setup_chain(
        &mut self,
        domain: i16,
        group: u8,
        endpoint: u8,
        endpoint_xml: &str,
    ) -> ObjectId {
        let p = ObjectId::new(1, object_kind::PARTICIPANT);
        let t = ObjectId::new(1, object_kind::TOPIC);
        let g = ObjectId::new(1, group);
        let e = ObjectId::new(1, endpoint);
        let steps = [
            (
                p,
                object_kind::PARTICIPANT,
                xml::PARTICIPANT,
                VariantExtra::DomainId(domain),
            ),
            (t, object_kind::TOPIC, xml::TOPIC, VariantExtra::Parent(p)),
            (g, group, "", VariantExtra::Parent(p)),
            (e, endpoint, endpoint_xml, VariantExtra::Parent(g)),
        ];
        for (id, kind, xml, extra) in steps {
            assert_eq!(self.create(id, kind, xml, extra), 0, "creating {id:?}");
        }
        e
    }

    /// Creates participant (in `domain`), topic, publisher and writer of the HelloWorld
    /// example; returns the writer id.
    pub fn setup_publisher(&mut self, domain: i16) -> ObjectId {
        self.setup_chain(
            domain,
            object_kind::PUBLISHER,
            object_kind::DATAWRITER,
            xml::WRITER,
        )
    }

    /// Creates participant, topic, subscriber and reader of the HelloWorld example and
    /// starts an unlimited READ_DATA on the reliable stream; returns the reader id.
    pub fn setup_subscriber(&mut self, domain: i16) -> ObjectId {
        self.setup_subscriber_with(domain, unlimited_reliable_read())
    }

    /// Participant, topic, subscriber and HelloWorld reader in `domain`, then READ_DATA with
    /// `spec`.
    pub fn setup_subscriber_with(&mut self, domain: i16, spec: ReadSpecification) -> ObjectId {
        let r = self.setup_chain(
            domain,
            object_kind::SUBSCRIBER,
            object_kind::DATAREADER,
            xml::READER,
        );
        self.client.read(Instant::now(), r, spec).expect("read");
        r
    }

    /// A participant in `domain` and an adder requester or replier (`kind`) under it, with an
    /// unlimited read started on it; returns the requester's or replier's id. (With either
    /// DDS backend: Cyclone DDS's C API cannot send a related sample identity, so with it the
    /// worker serves requesters and repliers through RustDDS beside it.)
    pub fn setup_adder(&mut self, domain: i16, kind: u8) -> ObjectId {
        let p = ObjectId::new(1, object_kind::PARTICIPANT);
        let e = ObjectId::new(1, kind);
        let status = self.create(
            p,
            object_kind::PARTICIPANT,
            xml::PARTICIPANT,
            VariantExtra::DomainId(domain),
        );
        assert_eq!(status, 0, "creating the participant");
        let element = if kind == object_kind::REQUESTER {
            "requester"
        } else {
            "replier"
        };
        let x = xml::ADDER_SERVICE.replace("{e}", element);
        let status = self.create(e, kind, &x, VariantExtra::Parent(p));
        assert_eq!(status, 0, "creating the {element}");
        self.read_unlimited(e);
        e
    }

    /// Takes the adder replies this requester (`req`) received so far into `answered` (the
    /// sums, by request id; a reply repeated shows as a second sum), checking that each
    /// names the requester.
    pub fn take_adder_replies(
        &mut self,
        req: ObjectId,
        answered: &mut std::collections::HashMap<RequestId, Vec<u32>>,
    ) {
        for (_, d) in self.take_data() {
            assert!(d.len() >= 8, "reply too short: {d:?}");
            assert_eq!(
                ObjectId([d[2], d[3]]),
                req,
                "the BaseObjectRequest names the requester"
            );
            let sum = u32::from_le_bytes([d[4], d[5], d[6], d[7]]);
            answered
                .entry(RequestId([d[0], d[1]]))
                .or_default()
                .push(sum);
        }
    }

    /// Whether the agent still serves this client's session: the STATUS of a DELETE of an
    /// object it never created (ERR_UNKNOWN_REFERENCE from a live session), within `d`.
    pub fn session_answers(&mut self, d: Duration) -> bool {
        let req = self
            .client
            .delete(Instant::now(), ObjectId::new(9, object_kind::DATAWRITER))
            .expect("delete");
        self.wait_status(req, d) == xrce_common::wire::status::ERR_UNKNOWN_REFERENCE
    }

    /// WRITE_DATA (FORMAT_DATA) on the reliable stream; returns its request id.
    pub fn write_reliable_id(&mut self, writer: ObjectId, sample: &[u8]) -> RequestId {
        let ok = self.run_until(Duration::from_secs(60), |c| {
            c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        });
        assert!(ok, "reliable window never opened");
        let id = self
            .client
            .write(Instant::now(), stream_id::BUILTIN_RELIABLE, writer, sample)
            .expect("write");
        self.step();
        id
    }

    /// READ_DATA on the reliable stream with unlimited delivery (data readers, requesters,
    /// repliers).
    pub fn read_unlimited(&mut self, object: ObjectId) {
        let spec = ReadSpecification {
            preferred_stream_id: stream_id::BUILTIN_RELIABLE,
            delivery_control: Some(DataDeliveryControl {
                max_samples: u16::MAX,
                ..Default::default()
            }),
            ..Default::default()
        };
        self.client
            .read(Instant::now(), object, spec)
            .expect("read");
    }

    /// WRITE_DATA in `format` on the reliable stream (`data` follows the BaseObjectRequest).
    pub fn write_reliable_format(&mut self, writer: ObjectId, format: u8, data: &[u8]) {
        let ok = self.run_until(Duration::from_secs(60), |c| {
            c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        });
        assert!(ok, "reliable window never opened");
        self.client
            .write_format(
                Instant::now(),
                stream_id::BUILTIN_RELIABLE,
                writer,
                format,
                data,
            )
            .expect("write");
        self.step();
    }

    /// Every DATA received so far as (format, bytes after the BaseObjectRequest).
    pub fn take_data(&mut self) -> Vec<(u8, Vec<u8>)> {
        let mut out = Vec::new();
        self.events.retain(|e| match e {
            ClientEvent::Data { format, data, .. } => {
                out.push((*format, data.clone()));
                false
            }
            _ => true,
        });
        out
    }

    /// Writes on the reliable stream, waiting for window room.
    pub fn write_reliable(&mut self, writer: ObjectId, sample: &[u8]) {
        let ok = self.run_until(Duration::from_secs(60), |c| {
            c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        });
        assert!(ok, "reliable window never opened");
        self.client
            .write(Instant::now(), stream_id::BUILTIN_RELIABLE, writer, sample)
            .expect("write");
        self.step();
    }

    /// Writes on the best-effort stream (nothing waits: what is lost is lost).
    pub fn write_best_effort(&mut self, writer: ObjectId, sample: &[u8]) {
        self.client
            .write(
                Instant::now(),
                stream_id::BUILTIN_BEST_EFFORT,
                writer,
                sample,
            )
            .expect("write");
        self.step();
    }

    /// HelloWorld samples received so far (consumed from `events`). A DATA that is not a
    /// HelloWorld sample fails the test: a corrupted sample must not pass as a lost one.
    pub fn take_samples(&mut self) -> Vec<(u32, String)> {
        let mut out = Vec::new();
        self.events.retain(|e| match e {
            ClientEvent::Data { data, .. } => {
                match parse_hello_world(data) {
                    Some(s) => out.push(s),
                    None => panic!("a DATA that is not a HelloWorld sample: {data:?}"),
                }
                false
            }
            _ => true,
        });
        out
    }
}

/// The Python virtual environment with Cyclone DDS, created once under `target/`.
pub fn cyclone_python() -> PathBuf {
    static PY: OnceLock<PathBuf> = OnceLock::new();
    PY.get_or_init(|| {
        let venv = target_dir().join("cyclonedds-venv");
        let py = venv.join("bin/python");
        let lock = std::fs::File::create(target_dir().join("cyclonedds-venv.lock")).expect("lock file");
        let _guard = nix::fcntl::Flock::lock(lock, nix::fcntl::FlockArg::LockExclusive).expect("flock");
        let ready = Command::new(&py)
            .args(["-c", &format!("import cyclonedds, importlib.metadata as m; assert m.version('cyclonedds') == '{CYCLONEDDS_VERSION}'")])
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !ready {
            let st = Command::new("python3").args(["-m", "venv"]).arg(&venv).status().expect("python3 -m venv");
            assert!(st.success(), "creating the venv failed");
            let st = Command::new(venv.join("bin/pip"))
                .args(["install", "--quiet", "--only-binary=:all:", &format!("cyclonedds=={CYCLONEDDS_VERSION}")])
                .status()
                .expect("pip install");
            assert!(st.success(), "installing cyclonedds {CYCLONEDDS_VERSION} failed");
        }
        py
    })
    .clone()
}

/// A running `dds_peer.py` (Cyclone DDS) process with its stdout lines on a channel.
#[derive(Debug)]
pub struct DdsPeer {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl DdsPeer {
    /// Starts `dds_peer.py <args>` pinned to loopback.
    pub fn start(args: &[&str]) -> Self {
        let xml = workspace().join("tests/python/cyclonedds-loopback.xml");
        let mut child = Command::new(cyclone_python())
            .arg(workspace().join("tests/python/dds_peer.py"))
            .args(args)
            .env("CYCLONEDDS_URI", format!("file://{}", xml.display()))
            .stdout(Stdio::piped())
            .spawn()
            .expect("start dds_peer.py");
        let stdout: ChildStdout = child.stdout.take().expect("stdout");
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        DdsPeer { child, lines }
    }

    /// The next output line, waiting up to `d`.
    pub fn line(&self, d: Duration) -> Option<String> {
        self.lines.recv_timeout(d).ok()
    }

    /// Waits for a line starting with `prefix`, while `pump` keeps other parties running.
    pub fn wait_for(&self, prefix: &str, d: Duration, mut pump: impl FnMut()) -> Option<String> {
        let end = Instant::now() + d;
        while Instant::now() < end {
            pump();
            if let Ok(l) = self.lines.recv_timeout(Duration::from_millis(2)) {
                if l.starts_with(prefix) {
                    return Some(l);
                }
            }
        }
        None
    }

    /// Waits for the process to end; returns its exit code.
    pub fn wait(&mut self, d: Duration, mut pump: impl FnMut()) -> Option<i32> {
        let end = Instant::now() + d;
        while Instant::now() < end {
            pump();
            if let Ok(Some(s)) = self.child.try_wait() {
                return s.code();
            }
        }
        None
    }

    /// All lines received so far.
    pub fn drain_lines(&self) -> Vec<String> {
        self.lines.try_iter().collect()
    }
}

impl Drop for DdsPeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Parses a `{"index": i, "message": "..."}` line from the peer.
pub fn parse_sample_line(l: &str) -> Option<(u32, String)> {
    let v: serde_json::Value = serde_json::from_str(l).ok()?;
    let index = u32::try_from(v.get("index")?.as_u64()?).ok()?;
    Some((index, v.get("message")?.as_str()?.to_string()))
}

/// Parses a sample line's index and the DDS writer it came from (Cyclone's publication
/// handle: one per remote writer).
pub fn parse_sample_writer(l: &str) -> Option<(u32, u64)> {
    let v: serde_json::Value = serde_json::from_str(l).ok()?;
    let index = u32::try_from(v.get("index")?.as_u64()?).ok()?;
    Some((index, v.get("writer")?.as_u64()?))
}

/// Every delivery of a HelloWorld sample, by index and in arrival order, so that a sample
/// delivered twice is as visible as one never delivered.
#[derive(Debug, Clone, Default)]
pub struct Deliveries {
    counts: std::collections::BTreeMap<u32, usize>,
    order: Vec<u32>,
}

impl Deliveries {
    /// Records one delivery.
    pub fn record(&mut self, index: u32) {
        *self.counts.entry(index).or_default() += 1;
        self.order.push(index);
    }

    /// Distinct indices delivered.
    pub fn distinct(&self) -> usize {
        self.counts.len()
    }

    /// Deliveries in all, duplicates included.
    pub fn total(&self) -> usize {
        self.order.len()
    }

    /// Deliveries recorded so far, duplicates included (a mark for [`Deliveries::order_from`]).
    pub fn order_len(&self) -> usize {
        self.order.len()
    }

    /// The indices delivered since `mark` (an earlier [`Deliveries::order_len`]), in order.
    pub fn order_from(&self, mark: usize) -> Vec<u32> {
        self.order.get(mark..).unwrap_or_default().to_vec()
    }

    /// The index delivered last (0 if none).
    pub fn order_last(&self) -> u32 {
        self.order.last().copied().unwrap_or(0)
    }

    /// How often `index` was delivered.
    pub fn count(&self, index: u32) -> usize {
        self.counts.get(&index).copied().unwrap_or(0)
    }

    /// The indices delivered more than once, with their counts.
    pub fn repeated(&self) -> Vec<(u32, usize)> {
        self.counts
            .iter()
            .filter(|(_, n)| **n > 1)
            .map(|(i, n)| (*i, *n))
            .collect()
    }

    /// Asserts that every index of `expected` arrived exactly once and nothing else did.
    pub fn assert_exactly_once(&self, expected: impl IntoIterator<Item = u32>, what: &str) {
        let expected: std::collections::BTreeSet<u32> = expected.into_iter().collect();
        let missing: Vec<u32> = expected
            .iter()
            .copied()
            .filter(|i| !self.counts.contains_key(i))
            .collect();
        let repeated: Vec<(u32, usize)> = self
            .counts
            .iter()
            .filter(|(_, n)| **n > 1)
            .map(|(i, n)| (*i, *n))
            .collect();
        let unexpected: Vec<u32> = self
            .counts
            .keys()
            .copied()
            .filter(|i| !expected.contains(i))
            .collect();
        assert!(
            missing.is_empty() && repeated.is_empty() && unexpected.is_empty(),
            "{what}: missing {missing:?}, delivered more than once {repeated:?}, unexpected {unexpected:?}"
        );
    }

    /// Asserts that the deliveries came in increasing index order (what a reliable stream
    /// from one writer promises).
    pub fn assert_in_order(&self, what: &str) {
        let inversions: Vec<(u32, u32)> = self
            .order
            .windows(2)
            .filter(|w| w[1] <= w[0])
            .map(|w| (w[0], w[1]))
            .collect();
        assert!(
            inversions.is_empty(),
            "{what}: out of order: {inversions:?}"
        );
    }
}

impl Deliveries {
    /// Runs `pump` (which returns the indices delivered in that round) until `want`
    /// distinct ones arrived and [`DUPLICATE_GRACE`] passed, or `d` passed.
    pub fn collect(want: usize, d: Duration, mut pump: impl FnMut() -> Vec<u32>) -> Self {
        let mut got = Deliveries::default();
        let end = Instant::now() + d;
        let mut complete_at: Option<Instant> = None;
        while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
            for i in pump() {
                got.record(i);
            }
            if complete_at.is_none() && got.distinct() >= want {
                complete_at = Some(Instant::now());
            }
        }
        got
    }
}

/// How long collections keep listening after the last expected sample, so that a duplicate
/// arriving just after it is seen too.
pub const DUPLICATE_GRACE: Duration = Duration::from_millis(500);

impl DdsPeer {
    /// Records the HelloWorld samples a `read` peer prints (checking each message is
    /// `message`) until `want` distinct ones arrived and [`DUPLICATE_GRACE`] passed, or `d`
    /// passed, while `pump` keeps other parties running.
    pub fn collect_deliveries(
        &self,
        want: usize,
        message: &str,
        d: Duration,
        mut pump: impl FnMut(),
    ) -> Deliveries {
        let mut got = Deliveries::default();
        let end = Instant::now() + d;
        let mut complete_at: Option<Instant> = None;
        while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
            pump();
            while let Some(l) = self.line(Duration::from_millis(1)) {
                if let Some((i, m)) = parse_sample_line(&l) {
                    assert_eq!(m, message, "sample {i} carries another message");
                    got.record(i);
                }
            }
            if complete_at.is_none() && got.distinct() >= want {
                complete_at = Some(Instant::now());
            }
        }
        got
    }
}

impl TestClient {
    /// Records the HelloWorld samples this client receives (checking each message is
    /// `message`) until `want` distinct ones arrived and [`DUPLICATE_GRACE`] passed, or `d`
    /// passed.
    pub fn collect_deliveries(&mut self, want: usize, message: &str, d: Duration) -> Deliveries {
        let mut got = Deliveries::default();
        let end = Instant::now() + d;
        let mut complete_at: Option<Instant> = None;
        while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
            self.step();
            for (i, m) in self.take_samples() {
                assert_eq!(m, message, "sample {i} carries another message");
                got.record(i);
            }
            if complete_at.is_none() && got.distinct() >= want {
                complete_at = Some(Instant::now());
            }
        }
        got
    }
}
