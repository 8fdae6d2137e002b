//! The metrics endpoint (`--metrics ADDR:PORT`, `[metrics] listen`): a small HTTP server on
//! its own thread that serves, from the status reports every process of the instance writes
//! ([`xrce_ipc::status`]):
//!
//! * `/metrics`: the Prometheus text exposition (format 0.0.4), encoded by
//!   `prometheus-client` from a collector that reads the reports on each scrape;
//! * `/status`: the same reports as one JSON document ([`AgentStatus`]), which
//!   `xrce-agent status --metrics URL` reads.
//!
//! Nothing is counted here but the endpoint's own refusals
//! (`xrce_metrics_connections_refused_total`): every other number is a process's own
//! counter, so a restarted process's counters start again from zero, which Prometheus's
//! `rate()` handles.
//!
//! The endpoint is bounded ([`Server`]): one thread and no thread per connection, at most
//! [`MAX_CONNECTIONS`] connections at once, a request must arrive whole within
//! [`REQUEST_TIMEOUT`] and fit in [`MAX_REQUEST_BYTES`], a response must be taken within
//! [`WRITE_TIMEOUT`] of progress and [`RESPONSE_TIMEOUT`] in all. Peers that connect and say
//! nothing cost a descriptor for two seconds each and cannot lock a scraper out: the oldest
//! of them makes room for a new connection. It binds where the operator says (there is no
//! default address: the endpoint is off unless `--metrics ADDR:PORT` or `[metrics] listen`
//! is given; the documented address is 127.0.0.1:9464) and warns when that is not loopback.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::os::fd::AsFd;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use nix::poll::{poll, PollFd, PollFlags};

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use serde::{Deserialize, Serialize};
use xrce_ipc::status::{self, ProcessReport};

/// Everything `/status` says: the instance and the reports of its live processes.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct AgentStatus {
    /// The instance name.
    pub instance: String,
    /// Reports of its live processes (supervisor, worker, front-ends).
    pub processes: Vec<ProcessReport>,
}

impl AgentStatus {
    /// Replaces every client key by its redacted form
    /// ([`crate::status_view::redact_key`]).
    pub fn redact_keys(&mut self) {
        for p in &mut self.processes {
            if let Some(f) = &mut p.frontend {
                for s in &mut f.sessions {
                    s.client_key = crate::status_view::redact_key(&s.client_key);
                }
            }
        }
    }

    /// The reports found now in an instance's status directory.
    pub fn read(instance: &str, dir: &std::path::Path) -> Self {
        AgentStatus {
            instance: instance.to_string(),
            processes: status::read_reports(dir),
        }
    }
}

