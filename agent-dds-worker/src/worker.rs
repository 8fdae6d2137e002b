//! The worker's event loop: executes the front-ends' operations on DDS entities and streams
//! samples of active reads back.
//!
//! Entities are keyed by (front-end id, client key, object id). The worker keeps nothing a
//! front-end cannot rebuild: after a restart it announces a new generation and the front-ends
//! replay their clients' object graphs.

use std::cell::Cell;
use std::collections::{HashMap, HashSet};
use std::os::fd::AsRawFd;
use std::time::{Duration, Instant};

use rustdds::mio1::{Events, Interest, Poll, Token};
use std::rc::Rc;
use std::sync::Arc;

use rustdds::{DomainParticipant, Publisher, QosPolicies, Subscriber, Topic, TopicKind};
use xrce_common::ipc::shm::{IpcNode, Receiver, Sender, ServiceKind, ShmError};
use xrce_common::ipc::status::{ProcessReport, Reporter, Watchdog, WorkerStatus};
use xrce_common::ipc::{
    self, IpcHeader, MessageKind, FLAG_DIALECT_SPEC, FLAG_LITTLE_ENDIAN, FLAG_REPLAY,
    FLAG_STATUS_REQUESTED,
};
use xrce_common::wire::cdr::CdrReader;
use xrce_common::wire::sample::{decode_samples, sample_state};
use xrce_common::wire::Dialect;
use xrce_common::wire::{
    object_kind, status, ClientKey, ObjectId, ObjectVariant, ReadSpecification, VariantExtra,
};

use crate::acks::{AckTracker, Acknowledging, Outstanding};
use crate::adoption::{Adoption, Origin};
use crate::dds::{effective_domain, endpoint_qos, DdsConfig, EndpointSide, ParticipantPool, Role};
use crate::filter::Filter;
use crate::raw::{RawReader, RawSample, RawWriter};
use crate::recent::RecentSamples;
use crate::representation::{
    check_plain, describe_endpoint, describe_service, describe_topic, participant_name,
};
use crate::ros_graph::{DomainNodes, RosGraph};
use crate::types::{sample_len, KeyDescriptor, StructDef, Ty, TypeSet};
use crate::xml::{self, TopicDesc};

/// Worker settings.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Agent instance name (prefix of every shared-memory resource).
    pub instance: String,
    /// DDS settings.
    pub dds: DdsConfig,
    /// Profiles clients may create by reference (`-r`).
    pub references: crate::references::References,
    /// Announce ROS 2 nodes on `ros_discovery_info`.
    pub ros_graph: bool,
    /// Map XRCE data writers of one domain, topic, type, byte order and QoS onto one shared
    /// DDS writer (volatile, shared-ownership writers only).
    pub share_writers: bool,
    /// How long the entities of a front-end whose process is gone are kept for it to come
    /// back (restarted by its supervisor) before they are deleted.
    pub frontend_grace: Duration,
}

/// How often the worker looks for front-ends whose process is gone.
const CENSUS_PERIOD: Duration = Duration::from_secs(1);
/// How often every writer's matched count is looked at and, when it changed, reported to its
/// front-end (which replays it to a restarted worker).
const MATCH_REPORT_PERIOD: Duration = Duration::from_secs(1);

type EntityKey = (u32, ClientKey, ObjectId);

enum EntityKind {
    /// A logical XRCE participant in a DDS domain, and the ROS node its name stands for.
    Participant(u16, Option<ros2_client::NodeName>),
    /// A topic description; RustDDS topics are made per DDS participant when endpoints are.
    Topic(TopicDesc),
    Publisher(Publisher, DomainParticipant),
    Subscriber(Subscriber, DomainParticipant),
    /// A type definition (`<types>`) the client's topics can use.
    Type(Arc<TypeSet>),
    /// A data writer (its DDS writer, possibly shared), its hold state, and its topic's type
    /// if known.
    Writer(Rc<DdsWriter>, Rematch, Option<Arc<StructDef>>),
    /// A data reader, its poll token, and what its content filters need.
    Reader(Box<RawReader>, Token, ReaderInfo),
    /// A requester (publishes requests, reads the replies to them) or a replier (reads
    /// requests, publishes replies).
    Service(Box<ServiceEndpoint>),
}

/// The DDS writer behind one XRCE data writer, or behind several with `share_writers`.
struct DdsWriter {
    raw: RawWriter,
    /// Its place among the shared writers, if it is one.
    shared: Option<SharedWriterKey>,
    /// When it first matched a reader (read from its status events, which only this
    /// structure consumes, so that every XRCE writer sharing it sees the match).
    matched_at: Cell<Option<Instant>>,
    /// How many readers it matches now (from the same status events).
    matched: Cell<usize>,
    /// Front-end operations written through it that its readers may not have acknowledged.
    outstanding: Outstanding,
}

impl Acknowledging for DdsWriter {
    fn all_acknowledged(&self) -> bool {
        self.raw.all_acknowledged()
    }
    fn outstanding(&self) -> &Outstanding {
        &self.outstanding
    }
}

impl DdsWriter {
    /// Reads the writer's pending status events; returns when it first matched a reader.
    fn poll_matched(&self, now: Instant) -> Option<Instant> {
        while let Some(st) = self.raw.try_recv_status() {
            if let rustdds::dds::statusevents::DataWriterStatus::PublicationMatched {
                current,
                ..
            } = st
            {
                if current.count() > 0 && self.matched_at.get().is_none() {
                    self.matched_at.set(Some(now));
                }
                self.matched.set(current.count().max(0) as usize);
            }
        }
        self.matched_at.get()
    }
}

/// A shared DDS writer, with the QoS and key type it was made with.
struct SharedWriterEntry {
    qos: QosPolicies,
    ty: Option<Arc<StructDef>>,
    writer: std::rc::Weak<DdsWriter>,
}

/// Whether XRCE writers with this QoS may share a DDS writer without changing what DDS
/// readers get beyond the writer's identity: a volatile writer keeps no history for late
/// joiners (a shared transient one would keep its depth over all clients together), and
/// exclusive ownership picks one writer per instance (sharing would merge the contenders).
fn shareable(qos: &QosPolicies) -> bool {
    use rustdds::policy::{Durability, Ownership};
    matches!(qos.durability(), None | Some(Durability::Volatile))
        && matches!(qos.ownership(), None | Some(Ownership::Shared))
}

/// Most XRCE writers on one shared DDS writer. The shared writer keeps this many times the
/// history depth the clients asked for, so that every client keeps the resend window of a
/// writer of its own (a reliable writer overwrites samples beyond its depth, acknowledged
/// or not), and its memory stays within what that many writers of their own would hold.
const SHARE_GROUP: usize = 32;

/// The QoS of a shared DDS writer: the clients' own, with [`SHARE_GROUP`] times their
/// keep-last depth.
fn shared_history(qos: &QosPolicies) -> QosPolicies {
    match qos.history() {
        Some(rustdds::policy::History::KeepLast { depth }) => {
            let deeper = depth.saturating_mul(SHARE_GROUP as i32);
            qos.modify_by(
                &rustdds::QosPolicyBuilder::new()
                    .history(rustdds::policy::History::KeepLast { depth: deeper })
                    .build(),
            )
        }
        _ => qos.clone(),
    }
}

/// What makes two XRCE data writers able to share one DDS writer, besides equal QoS and
/// type: the domain, topic name, type name and byte order.
type SharedWriterKey = (u16, String, String, bool);

/// What a data reader's content filters need.
struct ReaderInfo {
    /// The topic's name.
    topic: String,
    /// The topic's type, if known.
    ty: Option<Arc<StructDef>>,
    /// The reader's own filter (XML `<content_filter>` or the binary `contentbased_filter`).
    filter: Option<Filter>,
}

/// Most requests a requester keeps waiting for their reply (the oldest are forgotten).
const PENDING_REQUESTS_MAX: usize = 4096;

/// The DDS side of an XRCE requester or replier.
struct ServiceEndpoint {
    requester: bool,
    writer: RawWriter,
    reader: RawReader,
    token: Token,
    /// Requester: the sequence number of each published request -> its XRCE request id.
    pending: HashMap<i64, xrce_common::wire::RequestId>,
    pending_order: std::collections::VecDeque<i64>,
    _publisher: Publisher,
    _subscriber: Subscriber,
}

struct Entity {
    parent: Option<ObjectId>,
    kind: EntityKind,
    /// What it was created from (a restarted front-end's replay of the same adopts it).
    origin: Origin,
}

/// A new writer holds its writes until it has matched readers: volatile readers only get
/// samples written after they matched a writer, and DDS discovery takes 0.1–0.4 s here.
/// Without this, a client's first samples (the reference agent delivers them inside one Fast
/// DDS process) and the samples resent after a worker restart would reach nobody.
#[derive(Default)]
struct Rematch {
    /// Until when writes are held at most (None = not holding).
    until: Option<Instant>,
    /// When the writer first matched a reader again.
    matched_at: Option<Instant>,
    /// Held writes: (front-end operation sequence number, sample, is a dispose).
    held: std::collections::VecDeque<(u64, RawSample, bool)>,
    /// Bytes of the held samples.
    held_bytes: usize,
    /// Matched: the held samples are being written in batches (new writes still queue behind
    /// them, so order is kept).
    draining: bool,
    /// When the last batch of held samples was written.
    last_batch: Option<Instant>,
    /// Readers the writer had matched before the worker restarted (from the front-end): a
    /// replayed writer holds until as many match again (0 or 1: the first match).
    expected: u8,
    /// The matched count last reported to the front-end.
    reported: Option<u8>,
}

/// Held samples written per batch while a writer drains: a whole backlog at once would
/// overrun the writer's keep-last history before its reader acknowledged (RustDDS then drops
/// the oldest), which lost samples after a worker restart.
const RELEASE_BATCH: usize = 16;
/// The next batch waits until the readers acknowledged the previous one, at most this long
/// (the loop's pace while draining, so readers that acknowledge only on heartbeats do not
/// slow the drain below 8,000 samples/s per writer).
const RELEASE_ACK_WAIT: Duration = Duration::from_millis(2);

/// Longest hold of a replayed writer's samples when no reader matches.
const REMATCH_MAX: Duration = Duration::from_secs(3);
/// Longest hold of a new writer's first samples when no reader matches (there may be none).
const NEW_WRITER_HOLD_MAX: Duration = Duration::from_secs(1);
/// Margin after the writer's match so the reader has matched the writer too (with 200 ms,
/// a burst released at a replayed writer's match occasionally lost its last samples to
/// Cyclone DDS under load; RustDDS then never repaired them).
const REMATCH_MARGIN: Duration = Duration::from_millis(500);
/// Most samples one holding writer keeps; beyond, it stops waiting for its readers and
/// writes what it holds (logged). (4,096 was too few: 10,000 samples/s fill it in 0.4 s, and the writer then wrote all of
/// them before its readers matched: 3,000 lost per worker kill.)
const REMATCH_HELD_MAX: usize = 65_536;
/// Most bytes one holding writer keeps (the same rule).
const REMATCH_HELD_MAX_BYTES: usize = 32 << 20;

