//! The front-end's side of the IPC contract: operations out to the DDS worker, replies and
//! samples back, and what makes sessions survive a worker restart.
//!
//! * Every client's object graph and active reads are kept here ([`ObjectGraph`]).
//! * At most [`IN_FLIGHT_WINDOW`] operations are unprocessed by the worker at once, so its
//!   queue never overflows; the rest wait in a bounded outbox (best-effort writes in a
//!   short queue of their own, shared fairly among the clients: [`crate::waiting_writes`]).
//! * Writes that came on reliable streams are retained until the worker has executed them
//!   and a settle time has passed (RustDDS sends asynchronously, so "executed" is not yet
//!   "on the wire").
//! * When a new worker generation is announced, the graphs are replayed in creation order,
//!   reads re-issued and retained writes sent again, before anything new.
//! * When the outbox or the retention is full, [`OperationSink::has_room`] says no: the agent
//!   core then stops acknowledging reliable messages and clients send them again later.

use std::collections::{HashMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use xrce_common::fault::{self, Fault};
use xrce_common::ipc::shm::{IpcNode, Receiver, Sender, ServiceKind, ShmError};
use xrce_common::ipc::{
    self, Encode, Reply, ReplyMessage, Request, RequestMessage, Route, IN_FLIGHT_WINDOW,
};
use xrce_common::session::agent::{Agent, DataReply, Operation, OperationSink};
use xrce_common::session::budget::{BudgetSplit, Episodes, DEFAULT_MEMORY_BUDGET};
use xrce_common::session::graph::{ActiveRead, CreateDecision, GraphObject, ObjectGraph};
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::sample::{is_defined_format, sample_state};
use xrce_common::wire::{
    data_format, object_kind, status, stream_id, BaseObjectRequest, ClientKey, Dialect, ObjectId,
    ObjectVariant, RequestId, ResultStatus,
};

use crate::object_budget::ObjectBudget;
use crate::waiting_writes::{Room, WaitingWrites};

/// GET_INFO mask bit asking for the object's configuration.
const INFO_CONFIGURATION: u32 = 0x01;

/// Operations waiting for the window before new ones are refused (flow control).
pub const OUTBOX_MAX: usize = 8192;
/// Operations one client message may carry that still go to the worker at once when client
/// operations are only accepted that way ([`Bridge::set_hand_over_at_once`]): a 512-byte
/// message (the eProsima client's default MTU) holds at most about 40 small WRITE_DATA.
/// The operations of a larger message beyond this wait in the outbox.
pub const HAND_OVER_HEADROOM: u64 = 48;
/// Operations in flight (hand-over mode) that best-effort writes leave free beyond the
/// [`HAND_OVER_HEADROOM`] a largest reliable message needs: best-effort writes go only while
/// `in_flight + HAND_OVER_HEADROOM + BEST_EFFORT_RESERVE < IN_FLIGHT_WINDOW` (136 of 192), so
/// a best-effort flood alone never fills the window against reliable messages and control
/// operations (which ask room for what they carry: [`OperationSink::has_room_for`]). Small:
/// the worker handles what is in flight in batches, and a shallower window costs
/// best-effort throughput (a 48-operation reserve cost a fifth of it at 1 kB samples).
pub const BEST_EFFORT_RESERVE: u64 = 8;
/// Best-effort writes (hand-over mode) that wait in this process for the window's
/// best-effort share when the worker has not yet taken the ones before: a worker pass that
/// stalls for a while (DDS discovery, a burst of another client's) is absorbed instead of
/// dropping every write that comes meanwhile (50 ms of 20,000 samples/s, 17 ms of 60,000/s;
/// measured, samples lost a run: 1,000 clients at 20,000/s 0 against 15-125, 100 clients at
/// 60,000/s 16-910 against 2,807-8,416). The clients take turns and share it: when it is
/// full (or holds [`BEST_EFFORT_WAITING_MAX_BYTES`]), a write of a client holding less than
/// another takes the place of that other's newest, and the client holding the most has its
/// write dropped (counted) and is not queued for [`BEST_EFFORT_SHED_HOLD`]
/// ([`crate::waiting_writes`]). Nothing was acknowledged for them, so losing them with this
/// process breaks no promise.
pub const BEST_EFFORT_WAITING_MAX: usize = 1024;
/// Bytes of best-effort writes waiting (see [`BEST_EFFORT_WAITING_MAX`]).
pub const BEST_EFFORT_WAITING_MAX_BYTES: usize = 1 << 20;
/// How long a client's best-effort writes are not queued after it overflowed the waiting
/// queue (held the most of it when it was full): that is an overload, not a stall, and
/// queueing under an overload only feeds the flood (the worker and this process run at full
/// load for it) at the expense of every other client's service (measured: a quiet reliable
/// pair sharing the socket with a 10x flood fell from 660-824 to 620 samples/s). Meanwhile
/// its best-effort writes go to the worker only when nothing waits and the window's share
/// has room, else are dropped; other clients' writes still wait. A client whose newest
/// write was dropped to make room for a lighter client's is held as well.
pub const BEST_EFFORT_SHED_HOLD: Duration = Duration::from_millis(200);
/// Queued operations (outbox mode) beyond which best-effort writes are dropped rather than
/// queued: stale best-effort data is worth little, and reliable operations queued behind it
/// would wait for all of it.
pub const BEST_EFFORT_OUTBOX_MAX: usize = 1024;
/// Absolute bound of the outbox (`has_room` keeps it below [`OUTBOX_MAX`] between messages).
pub const OUTBOX_HARD_MAX: usize = 4 * OUTBOX_MAX;
/// Bytes of queued operations before new ones are refused (flow control; samples reach 1 MiB).
pub const OUTBOX_MAX_BYTES: usize = 64 << 20;
/// Reliable writes kept for a possible resend before new ones are refused (flow control);
/// writes are released once acknowledged by DDS readers, at the latest after
/// [`SETTLE_TIME`], which with readers that never acknowledge caps reliable throughput near
/// 43,000 samples/s.
pub const RETAIN_MAX: usize = 65_536;
/// Bytes of retained writes before new ones are refused (flow control).
pub const RETAIN_MAX_BYTES: usize = 64 << 20;
/// A read is paused when its client's reliable stream has this many messages (or bytes)
/// waiting for window room: its samples then wait in the DDS reader, not in agent memory.
pub const PAUSE_READ_AT: (usize, usize) = (1024, 1 << 20);
/// A paused read resumes when the backlog is down to this.
pub const RESUME_READ_AT: (usize, usize) = (256, 256 << 10);

/// Operations in flight below which a best-effort write tells the worker that its progress
/// can wait ([`RequestMessage::progress_can_wait`]): with most of the window free nothing here waits
/// for that progress, so the worker need not wake this process for it (the progress is read
/// on the next wake-up). From a sixth of the window on, progress wakes again, long before
/// the best-effort share (136) or the window (192) fills.
pub const PROGRESS_CAN_WAIT_BELOW: u64 = 32;

/// How long an executed reliable write is kept at most in case the worker dies right after.
/// A write is released as soon as the worker reports that every matched reliable reader of
/// its DDS writer acknowledged it (usually within milliseconds); this bound is for readers
/// that do not acknowledge (RustDDS heartbeats unacknowledged data every 100 ms to 1 s):
/// only writes still unacknowledged at a worker crash are resent to the new worker.
pub const SETTLE_TIME: Duration = Duration::from_millis(1500);

/// Why a bridge could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    /// The shared-memory services could not be opened.
    #[error(transparent)]
    Shm(#[from] ShmError),
    /// Another live front-end of the instance has this id.
    #[error("front-end {id} already runs in agent instance {instance:?}; give each front-end its own id")]
    DuplicateId {
        /// The id.
        id: u32,
        /// The instance.
        instance: String,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Awaited {
    /// The client waits for a STATUS.
    Yes,
    /// Internal or replayed: do not forward the STATUS.
    No,
}

/// Where a best-effort write goes ([`Bridge::best_effort_route`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BestEffortRoute {
    /// To the worker (or, outside hand-over mode, the outbox), as any operation.
    Now,
    /// To the best-effort waiting queue, for the window's best-effort share.
    Wait,
}

/// What a client waits for the STATUS of, by kind of operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PendingKind {
    Create,
    Delete,
    Write,
    Other,
}

impl PendingKind {
    fn of(request: &Request<'_>) -> Self {
        match request {
            Request::Create { .. } => PendingKind::Create,
            Request::Delete => PendingKind::Delete,
            Request::Write { .. } => PendingKind::Write,
            _ => PendingKind::Other,
        }
    }
}

#[derive(Debug)]
struct OwnedOp {
    message: RequestMessage<'static>,
    retain: bool,
    awaited: Awaited,
}

#[derive(Debug)]
struct Retained {
    seq: u64,
    executed_at: Option<Instant>,
    message: RequestMessage<'static>,
}

/// What an entry of a [`ByteQueue`] weighs.
trait Weighed {
    fn weight(&self) -> usize;
}

impl Weighed for OwnedOp {
    fn weight(&self) -> usize {
        self.message.encoded_len()
    }
}

impl Weighed for Retained {
    fn weight(&self) -> usize {
        self.message.encoded_len()
    }
}

/// A FIFO that knows how many bytes it holds (so memory is bounded by bytes, not entries).
#[derive(Debug)]
struct ByteQueue<T> {
    items: VecDeque<T>,
    bytes: usize,
}

impl<T> Default for ByteQueue<T> {
    fn default() -> Self {
        ByteQueue {
            items: VecDeque::new(),
            bytes: 0,
        }
    }
}

impl<T: Weighed> ByteQueue<T> {
    fn push_back(&mut self, t: T) {
        self.bytes += t.weight();
        self.items.push_back(t);
    }

    fn push_front(&mut self, t: T) {
        self.bytes += t.weight();
        self.items.push_front(t);
    }

    fn pop_front(&mut self) -> Option<T> {
        let t = self.items.pop_front()?;
        self.bytes -= t.weight();
        Some(t)
    }

    fn front(&self) -> Option<&T> {
        self.items.front()
    }

    /// Entries in order; callers must not change their weight.
    fn iter_mut(&mut self) -> impl Iterator<Item = &mut T> {
        self.items.iter_mut()
    }

    fn len(&self) -> usize {
        self.items.len()
    }

    fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    fn take(&mut self) -> VecDeque<T> {
        self.bytes = 0;
        std::mem::take(&mut self.items)
    }

    fn extend(&mut self, items: impl IntoIterator<Item = T>) {
        for t in items {
            self.push_back(t);
        }
    }
}

/// Counters of the bridge.
#[derive(Debug, Default, Clone)]
pub struct BridgeStats {
    /// Operations sent to a worker (replays included).
    pub ops_sent: u64,
    /// Replays performed (new worker generations seen).
    pub replays: u64,
    /// Reliable writes sent again after a worker restart.
    pub writes_resent: u64,
    /// IPC messages dropped (bad, stale generation, send failures).
    pub ipc_dropped: u64,
    /// Operations dropped because the outbox was full (best-effort writes, or beyond the
    /// hard bound).
    pub ops_dropped: u64,
    /// Times a client overflowed the best-effort waiting queue (held the most of it when it
    /// was full): each starts [`BEST_EFFORT_SHED_HOLD`] of shedding that client's writes.
    pub best_effort_sheds: u64,
    /// Samples the agent core could not queue for their client (output queue full).
    pub samples_dropped: u64,
    /// Times a read was paused because its client did not keep up.
    pub reads_paused: u64,
    /// Disposes and unregisters not delivered to a read whose format has no SampleInfo.
    pub instance_ends_skipped: u64,
    /// Samples not delivered again to a read replayed on a new worker (the client had them).
    pub samples_already_delivered: u64,
    /// Retained writes released because DDS readers acknowledged them.
    pub writes_acknowledged: u64,
    /// Retained writes released after [`SETTLE_TIME`] without an acknowledgement.
    pub writes_settled_unacknowledged: u64,
    /// CREATEs refused because their client had its quota of objects.
    pub objects_over_quota: u64,
    /// CREATEs refused because their description did not fit the client's share of the
    /// object-description memory.
    pub objects_over_budget: u64,
    /// Replies meant for the front-end process this one took over from, ignored.
    pub predecessor_replies: u64,
}

/// The front-end's IPC state.
#[derive(Debug)]
pub struct Bridge {
    frontend_id: u32,
    /// This process of the front-end, stamped on every request.
    incarnation: u16,
    /// Accept client operations only when they can go to the worker at once (sessions
    /// are stored for a successor: see [`Bridge::set_hand_over_at_once`]).
    hand_over_at_once: bool,
    node: IpcNode,
    requests: Sender,
    /// Taken while replies are handled straight from shared memory.
    replies: Option<Receiver>,
    announce: Receiver,
    generation: Option<u32>,
    next_seq: u64,
    processed: u64,
    /// Every write up to this operation was acknowledged by the readers of its DDS writer
    /// (reported by the worker; only rises).
    acknowledged: u64,
    outbox: ByteQueue<OwnedOp>,
    /// Best-effort writes waiting for the window's best-effort share (hand-over mode; see
    /// [`BEST_EFFORT_WAITING_MAX`]); sent after the outbox, the clients in turns.
    best_effort_waiting: WaitingWrites<OwnedOp>,
    retained: ByteQueue<Retained>,
    /// Sent operations whose STATUS a client waits for: seq -> (client, request, kind).
    pending: HashMap<u64, (ClientKey, BaseObjectRequest, PendingKind)>,
    graphs: HashMap<ClientKey, ObjectGraph>,
    /// Clients whose objects changed, and clients whose reads changed outside of their own
    /// messages, since [`Bridge::take_graph_changes`] (for the session store).
    objects_changed: HashSet<ClientKey>,
    reads_changed: HashSet<ClientKey>,
    replies_out: Vec<(ClientKey, BaseObjectRequest, ResultStatus)>,
    /// Reads paused because their client does not keep up: (client, reader) -> stream.
    paused: HashMap<(ClientKey, ObjectId), u8>,
    /// INFO replies decided here (GET_INFO about a client's objects).
    infos_out: Vec<(
        ClientKey,
        BaseObjectRequest,
        ResultStatus,
        Option<ObjectVariant>,
    )>,
    dirty: bool,
    stats: BridgeStats,
    /// Most objects per client.
    max_objects: usize,
    /// Memory for object descriptions, shared between addresses and sessions.
    object_budget: ObjectBudget,
    object_budget_episodes: Episodes,
    /// Bytes of queued operations before new ones are refused ([`OUTBOX_MAX_BYTES`] unless
    /// a memory budget says less).
    outbox_max_bytes: usize,
    /// Bytes of retained writes before new ones are refused ([`RETAIN_MAX_BYTES`] unless a
    /// memory budget says less).
    retain_max_bytes: usize,
}

/// `request` of `client` about the object and XRCE request of `base`.
fn message(
    frontend_id: u32,
    client: ClientKey,
    base: BaseObjectRequest,
    request: Request<'_>,
) -> RequestMessage<'_> {
    RequestMessage::new(
        Route::object(frontend_id, client, base.request_id, base.object_id),
        request,
    )
}