/// Labels of one sample.
type Labels = Vec<(&'static str, String)>;

/// A sample's value: counts stay integers in the exposition.
#[derive(Debug, Clone, Copy)]
enum Value {
    Count(u64),
    Real(f64),
}

/// One metric family being filled in.
struct Family {
    name: &'static str,
    help: &'static str,
    kind: MetricType,
    samples: Vec<(Labels, Value)>,
}

impl Family {
    fn new(name: &'static str, kind: MetricType, help: &'static str) -> Self {
        Family {
            name,
            help,
            kind,
            samples: Vec::new(),
        }
    }

    fn add(&mut self, labels: Labels, value: u64) {
        self.samples.push((labels, Value::Count(value)));
    }

    fn add_real(&mut self, labels: Labels, value: f64) {
        self.samples.push((labels, Value::Real(value)));
    }

    fn encode(&self, encoder: &mut DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        if self.samples.is_empty() {
            return Ok(());
        }
        let mut metric = encoder.encode_descriptor(self.name, self.help, None, self.kind)?;
        for (labels, value) in &self.samples {
            let family = metric.encode_family(labels)?;
            match (self.kind, *value) {
                (MetricType::Counter, Value::Count(v)) => ConstCounter::new(v).encode(family)?,
                (MetricType::Counter, Value::Real(v)) => ConstCounter::new(v).encode(family)?,
                (_, Value::Count(v)) => {
                    ConstGauge::new(i64::try_from(v).unwrap_or(i64::MAX)).encode(family)?
                }
                (_, Value::Real(v)) => ConstGauge::new(v).encode(family)?,
            }
        }
        Ok(())
    }
}

/// The metric families of a status snapshot. Counter names are given without `_total`,
/// which the encoder appends.
fn families(s: &AgentStatus) -> Vec<Family> {
    use MetricType::{Counter, Gauge};
    let mut sessions = Family::new("xrce_sessions", Gauge, "Live XRCE sessions of a front-end.");
    let mut connected = Family::new(
        "xrce_frontend_connected",
        Gauge,
        "1 while the front-end serves the running DDS worker's generation, else 0 (no worker, \
         or it died and its successor has not been seen yet).",
    );
    // The generation of the worker that runs now (its report is read only while it lives).
    let live_generation = s
        .processes
        .iter()
        .find_map(|p| p.worker.as_ref().map(|w| w.generation));
    let per_frontend: [(&str, &'static str, &'static str); 10] = [
        (
            "messages_received",
            "xrce_messages_received",
            "XRCE messages received from clients.",
        ),
        (
            "messages_sent",
            "xrce_messages_sent",
            "XRCE messages sent to clients (retransmissions included).",
        ),
        (
            "samples_written",
            "xrce_samples_written",
            "Samples clients wrote (WRITE_DATA handed to DDS).",
        ),
        (
            "samples_delivered",
            "xrce_samples_delivered",
            "Samples from DDS queued for clients (DATA).",
        ),
        (
            "retransmissions",
            "xrce_retransmissions",
            "Reliable messages sent again to clients.",
        ),
        (
            "reads_paused",
            "xrce_reads_paused",
            "Times a read was paused because its client did not keep up.",
        ),
        (
            "best_effort_sheds",
            "xrce_best_effort_sheds",
            "Times a client's best-effort writes overflowed their wait for the worker, shared by the clients (an overload: that client's are then shed, not queued, for 200 ms).",
        ),
        (
            "replays",
            "xrce_replays",
            "Object graphs replayed to a new DDS worker.",
        ),
        (
            "transport_opened",
            "xrce_transport_connections_opened",
            "Connections accepted or devices opened.",
        ),
        (
            "transport_closed",
            "xrce_transport_connections_closed",
            "Connections or devices closed.",
        ),
    ];
    let mut counters: Vec<Family> = per_frontend
        .iter()
        .map(|(_, name, help)| Family::new(name, Counter, help))
        .collect();
    let mut dropped = Family::new(
        "xrce_dropped",
        Counter,
        "Input, output and operations dropped, by process and reason.",
    );
    let mut worker_entities = Family::new(
        "xrce_worker_entities",
        Gauge,
        "DDS-side entities the worker holds, by kind.",
    );
    let mut worker_written = Family::new(
        "xrce_worker_samples_written",
        Counter,
        "Samples the worker accepted for DDS writers.",
    );
    let mut worker_taken = Family::new(
        "xrce_worker_samples_taken",
        Counter,
        "Samples the worker took from DDS readers for clients.",
    );
    let mut worker_restarts = Family::new(
        "xrce_worker_restarts",
        Counter,
        "Times the supervisor restarted the DDS worker.",
    );
    let mut frontend_restarts = Family::new(
        "xrce_frontend_restarts",
        Counter,
        "Times the supervisor restarted a front-end.",
    );
    let mut watchdog_kills = Family::new(
        "xrce_watchdog_kills",
        Counter,
        "Children killed (and restarted) because their event loop stopped reporting.",
    );
    let mut memory_kills = Family::new(
        "xrce_memory_limit_kills",
        Counter,
        "Children killed (and restarted) because their private resident memory (RssAnon) exceeded --memory-limit.",
    );
    let mut cpu = Family::new(
        "xrce_process_cpu_seconds",
        Counter,
        "User and system CPU time of each process of the agent.",
    );
    let mut memory = Family::new(
        "xrce_process_resident_memory_bytes",
        Gauge,
        "Resident memory of each process of the agent.",
    );
    let mut start = Family::new(
        "xrce_process_start_time_seconds",
        Gauge,
        "Start time of each process of the agent, in seconds since the Unix epoch.",
    );
    for p in &s.processes {
        let process: Labels = vec![("process", p.name.clone())];
        cpu.add_real(process.clone(), p.cpu_seconds);
        memory.add(process.clone(), p.resident_bytes);
        start.add_real(process.clone(), p.started_unix_ms as f64 / 1000.0);
        if let Some(f) = &p.frontend {
            let labels: Labels = vec![
                ("frontend", p.name.clone()),
                ("transport", f.transport.clone()),
            ];
            sessions.add(labels.clone(), f.sessions.len() as u64);
            // Reports older than the generation field count as connected while a worker runs.
            let serves_live = f.connected
                && live_generation.is_some()
                && f.generation.is_none_or(|g| Some(g) == live_generation);
            connected.add(labels.clone(), u64::from(serves_live));
            for ((key, _, _), family) in per_frontend.iter().zip(counters.iter_mut()) {
                family.add(labels.clone(), f.counters.get(*key).copied().unwrap_or(0));
            }
            for (reason, n) in &f.dropped {
                dropped.add(
                    vec![("process", p.name.clone()), ("reason", reason.clone())],
                    *n,
                );
            }
        }
        if let Some(w) = &p.worker {
            for (kind, n) in &w.entities {
                worker_entities.add(vec![("kind", kind.clone())], *n);
            }
            worker_written.add(Vec::new(), w.samples_written);
            worker_taken.add(Vec::new(), w.samples_taken);
            for (reason, n) in &w.dropped {
                dropped.add(
                    vec![("process", p.name.clone()), ("reason", reason.clone())],
                    *n,
                );
            }
        }
        for c in &p.children {
            let name = process_name(&c.name);
            match c.role.as_str() {
                "worker" => worker_restarts.add(Vec::new(), c.restarts),
                _ => frontend_restarts.add(vec![("frontend", name.clone())], c.restarts),
            }
            watchdog_kills.add(vec![("process", name.clone())], c.watchdog_kills);
            memory_kills.add(vec![("process", name)], c.memory_kills);
        }
    }
    let mut out = vec![sessions, connected];
    out.extend(counters);
    out.extend([
        dropped,
        worker_entities,
        worker_written,
        worker_taken,
        worker_restarts,
        frontend_restarts,
        watchdog_kills,
        memory_kills,
        cpu,
        memory,
        start,
    ]);
    out
}

/// A supervisor child's name (`xrce-dds-worker`, `xrce-frontend-<name>`) as the process
/// reports itself (`worker`, `<name>`).
pub fn process_name(child: &str) -> String {
    if child == "xrce-dds-worker" {
        return "worker".into();
    }
    child
        .strip_prefix("xrce-frontend-")
        .unwrap_or(child)
        .to_string()
}

/// Reads the reports on each scrape.
#[derive(Debug)]
struct StatusCollector {
    instance: String,
    dir: PathBuf,
}

impl Collector for StatusCollector {
    fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        let snapshot = AgentStatus::read(&self.instance, &self.dir);
        for f in families(&snapshot) {
            f.encode(&mut encoder)?;
        }
        Ok(())
    }
}

/// The Prometheus text exposition of a snapshot.
pub fn render(snapshot: &AgentStatus) -> Result<String, std::fmt::Error> {
    #[derive(Debug)]
    struct Fixed(AgentStatus);
    impl Collector for Fixed {
        fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
            for f in families(&self.0) {
                f.encode(&mut encoder)?;
            }
            Ok(())
        }
    }
    let mut registry = Registry::default();
    registry.register_collector(Box::new(Fixed(snapshot.clone())));
    let mut out = String::new();
    prometheus_client::encoding::prometheus_text::encode(&mut out, &registry)?;
    Ok(out)
}

