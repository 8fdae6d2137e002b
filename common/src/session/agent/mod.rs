//! The agent side of XRCE sessions, as a sans-IO state machine.
//!
//! The caller feeds datagrams with [`Agent::handle_datagram`] and timer expiries with
//! [`Agent::handle_timeout`]; operations for the DDS side come out through an
//! [`OperationSink`], replies go in through [`Agent::send_status`] and [`Agent::send_data`],
//! and datagrams to send come out of [`Agent::poll_transmit`].
//!
//! Flow control: before a reliable message is processed the sink is asked whether it has
//! room. If not, the message is dropped unacknowledged and the client sends it again later,
//! so nothing is lost while the DDS side is unavailable.
//!
//! Here: the configuration, the types at the boundary and the input path (datagrams, streams,
//! submessage dispatch). Beside it: `proxy` (one client's session state), `lifecycle`
//! (sessions created, ended, sessionless requests), `output` (replies, samples, the reliable
//! output window), `timers` (HEARTBEATs, liveliness, dead sessions) and `persist`
//! (snapshots for a successor front-end).

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, HashSet, VecDeque};
use std::fmt::Debug;
use std::hash::Hash;
use std::time::{Duration, Instant};

use super::admission::{Admission, KeyCheck, Metered, RateMeter};
use super::budget::{Budget, Decision, Episodes, Limits, Origin, OriginId};
use super::fragment::{fragments, Reassembly};
use super::snapshot::{OutputSnapshot, SessionSnapshot};
use super::stream::{Arrival, BestEffortInput, ReliableInput, ReliableOutput};
use crate::wire::cdr::CdrWriter;
use crate::wire::info::{
    ActivityInfo, AgentRepresentation, ObjectConfig, ObjectInfo, TransportLocator,
};
use crate::wire::sample::{encode_samples, SampleInfo, SampleInfoDetail, SampleRef};
use crate::wire::{
    data_format, hex, status, stream_id, submessage_id, AcknackPayload, BaseObjectReply,
    BaseObjectRequest, ClientKey, CreateClientPayload, CreatePayload, DataPayload, DecodeError,
    Dialect, InfoPayload, MessageBuilder, MessageHeader, ObjectId, ObjectVariant, Payload,
    RawSubmessage, ReadSpecification, ResultStatus, StatusAgentPayload, Submessages, Time,
    TimestampReplyPayload, VENDOR_EPROSIMA, XRCE_COOKIE, XRCE_VERSION,
};

mod lifecycle;
mod limits;
mod output;
mod persist;
mod proxy;
mod timers;

pub(crate) use output::agent_info_message;
pub use output::{DataReply, SendError};
use proxy::{OutStream, ProxyClient};

/// What the session core needs of an endpoint: an identity, and the host it belongs to.
pub trait Endpoint: Copy + Eq + Hash + Debug + Origin {}
impl<T: Copy + Eq + Hash + Debug + Origin> Endpoint for T {}

/// Largest datagram UDP over IPv4 carries: the default [`AgentConfig::max_message_size`].
pub const MAX_DATAGRAM: u16 = 65_507;

/// Tunables of the agent core.
#[derive(Debug, Clone)]
pub struct AgentConfig {
    /// Most sessions at once; a new one beyond evicts the most silent session without
    /// objects of the origin with the most sessions, or gets STATUS_ERR_RESOURCES.
    pub max_clients: usize,
    /// The memory budget, the per-origin session cap and the timeouts that bound what a
    /// client can make the front-end hold.
    pub limits: Limits,
    /// Early messages kept per reliable input stream (≤ 16, the ACKNACK bitmap width).
    pub input_window: u16,
    /// Unacknowledged messages per reliable output stream.
    pub output_window: usize,
    /// Messages queued behind a full output window before new ones are dropped (counted).
    pub max_output_queue: usize,
    /// Bytes queued behind a full output window, per stream, before new ones are dropped.
    pub max_output_queue_bytes: usize,
    /// Bytes of early (out-of-order) reliable messages kept per client; beyond, they are
    /// dropped unacknowledged and the client sends them again.
    pub max_early_bytes: usize,
    /// Reliable input streams a client may use (others are dropped, counted).
    pub max_input_streams: usize,
    /// Period of HEARTBEATs while output is unacknowledged, at first: each HEARTBEAT that
    /// brings no ACKNACK from a client heard nothing from meanwhile doubles it, up to
    /// [`Self::max_heartbeat_period`] (a client that talks keeps this period); an ACKNACK
    /// resets it.
    pub heartbeat_period: Duration,
    /// Longest period between HEARTBEATs to a client that does not acknowledge.
    pub max_heartbeat_period: Duration,
    /// Largest message reassembled from FRAGMENTs, per stream.
    pub max_reassembly: usize,
    /// MTU assumed for clients that announce none.
    pub default_mtu: u16,
    /// Largest message the transport carries (UDP: [`MAX_DATAGRAM`], TCP and serial: 65,535);
    /// client MTUs are capped to it.
    pub max_message_size: u16,
    /// Vendor id announced in STATUS_AGENT and INFO.
    pub vendor_id: [u8; 2],
    /// A CREATE_CLIENT repeating the current session this soon after it was established,
    /// once the client has used its streams, is a duplicate and does not reset the streams.
    pub duplicate_create_guard: Duration,
    /// Dialect for every session; `None` chooses per session from the CREATE_CLIENT vendor id.
    /// Forcing [`Dialect::Spec`] also drops the ResultStatus from STATUS_AGENT.
    pub dialect: Option<Dialect>,
    /// Who may hold a session and how much each client may send.
    pub admission: Admission,
    /// Silence after which a client that did not ask for hard liveliness is declared dead and
    /// its session deleted; `None` keeps silent sessions (the reference agent's behaviour).
    /// Silent clients are probed with GET_INFO from a quarter of this on.
    pub client_dead_time: Option<Duration>,
    /// Keep track of the sessions whose [`SessionSnapshot`] changed, for a front-end that
    /// stores them so that its successor takes them over ([`Agent::take_session_changes`]).
    pub track_sessions: bool,
}

