//! The worker's event loop: executes the front-ends' operations on DDS entities and streams
//! samples of active reads back.
//!
//! Entities are keyed by (front-end id, client key, object id). The worker keeps nothing a
//! front-end cannot rebuild: after a restart it announces a new generation and the front-ends
//! replay their clients' object graphs.
//!
//! The worker is sans-IO, as the front-end's relay is: what it sends goes through a
//! [`WorkerLink`] (shared memory in the process, memory in tests), and the caller gives it
//! the time with every event ([`Worker::handle_request`], [`Worker::pass`]) and asks when it
//! wants the next pass ([`Worker::poll_timeout`]). The process around it
//! ([`crate::process`]) polls, drains the requests, reports status and handles signals.
//!
//! This module is the worker's state and its pass; each job is a module of its own: the
//! dispatch of requests (`requests`), the reply ports (`ports`), the link (`link`), the DDS
//! side of each entity (`entities`; the tree itself is [`crate::tree`]), creation
//! (`create`), writes and held samples (`writes`), reads (`reads`), requesters and
//! repliers (`services`) and the ROS 2 graph (`graph`).

use std::cell::Cell;
use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};
use xrce_common::fault::{self, Fault};

use std::rc::Rc;
use std::sync::Arc;

use xrce_common::wire::cdr::CdrReader;
use xrce_common::wire::sample::{decode_samples, sample_state};
use xrce_common::wire::Dialect;
use xrce_common::wire::{
    object_kind, status, stream_id, ClientKey, ObjectId, ObjectVariant, ReadSpecification,
    ResultStatus, VariantExtra,
};
use xrce_ipc::status::{ProcessReport, WorkerStatus};
use xrce_ipc::{self as ipc, Encode, Reply, ReplyMessage, Request, RequestMessage, Route};

use crate::acks::{AckTracker, Acknowledging, Outstanding, Written};
use crate::adoption::{Adoption, Origin};
use crate::backend::{
    self, effective_domain, BackendError, DdsBackend, DdsConfig, DdsReader, EndpointQos,
    EndpointSide, ReaderToken, Sample, TopicSpec,
};
use crate::bounds::{Holdings, OverBound, WorkerBounds};
use crate::domains::{DomainPolicy, DomainRefusal, Domains};
use crate::episodes::Episodes;
use crate::filter::{Filter, Steps, Verdict};
use crate::recent::RecentSamples;
use crate::representation::{
    check_plain, describe_endpoint, describe_service, describe_topic, participant_name,
};
use crate::ros_graph::{DomainNodes, RosGraph};
use crate::tree::EntityTree;
use crate::turns::Turns;
use crate::types::{sample_len, KeyDescriptor, StructDef, Ty, TypeSet};
use crate::xml::{self, TopicDesc};

mod create;
mod entities;
mod executed;
mod graph;
mod in_process_link;
mod link;
mod ports;
mod reads;
mod release_gate;
mod replay_guard;
mod requests;
mod services;
mod take_log;
#[cfg(test)]
mod tests;
mod writes;

use create::*;
use entities::*;
use executed::{ExecutedWrites, Recorded};
pub use in_process_link::InProcessLink;
pub use link::{LinkError, MemoryWorkerLink, ShmWorkerLink, WorkerLink};
use ports::*;
use reads::*;
pub use replay_guard::{CrashedReplays, ReplayMark};
use replay_guard::{ReplayGuard, Screened};
use services::*;
use writes::*;

/// Worker settings.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Agent instance name (prefix of every shared-memory resource).
    pub instance: String,
    /// The DDS implementation.
    pub backend: backend::BackendKind,
    /// Where DDS may talk.
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
    /// Which DDS domains clients may use, and how many at once ([`crate::domains`]).
    pub domains: DomainPolicy,
    /// What clients may make the worker hold: entities, and the samples of their caches
    /// ([`crate::bounds`]).
    pub bounds: WorkerBounds,
    /// The DDS domain of participants created in "the agent's default" domain (id 255).
    pub default_domain: u16,
}

/// How often the worker looks for front-ends whose process is gone.
const CENSUS_PERIOD: Duration = Duration::from_secs(1);
/// How often every writer's matched count is looked at and, when it changed, reported to its
/// front-end (which replays it to a restarted worker).
const MATCH_REPORT_PERIOD: Duration = Duration::from_secs(1);

