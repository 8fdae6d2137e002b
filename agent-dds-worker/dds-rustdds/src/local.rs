//! Delivery inside the process between the worker's own writers and readers, for a backend
//! that would send it through the network instead.
//!
//! RustDDS delivers a sample from one of the worker's writers to one of its readers over UDP
//! loopback (between two participants, see [`crate::RustDds`]): two system calls, two thread
//! hand-overs and the RTPS encoding each way, for what never leaves the process. Cyclone DDS
//! delivers such samples itself and needs none of this. [`LocalDelivery`] wraps a backend:
//! when a writer and a reader of the worker match (same domain, partition, topic, type and
//! key kind, and QoS that match in the simple cases it models), each sample written is also
//! put at once into a queue of the reader, and the copy the backend delivers through the
//! network later is dropped by the reader (by its writer's GUID). Every sample reaches the
//! reader once, in the writer's order, with the identity the network copy has (sequence
//! numbers count each write and dispose of a writer from 1, RTPS 2.5 §8.2.4; the wrapper
//! follows them).
//!
//! What it does not model it leaves to the backend, unpaired: exclusive ownership, a
//! lifespan, a time-based filter, presentation, liveliness, partitions with wildcards, and a
//! transient-local reader joining a writer that already wrote (its history comes through the
//! network, and the writer's later samples must not overtake it).
//!
//! The reader's queue keeps the reader's history: KEEP_LAST n per instance (the oldest of an
//! instance goes), KEEP_ALL up to its resource limits (beyond, a sample is refused, counted
//! and logged, as a full DDS reader cache would refuse it), and never more than
//! [`LOCAL_QUEUE_MAX_BYTES`] of sample bytes. A refused sample is not let through from the
//! network instead: it would overtake the samples of its writer still queued here, and the
//! front-end, which keeps the highest sequence number delivered per writer, would then drop
//! those as delivered already.
//!
//! A volatile reader created after a transient-local writer wrote is paired at once: RustDDS
//! sends such a reader the writer's history (it looks at the writer's durability alone), and
//! those copies are dropped here as a volatile reader should never have had them.

use std::cell::{Cell, RefCell};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::os::fd::BorrowedFd;
use std::rc::Rc;
use std::sync::Arc;
use std::time::{Duration, Instant};

use xrce_dds_seam::policies::{Durability, History, OwnershipKind, Period, Reliability};
use xrce_dds_seam::types::KeyDescriptor;
use xrce_dds_seam::{
    BackendError, DdsBackend, DdsReader, DdsWriter, EndpointQos, Endpoints, Guid, Publisher,
    ReaderToken, Sample, SampleIdentity, Subscriber, Taken, TopicSpec,
};

/// Most samples a reader's local queue keeps when its resource limits set none.
pub const LOCAL_QUEUE_MAX: usize = 65_536;

/// Most sample bytes a reader's local queue keeps, whatever its limits (64 MiB).
pub const LOCAL_QUEUE_MAX_BYTES: usize = 64 << 20;

/// How long a reader keeps dropping the network copies of a deleted writer's samples: they
/// may still be on their way through loopback, or wait in the reader's cache.
const TWIN_GRACE: Duration = Duration::from_secs(5);

/// Most deleted writers a reader remembers (the oldest are forgotten first).
const TWINS_MAX: usize = 4096;

/// A backend, and delivery inside the process between its writers and readers.
pub struct LocalDelivery {
    inner: Box<dyn DdsBackend>,
    hub: Rc<Hub>,
}

impl std::fmt::Debug for LocalDelivery {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LocalDelivery")
            .field("inner", &self.inner.name())
            .field("pairs", &self.pairs())
            .finish()
    }
}

impl LocalDelivery {
    /// Wraps `inner`, which must deliver between its own writers and readers by itself too
    /// (those copies are dropped) and report each sample's writer GUID and sequence number.
    pub fn new(inner: Box<dyn DdsBackend>) -> Self {
        LocalDelivery {
            inner,
            hub: Rc::new(Hub::default()),
        }
    }

    /// Writer-reader pairs delivered inside the process now.
    pub fn pairs(&self) -> usize {
        self.hub
            .writers
            .borrow()
            .values()
            .map(|w| w.paired.borrow().len())
            .sum()
    }

    /// Samples a full local reader queue refused since the start.
    pub fn refused(&self) -> u64 {
        self.hub.refused.get()
    }
}