impl Bridge {
    /// Opens the services of front-end `frontend_id` in agent instance `instance`, as its
    /// process `incarnation` (nonzero, different from its predecessor's).
    pub fn new(instance: &str, frontend_id: u32, incarnation: u16) -> Result<Self, BridgeError> {
        let node = IpcNode::new(instance, &format!("xrce-frontend-{frontend_id}"))?;
        // Another live front-end with this id would lose its clients' entities to our
        // hello: the later one refuses to start.
        if node.older_namesakes() > 0 {
            return Err(BridgeError::DuplicateId {
                id: frontend_id,
                instance: instance.to_string(),
            });
        }
        let replies = node.receiver(
            &ipc::reply_service(instance, frontend_id),
            ServiceKind::Reply,
        )?;
        let announce = node.receiver(&ipc::announce_service(instance), ServiceKind::Announce)?;
        let requests = node.sender(&ipc::request_service(instance), ServiceKind::Data)?;
        // Announcements made before we subscribed are not delivered (iceoryx2 hands history
        // to late subscribers only when the publisher next acts), so ask: a worker answers
        // every FrontendHello with its WorkerHello on our reply service. Our subscribers
        // exist already, so either this probe or the worker's own announcement reaches us.
        let probe = RequestMessage::new(
            Route {
                incarnation,
                ..Route::frontend(frontend_id)
            },
            Request::FrontendHello,
        );
        requests.send(&probe)?;
        requests.notify()?;
        Ok(Bridge {
            frontend_id,
            incarnation,
            hand_over_at_once: false,
            node,
            requests,
            replies: Some(replies),
            announce,
            generation: None,
            next_seq: 1,
            processed: 0,
            acknowledged: 0,
            outbox: ByteQueue::default(),
            best_effort_waiting: WaitingWrites::new(
                BEST_EFFORT_WAITING_MAX,
                BEST_EFFORT_WAITING_MAX_BYTES,
                BEST_EFFORT_SHED_HOLD,
            ),
            retained: ByteQueue::default(),
            pending: HashMap::new(),
            graphs: HashMap::new(),
            objects_changed: HashSet::new(),
            reads_changed: HashSet::new(),
            replies_out: Vec::new(),
            infos_out: Vec::new(),
            paused: HashMap::new(),
            dirty: false,
            stats: BridgeStats::default(),
            max_objects: xrce_common::session::graph::MAX_OBJECTS,
            object_budget: ObjectBudget::new(BudgetSplit::of(DEFAULT_MEMORY_BUDGET).objects),
            object_budget_episodes: Episodes::default(),
            outbox_max_bytes: OUTBOX_MAX_BYTES,
            retain_max_bytes: RETAIN_MAX_BYTES,
        })
    }