impl Default for AgentConfig {
    fn default() -> Self {
        AgentConfig {
            max_clients: super::budget::DEFAULT_MAX_SESSIONS,
            limits: Limits::default(),
            input_window: 16,
            output_window: 16,
            max_output_queue: 4096,
            max_output_queue_bytes: 4 << 20,
            max_early_bytes: 256 << 10,
            max_input_streams: 8,
            heartbeat_period: Duration::from_millis(100),
            max_heartbeat_period: Duration::from_millis(3200),
            default_mtu: 512,
            max_message_size: MAX_DATAGRAM,
            max_reassembly: 1 << 20,
            // The reference client accepts any vendor; announce eProsima's so clients that
            // tune behaviour by vendor treat us like the agent they were tested against.
            vendor_id: VENDOR_EPROSIMA,
            duplicate_create_guard: Duration::from_millis(500),
            dialect: None,
            client_dead_time: None,
            admission: Admission::default(),
            track_sessions: false,
        }
    }
}

/// A datagram to send.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Transmit<A> {
    /// Where to.
    pub destination: A,
    /// The XRCE message.
    pub data: Vec<u8>,
}

/// An operation for the DDS side, borrowing from the datagram being processed.
#[derive(Debug, Clone, Copy)]
pub enum Operation<'a> {
    /// A new session replaced nothing or replaced a session with another session id.
    ClientCreated {
        /// Its key.
        client: ClientKey,
        /// The host it came from (what it holds elsewhere is shared by host too).
        origin: OriginId,
    },
    /// A session ended (deleted by the client, or replaced): drop all its objects.
    ClientDeleted { client: ClientKey },
    /// CREATE, with the byte order the client used (its data writers publish in it).
    Create {
        client: ClientKey,
        create: &'a CreatePayload,
        little_endian: bool,
    },
    /// DELETE of an object.
    Delete {
        client: ClientKey,
        request: BaseObjectRequest,
    },
    /// WRITE_DATA, with the stream it came on (reliable streams must not lose it) and the
    /// dialect its SampleInfos are in.
    Write {
        client: ClientKey,
        stream_id: u8,
        data: DataPayload<'a>,
        little_endian: bool,
        dialect: Dialect,
    },
    /// GET_INFO about an object of the client (not the agent itself, which the core answers).
    GetInfo {
        client: ClientKey,
        request: BaseObjectRequest,
        info_mask: u32,
    },
    /// READ_DATA.
    Read {
        client: ClientKey,
        request: BaseObjectRequest,
        spec: &'a ReadSpecification,
    },
}

/// Receives operations from the agent core.
pub trait OperationSink {
    /// Whether the operations of one more reliable message can be taken now.
    fn has_room(&self) -> bool;
    /// Whether the operations of one more reliable message of `submessages` submessages,
    /// none of them a FRAGMENT, can be taken now (a small message may fit where the largest
    /// would not). By default, as [`Self::has_room`].
    fn has_room_for(&self, submessages: usize) -> bool {
        let _ = submessages;
        self.has_room()
    }
    /// Takes one operation, at `now` (the time of the call that brought it).
    fn operation(&mut self, now: Instant, op: Operation<'_>);
}

/// What one client sent, received and lost.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ClientCounters {
    /// Messages accepted from it (its session's endpoint).
    pub messages_in: u64,
    /// Samples it wrote (WRITE_DATA submessages handed to DDS).
    pub samples_in: u64,
    /// Samples queued for it (DATA replies).
    pub samples_out: u64,
    /// Its messages and replies dropped and lost (refusals for room and duplicates, see
    /// [`NOT_LOST`], are not counted: nothing is lost by them).
    pub dropped: u64,
}

