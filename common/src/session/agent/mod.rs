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

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, HashSet, VecDeque};
use std::fmt::Debug;
use std::hash::Hash;
use std::time::{Duration, Instant};

use super::admission::{Admission, Metered, RateMeter};
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

/// Largest datagram UDP over IPv4 carries: the default [`AgentConfig::max_message_size`].
pub const MAX_DATAGRAM: u16 = 65_507;

/// Tunables of the agent core.
#[derive(Debug, Clone)]
pub struct AgentConfig {
    /// Most sessions at once; more get STATUS_ERR_RESOURCES.
    pub max_clients: usize,
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
            max_clients: 65_536,
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
    ClientCreated { client: ClientKey },
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
    /// Takes one operation.
    fn operation(&mut self, op: Operation<'_>);
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
/// copy of a message already taken. (A rate-quota refusal is counted: on a best-effort
/// stream it is lost.)
pub const NOT_LOST: [&str; 3] = ["backpressure", "early_buffer_full", "duplicate"];

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

#[derive(Debug)]
struct OutStream {
    /// Bytes in `queue`.
    queued_bytes: usize,
    reliable: ReliableOutput,
    /// Encoded submessages waiting for window room.
    queue: VecDeque<Vec<u8>>,
}

#[derive(Debug)]
struct ProxyClient<A> {
    key: ClientKey,
    session_id: u8,
    addr: A,
    mtu: u16,
    /// Whether the client announced its MTU (eProsima's CREATE_CLIENT property); if not,
    /// `mtu` is assumed, and bounds its fragments but not its best-effort messages.
    mtu_announced: bool,
    last_heard: Instant,
    reliable_in: HashMap<u8, ReliableInput>,
    best_effort_in: HashMap<u8, BestEffortInput>,
    reliable_out: HashMap<u8, OutStream>,
    best_effort_out: HashMap<u8, u16>,
    reassembly: HashMap<u8, Reassembly>,
    heartbeat_due: Option<Instant>,
    /// The period of the next HEARTBEAT (backs off while the client does not answer).
    heartbeat_interval: Duration,
    /// The entry of this client in the agent's timer heap, if any.
    timer: Option<Instant>,
    /// Its input rate quota's consumption (none when unlimited).
    meter: Option<RateMeter>,
    /// Messages dropped because they presented this client's key from another endpoint.
    foreign_drops: u64,
    /// What this client sent, received and lost.
    counters: ClientCounters,
    /// When its session was created (a CREATE_CLIENT of the same session keeps it).
    created_at: Instant,
    delete_requested: bool,
    /// When the session was created or its streams last reset by a CREATE_CLIENT.
    established_at: Instant,
    /// Whether the client sent anything on a stream since then.
    streams_used: bool,
    dialect: Dialect,
    /// Silence after which the client is dead (hard liveliness or the configured dead time).
    dead_time: Option<Duration>,
    /// Its endpoint closed (a TCP connection): nothing is sent until it is heard again.
    detached: bool,
    /// When the last GET_INFO liveliness probe went out.
    last_probe: Option<Instant>,
    /// The last ACKNACK sent on each reliable input stream and when (see [`AckCause`]).
    last_acknack: HashMap<u8, (u16, u16, Instant)>,
}

impl<A> ProxyClient<A> {
    /// A fresh session: no stream used yet.
    #[allow(clippy::too_many_arguments)]
    fn new(
        key: ClientKey,
        session_id: u8,
        addr: A,
        mtu: u16,
        dialect: Dialect,
        dead_time: Option<Duration>,
        now: Instant,
        config: &AgentConfig,
    ) -> Self {
        ProxyClient {
            key,
            session_id,
            addr,
            mtu,
            mtu_announced: false,
            last_heard: now,
            reliable_in: HashMap::new(),
            best_effort_in: HashMap::new(),
            reliable_out: HashMap::new(),
            best_effort_out: HashMap::new(),
            reassembly: HashMap::new(),
            heartbeat_due: None,
            heartbeat_interval: config.heartbeat_period,
            timer: None,
            meter: (!config.admission.rate.is_unlimited())
                .then(|| RateMeter::new(config.admission.rate, now)),
            foreign_drops: 0,
            counters: ClientCounters::default(),
            created_at: now,
            delete_requested: false,
            established_at: now,
            streams_used: false,
            dialect,
            dead_time,
            detached: false,
            last_probe: None,
            last_acknack: HashMap::new(),
        }
    }

    fn header(&self, stream: u8, seq: u16) -> MessageHeader {
        MessageHeader::new(self.session_id, stream, seq, self.key)
    }

    fn reset_streams(&mut self) {
        self.reliable_in.clear();
        self.best_effort_in.clear();
        self.reliable_out.clear();
        self.best_effort_out.clear();
        self.reassembly.clear();
        self.heartbeat_due = None;
        self.streams_used = false;
        self.last_acknack.clear();
    }

    /// When this client's timers have something to do next: a HEARTBEAT, a liveliness
    /// probe, or (detached: nobody to probe) the end of its dead time.
    fn next_due(&self) -> Option<Instant> {
        let liveliness = if self.detached {
            self.dead_time.map(|d| self.last_heard + d)
        } else {
            self.liveliness_due()
        };
        match (self.heartbeat_due.filter(|_| !self.detached), liveliness) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// When the liveliness check of this client has something to do next.
    fn liveliness_due(&self) -> Option<Instant> {
        let dead = self.dead_time?;
        let probe_every = probe_period(dead);
        let first_probe = self.last_heard + probe_every;
        let next_probe = self
            .last_probe
            .filter(|p| *p >= self.last_heard)
            .map_or(first_probe, |p| (p + probe_every).max(first_probe));
        Some(next_probe.min(self.last_heard + dead))
    }
}

/// An INFO payload (reply and ObjectInfo) encoded whole, so that the ObjectInfo is aligned
/// relative to the payload start as on the wire.
fn info_bytes(reply: BaseObjectReply, info: &ObjectInfo, dialect: Dialect) -> Vec<u8> {
    let mut buf = Vec::new();
    let w = &mut CdrWriter::new(&mut buf, true);
    reply.encode(w);
    info.encode(w, dialect);
    buf
}

/// An INFO message about the agent: its representation and activity (available, with
/// `locators`), answering `request`, with `header`'s session and key.
pub(crate) fn agent_info_message(
    header: MessageHeader,
    request: BaseObjectRequest,
    in_session: bool,
    dialect: Dialect,
    vendor_id: [u8; 2],
    locators: Vec<TransportLocator>,
) -> Vec<u8> {
    let reply = BaseObjectReply {
        related: request,
        result: ResultStatus {
            status: status::OK,
            implementation_status: in_session as u8,
        },
    };
    let info = ObjectInfo {
        activity: Some(ActivityInfo::Agent {
            availability: 1,
            locators,
        }),
        config: Some(ObjectConfig::Agent(AgentRepresentation {
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id,
            properties: None,
        })),
    };
    let h = MessageHeader {
        stream_id: stream_id::NONE,
        sequence_nr: 0,
        ..header
    };
    let mut b = MessageBuilder::new(h);
    let bytes = info_bytes(reply, &info, dialect);
    let _ = b.push(
        &Payload::Info(InfoPayload {
            reply,
            object_info: bytes.get(BaseObjectReply::LEN..).unwrap_or_default(),
        }),
        true,
    );
    b.finish()
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

/// How often a silent client is probed: four times within its dead time, at most every 10 s.
fn probe_period(dead_time: Duration) -> Duration {
    (dead_time / 4).clamp(Duration::from_millis(25), Duration::from_secs(10))
}

/// The hard-liveliness timeout a client asks for in CREATE_CLIENT (property `uxr_hl`, six
/// decimal digits of milliseconds).
fn hard_liveliness(c: &CreateClientPayload) -> Option<Duration> {
    let props = c.properties.as_ref()?;
    let (_, v) = props.iter().find(|(k, _)| k == "uxr_hl")?;
    let ms: u64 = v.trim().parse().ok()?;
    (ms > 0).then(|| Duration::from_millis(ms.max(100)))
}

/// Why a reply could not be queued.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SendError {
    /// The client has no session (any more).
    #[error("no such client")]
    NoClient,
    /// The output stream's queue is full; the reply was dropped.
    #[error("output queue full")]
    QueueFull,
    /// The reply does not fit one submessage.
    #[error("reply too large")]
    TooLarge,
    /// The read asked for an undefined DataFormat.
    #[error("undefined data format")]
    BadFormat,
}

/// A sample for [`Agent::send_data`].
#[derive(Debug, Clone, Copy)]
pub struct DataReply<'a> {
    /// The READ_DATA answered.
    pub request: BaseObjectRequest,
    /// The DataFormat the read asked for.
    pub format: u8,
    /// The serialized sample.
    pub sample: &'a [u8],
    /// Whether `sample` is little endian.
    pub little_endian: bool,
    /// [`crate::wire::sample::sample_state`] bits (0 = alive), for the formats with SampleInfo.
    pub state: u8,
    /// Sequence number of the sample within its read, for the formats with SampleInfo.
    pub sequence_number: u32,
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

impl<A: Copy + Eq + Hash + Debug> Agent<A> {
    /// An agent with no sessions.
    pub fn new(config: AgentConfig) -> Self {
        Agent {
            config,
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

    /// The sessions whose snapshot may have changed, and the sessions deleted, since the
    /// last call (empty unless `track_sessions`). A front-end stores the snapshots before
    /// it sends what the core produced, so what a client saw acknowledged or numbered is
    /// never behind what the stored state says.
    ///
    /// Sessions whose input positions changed are always returned; those where only the
    /// output side changed only with `with_output` (a successor copes with output state a
    /// little behind: its clients' ACKNACKs tell it where they are).
    pub fn take_session_changes(&mut self, with_output: bool) -> (Vec<ClientKey>, Vec<ClientKey>) {
        let mut changed: HashSet<ClientKey> = self.changed_input.drain().collect();
        if with_output {
            changed.extend(self.changed.drain());
        }
        (
            changed.into_iter().collect(),
            std::mem::take(&mut self.removed),
        )
    }

    /// The state a successor front-end needs to take a session over, with its endpoint
    /// encoded by `endpoint`.
    pub fn snapshot(
        &self,
        key: ClientKey,
        endpoint: impl Fn(A) -> Vec<u8>,
    ) -> Option<SessionSnapshot> {
        let c = self.clients.get(&key)?;
        let mut reliable_in: Vec<(u8, u16)> = c
            .reliable_in
            .iter()
            .map(|(s, i)| (*s, i.expected()))
            .collect();
        let mut best_effort_in: Vec<(u8, u16)> = c
            .best_effort_in
            .iter()
            .filter_map(|(s, i)| Some((*s, i.last()?)))
            .collect();
        let mut reliable_out: Vec<OutputSnapshot> = c
            .reliable_out
            .iter()
            .map(|(s, o)| OutputSnapshot {
                stream_id: *s,
                next: o.reliable.next_seq(),
                // A stream still asking the client where it is has nothing to resend.
                in_flight: (!o.reliable.is_resyncing()).then(|| {
                    o.reliable
                        .in_flight()
                        .map(|(seq, m)| (seq, m.to_vec()))
                        .collect()
                }),
                queued: o.queue.iter().cloned().collect(),
            })
            .collect();
        reliable_out.sort_by_key(|o| o.stream_id);
        let mut best_effort_out: Vec<(u8, u16)> =
            c.best_effort_out.iter().map(|(s, n)| (*s, *n)).collect();
        for list in [&mut reliable_in, &mut best_effort_in, &mut best_effort_out] {
            list.sort_unstable();
        }
        Some(SessionSnapshot {
            key,
            session_id: c.session_id,
            endpoint: endpoint(c.addr),
            mtu: c.mtu,
            dialect: c.dialect,
            dead_time: c.dead_time,
            reliable_in,
            best_effort_in,
            reliable_out,
            best_effort_out,
        })
    }

    /// Takes over a session a front-end that died stored (its object graph is the bridge's
    /// business): the client goes on where it was. Its reliable output streams first ask
    /// the client where it is (a HEARTBEAT now); a session of this key that exists already
    /// is kept instead.
    pub fn restore(&mut self, now: Instant, snapshot: &SessionSnapshot, endpoint: A) -> bool {
        if self.clients.contains_key(&snapshot.key) || self.clients.len() >= self.config.max_clients
        {
            return false;
        }
        let (in_window, out_window) = (self.config.input_window, self.config.output_window);
        let reliable_out = snapshot
            .reliable_out
            .iter()
            .map(|o| {
                let reliable = match &o.in_flight {
                    Some(m) => ReliableOutput::restored(o.stream_id, out_window, o.next, m.clone()),
                    None => ReliableOutput::resuming(o.stream_id, out_window, o.next),
                };
                (
                    o.stream_id,
                    OutStream {
                        queued_bytes: o.queued.iter().map(Vec::len).sum(),
                        reliable,
                        queue: o.queued.iter().cloned().collect(),
                    },
                )
            })
            .collect();
        // A HEARTBEAT now: the client says what it lacks (or, resyncing, where it is).
        let resyncing = snapshot
            .reliable_out
            .iter()
            .any(|o| o.in_flight.as_ref().is_none_or(|m| !m.is_empty()) || !o.queued.is_empty());
        let mut client = ProxyClient::new(
            snapshot.key,
            snapshot.session_id,
            endpoint,
            snapshot.mtu.clamp(64, self.config.max_message_size.max(64)),
            snapshot.dialect,
            snapshot.dead_time,
            now,
            &self.config,
        );
        // Not stored: eProsima clients announce their MTU, spec clients do not.
        client.mtu_announced = snapshot.dialect == Dialect::Eprosima;
        client.reliable_in = snapshot
            .reliable_in
            .iter()
            .map(|(s, e)| (*s, ReliableInput::resuming(in_window, *e)))
            .collect();
        client.best_effort_in = snapshot
            .best_effort_in
            .iter()
            .map(|(s, l)| (*s, BestEffortInput::resuming(*l)))
            .collect();
        client.reliable_out = reliable_out;
        client.best_effort_out = snapshot.best_effort_out.iter().copied().collect();
        client.heartbeat_due = resyncing.then_some(now);
        // Not a fresh session: a CREATE_CLIENT now is the client's own restart.
        client.established_at = now
            .checked_sub(self.config.duplicate_create_guard)
            .unwrap_or(now);
        client.streams_used = true;
        self.clients.insert(snapshot.key, client);
        self.by_addr.insert(endpoint, snapshot.key);
        // Output that waited for window room goes out as room allows.
        self.flush_client(now, snapshot.key);
        self.schedule(snapshot.key);
        tracing::info!(client = %snapshot.key, session = snapshot.session_id, ?endpoint, "session taken over from the previous front-end");
        true
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
        if let Some(due) = c.next_due() {
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
        client.detached = false;
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
        let input = client
            .reliable_in
            .entry(stream)
            .or_insert_with(|| ReliableInput::new(window));
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
                } else if let Some(input) = client.reliable_in.get_mut(&stream) {
                    input.store_early(header.sequence_nr, bytes.to_vec());
                }
            }
            Arrival::InOrder => {
                if room_for(sink, bytes, hlen) {
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

    fn handle_sessionless(
        &mut self,
        now: Instant,
        src: A,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        for raw in Submessages::new(bytes, hlen) {
            let raw = match raw {
                Ok(r) => r,
                Err(e) => return self.drop_input(e.reason(), bytes),
            };
            let payload = match raw.decode() {
                Ok(p) => p,
                // eProsima's client always declares 16 bytes for CREATE_CLIENT, also when it
                // appends properties (hard liveliness, shared memory) and then the MTU after
                // them: read the CREATE_CLIENT from the rest of the datagram instead.
                Err(DecodeError::Truncated) if raw.id == submessage_id::CREATE_CLIENT => {
                    let rest = bytes.get(raw.offset + 4..).unwrap_or_default();
                    match Payload::decode(raw.id, raw.flags, rest) {
                        Ok(Payload::CreateClient(c)) => {
                            tracing::trace!("CREATE_CLIENT longer than its declared length");
                            return self.create_client(now, src, &c, sink);
                        }
                        Ok(_) => return,
                        Err(e) => return self.drop_input(e.reason(), bytes),
                    }
                }
                Err(e) => return self.drop_input(e.reason(), bytes),
            };
            match payload {
                Payload::CreateClient(c) => self.create_client(now, src, &c, sink),
                Payload::GetInfo(g) if self.once(Reply::Info) => {
                    let dialect = self.config.dialect.unwrap_or_default();
                    self.reply_info(src, header, g.base, false, dialect)
                }
                Payload::GetInfo(_) => self.count_drop("repeated_request"),
                _ => self.drop_input("no_session", bytes),
            }
        }
    }

    fn create_client(
        &mut self,
        now: Instant,
        src: A,
        c: &CreateClientPayload,
        sink: &mut impl OperationSink,
    ) {
        let reply_header = MessageHeader::new(c.session_id, stream_id::NONE, 0, c.client_key);
        let result = if c.cookie != XRCE_COOKIE {
            status::ERR_INVALID_DATA
        } else if c.version[0] != XRCE_VERSION[0] {
            status::ERR_INCOMPATIBLE
        } else if c.session_id == 0x00 || c.session_id == 0x80 || c.client_key == ClientKey::INVALID
        {
            status::ERR_INVALID_DATA
        } else if !self.config.admission.admits(c.client_key) {
            self.count_drop("key_not_allowed");
            status::ERR_DENIED
        } else if !self.clients.contains_key(&c.client_key)
            && self.clients.len() >= self.config.max_clients
        {
            status::ERR_RESOURCES
        } else {
            status::OK
        };
        if result == status::OK {
            // Another client at the same source address is gone (it was restarted with a new key).
            if let Some(other) = self
                .by_addr
                .get(&src)
                .copied()
                .filter(|k| *k != c.client_key)
            {
                self.remove_client(other, sink);
            }
            // At least 64 (so fragments carry data), at most what the transport carries.
            let mtu = c
                .mtu
                .unwrap_or(self.config.default_mtu)
                .clamp(64, self.config.max_message_size.max(64));
            let dialect = self
                .config
                .dialect
                .unwrap_or(Dialect::for_vendor(c.vendor_id));
            let dead_time = hard_liveliness(c).or(self.config.client_dead_time);
            match self.clients.get_mut(&c.client_key) {
                Some(existing) if existing.session_id == c.session_id => {
                    // The same session again: a restarted client starts its streams at 0, so
                    // ours restart too; its objects stay (§7.8.2.1 "no action"). A copy of the
                    // CREATE_CLIENT that arrives just after the client began using its streams
                    // is a network duplicate or a stale retry, not a restart: keep the streams.
                    // From another endpoint (a new connection, a new source port) it is a
                    // restart whatever the timing.
                    let stale = existing.streams_used
                        && existing.addr == src
                        && !existing.detached
                        && now.saturating_duration_since(existing.established_at)
                            < self.config.duplicate_create_guard;
                    if stale {
                        self.stats.count("duplicate_create_client");
                    } else {
                        existing.reset_streams();
                        existing.established_at = now;
                    }
                    existing.mtu = mtu;
                    existing.mtu_announced = c.mtu.is_some();
                    existing.last_heard = now;
                    existing.detached = false;
                    existing.dialect = dialect;
                    existing.dead_time = dead_time;
                    let old = existing.addr;
                    existing.addr = src;
                    if self.by_addr.get(&old) == Some(&c.client_key) {
                        self.by_addr.remove(&old);
                    }
                    self.by_addr.insert(src, c.client_key);
                    tracing::info!(client = %c.client_key, session = c.session_id, "session re-established");
                }
                existing => {
                    if existing.is_some() {
                        self.remove_client(c.client_key, sink);
                    }
                    let mut client = ProxyClient::new(
                        c.client_key,
                        c.session_id,
                        src,
                        mtu,
                        dialect,
                        dead_time,
                        now,
                        &self.config,
                    );
                    client.mtu_announced = c.mtu.is_some();
                    self.clients.insert(c.client_key, client);
                    self.by_addr.insert(src, c.client_key);
                    sink.operation(Operation::ClientCreated {
                        client: c.client_key,
                    });
                    tracing::info!(client = %c.client_key, session = c.session_id, mtu, ?dialect, ?dead_time, "session created");
                }
            }
            self.schedule(c.client_key);
            self.touch_input(c.client_key);
        } else if result == status::ERR_DENIED {
            if self.denied_logged.len() < 1024 && self.denied_logged.insert(c.client_key) {
                tracing::warn!(client = %c.client_key, "CREATE_CLIENT refused: the key is not in --allow-keys (further attempts of this key are counted)");
            } else {
                tracing::debug!(client = %c.client_key, "CREATE_CLIENT refused: key not allowed");
            }
        } else {
            tracing::info!(client = %c.client_key, status = result, "CREATE_CLIENT refused");
        }
        // Without a ResultStatus a refusal cannot be reported: only a forced spec dialect drops it.
        let forced_spec = self.config.dialect == Some(Dialect::Spec);
        let payload = Payload::StatusAgent(StatusAgentPayload {
            result: (!forced_spec).then(|| ResultStatus::new(result)),
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id: self.config.vendor_id,
            properties: None,
        });
        let mut b = MessageBuilder::new(reply_header);
        let _ = b.push(&payload, true);
        self.push_transmit(src, b.finish());
    }

    fn reply_info(
        &mut self,
        dst: A,
        header: MessageHeader,
        request: BaseObjectRequest,
        in_session: bool,
        dialect: Dialect,
    ) {
        // Available, no locators advertised (discovery answers with them, see `discovery`).
        let m = agent_info_message(
            header,
            request,
            in_session,
            dialect,
            self.config.vendor_id,
            Vec::new(),
        );
        self.push_transmit(dst, m);
    }

    fn client_dialect(&self, key: ClientKey) -> Dialect {
        self.clients
            .get(&key)
            .map_or(Dialect::default(), |c| c.dialect)
    }

    /// Tells the core that a transport endpoint is gone for good (a TCP connection closed).
    /// The session there is kept, with its objects: a client that reconnects and creates its
    /// session again with the same key continues with them, as over UDP. Until it is heard
    /// again nothing is sent to it (replies meanwhile wait in its reliable streams, bounded as
    /// ever). Returns whether a session was at that endpoint.
    pub fn endpoint_closed(&mut self, endpoint: A) -> bool {
        let Some(key) = self.by_addr.remove(&endpoint) else {
            return false;
        };
        match self.clients.get_mut(&key) {
            Some(c) if c.addr == endpoint => {
                c.detached = true;
                c.heartbeat_due = None;
                tracing::info!(client = %key, "client's endpoint closed; session kept");
                self.schedule(key);
                true
            }
            _ => false,
        }
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

    fn remove_client(&mut self, key: ClientKey, sink: &mut impl OperationSink) {
        if let Some(c) = self.clients.remove(&key) {
            if self.config.track_sessions {
                self.changed.remove(&key);
                self.changed_input.remove(&key);
                self.removed.push(key);
            }
            if self.by_addr.get(&c.addr) == Some(&key) {
                self.by_addr.remove(&c.addr);
            }
            sink.operation(Operation::ClientDeleted { client: key });
            tracing::info!(client = %key, "session deleted");
        }
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
            Payload::Create(c) => sink.operation(Operation::Create {
                client: key,
                create: &c,
                little_endian: le,
            }),
            Payload::Delete(d) if d.object_id == ObjectId::CLIENT => {
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
            Payload::Delete(d) => sink.operation(Operation::Delete {
                client: key,
                request: d,
            }),
            Payload::WriteData(d) => {
                self.stats.samples_in += 1;
                if let Some(c) = self.clients.get_mut(&key) {
                    c.counters.samples_in += 1;
                }
                let dialect = self.client_dialect(key);
                sink.operation(Operation::Write {
                    client: key,
                    stream_id: stream,
                    data: d,
                    little_endian: le,
                    dialect,
                })
            }
            Payload::ReadData(r) => sink.operation(Operation::Read {
                client: key,
                request: r.base,
                spec: &r.spec,
            }),
            Payload::GetInfo(_) if !self.once(Reply::Info) => self.count_drop("repeated_request"),
            Payload::GetInfo(g)
                if g.base.object_id == ObjectId::AGENT || g.base.object_id == ObjectId::CLIENT =>
            {
                if let Some(c) = self.clients.get(&key) {
                    let (addr, h, d) = (c.addr, c.header(stream_id::NONE, 0), c.dialect);
                    self.reply_info(addr, h, g.base, true, d);
                }
            }
            Payload::GetInfo(g) => sink.operation(Operation::GetInfo {
                client: key,
                request: g.base,
                info_mask: g.info_mask,
            }),
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
                        c.reliable_in
                            .entry(h.stream_id)
                            .or_insert_with(|| ReliableInput::new(window))
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
        match c
            .reassembly
            .entry(stream)
            .or_default()
            .push(data, last, max)
        {
            Ok(None) => {}
            Ok(Some(whole)) => {
                for raw in Submessages::reassembled(&whole) {
                    match raw {
                        Ok(raw) => self.dispatch(now, key, stream, raw, true, sink),
                        Err(e) => return self.drop_input(e.reason(), &whole),
                    }
                }
            }
            Err(_) => self.count_drop("reassembly_too_large"),
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

    /// Removes a client that asked for its own deletion, after its STATUS went out.
    fn finish_client(&mut self, now: Instant, key: ClientKey, sink: &mut impl OperationSink) {
        if self.clients.get(&key).is_some_and(|c| c.delete_requested) {
            self.flush_client(now, key);
            self.remove_client(key, sink);
        }
    }

    /// Moves queued reliable submessages into free window slots and sends them.
    fn flush_client(&mut self, now: Instant, key: ClientKey) {
        self.touch(key);
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let mut out = Vec::new();
        for (sid, s) in c.reliable_out.iter_mut() {
            while s.reliable.has_room() {
                let Some(sub) = s.queue.pop_front() else {
                    break;
                };
                s.queued_bytes -= sub.len();
                let mut msg = Vec::with_capacity(8 + sub.len());
                MessageHeader::new(c.session_id, *sid, s.reliable.next_seq(), c.key)
                    .encode(&mut msg);
                msg.extend_from_slice(&sub);
                s.reliable.record(msg.clone());
                out.push(msg);
            }
        }
        if c.detached {
            // Kept for when it comes back; its streams restart if it creates its session anew.
            return;
        }
        let unacked = c.reliable_out.values().any(|s| s.reliable.unacked() > 0);
        let mut schedule = false;
        if unacked && c.heartbeat_due.is_none() {
            c.heartbeat_due = Some(now + c.heartbeat_interval);
            schedule = true;
        }
        let addr = c.addr;
        for m in out {
            self.push_transmit(addr, m);
        }
        if schedule {
            self.schedule(key);
        }
    }

    /// One message if the submessage fits the client's MTU, else FRAGMENTs filling it, as
    /// the reference agent sends them.
    fn fit_or_fragment(c: &ProxyClient<A>, sub: Vec<u8>) -> Vec<Vec<u8>> {
        let header_len = MessageHeader::encoded_len(c.session_id);
        if header_len + sub.len() <= c.mtu as usize {
            vec![sub]
        } else {
            fragments(&sub, c.mtu as usize - header_len - 4)
        }
    }

    fn encode_submessage(payload: &Payload<'_>, little_endian: bool) -> Result<Vec<u8>, SendError> {
        crate::wire::encode_submessage(payload, little_endian).map_err(|_| SendError::TooLarge)
    }

    /// Queues submessages (each one message) on a reliable output stream: all or none.
    fn queue_reliable(
        &mut self,
        key: ClientKey,
        stream: u8,
        subs: Vec<Vec<u8>>,
    ) -> Result<(), SendError> {
        let (window, max_queue) = (self.config.output_window, self.config.max_output_queue);
        let max_bytes = self.config.max_output_queue_bytes;
        let c = self.clients.get_mut(&key).ok_or(SendError::NoClient)?;
        let s = c.reliable_out.entry(stream).or_insert_with(|| OutStream {
            queued_bytes: 0,
            reliable: ReliableOutput::new(stream, window),
            queue: VecDeque::new(),
        });
        let bytes: usize = subs.iter().map(Vec::len).sum();
        if s.queue.len() + subs.len() > max_queue || s.queued_bytes + bytes > max_bytes {
            self.count_drop("output_queue_full");
            return Err(SendError::QueueFull);
        }
        s.queued_bytes += bytes;
        s.queue.extend(subs);
        Ok(())
    }

    fn queue_status(&mut self, key: ClientKey, request: BaseObjectRequest, result: ResultStatus) {
        let payload = Payload::Status(BaseObjectReply {
            related: request,
            result,
        });
        if let Ok(sub) = Self::encode_submessage(&payload, true) {
            let _ = self.queue_reliable(key, stream_id::BUILTIN_RELIABLE, vec![sub]);
        }
    }

    /// Queues a STATUS reply (on the built-in reliable stream, as the reference agent does).
    pub fn send_status(
        &mut self,
        now: Instant,
        key: ClientKey,
        request: BaseObjectRequest,
        result: ResultStatus,
    ) -> Result<(), SendError> {
        if !self.clients.contains_key(&key) {
            return Err(SendError::NoClient);
        }
        self.queue_status(key, request, result);
        self.flush_client(now, key);
        Ok(())
    }

    /// Queues an INFO reply about one of the client's objects on the built-in reliable
    /// stream: `config` is the object's description when the client asked for it.
    pub fn send_info(
        &mut self,
        now: Instant,
        key: ClientKey,
        request: BaseObjectRequest,
        result: ResultStatus,
        config: Option<&ObjectVariant>,
    ) -> Result<(), SendError> {
        let dialect = self.dialect(key).ok_or(SendError::NoClient)?;
        let reply = BaseObjectReply {
            related: request,
            result,
        };
        let info = ObjectInfo {
            activity: None,
            config: config.cloned().map(ObjectConfig::Object),
        };
        let buf = info_bytes(reply, &info, dialect);
        let payload = Payload::Info(InfoPayload {
            reply,
            object_info: buf.get(BaseObjectReply::LEN..).unwrap_or_default(),
        });
        let sub = Self::encode_submessage(&payload, true)?;
        let c = self.clients.get(&key).ok_or(SendError::NoClient)?;
        let parts = Self::fit_or_fragment(c, sub);
        self.queue_reliable(key, stream_id::BUILTIN_RELIABLE, parts)?;
        self.flush_client(now, key);
        Ok(())
    }

    /// Queues a DATA reply for a read request on `stream` (0 = built-in reliable), in the
    /// DataFormat the read asked for.
    pub fn send_data(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        reply: DataReply<'_>,
    ) -> Result<(), SendError> {
        let dropped_before = self.stats.dropped_total;
        let result = self.queue_data(now, key, stream, reply);
        self.touch(key);
        let dropped = self.stats.dropped_total - dropped_before;
        let queued = result.is_ok() && dropped == 0;
        if let Some(c) = self.clients.get_mut(&key) {
            if queued {
                c.counters.samples_out += 1;
            } else {
                // Not queued (an error is counted by the caller in its own drops).
                c.counters.dropped += dropped.max(1);
            }
        }
        if queued {
            self.stats.samples_out += 1;
        }
        result
    }

    fn queue_data(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        reply: DataReply<'_>,
    ) -> Result<(), SendError> {
        let c = self.clients.get_mut(&key).ok_or(SendError::NoClient)?;
        let little_endian = reply.little_endian;
        let mut wrapped = Vec::new();
        let data = if reply.format == data_format::DATA {
            reply.sample
        } else {
            let offset = now.saturating_duration_since(c.established_at).as_millis();
            let info = SampleInfo {
                state: reply.state,
                detail: SampleInfoDetail::Both {
                    sequence_number: reply.sequence_number,
                    session_time_offset: u32::try_from(offset).unwrap_or(u32::MAX),
                },
            };
            let one = [SampleRef {
                info: Some(info),
                data: reply.sample,
            }];
            encode_samples(reply.format, &one, little_endian, c.dialect, &mut wrapped)
                .map_err(|_| SendError::BadFormat)?;
            &wrapped
        };
        let payload = Payload::Data(DataPayload {
            base: reply.request,
            format: reply.format,
            data,
        });
        let stream = if stream == stream_id::NONE {
            stream_id::BUILTIN_RELIABLE
        } else {
            stream
        };
        if stream_id::is_reliable(stream) {
            let sub = crate::wire::encode_large_submessage(&payload, little_endian)
                .map_err(|_| SendError::TooLarge)?;
            let parts = Self::fit_or_fragment(c, sub);
            self.queue_reliable(key, stream, parts)?;
            self.flush_client(now, key);
        } else if c.detached {
            self.count_drop("endpoint_closed");
        } else {
            let seq = c.best_effort_out.entry(stream).or_insert(0);
            let mut b = MessageBuilder::new(MessageHeader::new(c.session_id, stream, *seq, c.key));
            b.push(&payload, little_endian)
                .map_err(|_| SendError::TooLarge)?;
            let message = b.finish();
            // A client that announced its MTU cannot take a bigger message (the eProsima
            // client's UDP buffer truncates it, its serial or TCP framing rejects it); for one
            // that announced none the MTU is assumed (for fragments), so only what the
            // transport carries bounds its best-effort messages, as before.
            let limit = if c.mtu_announced {
                c.mtu
            } else {
                self.config.max_message_size
            };
            if message.len() > usize::from(limit) {
                // A best-effort stream cannot fragment: dropped, as the reference agent does,
                // without using a sequence number; counted here (the client's drops too),
                // so not an error for the caller to count again.
                let (key, len) = (c.key, message.len());
                self.count_drop("over_mtu");
                let n = self.stats.dropped("over_mtu");
                if n.is_power_of_two() {
                    tracing::warn!(client = %key, mtu = limit, message = len, dropped = n, "best-effort sample dropped: larger than the client's MTU (read it on a reliable stream, which fragments, or build the client with a larger MTU); further ones are counted");
                }
                return Ok(());
            }
            *seq = seq.wrapping_add(1);
            let addr = c.addr;
            self.push_transmit(addr, message);
        }
        Ok(())
    }

    /// Sends due HEARTBEATs and liveliness probes, and deletes the sessions of clients that
    /// stayed silent past their dead time (their objects go with them through `sink`). Only
    /// the clients whose timer fell due are looked at.
    pub fn handle_timeout(&mut self, now: Instant, sink: &mut impl OperationSink) {
        let max_period = self.config.max_heartbeat_period;
        let base_period = self.config.heartbeat_period;
        let mut out = Vec::new();
        let mut dead = Vec::new();
        let mut due_clients = Vec::new();
        while let Some(Reverse((t, key))) = self.timers.peek().copied() {
            if t > now {
                break;
            }
            self.timers.pop();
            // Only the client's live entry counts (older ones were superseded).
            if let Some(c) = self.clients.get_mut(&key).filter(|c| c.timer == Some(t)) {
                c.timer = None;
                due_clients.push(key);
            }
        }
        for key in &due_clients {
            let Some(c) = self.clients.get_mut(key) else {
                continue;
            };
            if let Some(dead_time) = c.dead_time {
                let silence = now.saturating_duration_since(c.last_heard);
                if silence >= dead_time {
                    dead.push((c.key, silence));
                    continue;
                }
                if !c.detached && c.liveliness_due().is_some_and(|d| d <= now) {
                    // GET_INFO about the agent, as a ping: a live client answers with INFO.
                    let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
                    let probe = crate::wire::GetInfoPayload {
                        base: BaseObjectRequest {
                            request_id: LIVELINESS_PROBE_ID,
                            object_id: ObjectId::AGENT,
                        },
                        info_mask: 0x02,
                    };
                    let _ = b.push(&Payload::GetInfo(probe), true);
                    out.push((c.addr, b.finish()));
                    c.last_probe = Some(now);
                }
            }
            if c.detached {
                c.heartbeat_due = None;
            } else if c.heartbeat_due.is_some_and(|d| d <= now) {
                let mut any = false;
                for s in c.reliable_out.values() {
                    if let Some(hb) = s.reliable.heartbeat() {
                        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
                        let _ = b.push(&Payload::Heartbeat(hb), true);
                        out.push((c.addr, b.finish()));
                        any = true;
                    }
                }
                if any {
                    // Unanswered so far: the next one waits twice as long, unless the
                    // client was heard since the last one. A client that keeps talking is
                    // alive and its ACKNACKs were likely lost on the way (a flooded socket
                    // drops datagrams whatever their kind): every back-off step stalls its
                    // reliable output that much longer. Measured on a flooded socket, a
                    // back-off up to 400 ms for such clients left a reliable reader's
                    // median latency at 1.1 s with 6 % of its samples lost to its DDS
                    // history; keeping the base period, 0.09-0.28 s and none lost. The cost:
                    // a client that talks but never acknowledges gets ten small HEARTBEATs a
                    // second. Only a silent client is probed less and less, its period
                    // growing up to `max_heartbeat_period`.
                    let heard = now.saturating_duration_since(c.last_heard) < c.heartbeat_interval;
                    c.heartbeat_interval = if heard {
                        base_period
                    } else {
                        (c.heartbeat_interval * 2).min(max_period)
                    };
                }
                c.heartbeat_due = any.then_some(now + c.heartbeat_interval);
            }
        }
        for key in due_clients {
            self.schedule(key);
        }
        for (a, m) in out {
            self.push_transmit(a, m);
        }
        for (key, silence) in dead {
            tracing::warn!(client = %key, silent_ms = silence.as_millis() as u64, "client silent past its dead time; deleting its session");
            self.count_drop("client_dead");
            self.remove_client(key, sink);
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

/// A sink that takes nothing: for tests and for fuzzing the core.
#[derive(Debug, Default)]
pub struct NullSink;

impl OperationSink for NullSink {
    fn has_room(&self) -> bool {
        true
    }
    fn operation(&mut self, _: Operation<'_>) {}
}
