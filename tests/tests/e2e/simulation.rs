//! The whole agent in one thread, in memory: a client, the session core, the relay and the
//! real worker (over the fake DDS) joined by memory links, in simulated time (each step is a
//! millisecond, nothing sleeps). What the process tests show with sockets and shared memory,
//! shown here step by step and the same on every run: samples flow end to end, a worker
//! that dies (any number of times, at any step) loses and repeats none of them (not even a
//! write whose acknowledgement died with it), a front-end that dies between handing a client's
//! message over and storing that it took it has a successor that writes none of it twice, a
//! link that loses datagrams delays them only, and a client that resets keeps its objects.

use std::rc::Rc;
use std::time::{Duration, Instant};

use xrce_common::session::agent::{Agent, AgentConfig};
use xrce_common::session::client::{Client, ClientConfig, ClientError, ClientEvent};
use xrce_common::session::graph::ObjectGraph;
use xrce_common::session::snapshot::SessionSnapshot;
use xrce_common::wire::{
    object_kind as k, status, stream_id, ClientKey, ObjectId, ObjectVariant, Representation,
    VariantExtra,
};
use xrce_dds_seam::fake::{Fake, FakeBus};
use xrce_dds_worker::worker::{MemoryWorkerLink, Worker, WorkerConfig};
use xrce_frontend::relay::link::MemoryLink;
use xrce_frontend::relay::Relay;

/// The front-end's id, and the client's address on its transport.
const FE: u32 = 3;
const ADDR: u32 = 1;
/// One step of simulated time.
const TICK: Duration = Duration::from_millis(1);
/// Longest a scenario may take, in simulated time.
const PATIENCE: Duration = Duration::from_secs(120);
const TOPIC: &str = "SimTopic";

const PARTICIPANT: ObjectId = ObjectId::new(1, k::PARTICIPANT);
const PUBLISHER: ObjectId = ObjectId::new(1, k::PUBLISHER);
const SUBSCRIBER: ObjectId = ObjectId::new(1, k::SUBSCRIBER);
const WRITER: ObjectId = ObjectId::new(1, k::DATAWRITER);
const READER: ObjectId = ObjectId::new(1, k::DATAREADER);

fn worker_config() -> WorkerConfig {
    WorkerConfig {
        instance: "simulation".into(),
        backend: Default::default(),
        dds: Default::default(),
        references: Default::default(),
        ros_graph: false,
        share_writers: false,
        frontend_grace: Duration::from_secs(30),
        domains: Default::default(),
        bounds: Default::default(),
        default_domain: 0,
    }
}

/// Whether a client datagram carries a WRITE_DATA.
fn carries_a_write(datagram: &[u8]) -> bool {
    xrce_common::wire::Message::decode(datagram).is_ok_and(|m| {
        m.submessages
            .iter()
            .any(|s| matches!(s.payload, xrce_common::wire::Payload::WriteData(_)))
    })
}

/// Sample `n` as the client writes it (and its reader must get it).
fn sample(n: u32) -> Vec<u8> {
    [n.to_le_bytes(), [0xab; 4]].concat()
}

/// A client of the agent, and the agent: session core, relay and worker.
struct World {
    now: Instant,
    client: Client,
    session: Agent<u32>,
    relay: Relay<MemoryLink>,
    worker: Worker<MemoryWorkerLink>,
    bus: Rc<FakeBus>,
    generation: u32,
    /// The worker's announcements the relay has seen.
    announcements_seen: usize,
    /// The samples the client's reader got, in order.
    received: Vec<Vec<u8>>,
    /// The statuses the client got: (object, status).
    statuses: Vec<(ObjectId, u8)>,
    /// One datagram in this many is lost, each way (0: none).
    lose_every: u64,
    datagrams: u64,
    /// Workers that died.
    crashes: u32,
    /// When the worker asked for its next pass (`None`: not before a request comes).
    next_pass: Option<Instant>,
    /// Samples the client wrote.
    written: u32,
    /// The front-end's process (its incarnation), and how many died.
    incarnation: u16,
    frontend_crashes: u32,
    /// Client datagrams that arrived while the front-end died: they wait in the socket
    /// (kept open for the successor) and are read by the next step.
    in_socket: Vec<Vec<u8>>,
}