/// One live session, for status reports.
#[derive(Debug, Clone)]
pub struct SessionInfo<A> {
    /// The client's key.
    pub key: ClientKey,
    /// Its session id.
    pub session_id: u8,
    /// Where it is reached.
    pub endpoint: A,
    /// Since the session was created.
    pub age: Duration,
    /// Since the client was last heard.
    pub silent_for: Duration,
    /// Whether its endpoint closed (the session waits for it to come back).
    pub detached: bool,
    /// Its dialect.
    pub dialect: Dialect,
    /// What it sent, received and lost.
    pub counters: ClientCounters,
}

/// Drop reasons that lose nothing: a reliable message refused for lack of room in the agent
/// or among the messages held for a gap (not acknowledged: the client sends it again), and a
/// copy of a message already taken, a reliable message refused or an early one given up
/// for the memory budget (not acknowledged either), and a CREATE_CLIENT left unanswered
/// while the session's current endpoint is probed. (A rate-quota refusal is counted: on a
/// best-effort stream it is lost.)
pub const NOT_LOST: [&str; 6] = [
    "backpressure",
    "early_buffer_full",
    "duplicate",
    "memory_budget",
    "early_evicted",
    "takeover_probing",
];

/// Counters of what the core did and dropped.
#[derive(Debug, Clone, Default)]
pub struct AgentStats {
    /// Datagrams handled.
    pub datagrams_in: u64,
    /// Datagrams queued for sending (retransmissions included).
    pub datagrams_out: u64,
    /// Retransmitted messages.
    pub retransmissions: u64,
    /// Dropped inputs and outputs, by reason.
    pub dropped: HashMap<&'static str, u64>,
    /// Every drop, whatever the reason (the sum of `dropped`).
    pub dropped_total: u64,
    /// Drops that lost something: all but [`NOT_LOST`] (what a client's session shows).
    pub lost_total: u64,
    /// WRITE_DATA submessages handed to the DDS side (client to DDS).
    pub samples_in: u64,
    /// DATA replies queued for clients (DDS to client).
    pub samples_out: u64,
}

impl AgentStats {
    /// Counts one drop for `reason`.
    fn count(&mut self, reason: &'static str) {
        *self.dropped.entry(reason).or_default() += 1;
        self.dropped_total += 1;
        if !NOT_LOST.contains(&reason) {
            self.lost_total += 1;
        }
    }

    /// Total drops for a reason.
    pub fn dropped(&self, reason: &str) -> u64 {
        self.dropped.get(reason).copied().unwrap_or(0)
    }
}

/// An ACKNACK not asked for by a HEARTBEAT is not repeated unchanged within this time: the
/// eProsima client resends every unacknowledged message on each ACKNACK that asks for any,
/// so an ACKNACK per arriving duplicate or early message would multiply its resends.
pub const ACKNACK_REPEAT_INTERVAL: Duration = Duration::from_millis(20);

/// Why a reliable input stream is acknowledged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum AckCause {
    /// The client's HEARTBEAT asked: always answered, asking for every missing message.
    Heartbeat,
    /// A message arrived (as the reference agent does, one ACKNACK per reliable message):
    /// asks for the missing messages, not repeated unchanged within
    /// [`ACKNACK_REPEAT_INTERVAL`].
    Arrival,
    /// A message was refused for lack of room (flow control): acknowledges what was taken
    /// but asks for nothing, so the client resends only once its next HEARTBEAT is answered
    /// instead of at once, over and over, while the agent is still full.
    Refused,
}

/// Request id of the agent's liveliness probes (GET_INFO). Its first octet is no submessage id,
/// so that eProsima's answer, which lacks a submessage header (its `read_submessage_get_info`
/// serializes the INFO payload straight after the message header), is recognisable.
const LIVELINESS_PROBE_ID: crate::wire::RequestId = crate::wire::RequestId([0x7F, 0xA1]);

/// Whether the bytes after a message header are eProsima's answer to a liveliness probe: a
/// bare INFO payload (BaseObjectReply echoing the probe's request id, two absent optionals).
fn is_bare_probe_reply(after_header: &[u8]) -> bool {
    after_header.len() == 8 && after_header[..2] == LIVELINESS_PROBE_ID.0
}

/// The agent-side protocol state of every session of one front-end.
#[derive(Debug)]
pub struct Agent<A> {
    config: AgentConfig,
    clients: HashMap<ClientKey, ProxyClient<A>>,
    by_addr: HashMap<A, ClientKey>,
    transmits: VecDeque<Transmit<A>>,
    /// Clients' next timer: (when, client); an entry is live only while it matches the
    /// client's `timer` (later ones supersede, stale ones are skipped).
    timers: BinaryHeap<Reverse<(Instant, ClientKey)>>,
    /// Keys refused by the allow-list whose refusal was logged (bounded).
    denied_logged: HashSet<ClientKey>,
    wall_clock: Option<(Instant, Duration)>,
    stats: AgentStats,
    /// Replies already made for the datagram being handled.
    replied: Vec<Reply>,
    /// Reliable input streams named by HEARTBEATs inside reliable messages, whose buffered
    /// messages are delivered once the message is done.
    heartbeat_deliveries: Vec<u8>,
    /// Sessions whose snapshot changed since the last [`Agent::take_session_changes`]
    /// (with `track_sessions`), and sessions deleted since.
    changed: HashSet<ClientKey>,
    changed_input: HashSet<ClientKey>,
    removed: Vec<ClientKey>,
    /// What the sessions hold, by origin.
    budget: Budget,
    /// Refusals logged once per episode.
    episodes: Episodes,
}

