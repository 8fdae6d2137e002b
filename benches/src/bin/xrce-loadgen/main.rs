//! `xrce-loadgen`: a load generator. N publishing XRCE clients and one subscribing client
//! (common's client state machine, one UDP socket and session each) talk through an agent;
//! it reports session set-up time, the samples/s delivered client → agent → DDS → agent →
//! client, losses, latency percentiles (HdrHistogram), and the agent's CPU time and peak RSS
//! summed over its process group (from /proc).
//!
//! By default it starts our agent (`xrce-agent` next to this binary) on `--port`;
//! `--agent-cmd 'CMD {port}'` starts any other agent with a shell, and `--no-agent` uses one
//! already running. `--json FILE` writes the results for machines.
//!
//! An independent DDS reader (RustDDS, its own participant, pinned to loopback) counts what
//! reaches DDS and its latency client → agent → DDS (`--dds-reader false` leaves it out).
//!
//! `--compare-with 'OTHER-AGENT {port}'` runs the same scenario alternately against ours (or
//! `--agent-cmd`) and the other agent, `--rounds` times each, and prints medians and ratios.
//!
//! Example: `xrce-loadgen --publishers 100 --samples 50000 --best-effort --json run.json`.

mod dds_reader;
mod plot;

use std::collections::HashSet;
use std::net::UdpSocket;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use clap::Parser;

use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind as k, status, stream_id, ClientKey, DataDeliveryControl, ObjectId, ObjectVariant,
    ReadSpecification, Representation, RequestId, VariantExtra,
};

/// One simulated client: its protocol state and its socket.
struct Peer {
    client: Client,
    socket: UdpSocket,
    pending: HashSet<RequestId>,
    /// Something was queued on the client since its last pump (it has sends to make).
    dirty: bool,
    /// The client's next timer, as of its last pump.
    next_timeout: Option<Instant>,
}

impl Peer {
    fn new(port: u16, key: [u8; 4]) -> std::io::Result<Self> {
        let socket = UdpSocket::bind("127.0.0.1:0")?;
        socket.connect(("127.0.0.1", port))?;
        socket.set_nonblocking(true)?;
        Ok(Peer {
            client: Client::new(ClientConfig::new(ClientKey(key))),
            socket,
            pending: HashSet::new(),
            dirty: true,
            next_timeout: None,
        })
    }

    /// Sends what is due, receives what arrived (if `readable`), and collects events.
    fn pump(
        &mut self,
        now: Instant,
        readable: bool,
        buf: &mut [u8],
        events: &mut Vec<ClientEvent>,
    ) -> Result<(), String> {
        self.dirty = false;
        if readable {
            while let Ok(n) = self.socket.recv(buf) {
                self.client.handle_datagram(now, &buf[..n]);
            }
        }
        if self.client.poll_timeout().is_some_and(|t| t <= now) {
            self.client.handle_timeout(now);
        }
        while let Some(t) = self.client.poll_transmit() {
            let _ = self.socket.send(&t);
        }
        self.next_timeout = self.client.poll_timeout();
        for e in std::iter::from_fn(|| self.client.poll_event()) {
            match e {
                ClientEvent::Status(s) if self.pending.remove(&s.related.request_id) => {
                    if s.result.status != status::OK {
                        return Err(format!(
                            "creation refused with status {:#04x}",
                            s.result.status
                        ));
                    }
                }
                other => events.push(other),
            }
        }
        Ok(())
    }

    /// Queues a CREATE; its STATUS is awaited by [`pump`] through `pending`.
    fn create(
        &mut self,
        id: ObjectId,
        kind: u8,
        xml: &str,
        extra: VariantExtra,
    ) -> Result<(), String> {
        let v = ObjectVariant {
            kind,
            representation: Representation::Xml(xml.into()),
            extra,
        };
        let req = self
            .client
            .create(Instant::now(), id, v, false, true)
            .map_err(|e| e.to_string())?;
        self.pending.insert(req);
        self.dirty = true;
        Ok(())
    }
}

/// Readiness of every client's socket through one epoll set, so that with thousands of
/// clients an iteration costs one system call plus the sockets that have data.
struct Poller {
    epoll: nix::sys::epoll::Epoll,
    events: Vec<nix::sys::epoll::EpollEvent>,
    ready: Vec<bool>,
}

