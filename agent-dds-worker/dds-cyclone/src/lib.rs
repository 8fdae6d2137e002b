//! The Cyclone DDS backend (feature `cyclone`): one participant per domain, which delivers
//! between the agent's own writers and readers inside the process; topics of raw samples
//! with the worker's own key extraction (`ffi`'s sertype), so keyed topics keep their
//! instances; readiness through reader listeners and a socket pair.
//!
//! Sample identities: the writer's GUID and sequence number, read off the DATA submessage for
//! samples from other processes, and numbered by the writer itself for samples delivered
//! inside the process (Cyclone numbers its writes the same way, from 1).
//!
//! What it cannot do (docs/dds-backends.md): requesters and repliers (no related sample
//! identity can be put on a write through Cyclone's C API).
#![deny(unsafe_code)]
// The exception: `ffi`, the calls into Cyclone DDS's C API, with their invariants.
#![warn(unreachable_pub, missing_docs)]

use std::collections::{HashMap, VecDeque};
use std::fmt::Write as _;
use std::net::IpAddr;
use std::os::fd::BorrowedFd;
use std::rc::{Rc, Weak};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use bytes::Bytes;

use xrce_dds_seam::ports;
use xrce_dds_seam::types::KeyDescriptor;
use xrce_dds_seam::{
    BackendError, DdsBackend, DdsConfig, DdsReader, DdsWriter, Encoding, EndpointQos, Endpoints,
    Guid, ReaderToken, Sample, SampleIdentity, Taken, TopicSpec,
};

#[allow(unsafe_code)]
mod ffi;
pub mod qos;

/// DDS through Cyclone DDS.
pub struct Cyclone {
    // Declared first: its thread stops before any entity is deleted.
    acks: AckWatcher,
    config: DdsConfig,
    participants: HashMap<u16, Rc<ffi::Participant>>,
    /// Topics by (domain, name, type name, keyed), shared by their endpoints and deleted
    /// with the last of them.
    topics: HashMap<(u16, String, String, bool), Weak<ffi::Entity>>,
    readiness: ffi::Readiness,
}

impl std::fmt::Debug for Cyclone {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Cyclone")
            .field("participants", &self.participants.len())
            .field("topics", &self.topics.len())
            .finish()
    }
}

/// The agent's own Cyclone settings: heartbeats every 10 ms (at least 5 ms apart) while a
/// writer has unacknowledged samples, instead of every 100 ms, so that readers acknowledge
/// within tens of milliseconds and the front-ends can let go of their retained writes that
/// soon (what is unacknowledged at a worker crash is resent, so this bounds the repeats).
/// A deleted writer does not linger for unacknowledged samples (Cyclone's default is up to
/// 1 s, during which the deleting call, the worker's loop, would wait), as with RustDDS.
const AGENT_SETTINGS: &str =
    "<Internal><HeartbeatInterval minsched=\"5ms\">10ms</HeartbeatInterval>\
     <WriterLingerDuration>0 s</WriterLingerDuration></Internal>";

/// Cyclone's configuration: `CYCLONEDDS_URI`'s (`uri`), then the agent's settings and, with
/// `interfaces`, DDS restricted to them (later settings win). On loopback alone there is no
/// multicast, so discovery goes by unicast to the well-known ports of the first participant
/// indices on the same addresses (which is also how RustDDS and a loopback-pinned Cyclone
/// find each other). With `data_multicast_offset`, user-data multicast is received on that
/// port of the domain's range instead of its own (`7400 + 250·d + 1`, which an XRCE front-end
/// serves: [`xrce_dds_seam::ports`]); Cyclone announces the port, so other participants send there.
pub fn config_xml(
    interfaces: &[IpAddr],
    uri: Option<&str>,
    data_multicast_offset: Option<u32>,
) -> Result<String, BackendError> {
    let v6 = interfaces.iter().filter(|a| a.is_ipv6()).count();
    if v6 != 0 && v6 != interfaces.len() {
        return Err(BackendError::Placement(
            "Cyclone DDS uses either IPv4 or IPv6 addresses in a domain, not both".into(),
        ));
    }
    let mut s = String::new();
    if let Some(u) = uri.map(str::trim).filter(|u| !u.is_empty()) {
        s.push_str(u);
        s.push(',');
    }
    s.push_str("<CycloneDDS><Domain id=\"any\">");
    s.push_str(AGENT_SETTINGS);
    let mut discovery = String::new();
    if let Some(offset) = data_multicast_offset {
        let _ = write!(
            discovery,
            "<Ports><MulticastDataOffset>{offset}</MulticastDataOffset></Ports>"
        );
    }
    let loopback = !interfaces.is_empty() && interfaces.iter().all(|a| a.is_loopback());
    if loopback {
        discovery.push_str(
            "<ParticipantIndex>auto</ParticipantIndex>\
             <MaxAutoParticipantIndex>50</MaxAutoParticipantIndex><Peers>",
        );
        for a in interfaces {
            match a {
                IpAddr::V4(a) => {
                    let _ = write!(discovery, "<Peer address=\"{a}\"/>");
                }
                IpAddr::V6(a) => {
                    let _ = write!(discovery, "<Peer address=\"[{a}]\"/>");
                }
            }
        }
        discovery.push_str("</Peers>");
    }
    if !interfaces.is_empty() {
        s.push_str("<General><Interfaces>");
        for a in interfaces {
            let _ = write!(s, "<NetworkInterface address=\"{a}\"/>");
        }
        s.push_str("</Interfaces>");
        if v6 != 0 {
            s.push_str("<Transport>udp6</Transport>");
        }
        if loopback {
            s.push_str("<AllowMulticast>false</AllowMulticast>");
        }
        s.push_str("</General>");
    }
    if !discovery.is_empty() {
        let _ = write!(s, "<Discovery>{discovery}</Discovery>");
    }
    s.push_str("</Domain></CycloneDDS>");
    Ok(s)
}