type EntityKey = (u32, ClientKey, ObjectId);

use crate::representation::OpError;

/// A topic by domain and name, as a key: a hash of both under this worker's own random keys
/// (its readers and writers of one topic share it). Two topics whose keys collide would only
/// wait for each other's readers (acknowledgements, the release gate and the take log all
/// err on the late side), and the random keys give a client no way to aim at that.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) struct TopicKey(u64);

impl TopicKey {
    /// The key of `name` in `domain` under `keys`.
    fn of(keys: &std::hash::RandomState, domain: u16, name: &str) -> Self {
        use std::hash::BuildHasher;
        TopicKey(keys.hash_one((domain, name)))
    }
}

/// The DDS worker: executes the front-ends' operations on DDS entities, sends what they
/// are owed through its link `L`.
pub struct Worker<L: WorkerLink> {
    config: WorkerConfig,
    /// The random keys of [`TopicKey`]s.
    topic_keys: std::hash::RandomState,
    /// Where replies, wake-ups, announcements and replay marks go.
    link: L,
    /// The time of the event being handled, as the caller gave it (the worker reads no
    /// clock).
    now: Instant,
    generation: u32,
    /// What the worker knows of each front-end: its reply port, its hello, its entities
    /// while it is gone, its restarted successor.
    frontends: Frontends,
    /// The DDS implementation.
    dds: Box<dyn DdsBackend>,
    /// Where requesters and repliers live when `dds` cannot serve them (made on the first
    /// one): a backend that can, beside it in the same domains.
    services_dds: Option<Box<dyn DdsBackend>>,
    /// Every entity, with its parent and an index by client.
    entities: EntityTree<Entity>,
    /// The DDS readers: their wake-up tokens, active reads and turns.
    readers: Readers,
    /// The domains in use and the policy admitting new ones.
    domains: Domains,
    /// Refusals logged once per episode.
    episodes: Episodes,
    /// The samples each client's endpoints may keep, reserved against the bounds.
    holdings: Holdings<u32, ClientKey>,
    /// Replays under way, and the clients whose replay crashed the last worker.
    replay_guard: ReplayGuard,
    /// The DDS writers: those holding samples, acknowledgements, shared writers.
    writers: Writers,
    graph: RosGraph,
    /// When to look for gone front-ends next.
    next_census: Instant,
    /// When the writers' matched counts are next looked at (reported to the front-ends).
    next_match_report: Instant,
    /// Counters by reason of rejected or failed work.
    pub dropped: HashMap<&'static str, u64>,
    /// Samples accepted for DDS writers (written, or held until readers match).
    samples_written: u64,
    /// Samples taken from DDS readers and sent to front-ends.
    samples_taken: u64,
}

/// The DDS readers the worker made for XRCE readers, and whose turn it is to be read.
struct Readers {
    /// The entity behind each reader's wake-up token.
    by_token: HashMap<ReaderToken, EntityKey>,
    /// The token the next reader gets.
    next_token: ReaderToken,
    /// Tokens of readers the backend said may have data (kept to reuse its memory).
    ready: Vec<ReaderToken>,
    /// The reads clients asked for, by reader.
    reads: HashMap<EntityKey, ActiveRead>,
    /// Readers to pump this pass, first come first served.
    to_pump: Turns<EntityKey>,
    /// Readers that had more than one batch: pumped again next pass, behind the readers
    /// that became ready meanwhile (a flood takes one batch per turn, not every turn).
    pump_again: Turns<EntityKey>,
    /// Readers with content filters that got no turn because the pass's filter budget
    /// ([`crate::filter::PASS_BUDGET`]) was spent: pumped first next pass.
    over_budget: Turns<EntityKey>,
    /// What is left of this pass's filter budget.
    filter_pass_left: u64,
    /// The worker's write stamp when readers were last asked which have data.
    scan_stamp: u64,
    /// Where each reader that takes in write order stands in its topic's take log, between
    /// reads too ([`take_log`]).
    positions: HashMap<EntityKey, take_log::LogPosition>,
}

