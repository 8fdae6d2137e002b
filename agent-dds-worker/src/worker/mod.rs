//! The worker's event loop: executes the front-ends' operations on DDS entities and streams
//! samples of active reads back.
//!
//! Entities are keyed by (front-end id, client key, object id). The worker keeps nothing a
//! front-end cannot rebuild: after a restart it announces a new generation and the front-ends
//! replay their clients' object graphs.
//!
//! This module is the loop and the worker's state; each job is a module of its own: the
//! dispatch of requests (`requests`), the reply ports (`ports`), the DDS side of each
//! entity (`entities`; the tree itself is [`crate::tree`]), creation (`create`), writes
//! and held samples (`writes`), reads (`reads`), requesters and repliers (`services`)
//! and the ROS 2 graph (`graph`).

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
    object_kind, status, ClientKey, ObjectId, ObjectVariant, ReadSpecification, ResultStatus,
    VariantExtra,
};
use xrce_ipc::shm::{IpcNode, Receiver, Sender, ServiceKind, ShmError};
use xrce_ipc::status::{ProcessReport, Reporter, Watchdog, WorkerStatus};
use xrce_ipc::{self as ipc, Encode, Reply, ReplyMessage, Request, RequestMessage, Route};

use crate::acks::{AckTracker, Acknowledging, Outstanding};
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
mod graph;
mod ports;
mod reads;
mod replay_guard;
mod requests;
mod services;
#[cfg(test)]
mod tests;
mod writes;

use create::*;
use entities::*;
use ports::*;
use reads::*;
use replay_guard::ReplayGuard;
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

/// A loop pass longer than this is logged (front-ends' operations wait meanwhile, and a
/// front-end drops best-effort writes once its window to the worker is full).
const SLOW_PASS: Duration = Duration::from_millis(50);
/// A stopping worker stops once no operation came for this long (and DDS readers have
/// acknowledged every write).
pub const DRAIN_QUIET: Duration = Duration::from_millis(100);
/// Longest a stopping worker drains (below the supervisor's stop grace of 5 s).
pub const DRAIN_MAX: Duration = Duration::from_secs(3);
/// At most one such line in this period (with the count of slow passes so far).
const SLOW_PASS_LOG_PERIOD: Duration = Duration::from_secs(10);

/// How often the worker looks for front-ends whose process is gone.
const CENSUS_PERIOD: Duration = Duration::from_secs(1);
/// How often every writer's matched count is looked at and, when it changed, reported to its
/// front-end (which replays it to a restarted worker).
const MATCH_REPORT_PERIOD: Duration = Duration::from_secs(1);

type EntityKey = (u32, ClientKey, ObjectId);

use crate::representation::OpError;

/// The DDS worker.
pub struct Worker {
    config: WorkerConfig,
    node: IpcNode,
    generation: u32,
    /// Taken by [`Worker::run`] so requests can be handled straight from shared memory.
    requests: Option<Receiver>,
    announce: Sender,
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
    /// Loop passes that took [`SLOW_PASS`] or longer, and when one was last logged.
    slow_passes: u64,
    slow_logged: Option<Instant>,
    /// Writes this process's status report.
    reporter: Reporter,
    /// Pings systemd's watchdog when the worker is a unit of its own.
    watchdog: Watchdog,
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
        }
    }

    /// Forgets `key`'s reads and turns, and the wake-up token of its reader (dropped by the
    /// caller: the backend's reader is deleted and wakes nobody any more).
    fn forget(&mut self, key: EntityKey, token: Option<ReaderToken>) {
        if let Some(token) = token {
            self.by_token.remove(&token);
        }
        self.reads.remove(&key);
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
}

/// Most DDS writers kept retiring at once (each is a DDS entity a client made the worker
/// hold a while longer); beyond, the oldest goes at once (counted, logged).
pub(super) const MAX_RETIRING: usize = 1024;

impl Writers {
    fn new(now: Instant) -> Self {
        Writers {
            holding: HashSet::new(),
            acks: AckTracker::new(now),
            shared: HashMap::new(),
            retiring: std::collections::VecDeque::new(),
            retired_early: 0,
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
}

impl std::fmt::Debug for Worker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Worker")
            .field("generation", &self.generation)
            .field("entities", &self.entities.len())
            .finish()
    }
}