impl Cyclone {
    /// A backend with no participant yet, leaving the ports the configuration reserves
    /// ([`DdsConfig::reserved_ports`]) to the front-ends.
    pub fn new(config: DdsConfig) -> std::io::Result<Self> {
        Ok(Cyclone {
            config,
            participants: HashMap::new(),
            topics: HashMap::new(),
            readiness: ffi::Readiness::new()?,
            acks: AckWatcher::start()?,
        })
    }

    /// Leaves these UDP ports to the agent's front-ends (instead of the configuration's).
    #[cfg(test)]
    pub fn reserve_ports(&mut self, reserved: ports::ReservedPorts) {
        self.config.reserved_ports = reserved;
    }

    fn participant(&mut self, domain: u16) -> Result<Rc<ffi::Participant>, BackendError> {
        if let Some(p) = self.participants.get(&domain) {
            return Ok(p.clone());
        }
        // Cyclone binds its multicast sockets on the wildcard address of its transport's
        // family (IPv6 only when every configured address is one).
        let v6 = !self.config.interfaces.is_empty()
            && self.config.interfaces.iter().all(IpAddr::is_ipv6);
        let plan = ports::plan(
            domain,
            &self.config.reserved_ports,
            &self.config.interfaces,
            |p| ports::shareable(p, v6),
        )
        .map_err(|clash| BackendError::Placement(clash.to_string()))?;
        if let Some(taken) = plan.user_multicast_taken {
            let Some(offset) = plan.data_multicast_offset else {
                return Err(BackendError::Placement(format!(
                    "DDS domain {domain}: UDP port {taken}, its user-data multicast port, is \
                     taken (an XRCE port?), and so are its spare ports {}-{}",
                    ports::port_at(domain, *ports::SPARE_OFFSETS.start()).unwrap_or(0),
                    ports::port_at(domain, *ports::SPARE_OFFSETS.end()).unwrap_or(0),
                )));
            };
            tracing::info!(
                domain,
                taken,
                instead = ports::port_at(domain, offset),
                "the domain's user-data multicast port is taken (an XRCE port?): Cyclone DDS \
                 receives user-data multicast on a spare port instead, which it announces to \
                 the other participants"
            );
        }
        let uri = std::env::var("CYCLONEDDS_URI").ok();
        let xml = config_xml(
            &self.config.interfaces,
            uri.as_deref(),
            plan.data_multicast_offset,
        )?;
        let guard = plan.guard(v6);
        let p = ffi::Participant::new(u32::from(domain), Some(&xml))
            .map_err(|e| e.context("Cyclone DDS's reason is in the worker's log just before"));
        // Released before the sockets are confined (it is one of the process's wildcard
        // sockets).
        drop(guard);
        let p = Rc::new(p?);
        // Fails closed: unconfined, the participant (and its domain) is deleted here.
        xrce_dds_seam::confine_new_sockets(&self.config)
            .map_err(|e| e.context(&format!("DDS participant in domain {domain}")))?;
        tracing::info!(domain, "Cyclone DDS participant created");
        self.participants.insert(domain, p.clone());
        Ok(p)
    }