/// What a writer or reader is, for matching.
#[derive(Debug, Clone)]
struct Endpoint {
    domain: u16,
    partitions: Vec<String>,
    topic: String,
    type_name: String,
    keyed: bool,
    qos: EndpointQos,
}

impl Endpoint {
    fn new<G>(group: &LocalGroup<G>, domain: u16, spec: &TopicSpec, qos: &EndpointQos) -> Self {
        Endpoint {
            domain,
            partitions: group.partitions.clone(),
            topic: spec.name.clone(),
            type_name: spec.type_name.clone(),
            keyed: spec.key.is_some(),
            qos: *qos,
        }
    }
}

/// The state writers, readers and the backend share.
#[derive(Default)]
struct Hub {
    next_id: Cell<u64>,
    writers: RefCell<HashMap<u64, WriterSlot>>,
    readers: RefCell<HashMap<u64, Rc<LocalReaderState>>>,
    /// Readers given samples since the backend last named its ready readers.
    pending: RefCell<Vec<Rc<LocalReaderState>>>,
    refused: Cell<u64>,
}

/// A live writer as the hub sees it.
struct WriterSlot {
    endpoint: Endpoint,
    guid: Guid,
    /// Whether it wrote anything yet (a transient-local reader then is not paired with it).
    wrote: Rc<Cell<bool>>,
    /// The readers its samples go to inside the process.
    paired: Rc<RefCell<Vec<Rc<LocalReaderState>>>>,
}

impl Hub {
    fn next_id(&self) -> u64 {
        let id = self.next_id.get() + 1;
        self.next_id.set(id);
        id
    }

    /// Pairs a new writer with the live readers it matches.
    fn add_writer(&self, id: u64, slot: WriterSlot) {
        for r in self.readers.borrow().values() {
            if pairs(&slot.endpoint, &r.endpoint, slot.wrote.get()) {
                r.twin(slot.guid);
                slot.paired.borrow_mut().push(r.clone());
            }
        }
        self.writers.borrow_mut().insert(id, slot);
    }

    /// Pairs a new reader with the live writers it matches.
    fn add_reader(&self, id: u64, reader: Rc<LocalReaderState>) {
        for w in self.writers.borrow().values() {
            if pairs(&w.endpoint, &reader.endpoint, w.wrote.get()) {
                reader.twin(w.guid);
                w.paired.borrow_mut().push(reader.clone());
            }
        }
        self.readers.borrow_mut().insert(id, reader);
    }

    fn remove_writer(&self, id: u64) {
        let Some(slot) = self.writers.borrow_mut().remove(&id) else {
            return;
        };
        let now = Instant::now();
        for r in slot.paired.borrow().iter() {
            r.twin_deleted(slot.guid, now);
        }
    }

    fn remove_reader(&self, id: u64) {
        self.readers.borrow_mut().remove(&id);
        for w in self.writers.borrow().values() {
            w.paired.borrow_mut().retain(|r| r.id != id);
        }
    }

    /// Puts `taken` into every reader of `paired`.
    fn deliver(&self, paired: &[Rc<LocalReaderState>], taken: &Taken, dispose_key: Option<Key>) {
        for r in paired {
            let instance = match (&r.key, dispose_key) {
                (None, _) => Key::default(),
                (Some(_), Some(k)) => k,
                (Some(k), None) => instance_of(k, &taken.sample),
            };
            let copy = Taken {
                sample: taken.sample.clone(),
                identity: taken.identity,
                related: taken.related,
                disposed: taken.disposed,
                unregistered: false,
            };
            if r.queue.borrow_mut().push(instance, copy) {
                if !r.signalled.replace(true) {
                    self.pending.borrow_mut().push(r.clone());
                }
            } else {
                self.refuse(
                    &r.endpoint.topic,
                    1,
                    "a reader's queue is full (its resource limits): a sample from a writer \
                     of this agent was refused",
                );
            }
        }
    }

    /// Counts `n` samples not delivered inside the process; logged at powers of two.
    fn refuse(&self, topic: &str, n: u64, why: &str) {
        let before = self.refused.get();
        let after = before + n;
        self.refused.set(after);
        if after.is_power_of_two() || (after.ilog2() > before.max(1).ilog2()) {
            tracing::warn!(%topic, refused = after, "{why}");
        }
    }
}

