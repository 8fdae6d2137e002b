//! The front-end's relay to the DDS worker, as a state machine with no I/O inside: it takes
//! the session core's operations and the worker's replies (with the time, `now`), and hands
//! requests to a [`Link`] (iceoryx2 shared memory in the process, [`link::ShmLink`]; a vector
//! in the simulation tests). What makes sessions survive a worker restart lives here.
//!
//! Its parts, one module each:
//! * the window and the outbox (this module): at most [`IN_FLIGHT_WINDOW`] operations are
//!   unprocessed by the worker at once, so its queue never overflows; the rest wait in a
//!   bounded outbox (best-effort writes in a short queue of their own, shared fairly among
//!   the clients: [`crate::waiting_writes`]);
//! * `retention`: writes that came on reliable streams are kept until the worker has
//!   executed them and their DDS readers acknowledged them (or a settle time passed);
//! * `replay`: when a new worker generation is announced, the graphs are replayed in
//!   creation order, reads re-issued and retained writes sent again, before anything new;
//! * `operations`: the client object mirror ([`ObjectGraph`] per client, quotas, GET_INFO)
//!   and the routing of writes;
//! * `replies`: the worker's replies applied to the session core.
//!
//! When the outbox or the retention is full, [`OperationSink::has_room`] says no: the agent
//! core then stops acknowledging reliable messages and clients send them again later.

use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};
use xrce_common::session::origin::DeliveredOrigins;

use xrce_common::session::agent::{Agent, Endpoint, Operation, OperationSink};
use xrce_common::session::budget::{BudgetSplit, Episodes, DEFAULT_MEMORY_BUDGET};
use xrce_common::session::graph::ObjectGraph;
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::{
    BaseObjectRequest, ClientKey, ObjectId, ObjectVariant, RequestId, ResultStatus,
};
use xrce_ipc::{Request, RequestMessage, Route, IN_FLIGHT_WINDOW};

use crate::object_budget::ObjectBudget;
use crate::waiting_writes::WaitingWrites;

pub mod link;
mod operations;
mod queue;
mod replay;
mod replies;
mod retention;

pub use link::{Link, LinkError};
use queue::{Awaited, ByteQueue, OwnedOp, PendingKind};
use retention::Retention;

/// Operations waiting for the window before new ones are refused (flow control).
pub const OUTBOX_MAX: usize = 8192;
/// Operations one client message may carry that still go to the worker at once when client
/// operations are only accepted that way ([`Relay::set_hand_over_at_once`]): a 512-byte
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

/// Where a best-effort write goes ([`Relay::best_effort_route`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BestEffortRoute {
    /// To the worker (or, outside hand-over mode, the outbox), as any operation.
    Now,
    /// To the best-effort waiting queue, for the window's best-effort share.
    Wait,
}

/// Counters of the relay.
#[derive(Debug, Default, Clone)]
pub struct RelayStats {
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
    /// Of those, samples of writes resent to the new worker that the read had delivered
    /// (told by their origin: [`xrce_common::session::origin`]).
    pub resent_samples_already_delivered: u64,
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
    /// Sends and wake-ups the link refused (each tried again later, nothing dropped).
    pub link_refusals: u64,
}

/// The first retry after the link refused a send or a wake-up; each refusal in a row doubles
/// it, up to [`LINK_RETRY_MAX`], and one that goes through resets it.
pub const LINK_RETRY_MIN: Duration = Duration::from_millis(1);
/// The longest wait between retries of a link that keeps refusing.
pub const LINK_RETRY_MAX: Duration = Duration::from_millis(250);