impl Readers {
    fn new() -> Self {
        Readers {
            by_token: HashMap::new(),
            next_token: 1,
            ready: Vec::new(),
            reads: HashMap::new(),
            to_pump: Turns::new(),
            pump_again: Turns::new(),
            over_budget: Turns::new(),
            filter_pass_left: crate::filter::PASS_BUDGET,
            scan_stamp: 0,
            positions: HashMap::new(),
        }
    }

    /// For each topic some active read of a data reader is on: the write stamp up to which
    /// all those readers were drained ([`crate::acks`]). A reader that was emptied and not
    /// named ready since holds nothing written before the last readiness scan (the worker's
    /// writes reach its own readers inside the write call, and name them ready then: true
    /// of Cyclone DDS and of the RustDDS backend's in-process delivery, not of Zenoh's).
    ///
    /// Readers without a read do not count: their samples wait in DDS for a read that may
    /// never come, and nothing could keep them across a worker restart but holding the
    /// writers' acknowledgements for ever. Nor do paced reads (DataDeliveryControl: their
    /// client chose to take less than may come), nor the readers of front-ends whose process
    /// is gone (`orphaned`): nothing they take reaches a client before a successor replays
    /// their reads.
    fn drained_through(
        &self,
        orphaned: &HashMap<u32, Instant>,
    ) -> HashMap<TopicKey, release_gate::Drained> {
        let mut drained: HashMap<TopicKey, release_gate::Drained> = HashMap::new();
        for (key, r) in &self.reads {
            if orphaned.contains_key(&key.0) || r.pacing.limited() {
                continue;
            }
            if let Some(topic) = &r.topic {
                let through = if r.holds {
                    r.drained_through
                } else {
                    r.drained_through.max(self.scan_stamp)
                };
                let d = drained.entry(*topic).or_insert(release_gate::Drained {
                    through,
                    depth: r.depth,
                    taken: 0,
                });
                d.through = d.through.min(through);
                d.depth = d.depth.min(r.depth);
                d.taken = d.taken.wrapping_add(r.taken);
            }
        }
        drained
    }

    /// The oldest position a read of `topic` has in its take log ([`take_log`]).
    fn oldest_position(&self, topic: &TopicKey, epoch: u64) -> Option<u64> {
        self.reads
            .values()
            .filter(|r| r.topic.as_ref() == Some(topic))
            .filter_map(|r| r.position)
            .filter(|p| p.epoch == epoch)
            .map(|p| p.at)
            .min()
    }

    /// Forgets `key`'s reads and turns, and the wake-up token of its reader (dropped by the
    /// caller: the backend's reader is deleted and wakes nobody any more).
    fn forget(&mut self, key: EntityKey, token: Option<ReaderToken>) {
        if let Some(token) = token {
            self.by_token.remove(&token);
        }
        self.reads.remove(&key);
        self.positions.remove(&key);
        self.to_pump.remove(&key);
        self.pump_again.remove(&key);
        self.over_budget.remove(&key);
    }

    /// A token for a new reader (entered in `by_token` once the reader exists).
    fn new_token(&mut self) -> ReaderToken {
        let token = self.next_token;
        self.next_token += 1;
        token
    }
}

/// The DDS writers the worker made for XRCE writers, and what it watches of them.
struct Writers {
    /// Writers holding their samples until matched (kept apart so that the loop never scans
    /// every entity: with thousands of clients that scan dominated the worker's CPU).
    holding: HashSet<EntityKey>,
    /// Where the next release pass starts among the holding writers (it turns, so that no
    /// writer waits behind the others' whole backlogs).
    release_turn: usize,
    /// When held samples were last released (the pass budget grows with the time since).
    last_release: Option<Instant>,
    /// DDS writers with writes their readers may not have acknowledged.
    acks: AckTracker<DdsWriter>,
    /// DDS writers shared by XRCE writers (`share_writers`), with the QoS and type they
    /// were made with; dead entries are pruned on lookup.
    shared: HashMap<SharedWriterKey, Vec<SharedWriterEntry>>,
    /// DDS writers of XRCE writers deleted or replaced while their readers had not
    /// acknowledged every write, and since when: kept (and watched) until they have, at most
    /// [`crate::acks::ACK_GIVE_UP`], so that what the client was told is written reaches
    /// the readers (a DDS writer deleted at once takes its unacknowledged samples with it).
    retiring: std::collections::VecDeque<(Rc<DdsWriter>, Instant)>,
    /// Retiring writers let go before their readers acknowledged, for want of room.
    retired_early: u64,
    /// Writes recorded for acknowledgement so far, over every writer: the stamp of the
    /// newest, which the worker's own readers are drained past ([`crate::acks`]).
    stamp: u64,
    /// How much draining writers may release into each topic ([`release_gate`]).
    gates: release_gate::ReleaseGates,
    /// Which of these writes reads in write order took ([`take_log`]).
    take_logs: take_log::TakeLogs,
}