    /// Bounds what this process holds for clients by its parts of a front-end's memory
    /// budget: object descriptions, queued operations and retained writes (the session
    /// core has its own part, [`BudgetSplit::core`]).
    pub fn set_memory_budget(&mut self, split: BudgetSplit) {
        self.object_budget = ObjectBudget::new(split.objects);
        self.outbox_max_bytes = split.outbox.clamp(1 << 20, OUTBOX_MAX_BYTES);
        self.retain_max_bytes = split.retained.clamp(1 << 20, RETAIN_MAX_BYTES);
    }

    /// Bytes of object descriptions held, and their part of the budget.
    pub fn object_memory(&self) -> (usize, usize) {
        self.object_budget.held()
    }

    /// Sets the most objects one client may create (at least 1).
    pub fn set_max_objects_per_client(&mut self, max: usize) {
        self.max_objects = max.max(1);
    }

    /// Whether SIGINT/SIGTERM arrived.
    pub fn termination_requested(&self) -> bool {
        self.node.termination_requested()
    }

    /// Descriptors to wait on: replies and announcements.
    pub fn raw_fds(&self) -> [i32; 2] {
        [
            self.replies.as_ref().map_or(-1, Receiver::raw_fd),
            self.announce.raw_fd(),
        ]
    }

    /// Accept client operations only when they can be handed to the worker at once, so
    /// none waits in this process when it dies (for a front-end whose sessions a successor
    /// takes over).
    pub fn set_hand_over_at_once(&mut self, on: bool) {
        self.hand_over_at_once = on;
    }

    /// A client's object graph.
    pub fn graph(&self, client: ClientKey) -> Option<&ObjectGraph> {
        self.graphs.get(&client)
    }

    /// Takes over a client's graph a predecessor stored (before the first worker is seen:
    /// the replay to it creates the objects and restarts the reads).
    pub fn restore_graph(&mut self, client: ClientKey, graph: ObjectGraph) {
        for o in graph.objects() {
            let mut body = Vec::new();
            o.variant.encode(&mut CdrWriter::new(&mut body, true));
            self.object_budget.set(client, o.object_id, body.len());
        }
        self.graphs.insert(client, graph);
    }

    /// The clients whose objects changed since the last call (their objects are to be
    /// stored).
    pub fn take_objects_changed(&mut self) -> Vec<ClientKey> {
        self.objects_changed.drain().collect()
    }

