//! Simulation tests of the front-end's relay: a client, the session core and the relay
//! exchange in one thread with a fake worker that answers as the real one does, over an
//! in-memory link (no shared memory): what a new worker generation gets replayed (objects in
//! creation order, reads, retained writes, but not the writes DDS readers acknowledged),
//! that a replayed read does not deliver a sample its client had, and how best-effort
//! writes share the window.

use std::cell::{Cell, RefCell};
use std::time::{Duration, Instant};

use xrce_common::session::agent::{Agent, AgentConfig};
use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind as k, stream_id, ClientKey, DataDeliveryControl, ObjectId, ObjectVariant,
    ReadSpecification, Representation, VariantExtra,
};
use xrce_frontend::relay::link::MemoryLink;
use xrce_frontend::relay::Relay;
use xrce_ipc::{
    Encode, Reply, ReplyMessage, Request, RequestMessage, Route, Sample, SampleIdentity,
};

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
}

impl FakeWorker {
    fn start(generation: u32) -> Self {
        FakeWorker {
            generation,
            acknowledge: Cell::new(false),
            announced: Cell::new(false),
            greeted: Cell::new(false),
            replies: RefCell::new(Vec::new()),
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
        let route = Route::object(0, client, read.request_id, reader);
        let sample = Sample {
            identity,
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
    let spec = ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    rig.client.read(Instant::now(), rd, spec).expect("read");
    rig.client
        .write(Instant::now(), stream_id::BUILTIN_RELIABLE, w, b"kept")
        .expect("write");
    rig.run(&[&first], |_, s| {
        s.iter().any(|m| is(m, "Read")) && s.iter().any(|m| is(m, "Write"))
    });
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
    assert!(pos("Write") > pos("Read"), "{kinds:?}");
    assert_eq!(rig.relay.stats().replays, 2);
    assert!(rig.relay.stats().writes_resent >= 1);
    drop((rig, second));
}

#[test]
fn a_replayed_read_does_not_deliver_a_sample_twice() {
    let first = FakeWorker::start(21);
    let mut rig = Rig::connected(&first, 21);
    let p = ObjectId::new(1, k::PARTICIPANT);
    let sb = ObjectId::new(1, k::SUBSCRIBER);
    let rd = ObjectId::new(1, k::DATAREADER);
    rig.create(p, k::PARTICIPANT, "<dds/>", VariantExtra::DomainId(0));
    rig.create(sb, k::SUBSCRIBER, "", VariantExtra::Parent(p));
    rig.create(rd, k::DATAREADER, "<dds/>", VariantExtra::Parent(sb));
    let spec = ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    rig.client.read(Instant::now(), rd, spec).expect("read");
    let served = rig.run(&[&first], |_, s| s.iter().any(|m| is(m, "Read")));
    let read = served
        .iter()
        .find(|m| is(m, "Read"))
        .map(|m| m.route)
        .expect("read");
    let writer = [0x42u8; 16];
    let at = |n: i64| SampleIdentity {
        writer,
        sequence_number: n,
    };
    let data = |rig: &Rig| {
        rig.events
            .iter()
            .filter_map(|e| match e {
                ClientEvent::Data { data, .. } => Some(data.clone()),
                _ => None,
            })
            .collect::<Vec<_>>()
    };
    for n in 1..=3 {
        first.sample(rig.client.config().key, rd, read, at(n), &[n as u8]);
    }
    rig.run(&[&first], |r, _| data(r).len() == 3);
    // A new worker; the writer outlived the old one and offers its history again, then a
    // new sample.
    drop(first);
    let second = FakeWorker::start(22);
    let replay = rig.run(&[&second], |_, s| s.iter().any(|m| is(m, "Read")));
    let read = replay
        .iter()
        .find(|m| is(m, "Read"))
        .map(|m| m.route)
        .expect("read replayed");
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
    rig.run(&[&second], |r, _| data(r).len() >= 6);
    let got: Vec<u8> = data(&rig).iter().map(|d| d[0]).collect();
    assert_eq!(got, [1, 2, 3, 4, 70, 80], "delivered twice or lost");
    assert_eq!(rig.relay.stats().samples_already_delivered, 3);
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

/// Best-effort writes that go to the worker at once, in hand-over mode.
fn best_effort_share() -> u64 {
    use xrce_frontend::relay::{BEST_EFFORT_RESERVE, HAND_OVER_HEADROOM};
    use xrce_ipc::IN_FLIGHT_WINDOW;
    IN_FLIGHT_WINDOW - HAND_OVER_HEADROOM - BEST_EFFORT_RESERVE
}

/// Sends `n` best-effort writes of `w` (`{tag} {i}`) from the rig's client at `now`.
fn best_effort_writes(rig: &mut Rig, now: Instant, w: ObjectId, tag: &str, n: u64) {
    for i in 0..n {
        rig.client
            .write(
                now,
                stream_id::BUILTIN_BEST_EFFORT,
                w,
                format!("{tag} {i}").as_bytes(),
            )
            .expect("write");
        rig.deliver(now);
    }
    rig.relay.pump();
}

/// The bodies of the WRITE operations among `served`.
fn write_bodies(served: &[Served]) -> Vec<String> {
    served
        .iter()
        .filter(|m| is(m, "Write"))
        .map(|m| String::from_utf8_lossy(written(m)).into_owned())
        .collect()
}

#[test]
fn a_best_effort_flood_leaves_room_for_reliable_writes() {
    use xrce_frontend::relay::BEST_EFFORT_WAITING_MAX;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(5);
    // A worker that takes nothing for a while: best-effort writes fill what they may of
    // the window, a few wait for it, and the rest are dropped, counted.
    let now = Instant::now();
    let share = best_effort_share();
    let waiting = BEST_EFFORT_WAITING_MAX as u64;
    best_effort_writes(&mut rig, now, w, "flood", share + waiting + 100);
    assert_eq!(
        rig.relay.stats().ops_dropped,
        100,
        "the flood beyond the window's share and the waiting queue"
    );
    assert_eq!(rig.relay.backlog(), BEST_EFFORT_WAITING_MAX);
    // A reliable write is still taken at once, ahead of the waiting best-effort writes.
    rig.client
        .write(now, stream_id::BUILTIN_RELIABLE, w, b"urgent")
        .expect("write");
    rig.deliver(now);
    rig.relay.pump();
    let writes = write_bodies(&worker.serve(&mut rig));
    let flood = writes.iter().filter(|b| b.starts_with("flood")).count() as u64;
    assert_eq!(flood, share, "best-effort writes in flight");
    assert!(
        writes.iter().any(|b| b.ends_with("urgent")),
        "the reliable write was refused behind the flood ({flood} best-effort writes in flight)"
    );
    drop((rig, worker));
}

#[test]
fn best_effort_writes_wait_out_a_short_worker_stall_in_order() {
    let (worker, mut rig, w) = Rig::handing_over_with_writer(7);
    // The worker stalls while more best-effort writes come than the window's share holds.
    let n = best_effort_share() + 100;
    best_effort_writes(&mut rig, Instant::now(), w, "be", n);
    assert_eq!(rig.relay.stats().ops_dropped, 0, "nothing is dropped");
    assert_eq!(rig.relay.backlog(), 100, "the writes beyond the share wait");
    // It catches up: every write reaches it, once, in the order sent.
    let served = rig.serve_until(&worker, |_, s| write_bodies(s).len() as u64 >= n);
    let got: Vec<String> = write_bodies(&served)
        .iter()
        .map(|b| b[b.find("be ").expect("a write of this test")..].to_string())
        .collect();
    let expected: Vec<String> = (0..n).map(|i| format!("be {i}")).collect();
    assert_eq!(got, expected);
    assert_eq!(rig.relay.backlog(), 0);
    drop((rig, worker));
}

#[test]
fn waiting_writes_of_a_deleted_writer_are_dropped_not_sent_after_the_delete() {
    let (worker, mut rig, w) = Rig::handing_over_with_writer(9);
    let share = best_effort_share();
    best_effort_writes(&mut rig, Instant::now(), w, "be", share + 10);
    assert_eq!(rig.relay.backlog(), 10);
    // The client deletes the writer while ten of its writes wait: the delete goes to the
    // worker now, the ten are dropped (they would reach no writer, or a new one with the id).
    rig.client.delete(Instant::now(), w).expect("delete");
    rig.deliver(Instant::now());
    assert_eq!(rig.relay.backlog(), 0);
    assert_eq!(rig.relay.stats().ops_dropped, 10);
    let is_delete = |m: &Served| is(m, "Delete");
    let mut served = rig.serve_until(&worker, |_, s| s.iter().any(is_delete));
    let delete = served
        .iter()
        .position(is_delete)
        .expect("the delete reached the worker");
    served.extend(worker.serve(&mut rig));
    assert!(
        served[delete..].iter().all(|m| !is(m, "Write")),
        "a write reached the worker after the delete of its writer"
    );
    assert_eq!(write_bodies(&served).len() as u64, share);
    drop((rig, worker));
}

#[test]
fn waiting_writes_to_an_id_are_dropped_when_it_is_created() {
    let (worker, mut rig, w) = Rig::handing_over_with_writer(13);
    best_effort_writes(&mut rig, Instant::now(), w, "be", best_effort_share() + 10);
    // Five writes to a writer the client has not created yet wait behind the ten.
    let early = ObjectId::new(2, k::DATAWRITER);
    best_effort_writes(&mut rig, Instant::now(), early, "early", 5);
    assert_eq!(rig.relay.backlog(), 15);
    // Its CREATE goes to the worker now: the five must not reach the new writer after it.
    rig.create(
        early,
        k::DATAWRITER,
        "<dds/>",
        VariantExtra::Parent(ObjectId::new(1, k::PUBLISHER)),
    );
    rig.deliver(Instant::now());
    assert_eq!(
        rig.relay.backlog(),
        10,
        "only the writes to the new id are dropped"
    );
    assert_eq!(rig.relay.stats().ops_dropped, 5);
    drop((rig, worker));
}

#[test]
fn waiting_writes_are_dropped_when_their_worker_is_replaced() {
    let (first, mut rig, w) = Rig::handing_over_with_writer(10);
    best_effort_writes(&mut rig, Instant::now(), w, "be", best_effort_share() + 10);
    assert_eq!(rig.relay.backlog(), 10);
    // The worker dies with the window full; its successor gets the replay, not stale data.
    drop(first);
    let second = FakeWorker::start(30);
    let replay = rig.run(&[&second], |_, s| s.iter().any(|m| is(m, "ReplayDone")));
    assert!(
        write_bodies(&replay).is_empty(),
        "stale best-effort writes replayed"
    );
    assert_eq!(rig.relay.backlog(), 0);
    assert_eq!(rig.relay.stats().ops_dropped, 10);
    drop((rig, second));
}

/// Overflows the best-effort wait of a relay whose shedding lasts `hold`, lets the worker
/// catch up, then sends ten writes more than the window's share: how many of those wait.
fn waiting_after_an_overflow(generation: u32, hold: Duration) -> usize {
    use xrce_frontend::relay::BEST_EFFORT_WAITING_MAX;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(generation);
    rig.relay.set_best_effort_shed_hold(hold);
    let share = best_effort_share();
    let waiting = BEST_EFFORT_WAITING_MAX as u64;
    best_effort_writes(&mut rig, Instant::now(), w, "flood", share + waiting + 1);
    assert_eq!(rig.relay.stats().ops_dropped, 1);
    assert_eq!(rig.relay.stats().best_effort_sheds, 1);
    rig.catch_up(&worker);
    best_effort_writes(&mut rig, Instant::now(), w, "after", share + 10);
    let queued = rig.relay.backlog();
    assert_eq!(
        rig.relay.stats().ops_dropped,
        1 + 10 - queued as u64,
        "what does not wait is dropped"
    );
    drop((rig, worker));
    queued
}

#[test]
fn after_an_overflow_best_effort_writes_are_shed_not_queued_until_the_hold_ends() {
    // Within the hold (an hour: no machine is that slow), nothing beyond the share waits.
    assert_eq!(waiting_after_an_overflow(8, Duration::from_secs(3600)), 0);
    // A hold that has ended (none at all) queues again.
    assert_eq!(waiting_after_an_overflow(14, Duration::ZERO), 10);
}

/// Datagrams between a second client (at `addr`) and the rig's session core, and the rig's
/// IPC, once (the rig's own client gets what is meant for it).
fn exchange_with(rig: &mut Rig, worker: &FakeWorker, other: &mut Client, addr: u32) {
    let now = Instant::now();
    while let Some(d) = other.poll_transmit() {
        rig.agent.handle_datagram(now, addr, &d, &mut rig.relay);
    }
    rig.relay.pump();
    worker.serve(rig);
    rig.poll_ipc(now, &[worker]);
    rig.agent.handle_timeout(now, &mut rig.relay);
    while let Some(t) = rig.agent.poll_transmit() {
        if t.destination == addr {
            other.handle_datagram(now, &t.data);
        } else {
            rig.client.handle_datagram(now, &t.data);
        }
    }
}

#[test]
fn a_quiet_clients_best_effort_writes_wait_while_a_flooding_client_is_shed() {
    use xrce_frontend::relay::BEST_EFFORT_WAITING_MAX;
    const QUIET: u32 = 8;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(16);
    rig.relay
        .set_best_effort_shed_hold(Duration::from_secs(3600));
    let mut quiet = Client::new(ClientConfig::new(ClientKey([0xC3, 0, 0, 2])));
    quiet.connect(Instant::now());
    let end = Instant::now() + Duration::from_secs(10);
    while !quiet.is_connected() {
        assert!(Instant::now() < end, "the second client did not connect");
        exchange_with(&mut rig, &worker, &mut quiet, QUIET);
    }
    // The worker stalls; the rig's client floods it: the window's share goes, the wait
    // fills, and the write that overflows it is dropped and starts the flooder's hold.
    let share = best_effort_share();
    let waiting = BEST_EFFORT_WAITING_MAX as u64;
    best_effort_writes(&mut rig, Instant::now(), w, "flood", share + waiting + 1);
    assert_eq!(rig.relay.stats().ops_dropped, 1);
    assert_eq!(rig.relay.stats().best_effort_sheds, 1);
    // The quiet client's writes still wait, each in place of the flood's newest, and the
    // flooder's further writes are dropped.
    let now = Instant::now();
    for i in 0..10 {
        quiet
            .write(
                now,
                stream_id::BUILTIN_BEST_EFFORT,
                w,
                format!("quiet {i}").as_bytes(),
            )
            .expect("write");
    }
    while let Some(d) = quiet.poll_transmit() {
        rig.agent.handle_datagram(now, QUIET, &d, &mut rig.relay);
    }
    best_effort_writes(&mut rig, now, w, "late", 5);
    assert_eq!(rig.relay.backlog(), BEST_EFFORT_WAITING_MAX);
    assert_eq!(rig.relay.stats().ops_dropped, 1 + 10 + 5);
    assert_eq!(rig.relay.stats().best_effort_sheds, 1);
    // When the worker catches up, the two take turns: the quiet client's writes arrive
    // among the first waiting ones, in order, not behind the flood's backlog.
    let served = rig.serve_until(&worker, |_, s| {
        write_bodies(s).len() as u64 >= share + waiting
    });
    let bodies = write_bodies(&served);
    let quiet_at: Vec<usize> = (0..10)
        .map(|i| {
            let tag = format!("quiet {i}");
            bodies
                .iter()
                .position(|b| b.ends_with(&tag))
                .unwrap_or_else(|| panic!("{tag} did not reach the worker"))
        })
        .collect();
    assert!(
        quiet_at.windows(2).all(|p| p[0] < p[1]),
        "out of order: {quiet_at:?}"
    );
    assert!(
        quiet_at[9] < (share + 20) as usize,
        "the quiet client waited behind the flood: {quiet_at:?}"
    );
    // The flood kept its oldest writes, in order; its newest ten made the room.
    let flood: Vec<u64> = bodies
        .iter()
        .filter_map(|b| b.find("flood ").map(|at| &b[at + 6..]))
        .map(|n| n.parse().expect("a flood write's number"))
        .collect();
    let expected: Vec<u64> = (0..share + waiting - 10).collect();
    assert_eq!(flood, expected);
    assert!(!bodies.iter().any(|b| b.contains("late ")));
    drop((rig, worker));
}

#[test]
fn small_reliable_messages_may_fill_the_window() {
    use xrce_frontend::relay::HAND_OVER_HEADROOM;
    use xrce_ipc::IN_FLIGHT_WINDOW;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(6);
    // The worker takes nothing meanwhile; each message carries one WRITE_DATA, so each
    // needs room for one operation, not for the largest message.
    let mut now = Instant::now();
    for i in 0..IN_FLIGHT_WINDOW + 40 {
        let _ = rig.client.write(
            now,
            stream_id::BUILTIN_RELIABLE,
            w,
            format!("r{i}").as_bytes(),
        );
        for _ in 0..4 {
            rig.deliver(now);
            rig.relay.pump();
            rig.agent.handle_timeout(now, &mut rig.relay);
            while let Some(t) = rig.agent.poll_transmit() {
                rig.client.handle_datagram(now, &t.data);
            }
            now += Duration::from_millis(60);
            rig.client.handle_timeout(now);
        }
    }
    let writes = worker
        .serve(&mut rig)
        .iter()
        .filter(|m| is(m, "Write"))
        .count() as u64;
    // Room for two operations a submessage is asked for: all but the last slot fill (the
    // room for the largest message would have stopped them at 145).
    assert!(
        (IN_FLIGHT_WINDOW - 2..=IN_FLIGHT_WINDOW).contains(&writes),
        "{writes} writes in flight (the largest message needs {HAND_OVER_HEADROOM})"
    );
    drop((rig, worker));
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

/// A best-effort write tells the worker its progress can wait only while most of the window
/// is free; reliable writes and control operations never do.
#[test]
fn only_best_effort_writes_with_the_window_mostly_free_let_their_progress_wait() {
    use xrce_frontend::relay::PROGRESS_CAN_WAIT_BELOW;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(8);
    rig.catch_up(&worker);
    let can_wait = |m: &Served| m.progress_can_wait;
    // With the window free: a CREATE (its client waits for the STATUS) and a reliable write
    // (retained until executed) wait for their progress.
    let r = ObjectId::new(2, k::DATAWRITER);
    rig.create(
        r,
        k::DATAWRITER,
        "<dds/>",
        VariantExtra::Parent(ObjectId::new(1, k::PUBLISHER)),
    );
    rig.deliver(Instant::now());
    let served = rig.serve_until(&worker, |_, s| s.iter().any(|m| is(m, "Create")));
    assert!(!served.iter().any(can_wait));
    rig.catch_up(&worker);
    reliable_write(&mut rig, w, b"reliable");
    let served = worker.serve(&mut rig);
    assert_eq!(served.len(), 1);
    assert!(!can_wait(&served[0]), "a reliable write");
    rig.catch_up(&worker);
    // The worker takes nothing meanwhile: the window fills one write at a time.
    let n = PROGRESS_CAN_WAIT_BELOW + 10;
    best_effort_writes(&mut rig, Instant::now(), w, "be", n);
    reliable_write(&mut rig, w, b"reliable");
    let served = worker.serve(&mut rig);
    let writes: Vec<&Served> = served.iter().filter(|m| is(m, "Write")).collect();
    assert_eq!(writes.len() as u64, n + 1);
    let flagged: Vec<bool> = writes.iter().map(|m| can_wait(m)).collect();
    let mut expected = vec![true; PROGRESS_CAN_WAIT_BELOW as usize];
    expected.resize(n as usize + 1, false);
    assert_eq!(
        flagged, expected,
        "flagged while fewer than {PROGRESS_CAN_WAIT_BELOW} were in flight"
    );
    drop((rig, worker));
}

/// The STATUS replies the rig's client got for `object`.
fn statuses_of(rig: &Rig, object: ObjectId) -> Vec<u8> {
    rig.events
        .iter()
        .filter_map(|e| match e {
            ClientEvent::Status(r) if r.related.object_id == object => Some(r.result.status),
            _ => None,
        })
        .collect()
}

/// Requests the link refuses (its shared memory failed) wait in the outbox, the relay asks to
/// be called again soon, and they go in order once the link works again.
#[test]
fn requests_the_link_refuses_wait_and_go_in_order_once_it_works() {
    let worker = FakeWorker::start(41);
    let mut rig = Rig::connected(&worker, 41);
    let [.., w] = rig.create_writer();
    rig.run(&[&worker], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 4
    });
    rig.relay.link_mut().fail(true);
    for i in 0..5 {
        reliable_write(&mut rig, w, format!("w{i}").as_bytes());
    }
    assert_eq!(rig.relay.backlog(), 5, "all five wait");
    let now = Instant::now();
    assert!(
        rig.relay
            .poll_timeout(now)
            .is_some_and(|t| t <= now + Duration::from_millis(1)),
        "a retry is asked for"
    );
    rig.relay.link_mut().fail(false);
    let served = rig.run(&[&worker], |_, s| {
        s.iter().filter(|m| is(m, "Write")).count() >= 5
    });
    assert_eq!(write_bodies(&served), ["w0", "w1", "w2", "w3", "w4"]);
    assert_eq!(rig.relay.backlog(), 0);
}

/// A reply meant for the front-end process this one took over from, one from a worker
/// generation no longer served and bytes that are no message change nothing a client sees.
#[test]
fn replies_of_a_predecessor_a_dead_worker_or_no_worker_are_not_applied() {
    use xrce_common::wire::{status, RequestId, ResultStatus};
    let worker = FakeWorker::start(42);
    let mut rig = Rig::connected(&worker, 42);
    let w = ObjectId::new(1, k::DATAWRITER);
    let failed = |incarnation: u16, generation: u32| {
        let route = Route {
            incarnation,
            generation,
            op_seq: 1,
            ..Route::object(0, ClientKey([0xB2, 0, 0, 1]), RequestId([0, 1]), w)
        };
        let reply = Reply::Status {
            result: ResultStatus::new(status::ERR_DDS_ERROR),
            replay: false,
        };
        ReplyMessage::new(route, reply).encode()
    };
    let now = Instant::now();
    let before = rig.relay.stats().clone();
    rig.relay.handle_reply(now, &failed(9, 42), &mut rig.agent);
    rig.relay.handle_reply(now, &failed(1, 41), &mut rig.agent);
    rig.relay
        .handle_reply(now, b"not a message", &mut rig.agent);
    rig.relay.after_replies(now, &mut rig.agent);
    let after = rig.relay.stats();
    assert_eq!(after.predecessor_replies, before.predecessor_replies + 1);
    assert_eq!(after.ipc_dropped, before.ipc_dropped + 2);
    rig.run(&[&worker], |_, _| true);
    assert!(statuses_of(&rig, w).is_empty(), "{:?}", rig.events);
}

/// A worker that dies with CREATEs taken and not answered: its successor gets them again as
/// creations a client waits for (not as a replay), and the client gets one STATUS for each.
#[test]
fn creations_a_dead_worker_did_not_answer_are_answered_once_by_its_successor() {
    let first = FakeWorker::start(43);
    let mut rig = Rig::connected(&first, 43);
    let ids = rig.create_writer();
    let now = Instant::now();
    rig.deliver(now);
    rig.relay.pump();
    let taken = first.serve(&mut rig);
    assert_eq!(taken.iter().filter(|m| is(m, "Create")).count(), 4);
    // It dies with its answers.
    drop(first);
    let second = FakeWorker::start(44);
    let replay = rig.run(&[&second], |r, _| {
        ids.iter().all(|id| !statuses_of(r, *id).is_empty())
    });
    let creates: Vec<&Served> = replay.iter().filter(|m| is(m, "Create")).collect();
    assert_eq!(creates.len(), 4);
    assert!(
        !creates.iter().any(|m| replayed(m)),
        "the client waits for them"
    );
    // A while longer: nothing more comes.
    let end = Instant::now() + Duration::from_millis(200);
    rig.run(&[&second], |_, _| Instant::now() >= end);
    for id in ids {
        assert_eq!(statuses_of(&rig, id), [0], "{id:?}");
    }
}

/// Time is the caller's: an executed write no DDS reader acknowledges is released exactly
/// [`SETTLE_TIME`] after the worker reported it executed, whatever the wall clock says.
#[test]
fn an_unacknowledged_write_is_released_after_the_settle_time_on_the_callers_clock() {
    use xrce_frontend::relay::SETTLE_TIME;
    let worker = FakeWorker::start(45);
    let mut rig = Rig::connected(&worker, 45);
    let [.., w] = rig.create_writer();
    rig.run(&[&worker], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 4
    });
    reliable_write(&mut rig, w, b"kept");
    rig.run(&[&worker], |r, s| {
        s.iter().any(|m| is(m, "Write")) && r.relay.poll_timeout(Instant::now()).is_some()
    });
    let now = Instant::now();
    let release = rig.relay.poll_timeout(now).expect("a settle deadline");
    assert!(release > now && release <= now + SETTLE_TIME, "{release:?}");
    rig.relay
        .after_replies(release - Duration::from_millis(1), &mut rig.agent);
    assert_eq!(rig.relay.stats().writes_settled_unacknowledged, 0);
    rig.relay.after_replies(release, &mut rig.agent);
    assert_eq!(rig.relay.stats().writes_settled_unacknowledged, 1);
    assert_eq!(rig.relay.poll_timeout(release), None);
}