/// Replies the agent makes at most once per datagram, so that one datagram packed with
/// requests cannot make it send thousands (amplification).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reply {
    Info,
    Timestamp,
    Acknack(u8),
    Retransmit(u8),
}

impl<A: Endpoint> Agent<A> {
    /// An agent with no sessions.
    pub fn new(config: AgentConfig) -> Self {
        Agent {
            clients: HashMap::new(),
            by_addr: HashMap::new(),
            transmits: VecDeque::new(),
            timers: BinaryHeap::new(),
            denied_logged: HashSet::new(),
            wall_clock: None,
            stats: AgentStats::default(),
            replied: Vec::new(),
            heartbeat_deliveries: Vec::new(),
            changed: HashSet::new(),
            changed_input: HashSet::new(),
            removed: Vec::new(),
            budget: Budget::new(config.limits.memory_budget),
            episodes: Episodes::default(),
            config,
        }
    }

    /// Notes that a session's output side (or anything but its input positions) changed.
    fn touch(&mut self, key: ClientKey) {
        if self.config.track_sessions {
            self.changed.insert(key);
        }
    }

    /// Notes that a session's input positions changed (or that it is new).
    fn touch_input(&mut self, key: ClientKey) {
        if self.config.track_sessions {
            self.changed_input.insert(key);
        }
    }

    /// Tells the core what Unix time corresponds to `now`, for TIMESTAMP_REPLY.
    pub fn set_wall_clock(&mut self, now: Instant, since_unix_epoch: Duration) {
        self.wall_clock = Some((now, since_unix_epoch));
    }

    /// Counters.
    pub fn stats(&self) -> &AgentStats {
        &self.stats
    }

    /// Number of sessions.
    pub fn client_count(&self) -> usize {
        self.clients.len()
    }