    /// The clients whose reads changed without a message of theirs since the last call.
    pub fn take_reads_changed(&mut self) -> Vec<ClientKey> {
        self.reads_changed.drain().collect()
    }

    /// How many XRCE objects a client has.
    pub fn object_count(&self, client: ClientKey) -> usize {
        self.graphs.get(&client).map_or(0, ObjectGraph::len)
    }

    /// Counters.
    pub fn stats(&self) -> &BridgeStats {
        &self.stats
    }

    /// The worker generation served, if any.
    pub fn generation(&self) -> Option<u32> {
        self.generation
    }

    /// Operations waiting to be sent (the outbox and the best-effort writes waiting).
    pub fn backlog(&self) -> usize {
        self.outbox.len() + self.best_effort_waiting.len()
    }

    fn in_flight(&self) -> u64 {
        (self.next_seq - 1).saturating_sub(self.processed)
    }

    fn can_send_now(&self) -> bool {
        self.generation.is_some() && self.in_flight() < IN_FLIGHT_WINDOW
    }

    /// Sends now if the window allows (encoding `m` straight into shared memory), else
    /// queues an owned copy.
    fn submit(&mut self, mut m: RequestMessage<'_>, retain: bool, awaited: Awaited) {
        if self.outbox.len() >= OUTBOX_HARD_MAX || self.outbox.bytes >= 4 * self.outbox_max_bytes {
            // Only one message packed with operations gets here past `has_room`.
            self.stats.ops_dropped += 1;
            if self.stats.ops_dropped.is_power_of_two() {
                tracing::warn!(
                    client = %m.route.client_key,
                    dropped = self.stats.ops_dropped,
                    "operation dropped: outbox full"
                );
            }
            return;
        }
        m.route.incarnation = self.incarnation;
        if self.outbox.is_empty() && self.can_send_now() {
            m.route.op_seq = self.next_seq;
            m.progress_can_wait = self.progress_can_wait(&m.request, retain, awaited);
            if let Err(e) = self.requests.send(&m) {
                tracing::warn!(error = %e, "could not hand an operation to the worker; queued");
                // Sent later from the outbox, with whatever is in flight then.
                m.progress_can_wait = false;
                self.outbox.push_back(OwnedOp {
                    message: m.into_owned(),
                    retain,
                    awaited,
                });
                return;
            }
            let route = m.route;
            let kind = PendingKind::of(&m.request);
            self.after_send(route, kind, retain, awaited, || m.into_owned());
        } else {
            self.outbox.push_back(OwnedOp {
                message: m.into_owned(),
                retain,
                awaited,
            });
        }
    }

    /// Whether nothing here will wait for the progress of `request`, sent now: a
    /// best-effort write no one awaits an answer to, with nothing queued and most of the
    /// window free.
    fn progress_can_wait(&self, request: &Request<'_>, retain: bool, awaited: Awaited) -> bool {
        request.is_write()
            && !retain
            && awaited == Awaited::No
            && self.best_effort_waiting.is_empty()
            && self.in_flight() < PROGRESS_CAN_WAIT_BELOW
    }

    fn after_send(
        &mut self,
        route: Route,
        kind: PendingKind,
        retain: bool,
        awaited: Awaited,
        message: impl FnOnce() -> RequestMessage<'static>,
    ) {
        self.next_seq += 1;
        self.stats.ops_sent += 1;
        self.dirty = true;
        if retain {
            self.retained.push_back(Retained {
                seq: route.op_seq,
                executed_at: None,
                message: message(),
            });
        }
        if awaited == Awaited::Yes {
            self.pending.insert(
                route.op_seq,
                (
                    route.client_key,
                    BaseObjectRequest {
                        request_id: route.request_id,
                        object_id: route.object_id,
                    },
                    kind,
                ),
            );
        }
    }

    /// Sends queued operations while the window allows (the outbox first, then best-effort
    /// writes waiting for their share); wakes the worker once.
    pub fn pump(&mut self) {
        while self.can_send_now() && self.send_first() {}
        while self.outbox.is_empty() && self.best_effort_share_free() && self.send_waiting() {}
        if self.dirty {
            match self.requests.notify() {
                Ok(()) => self.dirty = false,
                // Kept dirty: tried again on the next pass.
                Err(e) => tracing::debug!(error = %e, "worker wake-up failed"),
            }
        }
    }

    /// Sends the first operation of the outbox; false if it is empty or the send failed
    /// (the operation stays first, tried again on a later pass).
    fn send_first(&mut self) -> bool {
        let Some(mut op) = self.outbox.pop_front() else {
            return false;
        };
        op.message.route.op_seq = self.next_seq;
        op.message.route.incarnation = self.incarnation;
        if let Err(e) = self.requests.send(&op.message) {
            tracing::warn!(error = %e, "could not hand an operation to the worker; will retry");
            self.outbox.push_front(op);
            return false;
        }
        self.sent_owned(op);
        true
    }

    /// Sends the waiting best-effort write whose turn it is; false if none waits or the
    /// send failed (it keeps its turn, tried again on a later pass).
    fn send_waiting(&mut self) -> bool {
        let Some(op) = self.best_effort_waiting.front() else {
            return false;
        };
        let mut route = op.message.route;
        route.op_seq = self.next_seq;
        route.incarnation = self.incarnation;
        let sent = RequestMessage {
            route,
            progress_can_wait: false,
            request: op.message.request.borrowed(),
        };
        if let Err(e) = self.requests.send(&sent) {
            tracing::warn!(error = %e, "could not hand an operation to the worker; will retry");
            return false;
        }
        if let Some(mut op) = self.best_effort_waiting.pop() {
            op.message.route = route;
            self.sent_owned(op);
        }
        true
    }

    fn sent_owned(&mut self, op: OwnedOp) {
        let OwnedOp {
            message,
            retain,
            awaited,
        } = op;
        let kind = PendingKind::of(&message.request);
        self.after_send(message.route, kind, retain, awaited, move || message);
    }

