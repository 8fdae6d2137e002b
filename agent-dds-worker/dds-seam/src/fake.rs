//! An in-memory backend for the worker's unit tests: a writer delivers each sample at once
//! to every live reader of the same domain and topic name, and the test inspects what was
//! made, written and deleted through a [`FakeBus`] handle.

use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::os::fd::{AsFd, BorrowedFd};
use std::os::unix::net::UnixStream;
use std::rc::Rc;
use std::sync::Arc;

use crate::types::KeyDescriptor;
use crate::{
    BackendError, DdsBackend, DdsReader, DdsWriter, EndpointQos, Endpoints, Guid, ReaderToken,
    Sample, SampleIdentity, Taken, TopicSpec,
};

/// What a fake writer did.
#[derive(Debug, Clone)]
pub struct Written {
    /// The writer's GUID.
    pub writer: Guid,
    /// Its topic.
    pub topic: String,
    /// The sample (for a dispose, what was given).
    pub sample: Sample,
    /// A dispose rather than a write.
    pub dispose: bool,
}

#[derive(Debug)]
struct ReaderSlot {
    id: u32,
    domain: u16,
    topic: String,
    token: ReaderToken,
    queue: Rc<RefCell<VecDeque<Taken>>>,
}

/// The shared state of a fake backend, which tests look into.
#[derive(Debug, Default)]
pub struct FakeBus {
    /// Which fake backend this is (in the GUIDs: two fakes, as two DDS participants, never
    /// share one).
    number: u32,
    next_id: Cell<u32>,
    readers: RefCell<Vec<ReaderSlot>>,
    live_writers: RefCell<Vec<(u32, u16, String)>>,
    /// Everything written, in order.
    pub written: RefCell<Vec<Written>>,
    /// Writers made so far (deleted ones included).
    pub writers_made: Cell<usize>,
    /// Readers made so far (deleted ones included).
    pub readers_made: Cell<usize>,
    ready: RefCell<Vec<ReaderToken>>,
    /// What `all_acknowledged` answers.
    pub acknowledged: Cell<bool>,
    /// The domains with a participant now, in the order they were made.
    pub domains: RefCell<Vec<u16>>,
    /// Domains whose participant was released, in order.
    pub released: RefCell<Vec<u16>>,
    /// Every endpoint made: its topic and the QoS it was given.
    pub endpoints: RefCell<Vec<(String, EndpointQos)>>,
    /// Writes reach no reader (as with readers in other partitions, or of incompatible QoS).
    pub unheard: Cell<bool>,
}

impl FakeBus {
    fn next(&self) -> u32 {
        let id = self.next_id.get() + 1;
        self.next_id.set(id);
        id
    }

    fn guid(&self, id: u32) -> Guid {
        let mut g = [0xfa; 16];
        g[8..12].copy_from_slice(&self.number.to_be_bytes());
        g[12..].copy_from_slice(&id.to_be_bytes());
        g
    }

    /// Live readers of a topic (in any domain).
    pub fn readers_of(&self, topic: &str) -> usize {
        self.readers
            .borrow()
            .iter()
            .filter(|r| r.topic == topic)
            .count()
    }

    /// Live writers and readers in `domain`.
    pub fn endpoints_in(&self, domain: u16) -> usize {
        let readers = self
            .readers
            .borrow()
            .iter()
            .filter(|r| r.domain == domain)
            .count();
        let writers = self
            .live_writers
            .borrow()
            .iter()
            .filter(|w| w.1 == domain)
            .count();
        readers + writers
    }

    /// Live writers of a topic (in any domain).
    pub fn writers_of(&self, topic: &str) -> usize {
        self.live_writers
            .borrow()
            .iter()
            .filter(|w| w.2 == topic)
            .count()
    }

    /// The samples written on `topic`, in order (disposes excluded).
    pub fn samples_on(&self, topic: &str) -> Vec<Vec<u8>> {
        self.written
            .borrow()
            .iter()
            .filter(|w| w.topic == topic && !w.dispose)
            .map(|w| w.sample.body.to_vec())
            .collect()
    }

    /// Delivers a sample from outside the agent (another DDS application) to the readers
    /// of `topic` in `domain`.
    pub fn inject(&self, domain: u16, topic: &str, taken: impl Fn() -> Taken) {
        for r in self.readers.borrow().iter() {
            if r.domain == domain && r.topic == topic {
                r.queue.borrow_mut().push_back(taken());
                self.ready.borrow_mut().push(r.token);
            }
        }
    }
}