/// What a front-end stored for its successor, encoded as its session store keeps it: the
/// client's session and its object graph (objects, and reads with what they delivered).
struct Stored {
    session: Vec<u8>,
    objects: Vec<u8>,
    reads: Vec<u8>,
}

impl World {
    fn new() -> Self {
        // The relay and the worker run in this process: a fault `tests/fault-check.sh` names
        // (XRCE_FAULT) is theirs as it is an agent process's, and said as an agent says it.
        if let Some(f) = xrce_common::fault::install_from_env().expect("XRCE_FAULT names a fault") {
            println!("FAULT INJECTION active: {f:?} in this test's relay and worker (XRCE_FAULT)");
        }
        let now = Instant::now();
        let (fake, bus) = Fake::new().expect("fake DDS");
        let generation = 0x101;
        let worker = Worker::new(
            worker_config(),
            Box::new(fake),
            MemoryWorkerLink::default(),
            generation,
            now,
        )
        .expect("worker");
        World {
            now,
            client: Client::new(ClientConfig::new(ClientKey([0x51, 0x4d, 0, 1]))),
            session: Agent::new(AgentConfig::default()),
            relay: Relay::new(FE, 1, MemoryLink::default()),
            worker,
            bus,
            generation,
            announcements_seen: 0,
            received: Vec::new(),
            statuses: Vec::new(),
            lose_every: 0,
            datagrams: 0,
            crashes: 0,
            next_pass: Some(now),
            written: 0,
            incarnation: 1,
            frontend_crashes: 0,
            in_socket: Vec::new(),
        }
    }

    /// A world keeping sessions whose client is connected, made its objects and published
    /// its first sample, which reached the reader (past the new writer's hold: until its
    /// reader matched, and 500 ms more).
    fn publishing_keeping_sessions() -> Self {
        let mut w = World::new().keeping_sessions();
        w.run_until("the relay knows the worker", |w| {
            w.relay.generation().is_some()
        });
        w.client.connect(w.now);
        w.run_until("connected", |w| w.client.is_connected());
        w.create_objects(false);
        w.write(0);
        w.run_until("the first sample", |w| w.received.len() == 1);
        w
    }

    /// Sessions kept for a successor, as a front-end runs by default: client operations go
    /// to the worker at once or are refused.
    fn keeping_sessions(mut self) -> Self {
        self.session = Agent::new(AgentConfig {
            track_sessions: true,
            epoch_seed: u64::from(self.incarnation),
            ..AgentConfig::default()
        });
        self.relay.set_hand_over_at_once(true);
        self
    }

    /// What the front-end stores now (it does so after each client message and before
    /// anything goes out).
    fn store(&self) -> Stored {
        let key = self.client.config().key;
        let session = self
            .session
            .snapshot(key, |a: u32| a.to_le_bytes().to_vec())
            .expect("a session to store");
        let graph = self.relay.graph(key).expect("a graph to store");
        Stored {
            session: session.encode(),
            objects: graph.encode_objects(),
            reads: graph.encode_reads(),
        }
    }