    /// Handles worker announcements and replies (consuming their wake-ups when their
    /// descriptors were readable: `replies_ready`, `announce_ready`); applies results to the
    /// agent core.
    pub fn poll_ipc<A: xrce_common::session::agent::Endpoint>(
        &mut self,
        now: Instant,
        agent: &mut Agent<A>,
        replies_ready: bool,
        announce_ready: bool,
    ) {
        // Wake-ups are consumed only when there are some (a system call each time, and the
        // loop runs per datagram under load); the queues themselves are read every time.
        let mut hellos = Vec::new();
        if announce_ready {
            self.announce.clear_events();
        }
        let _ = self.announce.drain(|m| hellos.push(m.to_vec()));
        for m in hellos {
            match ReplyMessage::decode(&m) {
                Ok(ReplyMessage {
                    route,
                    reply: Reply::WorkerHello,
                }) if Some(route.generation) != self.generation => {
                    self.new_generation(route.generation);
                }
                Ok(_) => {}
                Err(e) => {
                    self.stats.ipc_dropped += 1;
                    tracing::warn!(error = %e, "bad announcement");
                }
            }
        }
        if let Some(replies) = self.replies.take() {
            if replies_ready {
                replies.clear_events();
            }
            if let Err(e) = replies.drain(|m| self.handle_reply(now, m, agent)) {
                tracing::warn!(error = %e, "receiving from the worker failed");
            }
            self.replies = Some(replies);
        }
        self.settle(now);
        self.apply_replies(now, agent);
    }