/// The front-end's side of the IPC contract: its state between the session core and the
/// worker.
#[derive(Debug)]
pub struct Relay<L> {
    frontend_id: u32,
    /// This process of the front-end, stamped on every request.
    incarnation: u16,
    /// Accept client operations only when they can go to the worker at once (sessions
    /// are stored for a successor: see [`Relay::set_hand_over_at_once`]).
    hand_over_at_once: bool,
    /// Where requests go.
    link: L,
    generation: Option<u32>,
    /// A new generation was seen since [`Relay::take_generation_change`].
    generation_changed: bool,
    next_seq: u64,
    processed: u64,
    outbox: ByteQueue<OwnedOp>,
    /// Best-effort writes waiting for the window's best-effort share (hand-over mode; see
    /// [`BEST_EFFORT_WAITING_MAX`]); sent after the outbox, the clients in turns.
    best_effort_waiting: WaitingWrites<OwnedOp>,
    retention: Retention,
    /// Sent operations whose STATUS a client waits for: seq -> (client, request, kind).
    pending: HashMap<u64, (ClientKey, BaseObjectRequest, PendingKind)>,
    graphs: HashMap<ClientKey, ObjectGraph>,
    /// The client writes of the samples the reads delivered last, so that a write resent to
    /// a new worker is not delivered twice ([`xrce_common::session::origin`]).
    delivered_origins: DeliveredOrigins,
    /// Clients whose objects changed, and clients whose reads changed outside of their own
    /// messages, since they were last taken (for the session store).
    objects_changed: HashSet<ClientKey>,
    reads_changed: HashSet<ClientKey>,
    replies_out: Vec<(ClientKey, BaseObjectRequest, ResultStatus)>,
    /// Sessions to end: their replay crashed a worker ([`xrce_ipc::REPLAY_REFUSED`]).
    sessions_to_end: HashSet<ClientKey>,
    /// Reads paused because their client does not keep up: (client, reader) -> stream.
    paused: HashMap<(ClientKey, ObjectId), u8>,
    /// INFO replies decided here (GET_INFO about a client's objects).
    infos_out: Vec<(
        ClientKey,
        BaseObjectRequest,
        ResultStatus,
        Option<ObjectVariant>,
    )>,
    /// Requests went out since the worker was last woken (or a wake-up failed).
    dirty: bool,
    /// Sends and wake-ups the link refused in a row (0: it works).
    link_failures: u32,
    stats: RelayStats,
    /// Sessions were taken over from a predecessor and the worker has not yet said which
    /// of their writes it executed ([`xrce_ipc::Reply::Executed`], then its answer to this
    /// process's hello): client messages are refused (not acknowledged: sent again) until
    /// it did, so that none is handed over twice.
    awaiting_executed: bool,
    /// Most objects per client.
    max_objects: usize,
    /// Memory for object descriptions, shared between addresses and sessions.
    object_budget: ObjectBudget,
    object_budget_episodes: Episodes,
    /// Bytes of queued operations before new ones are refused ([`OUTBOX_MAX_BYTES`] unless
    /// a memory budget says less).
    outbox_max_bytes: usize,
    /// The instant reception times count from ([`Relay::received_us`]).
    clock_origin: Option<Instant>,
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

impl<L: Link> Relay<L> {
    /// The relay of front-end `frontend_id`, as its process `incarnation` (nonzero,
    /// different from its predecessor's), sending over `link`. It serves no worker until one
    /// says hello ([`Relay::handle_reply`], [`Relay::handle_announcement`]).
    pub fn new(frontend_id: u32, incarnation: u16, link: L) -> Self {
        Relay {
            frontend_id,
            incarnation,
            hand_over_at_once: false,
            link,
            generation: None,
            generation_changed: false,
            next_seq: 1,
            processed: 0,
            outbox: ByteQueue::default(),
            best_effort_waiting: WaitingWrites::new(
                BEST_EFFORT_WAITING_MAX,
                BEST_EFFORT_WAITING_MAX_BYTES,
                BEST_EFFORT_SHED_HOLD,
            ),
            retention: Retention::new(RETAIN_MAX_BYTES),
            pending: HashMap::new(),
            graphs: HashMap::new(),
            delivered_origins: DeliveredOrigins::default(),
            objects_changed: HashSet::new(),
            reads_changed: HashSet::new(),
            replies_out: Vec::new(),
            sessions_to_end: HashSet::new(),
            infos_out: Vec::new(),
            paused: HashMap::new(),
            dirty: false,
            link_failures: 0,
            stats: RelayStats::default(),
            awaiting_executed: false,
            max_objects: xrce_common::session::graph::MAX_OBJECTS,
            object_budget: ObjectBudget::new(BudgetSplit::of(DEFAULT_MEMORY_BUDGET).objects),
            object_budget_episodes: Episodes::default(),
            outbox_max_bytes: OUTBOX_MAX_BYTES,
            clock_origin: None,
        }
    }