    /// The live sessions, as of `now`.
    pub fn sessions(&self, now: Instant) -> impl Iterator<Item = SessionInfo<A>> + '_ {
        self.clients.values().map(move |c| SessionInfo {
            key: c.key,
            session_id: c.session_id,
            endpoint: c.addr,
            age: now.saturating_duration_since(c.created_at),
            silent_for: now.saturating_duration_since(c.last_heard),
            detached: c.detached,
            dialect: c.dialect,
            counters: c.counters,
        })
    }

    /// Whether a client has a session.
    pub fn has_client(&self, key: ClientKey) -> bool {
        self.clients.contains_key(&key)
    }

    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Transmit<A>> {
        self.transmits.pop_front()
    }

    /// When [`Self::handle_timeout`] should be called next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.timers.peek().map(|Reverse((t, _))| *t)
    }

    /// Enters a client's next timer in the heap when it is earlier than its live entry (a
    /// later one is looked at when the live entry falls due).
    fn schedule(&mut self, key: ClientKey) {
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        if let Some(due) = c.next_due(self.config.limits.reassembly_timeout) {
            if c.timer.is_none_or(|t| due < t) {
                c.timer = Some(due);
                self.timers.push(Reverse((due, key)));
            }
        }
    }

    fn drop_input(&mut self, reason: &'static str, bytes: &[u8]) {
        self.stats.count(reason);
        tracing::debug!(reason, len = bytes.len(), "dropped input");
        tracing::trace!(reason, bytes = %hex(bytes), "dropped input bytes");
    }

    fn count_drop(&mut self, reason: &'static str) {
        self.stats.count(reason);
    }

    fn push_transmit(&mut self, destination: A, data: Vec<u8>) {
        self.stats.datagrams_out += 1;
        tracing::trace!(?destination, len = data.len(), bytes = %hex(&data), "datagram out");
        self.transmits.push_back(Transmit { destination, data });
    }

    /// Whether this reply was not made yet for the current datagram (and records it).
    fn once(&mut self, r: Reply) -> bool {
        if self.replied.contains(&r) {
            return false;
        }
        self.replied.push(r);
        true
    }

    /// Handles one datagram from `src`.
    pub fn handle_datagram(
        &mut self,
        now: Instant,
        src: A,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        self.stats.datagrams_in += 1;
        self.replied.clear();
        tracing::trace!(?src, len = bytes.len(), bytes = %hex(bytes), "datagram in");
        let (header, hlen) = match MessageHeader::decode(bytes) {
            Ok(h) => h,
            Err(e) => return self.drop_input(e.reason(), bytes),
        };
        if header.session_id == 0x00 || header.session_id == 0x80 {
            return self.handle_sessionless(now, src, header, hlen, bytes, sink);
        }
        let key = match header.client_key {
            Some(k) => k,
            None => match self.by_addr.get(&src) {
                Some(k) => *k,
                None => return self.drop_input("no_client", bytes),
            },
        };
        let Some(client) = self.clients.get_mut(&key) else {
            return self.drop_input("no_client", bytes);
        };
        if client.session_id != header.session_id {
            return self.drop_input("wrong_session", bytes);
        }
        if client.addr != src {
            // Only a key in the header names a session from another endpoint.
            if !self.config.admission.allow_roaming {
                // Whoever learnt the key does not take the session over: only the client's
                // CREATE_CLIENT moves it (or roaming, when the operator allows it).
                client.foreign_drops += 1;
                if client.foreign_drops == 1 {
                    tracing::warn!(client = %key, from = ?src, at = ?client.addr, "message for a session from another endpoint dropped (a client that moved must send CREATE_CLIENT again, or run the agent with --allow-roaming); further ones are counted");
                }
                return self.drop_input("foreign_endpoint", bytes);
            }
            // The client moved (e.g. a new source port after a NAT rebinding).
            if self.by_addr.get(&client.addr) == Some(&key) {
                self.by_addr.remove(&client.addr);
            }
            tracing::info!(client = %key, from = ?client.addr, to = ?src, "session roamed");
            client.addr = src;
            self.by_addr.insert(src, key);
        }
        client.last_heard = now;
        client.reattach();
        client.counters.messages_in += 1;
        let lost_before = self.stats.lost_total;
        self.handle_session_message(now, key, header, hlen, bytes, sink);
        if stream_id::is_reliable(header.stream_id) {
            // Its input position moved: stored before anything acknowledges it.
            self.touch_input(key);
        } else {
            self.touch(key);
        }
        let lost = self.stats.lost_total - lost_before;
        if let Some(c) = self.clients.get_mut(&key) {
            c.counters.dropped += lost;
        }
        self.account(key);
    }

    /// A message of an existing session, from its endpoint.
    fn handle_session_message(
        &mut self,
        now: Instant,
        key: ClientKey,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        if let Some(meter) = &mut client.meter {
            match meter.admit(now, bytes.len()) {
                Metered::Admitted => {}
                Metered::BackWithin { dropped } => {
                    tracing::info!(client = %key, dropped, "client back within its rate quota");
                }
                Metered::WentOver(hit) => {
                    let quota = self.config.admission.rate;
                    tracing::warn!(client = %key, bound = hit.name(), messages_per_second = ?quota.messages_per_second, bytes_per_second = ?quota.bytes_per_second, "client over its rate quota: its messages are dropped until it slows down (reliable ones are sent again by the client)");
                    return self.drop_input("rate_quota", bytes);
                }
                Metered::StillOver => return self.drop_input("rate_quota", bytes),
            }
        }
        let stream = header.stream_id;
        if stream != stream_id::NONE {
            client.streams_used = true;
        }
        if stream == stream_id::NONE && is_bare_probe_reply(&bytes[hlen..]) {
            // A live client answered a liveliness probe (hearing it was the point).
        } else if stream == stream_id::NONE {
            self.process(now, key, bytes, hlen, sink);
        } else if !stream_id::is_reliable(stream) {
            let accepted = client
                .best_effort_in
                .entry(stream)
                .or_default()
                .accept(header.sequence_nr);
            if accepted {
                self.process(now, key, bytes, hlen, sink);
            } else {
                self.drop_input("stale_best_effort", bytes);
            }
        } else {
            self.handle_reliable(now, key, header, hlen, bytes, sink);
        }
        // HEARTBEATs that came inside reliable messages (delivering may bring more).
        while let Some(s) = self.heartbeat_deliveries.pop() {
            self.deliver_ready(now, key, s, sink);
            self.send_acknack(now, key, s, AckCause::Heartbeat);
        }
        self.flush_client(now, key);
        self.finish_client(now, key, sink);
    }

    fn handle_reliable(
        &mut self,
        now: Instant,
        key: ClientKey,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        let window = self.config.input_window;
        let max_streams = self.config.max_input_streams;
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        let stream = header.stream_id;
        if !client.reliable_in.contains_key(&stream) && client.reliable_in.len() >= max_streams {
            return self.drop_input("too_many_streams", bytes);
        }
        let first = client.first_seq;
        let input = client
            .reliable_in
            .entry(stream)
            .or_insert_with(|| ReliableInput::resuming(window, first));
        let mut cause = AckCause::Arrival;
        match input.classify(header.sequence_nr) {
            Arrival::Duplicate => self.count_drop("duplicate"),
            Arrival::OutOfWindow => self.drop_input("out_of_window", bytes),
            Arrival::Early => {
                let held: usize = client
                    .reliable_in
                    .values()
                    .map(ReliableInput::early_bytes)
                    .sum();
                if held + bytes.len() > self.config.max_early_bytes {
                    self.count_drop("early_buffer_full");
                } else if !self.make_room(now, key, bytes.len(), "memory_budget") {
                    // Not acknowledged: sent again once it is next.
                } else if let Some(input) = self
                    .clients
                    .get_mut(&key)
                    .and_then(|c| c.reliable_in.get_mut(&stream))
                {
                    input.store_early(header.sequence_nr, bytes.to_vec());
                    self.account(key);
                }
            }
            Arrival::InOrder => {
                // A FRAGMENT makes the core keep its bytes until the last one: room for
                // them first, or the message is not acknowledged and comes again.
                let kept = fragment_bytes(bytes, hlen);
                let growth = self
                    .clients
                    .get(&key)
                    .and_then(|c| c.reassembly.get(&stream))
                    .map_or(kept, |r| r.growth_for(kept));
                if growth > 0 && !self.make_room(now, key, growth, "memory_budget") {
                    cause = AckCause::Refused;
                } else if room_for(sink, bytes, hlen) {
                    if let Some(input) = self
                        .clients
                        .get_mut(&key)
                        .and_then(|c| c.reliable_in.get_mut(&stream))
                    {
                        input.advance();
                    }
                    self.process(now, key, bytes, hlen, sink);
                    if !self.deliver_ready(now, key, stream, sink) {
                        cause = AckCause::Refused;
                    }
                } else {
                    // Flow control: not acknowledged, so the client will send it again.
                    self.count_drop("backpressure");
                    cause = AckCause::Refused;
                }
            }
        }
        self.send_acknack(now, key, stream, cause);
    }

    /// Delivers messages that arrived early and are now next, while the sink has room. One
    /// that finds no room is dropped unacknowledged (false is returned): the ACKNACK that
    /// answers the client's next HEARTBEAT asks for it again.
    fn deliver_ready(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        sink: &mut impl OperationSink,
    ) -> bool {
        loop {
            let Some(input) = self
                .clients
                .get_mut(&key)
                .and_then(|c| c.reliable_in.get_mut(&stream))
            else {
                return true;
            };
            let Some(next) = input.take_ready() else {
                return true;
            };
            let Ok((_, hlen)) = MessageHeader::decode(&next) else {
                input.advance();
                continue;
            };
            if !room_for(sink, &next, hlen) {
                self.count_drop("backpressure");
                return false;
            }
            input.advance();
            self.process(now, key, &next, hlen, sink);
        }
    }

    /// Acknowledges a reliable input stream (see [`AckCause`] for when an ACKNACK asks for
    /// messages again and when one is left out).
    fn send_acknack(&mut self, now: Instant, key: ClientKey, stream: u8, cause: AckCause) {
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        let Some(input) = client.reliable_in.get(&stream) else {
            return;
        };
        let mut ack = input.acknack(stream);
        if cause == AckCause::Refused {
            ack.nack_bitmap = 0;
        }
        let same = (ack.first_unacked_seq_num, ack.nack_bitmap);
        if cause != AckCause::Heartbeat {
            let repeated = client.last_acknack.get(&stream).is_some_and(|&(f, m, at)| {
                (f, m) == same && now.saturating_duration_since(at) < ACKNACK_REPEAT_INTERVAL
            });
            if repeated {
                return;
            }
        }
        client.last_acknack.insert(stream, (same.0, same.1, now));
        let mut b = MessageBuilder::new(client.header(stream_id::NONE, 0));
        let _ = b.push(&Payload::Acknack(ack), true);
        let addr = client.addr;
        self.push_transmit(addr, b.finish());
    }

    fn client_dialect(&self, key: ClientKey) -> Dialect {
        self.clients
            .get(&key)
            .map_or(Dialect::default(), |c| c.dialect)
    }

    /// Messages and bytes waiting for window room on a client's reliable output stream
    /// (0 = the built-in one); `None` for best-effort streams and unknown clients.
    pub fn output_backlog(&self, key: ClientKey, stream: u8) -> Option<(usize, usize)> {
        let stream = if stream == stream_id::NONE {
            stream_id::BUILTIN_RELIABLE
        } else {
            stream
        };
        if !stream_id::is_reliable(stream) {
            return None;
        }
        let c = self.clients.get(&key)?;
        Some(
            c.reliable_out
                .get(&stream)
                .map_or((0, 0), |s| (s.queue.len(), s.queued_bytes)),
        )
    }

    /// The dialect a client's session speaks.
    pub fn dialect(&self, key: ClientKey) -> Option<Dialect> {
        self.clients.get(&key).map(|c| c.dialect)
    }

    /// Processes the submessages of one accepted message.
    fn process(
        &mut self,
        now: Instant,
        key: ClientKey,
        bytes: &[u8],
        hlen: usize,
        sink: &mut impl OperationSink,
    ) {
        let stream = bytes.get(1).copied().unwrap_or(0);
        for raw in Submessages::new(bytes, hlen) {
            let raw = match raw {
                Ok(r) => r,
                Err(e) => return self.drop_input(e.reason(), bytes),
            };
            self.dispatch(now, key, stream, raw, false, sink);
        }
    }

    /// Acts on one submessage of an accepted message (or of a reassembled one).
    fn dispatch(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        raw: RawSubmessage<'_>,
        reassembled: bool,
        sink: &mut impl OperationSink,
    ) {
        let payload = match raw.decode() {
            Ok(p) => p,
            Err(e) => return self.drop_submessage(e, raw.id, raw.payload),
        };
        let le = raw.little_endian();
        match payload {
            Payload::Create(c) => {
                if let Some(client) = self.clients.get_mut(&key) {
                    client.has_objects = true;
                }
                sink.operation(
                    now,
                    Operation::Create {
                        client: key,
                        create: &c,
                        little_endian: le,
                    },
                )
            }
            // The client object by its kind, whatever its number: eProsima's client names
            // it OBJECTID_CLIENT (0xFFFE), RTI's nano-client 0x000E (kind CLIENT, id 0);
            // MicroXRCEAgent also looks at the kind only.
            Payload::Delete(d) if d.object_id.kind() == crate::wire::object_kind::CLIENT => {
                if stream == stream_id::NONE {
                    // Answered the way it came, as the reference agent does: the
                    // session's streams end with it.
                    if let Some(c) = self.clients.get(&key) {
                        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
                        let reply = BaseObjectReply {
                            related: d,
                            result: ResultStatus::OK,
                        };
                        let _ = b.push(&Payload::Status(reply), true);
                        let addr = c.addr;
                        self.push_transmit(addr, b.finish());
                    }
                } else {
                    self.queue_status(key, d, ResultStatus::OK);
                }
                if let Some(c) = self.clients.get_mut(&key) {
                    c.delete_requested = true;
                }
            }
            Payload::Delete(d) => sink.operation(
                now,
                Operation::Delete {
                    client: key,
                    request: d,
                },
            ),
            Payload::WriteData(d) => {
                self.stats.samples_in += 1;
                if let Some(c) = self.clients.get_mut(&key) {
                    c.counters.samples_in += 1;
                }
                let dialect = self.client_dialect(key);
                sink.operation(
                    now,
                    Operation::Write {
                        client: key,
                        stream_id: stream,
                        data: d,
                        little_endian: le,
                        dialect,
                    },
                )
            }
            Payload::ReadData(r) => sink.operation(
                now,
                Operation::Read {
                    client: key,
                    request: r.base,
                    spec: &r.spec,
                },
            ),
            Payload::GetInfo(_) if !self.once(Reply::Info) => self.count_drop("repeated_request"),
            Payload::GetInfo(g)
                if g.base.object_id == ObjectId::AGENT || g.base.object_id == ObjectId::CLIENT =>
            {
                if let Some(c) = self.clients.get(&key) {
                    let (addr, h, d) = (c.addr, c.header(stream_id::NONE, 0), c.dialect);
                    self.reply_info(addr, h, g.base, true, d);
                }
            }
            Payload::GetInfo(g) => sink.operation(
                now,
                Operation::GetInfo {
                    client: key,
                    request: g.base,
                    info_mask: g.info_mask,
                },
            ),
            // A client's answer to a liveliness probe: hearing it was the point.
            Payload::Info(_) => {}
            Payload::Acknack(a) => {
                // One ACKNACK per stream per datagram: more would only multiply resends.
                if self.once(Reply::Retransmit(a.stream_id)) {
                    self.on_acknack(now, key, &a);
                }
            }
            Payload::Heartbeat(h) if stream_id::is_reliable(h.stream_id) => {
                // The stream may be new to us: if every message the client sent on it was
                // lost, this HEARTBEAT is the first we hear of it, and the ACKNACK must ask
                // for everything, or the client would wait for ever.
                let (window, max_streams) =
                    (self.config.input_window, self.config.max_input_streams);
                if let Some(c) = self.clients.get_mut(&key) {
                    if c.reliable_in.contains_key(&h.stream_id) || c.reliable_in.len() < max_streams
                    {
                        let first = c.first_seq;
                        c.reliable_in
                            .entry(h.stream_id)
                            .or_insert_with(|| ReliableInput::resuming(window, first))
                            .on_heartbeat(&h);
                    }
                }
                // Messages the sender gave up on may have unblocked buffered ones. Inside a
                // reliable message they wait for the end of it: its own operations were
                // given room and go first (delivered in its middle, buffered ones could take
                // that room and leave the rest of it behind, after it was acknowledged).
                if self.once(Reply::Acknack(h.stream_id)) {
                    if stream_id::is_reliable(stream) {
                        self.heartbeat_deliveries.push(h.stream_id);
                    } else {
                        self.deliver_ready(now, key, h.stream_id, sink);
                        self.send_acknack(now, key, h.stream_id, AckCause::Heartbeat);
                    }
                }
            }
            Payload::Heartbeat(_) => self.count_drop("heartbeat_for_best_effort_stream"),
            Payload::Reset => {
                if let Some(c) = self.clients.get_mut(&key) {
                    c.reset_streams();
                }
            }
            Payload::Timestamp(t) if self.once(Reply::Timestamp) => {
                self.reply_timestamp(now, key, t)
            }
            Payload::Timestamp(_) => self.count_drop("repeated_request"),
            Payload::Fragment { last, data } => {
                self.on_fragment(now, key, stream, last, data, reassembled, sink)
            }
            _ => self.drop_submessage(
                DecodeError::InvalidValue("submessage for an agent"),
                raw.id,
                raw.payload,
            ),
        }
    }

    /// Collects a FRAGMENT; the last one's reassembled submessages are processed as if they
    /// had arrived in the message of the last fragment.
    #[allow(clippy::too_many_arguments)]
    fn on_fragment(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        last: bool,
        data: &[u8],
        reassembled: bool,
        sink: &mut impl OperationSink,
    ) {
        if reassembled || !stream_id::is_reliable(stream) {
            return self.drop_submessage(
                DecodeError::InvalidValue("fragment outside a reliable stream"),
                submessage_id::FRAGMENT,
                data,
            );
        }
        let max = self.config.max_reassembly;
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let pushed = c
            .reassembly
            .entry(stream)
            .or_default()
            .push(data, last, max);
        if matches!(pushed, Ok(None)) {
            c.reassembly_at.insert(stream, now);
        } else {
            c.reassembly_at.remove(&stream);
        }
        if c.reassembly_at.len() == 1 {
            // The first reassembly in progress: its timeout is a timer of the client.
            self.schedule(key);
        }
        match pushed {
            Ok(None) => {}
            Ok(Some(whole)) => {
                for raw in Submessages::reassembled(&whole) {
                    match raw {
                        Ok(raw) => self.dispatch(now, key, stream, raw, true, sink),
                        Err(e) => return self.drop_input(e.reason(), &whole),
                    }
                }
            }
            Err(crate::session::fragment::ReassemblyError::TooLarge(_)) => {
                self.count_drop("reassembly_too_large")
            }
            Err(crate::session::fragment::ReassemblyError::Discarded) => {
                self.count_drop("reassembly_discarded")
            }
        }
    }

    fn drop_submessage(&mut self, e: DecodeError, id: u8, payload: &[u8]) {
        let reason = if id == submessage_id::FRAGMENT {
            "fragment_unsupported"
        } else {
            e.reason()
        };
        self.stats.count(reason);
        tracing::debug!(reason, id, error = %e, "dropped submessage");
        tracing::trace!(bytes = %hex(payload), "dropped submessage payload");
    }

    fn reply_timestamp(&mut self, now: Instant, key: ClientKey, originate: Time) {
        let Some((base, unix)) = self.wall_clock else {
            return self.count_drop("no_wall_clock");
        };
        let t = unix + now.saturating_duration_since(base);
        let t = Time {
            seconds: t.as_secs() as i32,
            nanoseconds: t.subsec_nanos(),
        };
        let Some(c) = self.clients.get(&key) else {
            return;
        };
        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
        let _ = b.push(
            &Payload::TimestampReply(TimestampReplyPayload {
                transmit: t,
                receive: t,
                originate,
            }),
            true,
        );
        let addr = c.addr;
        self.push_transmit(addr, b.finish());
    }

    fn on_acknack(&mut self, now: Instant, key: ClientKey, a: &AcknackPayload) {
        let base = self.config.heartbeat_period;
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        // It answers: HEARTBEATs at the base period again, the next one included.
        c.heartbeat_interval = base;
        let sooner = c.heartbeat_due.is_some_and(|d| d > now + base);
        if sooner {
            c.heartbeat_due = Some(now + base);
        }
        let addr = c.addr;
        let Some(out) = c.reliable_out.get_mut(&a.stream_id) else {
            return;
        };
        let resend: Vec<Vec<u8>> = out
            .reliable
            .on_acknack(a)
            .into_iter()
            .map(|m| m.to_vec())
            .collect();
        for m in resend {
            self.stats.retransmissions += 1;
            self.push_transmit(addr, m);
        }
        if sooner {
            self.schedule(key);
        }
    }
}