    /// The front-end dies right after it handed the client's next message over to the
    /// worker (which executes it), before it stored that it took the message (it stores
    /// after each message); its successor (the next incarnation, on the same address, the
    /// same socket) takes over what was stored before, and reads the datagrams that came
    /// after that message.
    fn crash_frontend_after_hand_over(&mut self) {
        self.now += TICK;
        let now = self.now;
        let mut arrived: Vec<Vec<u8>> = Vec::new();
        while let Some(d) = self.client.poll_transmit() {
            if self.survives() {
                arrived.push(d);
            }
        }
        // Stored after each datagram; the one carrying a write is handed over, not stored.
        let mut stored = self.store();
        while !arrived.is_empty() {
            let d = arrived.remove(0);
            self.session.handle_datagram(now, ADDR, &d, &mut self.relay);
            if carries_a_write(&d) {
                break;
            }
            stored = self.store();
        }
        self.in_socket = arrived;
        self.relay.pump();
        for m in self.relay.link_mut().take() {
            self.worker.handle_request(&m, now);
        }
        self.worker.pass(now).expect("a worker pass");
        self.next_pass = self.worker.poll_timeout(now).map(|d| now + d);
        let snapshot = SessionSnapshot::decode(&stored.session).expect("stored session");
        let graph = ObjectGraph::decode(&stored.objects, &stored.reads).expect("stored graph");
        self.incarnation += 1;
        self.frontend_crashes += 1;
        self.session = Agent::new(AgentConfig {
            track_sessions: true,
            epoch_seed: u64::from(self.incarnation),
            ..AgentConfig::default()
        });
        self.relay = Relay::new(FE, self.incarnation, MemoryLink::default());
        self.relay.set_hand_over_at_once(true);
        assert!(
            self.session.restore(self.now, &snapshot, ADDR),
            "taken over"
        );
        self.relay.restore_graph(snapshot.key, graph);
        // The successor finds the worker's announcement, as a process started after it.
        self.announcements_seen = 0;
    }

    /// Whether the next datagram gets through.
    fn survives(&mut self) -> bool {
        self.datagrams += 1;
        self.lose_every == 0 || self.datagrams % self.lose_every != 0
    }

    /// One millisecond: the client's datagrams to the session core, the relay's requests to
    /// the worker, a pass of the worker, its replies back, the timers, the session core's
    /// datagrams to the client.
    fn step(&mut self) {
        self.step_to_worker(false);
        self.step_from_worker();
    }

    /// The first half of a step: up to the worker's pass, which runs as in its process:
    /// when requests came or when it asked for one (`force`: in any case).
    fn step_to_worker(&mut self, force: bool) {
        self.now += TICK;
        let now = self.now;
        for d in std::mem::take(&mut self.in_socket) {
            self.session.handle_datagram(now, ADDR, &d, &mut self.relay);
        }
        while let Some(d) = self.client.poll_transmit() {
            if self.survives() {
                self.session.handle_datagram(now, ADDR, &d, &mut self.relay);
            }
        }
        self.relay.apply_replies(now, &mut self.session);
        self.relay.pump();
        let requests = self.relay.link_mut().take();
        for m in &requests {
            self.worker.handle_request(m, now);
        }
        if force || !requests.is_empty() || self.next_pass.is_some_and(|t| now >= t) {
            self.worker.pass(now).expect("a worker pass");
            self.next_pass = self.worker.poll_timeout(now).map(|d| now + d);
        }
    }

    /// Hands the relay the worker's announcements it has not seen.
    fn hand_announcements(&mut self) {
        let announced = self.worker.link().announced()[self.announcements_seen..].to_vec();
        self.announcements_seen += announced.len();
        for a in announced {
            self.relay.handle_announcement(&a);
        }
    }

    /// Hands the relay replies of the worker.
    fn hand_replies(&mut self, replies: Vec<Vec<u8>>) {
        for m in replies {
            self.relay.handle_reply(self.now, &m, &mut self.session);
        }
        self.relay.after_replies(self.now, &mut self.session);
    }

    /// The second half of a step: from the worker's replies on.
    fn step_from_worker(&mut self) {
        let now = self.now;
        self.hand_announcements();
        let replies = self.worker.link_mut().take(FE);
        self.hand_replies(replies);
        if self.relay.take_generation_change() {
            self.session.announce_streams(now);
        }
        self.relay.resume_reads(&self.session);
        self.session.handle_timeout(now, &mut self.relay);
        self.relay.pump();
        while let Some(t) = self.session.poll_transmit() {
            if self.survives() {
                self.client.handle_datagram(now, &t.data);
            }
        }
        self.client.handle_timeout(now);
        while let Some(e) = self.client.poll_event() {
            match e {
                ClientEvent::Data { data, .. } => self.received.push(data),
                ClientEvent::Status(s) => {
                    self.statuses.push((s.related.object_id, s.result.status))
                }
                _ => {}
            }
        }
    }