impl Poller {
    fn new(peers: &[Peer]) -> Result<Self, String> {
        use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags};
        let epoll = Epoll::new(EpollCreateFlags::empty()).map_err(|e| e.to_string())?;
        for (i, p) in peers.iter().enumerate() {
            epoll
                .add(&p.socket, EpollEvent::new(EpollFlags::EPOLLIN, i as u64))
                .map_err(|e| e.to_string())?;
        }
        Ok(Poller {
            epoll,
            events: vec![EpollEvent::empty(); 1024],
            ready: vec![false; peers.len()],
        })
    }

    /// Marks the sockets with data (level-triggered: still ready until drained).
    fn poll(&mut self) {
        self.ready.iter_mut().for_each(|r| *r = false);
        let n = self
            .epoll
            .wait(&mut self.events, nix::sys::epoll::EpollTimeout::ZERO)
            .unwrap_or(0);
        for e in &self.events[..n] {
            if let Some(r) = self.ready.get_mut(e.data() as usize) {
                *r = true;
            }
        }
    }
}

/// Every client handles what concerns it: received data, due timers, queued sends.
fn pump_all(
    peers: &mut [Peer],
    poller: &mut Poller,
    buf: &mut [u8],
    events: &mut Vec<ClientEvent>,
) -> Result<(), String> {
    poller.poll();
    let now = Instant::now();
    // Only the clients with data, with a due timer, or with something queued: with
    // thousands of idle clients an iteration stays cheap.
    for (p, r) in peers.iter_mut().zip(poller.ready.iter()) {
        if *r || p.dirty || p.next_timeout.is_some_and(|t| t <= now) {
            p.pump(now, *r, buf, events)?;
        }
    }
    Ok(())
}

/// Lets the open-file limit grow to its hard limit (one socket per simulated client).
fn raise_fd_limit() {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    if let Ok((_, hard)) = getrlimit(Resource::RLIMIT_NOFILE) {
        let _ = setrlimit(Resource::RLIMIT_NOFILE, hard, hard);
    }
}