/// Whether samples of writer `w` go to reader `r` inside the process (`wrote`: the writer
/// wrote before).
fn pairs(w: &Endpoint, r: &Endpoint, wrote: bool) -> bool {
    w.domain == r.domain
        && w.topic == r.topic
        && w.type_name == r.type_name
        && w.keyed == r.keyed
        && partitions_meet(&w.partitions, &r.partitions)
        && qos_match(&w.qos, &r.qos)
        // Its history comes through the network; the writer's next samples must not
        // overtake it.
        && !(wrote && r.qos.durability != Durability::Volatile)
}

/// Whether two groups' partitions meet; a wildcard is not modelled (no pair).
fn partitions_meet(a: &[String], b: &[String]) -> bool {
    let wild = |p: &String| p.contains(['*', '?', '[', '\\']);
    if a.iter().chain(b).any(wild) {
        return false;
    }
    let default = [String::new()];
    let a = if a.is_empty() { &default[..] } else { a };
    let b = if b.is_empty() { &default[..] } else { b };
    a.iter().any(|p| b.contains(p))
}

/// Whether a writer's QoS offers what a reader requests, in the cases modelled here; what
/// is not modelled does not match (the backend then delivers alone).
fn qos_match(w: &EndpointQos, r: &EndpointQos) -> bool {
    let rank = |d: Durability| match d {
        Durability::Volatile => 0,
        Durability::TransientLocal => 1,
        Durability::Transient => 2,
        Durability::Persistent => 3,
    };
    // A period offered (`a`) no longer than the one requested (`b`); absent is infinite.
    let within = |a: Option<Period>, b: Option<Period>| match (a, b) {
        (_, None | Some(Period::Infinite)) => true,
        (Some(Period::Finite(a)), Some(Period::Finite(b))) => a <= b,
        _ => false,
    };
    let (wd, rd) = (&w.described, &r.described);
    let exclusive = |o: Option<OwnershipKind>| o == Some(OwnershipKind::Exclusive);
    !(w.reliability == Reliability::BestEffort && r.reliability == Reliability::Reliable)
        && rank(w.durability) >= rank(r.durability)
        && within(wd.deadline, rd.deadline)
        && within(wd.latency_budget, rd.latency_budget)
        && wd.destination_order == rd.destination_order
        && !exclusive(wd.ownership)
        && !exclusive(rd.ownership)
        && wd.lifespan.is_none()
        && rd.time_based_filter.is_none()
        && wd.liveliness.is_none()
        && rd.liveliness.is_none()
        && wd.presentation.is_none()
        && rd.presentation.is_none()
        && !wd.partitions
        && !rd.partitions
}

/// An instance: its KeyHash (all zeros without a key).
type Key = [u8; 16];

/// The instance of a whole sample; one of its own when the key cannot be read (the writer
/// already refused such a sample, so this is not reached in practice).
fn instance_of(k: &KeyDescriptor, sample: &Sample) -> Key {
    k.of_sample(
        &sample.body,
        sample.little_endian(),
        sample.encoding.is_xcdr2(),
    )
    .map(|k| k.hash)
    .unwrap_or([0xff; 16])
}

/// A reader as the hub sees it, shared with the reader.
struct LocalReaderState {
    id: u64,
    endpoint: Endpoint,
    token: ReaderToken,
    key: Option<Arc<KeyDescriptor>>,
    queue: RefCell<LocalQueue>,
    /// Whether its token waits in the hub's pending list.
    signalled: Cell<bool>,
    /// Writers whose samples it gets inside the process, so it drops their network copies:
    /// live (None) or deleted when.
    twins: RefCell<HashMap<Guid, Option<Instant>>>,
}

impl LocalReaderState {
    fn twin(&self, guid: Guid) {
        self.twins.borrow_mut().insert(guid, None);
    }

    fn twin_deleted(&self, guid: Guid, at: Instant) {
        let mut twins = self.twins.borrow_mut();
        twins.insert(guid, Some(at));
        if twins.len() > TWINS_MAX {
            // Forget the writer deleted first.
            let oldest = twins
                .iter()
                .filter_map(|(g, t)| t.map(|t| (t, *g)))
                .min()
                .map(|(_, g)| g);
            if let Some(g) = oldest {
                twins.remove(&g);
            }
        }
    }

    /// Whether a sample the backend delivered is the network copy of one delivered here.
    /// Unregistrations (a writer went away) are the backend's alone and pass.
    fn is_twin(&self, t: &Taken) -> bool {
        !t.unregistered && self.twins.borrow().contains_key(&t.identity.writer)
    }