    /// Steps until `done` (at most [`PATIENCE`] of simulated time).
    fn run_until(&mut self, what: &str, mut done: impl FnMut(&World) -> bool) {
        let end = self.now + PATIENCE;
        while !done(self) {
            assert!(
                self.now < end,
                "{what}: not within {PATIENCE:?} (received {}, statuses {:?}, {} crashes)",
                self.received.len(),
                self.statuses,
                self.crashes
            );
            self.step();
        }
    }

    /// The worker dies; a new one (another generation, a new DDS) starts and announces
    /// itself.
    fn crash_worker(&mut self) {
        let (fake, bus) = Fake::new().expect("fake DDS");
        self.generation += 2;
        let link = self.worker.link().after_crash();
        self.worker = Worker::new(
            worker_config(),
            Box::new(fake),
            link,
            self.generation,
            self.now,
        )
        .expect("worker");
        self.bus = bus;
        self.announcements_seen = 0;
        self.crashes += 1;
        self.next_pass = Some(self.now);
    }

    /// The worker dies in the middle of a pass's output: the front-end got the first half of
    /// what it sent, and gets the rest after the new worker's announcement (two channels,
    /// no order between them).
    fn crash_worker_mid_pass(&mut self) {
        self.step_to_worker(true);
        let mut replies = self.worker.link_mut().take(FE);
        let late = replies.split_off(replies.len().div_ceil(2));
        assert!(!replies.is_empty(), "the pass sent something");
        self.hand_replies(replies);
        self.crash_worker();
        self.hand_announcements();
        self.hand_replies(late);
        self.step_from_worker();
    }

    /// The worker dies right after it handed the front-end a sample for the client's read,
    /// before the front-end heard that the sample's write was taken: what the worker sent
    /// after that sample (the progress that would have acknowledged the write) dies with it,
    /// so the front-end resends the write to the new worker.
    fn crash_worker_after_handing_a_sample_over(&mut self) {
        let is_sample = |m: &Vec<u8>| {
            matches!(
                xrce_ipc::ReplyMessage::decode(m).map(|r| r.reply),
                Ok(xrce_ipc::Reply::Sample(_))
            )
        };
        let end = self.now + PATIENCE;
        loop {
            assert!(self.now < end, "no sample handed over");
            self.step_to_worker(false);
            let mut replies = self.worker.link_mut().take(FE);
            let Some(last) = replies.iter().rposition(is_sample) else {
                self.hand_replies(replies);
                self.step_from_worker();
                continue;
            };
            replies.truncate(last + 1);
            self.hand_replies(replies);
            self.crash_worker();
            self.step_from_worker();
            return;
        }
    }

    /// A connected client with a participant, a writer and a reader of one topic, and an
    /// unbounded read on the reader.
    fn with_writer_and_reader() -> Self {
        let mut w = World::new();
        w.run_until("the relay knows the worker", |w| {
            w.relay.generation().is_some()
        });
        w.client.connect(w.now);
        w.run_until("connected", |w| w.client.is_connected());
        w.create_objects(false);
        w
    }

    /// Creates the client's participant, publisher, subscriber, reader and writer (with
    /// REUSE if `reuse`, as micro-ROS does) and starts an unbounded read on the reader.
    fn create_objects(&mut self, reuse: bool) {
        self.statuses.clear();
        let participant = "<dds><participant><rtps><name>sim</name></rtps></participant></dds>";
        let topic = format!(
            "<topic><kind>NO_KEY</kind><name>{TOPIC}</name><dataType>Sim</dataType></topic>"
        );
        let writer = format!(
            "<dds><data_writer>{topic}<qos><reliability><kind>RELIABLE</kind></reliability>\
             </qos></data_writer></dds>"
        );
        let reader = format!(
            "<dds><data_reader>{topic}<qos><reliability><kind>RELIABLE</kind></reliability>\
             </qos></data_reader></dds>"
        );
        let objects = [
            (PARTICIPANT, participant, VariantExtra::DomainId(0)),
            (PUBLISHER, "", VariantExtra::Parent(PARTICIPANT)),
            (SUBSCRIBER, "", VariantExtra::Parent(PARTICIPANT)),
            (READER, &reader, VariantExtra::Parent(SUBSCRIBER)),
            (WRITER, &writer, VariantExtra::Parent(PUBLISHER)),
        ];
        for (id, xml, extra) in objects {
            let variant = ObjectVariant {
                kind: id.kind(),
                representation: Representation::Xml(xml.to_string()),
                extra,
            };
            self.client
                .create(self.now, id, variant, reuse, !reuse)
                .expect("create");
        }
        self.run_until("every object created", |w| w.statuses.len() == 5);
        let created = [status::OK, status::OK_MATCHED];
        assert!(
            self.statuses.iter().all(|(_, s)| created.contains(s)),
            "{:?}",
            self.statuses
        );
        self.client
            .read(self.now, READER, xrce_tests::unlimited_reliable_read())
            .expect("read");
    }