fn pump_until(
    peers: &mut [Peer],
    poller: &mut Poller,
    limit: Duration,
    mut done: impl FnMut(&[Peer]) -> bool,
) -> Result<bool, String> {
    let end = Instant::now() + limit;
    let mut buf = vec![0u8; 65_536];
    let mut ignored = Vec::new();
    let mut last_report = Instant::now();
    while Instant::now() < end {
        pump_all(peers, poller, &mut buf, &mut ignored)?;
        ignored.clear();
        if done(peers) {
            return Ok(true);
        }
        if last_report.elapsed() > Duration::from_secs(1) {
            last_report = Instant::now();
            let connected = peers.iter().filter(|p| p.client.is_connected()).count();
            let pending: usize = peers.iter().map(|p| p.pending.len()).sum();
            eprintln!(
                "set-up: {connected} of {} sessions, {pending} creations pending",
                peers.len()
            );
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    Ok(false)
}

/// Command line.
#[derive(Debug, Clone, Parser)]
#[command(name = "xrce-loadgen", about = "Load generator for XRCE agents")]
struct Args {
    /// UDP port of the agent.
    #[arg(long, default_value_t = 8888)]
    port: u16,
    /// Publishing clients (each its own session and socket); one more client subscribes.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=60_000))]
    publishers: u32,
    /// Samples to send in the measured phase.
    #[arg(long, default_value_t = 20_000)]
    samples: u32,
    /// Samples per second in total (0 = as fast as the windows allow).
    #[arg(long, default_value_t = 0.0)]
    rate: f64,
    /// Sample size in bytes (at least 12: sequence number and send time).
    #[arg(long, default_value_t = 40)]
    payload: usize,
    /// DDS domain of the clients' participants.
    #[arg(long, default_value_t = 42)]
    domain: i16,
    /// Best-effort streams (default: reliable).
    #[arg(long)]
    best_effort: bool,
    /// History depth of the DDS writers and reader (0 = KEEP_ALL).
    #[arg(long, default_value_t = 1000)]
    history: u32,
    /// Longest measured phase in seconds.
    #[arg(long, default_value_t = 60)]
    duration: u64,
    /// Command starting the agent under test, `{port}` replaced (run with `sh -c`).
    #[arg(long)]
    agent_cmd: Option<String>,
    /// Use an agent that is already running on `--port`.
    #[arg(long, conflicts_with = "agent_cmd")]
    no_agent: bool,
    /// Write the results as JSON to this file.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
    /// Compare mode: also run the scenario against this agent command (`{port}` replaced),
    /// alternating with ours (or `--agent-cmd`), and print the medians and ratios.
    #[arg(long = "compare-with")]
    compare_with: Option<String>,
    /// Sweep mode: run the scenario once per publisher count in this list (e.g.
    /// `1,10,100,1000`), print a table, and with `--svg` plot it.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=60_000))]
    sweep: Vec<u32>,
    /// Sweep mode: write an SVG plot of throughput and latency against client count.
    #[arg(long)]
    svg: Option<std::path::PathBuf>,
    /// Rounds per agent in compare mode.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    rounds: u32,
    /// Count the samples that reach DDS with an independent RustDDS reader in this process.
    #[arg(long = "dds-reader", default_value_t = true, action = clap::ArgAction::Set)]
    dds_reader: bool,
}

/// The agent under test, started by the generator and stopped when dropped.
struct AgentUnderTest {
    child: Child,
}

impl AgentUnderTest {
    fn start(cmd: &str, port: u16) -> Result<Self, String> {
        let line = cmd.replace("{port}", &port.to_string());
        eprintln!("starting agent: {line}");
        let child = Command::new("sh")
            .arg("-c")
            .arg(format!("exec {line}"))
            .spawn()
            .map_err(|e| format!("starting {line:?}: {e}"))?;
        Ok(AgentUnderTest { child })
    }

    /// CPU seconds and summed peak RSS (KiB) of the agent and every descendant.
    fn usage(&self) -> Option<ProcUsage> {
        proc_usage(self.child.id())
    }
}

impl Drop for AgentUnderTest {
    fn drop(&mut self) {
        let pid = self.child.id() as i32;
        // SIGINT first (agents clean up), then give them 5 s.
        let _ = Command::new("kill")
            .args(["-INT", &pid.to_string()])
            .status();
        let end = Instant::now() + Duration::from_secs(5);
        while Instant::now() < end {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Resource use of a process tree.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
struct ProcUsage {
    /// User plus system CPU seconds.
    cpu_seconds: f64,
    /// Sum of the processes' peak resident set sizes, KiB.
    peak_rss_kib: u64,
    /// Processes counted.
    processes: usize,
    /// Threads of all the processes.
    threads: u64,
    /// Open file descriptors of all the processes.
    fds: u64,
}

/// Reads /proc for `root` and its descendants.
fn proc_usage(root: u32) -> Option<ProcUsage> {
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
        let after = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
        let f: Vec<&str> = after.split_whitespace().collect();
        // Fields after the command: state(0) ppid(1) ... utime(11) stime(12).
        let t = |k: usize| f.get(k).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        u.cpu_seconds += (t(11) + t(12)) / ticks;
        if let Ok(status) = std::fs::read_to_string(format!("/proc/{pid}/status")) {
            let field = |name: &str| {
                status
                    .lines()
                    .find_map(|l| l.strip_prefix(name))
                    .and_then(|v| v.split_whitespace().next())
                    .and_then(|v| v.parse::<u64>().ok())
                    .unwrap_or(0)
            };
            u.peak_rss_kib += field("VmHWM:");
            u.threads += field("Threads:");
        }
        u.fds += std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count() as u64);
        u.processes += 1;
    }
    Some(u)
}

/// Waits until something answers an XRCE ping on `port` (giving up early if the agent we
/// started exited).
fn wait_for_agent(port: u16, limit: Duration, agent: &mut Option<AgentUnderTest>) -> bool {
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

/// What one run measured (also written as JSON).
#[derive(Debug, serde::Serialize)]
struct Report {
    publishers: u32,
    subscribers: u32,
    payload_bytes: usize,
    reliable: bool,
    rate_requested: f64,
    sessions_ms: f64,
    setup_ms: f64,
    matched_ms: f64,
    unmatched_writers: usize,
    sent: u32,
    received: u64,
    lost: u64,
    duplicates: u64,
    seconds: f64,
    samples_per_second: f64,
    bytes_per_second: f64,
    /// What the independent DDS reader counted (client → agent → DDS).
    dds: Option<DdsReport>,
    latency_us: Percentiles,
    agent: Option<AgentUse>,
}

#[derive(Debug, serde::Serialize)]
struct Percentiles {
    p50: f64,
    p90: f64,
    p99: f64,
    p999: f64,
    max: f64,
}

#[derive(Debug, serde::Serialize)]
struct DdsReport {
    received: u64,
    lost: u64,
    duplicates: u64,
    samples_per_second: f64,
    latency_us: Percentiles,
}

#[derive(Debug, serde::Serialize)]
struct AgentUse {
    /// CPU seconds of the agent's processes during the measured phase.
    cpu_seconds: f64,
    /// CPU microseconds per delivered sample.
    cpu_us_per_sample: f64,
    /// Summed peak RSS of the agent's processes at the end, KiB.
    peak_rss_kib: u64,
    processes: usize,
    /// Threads of the agent's processes at the end of the measured phase.
    threads: u64,
    /// Open file descriptors of the agent's processes at the end of the measured phase.
    fds: u64,
}

fn main() -> Result<(), String> {
    let a = Args::parse();
    raise_fd_limit();
    if let Some(other) = &a.compare_with {
        return compare(&a, other);
    }
    if !a.sweep.is_empty() {
        return sweep(&a);
    }
    let report = run(&a, a.agent_cmd.as_deref())?;
    print_report(&report);
    if let Some(path) = &a.json {
        let text = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    Ok(())
}

/// Runs the scenario of `a` once against the agent `agent_cmd` starts (ours if None, none
/// with `--no-agent`).
fn run(a: &Args, agent_cmd: Option<&str>) -> Result<Report, String> {
    let (port, publishers, samples, payload, domain, rate) = (
        a.port,
        a.publishers as usize,
        a.samples,
        a.payload.max(12),
        a.domain,
        a.rate,
    );
    let stream = if a.best_effort {
        stream_id::BUILTIN_BEST_EFFORT
    } else {
        stream_id::BUILTIN_RELIABLE
    };
    let mut agent = if a.no_agent {
        None
    } else {
        let cmd = match agent_cmd {
            Some(c) => c.to_string(),
            None => {
                let exe = std::env::current_exe().map_err(|e| e.to_string())?;
                let ours = exe.with_file_name("xrce-agent");
                format!(
                    "{} udp4 -p {{port}} --bind 127.0.0.1 --dds-interface 127.0.0.1 -v 3",
                    ours.display()
                )
            }
        };
        Some(AgentUnderTest::start(&cmd, port)?)
    };
    if !wait_for_agent(port, Duration::from_secs(30), &mut agent) {
        return Err(format!("no agent answers a ping on UDP port {port}"));
    }
    let topic = "<dds><topic><name>LoadTopic</name><dataType>Load</dataType></topic></dds>";
    let history = if a.history == 0 {
        "<kind>KEEP_ALL</kind>".to_string()
    } else {
        format!("<kind>KEEP_LAST</kind><depth>{}</depth>", a.history)
    };
    // The DDS endpoints follow the scenario: reliable, or best-effort end to end.
    let reliability = if a.best_effort {
        "BEST_EFFORT"
    } else {
        "RELIABLE"
    };
    let endpoint = |e: &str| {
        format!(
            "<dds><{e}><topic><kind>NO_KEY</kind><name>LoadTopic</name><dataType>Load</dataType></topic><qos><reliability><kind>{reliability}</kind></reliability><durability><kind>VOLATILE</kind></durability><historyQos>{history}</historyQos></qos></{e}></dds>"
        )
    };
    let base = Instant::now();
    let dds = if a.dds_reader {
        Some(dds_reader::DdsReader::start(
            u16::try_from(domain).map_err(|_| format!("domain {domain} is not a DDS domain"))?,
            "LoadTopic",
            "Load",
            samples,
            publishers,
            base,
        )?)
    } else {
        None
    };
    // Peer 0 subscribes, the others publish.
    let mut peers = Vec::with_capacity(publishers + 1);
    for i in 0..=publishers {
        peers.push(
            Peer::new(port, [0x10, 0xAD, (i >> 8) as u8, i as u8]).map_err(|e| e.to_string())?,
        );
    }
    let mut poller = Poller::new(&peers)?;
    let t_start = Instant::now();
    for p in peers.iter_mut() {
        p.client.connect(Instant::now());
    }
    if !pump_until(&mut peers, &mut poller, Duration::from_secs(60), |ps| {
        ps.iter().all(|p| p.client.is_connected())
    })? {
        return Err("not every session was established within 60 s".into());
    }
    let sessions_at = t_start.elapsed();
    let (part, tp) = (ObjectId::new(1, k::PARTICIPANT), ObjectId::new(1, k::TOPIC));
    let (subscriber, reader) = (
        ObjectId::new(1, k::SUBSCRIBER),
        ObjectId::new(1, k::DATAREADER),
    );
    let (publisher, writer) = (
        ObjectId::new(1, k::PUBLISHER),
        ObjectId::new(1, k::DATAWRITER),
    );
    for (i, p) in peers.iter_mut().enumerate() {
        p.create(
            part,
            k::PARTICIPANT,
            "<dds><participant><rtps><name>load</name></rtps></participant></dds>",
            VariantExtra::DomainId(domain),
        )?;
        p.create(tp, k::TOPIC, topic, VariantExtra::Parent(part))?;
        if i == 0 {
            p.create(subscriber, k::SUBSCRIBER, "", VariantExtra::Parent(part))?;
            p.create(
                reader,
                k::DATAREADER,
                &endpoint("data_reader"),
                VariantExtra::Parent(subscriber),
            )?;
        } else {
            p.create(publisher, k::PUBLISHER, "", VariantExtra::Parent(part))?;
            p.create(
                writer,
                k::DATAWRITER,
                &endpoint("data_writer"),
                VariantExtra::Parent(publisher),
            )?;
        }
    }
    if !pump_until(&mut peers, &mut poller, Duration::from_secs(120), |ps| {
        ps.iter().all(|p| p.pending.is_empty())
    })? {
        return Err("not every entity was created within 120 s".into());
    }
    let setup = t_start.elapsed();
    eprintln!(
        "{} sessions in {:.0} ms, their {} entities in {:.0} ms ({:.0} sessions/s)",
        peers.len(),
        sessions_at.as_secs_f64() * 1e3,
        peers.len() * 4,
        setup.as_secs_f64() * 1e3,
        peers.len() as f64 / setup.as_secs_f64()
    );
    let spec = ReadSpecification {
        preferred_stream_id: stream,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    peers[0]
        .client
        .read(Instant::now(), reader, spec)
        .map_err(|e| e.to_string())?;
    peers[0].dirty = true;

    let sample = |seq: u32| {
        let mut v = vec![0u8; payload];
        v[0..4].copy_from_slice(&seq.to_le_bytes());
        v[4..12].copy_from_slice(&(base.elapsed().as_nanos() as u64).to_le_bytes());
        v
    };
    let mut buf = vec![0u8; 65_536];
    let mut events = Vec::new();
    // Probe until DDS matched every writer with the reader: each publisher's probe comes back.
    let mut heard = vec![false; peers.len()];
    heard[0] = true;
    let probe_end = Instant::now() + Duration::from_secs(60);
    let dds_pending = |d: &Option<dds_reader::DdsReader>| {
        d.as_ref().is_some_and(|d| d.probes_heard() < publishers)
    };
    let mut round = 0u64;
    while (heard.iter().any(|h| !h) || dds_pending(&dds)) && Instant::now() < probe_end {
        round += 1;
        // The DDS reader may still miss some: every publisher probes again now and then.
        let again = dds_pending(&dds) && round % 20 == 0;
        for (i, p) in peers.iter_mut().enumerate().skip(1) {
            if (!heard[i] || again) && p.client.can_send_reliable(stream) {
                let _ =
                    p.client
                        .write(Instant::now(), stream, writer, &sample(u32::MAX - i as u32));
                p.dirty = true;
            }
        }
        pump_all(&mut peers, &mut poller, &mut buf, &mut events)?;
        for e in events.drain(..) {
            if let ClientEvent::Data { data, .. } = e {
                let Some(tag) = data
                    .get(..4)
                    .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                else {
                    continue;
                };
                if let Some(i) = u32::MAX
                    .checked_sub(tag)
                    .map(|i| i as usize)
                    .filter(|i| *i < heard.len())
                {
                    heard[i] = true;
                }
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let matched = t_start.elapsed();
    let unmatched = heard.iter().filter(|h| !**h).count();
    if dds_pending(&dds) {
        eprintln!(
            "the DDS reader heard {} of {publishers} publishers before the run",
            dds.as_ref().map_or(0, |d| d.probes_heard())
        );
    }
    std::thread::sleep(Duration::from_millis(200));
    pump_all(&mut peers, &mut poller, &mut buf, &mut Vec::new())?;

    // The run: publishers take turns; the subscriber records each sample once.
    let (mut sent, mut next_pub) = (0u32, 1usize);
    let mut latencies = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 60_000_000_000, 3)
        .map_err(|e| e.to_string())?;
    let (mut received, mut duplicates) = (0u64, 0u64);
    let mut seen = vec![false; samples as usize];
    let usage_before = agent.as_ref().and_then(AgentUnderTest::usage);
    let t0 = Instant::now();
    let mut last_report = t0;
    let deadline = t0 + Duration::from_secs(a.duration);
    let mut last_rx = t0;
    while (received as u32) < samples && Instant::now() < deadline {
        // Everything sent and nothing more for a while: the rest is lost. Reliable samples
        // are still coming while the agent works through a backlog, so they get longer.
        let idle = if stream == stream_id::BUILTIN_RELIABLE {
            Duration::from_secs(10)
        } else {
            Duration::from_secs(2)
        };
        if sent == samples && last_rx.elapsed() > idle {
            break;
        }
        let allowed = if rate > 0.0 {
            ((t0.elapsed().as_secs_f64() * rate) as u32).min(samples)
        } else {
            samples
        };
        let mut tries = 0;
        while sent < allowed && tries < publishers {
            let p = &mut peers[next_pub];
            next_pub = if next_pub == publishers {
                1
            } else {
                next_pub + 1
            };
            if stream == stream_id::BUILTIN_RELIABLE && !p.client.can_send_reliable(stream) {
                tries += 1;
                continue;
            }
            tries = 0;
            let _ = p
                .client
                .write(Instant::now(), stream, writer, &sample(sent));
            p.dirty = true;
            sent += 1;
            if sent % 64 == 0 {
                break;
            }
        }
        pump_all(&mut peers, &mut poller, &mut buf, &mut events)?;
        let now_ns = base.elapsed().as_nanos() as u64;
        for e in events.drain(..) {
            if let ClientEvent::Data { data, .. } = e {
                if data.len() < 12 {
                    continue;
                }
                let seq = u32::from_le_bytes([data[0], data[1], data[2], data[3]]) as usize;
                if seq < seen.len() && !seen[seq] {
                    seen[seq] = true;
                    received += 1;
                    last_rx = Instant::now();
                    let mut ts = [0u8; 8];
                    ts.copy_from_slice(&data[4..12]);
                    let ns = now_ns.saturating_sub(u64::from_le_bytes(ts)).max(1);
                    let _ = latencies.record(ns.min(60_000_000_000));
                } else if seq < seen.len() {
                    duplicates += 1;
                }
            }
        }
        if last_report.elapsed() > Duration::from_secs(1) {
            last_report = Instant::now();
            eprintln!("progress: sent {sent}, received {received}");
        }
    }
    // Throughput over the time until the last sample arrived.
    let elapsed = last_rx
        .saturating_duration_since(t0)
        .max(Duration::from_millis(1));
    let usage_after = agent.as_ref().and_then(AgentUnderTest::usage);
    let pct = |q: f64| latencies.value_at_quantile(q) as f64 / 1000.0;
    let dds = match dds {
        Some(d) => {
            std::thread::sleep(Duration::from_millis(300));
            let c = d.finish()?;
            let secs = c
                .last_rx
                .map_or(Duration::from_millis(1), |l| {
                    l.saturating_duration_since(t0)
                })
                .max(Duration::from_millis(1))
                .as_secs_f64();
            let q = |x: f64| c.latencies.value_at_quantile(x) as f64 / 1000.0;
            Some(DdsReport {
                received: c.received,
                lost: u64::from(sent).saturating_sub(c.received),
                duplicates: c.duplicates,
                samples_per_second: c.received as f64 / secs,
                latency_us: Percentiles {
                    p50: q(0.5),
                    p90: q(0.9),
                    p99: q(0.99),
                    p999: q(0.999),
                    max: c.latencies.max() as f64 / 1000.0,
                },
            })
        }
        None => None,
    };
    let report = Report {
        publishers: publishers as u32,
        subscribers: 1,
        payload_bytes: payload,
        reliable: stream == stream_id::BUILTIN_RELIABLE,
        rate_requested: rate,
        sessions_ms: sessions_at.as_secs_f64() * 1e3,
        setup_ms: setup.as_secs_f64() * 1e3,
        matched_ms: matched.as_secs_f64() * 1e3,
        unmatched_writers: unmatched,
        sent,
        received,
        lost: u64::from(sent).saturating_sub(received),
        duplicates,
        seconds: elapsed.as_secs_f64(),
        samples_per_second: received as f64 / elapsed.as_secs_f64(),
        bytes_per_second: (received as f64 * payload as f64) / elapsed.as_secs_f64(),
        dds,
        latency_us: Percentiles {
            p50: pct(0.5),
            p90: pct(0.9),
            p99: pct(0.99),
            p999: pct(0.999),
            max: latencies.max() as f64 / 1000.0,
        },
        agent: match (usage_before, usage_after) {
            (Some(b), Some(e)) => Some(AgentUse {
                cpu_seconds: e.cpu_seconds - b.cpu_seconds,
                cpu_us_per_sample: (e.cpu_seconds - b.cpu_seconds) * 1e6 / (received.max(1) as f64),
                peak_rss_kib: e.peak_rss_kib,
                processes: e.processes,
                threads: e.threads,
                fds: e.fds,
            }),
            _ => None,
        },
    };
    drop(agent);
    Ok(report)
}

/// Prints a run's results for people.
fn print_report(report: &Report) {
    println!(
        "{} publishers + 1 subscriber, {} B {}: set-up {:.0} ms (sessions {:.0} ms), writers matched at {:.0} ms ({} never)",
        report.publishers,
        report.payload_bytes,
        if report.reliable { "reliable" } else { "best-effort" },
        report.setup_ms,
        report.sessions_ms,
        report.matched_ms,
        report.unmatched_writers
    );
    println!(
        "  {} of {} samples in {:.2} s = {:.0} samples/s ({:.1} MB/s), {} lost, {} duplicates",
        report.received,
        report.sent,
        report.seconds,
        report.samples_per_second,
        report.bytes_per_second / 1e6,
        report.lost,
        report.duplicates
    );
    let l = &report.latency_us;
    println!(
        "  latency us: p50 {:.0}  p90 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}",
        l.p50, l.p90, l.p99, l.p999, l.max
    );
    if let Some(d) = &report.dds {
        println!(
            "  into DDS (independent RustDDS reader): {} of {} = {:.0} samples/s, {} lost, {} duplicates; latency us: p50 {:.0}  p90 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}",
            d.received,
            report.sent,
            d.samples_per_second,
            d.lost,
            d.duplicates,
            d.latency_us.p50,
            d.latency_us.p90,
            d.latency_us.p99,
            d.latency_us.p999,
            d.latency_us.max
        );
    }
    if let Some(u) = &report.agent {
        println!(
            "  agent ({} processes, {} threads, {} fds): {:.2} CPU s = {:.1} us/sample, peak RSS {:.1} MiB",
            u.processes,
            u.threads,
            u.fds,
            u.cpu_seconds,
            u.cpu_us_per_sample,
            u.peak_rss_kib as f64 / 1024.0
        );
    }
}

/// Runs the scenario alternately against our agent (or `--agent-cmd`) and `other`,
/// `--rounds` times each, and prints the medians and their ratios.
fn compare(a: &Args, other: &str) -> Result<(), String> {
    if a.no_agent {
        return Err("--compare-with starts both agents; it cannot use --no-agent".into());
    }
    let mut runs: [Vec<Report>; 2] = [Vec::new(), Vec::new()];
    for round in 0..a.rounds {
        for (side, cmd) in [a.agent_cmd.as_deref(), Some(other)]
            .into_iter()
            .enumerate()
        {
            eprintln!(
                "round {} of {}, agent {}",
                round + 1,
                a.rounds,
                ["A", "B"][side]
            );
            let r = run(a, cmd)?;
            print_report(&r);
            runs[side].push(r);
        }
    }
    let median = |side: usize, f: &dyn Fn(&Report) -> f64| {
        let mut v: Vec<f64> = runs[side].iter().map(f).filter(|x| x.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    type Metric = (&'static str, Box<dyn Fn(&Report) -> f64>);
    let metrics: Vec<Metric> = vec![
        ("set-up ms", Box::new(|r| r.setup_ms)),
        ("samples/s", Box::new(|r| r.samples_per_second)),
        ("lost", Box::new(|r| r.lost as f64)),
        ("p50 us", Box::new(|r| r.latency_us.p50)),
        ("p99 us", Box::new(|r| r.latency_us.p99)),
        (
            "into DDS samples/s",
            Box::new(|r| r.dds.as_ref().map_or(f64::NAN, |d| d.samples_per_second)),
        ),
        (
            "agent CPU us/sample",
            Box::new(|r| r.agent.as_ref().map_or(f64::NAN, |u| u.cpu_us_per_sample)),
        ),
        (
            "agent peak RSS MiB",
            Box::new(|r| {
                r.agent
                    .as_ref()
                    .map_or(f64::NAN, |u| u.peak_rss_kib as f64 / 1024.0)
            }),
        ),
    ];
    println!(
        "\nmedians of {} rounds; A = {}, B = {other}",
        a.rounds,
        a.agent_cmd.as_deref().unwrap_or("our xrce-agent")
    );
    println!("{:<22} {:>12} {:>12} {:>8}", "metric", "A", "B", "B / A");
    let mut table = Vec::new();
    for (name, f) in &metrics {
        let (x, y) = (median(0, f), median(1, f));
        println!("{name:<22} {x:>12.1} {y:>12.1} {:>8.2}", y / x);
        table.push(serde_json::json!({"metric": name, "a": x, "b": y, "ratio_b_over_a": y / x}));
    }
    if let Some(path) = &a.json {
        let doc = serde_json::json!({"a": runs[0], "b": runs[1], "medians": table});
        let text = serde_json::to_string_pretty(&doc).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    Ok(())
}

/// Runs the scenario for each publisher count of `--sweep`, prints a table, and writes the
/// SVG plot and the JSON of every run when asked.
fn sweep(a: &Args) -> Result<(), String> {
    let mut points = Vec::new();
    let mut reports = Vec::new();
    for &n in &a.sweep {
        let mut one = a.clone();
        one.publishers = n;
        eprintln!("sweep: {n} publishing clients");
        let r = run(&one, a.agent_cmd.as_deref())?;
        print_report(&r);
        points.push(plot::SweepPoint {
            clients: n,
            samples_per_second: r.samples_per_second,
            into_dds_per_second: r.dds.as_ref().map(|d| d.samples_per_second),
            p50_us: r.latency_us.p50,
            p99_us: r.latency_us.p99,
            lost_fraction: r.lost as f64 / f64::from(r.sent.max(1)),
        });
        reports.push(r);
    }
    println!(
        "\n{:>8} {:>12} {:>12} {:>8} {:>10} {:>10}",
        "clients", "samples/s", "into DDS/s", "lost %", "p50 us", "p99 us"
    );
    for p in &points {
        println!(
            "{:>8} {:>12.0} {:>12} {:>8.2} {:>10.0} {:>10.0}",
            p.clients,
            p.samples_per_second,
            p.into_dds_per_second
                .map_or("-".to_string(), |v| format!("{v:.0}")),
            p.lost_fraction * 100.0,
            p.p50_us,
            p.p99_us
        );
    }
    if let Some(path) = &a.svg {
        let title = format!(
            "xrce-loadgen sweep: {} B {} samples, {} in total{}",
            a.payload.max(12),
            if a.best_effort {
                "best-effort"
            } else {
                "reliable"
            },
            a.samples,
            if a.rate > 0.0 {
                format!(" at {:.0}/s", a.rate)
            } else {
                ", unpaced".to_string()
            }
        );
        plot::write_svg(path, &title, &points)?;
        eprintln!("plot written to {}", path.display());
    }
    if let Some(path) = &a.json {
        let doc = serde_json::json!({"points": points, "runs": reports});
        let text = serde_json::to_string_pretty(&doc).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    Ok(())
}