    /// Forgets writers deleted long enough ago (called when the backend's reader is empty).
    fn prune(&self, now: Instant) {
        self.twins
            .borrow_mut()
            .retain(|_, t| t.is_none_or(|t| now.duration_since(t) < TWIN_GRACE));
    }
}

/// A reader's queue of samples delivered inside the process, with the reader's history.
#[derive(Debug)]
struct LocalQueue {
    /// The samples in arrival order, by arrival number (a sample KEEP_LAST evicted from the
    /// middle leaves a gap).
    samples: BTreeMap<u64, (Key, Taken)>,
    /// Each instance's samples, oldest first, by arrival number: KEEP_LAST finds the oldest
    /// of an instance without scanning the queue.
    per_instance: HashMap<Key, VecDeque<u64>>,
    /// The next arrival number.
    next: u64,
    /// KEEP_LAST depth (None: KEEP_ALL).
    depth: Option<usize>,
    max_samples: usize,
    max_per_instance: usize,
    max_instances: usize,
    /// Sample bytes held (at most [`LOCAL_QUEUE_MAX_BYTES`]).
    bytes: usize,
}

impl LocalQueue {
    fn new(qos: &EndpointQos) -> Self {
        let limit = |n: Option<i32>| {
            n.and_then(|n| usize::try_from(n).ok())
                .filter(|n| *n > 0)
                .unwrap_or(LOCAL_QUEUE_MAX)
                .min(LOCAL_QUEUE_MAX)
        };
        let rl = qos.resource_limits;
        LocalQueue {
            samples: BTreeMap::new(),
            per_instance: HashMap::new(),
            next: 0,
            depth: match qos.history {
                History::KeepLast(n) => Some(usize::try_from(n).unwrap_or(1).max(1)),
                History::KeepAll => None,
            },
            max_samples: limit(rl.map(|r| r.max_samples)),
            max_per_instance: limit(rl.map(|r| r.max_samples_per_instance)),
            max_instances: limit(rl.map(|r| r.max_instances)),
            bytes: 0,
        }
    }

    /// Adds a sample of `instance`; false if the reader's limits refuse it (then nothing
    /// changed: KEEP_LAST evicts only once the new sample is sure to be taken).
    fn push(&mut self, instance: Key, taken: Taken) -> bool {
        let len = taken.sample.body.len();
        let held = self.per_instance.get(&instance).map_or(0, VecDeque::len);
        if self.depth.is_some_and(|d| held >= d) {
            // KEEP_LAST: the instance's oldest sample makes room, if the byte cap allows
            // the new one in its place.
            let oldest = self
                .per_instance
                .get(&instance)
                .and_then(|q| q.front())
                .copied();
            let freed = oldest
                .and_then(|n| self.samples.get(&n))
                .map_or(0, |(_, t)| t.sample.body.len());
            if self.bytes - freed + len > LOCAL_QUEUE_MAX_BYTES {
                return false;
            }
            if let Some(n) = oldest {
                if let Some(q) = self.per_instance.get_mut(&instance) {
                    q.pop_front();
                }
                if self.samples.remove(&n).is_some() {
                    self.bytes -= freed;
                }
            }
        } else if held >= self.max_per_instance
            || self.samples.len() >= self.max_samples
            || (held == 0 && self.per_instance.len() >= self.max_instances)
            || self.bytes + len > LOCAL_QUEUE_MAX_BYTES
        {
            return false;
        }
        let n = self.next;
        self.next += 1;
        self.per_instance.entry(instance).or_default().push_back(n);
        self.bytes += len;
        self.samples.insert(n, (instance, taken));
        true
    }

    fn pop(&mut self) -> Option<Taken> {
        let (n, (k, t)) = self.samples.pop_first()?;
        self.bytes -= t.sample.body.len();
        if let Some(q) = self.per_instance.get_mut(&k) {
            // The queue's oldest sample is its instance's oldest.
            debug_assert_eq!(q.front(), Some(&n));
            q.pop_front();
            if q.is_empty() {
                self.per_instance.remove(&k);
            }
        }
        Some(t)
    }
}

/// A publisher or subscriber of the inner backend, with its partitions.
#[derive(Debug)]
pub struct LocalGroup<G> {
    inner: G,
    partitions: Vec<String>,
}