struct ActiveRead {
    request_id: xrce_common::wire::RequestId,
    /// Samples still to deliver (None = unlimited).
    remaining: Option<u32>,
    /// When the read ends by time.
    deadline: Option<Instant>,
    /// No delivery control: deliver what is there, or the first sample to come, then end.
    one_shot: bool,
    /// The front-end asked to hold samples back (its client is not keeping up).
    paused: bool,
    /// DataDeliveryControl pacing; samples wait in the DDS reader meanwhile.
    pacing: Pacing,
    /// The read's content filter.
    filter: Option<Filter>,
    /// The DataFormat the client asked for: without a SampleInfo (DATA, DATA_SEQ) a
    /// dispose cannot be told from a sample, so those reads get no instance ends.
    data_format: u8,
}

/// DataDeliveryControl's `min_pace_period` and `max_bytes_per_second`.
#[derive(Debug, Default)]
struct Pacing {
    /// At least this long between two samples (one DATA each).
    min_pace: Option<Duration>,
    /// At most this many sample bytes per one-second window.
    bytes_per_second: Option<u64>,
    /// No delivery before this.
    next_at: Option<Instant>,
    window_start: Option<Instant>,
    window_bytes: u64,
}

impl Pacing {
    fn new(d: &xrce_common::wire::DataDeliveryControl) -> Self {
        Pacing {
            min_pace: (d.min_pace_period > 0)
                .then(|| Duration::from_millis(u64::from(d.min_pace_period))),
            bytes_per_second: (d.max_bytes_per_second > 0)
                .then_some(u64::from(d.max_bytes_per_second)),
            ..Pacing::default()
        }
    }

    fn limited(&self) -> bool {
        self.min_pace.is_some() || self.bytes_per_second.is_some()
    }

    /// Whether a sample may go now; if not, `next_at` says when to try again.
    fn may_send(&mut self, now: Instant) -> bool {
        if self.next_at.is_some_and(|t| now < t) {
            return false;
        }
        self.next_at = None;
        if let Some(limit) = self.bytes_per_second {
            let start = *self.window_start.get_or_insert(now);
            if now >= start + Duration::from_secs(1) {
                self.window_start = Some(now);
                self.window_bytes = 0;
            } else if self.window_bytes >= limit {
                self.next_at = Some(start + Duration::from_secs(1));
                return false;
            }
        }
        true
    }

    /// Accounts a delivered sample of `len` bytes.
    fn sent(&mut self, now: Instant, len: usize) {
        self.window_bytes += len as u64;
        if let Some(p) = self.min_pace {
            self.next_at = Some(now + p);
        }
    }
}

struct FrontendPort {
    sender: Sender,
    /// The front-end process served (see [`IpcHeader::incarnation`]).
    incarnation: u16,
    processed: u64,
    dirty: bool,
    /// Replies the front-end's full queue refused, oldest first (sent before anything new).
    backlog: std::collections::VecDeque<Vec<u8>>,
    /// Bytes in `backlog`.
    backlog_bytes: usize,
    /// Readers not drained while the front-end is congested; pumped once it has room.
    deferred: HashSet<EntityKey>,
    /// When the front-end last took a message (a dead one takes none: back off).
    last_delivery: Instant,
    /// Messages were published since the front-end was last woken.
    unnotified: bool,
}

/// Most replies held for one congested front-end; beyond, the oldest are dropped (counted).
/// Samples stop being taken from DDS readers while a front-end is congested, so this only
/// fills if a front-end stops reading altogether.
const BACKLOG_MAX: usize = 4096;
/// Bytes of refused replies kept per front-end (samples reach 1 MiB each).
const BACKLOG_MAX_BYTES: usize = 64 << 20;

use crate::representation::OpError;

/// The DDS worker.
pub struct Worker {
    config: WorkerConfig,
    node: IpcNode,
    generation: u32,
    /// Taken by [`Worker::run`] so requests can be handled straight from shared memory.
    requests: Option<Receiver>,
    announce: Sender,
    ports: HashMap<u32, FrontendPort>,
    pool: ParticipantPool,
    entities: HashMap<EntityKey, Entity>,
    /// The object ids of each client's entities (per front-end), so that finding a client's
    /// objects or an entity's children never scans every client's entities.
    by_client: HashMap<(u32, ClientKey), HashSet<ObjectId>>,
    readers: HashMap<Token, EntityKey>,
    next_token: usize,
    reads: HashMap<EntityKey, ActiveRead>,
    to_pump: HashSet<EntityKey>,
    /// Writers holding their samples until matched (kept apart so that the loop never scans
    /// every entity: with thousands of clients that scan dominated the worker's CPU).
    holding: HashSet<EntityKey>,
    /// DDS writers with writes their readers may not have acknowledged.
    acks: AckTracker<DdsWriter>,
    /// DDS writers shared by XRCE writers (`share_writers`), with the QoS and type they
    /// were made with; dead entries are pruned on lookup.
    shared_writers: HashMap<SharedWriterKey, Vec<SharedWriterEntry>>,
    poll: Poll,
    graph: RosGraph,
    /// Front-ends with entities whose process is gone, and since when.
    orphaned: HashMap<u32, Instant>,
    /// When to look for gone front-ends next.
    next_census: Instant,
    /// When the writers' matched counts are next looked at (reported to the front-ends).
    next_match_report: Instant,
    /// Front-end processes (id, incarnation) that said FrontendHello to this worker: they
    /// know this generation, and their operations are meant for it (kept apart from the
    /// reply ports, which the census may drop and recreate).
    greeted: HashSet<(u32, u16)>,
    /// Entities of front-ends that said hello again, for their replay to take back.
    adoption: Adoption,
    /// The last samples handed to each front-end, for a successor's replayed reads.
    recent: HashMap<u32, RecentSamples>,
    /// Counters by reason of rejected or failed work.
    pub dropped: HashMap<&'static str, u64>,
    /// Restarted front-ends (id -> incarnation) whose requests wait for the end of the
    /// drain, and those requests.
    successors: HashMap<u32, u16>,
    deferred: Vec<Vec<u8>>,
    /// Samples accepted for DDS writers (written, or held until readers match).
    samples_written: u64,
    /// Samples taken from DDS readers and sent to front-ends.
    samples_taken: u64,
    /// Writes this process's status report.
    reporter: Reporter,
    /// Pings systemd's watchdog when the worker is a unit of its own.
    watchdog: Watchdog,
}

impl std::fmt::Debug for Worker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Worker")
            .field("generation", &self.generation)
            .field("entities", &self.entities.len())
            .finish()
    }
}

/// Samples taken from one reader per wake-up before others get a turn.
const PUMP_BATCH: usize = 256;

impl Worker {
    /// Opens the IPC services, then announces a new generation.
    pub fn new(config: WorkerConfig) -> anyhow::Result<Self> {
        let node = IpcNode::new(&config.instance, "xrce-dds-worker")?;
        let requests = node.receiver(&ipc::request_service(&config.instance), ServiceKind::Data)?;
        let announce = node.sender(
            &ipc::announce_service(&config.instance),
            ServiceKind::Announce,
        )?;
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let generation = (nanos ^ std::process::id().rotate_left(16)) | 1;
        let pool = ParticipantPool::new(config.dds.clone());
        let ros_graph = config.ros_graph;
        let config_instance = config.instance.clone();
        let w = Worker {
            config,
            node,
            generation,
            requests: Some(requests),
            announce,
            ports: HashMap::new(),
            pool,
            entities: HashMap::new(),
            by_client: HashMap::new(),
            readers: HashMap::new(),
            next_token: 1,
            reads: HashMap::new(),
            to_pump: HashSet::new(),
            holding: HashSet::new(),
            acks: AckTracker::new(Instant::now()),
            shared_writers: HashMap::new(),
            poll: Poll::new()?,
            graph: RosGraph::new(ros_graph),
            orphaned: HashMap::new(),
            next_census: Instant::now() + CENSUS_PERIOD,
            next_match_report: Instant::now() + MATCH_REPORT_PERIOD,
            greeted: HashSet::new(),
            adoption: Adoption::default(),
            recent: HashMap::new(),
            dropped: HashMap::new(),
            successors: HashMap::new(),
            deferred: Vec::new(),
            samples_written: 0,
            samples_taken: 0,
            reporter: Reporter::new(&config_instance, "worker"),
            watchdog: Watchdog::from_env(),
        };
        let mut hello = IpcHeader::new(MessageKind::WorkerHello);
        hello.generation = w.generation;
        w.announce.send(&hello, &[])?;
        w.announce.notify()?;
        tracing::info!(generation = w.generation, instance = %w.config.instance, "worker serving");
        Ok(w)
    }

    /// This worker's generation id.
    pub fn generation(&self) -> u32 {
        self.generation
    }

    fn count(&mut self, reason: &'static str) {
        *self.dropped.entry(reason).or_default() += 1;
    }

    /// Runs until SIGINT or SIGTERM.
    pub fn run(&mut self) -> anyhow::Result<()> {
        let requests = self
            .requests
            .take()
            .ok_or_else(|| anyhow::anyhow!("the worker runs only once"))?;
        let result = self.serve(&requests);
        self.reporter.remove();
        result
    }

    fn serve(&mut self, requests: &Receiver) -> anyhow::Result<()> {
        let mut events = Events::with_capacity(256);
        loop {
            if self.node.termination_requested() {
                tracing::info!("termination requested");
                return Ok(());
            }
            let now = Instant::now();
            if now >= self.reporter.due() {
                let report = self.status_report();
                self.reporter.maybe_write(now, || report);
            }
            self.watchdog.maybe_ping(now);
            // At least once per report period: the report's age is the loop's heartbeat.
            let period = xrce_common::ipc::status::REPORT_PERIOD.as_millis() as i32;
            let timeout = match self.poll_timeout() {
                t if t < 0 => period,
                t => t.min(period),
            };
            let ready = xrce_common::ipc::shm::wait_readable(
                &[requests.raw_fd(), self.poll.as_raw_fd()],
                timeout,
            )?;
            // Wake-ups are consumed only when there are some (a system call each time, and
            // the loop runs per sample under load); the queue itself is read every time.
            if ready & 1 != 0 {
                requests.clear_events();
            }
            requests.drain(|m| self.handle_request(m))?;
            self.serve_successors();
            // Always, not only when its descriptor polled readable: gated that way, every
            // reader stalled (measured with 3 and 100 publishers).
            self.poll.poll(&mut events, Some(Duration::ZERO))?;
            for e in events.iter() {
                if let Some(k) = self.readers.get(&e.token()) {
                    self.to_pump.insert(*k);
                }
            }
            let pump: Vec<EntityKey> = self.to_pump.drain().collect();
            for k in pump {
                self.pump(k);
            }
            self.expire_reads();
            self.release_rematched();
            self.report_matches();
            self.publish_graph();
            self.flush();
            self.watch_frontends();
        }
    }