    fn new_generation(&mut self, generation: u32) {
        let first = self.generation.is_none();
        tracing::info!(
            generation,
            first,
            clients = self.graphs.len(),
            "worker generation seen; replaying sessions"
        );
        self.generation = Some(generation);
        self.processed = self.next_seq - 1;
        self.stats.replays += 1;
        // The new worker starts every read unpaused.
        self.paused.clear();
        let old_outbox = self.outbox.take();
        // Best-effort writes that waited for the share of a worker now gone are stale: they
        // are dropped, as they would have been without the wait, and the new worker starts
        // without a shedding hold.
        self.stats.ops_dropped += self.best_effort_waiting.clear() as u64;
        // Operations a client still waits for: answered by the replay, or (deletes) now.
        let mut awaited: HashMap<(ClientKey, ObjectId), RequestId> = HashMap::new();
        // Writes of spec-dialect clients waiting for their STATUS.
        let mut awaited_writes: HashMap<u64, (ClientKey, BaseObjectRequest)> = HashMap::new();
        for (seq, (client, req, kind)) in self.pending.drain() {
            match kind {
                PendingKind::Create => {
                    awaited.insert((client, req.object_id), req.request_id);
                }
                PendingKind::Delete => self.replies_out.push((client, req, ResultStatus::OK)),
                PendingKind::Write => {
                    awaited_writes.insert(seq, (client, req));
                }
                PendingKind::Other => {}
            }
        }
        let mut writes = Vec::new();
        // Sessions that ended before this worker was seen: a worker that kept their entities
        // for this front-end (it took over from a predecessor) must not hand them to a
        // session created again with the same key.
        let mut deletes = Vec::new();
        for op in old_outbox {
            let r = op.message.route;
            match (&op.message.request, op.awaited) {
                (Request::Write { .. }, _) => writes.push(op),
                (Request::DeleteClient, _) => deletes.push(op),
                (Request::Create { .. }, Awaited::Yes) => {
                    awaited.insert((r.client_key, r.object_id), r.request_id);
                }
                (Request::Delete, Awaited::Yes) => self.replies_out.push((
                    r.client_key,
                    BaseObjectRequest {
                        request_id: r.request_id,
                        object_id: r.object_id,
                    },
                    ResultStatus::OK,
                )),
                _ => {}
            }
        }
        let fe = self.frontend_id;
        let internal = move |request: Request<'static>| OwnedOp {
            message: RequestMessage::new(Route::frontend(fe), request),
            retain: false,
            awaited: Awaited::No,
        };
        self.outbox.push_back(internal(Request::FrontendHello));
        self.outbox.extend(deletes);
        for (client, graph) in &self.graphs {
            for o in graph.objects() {
                let mut body = Vec::new();
                o.variant.encode(&mut CdrWriter::new(&mut body, true));
                let req = BaseObjectRequest {
                    request_id: o.request_id,
                    object_id: o.object_id,
                };
                let waited = awaited.get(&(*client, o.object_id)) == Some(&o.request_id);
                let create = Request::Create {
                    description: body.into(),
                    client_little_endian: o.little_endian,
                    replay: !waited,
                    readers_matched: o.readers_matched,
                };
                self.outbox.push_back(OwnedOp {
                    message: message(self.frontend_id, *client, req, create),
                    retain: false,
                    awaited: if waited { Awaited::Yes } else { Awaited::No },
                });
            }
            for (reader, read) in graph.reads() {
                if !first && fault::once(Fault::ReplaySkip) {
                    continue;
                }
                let mut body = Vec::new();
                read.spec.encode(&mut CdrWriter::new(&mut body, true));
                let req = BaseObjectRequest {
                    request_id: read.request_id,
                    object_id: *reader,
                };
                let read = Request::Read {
                    spec: body.into(),
                    replay: true,
                };
                self.outbox.push_back(OwnedOp {
                    message: message(self.frontend_id, *client, req, read),
                    retain: false,
                    awaited: Awaited::No,
                });
            }
        }
        // A worker that kept this front-end's entities (this process took over from a
        // predecessor) removes those the replay did not take back.
        self.outbox.push_back(internal(Request::ReplayDone));
        for r in self.retained.take() {
            self.stats.writes_resent += 1;
            let waited = awaited_writes.remove(&r.seq).is_some();
            self.outbox.push_back(OwnedOp {
                message: r.message,
                retain: true,
                awaited: if waited { Awaited::Yes } else { Awaited::No },
            });
        }
        // Best-effort writes the dead worker may not have published: say so.
        for (client, req) in awaited_writes.into_values() {
            self.replies_out
                .push((client, req, ResultStatus::new(status::ERR_DDS_ERROR)));
        }
        self.outbox.extend(writes);
    }

    fn handle_reply<A: xrce_common::session::agent::Endpoint>(
        &mut self,
        now: Instant,
        m: &[u8],
        agent: &mut Agent<A>,
    ) {
        let ReplyMessage { route: h, reply } = match ReplyMessage::decode(m) {
            Ok(v) => v,
            Err(e) => {
                self.stats.ipc_dropped += 1;
                return tracing::warn!(error = %e, "bad reply from the worker");
            }
        };
        if h.incarnation != 0 && h.incarnation != self.incarnation {
            // Meant for the process this one took over from (its operation numbers mean
            // something else here).
            self.stats.predecessor_replies += 1;
            return;
        }
        if reply == Reply::WorkerHello {
            if Some(h.generation) != self.generation {
                self.new_generation(h.generation);
            }
            return;
        }
        if Some(h.generation) != self.generation {
            // From a worker generation we no longer serve (or have not seen announced yet).
            self.stats.ipc_dropped += 1;
            return;
        }
        let req = BaseObjectRequest {
            request_id: h.request_id,
            object_id: h.object_id,
        };
        match reply {
            Reply::WorkerHello => {}
            Reply::Progress {
                executed,
                acknowledged,
            } => {
                self.processed = self.processed.max(h.op_seq);
                let executed = executed.min(h.op_seq);
                self.acknowledged = self.acknowledged.max(acknowledged.min(executed));
                for r in self.retained.iter_mut() {
                    if r.seq > executed {
                        break;
                    }
                    r.executed_at.get_or_insert(now);
                }
            }
            Reply::Status { result, replay } => {
                let code = result.status;
                let waited = self.pending.remove(&h.op_seq);
                if !status::is_ok(code) {
                    if let Some(g) = self.graphs.get_mut(&h.client_key) {
                        self.objects_changed.insert(h.client_key);
                        self.reads_changed.insert(h.client_key);
                        if waited.is_some_and(|w| w.2 == PendingKind::Create) {
                            let removed = g.remove(h.object_id);
                            self.object_budget.removed(h.client_key, &removed);
                        } else if g
                            .read_mut(h.object_id)
                            .is_some_and(|r| r.request_id == h.request_id)
                        {
                            // The read itself failed (not, say, a write to the same
                            // requester or replier).
                            g.end_read(h.object_id);
                        }
                    }
                }
                if waited.is_some() || (!replay && !status::is_ok(code)) {
                    self.replies_out.push((h.client_key, req, result));
                } else if !status::is_ok(code) {
                    tracing::warn!(client = %h.client_key, object = ?h.object_id, status = code, "replayed operation failed on the new worker");
                }
            }
            Reply::Sample(sample) => {
                let identity = sample.identity;
                // A sample this read delivered before the worker restarted (offered again
                // by a writer that outlived the worker) is not delivered twice.
                let read = self
                    .graphs
                    .get_mut(&h.client_key)
                    .and_then(|g| g.read_mut(h.object_id));
                if let Some(a) = &read {
                    if identity.is_known()
                        && a.marks
                            .already_delivered(&identity.writer, identity.sequence_number)
                    {
                        self.stats.samples_already_delivered += 1;
                        return;
                    }
                }
                // The read's stream and format; a sample that overtook the end of its read
                // goes out plain on the built-in reliable stream.
                let (stream, format, sequence_number) =
                    read.map_or((stream_id::BUILTIN_RELIABLE, data_format::DATA, 0), |a| {
                        a.delivered = a.delivered.wrapping_add(1);
                        if identity.is_known() {
                            a.marks.record(identity.writer, identity.sequence_number);
                        }
                        (a.spec.preferred_stream_id, a.spec.data_format, a.delivered)
                    });
                let mut state = 0;
                if sample.disposed {
                    state |= sample_state::INSTANCE_DISPOSED;
                }
                if sample.unregistered {
                    state |= sample_state::INSTANCE_UNREGISTERED;
                }
                if state != 0 && matches!(format, data_format::DATA | data_format::DATA_SEQ) {
                    // Without a SampleInfo the client could not tell a disposed instance's
                    // key from a sample: instance ends reach only SAMPLE-format reads.
                    self.stats.instance_ends_skipped += 1;
                    return;
                }
                let reply = DataReply {
                    request: req,
                    format,
                    sample: &sample.data,
                    little_endian: sample.little_endian,
                    state,
                    sequence_number,
                };
                for _ in 0..fault_copies(h.object_id) {
                    if let Err(e) = agent.send_data(now, h.client_key, stream, reply) {
                        // A full output queue is counted by the core (output_queue_full).
                        if e != xrce_common::session::agent::SendError::QueueFull {
                            self.stats.samples_dropped += 1;
                        }
                        tracing::debug!(client = %h.client_key, error = %e, "sample not delivered");
                    }
                }
                let congested = agent
                    .output_backlog(h.client_key, stream)
                    .is_some_and(|(m, b)| m >= PAUSE_READ_AT.0 || b >= PAUSE_READ_AT.1);
                let key = (h.client_key, h.object_id);
                if congested && !self.paused.contains_key(&key) {
                    self.paused.insert(key, stream);
                    self.stats.reads_paused += 1;
                    tracing::debug!(client = %h.client_key, reader = ?h.object_id, "read paused: the client is not keeping up");
                    let pause = message(self.frontend_id, h.client_key, req, Request::PauseRead);
                    self.submit(pause, false, Awaited::No);
                }
            }
            Reply::WriterMatched { readers } => {
                if let Some(o) = self
                    .graphs
                    .get_mut(&h.client_key)
                    .and_then(|g| g.get_mut(h.object_id))
                {
                    o.readers_matched = readers;
                }
            }
            Reply::ReadEnded => {
                self.paused.remove(&(h.client_key, h.object_id));
                if let Some(g) = self.graphs.get_mut(&h.client_key) {
                    let same = g
                        .reads()
                        .any(|(r, a)| *r == h.object_id && a.request_id == h.request_id);
                    if same {
                        g.end_read(h.object_id);
                        self.reads_changed.insert(h.client_key);
                    }
                }
            }
        }
    }

    /// Resumes paused reads whose clients caught up (or are gone). Cheap when none is paused.
    pub fn resume_reads<A: xrce_common::session::agent::Endpoint>(&mut self, agent: &Agent<A>) {
        if self.paused.is_empty() {
            return;
        }
        let ready: Vec<(ClientKey, ObjectId)> = self
            .paused
            .iter()
            .filter(|((client, _), stream)| {
                agent
                    .output_backlog(*client, **stream)
                    .is_none_or(|(m, b)| m <= RESUME_READ_AT.0 && b <= RESUME_READ_AT.1)
            })
            .map(|(k, _)| *k)
            .collect();
        for (client, reader) in ready {
            self.paused.remove(&(client, reader));
            tracing::debug!(%client, ?reader, "read resumed");
            let req = BaseObjectRequest {
                request_id: RequestId::default(),
                object_id: reader,
            };
            let resume = message(self.frontend_id, client, req, Request::ResumeRead);
            self.submit(resume, false, Awaited::No);
        }
    }

    /// Drops retained writes that every matched reliable DDS reader acknowledged, or that
    /// were executed long enough ago (a reader that never acknowledges does not keep them).
    fn settle(&mut self, now: Instant) {
        while let Some(r) = self.retained.front() {
            let acknowledged = r.seq <= self.acknowledged && r.executed_at.is_some();
            match r.executed_at {
                _ if acknowledged => {
                    self.retained.pop_front();
                    self.stats.writes_acknowledged += 1;
                }
                Some(t) if now.saturating_duration_since(t) >= SETTLE_TIME => {
                    self.retained.pop_front();
                    self.stats.writes_settled_unacknowledged += 1;
                }
                _ => break,
            }
        }
    }

    /// When retained writes need another look, or a failed wake-up of the worker is tried
    /// again.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let settle = self
            .retained
            .front()
            .and_then(|r| r.executed_at)
            .map(|t| t + SETTLE_TIME);
        let retry = self
            .dirty
            .then(|| Instant::now() + std::time::Duration::from_millis(1));
        settle.into_iter().chain(retry).min()
    }

    /// Sends STATUS replies decided here (creation modes, unknown objects, replays).
    pub fn apply_replies<A: xrce_common::session::agent::Endpoint>(
        &mut self,
        now: Instant,
        agent: &mut Agent<A>,
    ) {
        for (client, req, result) in self.replies_out.drain(..) {
            let _ = agent.send_status(now, client, req, result);
        }
        for (client, req, result, config) in self.infos_out.drain(..) {
            let _ = agent.send_info(now, client, req, result, config.as_ref());
        }
    }

    /// Whether the retained reliable writes leave room for more (flow control).
    fn retention_has_room(&self) -> bool {
        self.retained.len() < RETAIN_MAX && self.retained.bytes < self.retain_max_bytes
    }

    /// Drops the waiting best-effort writes of `client` (to `objects` only, if given): an
    /// operation sent now (a delete, a create, the end of the session) would otherwise reach
    /// the worker before them, and they would then go to no writer or to another one. They
    /// get no STATUS, as no dropped best-effort write does.
    fn drop_waiting_writes(&mut self, client: ClientKey, objects: Option<&[ObjectId]>) {
        let dropped = match objects {
            None => self.best_effort_waiting.remove_client(client),
            Some(ids) => self
                .best_effort_waiting
                .retain_of(client, |op| !ids.contains(&op.message.route.object_id)),
        };
        self.stats.ops_dropped += dropped as u64;
    }

    /// How long a client's best-effort writes are shed, not queued, after it overflowed
    /// their waiting queue (default [`BEST_EFFORT_SHED_HOLD`]).
    pub fn set_best_effort_shed_hold(&mut self, hold: Duration) {
        self.best_effort_waiting.set_hold(hold);
    }

    /// Whether the window has room for a best-effort write beyond the share kept for
    /// reliable and control operations ([`BEST_EFFORT_RESERVE`]).
    fn best_effort_share_free(&self) -> bool {
        self.can_send_now()
            && self.in_flight() + HAND_OVER_HEADROOM + BEST_EFFORT_RESERVE < IN_FLIGHT_WINDOW
    }

    /// Where a best-effort write of `client` weighing `weight` goes now, if anywhere: as
    /// [`OperationSink::has_room`], less the share kept for reliable and control operations
    /// ([`BEST_EFFORT_RESERVE`], [`BEST_EFFORT_OUTBOX_MAX`]), plus, in hand-over mode, a
    /// short wait unless the client is shed for overflowing it ([`BEST_EFFORT_WAITING_MAX`],
    /// [`BEST_EFFORT_SHED_HOLD`]).
    fn best_effort_route(&mut self, client: ClientKey, weight: usize) -> Option<BestEffortRoute> {
        if !self.retention_has_room() {
            return None;
        }
        if self.hand_over_at_once && self.generation.is_some() {
            if self.outbox.is_empty()
                && self.best_effort_waiting.is_empty()
                && self.best_effort_share_free()
            {
                return Some(BestEffortRoute::Now);
            }
            let now = Instant::now();
            match self.best_effort_waiting.make_room(client, weight, now) {
                Room::Yes {
                    evicted,
                    holds_started,
                } => {
                    self.stats.ops_dropped += evicted as u64;
                    self.stats.best_effort_sheds += holds_started as u64;
                    Some(BestEffortRoute::Wait)
                }
                Room::No { hold_started } => {
                    if hold_started {
                        self.stats.best_effort_sheds += 1;
                        tracing::debug!(
                            %client,
                            waiting = self.best_effort_waiting.len(),
                            of_client = self.best_effort_waiting.len_of(client),
                            "a client's best-effort writes overflow their waiting queue: shedding, not queueing, its writes for a while"
                        );
                    }
                    None
                }
            }
        } else {
            (self.has_room() && self.outbox.len() < BEST_EFFORT_OUTBOX_MAX)
                .then_some(BestEffortRoute::Now)
        }
    }
}