/// The fake backend.
#[derive(Debug)]
pub struct Fake {
    bus: Rc<FakeBus>,
    /// Never written: the worker's loop is not run over the fake.
    wake: (UnixStream, UnixStream),
}

impl Fake {
    /// A fake backend and the handle tests inspect it with.
    pub fn new() -> std::io::Result<(Self, Rc<FakeBus>)> {
        static MADE: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let bus = Rc::new(FakeBus {
            number: MADE.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            acknowledged: Cell::new(true),
            ..FakeBus::default()
        });
        Ok((
            Fake {
                bus: bus.clone(),
                wake: UnixStream::pair()?,
            },
            bus,
        ))
    }
}

/// A fake publisher or subscriber: nothing to hold.
#[derive(Debug)]
pub struct Group;

struct Writer {
    bus: Rc<FakeBus>,
    id: u32,
    domain: u16,
    topic: String,
    little_endian: bool,
    key: Option<Arc<KeyDescriptor>>,
    /// Writes made (the last sequence number).
    seq: Cell<i64>,
    /// Writes known acknowledged.
    acked: Cell<u64>,
}

impl Drop for Writer {
    fn drop(&mut self) {
        self.bus
            .live_writers
            .borrow_mut()
            .retain(|w| w.0 != self.id);
    }
}

impl Writer {
    fn publish(
        &self,
        sample: Sample,
        dispose: bool,
        related: Option<SampleIdentity>,
    ) -> SampleIdentity {
        let seq = self.seq.get() + 1;
        self.seq.set(seq);
        let identity = SampleIdentity {
            writer: self.bus.guid(self.id),
            sequence_number: seq,
        };
        self.bus.written.borrow_mut().push(Written {
            writer: identity.writer,
            topic: self.topic.clone(),
            sample: sample.clone(),
            dispose,
        });
        if self.bus.unheard.get() {
            return identity;
        }
        self.bus.inject(self.domain, &self.topic, || Taken {
            sample: sample.clone(),
            identity,
            related,
            disposed: dispose,
            unregistered: false,
        });
        identity
    }
}

impl DdsWriter for Writer {
    fn guid(&self) -> Guid {
        self.bus.guid(self.id)
    }
    fn topic_name(&self) -> &str {
        &self.topic
    }
    fn little_endian(&self) -> bool {
        self.little_endian
    }
    fn key(&self) -> Option<&Arc<KeyDescriptor>> {
        self.key.as_ref()
    }
    fn write(&self, sample: Sample) -> Result<(), BackendError> {
        self.publish(sample, false, None);
        Ok(())
    }
    fn dispose(&self, sample: &Sample) -> Result<(), BackendError> {
        if self.key.is_none() {
            return Err(BackendError::InvalidInput(
                "dispose on a topic without a key".into(),
            ));
        }
        self.publish(sample.clone(), true, None);
        Ok(())
    }
    fn write_identified(
        &self,
        sample: Sample,
        related: Option<SampleIdentity>,
    ) -> Result<SampleIdentity, BackendError> {
        Ok(self.publish(sample, false, related))
    }
    fn all_acknowledged(&self) -> bool {
        self.bus.acknowledged.get()
    }
    fn writes(&self) -> u64 {
        self.seq.get() as u64
    }
    fn last_sequence_number(&self) -> Option<i64> {
        Some(self.seq.get())
    }
    fn acknowledged_writes(&self) -> u64 {
        if self.bus.acknowledged.get() {
            self.acked.set(self.seq.get() as u64);
        }
        self.acked.get()
    }
    fn matched_readers(&self) -> usize {
        self.bus
            .readers
            .borrow()
            .iter()
            .filter(|r| r.domain == self.domain && r.topic == self.topic)
            .count()
    }
}

struct Reader {
    bus: Rc<FakeBus>,
    id: u32,
    queue: Rc<RefCell<VecDeque<Taken>>>,
}

impl Drop for Reader {
    fn drop(&mut self) {
        self.bus.readers.borrow_mut().retain(|r| r.id != self.id);
    }
}

impl DdsReader for Reader {
    fn guid(&self) -> Guid {
        self.bus.guid(self.id)
    }
    fn take_next(&mut self) -> Result<Option<Taken>, BackendError> {
        Ok(self.queue.borrow_mut().pop_front())
    }
}

impl Endpoints for Fake {
    type Publisher = Group;
    type Subscriber = Group;

