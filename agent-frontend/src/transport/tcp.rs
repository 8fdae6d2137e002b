//! TCP over IPv4 or IPv6: a listener and one connection per client, each XRCE message with a
//! 2-byte little-endian length prefix ([`xrce_common::framing::length_prefix`]).
//!
//! Bounded per connection: the receive buffer holds at most one message being completed,
//! the send buffer at most [`TcpConfig::send_buffer`] bytes. A client that does not read
//! (its kernel buffer full, then ours) first loses best-effort output (counted), then is
//! disconnected (counted), so one stuck client never holds memory or blocks the others. A
//! connection that sends no whole message within [`TcpConfig::first_message_limit`] of
//! opening, or takes longer than [`TcpConfig::frame_limit`] to finish a message it began
//! (however slowly it trickles bytes), is closed too, and so is one idle (nothing in, nothing out) for
//! [`TcpConfig::idle_timeout`]. At most [`TcpConfig::max_connections`] are served, at most
//! [`TcpConfig::max_per_address`] from one address; a connection beyond the first bound
//! takes the place of the oldest connection that has sent no whole message yet from the
//! address with the most connections (when that is not its own address), else it is closed
//! at once, with a log line per episode. Each connection gets at most [`READ_BUDGET`] bytes
//! read per loop pass, so a fast sender cannot starve the others.

use std::collections::{HashMap, VecDeque};
use std::io::{IoSlice, Read, Write};
use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

use mio::event::Event;
use mio::{Interest, Registry, Token};
use xrce_common::framing::length_prefix::{self, LengthPrefixDecoder};
use xrce_common::session::budget::{ip_origin, Origin, OriginId};
use xrce_common::wire::info::TransportLocator;

use super::{is_gone, Transport, TransportStats};

/// Limits of the TCP transport.
#[derive(Debug, Clone)]
pub struct TcpConfig {
    /// Connections served at once; more are closed as they arrive.
    pub max_connections: usize,
    /// Bytes waiting to be written to one connection before it is closed as stuck.
    pub send_buffer: usize,
    /// Largest message accepted (at most 65,535, what the prefix can say); a longer one
    /// closes its connection.
    pub max_message: usize,
    /// Connections from one source address served at once.
    pub max_per_address: usize,
    /// A connection with nothing received and nothing sent for this long is closed.
    pub idle_timeout: Option<Duration>,
    /// A connection that sends no whole message this long after opening is closed.
    pub first_message_limit: Duration,
    /// A message must arrive whole this long after its first bytes, or its connection is
    /// closed: trickling a byte now and then holds nothing.
    pub frame_limit: Duration,
    /// Bytes every connection's receive and send buffers may hold together; beyond, the
    /// connections of the address holding the most are closed, the largest first (counted
    /// as `tcp_memory_budget`). A share of the front-end's `--memory-budget`.
    pub memory_budget: usize,
}

impl Default for TcpConfig {
    fn default() -> Self {
        TcpConfig {
            // Worst case 2,000 × (64 KiB being received + 128 KiB unsent) = 384 MiB.
            max_connections: 2_000,
            send_buffer: 128 << 10,
            max_message: length_prefix::MAX_MESSAGE,
            max_per_address: 256,
            idle_timeout: Some(Duration::from_secs(300)),
            first_message_limit: FIRST_MESSAGE_LIMIT,
            frame_limit: FRAME_LIMIT,
            memory_budget: DEFAULT_BUFFER_BUDGET,
        }
    }
}

/// One connection, as the session core knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TcpEndpoint {
    slot: u32,
    generation: u32,
    /// The peer's address (the session core shares resources between addresses).
    ip: IpAddr,
}

impl Origin for TcpEndpoint {
    fn origin(&self) -> OriginId {
        ip_origin(self.ip)
    }
    fn ip(&self) -> Option<IpAddr> {
        Some(self.ip)
    }
}