/// Connections the endpoint holds open at once, whatever they are doing (waiting for a
/// request, being answered, being closed). Beyond, the oldest one that has not sent a whole
/// request yet is closed to make room (counted `evicted`), else the new one is closed at once
/// (counted `busy`).
pub const MAX_CONNECTIONS: usize = 16;
/// A connection must deliver its whole request (line and headers) within this time of being
/// accepted, or it is closed (counted `timeout`): a peer that sends nothing, or a byte at a
/// time, holds a slot this long at most.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(2);
/// A response that makes no progress (the peer does not read) for this long is abandoned
/// (counted `timeout`).
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(2);
/// A response not sent whole within this time is abandoned (counted `timeout`).
pub const RESPONSE_TIMEOUT: Duration = Duration::from_secs(10);
/// The largest request (line and headers) read; a larger one is answered 431 and closed
/// (counted `too_large`). A body is never read.
pub const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// After its response, a connection's remaining input is read and dropped for this long, or
/// this many bytes, so that closing it does not reset it before the peer read the response.
const LINGER: Duration = Duration::from_secs(1);
const LINGER_BYTES: usize = 64 * 1024;
/// A refusal episode ends after this long without refusals: logged when it starts and when
/// it ends, never per connection.
const EPISODE_QUIET: Duration = Duration::from_secs(10);
/// How long the listener rests after an accept failed for want of descriptors or memory.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);
/// Connections accepted per turn of the loop at most (the others wait in the backlog).
const ACCEPTS_PER_TURN: usize = 64;

/// Why the endpoint closed a connection without answering it, or before its answer was
/// taken: the `reason` label of `xrce_metrics_connections_refused_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// Every slot held a connection being answered: the new one was closed at once.
    Busy,
    /// The oldest connection without a whole request was closed to make room for a new one.
    Evicted,
    /// The request did not arrive, or the response was not taken, in time.
    Timeout,
    /// The request was larger than [`MAX_REQUEST_BYTES`].
    TooLarge,
}

impl Refusal {
    const ALL: [Refusal; 4] = [
        Refusal::Busy,
        Refusal::Evicted,
        Refusal::Timeout,
        Refusal::TooLarge,
    ];

    fn label(self) -> &'static str {
        match self {
            Refusal::Busy => "busy",
            Refusal::Evicted => "evicted",
            Refusal::Timeout => "timeout",
            Refusal::TooLarge => "too_large",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// The endpoint's own counters (it serves them with the processes' numbers).
#[derive(Debug, Default)]
pub struct ServerStats {
    refused: [AtomicU64; Refusal::ALL.len()],
}

impl ServerStats {
    /// Connections refused so far for `reason`.
    pub fn refused(&self, reason: Refusal) -> u64 {
        self.refused[reason.index()].load(Ordering::Relaxed)
    }

    fn count(&self, reason: Refusal) {
        self.refused[reason.index()].fetch_add(1, Ordering::Relaxed);
    }
}

/// Encodes [`ServerStats`] on each scrape.
#[derive(Debug)]
struct ServerCollector(Arc<ServerStats>);

impl Collector for ServerCollector {
    fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        let mut refused = Family::new(
            "xrce_metrics_connections_refused",
            MetricType::Counter,
            "Connections to the metrics endpoint closed without an answer, by reason: busy \
             (every slot answering), evicted (made room for a newer one), timeout (request or \
             response too slow), too_large (request over the size cap).",
        );
        for r in Refusal::ALL {
            refused.add(vec![("reason", r.label().to_string())], self.0.refused(r));
        }
        refused.encode(&mut encoder)
    }
}

/// Serves `/metrics` and `/status` for `instance` on `listen` from a thread of its own;
/// fails at once if the address cannot be bound. The address is the operator's
/// (`--metrics`, `[metrics] listen`); one that is not loopback is warned about.
pub fn serve(listen: SocketAddr, instance: &str) -> anyhow::Result<std::thread::JoinHandle<()>> {
    let server = Server::bind(listen, instance, status::status_dir(instance))?;
    if !listen.ip().is_loopback() {
        tracing::warn!(
            %listen,
            "the metrics endpoint is not on a loopback address: whoever reaches it reads the \
             agent's sessions and counters (/status, /metrics); prefer 127.0.0.1 or [::1], or \
             restrict who can reach it"
        );
    }
    tracing::info!(
        %listen,
        max_connections = MAX_CONNECTIONS,
        "metrics served at /metrics, status at /status"
    );
    let handle = std::thread::Builder::new()
        .name("metrics".into())
        .spawn(move || server.run())?;
    Ok(handle)
}

/// The metrics endpoint: one thread, no thread per connection, at most [`MAX_CONNECTIONS`]
/// connections, each with deadlines (see the constants above); non-blocking sockets under
/// `poll(2)`. A scrape is answered from the loop (reading the reports takes milliseconds).
/// Every connection is closed after its response (`Connection: close`).
#[derive(Debug)]
pub struct Server {
    listener: TcpListener,
    registry: Registry,
    instance: String,
    dir: PathBuf,
    stats: Arc<ServerStats>,
    conns: Vec<Conn>,
    episode: Option<Episode>,
    listener_rests_until: Option<Instant>,
    accept_error_logged: Option<Instant>,
}

/// A run of refusals, logged at its start and its end.
#[derive(Debug)]
struct Episode {
    started: Instant,
    last: Instant,
    counts: [u64; Refusal::ALL.len()],
}

#[derive(Debug)]
struct Conn {
    stream: TcpStream,
    accepted: Instant,
    state: State,
}

#[derive(Debug)]
enum State {
    /// Waiting for the whole request head.
    Reading { buf: Vec<u8> },
    /// Sending the response.
    Writing {
        out: Vec<u8>,
        sent: usize,
        last_progress: Instant,
        deadline: Instant,
    },
    /// Response sent and output shut down: reading what the peer still sends until it
    /// closes (or the linger ends), then closing.
    Draining { until: Instant, drained: usize },
}

/// What a connection's turn leads to.
enum Next {
    Keep,
    Close(Option<Refusal>),
}

impl Conn {
    /// When the connection must be closed if it has not moved on.
    fn deadline(&self) -> Instant {
        match &self.state {
            State::Reading { .. } => self.accepted + REQUEST_TIMEOUT,
            State::Writing {
                last_progress,
                deadline,
                ..
            } => (*last_progress + WRITE_TIMEOUT).min(*deadline),
            State::Draining { until, .. } => *until,
        }
    }