    /// A publisher (`publish`) or subscriber in `domain`.
    fn group(
        &mut self,
        domain: u16,
        publish: bool,
        partitions: &[String],
    ) -> Result<Group, BackendError> {
        let participant = self.participant(domain)?;
        let entity = participant.create_group(publish, partitions)?;
        Ok(Group {
            entity,
            participant,
            domain,
        })
    }

    fn topic(&mut self, group: &Group, spec: &TopicSpec) -> Result<Rc<ffi::Entity>, BackendError> {
        let id = (
            group.domain,
            spec.name.clone(),
            spec.type_name.clone(),
            spec.key.is_some(),
        );
        if let Some(t) = self.topics.get(&id).and_then(Weak::upgrade) {
            return Ok(t);
        }
        self.topics.retain(|_, t| t.strong_count() > 0);
        let t = Rc::new(group.participant.create_topic(
            &spec.name,
            &spec.type_name,
            spec.key.clone(),
        )?);
        self.topics.insert(id, Rc::downgrade(&t));
        Ok(t)
    }
}

/// How long the acknowledgement thread waits for one writer's readers per turn.
const ACK_WAIT: Duration = Duration::from_millis(25);
/// How long the acknowledgement thread pauses after a turn before it looks again. Writes
/// made meanwhile do not wake it (one futex wake and one thread switch per write otherwise:
/// measured, that was most of the worker's system calls at 1,000 samples/s); the worker asks
/// for the counts every 2 ms anyway.
const ACK_NAP: Duration = Duration::from_millis(2);

/// Counts, per writer, how many of its writes its readers acknowledged, on a thread of its
/// own. Cyclone's readers acknowledge when the writer's heartbeats ask (every few tens of
/// milliseconds), so while a writer writes every few milliseconds "everything acknowledged"
/// is almost never true; but `dds_wait_for_acks` waits for the writes made before it was
/// called, so a waiting call, which the worker's loop cannot make, tells that those are
/// acknowledged even while more are written.
struct AckWatcher {
    shared: Arc<AckShared>,
    thread: Option<std::thread::JoinHandle<()>>,
}

struct AckShared {
    writers: Mutex<HashMap<ffi::Handle, Arc<WriterAcks>>>,
    wake: Condvar,
    /// The thread waits for writes (set under the lock; a writer that clears it notifies).
    sleeping: AtomicBool,
    stop: AtomicBool,
}

/// One writer's counts.
#[derive(Default)]
struct WriterAcks {
    written: AtomicU64,
    acked: AtomicU64,
}

impl AckWatcher {
    fn start() -> std::io::Result<Self> {
        let shared = Arc::new(AckShared {
            writers: Mutex::new(HashMap::new()),
            wake: Condvar::new(),
            sleeping: AtomicBool::new(false),
            stop: AtomicBool::new(false),
        });
        let s = shared.clone();
        let thread = std::thread::Builder::new()
            .name("cyclone-acks".into())
            .spawn(move || s.run())?;
        Ok(AckWatcher {
            shared,
            thread: Some(thread),
        })
    }