/// Most DDS writers kept retiring at once (each is a DDS entity a client made the worker
/// hold a while longer); beyond, the oldest goes at once (counted, logged).
pub(super) const MAX_RETIRING: usize = 1024;

impl Writers {
    fn new(now: Instant) -> Self {
        Writers {
            holding: HashSet::new(),
            release_turn: 0,
            last_release: None,
            acks: AckTracker::new(now),
            shared: HashMap::new(),
            retiring: std::collections::VecDeque::new(),
            retired_early: 0,
            stamp: 0,
            gates: release_gate::ReleaseGates::default(),
            take_logs: take_log::TakeLogs::default(),
        }
    }

    /// Records front-end `frontend`'s operation `seq`, just written through `writer`, as
    /// outstanding until its readers acknowledged it.
    /// `positioned` tells the oldest position a read of its topic has in the topic's take log
    /// ([`take_log::TakeLogs::record`]).
    /// `origin` is the client write the sample came from, which the writer's readers here
    /// learn when they take it ([`AckTracker::origin_of`]).
    fn record(
        &mut self,
        writer: &Rc<DdsWriter>,
        frontend: u32,
        seq: u64,
        origin: Option<ipc::SampleOrigin>,
        now: Instant,
        positioned: impl FnOnce(u64) -> Option<u64>,
    ) {
        self.stamp += 1;
        let guid = writer.raw.guid();
        self.take_logs
            .record(&writer.topic, guid, self.stamp, positioned);
        let written = Written {
            frontend,
            seq,
            at: now,
            ordinal: writer.raw.writes(),
            stamp: self.stamp,
            // Without the sequence number the backend gave the sample, its readers here
            // cannot tell it by its identity (and learn no origin).
            sequence_number: writer.raw.last_sequence_number().unwrap_or(0),
            origin,
        };
        if writer.outstanding.record(written) {
            self.acks.watch(guid, writer);
        }
    }

    /// Lets go of the DDS writer of an XRCE writer that was deleted or replaced: kept until
    /// its readers acknowledged what was written through it ([`Writers::retiring`]).
    fn retire(&mut self, writer: Rc<DdsWriter>, now: Instant) {
        if writer.outstanding.is_empty() {
            return self.release(writer);
        }
        self.retiring.push_back((writer, now));
        if self.retiring.len() > MAX_RETIRING {
            if let Some((w, _)) = self.retiring.pop_front() {
                self.retired_early += 1;
                if self.retired_early.is_power_of_two() {
                    tracing::warn!(
                        retiring = MAX_RETIRING,
                        let_go = self.retired_early,
                        "a deleted data writer's DDS writer let go before its readers \
                         acknowledged everything: too many deleted writers waiting (their \
                         last samples may not reach every reader)"
                    );
                }
                self.release(w);
            }
        }
    }

    /// Lets go of the retiring writers whose readers acknowledged everything, or that
    /// waited [`crate::acks::ACK_GIVE_UP`].
    fn prune_retiring(&mut self, now: Instant) {
        let limit = now.checked_sub(crate::acks::ACK_GIVE_UP).unwrap_or(now);
        let mut done = Vec::new();
        self.retiring.retain(|(w, since)| {
            let keep = !w.outstanding.is_empty() && *since > limit;
            if !keep {
                done.push(w.clone());
            }
            keep
        });
        for w in done {
            self.release(w);
        }
    }