impl OperationSink for Bridge {
    fn has_room(&self) -> bool {
        let retained = self.retention_has_room();
        if self.hand_over_at_once && self.generation.is_some() {
            // What a client sent goes to the worker now or is refused unacknowledged (the
            // client sends it again): an operation left in this process's outbox would die
            // with it, after its message was acknowledged and stored as taken. (Before a
            // worker answers, and while one restarts, operations wait in the outbox as
            // always: they are replayed to the new worker.)
            return retained
                && self.outbox.is_empty()
                && self.in_flight() + HAND_OVER_HEADROOM <= IN_FLIGHT_WINDOW;
        }
        self.outbox.len() < OUTBOX_MAX && self.outbox.bytes < self.outbox_max_bytes && retained
    }

    fn has_room_for(&self, submessages: usize) -> bool {
        if self.hand_over_at_once && self.generation.is_some() {
            // Room for what this message can bring (a submessage is one operation; twice
            // that, for margin), not for the largest message: a client sending one WRITE_DATA
            // a message is not refused while the window has room for it.
            let need = u64::try_from(submessages)
                .unwrap_or(u64::MAX)
                .saturating_mul(2)
                .clamp(1, HAND_OVER_HEADROOM);
            return self.retention_has_room()
                && self.outbox.is_empty()
                && self.in_flight() + need <= IN_FLIGHT_WINDOW;
        }
        self.has_room()
    }