impl Worker {
    /// Opens the IPC services, then announces a new generation; DDS through the backend
    /// `config.backend` names, where `config.dds` says.
    pub fn new(mut config: WorkerConfig) -> anyhow::Result<Self> {
        let dds = backend::create(config.backend, &config.dds)?;
        config.domains.unservable = backend::unservable_domains(config.backend, &config.dds);
        Self::with_backend(config, dds)
    }

    /// Opens the IPC services, then announces a new generation; DDS through `dds`.
    pub fn with_backend(config: WorkerConfig, dds: Box<dyn DdsBackend>) -> anyhow::Result<Self> {
        tracing::info!(backend = dds.name(), "DDS backend");
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
        let ros_graph = config.ros_graph;
        let config_instance = config.instance.clone();
        let replay_guard = ReplayGuard::open(&config.instance);
        let domains = Domains::new(config.domains.clone());
        let w = Worker {
            config,
            node,
            generation,
            requests: Some(requests),
            announce,
            frontends: Frontends::default(),
            dds,
            services_dds: None,
            entities: EntityTree::default(),
            readers: Readers::new(),
            domains,
            episodes: Episodes::default(),
            holdings: Holdings::default(),
            replay_guard,
            writers: Writers::new(Instant::now()),
            graph: RosGraph::new(ros_graph),
            next_census: Instant::now() + CENSUS_PERIOD,
            next_match_report: Instant::now() + MATCH_REPORT_PERIOD,
            dropped: HashMap::new(),
            samples_written: 0,
            samples_taken: 0,
            slow_passes: 0,
            slow_logged: None,
            reporter: Reporter::new(&config_instance, "worker"),
            watchdog: Watchdog::from_env(),
        };
        let hello = ReplyMessage::new(
            Route {
                generation: w.generation,
                ..Route::default()
            },
            Reply::WorkerHello,
        );
        w.announce.send(&hello)?;
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

    /// Counts a refusal of one of the worker's bounds under `reason`, and logs it if it
    /// opens an episode of them (a client can cause them at will: one line per episode,
    /// not per refusal).
    fn refused(&mut self, reason: &'static str, why: &str) {
        self.count(reason);
        if self.episodes.refused(reason, Instant::now()) {
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

    /// Runs until SIGINT or SIGTERM, then drains (see [`DRAIN_MAX`]).
    pub fn run(&mut self) -> anyhow::Result<()> {
        let requests = self
            .requests
            .take()
            .ok_or_else(|| anyhow::anyhow!("the worker runs only once"))?;
        let result = self.serve(&requests);
        // The files of a front-end killed since the last census (once a second) would outlive
        // the agent: the census removes them now.
        let census = self.node.nodes();
        if !census.dead.is_empty() {
            tracing::debug!(dead = ?census.dead, "dead front-ends' shared-memory files removed");
        }
        self.reporter.remove();
        result
    }

    fn serve(&mut self, requests: &Receiver) -> anyhow::Result<()> {
        // Since when the worker drains before it stops, and when it last took a request.
        let mut draining: Option<Instant> = None;
        let mut last_request = Instant::now();
        loop {
            if let Some(since) = draining {
                // Stop once the front-ends have sent nothing for a moment (they stop with
                // it: a supervisor that stops or dies stops them all) and DDS readers have
                // acknowledged every write, or after DRAIN_MAX whatever is left.
                let quiet = last_request.elapsed() >= DRAIN_QUIET;
                let acknowledged = self.writers.acks.outstanding_writes() == 0;
                if (quiet && acknowledged) || since.elapsed() >= DRAIN_MAX {
                    tracing::info!(
                        drained_ms = since.elapsed().as_millis() as u64,
                        unacknowledged_writes = self.writers.acks.outstanding_writes(),
                        "stopping"
                    );
                    return Ok(());
                }
            } else if self.node.termination_requested() {
                // Operations a front-end handed over were acknowledged to its clients: they
                // are executed, and their samples given DDS's time to reach its readers,
                // before the DDS entities go with this process.
                tracing::info!(
                    "termination requested; executing what the front-ends handed over first"
                );
                draining = Some(Instant::now());
                self.replay_guard.stopping();
            }
            let now = Instant::now();
            if now >= self.reporter.due() {
                let report = self.status_report();
                self.reporter.maybe_write(now, || report);
            }
            self.watchdog.maybe_ping(now);
            // At least once per report period: the report's age is the loop's heartbeat.
            let period = xrce_ipc::status::REPORT_PERIOD.as_millis() as i32;
            let timeout = match self.poll_timeout() {
                t if t < 0 => period,
                t => t.min(period),
            };
            // Draining, it looks at the clock often enough to stop on time.
            let timeout = if draining.is_some() {
                timeout.min(20)
            } else {
                timeout
            };
            let requests_ready = self.wait(requests, timeout)?;
            let pass = Instant::now();
            // Wake-ups are consumed only when there are some (a system call each time, and
            // the loop runs per sample under load); the queue itself is read every time.
            if requests_ready {
                requests.clear_events();
            }
            let taken = requests.drain(|m| self.handle_request(m))?;
            if taken > 0 {
                last_request = Instant::now();
            }
            let after_requests = pass.elapsed();
            self.serve_successors();
            let pumped = self.pump_readers()?;
            let after_reads = pass.elapsed();
            self.expire_reads();
            self.release_rematched();
            self.report_matches();
            self.publish_graph();
            self.flush();
            self.watch_frontends();
            let took = pass.elapsed();
            if took >= SLOW_PASS {
                self.slow_passes += 1;
                let quiet = self
                    .slow_logged
                    .is_some_and(|t| t.elapsed() < SLOW_PASS_LOG_PERIOD);
                if quiet {
                    continue;
                }
                self.slow_logged = Some(Instant::now());
                tracing::warn!(
                    took_ms = took.as_millis() as u64,
                    slow_passes = self.slow_passes,
                    requests_ms = after_requests.as_millis() as u64,
                    reads_ms = after_reads.saturating_sub(after_requests).as_millis() as u64,
                    requests = taken,
                    readers = pumped,
                    "a worker loop pass took long; front-ends' operations waited meanwhile"
                );
            }
        }
    }

    /// Blocks until the front-ends' requests or a DDS backend's readers may have something,
    /// `timeout_ms` passes, or a signal arrives (then the caller checks for termination);
    /// whether the requests' descriptor polled readable.
    ///
    /// poll(2), level-triggered, not an edge-triggered poller as the front-end's: the
    /// backends' descriptors signal a condition (a Cyclone reader queue, a RustDDS poller)
    /// that each pass drains only up to a batch, and must wake the next wait as long as it
    /// holds.
    fn wait(&self, requests: &Receiver, timeout_ms: i32) -> std::io::Result<bool> {
        use nix::poll::{PollFd, PollFlags, PollTimeout};
        use std::os::fd::AsFd;
        let mut fds = vec![
            PollFd::new(requests.as_fd(), PollFlags::POLLIN),
            PollFd::new(self.dds.readiness_fd(), PollFlags::POLLIN),
        ];
        if let Some(s) = &self.services_dds {
            fds.push(PollFd::new(s.readiness_fd(), PollFlags::POLLIN));
        }
        let timeout = PollTimeout::try_from(timeout_ms.max(0)).unwrap_or(PollTimeout::MAX);
        match nix::poll::poll(&mut fds, timeout) {
            Ok(_) => Ok(fds[0].revents().is_some_and(|r| !r.is_empty())),
            Err(nix::errno::Errno::EINTR) => Ok(false),
            Err(e) => Err(e.into()),
        }
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
        // Readers served a full batch last pass queue behind the others; readers that got no
        // turn for the filter budget go first.
        for t in self.readers.ready.drain(..) {
            if let Some(k) = self.readers.by_token.get(&t) {
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

    fn poll_timeout(&self) -> i32 {
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
            .map(|d| d.saturating_duration_since(Instant::now()).as_millis() as i32 + 1);
        let t = self.timeout_without_acks();
        match (acks, t) {
            (Some(a), t) if t < 0 => a,
            (Some(a), t) => a.min(t),
            (None, t) => t,
        }
    }

    fn timeout_without_acks(&self) -> i32 {
        if !self.writers.holding.is_empty() {
            let draining = self.writers.holding.iter().any(|k| {
                matches!(self.entities.value(k), Some(Entity { kind: EntityKind::Writer { rematch: r, .. }, .. }) if r.draining)
            });
            return if draining { 1 } else { 20 };
        }
        let waiting = self
            .frontends
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
    fn status_report(&self) -> ProcessReport {
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
