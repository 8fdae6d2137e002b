//! The endpoint's bounded HTTP server: one thread, no thread per connection, every
//! connection's slot, time and bytes bounded (the limits are the constants below).

use nix::poll::{poll, PollFd, PollFlags};
use prometheus_client::collector::Collector;
use prometheus_client::encoding::DescriptorEncoder;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::os::fd::AsFd;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use xrce_ipc::status::{self};

use super::{AgentStatus, Family, StatusCollector};

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
    pub(super) const ALL: [Refusal; 4] = [
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
                            let stream = &conn.stream;
                            let own_user = || match (stream.peer_addr(), stream.local_addr()) {
                                (Ok(peer), Ok(local)) => peer_is_own_user(peer, local),
                                _ => false,
                            };
                            respond(
                                buf.get(..end).unwrap_or_default(),
                                registry,
                                instance,
                                dir,
                                &own_user,
                            )
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
/// Whether the process at `peer` (a TCP connection to `local`) runs as this process's user:
/// its socket's owner in the kernel's table of this network namespace (`/proc/net/tcp`,
/// `tcp6`). Not found (another host, another namespace): no.
fn peer_is_own_user(peer: SocketAddr, local: SocketAddr) -> bool {
    let canonical = |a: SocketAddr| match a {
        SocketAddr::V6(v6) => match v6.ip().to_ipv4_mapped() {
            Some(v4) => SocketAddr::new(v4.into(), v6.port()),
            None => a,
        },
        v4 => v4,
    };
    let (peer, local) = (canonical(peer), canonical(local));
    let me = xrce_ipc::runtime_dir::euid();
    [procfs::net::tcp(), procfs::net::tcp6()]
        .into_iter()
        .flatten()
        .flatten()
        .find(|e| canonical(e.local_address) == peer && canonical(e.remote_address) == local)
        .is_some_and(|e| e.uid == me)
}

fn respond(
    head: &[u8],
    registry: &Registry,
    instance: &str,
    dir: &std::path::Path,
    own_user: &dyn Fn() -> bool,
) -> Vec<u8> {
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
            // Client keys are the clients' credentials: shown only when asked for, and only
            // to a process of the agent's own user (whoever else may connect to a loopback
            // port gets them redacted, as with the default).
            let show_keys = target
                .split_once('?')
                .is_some_and(|(_, q)| q.split('&').any(|p| p == "keys=show"))
                && own_user();
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