#[derive(Debug)]
struct Connection {
    stream: mio::net::TcpStream,
    peer: SocketAddr,
    generation: u32,
    decoder: LengthPrefixDecoder,
    /// Framed bytes not written yet, from `out_start` on.
    out: Vec<u8>,
    out_start: usize,
    /// Registered for writability (only while `out` holds something).
    writable: bool,
    /// In the transport's ready list.
    queued: bool,
    opened_at: Instant,
    /// When bytes last arrived.
    last_input: Instant,
    /// When bytes were last written to it.
    last_output: Instant,
    /// When the message being received began (its first bytes arrived).
    frame_started: Option<Instant>,
    /// Whole messages received.
    delivered: u64,
    /// Bytes of its buffers as last counted in the transport's total.
    weight: usize,
}

impl Connection {
    fn endpoint(&self, slot: u32) -> TcpEndpoint {
        TcpEndpoint {
            slot,
            generation: self.generation,
            ip: self.peer.ip(),
        }
    }
}

impl Connection {
    fn pending_out(&self) -> usize {
        self.out.len() - self.out_start
    }

    /// Writes buffered output; `Err` when the connection is gone.
    fn flush(&mut self) -> std::io::Result<()> {
        while self.out_start < self.out.len() {
            match self.stream.write(&self.out[self.out_start..]) {
                Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
                Ok(n) => self.out_start += n,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        if self.out_start == self.out.len() {
            self.out.clear();
            self.out_start = 0;
            // What an idle connection keeps counts in the buffers' budget: little.
            if self.out.capacity() > 4 << 10 {
                self.out = Vec::new();
            }
        } else if self.out_start > self.out.len() / 2 {
            self.out.drain(..self.out_start);
            self.out_start = 0;
        }
        Ok(())
    }
}

/// The TCP transport.
#[derive(Debug)]
pub struct TcpTransport {
    listener: mio::net::TcpListener,
    local: SocketAddr,
    config: TcpConfig,
    slots: Vec<Option<Connection>>,
    free: Vec<u32>,
    live: usize,
    next_generation: u32,
    registry: Option<Registry>,
    first_token: usize,
    accept_ready: bool,
    /// Accepting paused (out of descriptors) until then.
    accept_retry: Option<Instant>,
    ready: VecDeque<u32>,
    closed: VecDeque<TcpEndpoint>,
    next_sweep: Instant,
    stats: TransportStats,
    /// Open connections per peer host (an IPv6 /64 is one host: [`ip_origin`]).
    per_address: HashMap<OriginId, usize>,
    /// Refusals logged once per episode.
    episodes: xrce_common::session::budget::Episodes,
    /// Bytes of every connection's buffers ([`TcpConfig::memory_budget`]).
    held: usize,
}

/// Why a connection was closed by us (counted as drops; a peer's own close is not one).
const STUCK: &str = "tcp_send_buffer_overflow";
const TOO_LONG: &str = "tcp_frame_too_long";
const REFUSED: &str = "tcp_connection_refused";
const SILENT: &str = "tcp_silent_connection";
const STALLED: &str = "tcp_stalled_message";
const IDLE: &str = "tcp_idle_connection";
const PER_ADDRESS: &str = "tcp_connection_refused_per_address";
const DISPLACED: &str = "tcp_connection_displaced";

/// Default [`TcpConfig::memory_budget`]: a quarter of the default `--memory-budget`.
pub const DEFAULT_BUFFER_BUDGET: usize = 16 << 20;
const OVER_BUDGET: &str = "tcp_memory_budget";

/// Bytes read from one connection per loop pass before the others get a turn.
pub const READ_BUDGET: usize = 256 << 10;
/// Default [`TcpConfig::first_message_limit`].
pub const FIRST_MESSAGE_LIMIT: Duration = Duration::from_secs(10);
/// Default [`TcpConfig::frame_limit`] (a 64 KiB message then needs 6.6 KB/s).
pub const FRAME_LIMIT: Duration = Duration::from_secs(10);
/// How often connections are checked against the limits above.
const SWEEP_PERIOD: Duration = Duration::from_secs(1);
/// Accept errors tolerated in one pass (aborted handshakes and the like) before the
/// listener waits for the next retry.
const ACCEPT_ERRORS_PER_PASS: usize = 64;

/// Whether an XRCE message travels on a best-effort stream (its header's stream id, the
/// second octet, is 1 to 127): such output may be dropped rather than queued for ever.
fn is_best_effort(message: &[u8]) -> bool {
    matches!(message.get(1), Some(1..=0x7F))
}

impl super::StoredEndpoint for TcpEndpoint {
    fn stored(&self) -> Vec<u8> {
        // The connection closes with this process: the client connects again.
        Vec::new()
    }
}

impl TcpTransport {
    /// Serves clients on a bound listener.
    pub fn new(listener: std::net::TcpListener, config: TcpConfig) -> std::io::Result<Self> {
        listener.set_nonblocking(true)?;
        let local = listener.local_addr()?;
        Ok(TcpTransport {
            listener: mio::net::TcpListener::from_std(listener),
            local,
            config,
            slots: Vec::new(),
            free: Vec::new(),
            live: 0,
            next_generation: 0,
            registry: None,
            first_token: 0,
            accept_ready: true,
            accept_retry: None,
            ready: VecDeque::new(),
            closed: VecDeque::new(),
            next_sweep: Instant::now() + SWEEP_PERIOD,
            stats: TransportStats::default(),
            per_address: HashMap::new(),
            episodes: Default::default(),
            held: 0,
        })
    }

    /// The address served.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Connections open now.
    pub fn connections(&self) -> usize {
        self.live
    }

    /// Bytes held in the connections' receive and send buffers (what
    /// [`TcpConfig::memory_budget`] bounds).
    pub fn buffered_capacity(&self) -> usize {
        self.slots
            .iter()
            .flatten()
            .map(|c| c.decoder.capacity() + c.out.capacity())
            .sum()
    }

    /// Counts a connection's buffers again after they may have grown or shrunk.
    fn reweigh(&mut self, slot: u32) {
        if let Some(c) = self.slots.get_mut(slot as usize).and_then(Option::as_mut) {
            let now = c.decoder.capacity() + c.out.capacity();
            self.held = self.held - c.weight + now;
            c.weight = now;
        }
    }

    /// Keeps the buffers within [`TcpConfig::memory_budget`]: while over it, closes the
    /// connection holding the most of the address holding the most (a flood of frames that
    /// never end, from one place, pays first; a client elsewhere keeps its connection).
    fn keep_within_budget(&mut self) {
        while self.held > self.config.memory_budget {
            let mut by_origin: HashMap<OriginId, usize> = HashMap::new();
            for c in self.slots.iter().flatten() {
                *by_origin.entry(ip_origin(c.peer.ip())).or_default() += c.weight;
            }
            let Some((&busiest, &bytes)) = by_origin.iter().max_by_key(|(o, b)| (**b, **o)) else {
                return;
            };
            let victim = self
                .slots
                .iter()
                .enumerate()
                .filter_map(|(slot, c)| c.as_ref().map(|c| (slot, c)))
                .filter(|(_, c)| ip_origin(c.peer.ip()) == busiest)
                .max_by_key(|(_, c)| (c.weight, std::cmp::Reverse(c.opened_at)))
                .map(|(slot, _)| slot as u32);
            let Some(victim) = victim else {
                return;
            };
            if self.episodes.bite(Instant::now(), OVER_BUDGET).is_some() {
                tracing::warn!(from = %busiest, held_by_it = bytes, held = self.held, budget = self.config.memory_budget, "TCP buffers over their share of the memory budget: the largest connection of the address holding the most closed (logged once per episode)");
            }
            self.close(
                victim,
                Some(OVER_BUDGET),
                "its address held the most of the TCP buffers' memory budget",
            );
        }
    }

    fn token(&self, slot: u32) -> Token {
        Token(self.first_token + 1 + slot as usize)
    }

    fn queue_read(&mut self, slot: u32) {
        if let Some(c) = self.slots.get_mut(slot as usize).and_then(Option::as_mut) {
            if !c.queued {
                c.queued = true;
                self.ready.push_back(slot);
            }
        }
    }

    /// Closes a connection; `reason` is counted as a drop unless the peer closed it.
    fn close(&mut self, slot: u32, reason: Option<&'static str>, detail: &str) {
        let Some(mut c) = self.slots.get_mut(slot as usize).and_then(Option::take) else {
            return;
        };
        if let Some(r) = &self.registry {
            let _ = r.deregister(&mut c.stream);
        }
        self.free.push(slot);
        self.live -= 1;
        self.stats.closed += 1;
        self.held -= c.weight;
        let host = ip_origin(c.peer.ip());
        if let Some(n) = self.per_address.get_mut(&host) {
            *n -= 1;
            if *n == 0 {
                self.per_address.remove(&host);
            }
        }
        self.closed.push_back(c.endpoint(slot));
        let age_ms = c.opened_at.elapsed().as_millis() as u64;
        match reason {
            Some(reason) => {
                let n = self.stats.drop(reason);
                if self.episodes.bite(Instant::now(), reason).is_some() {
                    tracing::warn!(peer = %c.peer, reason, detail, closed_for_this_reason = n, age_ms, "TCP connection closed (further closes for this reason are logged at debug until they stop for 10 s)");
                } else {
                    tracing::debug!(peer = %c.peer, reason, detail, closed_for_this_reason = n, age_ms, "TCP connection closed");
                }
            }
            None => tracing::debug!(peer = %c.peer, detail, age_ms, "TCP connection closed"),
        }
    }

    /// Makes room for a connection from `ip` when every slot is taken: closes the oldest
    /// connection that has sent no whole message yet of the address with the most
    /// connections, if that is another address with more connections than `ip` has (so a
    /// flood of unfinished connections from one place cannot keep others out). Whether
    /// one was closed.
    fn displace_for(&mut self, ip: IpAddr) -> bool {
        let ip = ip_origin(ip);
        let mine = self.per_address.get(&ip).copied().unwrap_or(0);
        let Some((&busiest, &n)) = self.per_address.iter().max_by_key(|(a, n)| (**n, **a)) else {
            return false;
        };
        if busiest == ip || n <= mine + 1 {
            return false;
        }
        let victim = self
            .slots
            .iter()
            .enumerate()
            .filter_map(|(slot, c)| c.as_ref().map(|c| (slot, c)))
            .filter(|(_, c)| ip_origin(c.peer.ip()) == busiest && c.delivered == 0)
            .min_by_key(|(_, c)| c.opened_at)
            .map(|(slot, _)| slot as u32);
        let Some(victim) = victim else {
            return false;
        };
        if self.episodes.bite(Instant::now(), DISPLACED).is_some() {
            tracing::warn!(from = %busiest, connections = n, "TCP connections full: a connection that sent nothing whole yet, from the address with the most, closed for a newcomer (logged once per episode)");
        }
        self.close(
            victim,
            Some(DISPLACED),
            "displaced by a connection from another address",
        );
        true
    }

    fn accept(&mut self) {
        let mut errors = 0;
        loop {
            let (stream, peer) = match self.listener.accept() {
                Ok(s) => s,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    self.accept_ready = false;
                    return;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) if matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE)) => {
                    // Out of descriptors: pending connections wait in the backlog.
                    let n = self.stats.drop("tcp_accept_no_descriptors");
                    if n.is_power_of_two() {
                        tracing::error!(error = %e, connections = self.live, "cannot accept TCP connections: out of file descriptors (raise LimitNOFILE / ulimit -n)");
                    }
                    self.accept_ready = false;
                    self.accept_retry = Some(Instant::now() + Duration::from_millis(100));
                    return;
                }
                Err(e) => {
                    // ECONNABORTED and the like concern one connection, not the listener;
                    // others (ENOBUFS, ENOMEM) may repeat: then wait for the retry timer.
                    errors += 1;
                    let n = self.stats.drop("tcp_accept_failed");
                    if n.is_power_of_two() {
                        tracing::warn!(error = %e, failed = n, "accepting a TCP connection failed");
                    }
                    if errors >= ACCEPT_ERRORS_PER_PASS {
                        self.accept_ready = false;
                        self.accept_retry = Some(Instant::now() + Duration::from_millis(100));
                        return;
                    }
                    continue;
                }
            };
            let from_peer = self
                .per_address
                .get(&ip_origin(peer.ip()))
                .copied()
                .unwrap_or(0);
            if from_peer >= self.config.max_per_address {
                let n = self.stats.drop(PER_ADDRESS);
                if self.episodes.bite(Instant::now(), PER_ADDRESS).is_some() {
                    tracing::warn!(%peer, max = self.config.max_per_address, refused = n, "TCP connection refused: its address has its maximum of connections (--max-connections-per-address; logged once per episode)");
                }
                drop(stream);
                continue;
            }
            if self.live >= self.config.max_connections && !self.displace_for(peer.ip()) {
                let n = self.stats.drop(REFUSED);
                if self.episodes.bite(Instant::now(), REFUSED).is_some() {
                    tracing::warn!(%peer, max = self.config.max_connections, refused = n, "TCP connection refused: the front-end serves its maximum of connections (--max-connections) and none that sent nothing whole yet can make room (logged once per episode)");
                }
                drop(stream);
                continue;
            }
            if let Err(e) = stream.set_nodelay(true) {
                tracing::debug!(%peer, error = %e, "TCP_NODELAY");
            }
            let slot = match self.free.pop() {
                Some(s) => s,
                None => {
                    self.slots.push(None);
                    (self.slots.len() - 1) as u32
                }
            };
            let generation = self.next_generation;
            self.next_generation = self.next_generation.wrapping_add(1);
            let mut c = Connection {
                stream,
                peer,
                generation,
                decoder: LengthPrefixDecoder::new(self.config.max_message),
                out: Vec::new(),
                out_start: 0,
                writable: false,
                queued: false,
                opened_at: Instant::now(),
                last_input: Instant::now(),
                last_output: Instant::now(),
                frame_started: None,
                delivered: 0,
                weight: 0,
            };
            let token = self.token(slot);
            if let Some(r) = &self.registry {
                if let Err(e) = r.register(&mut c.stream, token, Interest::READABLE) {
                    tracing::warn!(%peer, error = %e, "could not watch a TCP connection");
                    self.free.push(slot);
                    continue;
                }
            }
            self.slots[slot as usize] = Some(c);
            self.live += 1;
            *self.per_address.entry(ip_origin(peer.ip())).or_default() += 1;
            self.stats.opened += 1;
            tracing::debug!(%peer, connections = self.live, "TCP connection accepted");
            // Data may have arrived before the registration.
            self.queue_read(slot);
        }
    }

    /// Reads one connection; returns how many messages it delivered, and whether it still
    /// has input (budget used up).
    fn read_connection(
        &mut self,
        slot: u32,
        budget: usize,
        deliver: &mut dyn FnMut(TcpEndpoint, &[u8]),
    ) -> (usize, bool) {
        let mut delivered = 0;
        let mut read = 0;
        let mut close: Option<(Option<&'static str>, String)> = None;
        let mut left = false;
        let Some(c) = self.slots.get_mut(slot as usize).and_then(Option::as_mut) else {
            return (0, false);
        };
        let ep = c.endpoint(slot);
        'read: loop {
            let before = delivered;
            // Whole messages first (some may be left from a budget used up).
            while let Some(m) = c.decoder.next_message() {
                match m {
                    Ok(msg) => {
                        deliver(ep, msg);
                        delivered += 1;
                        if delivered >= budget {
                            left = true;
                            break 'read;
                        }
                    }
                    Err(e) => {
                        close = Some((Some(TOO_LONG), e.to_string()));
                        break 'read;
                    }
                }
            }
            // The message being received (if any) began with the bytes that are left: its
            // time starts when the one before it was taken, or when its first bytes came.
            if c.decoder.buffered() == 0 {
                c.frame_started = None;
            } else if delivered > before || c.frame_started.is_none() {
                c.frame_started = Some(Instant::now());
            }
            if read >= READ_BUDGET {
                left = true;
                break;
            }
            match c.stream.read(c.decoder.spare()) {
                Ok(0) => {
                    close = Some((None, "closed by the client".into()));
                    break;
                }
                Ok(n) => {
                    c.decoder.filled(n);
                    read += n;
                    c.last_input = Instant::now();
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    close = Some((None, e.to_string()));
                    break;
                }
            }
        }
        self.stats.messages_in += delivered as u64;
        if let Some(c) = self.slots.get_mut(slot as usize).and_then(Option::as_mut) {
            c.delivered += delivered as u64;
        }
        self.reweigh(slot);
        if let Some((reason, detail)) = close {
            self.close(slot, reason, &detail);
            return (delivered, false);
        }
        (delivered, left)
    }
}