    /// Lets go of an XRCE writer's DDS writer: the last XRCE writer of a shared one takes
    /// its entry with it.
    fn release(&mut self, writer: Rc<DdsWriter>) {
        let Some(k) = writer.shared.clone() else {
            return;
        };
        drop(writer);
        if let Some(entries) = self.shared.get_mut(&k) {
            entries.retain(|e| e.writer.strong_count() > 0);
            if entries.is_empty() {
                self.shared.remove(&k);
            }
        }
    }
}

/// What the worker knows of each front-end process.
#[derive(Default)]
struct Frontends {
    /// The reply port of each front-end (by id).
    ports: HashMap<u32, FrontendPort>,
    /// Front-ends with entities whose process is gone, and since when.
    orphaned: HashMap<u32, Instant>,
    /// Front-end processes (id, incarnation) that said FrontendHello to this worker: they
    /// know this generation, and their operations are meant for it (kept apart from the
    /// reply ports, which the census may drop and recreate).
    greeted: HashSet<(u32, u16)>,
    /// Entities of front-ends that said hello again, for their replay to take back.
    adoption: Adoption,
    /// The last samples handed to each front-end, for a successor's replayed reads.
    recent: HashMap<u32, RecentSamples>,
    /// Restarted front-ends (id -> incarnation) whose requests wait for the end of the
    /// drain.
    successors: HashMap<u32, u16>,
    /// Those requests.
    deferred: Vec<Vec<u8>>,
    /// The last write executed on each reliable stream of each client, for a process that
    /// takes a front-end over.
    executed: ExecutedWrites,
}

impl<L: WorkerLink> std::fmt::Debug for Worker<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Worker")
            .field("generation", &self.generation)
            .field("entities", &self.entities.len())
            .finish()
    }
}