    /// Deletes the entities of front-ends whose process has been gone for the grace period
    /// (a gateway front-end stopped for good); a restarted one says hello within it and
    /// takes over, as before. Dead nodes' shared-memory resources are removed on the way.
    fn watch_frontends(&mut self) {
        let now = Instant::now();
        if now < self.next_census {
            return;
        }
        self.next_census = now + CENSUS_PERIOD;
        let served: HashSet<u32> = self.by_client.keys().map(|(fe, _)| *fe).collect();
        if served.is_empty() && self.orphaned.is_empty() {
            return;
        }
        let census = self.node.nodes();
        self.orphaned.retain(|fe, _| served.contains(fe));
        for fe in served {
            let name = format!("xrce-frontend-{fe}");
            if census.alive.contains(&name) {
                if self.orphaned.remove(&fe).is_some() {
                    tracing::info!(frontend = fe, "front-end is back");
                }
                continue;
            }
            let grace = self.config.frontend_grace;
            let since = *self.orphaned.entry(fe).or_insert_with(|| {
                tracing::warn!(
                    frontend = fe,
                    grace_s = grace.as_secs_f64(),
                    "front-end process gone; its clients' entities are kept for it to come back"
                );
                now
            });
            if now.saturating_duration_since(since) >= grace {
                let clients = self.by_client.keys().filter(|(f, _)| *f == fe).count();
                tracing::warn!(
                    frontend = fe,
                    clients,
                    "front-end did not come back; deleting its clients' entities"
                );
                self.remove_where(|c| c.0 == fe);
                self.adoption.forget(fe);
                self.recent.remove(&fe);
                self.ports.remove(&fe);
                self.greeted.retain(|(f, _)| *f != fe);
                self.orphaned.remove(&fe);
                self.count("frontend_gone");
            }
        }
    }

    /// Publishes the ROS graph of every domain that changed, when its update is due.
    fn publish_graph(&mut self) {
        let now = Instant::now();
        for domain in self.graph.due(now) {
            let nodes = self.domain_nodes(domain);
            if nodes.nodes.is_empty() && !self.graph.has_writer(domain) {
                // No node ever: no graph writer (nor DDS participant) for this domain.
                continue;
            }
            let published = self
                .pool
                .get(domain, Role::Publish)
                .and_then(|dp| self.graph.publish(domain, &dp, nodes));
            if let Err(e) = published {
                tracing::warn!(domain, error = %e, "ROS graph not published; retrying");
                self.graph.touch(domain, now);
            }
        }
    }

    /// The ROS nodes of `domain`: participants with a node name, with the GUIDs of the
    /// writers and readers below them (requesters and repliers included).
    fn domain_nodes(&self, domain: u16) -> DomainNodes {
        let mut nodes: std::collections::BTreeMap<
            EntityKey,
            (
                ros2_client::NodeName,
                Vec<rustdds::GUID>,
                Vec<rustdds::GUID>,
            ),
        > = Default::default();
        for (k, e) in &self.entities {
            if let EntityKind::Participant(d, Some(name)) = &e.kind {
                if *d == domain {
                    nodes.insert(*k, (name.clone(), Vec::new(), Vec::new()));
                }
            }
        }
        // A participant is announced as a ROS node once it has an endpoint on a ROS topic
        // (`rt/`, `rq/`, `rr/`, as micro-ROS names them): plain XRCE applications, whose
        // participants are named too, stay out of the ROS graph.
        let mut ros = std::collections::BTreeSet::new();
        let is_ros = |t: &str| ["rt/", "rq/", "rr/"].iter().any(|p| t.starts_with(p));
        for (k, e) in &self.entities {
            let (writer, reader, ros_topic) = match &e.kind {
                EntityKind::Writer(w, _, _) => {
                    (Some(w.raw.guid()), None, is_ros(&w.raw.topic_name()))
                }
                EntityKind::Reader(r, _, info) => (None, Some(r.guid()), is_ros(&info.topic)),
                EntityKind::Service(s) => (
                    Some(s.writer.guid()),
                    Some(s.reader.guid()),
                    is_ros(&s.writer.topic_name()),
                ),
                _ => continue,
            };
            let Some((pid, _)) = e.parent.and_then(|p| self.participant_of(*k, p)) else {
                continue;
            };
            if let Some(n) = nodes.get_mut(&(k.0, k.1, pid)) {
                n.1.extend(writer);
                n.2.extend(reader);
                if ros_topic {
                    ros.insert((k.0, k.1, pid));
                }
            }
        }
        DomainNodes {
            nodes: nodes
                .into_iter()
                .filter(|(k, _)| ros.contains(k))
                .map(|(_, (n, mut w, mut r))| {
                    w.sort();
                    r.sort();
                    (n, w, r)
                })
                .collect(),
        }
    }

    /// The domain an entity lives in, if it is part of a participant.
    fn domain_of(&self, key: EntityKey) -> Option<u16> {
        match &self.entities.get(&key)?.kind {
            EntityKind::Participant(d, _) => Some(*d),
            _ => self
                .participant_of(key, self.entities.get(&key)?.parent?)
                .map(|(_, d)| d),
        }
    }

    fn poll_timeout(&self) -> i32 {
        if !self.to_pump.is_empty() {
            return 0;
        }
        let acks = self
            .acks
            .due()
            .map(|d| d.saturating_duration_since(Instant::now()).as_millis() as i32 + 1);
        let t = self.timeout_without_acks();
        match (acks, t) {
            (Some(a), t) if t < 0 => a,
            (Some(a), t) => a.min(t),
            (None, t) => t,
        }
    }

    fn timeout_without_acks(&self) -> i32 {
        if !self.holding.is_empty() {
            let draining = self.holding.iter().any(|k| {
                matches!(self.entities.get(k), Some(Entity { kind: EntityKind::Writer(_, r, _), .. }) if r.draining)
            });
            return if draining { 1 } else { 20 };
        }
        let waiting = self
            .ports
            .values()
            .filter(|p| !p.backlog.is_empty() || p.dirty || p.unnotified);
        if let Some(newest) = waiting.map(|p| p.last_delivery).max() {
            // A congested front-end does not signal when it drained: try again shortly, and
            // rarely once it has taken nothing for a while (it may be gone).
            return if newest.elapsed() < Duration::from_secs(1) {
                1
            } else {
                100
            };
        }
        let now = Instant::now();
        let census =
            (!self.by_client.is_empty() || !self.orphaned.is_empty()).then_some(self.next_census);
        self.reads
            .values()
            .flat_map(|r| [r.deadline, r.pacing.next_at])
            .flatten()
            .chain(self.graph.deadline())
            .chain(census)
            .min()
            .map(|d| {
                d.saturating_duration_since(now)
                    .as_millis()
                    .min(i32::MAX as u128) as i32
                    + 1
            })
            .unwrap_or(-1)
    }

    /// This worker's status report (what it holds and did).
    fn status_report(&self) -> ProcessReport {
        let mut entities: std::collections::BTreeMap<String, u64> = Default::default();
        for e in self.entities.values() {
            let kind = match &e.kind {
                EntityKind::Participant(..) => "participant",
                EntityKind::Topic(_) => "topic",
                EntityKind::Publisher(..) => "publisher",
                EntityKind::Subscriber(..) => "subscriber",
                EntityKind::Type(_) => "type",
                EntityKind::Writer(..) => "writer",
                EntityKind::Reader(..) => "reader",
                EntityKind::Service(_) => "service",
            };
            *entities.entry(kind.into()).or_default() += 1;
        }
        ProcessReport {
            name: "worker".into(),
            role: "worker".into(),
            worker: Some(WorkerStatus {
                generation: self.generation,
                entities,
                frontends: self.ports.len() as u64,
                samples_written: self.samples_written,
                samples_taken: self.samples_taken,
                dropped: self
                    .dropped
                    .iter()
                    .map(|(k, v)| (k.to_string(), *v))
                    .collect(),
            }),
            ..Default::default()
        }
    }

    /// The reply port of a front-end, opened on first use.
    fn port(&mut self, frontend: u32) -> Result<&mut FrontendPort, ShmError> {
        use std::collections::hash_map::Entry;
        match self.ports.entry(frontend) {
            Entry::Occupied(e) => Ok(e.into_mut()),
            Entry::Vacant(v) => {
                let sender = self.node.sender(
                    &ipc::reply_service(&self.config.instance, frontend),
                    ServiceKind::Reply,
                )?;
                Ok(v.insert(FrontendPort {
                    sender,
                    incarnation: 0,
                    processed: 0,
                    dirty: false,
                    backlog: Default::default(),
                    backlog_bytes: 0,
                    unnotified: false,
                    deferred: HashSet::new(),
                    last_delivery: Instant::now(),
                }))
            }
        }
    }

    /// Sends a reply to its front-end, or queues it behind earlier refused ones.
    fn reply(&mut self, h: IpcHeader, body: &[u8]) {
        self.reply_with(h, body.len(), |b| b.copy_from_slice(body));
    }