    /// Whether it may be closed to make room for a new connection: it has not sent a whole
    /// request (or has been answered already).
    fn evictable(&self) -> bool {
        !matches!(self.state, State::Writing { .. })
    }

    fn events(&self) -> PollFlags {
        match self.state {
            State::Writing { .. } => PollFlags::POLLOUT,
            State::Reading { .. } | State::Draining { .. } => PollFlags::POLLIN,
        }
    }
}

impl Server {
    /// Binds `listen`; the reports are read from `dir`.
    pub fn bind(listen: SocketAddr, instance: &str, dir: PathBuf) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(listen)
            .map_err(|e| anyhow::anyhow!("cannot serve metrics on {listen}: {e}"))?;
        listener
            .set_nonblocking(true)
            .map_err(|e| anyhow::anyhow!("metrics listener on {listen}: {e}"))?;
        let stats = Arc::new(ServerStats::default());
        let mut registry = Registry::default();
        registry.register_collector(Box::new(StatusCollector {
            instance: instance.to_string(),
            dir: dir.clone(),
        }));
        registry.register_collector(Box::new(ServerCollector(stats.clone())));
        Ok(Server {
            listener,
            registry,
            instance: instance.to_string(),
            dir,
            stats,
            conns: Vec::with_capacity(MAX_CONNECTIONS),
            episode: None,
            listener_rests_until: None,
            accept_error_logged: None,
        })
    }

    /// The bound address (the port, when bound to port 0).
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// The endpoint's counters.
    pub fn stats(&self) -> Arc<ServerStats> {
        self.stats.clone()
    }

    /// Serves for ever.
    pub fn run(mut self) {
        loop {
            self.turn();
        }
    }

    /// One turn: waits for readiness or the next deadline, then serves what is ready.
    fn turn(&mut self) {
        let now = Instant::now();
        self.expire(now);
        self.end_quiet_episode(now);
        let listening = self.listener_rests_until.is_none_or(|t| now >= t);
        if listening {
            self.listener_rests_until = None;
        }
        let wait = self.next_wake(now).saturating_duration_since(now);
        // Rounded up, so that a deadline a fraction of a millisecond away is not spun on.
        let wait_ms = u16::try_from(wait.as_millis() + 1).unwrap_or(u16::MAX);
        let ready: Vec<bool> = {
            let mut fds = Vec::with_capacity(self.conns.len() + 1);
            fds.push(PollFd::new(
                self.listener.as_fd(),
                if listening {
                    PollFlags::POLLIN
                } else {
                    PollFlags::empty()
                },
            ));
            for c in &self.conns {
                fds.push(PollFd::new(c.stream.as_fd(), c.events()));
            }
            match poll(&mut fds, wait_ms) {
                Ok(_) => fds
                    .iter()
                    .map(|f| f.revents().is_some_and(|r| !r.is_empty()))
                    .collect(),
                Err(nix::errno::Errno::EINTR) => return,
                Err(e) => {
                    tracing::warn!(error = %e, "metrics endpoint: poll failed");
                    std::thread::sleep(ACCEPT_BACKOFF);
                    return;
                }
            }
        };
        let now = Instant::now();
        // Connections first (by index, from the end, so that removals keep the indices of
        // those not yet served), then the new ones.
        for i in (0..self.conns.len()).rev() {
            if !ready.get(i + 1).copied().unwrap_or(false) {
                continue;
            }
            if let Next::Close(reason) = self.serve_conn(i, now) {
                self.close(i, reason, now);
            }
        }
        if listening && ready.first().copied().unwrap_or(false) {
            self.accept(now);
        }
    }

    /// The earliest instant the loop must wake up at.
    fn next_wake(&self, now: Instant) -> Instant {
        let mut wake = now + Duration::from_secs(1);
        for c in &self.conns {
            wake = wake.min(c.deadline());
        }
        if let Some(t) = self.listener_rests_until {
            wake = wake.min(t);
        }
        if let Some(e) = &self.episode {
            wake = wake.min(e.last + EPISODE_QUIET);
        }
        wake
    }

    /// Closes the connections whose deadline has passed.
    fn expire(&mut self, now: Instant) {
        for i in (0..self.conns.len()).rev() {
            if self.conns[i].deadline() <= now {
                let reason = match self.conns[i].state {
                    State::Draining { .. } => None,
                    State::Reading { .. } | State::Writing { .. } => Some(Refusal::Timeout),
                };
                self.close(i, reason, now);
            }
        }
    }

    /// Closes connection `i`, counting why if it was refused. Counted before the socket is
    /// closed, so that a peer that sees the close also sees it counted.
    fn close(&mut self, i: usize, reason: Option<Refusal>, now: Instant) {
        if let Some(reason) = reason {
            self.refused(reason, now);
        }
        let conn = self.conns.swap_remove(i);
        drop(conn);
    }

    /// Counts a refusal; logs the first of an episode.
    fn refused(&mut self, reason: Refusal, now: Instant) {
        note_refusal(&self.stats, &mut self.episode, reason, now);
    }