impl<L: WorkerLink> Worker<L> {
    /// A worker of generation `generation` over DDS `dds`, at `now`: it announces itself
    /// through `link` (front-ends that knew another generation replay to it).
    pub fn new(
        config: WorkerConfig,
        dds: Box<dyn DdsBackend>,
        mut link: L,
        generation: u32,
        now: Instant,
    ) -> Result<Self, LinkError> {
        tracing::info!(backend = dds.name(), "DDS backend");
        let replay_guard = ReplayGuard::new(link.take_crashed_replays());
        let domains = Domains::new(config.domains.clone());
        let graph = RosGraph::new(config.ros_graph);
        let mut w = Worker {
            config,
            topic_keys: std::hash::RandomState::new(),
            link,
            now,
            generation,
            frontends: Frontends::default(),
            dds,
            services_dds: None,
            entities: EntityTree::default(),
            readers: Readers::new(),
            domains,
            episodes: Episodes::default(),
            holdings: Holdings::default(),
            replay_guard,
            writers: Writers::new(now),
            graph,
            next_census: now + CENSUS_PERIOD,
            next_match_report: now + MATCH_REPORT_PERIOD,
            dropped: HashMap::new(),
            samples_written: 0,
            samples_taken: 0,
        };
        let hello = ReplyMessage::new(
            Route {
                generation: w.generation,
                ..Route::default()
            },
            Reply::WorkerHello,
        );
        w.link.announce(&hello)?;
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

    /// Counts a refusal of one of the worker's bounds under `reason`, and logs it if it
    /// opens an episode of them (a client can cause them at will: one line per episode,
    /// not per refusal).
    fn refused(&mut self, reason: &'static str, why: &str) {
        self.count(reason);
        if self.episodes.refused(reason, self.now) {
            tracing::warn!(
                reason,
                total = self.dropped.get(reason).copied().unwrap_or(0),
                "{why} (further refusals of this kind are counted, not logged, until the \
                 episode ends)"
            );
        }
    }

    /// Admits a new XRCE participant's domain, or refuses it (counted, logged once per
    /// episode).
    fn admit_domain(&mut self, domain: u16, key: EntityKey) -> Result<(), OpError> {
        self.domains.admit(domain).map_err(|r: DomainRefusal| {
            let why = format!("client {} of front-end {}: {r}", key.1, key.0);
            self.refused(r.reason(), &why);
            if r.status() == status::ERR_DENIED {
                OpError::Denied(r.to_string())
            } else {
                OpError::Resources(r.to_string())
            }
        })
    }

    /// The last XRCE participant of `domain` was deleted (everything under it went first):
    /// the domain's DDS participants go, with their threads and sockets.
    fn release_domain(&mut self, domain: u16) {
        // The graph writer is the one thing of the worker left in the domain.
        self.graph.forget(domain);
        self.writers.shared.retain(|k, _| k.0 != domain);
        self.dds.release_domain(domain);
        if let Some(s) = &mut self.services_dds {
            s.release_domain(domain);
        }
        let in_use = self.domains.in_use().count();
        tracing::info!(
            domain,
            in_use,
            "DDS domain released: its last XRCE participant was deleted"
        );
        // A domain freed: a refusal for the cap from now on is a new episode.
        if let Some(n) = self.episodes.end("domains_refused") {
            tracing::info!(refused = n, "DDS domains free again after refusals");
        }
    }

    /// Handles one request of a front-end (its encoded message), at `now`.
    pub fn handle_request(&mut self, message: &[u8], now: Instant) {
        self.now = now;
        self.screen_request(message);
    }

    /// One pass at `now`, after the requests that came: the requests held for restarted
    /// front-ends, the readers' samples, expired reads, held writes, matched counts, the ROS
    /// graph, what the front-ends are owed, and gone front-ends. Returns how many readers
    /// were pumped; fails only if a backend cannot tell which readers have data.
    pub fn pass(&mut self, now: Instant) -> std::io::Result<usize> {
        self.now = now;
        self.serve_successors();
        let pumped = self.pump_readers()?;
        self.expire_reads();
        self.release_rematched();
        self.report_matches();
        self.publish_graph();
        self.flush();
        self.watch_frontends();
        let ended = self.writers.take_logs.take_ended();
        if ended > 0 {
            *self.dropped.entry("take_logs_ended").or_default() += ended;
            tracing::info!(
                ended,
                "take logs ended at their bounds (topics, or writers of one topic): their \
                 reads count as drained only once emptied again"
            );
        }
        Ok(pumped)
    }

    /// The worker stops of its own accord (it drains first): the replays under way did not
    /// crash it, their marks go; writers holding samples for their readers release them over
    /// the next passes.
    pub fn stop(&mut self) {
        for fe in self.replay_guard.stopping() {
            self.link.mark_replay(fe, None);
        }
        self.stop_holding();
    }

    /// Writes not yet done with: held for readers to match, or written and not acknowledged
    /// by DDS readers yet (a stopping worker waits for them a while).
    pub fn unacknowledged_writes(&self) -> usize {
        self.writers.acks.outstanding_writes() + self.held_samples()
    }

    /// The descriptors that become readable when a DDS backend's readers may have data
    /// (level-triggered: readable as long as they hold some).
    pub fn readiness_fds(&self) -> Vec<std::os::fd::BorrowedFd<'_>> {
        std::iter::once(&self.dds)
            .chain(self.services_dds.as_ref())
            .map(|b| b.readiness_fd())
            .collect()
    }

    /// The link.
    pub fn link(&self) -> &L {
        &self.link
    }

    /// The link, to drive it.
    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    /// Sends the samples of every reader with an active read that has some, each in its
    /// turn (see [`Turns`]); returns how many readers were pumped.
    fn pump_readers(&mut self) -> std::io::Result<usize> {
        // Always, not only when its descriptor polled readable: gated that way, every
        // reader stalled (measured with 3 and 100 publishers).
        self.dds.ready_readers(&mut self.readers.ready)?;
        if let Some(s) = &mut self.services_dds {
            s.ready_readers(&mut self.readers.ready)?;
        }
        // Every write so far that reached a reader named it ready by now.
        self.readers.scan_stamp = self.writers.stamp;
        // Readers served a full batch last pass queue behind the others; readers that got no
        // turn for the filter budget go first.
        for t in self.readers.ready.drain(..) {
            if let Some(k) = self.readers.by_token.get(&t) {
                if let Some(r) = self.readers.reads.get_mut(k) {
                    r.holds = true;
                }
                if !self.readers.pump_again.contains(k) {
                    self.readers.to_pump.push(*k);
                }
            }
        }
        let mut line = std::mem::take(&mut self.readers.over_budget);
        line.append(&mut self.readers.to_pump);
        line.append(&mut self.readers.pump_again);
        self.readers.filter_pass_left = crate::filter::PASS_BUDGET;
        let pump: Vec<EntityKey> = line.take_all();
        let pumped = pump.len();
        for k in pump {
            self.pump(k);
        }
        Ok(pumped)
    }