    fn operation(&mut self, op: Operation<'_>) {
        let fe = self.frontend_id;
        match op {
            Operation::ClientCreated { client, origin } => {
                self.graphs.insert(client, ObjectGraph::default());
                self.object_budget.client_created(client, origin);
                self.objects_changed.insert(client);
            }
            Operation::ClientDeleted { client } => {
                self.graphs.remove(&client);
                self.object_budget.client_deleted(client);
                self.drop_waiting_writes(client, None);
                let delete = message(
                    fe,
                    client,
                    BaseObjectRequest::default(),
                    Request::DeleteClient,
                );
                self.submit(delete, false, Awaited::No);
            }
            Operation::Create {
                client,
                create,
                little_endian,
            } => {
                self.objects_changed.insert(client);
                let graph = self.graphs.entry(client).or_default();
                let id = create.base.object_id;
                let max = self.max_objects;
                match graph.decide_create(id, &create.variant, create.reuse, create.replace, max) {
                    CreateDecision::Reply(code) => {
                        if code == status::ERR_RESOURCES && graph.len() >= max {
                            self.stats.objects_over_quota += 1;
                            if self.stats.objects_over_quota.is_power_of_two() {
                                tracing::warn!(%client, objects = graph.len(), quota = max, refused = self.stats.objects_over_quota, "CREATE refused: the client has its quota of objects (--max-objects-per-client)");
                            }
                        }
                        self.replies_out
                            .push((client, create.base, ResultStatus::new(code)))
                    }
                    decision => {
                        let mut body = Vec::new();
                        create.variant.encode(&mut CdrWriter::new(&mut body, true));
                        if !self.object_budget.admit(client, id, body.len()) {
                            self.stats.objects_over_budget += 1;
                            let (held, pool) = self.object_budget.held();
                            if self
                                .object_budget_episodes
                                .bite(std::time::Instant::now(), "objects")
                                .is_some()
                            {
                                tracing::warn!(%client, bytes = body.len(), held, pool, refused = self.stats.objects_over_budget, "CREATE refused with STATUS_ERR_RESOURCES: object descriptions over the client's share of the memory budget (--memory-budget; logged once per episode)");
                            }
                            self.replies_out.push((
                                client,
                                create.base,
                                ResultStatus::new(status::ERR_RESOURCES),
                            ));
                            return;
                        }
                        let Some(graph) = self.graphs.get_mut(&client) else {
                            return;
                        };
                        let mut replaced = if decision == CreateDecision::Replace {
                            graph.remove(id)
                        } else {
                            Vec::new()
                        };
                        let children: Vec<ObjectId> =
                            replaced.iter().copied().filter(|r| *r != id).collect();
                        self.object_budget.removed(client, &children);
                        // Writes a client sent to the id before it existed must not go to
                        // the new object either.
                        replaced.push(id);
                        graph.insert(GraphObject {
                            object_id: id,
                            request_id: create.base.request_id,
                            variant: create.variant.clone(),
                            little_endian,
                            readers_matched: 0,
                        });
                        if !self.best_effort_waiting.is_empty() {
                            self.drop_waiting_writes(client, Some(&replaced));
                        }
                        let request = Request::Create {
                            description: body.into(),
                            client_little_endian: little_endian,
                            replay: false,
                            readers_matched: 0,
                        };
                        let m = message(fe, client, create.base, request);
                        self.submit(m, false, Awaited::Yes);
                    }
                }
            }
            Operation::Delete { client, request } => {
                let removed = self
                    .graphs
                    .get_mut(&client)
                    .map(|g| g.remove(request.object_id))
                    .unwrap_or_default();
                self.object_budget.removed(client, &removed);
                self.objects_changed.insert(client);
                if !removed.is_empty() {
                    self.drop_waiting_writes(client, Some(&removed));
                    self.submit(
                        message(fe, client, request, Request::Delete),
                        false,
                        Awaited::Yes,
                    );
                } else {
                    self.replies_out.push((
                        client,
                        request,
                        ResultStatus::new(status::ERR_UNKNOWN_REFERENCE),
                    ));
                }
            }
            Operation::Write {
                client,
                stream_id: stream,
                data,
                little_endian,
                dialect,
            } => {
                if !is_defined_format(data.format) {
                    tracing::debug!(%client, format = data.format, "WRITE_DATA with an undefined DataFormat");
                    self.replies_out.push((
                        client,
                        data.base,
                        ResultStatus::new(status::ERR_INVALID_DATA),
                    ));
                    return;
                }
                // The worker splits the samples (it knows the types) and, for spec-dialect
                // clients, answers every write with a STATUS.
                let status_requested = dialect == Dialect::Spec;
                let awaited = if status_requested {
                    Awaited::Yes
                } else {
                    Awaited::No
                };
                let write = Request::Write {
                    data: data.data.into(),
                    data_format: data.format,
                    little_endian,
                    dialect,
                    status_requested,
                };
                let mut m = message(fe, client, data.base, write);
                let reliable = stream_id::is_reliable(stream);
                let route = if reliable {
                    Some(BestEffortRoute::Now)
                } else {
                    self.best_effort_route(client, m.encoded_len())
                };
                let Some(route) = route else {
                    // Best-effort data is not held back by flow control: drop it, counted.
                    self.stats.ops_dropped += 1;
                    if self.stats.ops_dropped.is_power_of_two() {
                        tracing::warn!(
                            client = %client,
                            dropped = self.stats.ops_dropped,
                            in_flight = self.in_flight(),
                            outbox = self.outbox.len(),
                            retained = self.retained.len(),
                            waiting = self.best_effort_waiting.len(),
                            "best-effort write dropped: the worker has not taken the \
                             operations sent before it (further drops are counted)"
                        );
                    }
                    return;
                };
                match route {
                    BestEffortRoute::Now => self.submit(m, reliable, awaited),
                    BestEffortRoute::Wait => {
                        m.route.incarnation = self.incarnation;
                        let op = OwnedOp {
                            message: m.into_owned(),
                            retain: false,
                            awaited,
                        };
                        let weight = op.weight();
                        self.best_effort_waiting.push(client, op, weight);
                    }
                }
            }
            Operation::GetInfo {
                client,
                request,
                info_mask,
            } => {
                let object = self
                    .graphs
                    .get(&client)
                    .and_then(|g| g.get(request.object_id));
                let result = if object.is_some() {
                    status::OK
                } else {
                    status::ERR_UNKNOWN_REFERENCE
                };
                let config = object
                    .filter(|_| info_mask & INFO_CONFIGURATION != 0)
                    .map(|o| o.variant.clone());
                self.infos_out
                    .push((client, request, ResultStatus::new(result), config));
            }
            Operation::Read {
                client,
                request,
                spec,
            } => {
                let known = self
                    .graphs
                    .get(&client)
                    .is_some_and(|g| g.get(request.object_id).is_some());
                if !known {
                    self.replies_out.push((
                        client,
                        request,
                        ResultStatus::new(status::ERR_UNKNOWN_REFERENCE),
                    ));
                    return;
                }
                // A new read starts unpaused on both sides.
                self.paused.remove(&(client, request.object_id));
                if let Some(g) = self.graphs.get_mut(&client) {
                    g.set_read(
                        request.object_id,
                        ActiveRead {
                            request_id: request.request_id,
                            spec: spec.clone(),
                            delivered: 0,
                            marks: Default::default(),
                        },
                    );
                }
                let mut body = Vec::new();
                spec.encode(&mut CdrWriter::new(&mut body, true));
                let read = Request::Read {
                    spec: body.into(),
                    replay: false,
                };
                self.submit(message(fe, client, request, read), false, Awaited::No);
            }
        }
    }
}

/// How many times a sample from the worker goes to its client: once, unless a fault injected
/// on purpose (`xrce_common::fault`, test builds only) drops or repeats it.
fn fault_copies(reader: ObjectId) -> usize {
    if reader.kind() == object_kind::REQUESTER && fault::hit(Fault::ReplyDuplicate, 1) {
        return 2;
    }
    if fault::hit(Fault::ClientDuplicate, 10) {
        return 2;
    }
    if fault::hit(Fault::ClientDrop, 10) {
        return 0;
    }
    1
}