    /// Ends (and logs) an episode with no refusal for [`EPISODE_QUIET`].
    fn end_quiet_episode(&mut self, now: Instant) {
        let quiet = self
            .episode
            .as_ref()
            .is_some_and(|e| now.saturating_duration_since(e.last) >= EPISODE_QUIET);
        if !quiet {
            return;
        }
        if let Some(e) = self.episode.take() {
            let n = |r: Refusal| e.counts[r.index()];
            tracing::info!(
                busy = n(Refusal::Busy),
                evicted = n(Refusal::Evicted),
                timeout = n(Refusal::Timeout),
                too_large = n(Refusal::TooLarge),
                lasted_s = e.last.saturating_duration_since(e.started).as_secs(),
                "metrics endpoint: refusals stopped"
            );
        }
    }

    /// Accepts what waits in the backlog, making room or refusing beyond the cap.
    fn accept(&mut self, now: Instant) {
        for _ in 0..ACCEPTS_PER_TURN {
            let stream = match self.listener.accept() {
                Ok((stream, _)) => stream,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::Interrupted | std::io::ErrorKind::ConnectionAborted
                    ) =>
                {
                    continue
                }
                Err(e) => {
                    // Out of descriptors or memory: the connection stays in the backlog;
                    // rest a little rather than spin on it.
                    if self
                        .accept_error_logged
                        .is_none_or(|t| now.saturating_duration_since(t) >= EPISODE_QUIET)
                    {
                        tracing::warn!(error = %e, "metrics endpoint: cannot accept");
                        self.accept_error_logged = Some(now);
                    }
                    self.listener_rests_until = Some(now + ACCEPT_BACKOFF);
                    return;
                }
            };
            if self.conns.len() >= MAX_CONNECTIONS && !self.make_room(now) {
                // Dropped: closed at once.
                drop(stream);
                self.refused(Refusal::Busy, now);
                continue;
            }
            if let Err(e) = stream.set_nonblocking(true) {
                tracing::debug!(error = %e, "metrics connection dropped");
                continue;
            }
            self.conns.push(Conn {
                stream,
                accepted: now,
                state: State::Reading { buf: Vec::new() },
            });
        }
    }

    /// Closes the oldest connection that has not sent a whole request (one being closed
    /// already first); false if every slot is answering a request.
    fn make_room(&mut self, now: Instant) -> bool {
        let oldest = |draining: bool| {
            self.conns
                .iter()
                .enumerate()
                .filter(|(_, c)| c.evictable())
                .filter(|(_, c)| matches!(c.state, State::Draining { .. }) == draining)
                .min_by_key(|(_, c)| c.accepted)
                .map(|(i, _)| i)
        };
        if let Some(i) = oldest(true) {
            self.close(i, None, now);
            true
        } else if let Some(i) = oldest(false) {
            self.close(i, Some(Refusal::Evicted), now);
            true
        } else {
            false
        }
    }

    /// Serves connection `i`, ready for its state's event.
    fn serve_conn(&mut self, i: usize, now: Instant) -> Next {
        let registry = &self.registry;
        let (instance, dir) = (self.instance.as_str(), self.dir.as_path());
        let conn = &mut self.conns[i];
        loop {
            match &mut conn.state {
                State::Reading { buf } => {
                    let response = match read_head(&mut conn.stream, buf) {
                        Head::Pending => return Next::Keep,
                        Head::Gone => return Next::Close(None),
                        Head::Complete(end) => {
                            respond(buf.get(..end).unwrap_or_default(), registry, instance, dir)
                        }
                        Head::TooLarge => {
                            // Counted now; the answer still goes out.
                            note_refusal(&self.stats, &mut self.episode, Refusal::TooLarge, now);
                            response(
                                431,
                                "Request Header Fields Too Large",
                                "request too large\n",
                                "text/plain",
                            )
                        }
                    };
                    conn.state = State::Writing {
                        out: response,
                        sent: 0,
                        last_progress: now,
                        deadline: now + RESPONSE_TIMEOUT,
                    };
                    // Written at once: most responses fit in the socket's buffer.
                }
                State::Writing {
                    out,
                    sent,
                    last_progress,
                    ..
                } => {
                    match write_some(&mut conn.stream, out, sent) {
                        Written::Pending { progressed } => {
                            if progressed {
                                *last_progress = now;
                            }
                            return Next::Keep;
                        }
                        Written::Gone => return Next::Close(None),
                        Written::All => {}
                    }
                    // Whole: no more output; what the peer still sends is read and dropped.
                    let _ = conn.stream.shutdown(Shutdown::Write);
                    conn.state = State::Draining {
                        until: now + LINGER,
                        drained: 0,
                    };
                }
                State::Draining { drained, .. } => {
                    let mut scratch = [0u8; 4096];
                    loop {
                        match conn.stream.read(&mut scratch) {
                            Ok(0) => return Next::Close(None),
                            Ok(n) => {
                                *drained += n;
                                if *drained > LINGER_BYTES {
                                    return Next::Close(None);
                                }
                            }
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                                return Next::Keep
                            }
                            Err(_) => return Next::Close(None),
                        }
                    }
                }
            }
        }
    }
}

/// Counts a refusal; logs it if it starts an episode.
fn note_refusal(stats: &ServerStats, episode: &mut Option<Episode>, reason: Refusal, now: Instant) {
    stats.count(reason);
    match episode {
        Some(e) => {
            e.last = now;
            e.counts[reason.index()] += 1;
        }
        None => {
            tracing::warn!(
                reason = reason.label(),
                max_connections = MAX_CONNECTIONS,
                max_request_bytes = MAX_REQUEST_BYTES,
                "metrics endpoint: refusing connections (too many at once, too slow, or too \
                 large); counted in xrce_metrics_connections_refused_total, logged again when \
                 it stops"
            );
            let mut counts = [0; Refusal::ALL.len()];
            counts[reason.index()] = 1;
            *episode = Some(Episode {
                started: now,
                last: now,
                counts,
            });
        }
    }
}

/// What reading a request head found.
enum Head {
    /// Not whole yet.
    Pending,
    /// Whole: it ends at this offset of the buffer (its blank line included).
    Complete(usize),
    /// Over [`MAX_REQUEST_BYTES`].
    TooLarge,
    /// The peer closed, or the connection failed, before a whole request.
    Gone,
}