    fn new_publisher(
        &mut self,
        domain: u16,
        _partitions: &[String],
    ) -> Result<Group, BackendError> {
        self.enter(domain);
        Ok(Group)
    }

    fn new_subscriber(
        &mut self,
        domain: u16,
        _partitions: &[String],
    ) -> Result<Group, BackendError> {
        self.enter(domain);
        Ok(Group)
    }

    fn new_writer(
        &mut self,
        _publisher: &Group,
        domain: u16,
        topic: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError> {
        self.bus
            .endpoints
            .borrow_mut()
            .push((topic.name.clone(), *qos));
        let id = self.bus.next();
        self.bus
            .live_writers
            .borrow_mut()
            .push((id, domain, topic.name.clone()));
        self.bus.writers_made.set(self.bus.writers_made.get() + 1);
        Ok(Box::new(Writer {
            bus: self.bus.clone(),
            id,
            domain,
            topic: topic.name.clone(),
            little_endian,
            key: topic.key.clone(),
            seq: Cell::new(0),
            acked: Cell::new(0),
        }))
    }

    fn new_reader(
        &mut self,
        _subscriber: &Group,
        domain: u16,
        topic: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError> {
        self.bus
            .endpoints
            .borrow_mut()
            .push((topic.name.clone(), *qos));
        let id = self.bus.next();
        let queue = Rc::new(RefCell::new(VecDeque::new()));
        self.bus.readers.borrow_mut().push(ReaderSlot {
            id,
            domain,
            topic: topic.name.clone(),
            token,
            queue: queue.clone(),
        });
        self.bus.readers_made.set(self.bus.readers_made.get() + 1);
        Ok(Box::new(Reader {
            bus: self.bus.clone(),
            id,
            queue,
        }))
    }
}

impl Fake {
    /// Notes a domain the worker made a group in.
    fn enter(&self, domain: u16) {
        if !self.bus.domains.borrow().contains(&domain) {
            self.bus.domains.borrow_mut().push(domain);
        }
    }
}

impl DdsBackend for Fake {
    fn name(&self) -> &'static str {
        "fake"
    }

    fn delivers_locally_in_write_order(&self) -> bool {
        // Published samples reach the bus's readers inside the write, in order.
        true
    }

    fn participant_guid(&mut self, domain: u16) -> Result<Guid, BackendError> {
        let mut g = [0xfb; 16];
        g[8..12].copy_from_slice(&self.bus.number.to_be_bytes());
        g[14..].copy_from_slice(&domain.to_be_bytes());
        Ok(g)
    }

    fn readiness_fd(&self) -> BorrowedFd<'_> {
        self.wake.0.as_fd()
    }

    fn ready_readers(&mut self, out: &mut Vec<ReaderToken>) -> std::io::Result<()> {
        out.append(&mut self.bus.ready.borrow_mut());
        Ok(())
    }

    /// Its readers get their samples inside the process, with no wake-up: a loop over the
    /// fake (a simulation) learns of them here.
    fn readers_queued(&self) -> bool {
        !self.bus.ready.borrow().is_empty()
    }

    fn participants(&self) -> usize {
        self.bus.domains.borrow().len()
    }

    fn participant_domains(&self) -> Vec<u16> {
        let mut d = self.bus.domains.borrow().clone();
        d.sort_unstable();
        d
    }

    fn release_domain(&mut self, domain: u16) {
        let mut domains = self.bus.domains.borrow_mut();
        if domains.contains(&domain) {
            domains.retain(|d| *d != domain);
            self.bus.released.borrow_mut().push(domain);
        }
    }
}

/// A keyed test type: `id` (int32, the key) and `value` (int32).
pub const KEYED: &str = r#"<dds><types><struct name="Keyed">
    <member name="id" key="true" type="int32"/>
    <member name="value" type="int32"/>
  </struct></types></dds>"#;

/// A sample body of [`KEYED`], little endian.
pub fn keyed(id: i32, value: i32) -> Vec<u8> {
    [id.to_le_bytes(), value.to_le_bytes()].concat()
}

/// A topic of [`KEYED`] named `name`.
pub fn keyed_spec(name: &str) -> TopicSpec {
    let ty = crate::types::TypeSet::parse(KEYED).expect("type");
    let key = Arc::new(KeyDescriptor::new(ty.get("Keyed").expect("Keyed")).expect("key"));
    TopicSpec {
        name: name.into(),
        type_name: "Keyed".into(),
        key: Some(key),
    }
}