    /// The client writes sample `n` on its reliable stream (once its window has room).
    fn write(&mut self, n: u32) {
        loop {
            match self
                .client
                .write(self.now, stream_id::BUILTIN_RELIABLE, WRITER, &sample(n))
            {
                Ok(_) => {
                    self.written += 1;
                    return;
                }
                Err(ClientError::WindowFull) => self.step(),
                Err(e) => panic!("write {n}: {e}"),
            }
        }
    }

    /// Steps until the reader got `n` samples; they must be samples 0 to n - 1, in order,
    /// each once.
    fn expect_received(&mut self, n: u32) {
        self.run_until("every sample received", |w| w.received.len() >= n as usize);
        // A little longer: a repeat would come now.
        for _ in 0..500 {
            self.step();
        }
        assert_eq!(
            self.received,
            (0..n).map(sample).collect::<Vec<_>>(),
            "after {} worker and {} front-end crashes",
            self.crashes,
            self.frontend_crashes
        );
    }
}

#[test]
fn samples_reach_the_clients_reader_through_the_worker_in_order() {
    let mut w = World::with_writer_and_reader();
    for n in 0..40 {
        w.write(n);
    }
    w.expect_received(40);
    assert_eq!(
        w.bus.samples_on(TOPIC).len(),
        40,
        "written once each in DDS"
    );
}

/// The worker dies three times while the client writes: right after samples were handed to
/// it (held by its new writer), or once they reached the reader, or in the middle of what a
/// pass sent (the front-end gets the first half, the rest after the new worker's
/// announcement). The new workers get the client's objects and read again, the writes the
/// dead ones had not executed are resent, and the reader gets every sample, in order, once.
#[test]
fn worker_crashes_at_any_step_lose_no_sample_and_repeat_none() {
    for (gap, mid_pass) in [
        (1, false),
        (7, true),
        (23, false),
        (700, false),
        (700, true),
    ] {
        let mut w = World::with_writer_and_reader();
        for n in 0..60 {
            if n % 20 != 19 {
                w.write(n);
                w.step();
                continue;
            }
            if mid_pass {
                for _ in 0..gap {
                    w.step();
                }
                w.write(n);
                w.crash_worker_mid_pass();
            } else {
                w.write(n);
                w.step();
                for _ in 0..gap {
                    w.step();
                }
                if gap < 100 {
                    assert!(w.received.len() < w.written as usize, "samples in flight");
                }
                w.crash_worker();
            }
        }
        w.expect_received(60);
        assert_eq!(w.crashes, 3);
        assert_eq!(w.relay.stats().replays, 4, "a replay to each worker");
    }
}

/// The worker dies four times right after it handed a sample over to the front-end and
/// before the front-end heard that the sample's write was taken (the progress that would
/// have said so dies with it). The front-end resends that write to the new worker, whose new
/// DDS writer publishes it again under another identity; the read knows the write by its
/// origin and does not deliver it twice.
#[test]
fn a_worker_that_dies_between_delivering_a_sample_and_acknowledging_its_write_repeats_none() {
    let mut w = World::with_writer_and_reader();
    w.write(0);
    w.run_until("the first sample, past the new writer's hold", |w| {
        w.received.len() == 1
    });
    for n in 1..40 {
        w.write(n);
        if n % 10 == 5 {
            w.crash_worker_after_handing_a_sample_over();
            // Past the new writer's hold, so that the next crash finds samples delivered.
            w.run_until("every sample so far", |w| {
                w.received.len() >= w.written as usize
            });
        }
        w.step();
    }
    w.expect_received(40);
    assert_eq!(w.crashes, 4);
    let stats = w.relay.stats();
    assert!(
        stats.writes_resent >= 4,
        "the writes whose acknowledgement died were resent: {stats:?}"
    );
    assert!(
        stats.resent_samples_already_delivered >= 4,
        "a delivered sample resent at each crash: {stats:?}"
    );
}

