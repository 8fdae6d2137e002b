//! Simulation tests of the front-end's relay: a client, the session core and the relay
//! exchange in one thread with a fake worker that answers as the real one does, over an
//! in-memory link (no shared memory): what a new worker generation gets replayed (objects in
//! creation order, reads, retained writes, but not the writes DDS readers acknowledged),
//! that a replayed read does not deliver a sample its client had, and how best-effort
//! writes share the window, and that a relay that took sessions over takes no client message
//! before the worker answered its hello.

use std::cell::{Cell, RefCell};
use std::time::{Duration, Instant};

use xrce_common::session::agent::{Agent, AgentConfig};
use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind as k, status, stream_id, ClientKey, DataDeliveryControl, ObjectId, ObjectVariant,
    ReadSpecification, Representation, ResultStatus, VariantExtra,
};
use xrce_frontend::relay::link::MemoryLink;
use xrce_frontend::relay::Relay;
use xrce_ipc::{
    Encode, Reply, ReplyMessage, Request, RequestMessage, Route, Sample, SampleIdentity,
    SampleOrigin, WriteOrigin,
};

#[path = "relay/flow.rs"]
mod flow;
#[path = "relay/link.rs"]
mod link;

const ADDR: u32 = 7;

/// A request as the fake worker took it.
type Served = RequestMessage<'static>;

/// Whether `m` is a request of kind `name` (one of [`Request::name`]'s).
fn is(m: &Served, name: &str) -> bool {
    const KINDS: [&str; 9] = [
        "FrontendHello",
        "Create",
        "Delete",
        "Write",
        "Read",
        "DeleteClient",
        "PauseRead",
        "ResumeRead",
        "ReplayDone",
    ];
    assert!(KINDS.contains(&name), "no request kind {name}");
    m.request.name() == name
}

/// Whether `m` is part of a replay to a new worker.
fn replayed(m: &Served) -> bool {
    matches!(
        m.request,
        Request::Create { replay: true, .. } | Request::Read { replay: true, .. }
    )
}