/// A writer of the inner backend that also delivers inside the process.
struct LocalWriter {
    inner: Box<dyn DdsWriter>,
    hub: Rc<Hub>,
    id: u64,
    /// The sequence number of its last write or dispose.
    last_seq: Cell<i64>,
    wrote: Rc<Cell<bool>>,
    paired: Rc<RefCell<Vec<Rc<LocalReaderState>>>>,
}

impl Drop for LocalWriter {
    fn drop(&mut self) {
        self.hub.remove_writer(self.id);
    }
}

impl DdsWriter for LocalWriter {
    fn guid(&self) -> Guid {
        self.inner.guid()
    }
    fn topic_name(&self) -> &str {
        self.inner.topic_name()
    }
    fn little_endian(&self) -> bool {
        self.inner.little_endian()
    }
    fn key(&self) -> Option<&Arc<KeyDescriptor>> {
        self.inner.key()
    }
    fn write(&self, sample: Sample) -> Result<(), BackendError> {
        self.write_identified(sample, None).map(|_| ())
    }
    fn dispose(&self, sample: &Sample) -> Result<(), BackendError> {
        self.inner.dispose(sample)?;
        let seq = self.last_seq.get() + 1;
        self.last_seq.set(seq);
        self.wrote.set(true);
        let paired = self.paired.borrow();
        if paired.is_empty() {
            return Ok(());
        }
        let identity = SampleIdentity {
            writer: self.inner.guid(),
            sequence_number: seq,
        };
        // The readers get the key fields alone, little endian, as from the network.
        let (le, xcdr2) = (sample.little_endian(), sample.encoding.is_xcdr2());
        let key = self.inner.key().and_then(|k| {
            k.of_received(&sample.body, le, xcdr2, false)
                .or_else(|_| k.of_received(&sample.body, le, xcdr2, true))
                .ok()
        });
        let Some(key) = key else {
            // Not reached: the worker checked the key before the write. Letting the network
            // copy through instead could overtake queued samples of this writer.
            self.hub.refuse(
                self.inner.topic_name(),
                paired.len() as u64,
                "a dispose whose key cannot be read was not delivered inside the process",
            );
            return Ok(());
        };
        let taken = Taken {
            sample: Sample {
                encoding: xrce_dds_seam::Encoding::CDR_LE,
                body: key.payload.into(),
            },
            identity,
            related: None,
            disposed: true,
            unregistered: false,
        };
        self.hub.deliver(&paired, &taken, Some(key.hash));
        Ok(())
    }
    fn write_identified(
        &self,
        sample: Sample,
        related: Option<SampleIdentity>,
    ) -> Result<SampleIdentity, BackendError> {
        let paired = self.paired.borrow();
        let local = (!paired.is_empty()).then(|| sample.clone());
        let identity = self.inner.write_identified(sample, related)?;
        self.last_seq.set(identity.sequence_number);
        self.wrote.set(true);
        if let Some(sample) = local {
            let taken = Taken {
                sample,
                identity,
                related,
                disposed: false,
                unregistered: false,
            };
            self.hub.deliver(&paired, &taken, None);
        }
        Ok(identity)
    }
    fn all_acknowledged(&self) -> bool {
        self.inner.all_acknowledged()
    }
    fn writes(&self) -> u64 {
        self.inner.writes()
    }
    fn last_sequence_number(&self) -> Option<i64> {
        Some(self.last_seq.get())
    }
    fn acknowledged_writes(&self) -> u64 {
        self.inner.acknowledged_writes()
    }
    fn matched_readers(&self) -> usize {
        self.inner.matched_readers()
    }
}

/// A reader of the inner backend that also takes what was delivered inside the process.
struct LocalReader {
    inner: Box<dyn DdsReader>,
    hub: Rc<Hub>,
    state: Rc<LocalReaderState>,
    /// Which source the next take tries first (alternating, so neither starves the other).
    local_first: bool,
}

impl Drop for LocalReader {
    fn drop(&mut self) {
        self.hub.remove_reader(self.state.id);
    }
}

impl LocalReader {
    fn take_inner(&mut self) -> Result<Option<Taken>, BackendError> {
        loop {
            match self.inner.take_next()? {
                None => {
                    self.state.prune(Instant::now());
                    return Ok(None);
                }
                Some(t) if self.state.is_twin(&t) => continue,
                Some(t) => return Ok(Some(t)),
            }
        }
    }
}