/// Reads what the peer sent into `buf`, up to the end of the request head.
fn read_head(stream: &mut TcpStream, buf: &mut Vec<u8>) -> Head {
    let mut chunk = [0u8; 4096];
    loop {
        // At most MAX_REQUEST_BYTES + 1 bytes are kept: enough to tell "too large".
        let room = (MAX_REQUEST_BYTES + 1).saturating_sub(buf.len());
        let want = room.min(chunk.len());
        if want == 0 {
            return Head::TooLarge;
        }
        match stream.read(&mut chunk[..want]) {
            Ok(0) => return Head::Gone,
            Ok(n) => {
                let from = buf.len().saturating_sub(3);
                buf.extend_from_slice(&chunk[..n]);
                if let Some(end) = head_end(buf, from) {
                    return if end > MAX_REQUEST_BYTES {
                        Head::TooLarge
                    } else {
                        Head::Complete(end)
                    };
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return Head::Pending,
            Err(_) => return Head::Gone,
        }
    }
}

/// The end of a request head (after its blank line, `\r\n\r\n` or a bare `\n\n`) found at
/// or after `from`.
fn head_end(buf: &[u8], from: usize) -> Option<usize> {
    let tail = buf.get(from..)?;
    tail.windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map(|p| from + p + 4)
        .or_else(|| {
            tail.windows(2)
                .position(|w| w == b"\n\n")
                .map(|p| from + p + 2)
        })
}

/// What writing found.
enum Written {
    /// The socket is full; `progressed` if some bytes went out.
    Pending { progressed: bool },
    /// Everything is out.
    All,
    /// The connection failed.
    Gone,
}

fn write_some(stream: &mut TcpStream, out: &[u8], sent: &mut usize) -> Written {
    let mut progressed = false;
    while let Some(rest) = out.get(*sent..).filter(|r| !r.is_empty()) {
        match stream.write(rest) {
            Ok(0) => return Written::Gone,
            Ok(n) => {
                *sent += n;
                progressed = true;
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                return Written::Pending { progressed }
            }
            Err(_) => return Written::Gone,
        }
    }
    Written::All
}

/// An HTTP/1.1 response that closes the connection.
fn response(code: u16, reason: &str, body: &str, content_type: &str) -> Vec<u8> {
    let mut out = format!(
        "HTTP/1.1 {code} {reason}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\n\
         Connection: close\r\n{}\r\n",
        body.len(),
        if code == 405 { "Allow: GET\r\n" } else { "" },
    )
    .into_bytes();
    out.extend_from_slice(body.as_bytes());
    out
}

/// The response to a request head (request line and headers, from the peer: anything).
fn respond(head: &[u8], registry: &Registry, instance: &str, dir: &std::path::Path) -> Vec<u8> {
    let line_end = head.iter().position(|&b| b == b'\n').unwrap_or(head.len());
    let line = head.get(..line_end).unwrap_or_default();
    let Ok(line) = std::str::from_utf8(line) else {
        return response(400, "Bad Request", "bad request\n", "text/plain");
    };
    let mut parts = line.trim_end_matches('\r').split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return response(400, "Bad Request", "bad request\n", "text/plain");
    };
    if !version.starts_with("HTTP/1.") {
        return response(
            505,
            "HTTP Version Not Supported",
            "HTTP/1.x only\n",
            "text/plain",
        );
    }
    if method != "GET" {
        return response(405, "Method Not Allowed", "only GET\n", "text/plain");
    }
    let path = target.split('?').next().unwrap_or_default();
    match path {
        "/metrics" => {
            let mut out = String::new();
            match prometheus_client::encoding::prometheus_text::encode(&mut out, registry) {
                Ok(()) => response(
                    200,
                    "OK",
                    &out,
                    prometheus_client::encoding::prometheus_text::CONTENT_TYPE,
                ),
                Err(_) => response(
                    500,
                    "Internal Server Error",
                    "encoding failed\n",
                    "text/plain",
                ),
            }
        }
        "/status" => {
            let mut snapshot = AgentStatus::read(instance, dir);
            // Client keys are the clients' credentials: shown only when asked for.
            let show_keys = target
                .split_once('?')
                .is_some_and(|(_, q)| q.split('&').any(|p| p == "keys=show"));
            if !show_keys {
                snapshot.redact_keys();
            }
            match serde_json::to_string_pretty(&snapshot) {
                Ok(json) => response(200, "OK", &json, "application/json"),
                Err(e) => response(
                    500,
                    "Internal Server Error",
                    &format!("{e}\n"),
                    "text/plain",
                ),
            }
        }
        "/" => response(
            200,
            "OK",
            "xrce-agent: /metrics (Prometheus), /status (JSON)\n",
            "text/plain",
        ),
        _ => response(
            404,
            "Not Found",
            "not found: try /metrics or /status\n",
            "text/plain",
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;
    use xrce_ipc::status::{ChildStatus, FrontendStatus, WorkerStatus};

    fn snapshot() -> AgentStatus {
        AgentStatus {
            instance: "t".into(),
            processes: vec![
                ProcessReport {
                    name: "supervisor".into(),
                    role: "supervisor".into(),
                    children: vec![
                        ChildStatus {
                            name: "xrce-dds-worker".into(),
                            role: "worker".into(),
                            restarts: 2,
                            memory_kills: 1,
                            ..Default::default()
                        },
                        ChildStatus {
                            name: "xrce-frontend-udp4-8888".into(),
                            role: "frontend".into(),
                            restarts: 1,
                            ..Default::default()
                        },
                    ],
                    ..Default::default()
                },
                ProcessReport {
                    name: "worker".into(),
                    role: "worker".into(),
                    cpu_seconds: 1.5,
                    worker: Some(WorkerStatus {
                        entities: BTreeMap::from([("writer".to_string(), 3)]),
                        dropped: BTreeMap::from([("frontend_gone".to_string(), 1)]),
                        ..Default::default()
                    }),
                    ..Default::default()
                },
                ProcessReport {
                    name: "udp4-8888".into(),
                    role: "frontend".into(),
                    resident_bytes: 4096,
                    frontend: Some(FrontendStatus {
                        transport: "udp4".into(),
                        connected: true,
                        counters: BTreeMap::from([("samples_written".to_string(), 42)]),
                        dropped: BTreeMap::from([("bad_header".to_string(), 5)]),
                        sessions: vec![Default::default(), Default::default()],
                        ..Default::default()
                    }),
                    ..Default::default()
                },
            ],
        }
    }

    #[test]
    fn the_exposition_names_counters_with_total_and_labels_them() {
        let text = render(&snapshot()).expect("render");
        for line in [
            "# TYPE xrce_sessions gauge",
            "xrce_sessions{frontend=\"udp4-8888\",transport=\"udp4\"} 2",
            "# TYPE xrce_samples_written_total counter",
            "xrce_samples_written_total{frontend=\"udp4-8888\",transport=\"udp4\"} 42",
            "xrce_samples_delivered_total{frontend=\"udp4-8888\",transport=\"udp4\"} 0",
            "xrce_dropped_total{process=\"udp4-8888\",reason=\"bad_header\"} 5",
            "xrce_dropped_total{process=\"worker\",reason=\"frontend_gone\"} 1",
            "xrce_worker_restarts_total 2",
            "xrce_memory_limit_kills_total{process=\"worker\"} 1",
            "xrce_frontend_restarts_total{frontend=\"udp4-8888\"} 1",
            "xrce_worker_entities{kind=\"writer\"} 3",
            "xrce_process_cpu_seconds_total{process=\"worker\"} 1.5",
            "xrce_process_resident_memory_bytes{process=\"udp4-8888\"} 4096",
            "xrce_frontend_connected{frontend=\"udp4-8888\",transport=\"udp4\"} 1",
        ] {
            assert!(
                text.lines().any(|l| l == line),
                "missing {line:?} in:\n{text}"
            );
        }
    }

    #[test]
    fn a_frontend_is_connected_only_to_the_running_workers_generation() {
        let connected = |s: &AgentStatus| {
            let text = render(s).expect("render");
            let line = text
                .lines()
                .find(|l| l.starts_with("xrce_frontend_connected{"))
                .map(str::to_string);
            line.expect("connected gauge").ends_with(" 1")
        };
        let mut s = snapshot();
        let set = |s: &mut AgentStatus, fe: Option<u32>, worker: u32| {
            for p in &mut s.processes {
                if let Some(f) = &mut p.frontend {
                    f.generation = fe;
                }
                if let Some(w) = &mut p.worker {
                    w.generation = worker;
                }
            }
        };
        set(&mut s, Some(6), 6);
        assert!(connected(&s));
        // The worker was restarted and the front-end has not seen the new one yet.
        set(&mut s, Some(6), 7);
        assert!(!connected(&s));
        // The worker is gone (its report is read only while it lives).
        set(&mut s, Some(6), 6);
        s.processes.retain(|p| p.worker.is_none());
        assert!(!connected(&s));
    }

    /// A server on an ephemeral loopback port, serving for ever from a thread of its own,
    /// with no report to read (its directory does not exist).
    fn start() -> (SocketAddr, Arc<ServerStats>) {
        let dir = std::env::temp_dir().join(format!(
            "xrce-metrics-test-no-reports-{}",
            std::process::id()
        ));
        let listen = "127.0.0.1:0".parse().expect("address");
        let server = Server::bind(listen, "t", dir).expect("bind");
        let addr = server.local_addr().expect("bound address");
        let stats = server.stats();
        std::thread::spawn(move || server.run());
        (addr, stats)
    }

    /// Far longer than any deadline of the server: a test fails, it does not hang.
    const CLIENT_TIMEOUT: Duration = Duration::from_secs(15);

    /// Sends `request` on a new connection and reads the response until the server closes.
    fn exchange(addr: SocketAddr, request: &[u8]) -> std::io::Result<String> {
        let mut s = TcpStream::connect(addr)?;
        s.set_read_timeout(Some(CLIENT_TIMEOUT))?;
        s.write_all(request)?;
        let mut out = Vec::new();
        s.read_to_end(&mut out)?;
        Ok(String::from_utf8_lossy(&out).into_owned())
    }

    /// A response's head and body.
    fn split(response: &str) -> (&str, &str) {
        response.split_once("\r\n\r\n").expect("a head and a body")
    }

    const SCRAPE: &[u8] = b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: */*\r\n\r\n";

    #[test]
    fn idle_connections_do_not_lock_a_scrape_out() {
        let (addr, stats) = start();
        let mut idle: Vec<TcpStream> = (0..40)
            .map(|_| TcpStream::connect(addr).expect("connect"))
            .collect();
        // The 41st connection, a scrape, is answered while the 40 are still open.
        let response = exchange(addr, SCRAPE).expect("the scrape is answered");
        assert!(response.starts_with("HTTP/1.1 200 OK\r\n"), "{response}");
        assert!(split(&response)
            .1
            .contains("xrce_metrics_connections_refused_total{reason=\"evicted\"}"));
        // At most MAX_CONNECTIONS were open when the scrape was: the others were closed to
        // make room (or, on a very slow machine, timed out).
        let closed = stats.refused(Refusal::Evicted) + stats.refused(Refusal::Timeout);
        assert!(
            closed >= (41 - MAX_CONNECTIONS) as u64,
            "only {closed} idle connections closed"
        );
        // And none of the idle ones holds a slot for long: each is closed by the server.
        for s in &mut idle {
            s.set_read_timeout(Some(CLIENT_TIMEOUT)).expect("timeout");
            let mut byte = [0u8; 1];
            match s.read(&mut byte) {
                Ok(0) => {}
                Ok(_) => panic!("an idle connection got data"),
                Err(e) => assert!(
                    !matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ),
                    "an idle connection is still open: {e}"
                ),
            }
        }
        assert!(stats.refused(Refusal::Evicted) + stats.refused(Refusal::Timeout) >= 40);
        assert_eq!(stats.refused(Refusal::Busy), 0);
    }

    #[test]
    fn a_request_dribbled_byte_by_byte_is_cut_at_the_request_timeout() {
        let (addr, stats) = start();
        let mut s = TcpStream::connect(addr).expect("connect");
        s.set_read_timeout(Some(Duration::from_millis(100)))
            .expect("timeout");
        let started = Instant::now();
        let mut closed = false;
        // A request line, a byte every 100 ms, never the blank line that ends the head.
        for &b in b"GET /metrics HTTP/1.1\r\nX-Slow: ".iter().cycle() {
            if started.elapsed() > CLIENT_TIMEOUT {
                break;
            }
            if s.write_all(&[b]).is_err() {
                closed = true;
                break;
            }
            let mut byte = [0u8; 1];
            match s.read(&mut byte) {
                Ok(0) => {
                    closed = true;
                    break;
                }
                Ok(_) => panic!("a partial request was answered"),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(_) => {
                    closed = true;
                    break;
                }
            }
        }
        assert!(closed, "the server never closed a dribbling connection");
        assert!(stats.refused(Refusal::Timeout) >= 1);
    }

    #[test]
    fn a_request_over_the_size_cap_is_refused() {
        let (addr, stats) = start();
        // A head that never ends within the cap.
        let mut request = b"GET /metrics HTTP/1.1\r\nX-Filler: ".to_vec();
        request.resize(MAX_REQUEST_BYTES + 1024, b'a');
        let response = exchange(addr, &request).expect("answered");
        assert!(
            response.starts_with("HTTP/1.1 431 "),
            "{}",
            &response[..response.len().min(200)]
        );
        assert!(
            !response.contains("xrce_"),
            "metrics sent to a refused request"
        );
        assert_eq!(stats.refused(Refusal::TooLarge), 1);
        // A whole head, but over the cap.
        request.extend_from_slice(b"\r\n\r\n");
        let response = exchange(addr, &request).expect("answered");
        assert!(response.starts_with("HTTP/1.1 431 "));
        assert_eq!(stats.refused(Refusal::TooLarge), 2);
        // Just under the cap is served.
        let mut request = b"GET /metrics HTTP/1.1\r\nX-Filler: ".to_vec();
        request.resize(MAX_REQUEST_BYTES - 4, b'a');
        request.extend_from_slice(b"\r\n\r\n");
        let response = exchange(addr, &request).expect("answered");
        assert!(response.starts_with("HTTP/1.1 200 OK\r\n"));
        assert_eq!(stats.refused(Refusal::TooLarge), 2);
    }

    #[test]
    fn a_scrape_gets_the_metrics_text_and_the_status() {
        let (addr, stats) = start();
        let response = exchange(addr, SCRAPE).expect("answered");
        let (head, body) = split(&response);
        assert!(head.starts_with("HTTP/1.1 200 OK\r\n"), "{head}");
        let content_type = format!(
            "Content-Type: {}",
            prometheus_client::encoding::prometheus_text::CONTENT_TYPE
        );
        assert!(head.lines().any(|l| l == content_type), "{head}");
        assert!(head
            .lines()
            .any(|l| l == format!("Content-Length: {}", body.len())));
        assert!(head.lines().any(|l| l == "Connection: close"));
        for reason in ["busy", "evicted", "timeout", "too_large"] {
            let line = format!("xrce_metrics_connections_refused_total{{reason=\"{reason}\"}} 0");
            assert!(
                body.lines().any(|l| l == line),
                "missing {line:?} in:\n{body}"
            );
        }
        assert!(
            body.lines()
                .any(|l| l == "# TYPE xrce_metrics_connections_refused_total counter"),
            "{body}"
        );
        // The status document, query string ignored.
        let response = exchange(addr, b"GET /status?x=1 HTTP/1.0\r\n\r\n").expect("answered");
        let (head, body) = split(&response);
        assert!(head.starts_with("HTTP/1.1 200 OK\r\n"), "{head}");
        let status: AgentStatus = serde_json::from_str(body).expect("a status document");
        assert_eq!(status.instance, "t");
        // Anything else.
        let response = exchange(addr, b"GET /nothing HTTP/1.1\r\n\r\n").expect("answered");
        assert!(response.starts_with("HTTP/1.1 404 "));
        let response = exchange(addr, b"POST /metrics HTTP/1.1\r\n\r\n").expect("answered");
        assert!(response.starts_with("HTTP/1.1 405 "));
        let response = exchange(addr, b"\xff\xfe garbage\r\n\r\n").expect("answered");
        assert!(response.starts_with("HTTP/1.1 400 "));
        for r in Refusal::ALL {
            assert_eq!(stats.refused(r), 0, "{r:?}");
        }
    }

    #[test]
    fn status_keys_are_redacted_unless_asked_for() {
        let mut s = snapshot();
        let key = |s: &AgentStatus| {
            s.processes
                .iter()
                .filter_map(|p| p.frontend.as_ref())
                .flat_map(|f| f.sessions.iter())
                .map(|x| x.client_key.clone())
                .collect::<Vec<_>>()
        };
        for p in &mut s.processes {
            if let Some(f) = &mut p.frontend {
                for x in &mut f.sessions {
                    x.client_key = "0xAAAABBBB".into();
                }
            }
        }
        assert!(!key(&s).is_empty());
        s.redact_keys();
        assert!(key(&s).iter().all(|k| k == "0x****BBBB"), "{:?}", key(&s));
    }

    #[test]
    fn the_status_document_round_trips() {
        let s = snapshot();
        let json = serde_json::to_string(&s).expect("encode");
        let back: AgentStatus = serde_json::from_str(&json).expect("decode");
        assert_eq!(back, s);
    }
}