/// A read of every sample, on the built-in reliable stream.
fn unlimited_read() -> ReadSpecification {
    ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// The sample a write carries (empty for other kinds).
fn written(m: &Served) -> &[u8] {
    match &m.request {
        Request::Write { data, .. } => data,
        _ => &[],
    }
}

/// The worker's side of the IPC contract, driven by the test: it takes what the relay sent
/// over the rig's link and answers as the real worker does.
struct FakeWorker {
    generation: u32,
    /// Whether progress reports the writes as acknowledged by DDS readers.
    acknowledge: Cell<bool>,
    /// Its announcement reached the relay.
    announced: Cell<bool>,
    /// The relay said hello to it: requests sent before (to a worker that died) are not
    /// served, as the real worker drops them.
    greeted: Cell<bool>,
    /// Replies not yet handed to the relay.
    replies: RefCell<Vec<Vec<u8>>>,
    /// Refuses replayed objects as a worker does whose predecessor died replaying them.
    refuse_replays: Cell<bool>,
}

impl FakeWorker {
    fn start(generation: u32) -> Self {
        FakeWorker {
            generation,
            acknowledge: Cell::new(false),
            announced: Cell::new(false),
            greeted: Cell::new(false),
            replies: RefCell::new(Vec::new()),
            refuse_replays: Cell::new(false),
        }
    }

    fn reply(&self, mut route: Route, reply: Reply<'_>) {
        route.generation = self.generation;
        self.replies
            .borrow_mut()
            .push(ReplyMessage::new(route, reply).encode());
    }

    /// Every request so far; answers each as the real worker does (a WorkerHello for a
    /// FrontendHello, STATUS OK for creations, reads, deletes), then reports progress.
    fn serve(&self, rig: &mut Rig) -> Vec<Served> {
        let mut got = Vec::new();
        for m in rig.relay.link_mut().take() {
            let m = RequestMessage::decode(&m)
                .expect("IPC request")
                .into_owned();
            if m.request == Request::FrontendHello {
                self.greeted.set(true);
            } else if !self.greeted.get() {
                continue;
            }
            got.push(m);
        }
        let mut last = 0;
        for m in &got {
            last = last.max(m.route.op_seq);
            let replay = replayed(m);
            match m.request {
                Request::FrontendHello => {
                    self.reply(Route::frontend(m.route.frontend_id), Reply::WorkerHello)
                }
                Request::Create { .. } if replay && self.refuse_replays.get() => self.reply(
                    m.route,
                    Reply::Status {
                        result: ResultStatus {
                            status: status::ERR_RESOURCES,
                            implementation_status: xrce_ipc::REPLAY_REFUSED,
                        },
                        replay,
                    },
                ),
                Request::Create { .. } | Request::Delete | Request::Read { .. } => self.reply(
                    m.route,
                    Reply::Status {
                        result: Default::default(),
                        replay,
                    },
                ),
                _ => {}
            }
        }
        if last > 0 {
            // Executed through `last`; acknowledged through `last` or nothing.
            let acknowledged = if self.acknowledge.get() { last } else { 0 };
            let route = Route {
                op_seq: last,
                ..Route::default()
            };
            self.reply(
                route,
                Reply::Progress {
                    executed: last,
                    acknowledged,
                },
            );
        }
        got
    }

    /// A sample for `client`'s read of `reader`.
    fn sample(
        &self,
        client: ClientKey,
        reader: ObjectId,
        read: Route,
        identity: SampleIdentity,
        data: &[u8],
    ) {
        self.sample_from(client, reader, read, identity, None, data);
    }

    /// A sample for `client`'s read of `reader`, of a client write's `origin`.
    fn sample_from(
        &self,
        client: ClientKey,
        reader: ObjectId,
        read: Route,
        identity: SampleIdentity,
        origin: Option<SampleOrigin>,
        data: &[u8],
    ) {
        let route = Route::object(0, client, read.request_id, reader);
        let sample = Sample {
            identity,
            origin,
            data: data.into(),
            little_endian: true,
            disposed: false,
            unregistered: false,
        };
        self.reply(route, Reply::Sample(sample));
    }
}

/// A client, the session core and the relay, exchanging until `done` or `d`.
struct Rig {
    client: Client,
    agent: Agent<u32>,
    relay: Relay<MemoryLink>,
    events: Vec<ClientEvent>,
}

impl Rig {
    /// A client with a participant, a subscriber and a reader, reading it without limits on
    /// a worker of `generation`: the worker, the rig, the reader and the read's route.
    fn reading(generation: u32) -> (FakeWorker, Self, ObjectId, Route) {
        let worker = FakeWorker::start(generation);
        let mut rig = Rig::connected(&worker, generation);
        let p = ObjectId::new(1, k::PARTICIPANT);
        let sb = ObjectId::new(1, k::SUBSCRIBER);
        let rd = ObjectId::new(1, k::DATAREADER);
        rig.create(p, k::PARTICIPANT, "<dds/>", VariantExtra::DomainId(0));
        rig.create(sb, k::SUBSCRIBER, "", VariantExtra::Parent(p));
        rig.create(rd, k::DATAREADER, "<dds/>", VariantExtra::Parent(sb));
        let spec = unlimited_read();
        rig.client.read(Instant::now(), rd, spec).expect("read");
        let read = rig.read_replayed_on(&worker);
        (worker, rig, rd, read)
    }

    /// Runs until `worker` got the client's read (replayed, or the first); its route.
    fn read_replayed_on(&mut self, worker: &FakeWorker) -> Route {
        let served = self.run(&[worker], |_, s| s.iter().any(|m| is(m, "Read")));
        served
            .iter()
            .find(|m| is(m, "Read"))
            .map(|m| m.route)
            .expect("a read")
    }

    /// The first byte of each sample the client got, in order.
    fn first_bytes_delivered(&self) -> Vec<u8> {
        self.events
            .iter()
            .filter_map(|e| match e {
                ClientEvent::Data { data, .. } => data.first().copied(),
                _ => None,
            })
            .collect()
    }

    fn new() -> Self {
        Rig {
            client: Client::new(ClientConfig::new(ClientKey([0xB2, 0, 0, 1]))),
            agent: Agent::new(AgentConfig::default()),
            relay: Relay::new(0, 1, MemoryLink::default()),
            events: Vec::new(),
        }
    }

    /// Hands the relay what `workers` announced and answered.
    fn poll_ipc(&mut self, now: Instant, workers: &[&FakeWorker]) {
        for w in workers {
            if !w.announced.replace(true) {
                let hello = ReplyMessage::new(
                    Route {
                        generation: w.generation,
                        ..Route::default()
                    },
                    Reply::WorkerHello,
                );
                self.relay.handle_announcement(&hello.encode());
            }
            for m in w.replies.take() {
                self.relay.handle_reply(now, &m, &mut self.agent);
            }
        }
        self.relay.after_replies(now, &mut self.agent);
    }

    /// One round: datagrams both ways, the relay's IPC, timers.
    fn step(&mut self, workers: &[&FakeWorker], served: &mut Vec<Served>) {
        let now = Instant::now();
        self.deliver(now);
        self.relay.pump();
        for w in workers {
            served.extend(w.serve(self));
        }
        self.poll_ipc(now, workers);
        self.relay.pump();
        self.agent.handle_timeout(now, &mut self.relay);
        while let Some(t) = self.agent.poll_transmit() {
            self.client.handle_datagram(now, &t.data);
        }
        self.client.handle_timeout(now);
        self.events
            .extend(std::iter::from_fn(|| self.client.poll_event()));
    }

    fn run(
        &mut self,
        workers: &[&FakeWorker],
        mut done: impl FnMut(&Rig, &[Served]) -> bool,
    ) -> Vec<Served> {
        let mut served = Vec::new();
        let end = Instant::now() + Duration::from_secs(10);
        while Instant::now() < end {
            self.step(workers, &mut served);
            if done(self, &served) {
                return served;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        panic!(
            "not done within 10 s; served {:?}",
            served.iter().map(|m| m.request.name()).collect::<Vec<_>>()
        );
    }

    /// A rig whose relay sees `worker` (generation `generation`) and whose client is
    /// connected.
    fn connected(worker: &FakeWorker, generation: u32) -> Self {
        let mut rig = Rig::new();
        rig.run(&[worker], |r, _| r.relay.generation() == Some(generation));
        rig.client.connect(Instant::now());
        rig.run(&[worker], |r, _| r.client.is_connected());
        rig
    }

    /// A worker, and a rig connected to it whose relay hands every operation over at once
    /// (as in a front-end that stores its sessions: nothing waits in the outbox), with a
    /// data writer the worker has created (its id).
    fn handing_over_with_writer(generation: u32) -> (FakeWorker, Self, ObjectId) {
        let worker = FakeWorker::start(generation);
        let mut rig = Rig::connected(&worker, generation);
        rig.relay.set_hand_over_at_once(true);
        let [.., w] = rig.create_writer();
        rig.run(&[&worker], |_, s| {
            s.iter().filter(|m| is(m, "Create")).count() == 4
        });
        (worker, rig, w)
    }

    /// Creates a participant, a topic, a publisher and a data writer (their ids, in that
    /// order).
    fn create_writer(&mut self) -> [ObjectId; 4] {
        let p = ObjectId::new(1, k::PARTICIPANT);
        let t = ObjectId::new(1, k::TOPIC);
        let pb = ObjectId::new(1, k::PUBLISHER);
        let w = ObjectId::new(1, k::DATAWRITER);
        self.create(p, k::PARTICIPANT, "<dds/>", VariantExtra::DomainId(0));
        self.create(t, k::TOPIC, "<dds/>", VariantExtra::Parent(p));
        self.create(pb, k::PUBLISHER, "", VariantExtra::Parent(p));
        self.create(w, k::DATAWRITER, "<dds/>", VariantExtra::Parent(pb));
        [p, t, pb, w]
    }

    fn create(&mut self, id: ObjectId, kind: u8, xml: &str, extra: VariantExtra) {
        let v = ObjectVariant {
            kind,
            representation: Representation::Xml(xml.into()),
            extra,
        };
        self.client
            .create(Instant::now(), id, v, false, true)
            .expect("create");
    }
}

#[test]
fn a_new_worker_gets_the_objects_in_order_then_the_reads_then_the_retained_writes() {
    let first = FakeWorker::start(11);
    let mut rig = Rig::connected(&first, 11);
    let [p, t, pb, w] = rig.create_writer();
    let sb = ObjectId::new(1, k::SUBSCRIBER);
    let rd = ObjectId::new(1, k::DATAREADER);
    rig.create(sb, k::SUBSCRIBER, "", VariantExtra::Parent(p));
    rig.create(rd, k::DATAREADER, "<dds/>", VariantExtra::Parent(sb));
    let served = rig.run(&[&first], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 6
    });
    assert!(!served.iter().any(replayed));
    let spec = unlimited_read();
    rig.client.read(Instant::now(), rd, spec).expect("read");
    rig.client
        .write(Instant::now(), stream_id::BUILTIN_RELIABLE, w, b"kept")
        .expect("write");
    let first_sent = rig.run(&[&first], |_, s| {
        s.iter().any(|m| is(m, "Read")) && s.iter().any(|m| is(m, "Write"))
    });
    let first_write = first_sent
        .iter()
        .find(|m| is(m, "Write"))
        .expect("the write sent");
    assert!(
        matches!(
            first_write.request,
            Request::Write {
                resend_of: None,
                ..
            }
        ),
        "a first send is no resend"
    );
    // The worker dies; a new generation announces itself.
    drop(first);
    let second = FakeWorker::start(12);
    let replay = rig.run(&[&second], |_, s| s.iter().any(|m| is(m, "Write")));
    let kinds: Vec<(&str, ObjectId)> = replay
        .iter()
        .map(|m| (m.request.name(), m.route.object_id))
        .collect();
    assert_eq!(kinds[0].0, "FrontendHello", "{kinds:?}");
    let creates: Vec<ObjectId> = kinds
        .iter()
        .filter(|(kind, _)| *kind == "Create")
        .map(|(_, o)| *o)
        .collect();
    assert_eq!(creates, [p, t, pb, w, sb, rd], "creation order");
    assert!(replay.iter().filter(|m| is(m, "Create")).all(replayed));
    let pos = |kind: &str| kinds.iter().position(|(k2, _)| *k2 == kind);
    let last_create = kinds
        .iter()
        .rposition(|(kind, _)| *kind == "Create")
        .expect("creates");
    assert!(pos("Read").is_some_and(|r| r > last_create), "{kinds:?}");
    let write = replay
        .iter()
        .find(|m| is(m, "Write"))
        .expect("the retained write resent");
    assert!(written(write).ends_with(b"kept"));
    // Resent under a new operation number, it names its first one: its origin.
    assert!(
        matches!(write.request, Request::Write { resend_of: Some(n), .. } if n == first_write.route.op_seq),
        "{:?}",
        write.request
    );
    assert!(write.route.op_seq > first_write.route.op_seq);
    assert!(pos("Write") > pos("Read"), "{kinds:?}");
    assert_eq!(rig.relay.stats().replays, 2);
    assert!(rig.relay.stats().writes_resent >= 1);
    // Not acknowledged by the second worker either: resent to a third, it still names its
    // first send.
    drop(second);
    let third = FakeWorker::start(13);
    let again = rig.run(&[&third], |_, s| s.iter().any(|m| is(m, "Write")));
    let write = again
        .iter()
        .find(|m| is(m, "Write"))
        .expect("the retained write resent again");
    assert!(
        matches!(write.request, Request::Write { resend_of: Some(n), .. } if n == first_write.route.op_seq),
        "{:?}",
        write.request
    );
    drop((rig, third));
}

#[test]
fn a_replayed_read_does_not_deliver_a_sample_twice() {
    let (first, mut rig, rd, read) = Rig::reading(21);
    let writer = [0x42u8; 16];
    let at = |n: i64| SampleIdentity {
        writer,
        sequence_number: n,
    };
    for n in 1..=3 {
        first.sample(rig.client.config().key, rd, read, at(n), &[n as u8]);
    }
    rig.run(&[&first], |r, _| r.first_bytes_delivered().len() == 3);
    // A new worker; the writer outlived the old one and offers its history again, then a
    // new sample.
    drop(first);
    let second = FakeWorker::start(22);
    let read = rig.read_replayed_on(&second);
    for n in 1..=4 {
        second.sample(rig.client.config().key, rd, read, at(n), &[n as u8]);
    }
    // Samples of a writer never seen, and of unknown identity, are delivered.
    second.sample(
        rig.client.config().key,
        rd,
        read,
        SampleIdentity {
            writer: [7; 16],
            sequence_number: 1,
        },
        &[70],
    );
    second.sample(
        rig.client.config().key,
        rd,
        read,
        SampleIdentity::default(),
        &[80],
    );
    rig.run(&[&second], |r, _| r.first_bytes_delivered().len() >= 6);
    assert_eq!(
        rig.first_bytes_delivered(),
        [1, 2, 3, 4, 70, 80],
        "delivered twice or lost"
    );
    assert_eq!(rig.relay.stats().samples_already_delivered, 3);
    drop((rig, second));
}

/// A worker that died after it handed a read the samples of two writes, before their
/// publisher heard that they were taken: the publisher resends them to the new worker, whose
/// new DDS writer publishes them again under another identity. Their origin (the client
/// write) is the same, so the read delivers neither twice; a resent write the read had not
/// delivered, and samples without an origin, are delivered.
#[test]
fn a_resent_write_the_read_delivered_before_the_worker_died_is_not_delivered_again() {
    let (first, mut rig, rd, read) = Rig::reading(31);
    let key = rig.client.config().key;
    let origin = |write: u64, index: u32, resent: bool| {
        Some(SampleOrigin {
            write: WriteOrigin {
                frontend: 9,
                incarnation: 1,
                write,
                index,
            },
            resent,
        })
    };
    let identity = |writer: u8, n: i64| SampleIdentity {
        writer: [writer; 16],
        sequence_number: n,
    };
    // Write 5, then write 6 of two samples.
    first.sample_from(key, rd, read, identity(1, 1), origin(5, 0, false), &[50]);
    first.sample_from(key, rd, read, identity(1, 2), origin(6, 0, false), &[60]);
    first.sample_from(key, rd, read, identity(1, 3), origin(6, 1, false), &[61]);
    rig.run(&[&first], |r, _| r.first_bytes_delivered().len() == 3);
    drop(first);
    let second = FakeWorker::start(32);
    let read = rig.read_replayed_on(&second);
    // Writes 6 and 7 resent (7 never reached the read), then a new write 8.
    second.sample_from(key, rd, read, identity(2, 1), origin(6, 0, true), &[60]);
    second.sample_from(key, rd, read, identity(2, 2), origin(6, 1, true), &[61]);
    second.sample_from(key, rd, read, identity(2, 3), origin(7, 0, true), &[70]);
    second.sample_from(key, rd, read, identity(2, 4), origin(8, 0, false), &[80]);
    second.sample(key, rd, read, SampleIdentity::default(), &[90]);
    rig.run(&[&second], |r, _| r.first_bytes_delivered().len() >= 6);
    assert_eq!(
        rig.first_bytes_delivered(),
        [50, 60, 61, 70, 80, 90],
        "delivered twice or lost"
    );
    let stats = rig.relay.stats();
    assert_eq!(stats.resent_samples_already_delivered, 2);
    assert_eq!(stats.samples_already_delivered, 2);
    drop((rig, second));
}

/// A reader deleted and created again under the same id is another reader (it may get the
/// samples again from DDS history): what the first one delivered does not hold back a
/// resent write's sample from the second.
#[test]
fn a_reader_created_again_gets_a_resent_write_its_predecessor_delivered() {
    let (first, mut rig, rd, read) = Rig::reading(41);
    let key = rig.client.config().key;
    let origin = |resent: bool| {
        Some(SampleOrigin {
            write: WriteOrigin {
                frontend: 9,
                incarnation: 1,
                write: 6,
                index: 0,
            },
            resent,
        })
    };
    let identity = |writer: u8| SampleIdentity {
        writer: [writer; 16],
        sequence_number: 1,
    };
    first.sample_from(key, rd, read, identity(1), origin(false), &[60]);
    rig.run(&[&first], |r, _| r.first_bytes_delivered().len() == 1);
    rig.client.delete(Instant::now(), rd).expect("delete");
    let sb = ObjectId::new(1, k::SUBSCRIBER);
    rig.create(rd, k::DATAREADER, "<dds/>", VariantExtra::Parent(sb));
    rig.client
        .read(Instant::now(), rd, unlimited_read())
        .expect("read again");
    rig.run(&[&first], |_, s| s.iter().any(|m| is(m, "Read")));
    drop(first);
    let second = FakeWorker::start(42);
    let read = rig.read_replayed_on(&second);
    second.sample_from(key, rd, read, identity(2), origin(true), &[60]);
    rig.run(&[&second], |r, _| r.first_bytes_delivered().len() >= 2);
    assert_eq!(
        rig.first_bytes_delivered(),
        [60, 60],
        "the new reader's lost"
    );
    assert_eq!(rig.relay.stats().resent_samples_already_delivered, 0);
    drop((rig, second));
}

#[test]
fn a_write_its_readers_acknowledged_is_not_resent_to_a_new_worker() {
    let first = FakeWorker::start(21);
    let mut rig = Rig::connected(&first, 21);
    let [_, _, _, w] = rig.create_writer();
    rig.run(&[&first], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 4
    });
    // Acknowledged by the readers: released at once (not after the settle time).
    first.acknowledge.set(true);
    rig.client
        .write(Instant::now(), stream_id::BUILTIN_RELIABLE, w, b"acked")
        .expect("write");
    rig.run(&[&first], |r, _| r.relay.stats().writes_acknowledged == 1);
    // Executed, not acknowledged: kept.
    first.acknowledge.set(false);
    rig.client
        .write(Instant::now(), stream_id::BUILTIN_RELIABLE, w, b"in flight")
        .expect("write");
    rig.run(&[&first], |_, s| {
        s.iter()
            .any(|m| is(m, "Write") && written(m).ends_with(b"in flight"))
    });
    drop(first);
    let second = FakeWorker::start(22);
    let replay = rig.run(&[&second], |_, s| s.iter().any(|m| is(m, "Write")));
    let writes: Vec<&[u8]> = replay
        .iter()
        .filter(|m| is(m, "Write"))
        .map(written)
        .collect();
    assert_eq!(writes.len(), 1, "only the unacknowledged write is resent");
    assert!(writes[0].ends_with(b"in flight"));
    assert_eq!(rig.relay.stats().writes_acknowledged, 1);
    assert_eq!(rig.relay.stats().writes_resent, 1);
    drop((rig, second));
}

impl Rig {
    /// Hands what the client sent to the session core (and so to the relay).
    fn deliver(&mut self, now: Instant) {
        while let Some(d) = self.client.poll_transmit() {
            self.agent.handle_datagram(now, ADDR, &d, &mut self.relay);
        }
    }

    /// Lets `worker` take what was sent, the relay see its progress and send what waits,
    /// until `done` holds for the rig and what the worker took (up to 10 s); returns that.
    fn serve_until(
        &mut self,
        worker: &FakeWorker,
        mut done: impl FnMut(&Rig, &[Served]) -> bool,
    ) -> Vec<Served> {
        let mut served = Vec::new();
        let end = Instant::now() + Duration::from_secs(10);
        while Instant::now() < end {
            served.extend(worker.serve(self));
            self.poll_ipc(Instant::now(), &[worker]);
            self.relay.pump();
            if done(self, &served) {
                return served;
            }
        }
        panic!("the worker did not get there within 10 s");
    }

    /// Lets `worker` take everything sent and waiting.
    fn catch_up(&mut self, worker: &FakeWorker) {
        self.serve_until(worker, |r, _| r.relay.backlog() == 0);
        // The last ones sent, and the worker's word that it took them.
        worker.serve(self);
        self.poll_ipc(Instant::now(), &[worker]);
    }
}

/// The bodies of the WRITE operations among `served`.
fn write_bodies(served: &[Served]) -> Vec<String> {
    served
        .iter()
        .filter(|m| is(m, "Write"))
        .map(|m| String::from_utf8_lossy(written(m)).into_owned())
        .collect()
}

/// Sends a reliable write of `w` from the rig's client and hands it to the relay.
fn reliable_write(rig: &mut Rig, w: ObjectId, body: &[u8]) {
    let now = Instant::now();
    rig.client
        .write(now, stream_id::BUILTIN_RELIABLE, w, body)
        .expect("write");
    rig.deliver(now);
    rig.relay.pump();
}

#[test]
fn a_client_whose_replay_crashed_the_last_worker_has_its_session_ended() {
    let first = FakeWorker::start(21);
    let mut rig = Rig::connected(&first, 21);
    rig.create_writer();
    rig.run(&[&first], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 4
    });
    let key = ClientKey([0xB2, 0, 0, 1]);
    assert!(rig.agent.has_client(key));
    // The next worker refuses the client's objects: its predecessor died replaying them.
    let second = FakeWorker::start(22);
    second.refuse_replays.set(true);
    let served = rig.run(&[&second], |r, _| !r.agent.has_client(key));
    assert!(served.iter().any(|m| is(m, "Create")));
    assert_eq!(rig.agent.stats().dropped("replay_crash"), 1);
    // And the worker is told the session is gone (its entities, if any, go with it).
    let told = rig.run(&[&second], |_, s| s.iter().any(|m| is(m, "DeleteClient")));
    assert!(told.iter().any(|m| m.route.client_key == key));
}

