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

use super::admission::{Admission, CreationMeter, KeyCheck, Metered, RateMeter};
use super::budget::{Budget, Decision, Episodes, Limits, Origin, OriginId};
use super::fragment::{fragments, Reassembly};
use super::snapshot::{OutputSnapshot, SessionSnapshot};
use super::stream::{Arrival, BestEffortInput, InputPosition, ReliableInput, ReliableOutput};
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

mod dispatch;
mod input;
mod lifecycle;
mod limits;
mod output;
mod persist;
mod proxy;
mod timers;

use input::MessageAt;
pub(crate) use output::agent_info_message;
pub use output::{DataReply, SendError};
use proxy::{ExecutedFloor, OutStream, ProxyClient};

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
    /// Drawn at random by each front-end process: the epochs of clients' streams this core
    /// issues ([`InputPosition::epoch`]) are a one-to-one mix of it and a count, so one
    /// process never issues an epoch twice, and a successor issues one its predecessor
    /// handed to the worker with a chance of about one in 2^64 per pair.
    pub epoch_seed: u64,
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
            epoch_seed: 0,
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
    ClientDeleted {
        /// Its key.
        client: ClientKey,
    },
    /// CREATE, with the byte order the client used (its data writers publish in it).
    Create {
        /// The client whose session it came on.
        client: ClientKey,
        /// What to create, and how.
        create: &'a CreatePayload,
        /// The byte order of the submessage.
        little_endian: bool,
    },
    /// DELETE of an object.
    Delete {
        /// The client whose session it came on.
        client: ClientKey,
        /// The object, and the request id its STATUS answers.
        request: BaseObjectRequest,
    },
    /// WRITE_DATA, with the stream it came on (reliable streams must not lose it) and the
    /// dialect its SampleInfos are in.
    Write {
        /// The client whose session it came on.
        client: ClientKey,
        /// The stream it came on.
        stream_id: u8,
        /// Where it stood on a reliable stream (`None` on others): the worker keeps the last
        /// one it executed for a front-end that takes over from this one.
        position: Option<InputPosition>,
        /// The data writer, and the sample(s) in the payload's data format.
        data: DataPayload<'a>,
        /// The byte order of the submessage.
        little_endian: bool,
        /// How its SampleInfos are written (the spec's or eProsima's).
        dialect: Dialect,
    },
    /// GET_INFO about an object of the client (not the agent itself, which the core answers).
    GetInfo {
        /// The client whose session it came on.
        client: ClientKey,
        /// The object, and the request id its INFO answers.
        request: BaseObjectRequest,
        /// What is asked (configuration, activity).
        info_mask: u32,
    },
    /// READ_DATA.
    Read {
        /// The client whose session it came on.
        client: ClientKey,
        /// The data reader, and the request id its DATA answers.
        request: BaseObjectRequest,
        /// What to read and how to deliver it.
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
/// for the memory budget (not acknowledged either), a CREATE_CLIENT left unanswered
/// while the session's current endpoint is probed, and a DELETE or GET_INFO for a session the
/// agent does not have (answered, not dropped: counted to show how often it happens). (A rate-quota refusal is counted: on a
/// best-effort stream it is lost.)
pub const NOT_LOST: [&str; 8] = [
    "backpressure",
    "early_buffer_full",
    "duplicate",
    "memory_budget",
    "early_evicted",
    "takeover_probing",
    "delete_without_session",
    "info_without_session",
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
    /// New sessions each origin may start per second.
    creations: CreationMeter,
    /// Epochs of clients' streams issued so far.
    epochs_issued: u64,
}

/// Replies the agent makes at most once per datagram, so that one datagram packed with
/// requests cannot make it send thousands (amplification).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reply {
    Info,
    /// A STATUS to a DELETE of a session the agent does not have.
    Status,
    Timestamp,
    Acknack(u8),
    Retransmit(u8),
}

/// The epoch of a run of a client's streams that starts now: the count of those `issued`
/// mixed with the process's `seed` by SplitMix64's finalizer (one-to-one, so distinct
/// counts give distinct epochs); 0, the epoch of a session stored before epochs were, is
/// skipped.
fn issue_epoch(issued: &mut u64, seed: u64) -> u64 {
    loop {
        *issued = issued.wrapping_add(1);
        let mut z = seed.wrapping_add(issued.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        if z != 0 {
            return z;
        }
    }
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
            creations: CreationMeter::new(config.limits.new_sessions_per_second),
            epochs_issued: 0,
            config,
        }
    }

    /// The epoch of a run of a client's streams that starts now ([`issue_epoch`]).
    fn next_epoch(&mut self) -> u64 {
        issue_epoch(&mut self.epochs_issued, self.config.epoch_seed)
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
        let limits = &self.config.limits;
        if let Some(due) = c.next_due(limits.reassembly_timeout, limits.takeover_probe_wait) {
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