    /// How long until the worker wants its next pass if nothing comes meanwhile (zero: at
    /// once; `None`: not before something comes).
    pub fn poll_timeout(&self, now: Instant) -> Option<Duration> {
        match self.timeout_ms(now) {
            t if t < 0 => None,
            t => Some(Duration::from_millis(t as u64)),
        }
    }

    fn timeout_ms(&self, now: Instant) -> i32 {
        let queued = self.dds.readers_queued()
            || self
                .services_dds
                .as_ref()
                .is_some_and(|s| s.readers_queued());
        if !self.readers.to_pump.is_empty()
            || !self.readers.pump_again.is_empty()
            || !self.readers.over_budget.is_empty()
            || queued
        {
            return 0;
        }
        let acks = self
            .writers
            .acks
            .due()
            .map(|d| d.saturating_duration_since(now).as_millis() as i32 + 1);
        sooner(acks, self.timeout_without_acks(now))
    }

    fn timeout_without_acks(&self, now: Instant) -> i32 {
        // A draining writer's next sample is due at its time (at least 1 ms on: the pace
        // between batches); the others look for their readers every 20 ms.
        let holding = (!self.writers.holding.is_empty()).then(|| match self.next_release() {
            Some(due) => (due.saturating_duration_since(now).as_millis() as i32).clamp(1, 20),
            None => 20,
        });
        sooner(holding, self.timeout_for_ports_and_reads(now))
    }

    /// The timeout the front-ends' queues, the reads' deadlines and pacing, the ROS graph
    /// and the census ask for (-1: none).
    fn timeout_for_ports_and_reads(&self, now: Instant) -> i32 {
        let waiting = self
            .frontends
            .ports
            .values()
            .filter(|p| !p.backlog.is_empty() || p.dirty || p.unnotified);
        if let Some(newest) = waiting.map(|p| p.last_delivery).max() {
            // A congested front-end does not signal when it drained: try again shortly, and
            // rarely once it has taken nothing for a while (it may be gone).
            return if now.saturating_duration_since(newest) < Duration::from_secs(1) {
                1
            } else {
                100
            };
        }
        let census = (!self.entities.is_empty() || !self.frontends.orphaned.is_empty())
            .then_some(self.next_census);
        self.readers
            .reads
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
    pub fn status_report(&self) -> ProcessReport {
        let mut entities: std::collections::BTreeMap<String, u64> = Default::default();
        for e in self.entities.values() {
            let kind = match &e.kind {
                EntityKind::Participant { .. } => "participant",
                EntityKind::Topic(_) => "topic",
                EntityKind::Publisher(..) => "publisher",
                EntityKind::Subscriber(..) => "subscriber",
                EntityKind::Type(_) => "type",
                EntityKind::Writer { .. } => "writer",
                EntityKind::Reader { .. } => "reader",
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
                frontends: self.frontends.ports.len() as u64,
                samples_written: self.samples_written,
                samples_taken: self.samples_taken,
                dropped: {
                    let mut d: std::collections::BTreeMap<String, u64> = self
                        .dropped
                        .iter()
                        .map(|(k, v)| (k.to_string(), *v))
                        .collect();
                    // The backends' own drops (a full local reader queue, ...).
                    let backends = std::iter::once(&self.dds).chain(self.services_dds.as_ref());
                    for (k, v) in backends.flat_map(|b| b.dropped()) {
                        *d.entry(k.to_string()).or_default() += v;
                    }
                    d
                },
            }),
            ..Default::default()
        }
    }
}

/// The sooner of an optional timeout and one where -1 means none (milliseconds).
fn sooner(timeout: Option<i32>, or: i32) -> i32 {
    match timeout {
        Some(t) if or < 0 => t,
        Some(t) => t.min(or),
        None => or,
    }
}