    /// Sends a reply of `len` body bytes that `fill` writes (in place in shared memory when
    /// the front-end's queue has room), else keeps it in the front-end's backlog.
    fn reply_with(&mut self, mut h: IpcHeader, len: usize, fill: impl Fn(&mut [u8])) {
        h.generation = self.generation;
        let incarnation = self.ports.get(&h.frontend_id).map_or(0, |p| p.incarnation);
        if h.incarnation == 0 {
            h.incarnation = incarnation;
        }
        if len > ipc::MAX_BODY {
            tracing::warn!(frontend = h.frontend_id, client = %h.client_key, len, "sample too large for the front-end link; dropped");
            return self.count("sample_too_large");
        }
        let port = match self.port(h.frontend_id) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!(frontend = h.frontend_id, error = %e, "reply lost");
                return self.count("reply_send_failed");
            }
        };
        port.dirty = true;
        if port.backlog.is_empty() {
            match port.sender.send_with(&h, len, &fill) {
                Ok(true) => {
                    port.last_delivery = Instant::now();
                    port.unnotified = true;
                    return;
                }
                Ok(false) => {}
                Err(e) => tracing::debug!(error = %e, "reply send failed; queued"),
            }
        }
        let mut m = vec![0u8; IpcHeader::LEN + len];
        h.write(&mut m, len);
        fill(&mut m[IpcHeader::LEN..]);
        let mut overflow = false;
        while !port.backlog.is_empty()
            && (port.backlog.len() >= BACKLOG_MAX
                || port.backlog_bytes + m.len() > BACKLOG_MAX_BYTES)
        {
            if let Some(old) = port.backlog.pop_front() {
                port.backlog_bytes -= old.len();
            }
            overflow = true;
        }
        port.backlog_bytes += m.len();
        port.backlog.push_back(m);
        if overflow {
            self.count("reply_backlog_overflow");
        }
    }

    fn status(&mut self, req: &IpcHeader, result: Result<(), OpError>) {
        let code = match &result {
            Ok(()) => status::OK,
            Err((code, why)) => {
                tracing::warn!(client = %req.client_key, object = ?req.object_id, kind = ?req.kind, status = code, "{why}");
                *code
            }
        };
        let h = IpcHeader {
            kind: MessageKind::Status,
            ..*req
        };
        self.reply(h, &[code, 0]);
    }

    /// Screens a request by the front-end process that sent it: a restarted front-end's
    /// requests wait until the queue holds nothing more of its predecessor's (whose
    /// operations run first, on the entities they were meant for); a predecessor's request
    /// that comes after its successor took over is dropped.
    fn handle_request(&mut self, bytes: &[u8]) {
        let (h, body) = match IpcHeader::decode(bytes) {
            Ok(v) => v,
            Err(e) => {
                tracing::warn!(error = %e, "dropped IPC message");
                return self.count("bad_ipc_message");
            }
        };
        let fe = h.frontend_id;
        if self.successors.get(&fe) == Some(&h.incarnation) {
            return self.deferred.push(bytes.to_vec());
        }
        let current = self
            .ports
            .get(&fe)
            .map(|p| p.incarnation)
            .filter(|i| *i != 0);
        let greeted = self.greeted.contains(&(fe, h.incarnation));
        match current {
            Some(c) if c != h.incarnation && h.kind == MessageKind::FrontendHello => {
                self.successors.insert(fe, h.incarnation);
                self.deferred.push(bytes.to_vec());
            }
            Some(c) if c != h.incarnation => self.count("predecessor_operation"),
            _ if !greeted && h.kind != MessageKind::FrontendHello => {
                // Sent before the front-end knew this worker (to the one that died): the
                // front-end replays and resends what matters after its hello.
                self.count("operation_before_hello");
            }
            _ => self.process_request(h, body),
        }
    }

    /// Serves the requests of restarted front-ends held back by [`Self::handle_request`],
    /// once the queue was drained of their predecessors'.
    fn serve_successors(&mut self) {
        if self.deferred.is_empty() {
            return;
        }
        self.successors.clear();
        for m in std::mem::take(&mut self.deferred) {
            if let Ok((h, body)) = IpcHeader::decode(&m) {
                self.process_request(h, body);
            }
        }
    }

    fn process_request(&mut self, h: IpcHeader, body: &[u8]) {
        let key = (h.frontend_id, h.client_key, h.object_id);
        match h.kind {
            MessageKind::FrontendHello => {
                tracing::info!(
                    frontend = h.frontend_id,
                    incarnation = h.incarnation,
                    "front-end (re)connected"
                );
                self.greeted.retain(|(fe, _)| *fe != h.frontend_id);
                self.greeted.insert((h.frontend_id, h.incarnation));
                self.offer_entities(h.frontend_id);
                if let Ok(p) = self.port(h.frontend_id) {
                    // Its operations are numbered from its hello on.
                    p.incarnation = h.incarnation;
                    p.processed = h.op_seq;
                }
                // Replies held for a previous incarnation of this front-end mean nothing now.
                if let Some(p) = self.ports.get_mut(&h.frontend_id) {
                    p.backlog.clear();
                    p.backlog_bytes = 0;
                    p.deferred.clear();
                }
                let mut hello = IpcHeader::new(MessageKind::WorkerHello);
                hello.frontend_id = h.frontend_id;
                self.reply(hello, &[]);
            }
            MessageKind::ReplayDone => self.end_adoption(h.frontend_id),
            MessageKind::DeleteClient => {
                self.remove_where(|c| c.0 == h.frontend_id && c.1 == h.client_key)
            }
            MessageKind::Create => {
                let r = self.create(
                    key,
                    body,
                    h.flags & FLAG_REPLAY != 0,
                    h.flags & FLAG_LITTLE_ENDIAN != 0,
                    h.readers,
                );
                if r.is_ok() {
                    tracing::debug!(client = %h.client_key, object = ?h.object_id, replay = h.flags & FLAG_REPLAY != 0, "created");
                }
                self.status(&h, r);
            }
            MessageKind::Delete => {
                let r = if self.entities.contains_key(&key) {
                    self.remove_subtree(key);
                    Ok(())
                } else {
                    Err((
                        status::ERR_UNKNOWN_REFERENCE,
                        "delete of an unknown object".into(),
                    ))
                };
                self.status(&h, r);
            }
            MessageKind::Write => {
                let r = self.write(key, &h, body);
                if r.is_err() || h.flags & FLAG_STATUS_REQUESTED != 0 {
                    self.status(&h, r);
                }
            }
            MessageKind::PauseRead | MessageKind::ResumeRead => {
                let pause = h.kind == MessageKind::PauseRead;
                if let Some(r) = self.reads.get_mut(&key) {
                    r.paused = pause;
                    if !pause {
                        self.to_pump.insert(key);
                    }
                }
            }
            MessageKind::Read => {
                let r = self.start_read(key, &h, body);
                if r.is_err() {
                    self.status(&h, r);
                } else {
                    self.to_pump.insert(key);
                }
            }
            other => {
                tracing::warn!(kind = ?other, "unexpected IPC message kind on the request service");
                self.count("unexpected_ipc_kind");
            }
        }
        if let Ok(p) = self.port(h.frontend_id) {
            if p.incarnation == h.incarnation {
                p.processed = p.processed.max(h.op_seq);
            }
            p.dirty = true;
        }
    }

    /// Sends refused replies again, then progress; wakes every front-end that got something.
    /// Failures are logged and retried on the next pass; they never stop the worker.
    fn flush(&mut self) {
        let generation = self.generation;
        let held = self.oldest_held();
        let (moved, all) = self.acks.poll(Instant::now());
        for (fe, p) in self.ports.iter_mut() {
            if all || moved.contains(fe) {
                p.dirty = true;
            }
        }
        // Computed once, and only when a progress message goes out (the loop runs per sample).
        let acks = &self.acks;
        let mut outstanding: Option<HashMap<u32, u64>> = None;
        for (fe, p) in self.ports.iter_mut() {
            let mut sent = false;
            while let Some(m) = p.backlog.front() {
                match p.sender.send_encoded(m) {
                    Ok(true) => {}
                    Ok(false) => break,
                    Err(e) => {
                        // Not deliverable at all (it cannot happen for messages within
                        // MAX_BODY): drop it rather than block the front-end for ever.
                        tracing::warn!(frontend = fe, error = %e, "reply dropped");
                    }
                }
                if let Some(m) = p.backlog.pop_front() {
                    p.backlog_bytes -= m.len();
                }
                sent = true;
            }
            if p.backlog.is_empty() {
                self.to_pump.extend(p.deferred.drain());
            }
            // Held writes left the queue but are not executed yet: execution stops just
            // before the oldest.
            let executed = held.get(fe).map_or(p.processed, |oldest| {
                p.processed.min(oldest.saturating_sub(1))
            });
            if (p.dirty || held.contains_key(fe)) && p.backlog.is_empty() {
                let mut h = IpcHeader::new(MessageKind::Progress);
                h.frontend_id = *fe;
                h.generation = generation;
                h.incarnation = p.incarnation;
                h.op_seq = p.processed;
                // Acknowledged by every matched reliable reader: up to just before the
                // oldest write still outstanding.
                let acknowledged = outstanding
                    .get_or_insert_with(|| acks.oldest_outstanding())
                    .get(fe)
                    .map_or(executed, |oldest| executed.min(oldest.saturating_sub(1)));
                let mut body = [0u8; 16];
                body[..8].copy_from_slice(&executed.to_le_bytes());
                body[8..].copy_from_slice(&acknowledged.to_le_bytes());
                if let Ok(true) = p.sender.send(&h, &body) {
                    p.dirty = false;
                    sent = true;
                }
            }
            if sent {
                p.last_delivery = Instant::now();
            }
            // Also when only replies sent directly went out (a full queue may have refused
            // the progress message): a front-end that is not woken does not read them.
            if sent || p.unnotified {
                p.unnotified = false;
                if let Err(e) = p.sender.notify() {
                    // Tried again on the next pass.
                    p.unnotified = true;
                    tracing::debug!(frontend = fe, error = %e, "front-end wake-up failed");
                }
            }
        }
    }

    fn parent_entity(
        &self,
        key: EntityKey,
        parent: ObjectId,
        kind: u8,
    ) -> Result<&Entity, OpError> {
        let e = self.entities.get(&(key.0, key.1, parent)).ok_or((
            status::ERR_UNKNOWN_REFERENCE,
            format!("parent {parent:?} does not exist"),
        ))?;
        if parent.kind() != kind {
            return Err((
                status::ERR_UNKNOWN_REFERENCE,
                format!("parent {parent:?} is not of kind {kind}"),
            ));
        }
        Ok(e)
    }

    /// The participant entity an object hangs under, and its domain.
    fn participant_of(&self, key: EntityKey, mut id: ObjectId) -> Option<(ObjectId, u16)> {
        for _ in 0..8 {
            let e = self.entities.get(&(key.0, key.1, id))?;
            match &e.kind {
                EntityKind::Participant(domain, _) => return Some((id, *domain)),
                _ => id = e.parent?,
            }
        }
        None
    }

    /// A front-end said hello (it started, or took over from a predecessor): the entities
    /// held for it wait for its replay to take them back, and their reads stop (the replay
    /// starts those the client still has; samples wait in the DDS readers meanwhile).
    fn offer_entities(&mut self, fe: u32) {
        let keys: Vec<EntityKey> = self
            .by_client
            .iter()
            .filter(|(c, _)| c.0 == fe)
            .flat_map(|(c, ids)| ids.iter().map(move |id| (c.0, c.1, *id)))
            .collect();
        if !keys.is_empty() {
            tracing::info!(
                frontend = fe,
                entities = keys.len(),
                "front-end came back; its entities are kept for its replay to take back"
            );
        }
        self.reads.retain(|k, _| k.0 != fe);
        self.to_pump.retain(|k| k.0 != fe);
        self.acks.forget_frontend(fe);
        self.adoption.offer(fe, keys);
    }

    /// The replay of front-end `fe` is complete: what it did not take back goes.
    fn end_adoption(&mut self, fe: u32) {
        let (left, adopted) = self.adoption.finish(fe);
        let mut removed = 0;
        for k in left {
            if self.entities.contains_key(&k) {
                self.remove_subtree(k);
                removed += 1;
            }
        }
        if adopted + removed > 0 {
            tracing::info!(frontend = fe, adopted, removed, "front-end replay complete");
        }
    }

    /// Takes entity `key` back for a replay of its CREATE (`body`, `little_endian`), if it
    /// was created from the same; whether it was.
    fn adopt(&mut self, key: EntityKey, body: &[u8], little_endian: bool) -> bool {
        let Some(e) = self.entities.get_mut(&key) else {
            return false;
        };
        if e.origin != Origin::new(body, little_endian) {
            return false;
        }
        if let EntityKind::Writer(_, rematch, _) = &mut e.kind {
            // Samples it still holds were numbered by the predecessor: as old as any.
            for h in rematch.held.iter_mut() {
                h.0 = 0;
            }
        }
        self.adoption.adopted(key.0);
        tracing::debug!(client = %key.1, object = ?key.2, "entity taken back");
        true
    }

    fn create(
        &mut self,
        key: EntityKey,
        body: &[u8],
        replay: bool,
        little_endian: bool,
        readers: u8,
    ) -> Result<(), OpError> {
        let variant = ObjectVariant::decode(&mut CdrReader::new(body, true)).map_err(|e| {
            (
                status::ERR_INVALID_DATA,
                format!("object representation: {e}"),
            )
        })?;
        if variant.kind != key.2.kind() {
            return Err((
                status::ERR_INVALID_DATA,
                "object id kind differs from the representation kind".into(),
            ));
        }
        if self.adoption.claim(&key) && self.adopt(key, body, little_endian) {
            return Ok(());
        }
        if self.entities.contains_key(&key) {
            // The front-end decides creation modes; here an existing object is replaced.
            self.remove_subtree(key);
        }
        let repr = &variant.representation;
        let dds_err =
            |what: &str, e: &dyn std::fmt::Debug| (status::ERR_DDS_ERROR, format!("{what}: {e:?}"));
        let (parent, kind) = match (variant.kind, variant.extra) {
            (object_kind::PARTICIPANT, VariantExtra::DomainId(d)) => {
                check_plain(repr, variant.kind, &self.config.references, little_endian)?;
                let domain = effective_domain(d).map_err(|e| (status::ERR_INVALID_DATA, e))?;
                let node = participant_name(repr, &self.config.references, little_endian)
                    .as_deref()
                    .and_then(crate::ros_graph::node_name);
                (None, EntityKind::Participant(domain, node))
            }
            (object_kind::TOPIC, VariantExtra::Parent(p)) => {
                self.parent_entity(key, p, object_kind::PARTICIPANT)?;
                let desc = describe_topic(repr, &self.config.references, little_endian)?;
                (Some(p), EntityKind::Topic(desc))
            }
            (
                kind @ (object_kind::PUBLISHER | object_kind::SUBSCRIBER),
                VariantExtra::Parent(p),
            ) => {
                self.parent_entity(key, p, object_kind::PARTICIPANT)?;
                check_plain(repr, kind, &self.config.references, little_endian)?;
                let (_, domain) = self
                    .participant_of(key, p)
                    .ok_or((status::ERR_UNKNOWN_REFERENCE, "no participant".into()))?;
                let role = if kind == object_kind::PUBLISHER {
                    Role::Publish
                } else {
                    Role::Subscribe
                };
                let dp = self
                    .pool
                    .get(domain, role)
                    .map_err(|e| (status::ERR_DDS_ERROR, e))?;
                let entity = if role == Role::Publish {
                    let publisher = dp
                        .create_publisher(&QosPolicies::qos_none())
                        .map_err(|e| dds_err("create publisher", &e))?;
                    EntityKind::Publisher(publisher, dp)
                } else {
                    let subscriber = dp
                        .create_subscriber(&QosPolicies::qos_none())
                        .map_err(|e| dds_err("create subscriber", &e))?;
                    EntityKind::Subscriber(subscriber, dp)
                };
                (Some(p), entity)
            }
            (object_kind::DATAWRITER, VariantExtra::Parent(p)) => {
                let (publisher, dp) =
                    match &self.parent_entity(key, p, object_kind::PUBLISHER)?.kind {
                        EntityKind::Publisher(x, dp) => (x.clone(), dp.clone()),
                        _ => {
                            return Err((
                                status::ERR_UNKNOWN_REFERENCE,
                                "parent is not a publisher".into(),
                            ))
                        }
                    };
                let desc = describe_endpoint(repr, true, &self.config.references, little_endian)?;
                let (topic, tdesc, ty, kd) = self.endpoint_topic(key, p, &dp, &desc)?;
                let qos = endpoint_qos(EndpointSide::Writer, &tdesc.qos, &desc.qos);
                let domain = self.participant_of(key, p).map_or(0, |(_, d)| d);
                let shared_key: Option<SharedWriterKey> =
                    (self.config.share_writers && shareable(&qos)).then(|| {
                        (
                            domain,
                            tdesc.name.clone(),
                            tdesc.type_name.clone(),
                            little_endian,
                        )
                    });
                let existing = shared_key
                    .as_ref()
                    .and_then(|k| self.shared_writer(k, &qos, ty.as_ref()));
                let w = match existing {
                    Some(w) => w,
                    None => {
                        let dds_qos = if shared_key.is_some() {
                            shared_history(&qos)
                        } else {
                            qos.clone()
                        };
                        // A client writes in its native byte order, the one of its CREATE.
                        let raw = RawWriter::create(&publisher, &topic, dds_qos, little_endian, kd)
                            .map_err(|e| dds_err("create data writer", &e))?;
                        let w = Rc::new(DdsWriter {
                            raw,
                            shared: shared_key.clone(),
                            matched_at: Cell::new(None),
                            matched: Cell::new(0),
                            outstanding: Outstanding::default(),
                        });
                        if let Some(k) = shared_key {
                            self.shared_writers
                                .entry(k)
                                .or_default()
                                .push(SharedWriterEntry {
                                    qos,
                                    ty: ty.clone(),
                                    writer: Rc::downgrade(&w),
                                });
                        }
                        w
                    }
                };
                let now = Instant::now();
                // A writer joining a shared DDS writer that matched its readers long enough
                // ago writes at once.
                let matched = w
                    .poll_matched(now)
                    .is_some_and(|t| now >= t + REMATCH_MARGIN)
                    && w.matched.get() >= usize::from(readers);
                let rematch = Rematch {
                    until: (!matched).then(|| {
                        now + if replay {
                            REMATCH_MAX
                        } else {
                            NEW_WRITER_HOLD_MAX
                        }
                    }),
                    expected: readers,
                    ..Default::default()
                };
                (Some(p), EntityKind::Writer(w, rematch, ty))
            }
            (object_kind::DATAREADER, VariantExtra::Parent(p)) => {
                let (subscriber, dp) =
                    match &self.parent_entity(key, p, object_kind::SUBSCRIBER)?.kind {
                        EntityKind::Subscriber(x, dp) => (x.clone(), dp.clone()),
                        _ => {
                            return Err((
                                status::ERR_UNKNOWN_REFERENCE,
                                "parent is not a subscriber".into(),
                            ))
                        }
                    };
                let desc = describe_endpoint(repr, false, &self.config.references, little_endian)?;
                let (topic, tdesc, ty, kd) = self.endpoint_topic(key, p, &dp, &desc)?;
                let filter = desc
                    .content_filter
                    .as_deref()
                    .map(|f| compile_filter(f, ty.as_ref(), &tdesc.type_name))
                    .transpose()?;
                let qos = endpoint_qos(EndpointSide::Reader, &tdesc.qos, &desc.qos);
                let mut r = RawReader::create(&subscriber, &topic, qos, kd)
                    .map_err(|e| dds_err("create data reader", &e))?;
                let token = Token(self.next_token);
                self.next_token += 1;
                self.poll
                    .registry()
                    .register(&mut r, token, Interest::READABLE)
                    .map_err(|e| dds_err("register reader", &e))?;
                self.readers.insert(token, key);
                (
                    Some(p),
                    EntityKind::Reader(
                        Box::new(r),
                        token,
                        ReaderInfo {
                            topic: tdesc.name.clone(),
                            ty,
                            filter,
                        },
                    ),
                )
            }
            (kind @ (object_kind::REQUESTER | object_kind::REPLIER), VariantExtra::Parent(p)) => {
                self.parent_entity(key, p, object_kind::PARTICIPANT)?;
                let requester = kind == object_kind::REQUESTER;
                let desc =
                    describe_service(repr, requester, &self.config.references, little_endian)?;
                let (_, domain) = self
                    .participant_of(key, p)
                    .ok_or((status::ERR_UNKNOWN_REFERENCE, "no participant".into()))?;
                let endpoint = self.create_service(&desc, domain, requester, little_endian)?;
                self.readers.insert(endpoint.token, key);
                tracing::info!(
                    frontend = key.0,
                    client = %key.1,
                    service = %desc.service_name,
                    request_topic = %desc.request_topic,
                    reply_topic = %desc.reply_topic,
                    requester,
                    "service endpoint created"
                );
                (Some(p), EntityKind::Service(Box::new(endpoint)))
            }
            (object_kind::TYPE, _) => {
                let set = match repr {
                    xrce_common::wire::Representation::Xml(x) => {
                        TypeSet::parse(x).map_err(|e| (status::ERR_INVALID_DATA, e.to_string()))?
                    }
                    xrce_common::wire::Representation::Reference(r) => {
                        let t = self.config.references.types().get(r).ok_or_else(|| {
                            (
                                status::ERR_UNKNOWN_REFERENCE,
                                format!("type {r:?} is not in the references file"),
                            )
                        })?;
                        TypeSet::single(t)
                    }
                    xrce_common::wire::Representation::Binary(_) => {
                        return Err((
                            status::ERR_INVALID_DATA,
                            "a TYPE object is described by XML or by reference".into(),
                        ))
                    }
                };
                if set.is_empty() {
                    return Err((
                        status::ERR_INVALID_DATA,
                        "the TYPE representation defines no structure".into(),
                    ));
                }
                tracing::info!(main = ?set.main(), "types registered");
                (None, EntityKind::Type(Arc::new(set)))
            }
            (k, _) => {
                return Err((
                    status::ERR_INVALID_DATA,
                    format!("object kind {k:#04x} is not supported yet"),
                ))
            }
        };
        if matches!(&kind, EntityKind::Writer(_, r, _) if r.until.is_some()) {
            self.holding.insert(key);
        }
        let graph_change = matches!(
            &kind,
            EntityKind::Participant(_, Some(_))
                | EntityKind::Writer(..)
                | EntityKind::Reader(..)
                | EntityKind::Service(..)
        );
        let origin = Origin::new(body, little_endian);
        self.entities.insert(
            key,
            Entity {
                parent,
                kind,
                origin,
            },
        );
        self.by_client
            .entry((key.0, key.1))
            .or_default()
            .insert(key.2);
        if graph_change {
            if let Some(d) = self.domain_of(key) {
                self.graph.touch(d, Instant::now());
            }
        }
        Ok(())
    }

    fn make_topic(
        dp: &DomainParticipant,
        desc: &TopicDesc,
        keyed: bool,
    ) -> Result<Topic, rustdds::dds::CreateError> {
        dp.create_topic(
            desc.name.clone(),
            desc.type_name.clone(),
            &QosPolicies::qos_none(),
            if keyed {
                TopicKind::WithKey
            } else {
                TopicKind::NoKey
            },
        )
    }

    /// A type by name: from the client's TYPE objects, else the references file.
    fn type_named(&self, key: EntityKey, name: &str) -> Option<Arc<StructDef>> {
        // The client's TYPE object with the lowest id wins when several define the name.
        self.entities
            .iter()
            .filter(|(k, _)| k.0 == key.0 && k.1 == key.1)
            .filter_map(|(k, e)| match &e.kind {
                EntityKind::Type(set) => Some((k.2 .0, set.get(name)?)),
                _ => None,
            })
            .min_by_key(|(id, _)| *id)
            .map(|(_, t)| t)
            .or_else(|| self.config.references.types().get(name))
    }

    /// A topic's type and key, when its type is known.
    fn topic_type(
        &self,
        key: EntityKey,
        tdesc: &TopicDesc,
    ) -> (Option<Arc<StructDef>>, Option<Arc<KeyDescriptor>>) {
        let ty = self.type_named(key, &tdesc.type_name);
        let kd = ty.clone().and_then(KeyDescriptor::new).map(Arc::new);
        if tdesc.keyed && kd.is_none() {
            tracing::warn!(
                frontend = key.0,
                client = %key.1,
                topic = %tdesc.name,
                r#type = %tdesc.type_name,
                known = ty.is_some(),
                "WITH_KEY topic carried without a key: its type is unknown or has no key member \
                 (define it in <types>, by a TYPE object or in the references file)"
            );
        }
        (ty, kd)
    }

    /// The writer and reader of a requester or replier, on the DDS participants of `domain`.
    /// Both are reliable and volatile (as RPC over DDS); the writer publishes in the
    /// client's byte order.
    fn create_service(
        &mut self,
        desc: &crate::xml::ServiceDesc,
        domain: u16,
        requester: bool,
        little_endian: bool,
    ) -> Result<ServiceEndpoint, OpError> {
        let dds_err =
            |what: &str, e: &dyn std::fmt::Debug| (status::ERR_DDS_ERROR, format!("{what}: {e:?}"));
        let pub_dp = self
            .pool
            .get(domain, Role::Publish)
            .map_err(|e| (status::ERR_DDS_ERROR, e))?;
        let sub_dp = self
            .pool
            .get(domain, Role::Subscribe)
            .map_err(|e| (status::ERR_DDS_ERROR, e))?;
        let (out_topic, out_type, in_topic, in_type) = if requester {
            (
                &desc.request_topic,
                &desc.request_type,
                &desc.reply_topic,
                &desc.reply_type,
            )
        } else {
            (
                &desc.reply_topic,
                &desc.reply_type,
                &desc.request_topic,
                &desc.request_type,
            )
        };
        let qos_desc = crate::xml::QosDesc {
            reliability: Some(crate::xml::Reliability::Reliable),
            durability: Some(crate::xml::Durability::Volatile),
            ..Default::default()
        };
        let make = |dp: &DomainParticipant, name: &str, type_name: &str| {
            dp.create_topic(
                name.to_string(),
                type_name.to_string(),
                &QosPolicies::qos_none(),
                TopicKind::NoKey,
            )
            .map_err(|e| dds_err("create topic", &e))
        };
        let publisher = pub_dp
            .create_publisher(&QosPolicies::qos_none())
            .map_err(|e| dds_err("create publisher", &e))?;
        let subscriber = sub_dp
            .create_subscriber(&QosPolicies::qos_none())
            .map_err(|e| dds_err("create subscriber", &e))?;
        let wt = make(&pub_dp, out_topic, out_type)?;
        let rt = make(&sub_dp, in_topic, in_type)?;
        let wq = endpoint_qos(
            EndpointSide::Writer,
            &qos_desc,
            &crate::xml::QosDesc::default(),
        );
        let rq = endpoint_qos(
            EndpointSide::Reader,
            &qos_desc,
            &crate::xml::QosDesc::default(),
        );
        let writer = RawWriter::create(&publisher, &wt, wq, little_endian, None)
            .map_err(|e| dds_err("create data writer", &e))?;
        let mut reader = RawReader::create(&subscriber, &rt, rq, None)
            .map_err(|e| dds_err("create data reader", &e))?;
        let token = Token(self.next_token);
        self.next_token += 1;
        self.poll
            .registry()
            .register(&mut reader, token, Interest::READABLE)
            .map_err(|e| dds_err("register reader", &e))?;
        Ok(ServiceEndpoint {
            requester,
            writer,
            reader,
            token,
            pending: HashMap::new(),
            pending_order: std::collections::VecDeque::new(),
            _publisher: publisher,
            _subscriber: subscriber,
        })
    }

    /// The topic an endpoint names (inline, or a topic object of the same participant),
    /// made on the DDS participant `dp` the endpoint lives on.
    fn endpoint_topic(
        &self,
        key: EntityKey,
        parent: ObjectId,
        dp: &DomainParticipant,
        desc: &xml::EndpointDesc,
    ) -> Result<EndpointTopic, OpError> {
        let (pid, _) = self
            .participant_of(key, parent)
            .ok_or((status::ERR_UNKNOWN_REFERENCE, "no participant".into()))?;
        // A topic object created by the client with the same name carries its QoS.
        if let Some(id) = desc.topic_id {
            let d = match self.entities.get(&(key.0, key.1, id)) {
                Some(Entity {
                    kind: EntityKind::Topic(d),
                    ..
                }) => d.clone(),
                _ => {
                    return Err((
                        status::ERR_UNKNOWN_REFERENCE,
                        format!("topic {id:?} does not exist"),
                    ))
                }
            };
            let (ty, kd) = self.topic_type(key, &d);
            let t = Self::make_topic(dp, &d, kd.is_some())
                .map_err(|e| (status::ERR_DDS_ERROR, format!("create topic: {e:?}")))?;
            return Ok((t, d, ty, kd));
        }
        let wanted = desc
            .topic
            .as_ref()
            .map(|t| t.name.as_str())
            .or(desc.topic_ref.as_deref())
            .unwrap_or_default();
        let existing = self.entities.iter().find_map(|(k, e)| match &e.kind {
            EntityKind::Topic(d)
                if k.0 == key.0 && k.1 == key.1 && e.parent == Some(pid) && d.name == wanted =>
            {
                Some(d.clone())
            }
            _ => None,
        });
        let tdesc = match (&desc.topic, existing) {
            (Some(inline), Some(d)) if inline.type_name != d.type_name => {
                return Err((
                    status::ERR_MISMATCH,
                    format!("topic {wanted} exists with type {}", d.type_name),
                ))
            }
            (Some(inline), Some(found)) => found.refined_by(inline),
            (None, Some(found)) => found,
            (Some(inline), None) => inline.clone(),
            (None, None) => {
                return Err((
                    status::ERR_UNKNOWN_REFERENCE,
                    format!("topic {wanted} is unknown"),
                ))
            }
        };
        let (ty, kd) = self.topic_type(key, &tdesc);
        let t = Self::make_topic(dp, &tdesc, kd.is_some())
            .map_err(|e| (status::ERR_DDS_ERROR, format!("create topic: {e:?}")))?;
        Ok((t, tdesc, ty, kd))
    }

    /// Publishes the samples of one WRITE_DATA (one, or several in the sequence formats).
    fn write(&mut self, key: EntityKey, h: &IpcHeader, body: &[u8]) -> Result<(), OpError> {
        let little_endian = h.flags & FLAG_LITTLE_ENDIAN != 0;
        let dialect = if h.flags & FLAG_DIALECT_SPEC != 0 {
            Dialect::Spec
        } else {
            Dialect::Eprosima
        };
        // Without a type description the end of a sample is the end of the submessage, so
        // a sequence can be split only when it holds one sample; with it, the type says
        // where each sample ends.
        let ty = match self.entities.get(&key) {
            Some(Entity {
                kind: EntityKind::Writer(_, _, ty),
                ..
            }) => ty.clone().map(Ty::Struct),
            _ => None,
        };
        let sizer_ty = ty.clone();
        let sizer =
            ty.map(|t| move |b: &[u8], origin: usize| sample_len(&t, b, origin, little_endian));
        let sizer_ref = sizer
            .as_ref()
            .map(|f| f as &dyn Fn(&[u8], usize) -> Option<usize>);
        let samples = decode_samples(h.data_format, body, little_endian, dialect, sizer_ref)
            .map_err(|e| (status::ERR_INVALID_DATA, format!("WRITE_DATA: {e}")))?;
        let ends_instance = |s: &xrce_common::wire::sample::SampleRef<'_>| {
            s.info.is_some_and(|i| {
                i.state & (sample_state::INSTANCE_DISPOSED | sample_state::INSTANCE_UNREGISTERED)
                    != 0
            })
        };
        if let Some(Entity {
            kind: EntityKind::Service(svc),
            ..
        }) = self.entities.get_mut(&key)
        {
            if samples.iter().any(ends_instance) {
                return Err((
                    status::ERR_INCOMPATIBLE,
                    "a requester or replier cannot dispose or unregister".into(),
                ));
            }
            for s in samples {
                service_write(svc, h.request_id, little_endian, s.data)?;
            }
            return Ok(());
        }
        let several = samples.len() > 1;
        for s in samples {
            let dispose = ends_instance(&s);
            // A sample split out of a sequence aligns from the WRITE_DATA's payload; DDS
            // wants it aligned from its own start.
            let offset = (s.data.as_ptr() as usize).saturating_sub(body.as_ptr() as usize);
            let rebased = match (&sizer_ty, several && offset % 8 != 0) {
                (Some(t), true) => Some(
                    crate::types::rebase(t, s.data, offset, little_endian).map_err(|e| {
                        (status::ERR_INVALID_DATA, format!("WRITE_DATA sample: {e}"))
                    })?,
                ),
                _ => None,
            };
            let data = rebased.as_deref().unwrap_or(s.data);
            self.write_one(key, h.op_seq, little_endian, data, dispose)?;
            self.samples_written += 1;
        }
        Ok(())
    }

    fn write_one(
        &mut self,
        key: EntityKey,
        seq: u64,
        little_endian: bool,
        body: &[u8],
        dispose: bool,
    ) -> Result<(), OpError> {
        let Some(Entity {
            kind: EntityKind::Writer(w, rematch, _),
            ..
        }) = self.entities.get_mut(&key)
        else {
            return Err((
                status::ERR_UNKNOWN_REFERENCE,
                "write to an unknown data writer".into(),
            ));
        };
        if little_endian != w.raw.little_endian() {
            // Without the type the bytes cannot be swapped.
            return Err((
                status::ERR_INVALID_DATA,
                format!(
                    "a {}-endian sample for a data writer created {}-endian",
                    if little_endian { "little" } else { "big" },
                    if w.raw.little_endian() {
                        "little"
                    } else {
                        "big"
                    },
                ),
            ));
        }
        let sample = RawSample {
            encoding: if little_endian {
                rustdds::RepresentationIdentifier::CDR_LE
            } else {
                rustdds::RepresentationIdentifier::CDR_BE
            },
            body: rustdds::bytes::Bytes::copy_from_slice(body),
        };
        if dispose && w.raw.key().is_none() {
            // DDS has no instances on a topic without a key.
            return Err((
                status::ERR_INCOMPATIBLE,
                "dispose or unregister on a topic without a key (or whose type is unknown)".into(),
            ));
        }
        if let Some(k) = w.raw.key() {
            // Checked now, so a held sample cannot fail later, unreported.
            let whole = k.of_sample(body, little_endian, false);
            if whole.is_err() && !(dispose && k.of_key_payload(body, little_endian, false).is_ok())
            {
                return Err((
                    status::ERR_INVALID_DATA,
                    format!("a sample that is not a {}", k.ty().name),
                ));
            }
        }
        if rematch.until.is_some() {
            if rematch.held.len() < REMATCH_HELD_MAX
                && rematch.held_bytes + sample.body.len() <= REMATCH_HELD_MAX_BYTES
            {
                rematch.held_bytes += sample.body.len();
                rematch.held.push_back((seq, sample, dispose));
                return Ok(());
            }
            // Bounded: a writer that would hold more stops waiting for its readers.
            tracing::warn!(
                frontend = key.0,
                client = %key.1,
                held = rematch.held.len(),
                "writer stops waiting for readers: too many samples held"
            );
            rematch.until = None;
            rematch.draining = false;
            let now = Instant::now();
            rematch.held_bytes = 0;
            for (s_seq, s, d) in rematch.held.drain(..) {
                let done = if d { w.raw.dispose(&s) } else { w.raw.write(s) };
                if done.is_ok() && w.outstanding.record(key.0, s_seq, now) {
                    self.acks.watch(w);
                }
            }
        }
        let done = if dispose {
            w.raw
                .dispose(&sample)
                .map_err(|e| (status::ERR_DDS_ERROR, format!("DDS dispose: {e}")))
        } else {
            w.raw
                .write(sample)
                .map_err(|e| (status::ERR_DDS_ERROR, format!("DDS write: {e}")))
        };
        if done.is_ok() && w.outstanding.record(key.0, seq, Instant::now()) {
            self.acks.watch(w);
        }
        done
    }

    /// A live shared DDS writer made with this QoS and type, if any (dead entries pruned).
    fn shared_writer(
        &mut self,
        key: &SharedWriterKey,
        qos: &QosPolicies,
        ty: Option<&Arc<StructDef>>,
    ) -> Option<Rc<DdsWriter>> {
        let entries = self.shared_writers.get_mut(key)?;
        entries.retain(|e| e.writer.strong_count() > 0);
        let found = entries
            .iter()
            .filter(|e| e.writer.strong_count() < SHARE_GROUP)
            .find(|e| &e.qos == qos && e.ty.as_deref() == ty.map(|t| &**t))
            .and_then(|e| e.writer.upgrade());
        if entries.is_empty() {
            self.shared_writers.remove(key);
        }
        found
    }

    /// Releases the samples of replayed writers that matched again (or waited long enough).
    fn release_rematched(&mut self) {
        let now = Instant::now();
        let mut failures = 0u64;
        let mut done = Vec::new();
        for key in &self.holding {
            let Some(Entity {
                kind: EntityKind::Writer(w, rematch, _),
                ..
            }) = self.entities.get_mut(key)
            else {
                done.push(*key);
                continue;
            };
            let Some(until) = rematch.until else {
                done.push(*key);
                continue;
            };
            if rematch.matched_at.is_none() {
                // As many readers as before the restart (at least one): a writer that
                // released when the first of several matched lost samples to the others.
                let first = w.poll_matched(now);
                if w.matched.get() >= usize::from(rematch.expected) {
                    rematch.matched_at = if rematch.expected <= 1 {
                        first
                    } else {
                        Some(now)
                    };
                }
            }
            let ready = rematch
                .matched_at
                .is_some_and(|t| now >= t + REMATCH_MARGIN)
                || now >= until;
            if ready && !rematch.draining {
                // Debug: with many clients every new writer passes here once.
                tracing::debug!(
                    held = rematch.held.len(),
                    matched = rematch.matched_at.is_some(),
                    "holding writer resumes"
                );
                rematch.draining = true;
            }
            let paced = rematch.last_batch.is_some_and(|t| {
                now.saturating_duration_since(t) < RELEASE_ACK_WAIT && !w.raw.all_acknowledged()
            });
            if rematch.draining && !paced {
                rematch.last_batch = Some(now);
                for _ in 0..RELEASE_BATCH {
                    let Some((seq, sample, dispose)) = rematch.held.pop_front() else {
                        break;
                    };
                    rematch.held_bytes = rematch.held_bytes.saturating_sub(sample.body.len());
                    let done = if dispose {
                        w.raw.dispose(&sample)
                    } else {
                        w.raw.write(sample)
                    };
                    if let Err(e) = &done {
                        tracing::warn!(frontend = key.0, client = %key.1, error = %e, dispose, "held sample not published");
                    }
                    if done.is_err() {
                        failures += 1;
                    } else if w.outstanding.record(key.0, seq, now) {
                        self.acks.watch(w);
                    }
                }
                if rematch.held.is_empty() {
                    rematch.until = None;
                    rematch.draining = false;
                    done.push(*key);
                }
            }
        }
        for k in done {
            self.holding.remove(&k);
        }
        for _ in 0..failures {
            self.count("dds_write_failed");
        }
    }

    /// Tells front-ends how many readers each of their data writers matches, when that
    /// changed (every [`MATCH_REPORT_PERIOD`]).
    fn report_matches(&mut self) {
        let now = Instant::now();
        if now < self.next_match_report {
            return;
        }
        self.next_match_report = now + MATCH_REPORT_PERIOD;
        let mut changed = Vec::new();
        for (key, e) in self.entities.iter_mut() {
            if let EntityKind::Writer(w, rematch, _) = &mut e.kind {
                w.poll_matched(now);
                let n = u8::try_from(w.matched.get()).unwrap_or(u8::MAX);
                if rematch.reported != Some(n) {
                    rematch.reported = Some(n);
                    changed.push((*key, n));
                }
            }
        }
        for ((fe, client, object), n) in changed {
            let mut h = IpcHeader::new(MessageKind::WriterMatched);
            h.frontend_id = fe;
            h.client_key = client;
            h.object_id = object;
            h.readers = n;
            self.reply(h, &[]);
        }
    }

    /// The oldest operation held by a replayed writer, per front-end.
    fn oldest_held(&self) -> HashMap<u32, u64> {
        let mut m: HashMap<u32, u64> = HashMap::new();
        for (k, e) in self
            .holding
            .iter()
            .filter_map(|k| Some((k, self.entities.get(k)?)))
        {
            if let EntityKind::Writer(_, r, _) = &e.kind {
                if let Some((seq, _, _)) = r.held.front() {
                    let v = m.entry(k.0).or_insert(*seq);
                    *v = (*v).min(*seq);
                }
            }
        }
        m
    }

    fn start_read(&mut self, key: EntityKey, h: &IpcHeader, body: &[u8]) -> Result<(), OpError> {
        let reader_type = match self.entities.get(&key) {
            Some(Entity {
                kind: EntityKind::Reader(_, _, info),
                ..
            }) => Some(info.ty.clone()),
            Some(Entity {
                kind: EntityKind::Service(..),
                ..
            }) => None,
            _ => {
                return Err((
                    status::ERR_UNKNOWN_REFERENCE,
                    "read from an unknown data reader, requester or replier".into(),
                ))
            }
        };
        let spec = ReadSpecification::decode(&mut CdrReader::new(body, true))
            .map_err(|e| (status::ERR_INVALID_DATA, format!("read specification: {e}")))?;
        // The front-end puts each sample in the requested format.
        if !xrce_common::wire::sample::is_defined_format(spec.data_format) {
            return Err((
                status::ERR_INVALID_DATA,
                format!("undefined data format {:#04x}", spec.data_format),
            ));
        }
        let filter = match (spec.content_filter_expression.as_deref(), reader_type) {
            (None, _) => None,
            (Some(f), _) if f.trim().is_empty() => None,
            (Some(f), Some(ty)) => Some(compile_filter(f, ty.as_ref(), "the reader's topic")?),
            (Some(_), None) => {
                return Err((
                    status::ERR_INCOMPATIBLE,
                    "content filters apply to data readers, not requesters or repliers".into(),
                ))
            }
        };
        // A new read starts unpaused (the front-end forgets its pause too).
        let paused = false;
        let read = match spec.delivery_control {
            Some(d) if d.max_samples == 0 => {
                self.reads.remove(&key);
                return Ok(());
            }
            Some(d) => ActiveRead {
                request_id: h.request_id,
                remaining: (d.max_samples != u16::MAX).then_some(d.max_samples as u32),
                deadline: (d.max_elapsed_time != 0)
                    .then(|| Instant::now() + Duration::from_secs(d.max_elapsed_time as u64)),
                one_shot: false,
                paused,
                pacing: Pacing::new(&d),
                filter,
                data_format: spec.data_format,
            },
            None => ActiveRead {
                request_id: h.request_id,
                remaining: None,
                deadline: None,
                one_shot: true,
                paused,
                pacing: Pacing::default(),
                filter,
                data_format: spec.data_format,
            },
        };
        self.reads.insert(key, read);
        if h.flags & FLAG_REPLAY != 0 {
            self.offer_recent(key, h.request_id);
        } else if let Some(r) = self.recent.get_mut(&key.0) {
            // The client has no record of what an earlier read on this reader delivered.
            r.forget(&key);
        }
        Ok(())
    }

    /// Sends a replayed read the samples last handed to its front-end for it: a successor
    /// of a front-end that died gets those its predecessor may not have delivered (it drops
    /// the others by their identity).
    ///
    /// The read's limits count them: a one-shot read gets the newest and ends (the front-end
    /// drops it if its predecessor delivered it, and the read is over either way), a read of
    /// at most so many samples counts them all as delivered (it may end short by those the
    /// front-end drops, never beyond its limit).
    fn offer_recent(&mut self, key: EntityKey, request_id: xrce_common::wire::RequestId) {
        let mut samples = self
            .recent
            .get(&key.0)
            .map(|r| r.of(&key, request_id))
            .unwrap_or_default();
        if samples.is_empty() {
            return;
        }
        let ended = match self.reads.get_mut(&key) {
            Some(r) if r.one_shot => {
                samples.drain(..samples.len() - 1);
                true
            }
            Some(r) => match r.remaining.as_mut() {
                Some(rem) => {
                    let n = (*rem as usize).min(samples.len());
                    samples.drain(..samples.len() - n);
                    *rem -= n as u32;
                    *rem == 0
                }
                None => false,
            },
            None => false,
        };
        tracing::info!(client = %key.1, reader = ?key.2, samples = samples.len(), "recent samples offered again to a replayed read");
        for (flags, body) in &samples {
            let mut h = IpcHeader::new(MessageKind::Sample);
            h.frontend_id = key.0;
            h.client_key = key.1;
            h.object_id = key.2;
            h.request_id = request_id;
            h.flags = *flags;
            self.reply(h, body);
        }
        if ended {
            self.end_read(key);
        }
    }

    /// Takes samples of a reader with an active read and sends them to its front-end.
    fn pump(&mut self, key: EntityKey) {
        let Some(read) = self.reads.get_mut(&key).filter(|r| !r.paused) else {
            return;
        };
        if let Some(p) = self.ports.get_mut(&key.0).filter(|p| !p.backlog.is_empty()) {
            // The front-end is congested: leave the samples in the DDS reader for now.
            p.deferred.insert(key);
            return;
        }
        let request_id = read.request_id;
        let (reader, mut service, reader_filter) = match self.entities.get_mut(&key) {
            Some(Entity {
                kind: EntityKind::Reader(reader, _, info),
                ..
            }) => (&mut **reader, None, info.filter.as_ref()),
            Some(Entity {
                kind: EntityKind::Service(s),
                ..
            }) => {
                let s = &mut **s;
                (
                    &mut s.reader,
                    Some((s.requester, &s.writer, &mut s.pending)),
                    None,
                )
            }
            _ => return,
        };
        let mut out = Vec::new();
        let mut more = false;
        let mut limit = read.remaining.unwrap_or(u32::MAX).min(PUMP_BATCH as u32);
        let one_shot = read.one_shot;
        let mut errors = 0u64;
        let mut filtered = 0u64;
        let now = Instant::now();
        while limit > 0 {
            if read.pacing.limited() && !read.pacing.may_send(now) {
                // Paced: the rest waits in the DDS reader until `next_at`.
                break;
            }
            match reader.take_next() {
                Ok(Some(taken)) => {
                    let info = taken.info;
                    let mut s = taken.sample;
                    if let Some((requester, writer, pending)) = service.as_mut() {
                        match service_sample(*requester, writer, pending, &info, key.2, s) {
                            Some(wrapped) => s = wrapped,
                            // A reply to another requester.
                            None => continue,
                        }
                    }
                    let ends = taken.disposed || taken.unregistered;
                    if ends
                        && matches!(
                            read.data_format,
                            xrce_common::wire::data_format::DATA
                                | xrce_common::wire::data_format::DATA_SEQ
                        )
                    {
                        // Taken, not delivered, not counted against max_samples.
                        continue;
                    }
                    // A filter sees samples; instance ends (key fields only) pass.
                    let passes = |f: Option<&Filter>| {
                        f.is_none_or(|f| {
                            f.matches(&s.body, s.little_endian(), crate::raw::is_xcdr2(s.encoding))
                        })
                    };
                    let selected = ends || (passes(reader_filter) && passes(read.filter.as_ref()));
                    if !selected {
                        // Taken and dropped; it does not count against max_samples, but it
                        // counts against the batch so a flood cannot starve the loop.
                        filtered += 1;
                        if filtered > 4 * PUMP_BATCH as u64 {
                            more = true;
                            break;
                        }
                        continue;
                    }
                    let mut flags = 0;
                    if taken.disposed {
                        flags |= ipc::FLAG_DISPOSED;
                    }
                    if taken.unregistered {
                        flags |= ipc::FLAG_UNREGISTERED;
                    }
                    read.pacing.sent(now, s.body.len());
                    let id = info.sample_identity();
                    let identity = ipc::SampleIdentity {
                        writer: id.writer_guid.to_bytes(),
                        sequence_number: i64::from(id.sequence_number),
                    };
                    out.push((s, flags, identity));
                    limit -= 1;
                    if one_shot {
                        break;
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    // Counted against the batch, so a flood of them cannot starve the loop.
                    errors += 1;
                    limit -= 1;
                    tracing::debug!(error = ?e, "undecodable DDS sample skipped");
                }
            }
            if limit == 0 {
                // The batch is used up (by samples or by undecodable ones): come back.
                more = true;
            }
        }
        for _ in 0..errors {
            self.count("dds_sample_undecodable");
        }
        if filtered > 0 {
            // Not a fault: counted so a filter's effect can be seen.
            *self.dropped.entry("content_filtered").or_default() += filtered;
        }
        let sent = out.len() as u32;
        self.samples_taken += u64::from(sent);
        for (s, flags, identity) in out {
            let mut h = IpcHeader::new(MessageKind::Sample);
            h.frontend_id = key.0;
            h.client_key = key.1;
            h.object_id = key.2;
            h.request_id = request_id;
            h.flags = flags
                | if s.little_endian() {
                    FLAG_LITTLE_ENDIAN
                } else {
                    0
                };
            let id = identity.encode();
            let flags = h.flags;
            let len = ipc::SAMPLE_IDENTITY_LEN + s.body.len();
            self.reply_with(h, len, |b| {
                b[..ipc::SAMPLE_IDENTITY_LEN].copy_from_slice(&id);
                b[ipc::SAMPLE_IDENTITY_LEN..].copy_from_slice(&s.body);
            });
            // Kept for a successor only if it went (or waits) to the front-end, and can be
            // told from what the front-end delivered already.
            if len <= ipc::MAX_BODY && identity.is_known() {
                self.recent.entry(key.0).or_default().record(
                    key,
                    request_id,
                    flags,
                    [&id, &s.body],
                );
            }
        }
        let ended = match self.reads.get_mut(&key) {
            Some(r) => {
                if let Some(rem) = r.remaining.as_mut() {
                    *rem = rem.saturating_sub(sent);
                }
                r.remaining == Some(0) || (r.one_shot && sent > 0)
            }
            None => false,
        };
        if ended {
            self.end_read(key);
        } else if more {
            self.to_pump.insert(key);
        }
    }

    fn end_read(&mut self, key: EntityKey) {
        if let Some(r) = self.reads.remove(&key) {
            let mut h = IpcHeader::new(MessageKind::ReadEnded);
            h.frontend_id = key.0;
            h.client_key = key.1;
            h.object_id = key.2;
            h.request_id = r.request_id;
            self.reply(h, &[]);
        }
    }

    fn expire_reads(&mut self) {
        let now = Instant::now();
        // Paced reads whose wait is over take their next samples.
        for (k, r) in self.reads.iter_mut() {
            if r.pacing.next_at.is_some_and(|t| t <= now) {
                r.pacing.next_at = None;
                self.to_pump.insert(*k);
            }
        }
        let expired: Vec<EntityKey> = self
            .reads
            .iter()
            .filter(|(_, r)| r.deadline.is_some_and(|d| d <= now))
            .map(|(k, _)| *k)
            .collect();
        for k in expired {
            self.end_read(k);
        }
    }

    /// Removes the entities of the clients `pred` selects (by front-end and client key).
    fn remove_where(&mut self, pred: impl Fn(&(u32, ClientKey)) -> bool) {
        let keys: Vec<EntityKey> = self
            .by_client
            .iter()
            .filter(|(c, _)| pred(c))
            .flat_map(|(c, ids)| ids.iter().map(|id| (c.0, c.1, *id)))
            .collect();
        for k in keys {
            // Already gone with its parent's subtree, or still there.
            if self.entities.contains_key(&k) {
                self.remove_subtree(k);
            }
        }
    }

    /// Removes an entity and its descendants, endpoints before their parents.
    fn remove_subtree(&mut self, key: EntityKey) {
        let children: Vec<EntityKey> = self
            .by_client
            .get(&(key.0, key.1))
            .into_iter()
            .flatten()
            .map(|id| (key.0, key.1, *id))
            .filter(|k| {
                self.entities
                    .get(k)
                    .is_some_and(|e| e.parent == Some(key.2))
            })
            .collect();
        for c in children {
            self.remove_subtree(c);
        }
        if let Some(d) = self.domain_of(key) {
            self.graph.touch(d, Instant::now());
        }
        self.holding.remove(&key);
        if let Some(r) = self.recent.get_mut(&key.0) {
            r.forget(&key);
        }
        if let Some(ids) = self.by_client.get_mut(&(key.0, key.1)) {
            ids.remove(&key.2);
            if ids.is_empty() {
                self.by_client.remove(&(key.0, key.1));
            }
        }
        if let Some(e) = self.entities.remove(&key) {
            match e.kind {
                EntityKind::Writer(w, _, _) => {
                    // The last XRCE writer of a shared DDS writer: forget the entry.
                    if let Some(k) = w.shared.clone() {
                        drop(w);
                        if let Some(entries) = self.shared_writers.get_mut(&k) {
                            entries.retain(|e| e.writer.strong_count() > 0);
                            if entries.is_empty() {
                                self.shared_writers.remove(&k);
                            }
                        }
                    }
                }
                EntityKind::Reader(mut r, token, _) => {
                    let _ = self.poll.registry().deregister(&mut *r);
                    self.readers.remove(&token);
                }
                EntityKind::Service(mut s) => {
                    let _ = self.poll.registry().deregister(&mut s.reader);
                    self.readers.remove(&s.token);
                }
                _ => {}
            }
            self.reads.remove(&key);
            self.to_pump.remove(&key);
        }
    }
}