impl Transport for TcpTransport {
    type Endpoint = TcpEndpoint;

    fn name(&self) -> &'static str {
        if self.local.is_ipv4() {
            "tcp4"
        } else {
            "tcp6"
        }
    }

    fn max_message_size(&self) -> u16 {
        self.config.max_message.min(length_prefix::MAX_MESSAGE) as u16
    }

    fn register(&mut self, registry: &Registry, first_token: usize) -> std::io::Result<()> {
        self.first_token = first_token;
        registry.register(&mut self.listener, Token(first_token), Interest::READABLE)?;
        self.registry = Some(registry.try_clone()?);
        tracing::info!(local = %self.local, max_connections = self.config.max_connections, "TCP front-end listening");
        Ok(())
    }

    fn on_event(&mut self, event: &Event) {
        let token = event.token().0;
        if token == self.first_token {
            self.accept_ready = self.accept_retry.is_none();
            return;
        }
        let Some(slot) = token.checked_sub(self.first_token + 1) else {
            return;
        };
        let slot = slot as u32;
        if event.is_readable() || event.is_read_closed() || event.is_error() {
            self.queue_read(slot);
        }
        if event.is_writable() {
            let Some(c) = self.slots.get_mut(slot as usize).and_then(Option::as_mut) else {
                return;
            };
            let before = c.pending_out();
            let flushed = c.flush();
            if c.pending_out() < before {
                c.last_output = Instant::now();
            }
            let (empty, writable) = (c.pending_out() == 0, c.writable);
            match flushed {
                Err(e) => self.close(slot, None, &e.to_string()),
                Ok(()) if empty && writable => {
                    let token = self.token(slot);
                    if let (Some(r), Some(c)) = (
                        &self.registry,
                        self.slots.get_mut(slot as usize).and_then(Option::as_mut),
                    ) {
                        if r.reregister(&mut c.stream, token, Interest::READABLE)
                            .is_ok()
                        {
                            c.writable = false;
                        }
                    }
                }
                Ok(()) => {}
            }
            self.reweigh(slot);
        }
    }

    fn receive(
        &mut self,
        _now: Instant,
        budget: usize,
        deliver: &mut dyn FnMut(TcpEndpoint, &[u8]),
    ) -> bool {
        if self.accept_ready {
            self.accept();
        }
        let mut budget = budget;
        // Each connection gets a turn; one with more input goes to the back.
        for _ in 0..self.ready.len() {
            if budget == 0 {
                break;
            }
            let Some(slot) = self.ready.pop_front() else {
                break;
            };
            let (n, left) = self.read_connection(slot, budget, deliver);
            budget = budget.saturating_sub(n);
            self.keep_within_budget();
            match self.slots.get_mut(slot as usize).and_then(Option::as_mut) {
                Some(_) if left => self.ready.push_back(slot),
                Some(c) => c.queued = false,
                None => {}
            }
        }
        !self.ready.is_empty() || self.accept_ready
    }

    fn send(&mut self, to: TcpEndpoint, message: &[u8]) {
        let limit = self.config.send_buffer;
        let token = self.token(to.slot);
        let registry = self.registry.as_ref();
        let Some(c) = self
            .slots
            .get_mut(to.slot as usize)
            .and_then(Option::as_mut)
            .filter(|c| c.generation == to.generation)
        else {
            self.stats.drop("tcp_connection_gone");
            return;
        };
        let Ok(len) = u16::try_from(message.len()) else {
            self.stats.drop("message_too_long");
            return;
        };
        let prefix = len.to_le_bytes();
        let mut written = 0;
        if c.pending_out() == 0 {
            match c
                .stream
                .write_vectored(&[IoSlice::new(&prefix), IoSlice::new(message)])
            {
                Ok(n) => {
                    written = n;
                    c.last_output = Instant::now();
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    let detail = e.to_string();
                    let gone = is_gone(&e);
                    self.close(to.slot, (!gone).then_some("tcp_send_failed"), &detail);
                    return;
                }
            }
        }
        let total = prefix.len() + message.len();
        if written < total {
            if written == 0 && c.pending_out() > limit / 2 && is_best_effort(message) {
                // Half full: best-effort output is dropped first (the client loses samples
                // it would lose on a lossy link anyway) before the connection is given up.
                let n = self.stats.drop("tcp_best_effort_dropped");
                if n.is_power_of_two() {
                    tracing::debug!(peer = %c.peer, dropped = n, "best-effort output dropped for a slow TCP client");
                }
                return;
            }
            if c.pending_out() + (total - written) > limit {
                let detail = format!(
                    "{} bytes waiting for a client that does not read",
                    c.pending_out() + total - written
                );
                self.close(to.slot, Some(STUCK), &detail);
                return;
            }
            let framed = prefix.iter().chain(message).skip(written);
            c.out.extend(framed);
            if !c.writable {
                if let Some(r) = registry {
                    if r.reregister(
                        &mut c.stream,
                        token,
                        Interest::READABLE | Interest::WRITABLE,
                    )
                    .is_ok()
                    {
                        c.writable = true;
                    }
                }
            }
            self.reweigh(to.slot);
            self.keep_within_budget();
        }
        self.stats.messages_out += 1;
    }

    fn poll_closed(&mut self) -> Option<TcpEndpoint> {
        self.closed.pop_front()
    }

    fn poll_timeout(&self) -> Option<Instant> {
        let sweep = (self.live > 0).then_some(self.next_sweep);
        match (self.accept_retry, sweep) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    fn handle_timeout(&mut self, now: Instant) {
        if self.accept_retry.is_some_and(|t| t <= now) {
            self.accept_retry = None;
            self.accept_ready = true;
        }
        if now >= self.next_sweep {
            self.next_sweep = now + SWEEP_PERIOD;
            let (idle, first, frame) = (
                self.config.idle_timeout,
                self.config.first_message_limit,
                self.config.frame_limit,
            );
            let mut silent = Vec::new();
            for (slot, c) in self.slots.iter().enumerate() {
                let Some(c) = c else { continue };
                let since = |t: Instant| now.saturating_duration_since(t);
                if c.delivered == 0 && since(c.opened_at) > first {
                    silent.push((slot as u32, SILENT, "no whole message since it opened"));
                } else if c.decoder.buffered() > 0
                    && c.frame_started.is_some_and(|t| since(t) > frame)
                {
                    silent.push((
                        slot as u32,
                        STALLED,
                        "a message begun but not finished in time",
                    ));
                } else if idle.is_some_and(|d| since(c.last_input.max(c.last_output)) > d) {
                    silent.push((slot as u32, IDLE, "nothing received or sent for too long"));
                }
            }
            for (slot, reason, detail) in silent {
                self.close(slot, Some(reason), detail);
            }
        }
    }

    fn stats(&self) -> &TransportStats {
        &self.stats
    }

    fn locators(&self) -> Vec<TransportLocator> {
        super::discovery::ip_locators(self.local)
    }

    fn serving(&self) -> String {
        self.local.to_string()
    }

    fn describe(&self, endpoint: TcpEndpoint) -> String {
        match self
            .slots
            .get(endpoint.slot as usize)
            .and_then(Option::as_ref)
            .filter(|c| c.generation == endpoint.generation)
        {
            Some(c) => c.peer.to_string(),
            None => "(connection closed)".into(),
        }
    }

    fn decode_endpoint(&self, _: &[u8]) -> Option<TcpEndpoint> {
        None
    }
}

/// `tcp4` and `tcp6`: a listener on `addr` with the connection bounds of `config`.
pub fn open(addr: std::net::SocketAddr, config: TcpConfig) -> std::io::Result<TcpTransport> {
    let listener = std::net::TcpListener::bind(addr)
        .map_err(|e| std::io::Error::new(e.kind(), format!("binding TCP {addr}: {e}")))?;
    TcpTransport::new(listener, config)
}