/// One datagram in five lost each way, and a worker crash: the reliable streams resend, and
/// every sample still arrives once, in order.
#[test]
fn a_lossy_link_and_a_worker_crash_delay_samples_but_lose_and_repeat_none() {
    let mut w = World::with_writer_and_reader();
    w.lose_every = 5;
    for n in 0..50 {
        w.write(n);
        w.step();
        if n == 25 {
            w.crash_worker();
        }
    }
    w.expect_received(50);
}

/// A board that resets (micro-ROS after a watchdog reset): the same client key connects
/// again without deleting its session, creates its objects again with REUSE and reads
/// again; what it writes afterwards reaches its reader, each sample once.
#[test]
fn a_client_that_resets_and_creates_its_objects_again_with_reuse_keeps_publishing() {
    let mut w = World::with_writer_and_reader();
    for n in 0..10 {
        w.write(n);
    }
    w.run_until("the samples before the reset", |w| w.received.len() == 10);
    let key = w.client.config().key;
    let writers = w.bus.writers_made.get();
    w.client = Client::new(ClientConfig::new(key));
    w.client.connect(w.now);
    w.run_until("connected again", |w| w.client.is_connected());
    w.create_objects(true);
    assert!(
        w.statuses.iter().all(|(_, s)| *s == status::OK_MATCHED),
        "every object found as it was: {:?}",
        w.statuses
    );
    assert_eq!(w.bus.writers_made.get(), writers, "the DDS writer kept");
    for n in 10..40 {
        w.write(n);
    }
    w.expect_received(40);
}

/// The front-end dies after handing a client's reliable message over to the worker, which
/// wrote its sample, and before storing that it took the message (four times in a run). The
/// client sends the message again to the successor, which learns from the worker what it
/// executed for its predecessor and does not hand that sample over again: every sample is
/// written to DDS once and reaches the reader once, in order.
#[test]
fn a_frontend_that_dies_between_handing_over_and_storing_repeats_no_write() {
    let mut w = World::publishing_keeping_sessions();
    for n in 1..50 {
        w.write(n);
        if n % 12 == 5 {
            w.crash_frontend_after_hand_over();
            assert!(
                w.bus.samples_on(TOPIC).contains(&sample(n)),
                "the worker wrote sample {n} before the front-end died"
            );
        }
        w.step();
    }
    w.expect_received(50);
    assert_eq!(w.frontend_crashes, 4);
    assert_eq!(
        w.bus.samples_on(TOPIC),
        (0..50).map(sample).collect::<Vec<_>>(),
        "each sample written to DDS once, in order"
    );
}

/// Front-end crashes on a link that loses one datagram in five each way, with a worker crash
/// before them: every sample reaches the reader, in order, once (the writes whose
/// acknowledgement died with the worker included: resent, their samples are known by their
/// origin). Among the crashes,
/// one datagram (the resend of a lost message) lets the session core deliver the ten
/// messages it had kept as early, and all their writes go to the worker before the
/// front-end dies and before it stored any of them: the worker's last executed write is
/// then several messages ahead of the stored session, and the successor skips the writes of
/// all of them.
#[test]
fn frontend_crashes_after_a_worker_crash_on_a_lossy_link_repeat_nothing() {
    let mut w = World::publishing_keeping_sessions();
    w.lose_every = 5;
    for n in 1..60 {
        w.write(n);
        match n {
            23 => w.crash_worker(),
            _ if n % 15 == 4 || n % 15 == 11 => w.crash_frontend_after_hand_over(),
            _ => {}
        }
        w.step();
    }
    w.expect_received(60);
    assert_eq!((w.frontend_crashes, w.crashes), (8, 1));
}