/// What a requester or replier client gets for a DDS sample: a replier the request's
/// SampleIdentity in front of it (24 bytes, the sample's byte order); a requester the
/// BaseObjectRequest of its own request in front of the reply, and only replies to its own
/// requests (`None` for the others), as eProsima's agent does.
fn service_sample(
    requester: bool,
    writer: &RawWriter,
    pending: &mut HashMap<i64, xrce_common::wire::RequestId>,
    info: &rustdds::SampleInfo,
    object: ObjectId,
    s: RawSample,
) -> Option<RawSample> {
    let le = s.little_endian();
    let mut body = Vec::with_capacity(24 + s.body.len());
    if requester {
        let related = info.related_sample_identity()?;
        if related.writer_guid != writer.guid() {
            return None;
        }
        let request_id = pending.remove(&i64::from(related.sequence_number))?;
        body.extend_from_slice(&request_id.0);
        body.extend_from_slice(&object.0);
    } else {
        body.extend_from_slice(&crate::raw::encode_sample_identity(
            &info.sample_identity(),
            le,
        ));
    }
    body.extend_from_slice(&s.body);
    Some(RawSample {
        encoding: s.encoding,
        body: rustdds::bytes::Bytes::from(body),
    })
}

/// A WRITE_DATA to a requester (a request: remembered with its XRCE request id, so the reply
/// finds its way back) or to a replier (a reply: the request's SampleIdentity first).
fn service_write(
    svc: &mut ServiceEndpoint,
    request_id: xrce_common::wire::RequestId,
    little_endian: bool,
    data: &[u8],
) -> Result<(), OpError> {
    if little_endian != svc.writer.little_endian() {
        return Err((
            status::ERR_INVALID_DATA,
            "a sample in another byte order than the client's CREATE".into(),
        ));
    }
    let encoding = if little_endian {
        rustdds::RepresentationIdentifier::CDR_LE
    } else {
        rustdds::RepresentationIdentifier::CDR_BE
    };
    let dds = |e: String| (status::ERR_DDS_ERROR, format!("DDS write: {e}"));
    if svc.requester {
        let sample = RawSample {
            encoding,
            body: rustdds::bytes::Bytes::copy_from_slice(data),
        };
        let id = svc.writer.write_identified(sample, None).map_err(dds)?;
        let seq = i64::from(id.sequence_number);
        svc.pending.insert(seq, request_id);
        svc.pending_order.push_back(seq);
        while svc.pending_order.len() > PENDING_REQUESTS_MAX {
            if let Some(old) = svc.pending_order.pop_front() {
                svc.pending.remove(&old);
            }
        }
        Ok(())
    } else {
        let related = crate::raw::decode_sample_identity(data, little_endian).ok_or((
            status::ERR_INVALID_DATA,
            "a reply without the request's SampleIdentity".to_string(),
        ))?;
        let sample = RawSample {
            encoding,
            body: rustdds::bytes::Bytes::copy_from_slice(data.get(24..).unwrap_or_default()),
        };
        svc.writer
            .write_identified(sample, Some(related))
            .map(drop)
            .map_err(dds)
    }
}

/// Every endpoint's topic: the RustDDS topic, its description, its type and its key.
type EndpointTopic = (
    Topic,
    TopicDesc,
    Option<Arc<StructDef>>,
    Option<Arc<KeyDescriptor>>,
);

/// Compiles a content filter against a reader's type (which it needs).
fn compile_filter(
    expression: &str,
    ty: Option<&Arc<StructDef>>,
    type_name: &str,
) -> Result<Filter, OpError> {
    let ty = ty.ok_or_else(|| {
        (
            status::ERR_INCOMPATIBLE,
            format!(
                "a content filter needs the type of {type_name}: define it in <types>, by a \
                 TYPE object or in the references file"
            ),
        )
    })?;
    Filter::compile(expression, ty.clone()).map_err(|e| {
        (
            status::ERR_INVALID_DATA,
            format!("content filter {expression:?}: {e}"),
        )
    })
}