/// Whether `sink` has room for the operations of the reliable message `bytes` (header
/// `hlen` bytes long): asked for its submessages' count when none is a FRAGMENT (whose
/// completion can bring a message of any size) and every header is whole, else for the
/// largest message. (A HEARTBEAT in it delivers buffered messages only after it.)
fn room_for(sink: &impl OperationSink, bytes: &[u8], hlen: usize) -> bool {
    let mut count = 0;
    for raw in Submessages::new(bytes, hlen) {
        match raw {
            Ok(r) if r.id != submessage_id::FRAGMENT => count += 1,
            _ => return sink.has_room(),
        }
    }
    sink.has_room_for(count)
}

/// Bytes of FRAGMENT payload in a message (what the core keeps of it until the last
/// fragment).
fn fragment_bytes(bytes: &[u8], hlen: usize) -> usize {
    Submessages::new(bytes, hlen)
        .filter_map(Result::ok)
        .filter(|r| r.id == submessage_id::FRAGMENT)
        .map(|r| r.payload.len())
        .sum()
}

/// A sink that takes nothing: for tests and for fuzzing the core.
#[derive(Debug, Default)]
pub struct NullSink;

impl OperationSink for NullSink {
    fn has_room(&self) -> bool {
        true
    }
    fn operation(&mut self, _: Instant, _: Operation<'_>) {}
}