/// A front-end that took sessions over takes no client message (its relay has no room)
/// until the worker answered its hello: the worker's last executed writes come before that
/// answer, and a client's resend taken earlier would be handed over a second time. The
/// announcement of a worker alone does not open it; the answer to this process does.
#[test]
fn a_relay_that_took_sessions_over_has_no_room_until_the_worker_answered_its_hello() {
    use xrce_common::session::agent::OperationSink;
    let now = Instant::now();
    let mut agent: Agent<u32> = Agent::new(AgentConfig::default());
    let mut relay = Relay::new(0, 2, MemoryLink::default());
    relay.set_hand_over_at_once(true);
    assert!(relay.has_room(), "nothing taken over: open");
    relay.restore_graph(
        ClientKey([0xB2, 0, 0, 1]),
        xrce_common::session::graph::ObjectGraph::default(),
    );
    assert!(!relay.has_room() && !relay.has_room_for(1));
    let worker = FakeWorker::start(0x31);
    let announcement = ReplyMessage::new(
        Route {
            generation: 0x31,
            ..Route::default()
        },
        Reply::WorkerHello,
    );
    relay.handle_announcement(&announcement.encode());
    assert_eq!(relay.generation(), Some(0x31));
    assert!(!relay.has_room(), "announced, not answered");
    relay.pump();
    let hello = relay
        .link_mut()
        .take()
        .into_iter()
        .map(|m| RequestMessage::decode(&m).expect("request").into_owned())
        .find(|m| m.request == Request::FrontendHello)
        .expect("the hello");
    worker.reply(
        Route {
            incarnation: hello.route.incarnation,
            ..Route::frontend(0)
        },
        Reply::WorkerHello,
    );
    for m in worker.replies.take() {
        relay.handle_reply(now, &m, &mut agent);
    }
    assert!(relay.has_room() && relay.has_room_for(1));
}