    fn watch(&self, writer: ffi::Handle) -> Arc<WriterAcks> {
        let acks = Arc::new(WriterAcks::default());
        lock(&self.shared.writers).insert(writer, acks.clone());
        acks
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl AckShared {
    fn run(&self) {
        let wait_ns = i64::try_from(ACK_WAIT.as_nanos()).unwrap_or(i64::MAX);
        loop {
            let pending: Vec<(ffi::Handle, Arc<WriterAcks>)> = {
                let mut writers = lock(&self.writers);
                loop {
                    if self.stop.load(Ordering::SeqCst) {
                        return;
                    }
                    self.sleeping.store(true, Ordering::SeqCst);
                    let p: Vec<_> = writers
                        .iter()
                        .filter(|(_, a)| {
                            a.acked.load(Ordering::SeqCst) < a.written.load(Ordering::SeqCst)
                        })
                        .map(|(h, a)| (*h, a.clone()))
                        .collect();
                    if !p.is_empty() {
                        self.sleeping.store(false, Ordering::SeqCst);
                        break p;
                    }
                    writers = self
                        .wake
                        .wait_timeout(writers, Duration::from_millis(200))
                        .unwrap_or_else(std::sync::PoisonError::into_inner)
                        .0;
                }
            };
            for (h, a) in pending {
                if self.stop.load(Ordering::SeqCst) {
                    return;
                }
                // Read before the wait, which covers every write made before it.
                let n = a.written.load(Ordering::SeqCst);
                if ffi::wait_for_acks(h, wait_ns) {
                    a.acked.fetch_max(n, Ordering::SeqCst);
                }
            }
            std::thread::sleep(ACK_NAP);
        }
    }

    /// A write was made: wake the thread if it waits.
    fn wrote(&self, acks: &WriterAcks) {
        acks.written.fetch_add(1, Ordering::SeqCst);
        if self.sleeping.swap(false, Ordering::SeqCst) {
            let _held = lock(&self.writers);
            self.wake.notify_one();
        }
    }
}

impl Drop for AckWatcher {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        {
            let _held = lock(&self.shared.writers);
            self.shared.wake.notify_one();
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A Cyclone DDS publisher or subscriber, on the participant of its domain.
pub struct Group {
    entity: ffi::Entity,
    participant: Rc<ffi::Participant>,
    domain: u16,
}

impl std::fmt::Debug for Group {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Group")
            .field("domain", &self.domain)
            .finish_non_exhaustive()
    }
}

struct Writer {
    // Declared before the topic: deleted first.
    raw: ffi::Writer,
    _topic: Rc<ffi::Entity>,
    guid: Guid,
    topic_name: String,
    little_endian: bool,
    key: Option<Arc<KeyDescriptor>>,
    acks: Arc<WriterAcks>,
    /// The acknowledgement thread, for a reliable writer; a best-effort one has no readers
    /// that acknowledge, so each of its writes counts as acknowledged at once.
    watcher: Option<Arc<AckShared>>,
}

impl Writer {
    /// Counts a write that succeeded.
    fn count(&self, done: Result<(), BackendError>) -> Result<(), BackendError> {
        if done.is_ok() {
            match &self.watcher {
                Some(w) => w.wrote(&self.acks),
                None => {
                    let n = self.acks.written.fetch_add(1, Ordering::SeqCst) + 1;
                    self.acks.acked.store(n, Ordering::SeqCst);
                }
            }
        }
        done
    }
}

impl Drop for Writer {
    fn drop(&mut self) {
        if let Some(w) = &self.watcher {
            lock(&w.writers).remove(&self.raw.handle());
        }
    }
}

impl DdsWriter for Writer {
    fn guid(&self) -> Guid {
        self.guid
    }
    fn topic_name(&self) -> &str {
        &self.topic_name
    }
    fn little_endian(&self) -> bool {
        self.little_endian
    }
    fn key(&self) -> Option<&Arc<KeyDescriptor>> {
        self.key.as_ref()
    }
    fn write(&self, sample: Sample) -> Result<(), BackendError> {
        self.count(self.raw.write(sample.encoding.0, &sample.body, false))
    }
    fn dispose(&self, sample: &Sample) -> Result<(), BackendError> {
        let Some(k) = &self.key else {
            return Err(BackendError::InvalidInput(
                "dispose on a topic without a key".into(),
            ));
        };
        let (le, xcdr2) = (sample.little_endian(), sample.encoding.is_xcdr2());
        let key = k
            .of_sample(&sample.body, le, xcdr2)
            .or_else(|_| k.of_key_payload(&sample.body, le, xcdr2))
            .map_err(|e| {
                BackendError::InvalidInput(format!("key of a {} sample: {e}", k.ty().name))
            })?;
        self.count(self.raw.write(Encoding::cdr(le).0, &key.payload, true))
    }
    fn write_identified(
        &self,
        _sample: Sample,
        _related: Option<SampleIdentity>,
    ) -> Result<SampleIdentity, BackendError> {
        Err(BackendError::Unsupported(
            "requesters and repliers are not supported by the Cyclone DDS backend (its C API \
             cannot tell a written sample's identity nor send a related one); the worker \
             serves them through the backend `backend::for_services` makes",
        ))
    }
    fn all_acknowledged(&self) -> bool {
        self.raw.all_acknowledged()
    }
    fn writes(&self) -> u64 {
        self.acks.written.load(Ordering::SeqCst)
    }
    fn last_sequence_number(&self) -> Option<i64> {
        Some(self.raw.sequence())
    }
    fn acknowledged_writes(&self) -> u64 {
        self.acks.acked.load(Ordering::SeqCst)
    }
    fn matched_readers(&self) -> usize {
        self.raw.matched()
    }
}

struct Reader {
    // Declared before the topic: deleted first.
    raw: ffi::Reader,
    _topic: Rc<ffi::Entity>,
    guid: Guid,
    key: Option<Arc<KeyDescriptor>>,
    pending: VecDeque<Taken>,
    batch: Vec<ffi::TakenRaw>,
    /// The disposal already reported per instance (its disposed-generation count).
    announced: HashMap<u64, u32>,
    /// Disposed instances whose last sample ended a full batch (see `refill`).
    carried: Vec<ffi::TakenRaw>,
    /// The disposed-generation count of each instance's last valid sample.
    seen: HashMap<u64, u32>,
}

/// An identity nobody has: what the front-end treats as unknown.
const UNKNOWN: SampleIdentity = SampleIdentity {
    writer: [0; 16],
    sequence_number: 0,
};

/// Instances whose reported disposal is remembered (beyond, the memory starts again).
const ANNOUNCED_INSTANCES: usize = 4096;

impl Reader {
    /// Takes a batch from Cyclone and turns it into what the worker expects of a DDS
    /// reader: every sample, and a dispose as a sample of its own (key fields only, little
    /// endian) after the instance's last sample. Cyclone folds a dispose into the instance
    /// state of an unread sample instead of queueing it (it makes an invalid sample only
    /// when everything of the instance was read), so both forms are reported once per
    /// disposal. An instance left by its writers is not a sample (as with RustDDS).
    fn refill(&mut self) -> Result<(), BackendError> {
        loop {
            self.batch.clear();
            let n = self.raw.take(&mut self.batch)?;
            // Cyclone takes instance by instance: after a full batch, its last instance may
            // have samples left in Cyclone, so that instance's dispose waits for the next
            // batch, which either has more of the instance (and decides) or not (then it is
            // reported first thing, still after the instance's last sample).
            let full = n >= ffi::TAKE_BATCH;
            let last_instance = self.batch.last().map(|t| t.instance);
            for c in std::mem::take(&mut self.carried) {
                if !self.batch.iter().any(|u| u.instance == c.instance) {
                    self.report_dispose(&c, c.disposed_generation);
                }
            }
            for i in 0..self.batch.len() {
                let t = self.batch[i].clone();
                if t.valid {
                    self.saw_valid(&t);
                    let identity = match t.writer {
                        Some(writer) if t.sequence > 0 => SampleIdentity {
                            writer,
                            sequence_number: t.sequence,
                        },
                        _ => UNKNOWN,
                    };
                    self.pending.push_back(Taken {
                        sample: Sample {
                            encoding: Encoding(t.encoding),
                            body: Bytes::from(t.body.clone()),
                        },
                        identity,
                        related: None,
                        disposed: false,
                        unregistered: false,
                    });
                }
                let last_of_instance =
                    !self.batch[i + 1..].iter().any(|u| u.instance == t.instance);
                if !(t.disposed && last_of_instance) {
                    continue;
                }
                if full && t.valid && Some(t.instance) == last_instance {
                    self.carried.push(t);
                } else {
                    self.report_dispose(&t, t.disposed_generation);
                }
            }
            // Everything taken was left out (instances left by their writers, say) while
            // more may wait: take again rather than report "empty".
            if !self.pending.is_empty() || !full {
                return Ok(());
            }
        }
    }

    /// Before valid sample `t` is reported: an instance disposed and written again between
    /// two looks shows only its new generation, so a disposal not seen yet is reported now,
    /// before the sample that revived it; and a handle Cyclone gave a new instance (the
    /// generation starts again) forgets the old one's reported disposal.
    fn saw_valid(&mut self, t: &ffi::TakenRaw) {
        if let Some(&g) = self.seen.get(&t.instance) {
            if t.disposed_generation > g {
                self.report_dispose(t, g);
            }
        }
        // Samples of a reported generation all came before its report (later ones belong to
        // a newer generation), so one at or below it is of a new instance under the handle.
        if self
            .announced
            .get(&t.instance)
            .is_some_and(|&a| t.disposed_generation <= a)
        {
            self.announced.remove(&t.instance);
        }
        if self.seen.len() >= ANNOUNCED_INSTANCES {
            self.seen.clear();
        }
        self.seen.insert(t.instance, t.disposed_generation);
    }

    /// Reports the disposal of `t`'s instance that ended its `generation`, once.
    fn report_dispose(&mut self, t: &ffi::TakenRaw, generation: u32) {
        if self.announced.get(&t.instance) == Some(&generation) {
            return;
        }
        if self.announced.len() >= ANNOUNCED_INSTANCES {
            self.announced.clear();
        }
        self.announced.insert(t.instance, generation);
        let enc = Encoding(t.encoding);
        let payload = self.key.as_ref().and_then(|k| {
            k.of_received(&t.body, enc.little_endian(), enc.is_xcdr2(), !t.valid)
                .ok()
        });
        // Cyclone builds an invalid sample from the instance's key, not from the dispose
        // message: there is no sequence number of the dispose to tell.
        self.pending.push_back(Taken {
            sample: Sample {
                encoding: Encoding::CDR_LE,
                body: payload.map(|k| Bytes::from(k.payload)).unwrap_or_default(),
            },
            identity: UNKNOWN,
            related: None,
            disposed: true,
            unregistered: false,
        });
    }
}

impl DdsReader for Reader {
    fn guid(&self) -> Guid {
        self.guid
    }
    fn take_next(&mut self) -> Result<Option<Taken>, BackendError> {
        if self.pending.is_empty() {
            self.refill()?;
        }
        Ok(self.pending.pop_front())
    }
}

impl Endpoints for Cyclone {
    type Publisher = Group;
    type Subscriber = Group;

    fn new_publisher(&mut self, domain: u16, partitions: &[String]) -> Result<Group, BackendError> {
        self.group(domain, true, partitions)
    }

    fn new_subscriber(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Group, BackendError> {
        self.group(domain, false, partitions)
    }

    fn new_writer(
        &mut self,
        g: &Group,
        _domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError> {
        let topic = self.topic(g, spec)?;
        let raw = ffi::Writer::new(g.entity.handle(), &topic, &qos::to_cyclone(qos)?)?;
        let reliable = qos.reliability == xrce_dds_seam::policies::Reliability::Reliable;
        let (acks, watcher) = if reliable {
            (
                self.acks.watch(raw.handle()),
                Some(self.acks.shared.clone()),
            )
        } else {
            (Arc::new(WriterAcks::default()), None)
        };
        Ok(Box::new(Writer {
            acks,
            watcher,
            guid: raw.guid()?,
            raw,
            _topic: topic,
            topic_name: spec.name.clone(),
            little_endian,
            key: spec.key.clone(),
        }))
    }

    fn new_reader(
        &mut self,
        g: &Group,
        _domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError> {
        let topic = self.topic(g, spec)?;
        let raw = ffi::Reader::new(
            g.entity.handle(),
            &topic,
            &qos::to_cyclone(qos)?,
            &self.readiness,
            token,
        )?;
        Ok(Box::new(Reader {
            guid: raw.guid()?,
            raw,
            _topic: topic,
            key: spec.key.clone(),
            pending: VecDeque::new(),
            batch: Vec::new(),
            announced: HashMap::new(),
            carried: Vec::new(),
            seen: HashMap::new(),
        }))
    }
}

impl DdsBackend for Cyclone {
    fn name(&self) -> &'static str {
        "cyclone"
    }

    fn supports_partitions(&self) -> bool {
        true
    }

    fn delivers_locally_in_write_order(&self) -> bool {
        // A local reader gets the sample inside `dds_writecdr`, in the reader's history in
        // arrival order for a topic without a key.
        true
    }

    fn supports_services(&self) -> bool {
        false
    }

    fn participant_guid(&mut self, domain: u16) -> Result<Guid, BackendError> {
        self.participant(domain)?.guid()
    }

    fn readiness_fd(&self) -> BorrowedFd<'_> {
        self.readiness.fd()
    }

    fn ready_readers(&mut self, out: &mut Vec<ReaderToken>) -> std::io::Result<()> {
        self.readiness.drain(out);
        Ok(())
    }

    fn readers_queued(&self) -> bool {
        self.readiness.has_queued()
    }

    fn participants(&self) -> usize {
        self.participants.len()
    }

    fn participant_domains(&self) -> Vec<u16> {
        let mut d: Vec<u16> = self.participants.keys().copied().collect();
        d.sort_unstable();
        d
    }

    fn release_domain(&mut self, domain: u16) {
        // The last reference deletes the participant and the domain made for it (with the
        // domain's threads and sockets, `ffi::Participant`).
        if self.participants.remove(&domain).is_some() {
            tracing::info!(domain, "Cyclone DDS participant released");
        }
        self.topics
            .retain(|(d, ..), t| *d != domain && t.strong_count() > 0);
    }
}

#[cfg(test)]
mod tests;