impl DdsReader for LocalReader {
    fn guid(&self) -> Guid {
        self.inner.guid()
    }
    fn take_next(&mut self) -> Result<Option<Taken>, BackendError> {
        self.local_first = !self.local_first;
        if self.local_first {
            if let Some(t) = self.state.queue.borrow_mut().pop() {
                return Ok(Some(t));
            }
            return self.take_inner();
        }
        match self.take_inner()? {
            Some(t) => Ok(Some(t)),
            None => Ok(self.state.queue.borrow_mut().pop()),
        }
    }
}

impl Endpoints for LocalDelivery {
    type Publisher = LocalGroup<Publisher>;
    type Subscriber = LocalGroup<Subscriber>;

    fn new_publisher(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Self::Publisher, BackendError> {
        Ok(LocalGroup {
            inner: self.inner.create_publisher(domain, partitions)?,
            partitions: partitions.to_vec(),
        })
    }

    fn new_subscriber(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Self::Subscriber, BackendError> {
        Ok(LocalGroup {
            inner: self.inner.create_subscriber(domain, partitions)?,
            partitions: partitions.to_vec(),
        })
    }

    fn new_writer(
        &mut self,
        g: &LocalGroup<Publisher>,
        domain: u16,
        topic: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError> {
        let inner = self
            .inner
            .create_writer(&g.inner, topic, qos, little_endian)?;
        let id = self.hub.next_id();
        let slot = WriterSlot {
            endpoint: Endpoint::new(g, domain, topic, qos),
            guid: inner.guid(),
            wrote: Rc::new(Cell::new(inner.writes() > 0)),
            paired: Rc::default(),
        };
        let writer = LocalWriter {
            inner,
            hub: self.hub.clone(),
            id,
            last_seq: Cell::new(0),
            wrote: slot.wrote.clone(),
            paired: slot.paired.clone(),
        };
        self.hub.add_writer(id, slot);
        Ok(Box::new(writer))
    }

    fn new_reader(
        &mut self,
        g: &LocalGroup<Subscriber>,
        domain: u16,
        topic: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError> {
        let inner = self.inner.create_reader(&g.inner, topic, qos, token)?;
        let id = self.hub.next_id();
        let state = Rc::new(LocalReaderState {
            id,
            endpoint: Endpoint::new(g, domain, topic, qos),
            token,
            key: topic.key.clone(),
            queue: RefCell::new(LocalQueue::new(qos)),
            signalled: Cell::new(false),
            twins: RefCell::default(),
        });
        self.hub.add_reader(id, state.clone());
        Ok(Box::new(LocalReader {
            inner,
            hub: self.hub.clone(),
            state,
            local_first: false,
        }))
    }
}

impl DdsBackend for LocalDelivery {
    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn supports_partitions(&self) -> bool {
        self.inner.supports_partitions()
    }

    fn supports_services(&self) -> bool {
        self.inner.supports_services()
    }

    fn announces_graph(&self) -> bool {
        self.inner.announces_graph()
    }

    fn announce_graph(
        &mut self,
        domain: u16,
        nodes: &xrce_dds_seam::ros_nodes::DomainNodes,
    ) -> Result<(), BackendError> {
        self.inner.announce_graph(domain, nodes)
    }

    fn participant_guid(&mut self, domain: u16) -> Result<Guid, BackendError> {
        self.inner.participant_guid(domain)
    }

    fn readiness_fd(&self) -> BorrowedFd<'_> {
        self.inner.readiness_fd()
    }

    fn ready_readers(&mut self, out: &mut Vec<ReaderToken>) -> std::io::Result<()> {
        self.inner.ready_readers(out)?;
        for r in self.hub.pending.borrow_mut().drain(..) {
            r.signalled.set(false);
            out.push(r.token);
        }
        Ok(())
    }

    fn readers_queued(&self) -> bool {
        self.inner.readers_queued() || !self.hub.pending.borrow().is_empty()
    }

    fn participants(&self) -> usize {
        self.inner.participants()
    }

    fn participant_domains(&self) -> Vec<u16> {
        self.inner.participant_domains()
    }

    fn release_domain(&mut self, domain: u16) {
        // The hub forgets endpoints as they are dropped: nothing of the domain is left here.
        self.inner.release_domain(domain);
    }

    fn dropped(&self) -> Vec<(&'static str, u64)> {
        let mut d = self.inner.dropped();
        if self.refused() > 0 {
            d.push(("local_queue_refused", self.refused()));
        }
        d
    }
}

#[cfg(test)]
mod tests;