    /// Microseconds from the first write this relay took to `now`: the reception time a
    /// write carries to the worker (only spacings between one process's writes matter
    /// there).
    fn received_us(&mut self, now: Instant) -> u64 {
        let origin = *self.clock_origin.get_or_insert(now);
        u64::try_from(now.saturating_duration_since(origin).as_micros()).unwrap_or(u64::MAX)
    }

    /// The link requests go over.
    pub fn link(&self) -> &L {
        &self.link
    }

    /// The link, to act on it (a test's simulated worker takes what was sent).
    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    /// Bounds what this process holds for clients by its parts of a front-end's memory
    /// budget: object descriptions, queued operations and retained writes (the session
    /// core has its own part, [`BudgetSplit::core`]).
    pub fn set_memory_budget(&mut self, split: BudgetSplit) {
        self.object_budget = ObjectBudget::new(split.objects);
        self.outbox_max_bytes = split.outbox.clamp(1 << 20, OUTBOX_MAX_BYTES);
        self.retention
            .set_max_bytes(split.retained.clamp(1 << 20, RETAIN_MAX_BYTES));
    }

    /// Bytes of object descriptions held, and their part of the budget.
    pub fn object_memory(&self) -> (usize, usize) {
        self.object_budget.held()
    }

    /// Sets the most objects one client may create (at least 1).
    pub fn set_max_objects_per_client(&mut self, max: usize) {
        self.max_objects = max.max(1);
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
        self.awaiting_executed = true;
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
    pub fn stats(&self) -> &RelayStats {
        &self.stats
    }

    /// The worker generation served, if any.
    pub fn generation(&self) -> Option<u32> {
        self.generation
    }

    /// Whether a new worker generation took the replay since the last call: the caller then
    /// tells the clients where their streams stand ([`Agent::announce_streams`]), so that
    /// what was refused while no worker served is sent again at once.
    pub fn take_generation_change(&mut self) -> bool {
        std::mem::take(&mut self.generation_changed)
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

    /// Sends now if the window allows (the link encodes `m` in place: into shared memory in
    /// the process), else
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
            if let Err(e) = self.link.send(&m) {
                self.link_refused("operation", &e);
                // Sent later from the outbox, with whatever is in flight then.
                m.progress_can_wait = false;
                self.outbox.push_back(OwnedOp {
                    message: m.into_owned(),
                    retain,
                    awaited,
                });
                return;
            }
            self.link_works();
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
            self.retention.keep(route.op_seq, message());
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
            match self.link.wake() {
                Ok(()) => {
                    self.dirty = false;
                    self.link_works();
                }
                // Kept dirty: tried again on the next pass.
                Err(e) => self.link_refused("worker wake-up", &e),
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
        if let Err(e) = self.link.send(&op.message) {
            self.link_refused("operation", &e);
            self.outbox.push_front(op);
            return false;
        }
        self.link_works();
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
        if let Err(e) = self.link.send(&sent) {
            self.link_refused("operation", &e);
            return false;
        }
        self.link_works();
        if let Some(mut op) = self.best_effort_waiting.pop() {
            op.message.route = route;
            self.sent_owned(op);
        }
        true
    }

    /// Counts a refusal of the link; the first of a run is a warning, the rest debug lines
    /// (a link that keeps refusing is retried ever more slowly: [`Relay::poll_timeout`]).
    fn link_refused(&mut self, what: &str, e: &dyn std::fmt::Display) {
        self.stats.link_refusals += 1;
        self.link_failures = self.link_failures.saturating_add(1);
        if self.link_failures == 1 {
            tracing::warn!(error = %e, "could not hand an {what} to the worker; will retry");
        } else {
            tracing::debug!(error = %e, refusals = self.link_failures, "the link still refuses an {what}");
        }
    }

    /// A send went through: the next refusal starts a new run.
    fn link_works(&mut self) {
        if self.link_failures > 1 {
            tracing::info!(
                refusals = self.link_failures,
                "the link to the worker works again"
            );
        }
        self.link_failures = 0;
    }

    /// How long to wait before trying a refusing link again.
    fn link_retry(&self) -> Duration {
        let doublings = self.link_failures.saturating_sub(1).min(16);
        LINK_RETRY_MIN
            .saturating_mul(1 << doublings)
            .min(LINK_RETRY_MAX)
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

    /// Resumes paused reads whose clients caught up (or are gone). Cheap when none is paused.
    pub fn resume_reads<A: Endpoint>(&mut self, agent: &Agent<A>) {
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

    /// When retained writes need another look, or a failed wake-up or send is tried again
    /// (operations the link refused wait in the outbox while the window has room): at once
    /// after [`LINK_RETRY_MIN`], ever more slowly while the link keeps refusing, up to
    /// [`LINK_RETRY_MAX`].
    pub fn poll_timeout(&self, now: Instant) -> Option<Instant> {
        let settle = self.retention.deadline();
        // The outbox, or a waiting best-effort write whose send the link refused.
        let refused = (!self.outbox.is_empty() && self.can_send_now())
            || (self.link_failures > 0 && !self.best_effort_waiting.is_empty());
        let retry = (self.dirty || refused).then(|| now + self.link_retry());
        settle.into_iter().chain(retry).min()
    }

    /// Sends STATUS replies decided here (creation modes, unknown objects, replays).
    pub fn apply_replies<A: Endpoint>(&mut self, now: Instant, agent: &mut Agent<A>) {
        for (client, req, result) in self.replies_out.drain(..) {
            let _ = agent.send_status(now, client, req, result);
        }
        for (client, req, result, config) in self.infos_out.drain(..) {
            let _ = agent.send_info(now, client, req, result, config.as_ref());
        }
        // Ended rather than kept without the objects its client believes it has: the client
        // finds its session gone (a ping, a write) and creates it again.
        let ending: Vec<ClientKey> = self.sessions_to_end.drain().collect();
        for client in ending {
            agent.end_session(now, client, "replay_crash", self);
        }
    }
}

impl<L: Link> OperationSink for Relay<L> {
    fn has_room(&self) -> bool {
        if self.awaiting_executed {
            return false;
        }
        let retained = self.retention.has_room();
        if self.hand_over_at_once && self.generation.is_some() {
            // What a client sent goes to the worker now or is refused unacknowledged (the
            // client sends it again): an operation left in this process's outbox would die
            // with it, after its message was acknowledged and stored as taken. (Before a
            // worker answers, and while one restarts, operations wait in the outbox as
            // always: they are replayed to the new worker; except after a takeover, when
            // nothing is taken until the worker answered, `awaiting_executed`.)
            return retained
                && self.outbox.is_empty()
                && self.in_flight() + HAND_OVER_HEADROOM <= IN_FLIGHT_WINDOW;
        }
        self.outbox.len() < OUTBOX_MAX && self.outbox.bytes < self.outbox_max_bytes && retained
    }

    fn has_room_for(&self, submessages: usize) -> bool {
        if self.awaiting_executed {
            return false;
        }
        if self.hand_over_at_once && self.generation.is_some() {
            // Room for what this message can bring (a submessage is one operation; twice
            // that, for margin), not for the largest message: a client sending one WRITE_DATA
            // a message is not refused while the window has room for it.
            let need = u64::try_from(submessages)
                .unwrap_or(u64::MAX)
                .saturating_mul(2)
                .clamp(1, HAND_OVER_HEADROOM);
            return self.retention.has_room()
                && self.outbox.is_empty()
                && self.in_flight() + need <= IN_FLIGHT_WINDOW;
        }
        self.has_room()
    }

    fn operation(&mut self, now: Instant, op: Operation<'_>) {
        self.take_operation(now, op);
    }
}
