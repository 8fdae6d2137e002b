//! The worker over the fake backend and a link in memory: what it makes, writes, holds and
//! deletes in DDS for the XRCE objects of a client, and what reaches the front-end. Time is
//! the harness's: it moves only when a test advances it.

use super::release_gate::RELEASE_GATE_MAX;
use super::*;
use crate::backend::fake::{Fake, FakeBus};
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::{DataDeliveryControl, Representation};

mod domains;
mod filters;
mod link;
mod origins;
mod progress;
mod services;

const FE: u32 = 7;
const CLIENT: ClientKey = ClientKey([0xaa, 0xbb, 0xcc, 0x01]);
const OTHER: ClientKey = ClientKey([0xaa, 0xbb, 0xcc, 0x02]);

const PARTICIPANT: ObjectId = ObjectId::new(1, object_kind::PARTICIPANT);
const PUBLISHER: ObjectId = ObjectId::new(1, object_kind::PUBLISHER);
const SUBSCRIBER: ObjectId = ObjectId::new(1, object_kind::SUBSCRIBER);
const WRITER: ObjectId = ObjectId::new(1, object_kind::DATAWRITER);
const READER: ObjectId = ObjectId::new(1, object_kind::DATAREADER);
const OTHER_WRITER: ObjectId = ObjectId::new(2, object_kind::DATAWRITER);
const TYPES: ObjectId = ObjectId::new(1, object_kind::TYPE);

const TOPIC: &str = "HelloWorldTopic";

/// The generation of the harness's workers.
const GENERATION: u32 = 0x11;

/// The default settings of a test worker.
fn config() -> WorkerConfig {
    WorkerConfig {
        instance: "worker-test".into(),
        backend: Default::default(),
        dds: DdsConfig::default(),
        references: Default::default(),
        ros_graph: false,
        share_writers: false,
        frontend_grace: Duration::from_secs(30),
        domains: DomainPolicy::default(),
        bounds: crate::bounds::WorkerBounds::default(),
        default_domain: 0,
    }
}

/// A writer on `topic`: keyed ones have the type `Keyed` (defined by the client's TYPE
/// object), the others a type the worker does not know.
fn writer_xml(topic: &str, kind: &str, durability: &str) -> String {
    let ty = type_for(kind);
    format!(
        "<dds><data_writer><topic><kind>{kind}</kind><name>{topic}</name>\
         <dataType>{ty}</dataType></topic><qos><durability><kind>{durability}</kind>\
         </durability></qos></data_writer></dds>"
    )
}

fn reader_xml(topic: &str, kind: &str) -> String {
    let ty = type_for(kind);
    format!(
        "<dds><data_reader><topic><kind>{kind}</kind><name>{topic}</name>\
         <dataType>{ty}</dataType></topic><qos><reliability><kind>RELIABLE</kind>\
         </reliability></qos></data_reader></dds>"
    )
}

fn type_for(kind: &str) -> &'static str {
    if kind == "WITH_KEY" {
        "Keyed"
    } else {
        "HelloWorld"
    }
}

const KEYED_TYPE: &str = r#"<dds><types><struct name="Keyed">
    <member name="id" key="true" type="int32"/>
    <member name="value" type="int32"/>
  </struct></types></dds>"#;

/// A `Keyed` sample, little endian.
fn keyed(id: i32, value: i32) -> Vec<u8> {
    [id.to_le_bytes(), value.to_le_bytes()].concat()
}

fn variant(kind: u8, xml: &str, extra: VariantExtra) -> Vec<u8> {
    let mut b = Vec::new();
    ObjectVariant {
        kind,
        representation: Representation::Xml(xml.to_string()),
        extra,
    }
    .encode(&mut CdrWriter::new(&mut b, true));
    b
}

/// A worker over a fake backend and a link in memory.
struct Harness {
    worker: Worker<MemoryWorkerLink>,
    bus: Rc<FakeBus>,
}

impl Harness {
    fn new(share_writers: bool) -> Self {
        Self::with(|c| c.share_writers = share_writers)
    }

    /// A worker over a fake backend with the settings `configure` makes of the defaults.
    fn with(configure: impl FnOnce(&mut WorkerConfig)) -> Self {
        let mut config = config();
        configure(&mut config);
        Self::over(config, MemoryWorkerLink::default())
    }

    /// A worker with `config` over a new fake backend and `link`.
    fn over(config: WorkerConfig, link: MemoryWorkerLink) -> Self {
        let (fake, bus) = Fake::new().expect("fake backend");
        let worker =
            Worker::new(config, Box::new(fake), link, GENERATION, Instant::now()).expect("worker");
        Harness { worker, bus }
    }

    /// Moves the worker's time on by `by`.
    fn advance(&mut self, by: Duration) {
        self.worker.now += by;
    }

    /// The replies the front-end got since the last call, decoded, oldest first.
    fn replies(&mut self) -> Vec<ReplyMessage<'static>> {
        self.worker
            .link
            .take(FE)
            .into_iter()
            .map(|m| {
                let m = ReplyMessage::decode(&m).expect("reply");
                ReplyMessage::new(m.route, m.reply.into_owned())
            })
            .collect()
    }

    fn create(&mut self, client: ClientKey, id: ObjectId, body: &[u8]) -> Result<(), OpError> {
        self.worker.create((FE, client, id), body, false, true, 0)
    }

    /// A participant with a publisher and a subscriber (and the keyed type).
    fn participant(&mut self, client: ClientKey) {
        let p = variant(
            object_kind::PARTICIPANT,
            "<dds><participant><rtps><name>p</name></rtps></participant></dds>",
            VariantExtra::DomainId(3),
        );
        self.create(client, PARTICIPANT, &p).expect("participant");
        let types = variant(object_kind::TYPE, KEYED_TYPE, VariantExtra::None);
        self.create(client, TYPES, &types).expect("types");
        for (id, kind) in [
            (PUBLISHER, object_kind::PUBLISHER),
            (SUBSCRIBER, object_kind::SUBSCRIBER),
        ] {
            let g = variant(kind, "", VariantExtra::Parent(PARTICIPANT));
            self.create(client, id, &g).expect("group");
        }
    }

    fn writer(&mut self, client: ClientKey, id: ObjectId, xml: &str) -> Result<(), OpError> {
        let body = variant(
            object_kind::DATAWRITER,
            xml,
            VariantExtra::Parent(PUBLISHER),
        );
        self.create(client, id, &body)
    }

    fn reader(&mut self, client: ClientKey, id: ObjectId, xml: &str) -> Result<(), OpError> {
        let body = variant(
            object_kind::DATAREADER,
            xml,
            VariantExtra::Parent(SUBSCRIBER),
        );
        self.create(client, id, &body)
    }

    /// Starts an unlimited read on a reader.
    fn read(&mut self, client: ClientKey, id: ObjectId) {
        self.read_paced(client, id, 0);
    }

    /// Starts an unlimited read on a reader, at most one sample per `pace_ms` (0: no pace).
    fn read_paced(&mut self, client: ClientKey, id: ObjectId, pace_ms: u16) {
        let mut body = Vec::new();
        ReadSpecification {
            data_format: xrce_common::wire::data_format::DATA,
            delivery_control: Some(DataDeliveryControl {
                max_samples: u16::MAX,
                min_pace_period: pace_ms,
                ..Default::default()
            }),
            ..Default::default()
        }
        .encode(&mut CdrWriter::new(&mut body, true));
        self.worker
            .start_read(
                (FE, client, id),
                xrce_common::wire::RequestId([0, 9]),
                false,
                &body,
            )
            .expect("read");
    }

    /// A pass `by` after the last; how many samples of the topic were written so far.
    fn pass_after(&mut self, by: Duration) -> usize {
        self.advance(by);
        let now = self.worker.now;
        self.worker.pass(now).expect("pass");
        self.bus.samples_on(TOPIC).len()
    }

    /// A release of held samples `by` after the last look; how many samples of the topic
    /// were written so far.
    fn release_after(&mut self, by: Duration) -> usize {
        self.advance(by);
        self.worker.release_rematched();
        self.bus.samples_on(TOPIC).len()
    }

    /// Hands the worker a pause or resume of the client's read.
    fn pause_read(&mut self, pause: bool) {
        let route = Route::object(FE, CLIENT, Default::default(), READER);
        self.worker.process_request(RequestMessage {
            route,
            progress_can_wait: false,
            request: if pause {
                Request::PauseRead
            } else {
                Request::ResumeRead
            },
        });
    }

    /// Lets a holding writer's readers have matched long enough, then releases (twice: the
    /// first sample goes alone).
    fn matched_long_ago(&mut self, client: ClientKey, id: ObjectId) {
        self.worker.release_rematched();
        if let Some(Entity {
            kind: EntityKind::Writer { rematch: r, .. },
            ..
        }) = self.worker.entities.value_mut(&(FE, client, id))
        {
            r.matched_at = r.matched_at.and_then(|t| t.checked_sub(REMATCH_MARGIN));
        }
        // The first sample alone, then (acknowledged) the next batch.
        self.worker.release_rematched();
        self.worker.release_rematched();
    }

    /// The bodies of the samples the front-end got, in order, with their writers.
    fn samples(&mut self) -> Vec<(backend::Guid, i64, Vec<u8>)> {
        self.replies()
            .into_iter()
            .filter_map(|m| match m.reply {
                Reply::Sample(s) => Some((
                    s.identity.writer,
                    s.identity.sequence_number,
                    s.data.to_vec(),
                )),
                _ => None,
            })
            .collect()
    }
}

/// A client's participant with a reader and a new volatile writer of one topic.
fn reader_and_new_writer() -> Harness {
    reader_and_new_writer_over(Harness::new(false))
}

/// [`reader_and_new_writer`] in `t`.
fn reader_and_new_writer_over(t: Harness) -> Harness {
    reader_and_new_writer_of(t, "NO_KEY")
}

/// [`reader_and_new_writer`] in `t`, of a topic of `kind` (`NO_KEY`, `WITH_KEY`).
fn reader_and_new_writer_of(mut t: Harness, kind: &str) -> Harness {
    t.participant(CLIENT);
    t.reader(CLIENT, READER, &reader_xml(TOPIC, kind))
        .expect("reader");
    t.writer(CLIENT, WRITER, &writer_xml(TOPIC, kind, "VOLATILE"))
        .expect("writer");
    t
}

/// A new writer that held `n` samples, matched long enough ago and released, with its
/// readers not acknowledging.
fn released_unacknowledged(n: u64) -> Harness {
    let mut t = reader_and_new_writer();
    for i in 0..n {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, 0, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    assert!(t.bus.written.borrow().is_empty());
    t.bus.acknowledged.set(false);
    t.matched_long_ago(CLIENT, WRITER);
    t
}

/// Released held samples: the first alone, the rest only once it was acknowledged (or
/// after a while), so every remote reader has seen a heartbeat before a burst.
#[test]
fn a_released_writer_sends_one_sample_first_and_the_rest_once_it_was_acknowledged() {
    let mut t = released_unacknowledged(40);
    assert_eq!(t.bus.samples_on(TOPIC), vec![keyed(0, 0)]);
    // Not acknowledged yet: the rest waits.
    t.worker.release_rematched();
    assert_eq!(t.bus.samples_on(TOPIC).len(), 1);
    // Acknowledged: the rest goes, in batches, in order.
    t.bus.acknowledged.set(true);
    t.worker.release_rematched();
    assert_eq!(t.bus.samples_on(TOPIC).len(), 1 + RELEASE_BATCH);
    while !t.worker.writers.holding.is_empty() {
        t.worker.release_rematched();
    }
    assert_eq!(
        t.bus.samples_on(TOPIC),
        (0..40).map(|i| keyed(i, 0)).collect::<Vec<_>>()
    );
}

/// Held samples go out with the spacing their front-end received them with, faster by
/// [`RELEASE_CATCH_UP`]: a second's worth is not one burst for the readers.
#[test]
fn held_samples_are_released_with_the_spacing_they_came_with() {
    let mut t = reader_and_new_writer();
    // Received 100 ms apart.
    for i in 0..5 {
        t.worker
            .write_one(
                (FE, CLIENT, WRITER),
                i,
                i * 100_000,
                true,
                &keyed(i as i32, 0),
                false,
            )
            .expect("write");
    }
    t.matched_long_ago(CLIENT, WRITER);
    let step = Duration::from_millis(100 / RELEASE_CATCH_UP);
    // The first at once; the next one step after.
    assert_eq!(t.bus.samples_on(TOPIC).len(), 1);
    assert_eq!(t.worker.next_release(), Some(t.worker.now + step));
    for n in 2..=5 {
        t.advance(step - Duration::from_millis(1));
        t.worker.release_rematched();
        assert_eq!(t.bus.samples_on(TOPIC).len(), n - 1, "not yet due");
        t.advance(Duration::from_millis(1));
        t.worker.release_rematched();
        assert_eq!(t.bus.samples_on(TOPIC).len(), n);
    }
    assert!(t.worker.writers.holding.is_empty());
    assert_eq!(t.worker.next_release(), None);
}

/// Eight writers holding 16 samples each, matched long enough ago.
fn eight_holding_writers() -> Harness {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.reader(CLIENT, READER, &reader_xml(TOPIC, "NO_KEY"))
        .expect("reader");
    let writers: Vec<ObjectId> = (0..8)
        .map(|i| ObjectId::new(10 + i, object_kind::DATAWRITER))
        .collect();
    for (n, w) in writers.iter().enumerate() {
        t.writer(CLIENT, *w, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
            .expect("writer");
        for i in 0..16u64 {
            let seq = n as u64 * 100 + i;
            t.worker
                .write_one((FE, CLIENT, *w), seq, 0, true, &keyed(seq as i32, 0), false)
                .expect("write");
        }
    }
    for w in &writers {
        t.matched_long_ago(CLIENT, *w);
    }
    t
}

/// Many writers draining at once write at most [`RELEASE_PASS_MAX`] held samples in a
/// pass (the worker's time standing still), each writer's in order.
#[test]
fn a_pass_releases_a_bounded_number_of_held_samples_over_all_writers() {
    let mut t = eight_holding_writers();
    let mut passes = 0;
    let mut before = t.bus.samples_on(TOPIC).len();
    while !t.worker.writers.holding.is_empty() {
        t.worker.release_rematched();
        let now = t.bus.samples_on(TOPIC).len();
        assert!(
            now - before <= RELEASE_PASS_MAX,
            "{} in one pass",
            now - before
        );
        before = now;
        passes += 1;
        assert!(passes < 100, "the writers drain");
    }
    let written = t.bus.samples_on(TOPIC);
    assert_eq!(written.len(), 8 * 16);
    for n in 0..8 {
        let mine: Vec<_> = written
            .iter()
            .filter(|s| (n * 100..n * 100 + 16).any(|seq| **s == keyed(seq, 0)))
            .cloned()
            .collect();
        assert_eq!(
            mine,
            (0..16).map(|i| keyed(n * 100 + i, 0)).collect::<Vec<_>>()
        );
    }
}

/// A stopping worker's writers are held neither to the schedule nor to the pass budget: the
/// drain has seconds, not the time the clients took.
#[test]
fn a_stopping_worker_releases_past_the_pass_budget() {
    let mut t = eight_holding_writers();
    t.worker.stop();
    t.worker.release_rematched();
    t.worker.release_rematched();
    assert_eq!(t.bus.samples_on(TOPIC).len(), 8 * 16);
    assert!(t.worker.writers.holding.is_empty());
}

/// A reader that never acknowledges holds the release up only so long.
#[test]
fn an_unacknowledged_first_sample_holds_the_rest_back_only_briefly() {
    let mut t = released_unacknowledged(3);
    assert_eq!(t.bus.samples_on(TOPIC).len(), 1);
    t.advance(RELEASE_FIRST_ACK_WAIT);
    t.worker.release_rematched();
    assert_eq!(t.bus.samples_on(TOPIC).len(), 3);
    assert!(t.worker.writers.holding.is_empty());
}

/// A stopping worker does not take what a writer holds for its readers away with it: it
/// counts as not done with (the drain waits for it), and the writer releases it, in order,
/// without waiting for its readers any longer.
#[test]
fn a_stopping_worker_releases_what_its_writers_hold() {
    let mut t = reader_and_new_writer();
    for i in 0..3 {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, 0, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    assert!(t.bus.written.borrow().is_empty());
    assert_eq!(t.worker.unacknowledged_writes(), 3, "held samples count");
    t.worker.stop();
    let now = t.worker.now;
    for _ in 0..10 {
        t.worker.pass(now).expect("pass");
    }
    assert_eq!(
        t.bus.samples_on(TOPIC),
        (0..3).map(|i| keyed(i, 0)).collect::<Vec<_>>()
    );
    assert!(t.worker.writers.holding.is_empty());
}

#[test]
fn a_writer_holds_until_matched_then_its_samples_reach_a_reader_in_order() {
    let mut t = reader_and_new_writer();
    assert_eq!(t.bus.domains.borrow().as_slice(), &[3]);
    t.read(CLIENT, READER);
    for i in 0..3 {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, 0, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    // New writers hold their first samples until their readers matched a while.
    assert!(t.bus.written.borrow().is_empty());
    assert!(t.worker.writers.holding.contains(&(FE, CLIENT, WRITER)));
    t.matched_long_ago(CLIENT, WRITER);
    // The first alone, then (acknowledged) the rest: room in the worker's reader.
    assert!(t.worker.writers.holding.is_empty());
    assert_eq!(
        t.bus.samples_on(TOPIC),
        (0..3).map(|i| keyed(i, 0)).collect::<Vec<_>>()
    );
    // What the reader took goes to the front-end with the writer's identity, in order.
    t.advance(Duration::from_millis(5));
    let now = t.worker.now;
    t.worker.pass(now).expect("pass");
    let got = t.samples();
    let writer = match &t
        .worker
        .entities
        .value(&(FE, CLIENT, WRITER))
        .expect("w")
        .kind
    {
        EntityKind::Writer { writer: w, .. } => w.raw.guid(),
        _ => unreachable!("a writer"),
    };
    assert_eq!(
        got,
        (0..3)
            .map(|i| (writer, i64::from(i) + 1, keyed(i, 0)))
            .collect::<Vec<_>>()
    );
    assert_eq!(t.worker.samples_taken, 3);
}

#[test]
fn removing_a_client_deletes_every_backend_endpoint_and_index_entry() {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.participant(OTHER);
    for c in [CLIENT, OTHER] {
        t.reader(c, READER, &reader_xml(TOPIC, "NO_KEY"))
            .expect("r");
        t.writer(c, WRITER, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
            .expect("w");
        t.read(c, READER);
    }
    assert_eq!((t.bus.readers_of(TOPIC), t.bus.writers_of(TOPIC)), (2, 2));
    t.worker.remove_where(|c| c.1 == CLIENT);
    assert_eq!((t.bus.readers_of(TOPIC), t.bus.writers_of(TOPIC)), (1, 1));
    assert_eq!(t.worker.readers.by_token.len(), 1);
    assert_eq!(t.worker.readers.reads.len(), 1);
    assert!(t.worker.entities.iter().all(|(k, _)| k.1 == OTHER));
    t.worker.remove_subtree((FE, OTHER, PARTICIPANT));
    assert_eq!((t.bus.readers_of(TOPIC), t.bus.writers_of(TOPIC)), (0, 0));
    assert!(t.worker.readers.by_token.is_empty() && t.worker.readers.reads.is_empty());
    assert!(t.worker.writers.holding.is_empty());
    // The client's TYPE object has no parent and stays until the client goes.
    assert_eq!(t.worker.entities.len(), 1);
}

#[test]
fn a_replaced_reader_is_deleted_in_the_backend_and_its_token_forgotten() {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.reader(CLIENT, READER, &reader_xml(TOPIC, "NO_KEY"))
        .expect("first");
    let first: Vec<ReaderToken> = t.worker.readers.by_token.keys().copied().collect();
    t.reader(CLIENT, READER, &reader_xml("Other", "NO_KEY"))
        .expect("replacement");
    assert_eq!(t.bus.readers_made.get(), 2);
    assert_eq!((t.bus.readers_of(TOPIC), t.bus.readers_of("Other")), (0, 1));
    assert_eq!(t.worker.readers.by_token.len(), 1);
    assert!(!t.worker.readers.by_token.contains_key(&first[0]));
}

#[test]
fn disposes_need_a_key_and_reach_the_backend_in_order_with_writes() {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.writer(CLIENT, WRITER, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
        .expect("keyless");
    let err = t
        .worker
        .write_one((FE, CLIENT, WRITER), 1, 0, true, &keyed(1, 1), true)
        .expect_err("a dispose without a key");
    assert_eq!(err.status(), status::ERR_INCOMPATIBLE);
    let keyed_writer = ObjectId::new(2, object_kind::DATAWRITER);
    t.writer(
        CLIENT,
        keyed_writer,
        &writer_xml("Shapes", "WITH_KEY", "VOLATILE"),
    )
    .expect("keyed");
    t.reader(CLIENT, READER, &reader_xml("Shapes", "WITH_KEY"))
        .expect("reader");
    let key = (FE, CLIENT, keyed_writer);
    // A sample that is not of the topic's type is refused at once, not when released.
    let err = t
        .worker
        .write_one(key, 2, 0, true, &[1, 2], false)
        .expect_err("not a Keyed");
    assert_eq!(err.status(), status::ERR_INVALID_DATA);
    t.worker
        .write_one(key, 3, 0, true, &keyed(5, 50), false)
        .expect("write");
    t.worker
        .write_one(key, 4, 0, true, &keyed(5, 0), true)
        .expect("dispose");
    t.matched_long_ago(CLIENT, keyed_writer);
    let written: Vec<(bool, Vec<u8>)> = t
        .bus
        .written
        .borrow()
        .iter()
        .map(|w| (w.dispose, w.sample.body.to_vec()))
        .collect();
    assert_eq!(written, vec![(false, keyed(5, 50)), (true, keyed(5, 0))]);
    // Nothing is held any more.
    assert!(t.worker.oldest_held().is_empty());
}

#[test]
fn shared_writers_share_one_backend_writer_per_qos_and_byte_order() {
    let mut t = Harness::new(true);
    t.participant(CLIENT);
    t.participant(OTHER);
    let volatile = writer_xml(TOPIC, "NO_KEY", "VOLATILE");
    t.writer(CLIENT, WRITER, &volatile).expect("first");
    t.writer(OTHER, WRITER, &volatile).expect("second");
    assert_eq!(t.bus.writers_made.get(), 1);
    // The shared DDS writer keeps every client's resend window.
    let (topic, qos) = t.bus.endpoints.borrow()[0].clone();
    assert_eq!(topic, TOPIC);
    assert_eq!(
        qos.history,
        crate::backend::policies::History::KeepLast(
            crate::backend::qos::DEFAULT_DEPTH * SHARE_GROUP as i32
        )
    );
    // Transient-local writers keep history for late joiners: never shared.
    let transient = writer_xml(TOPIC, "NO_KEY", "TRANSIENT_LOCAL");
    t.writer(
        CLIENT,
        ObjectId::new(2, object_kind::DATAWRITER),
        &transient,
    )
    .expect("third");
    t.writer(OTHER, ObjectId::new(2, object_kind::DATAWRITER), &transient)
        .expect("fourth");
    assert_eq!(t.bus.writers_made.get(), 3);
    // A big-endian client gets a writer of its own.
    let body = variant(
        object_kind::DATAWRITER,
        &volatile,
        VariantExtra::Parent(PUBLISHER),
    );
    t.worker
        .create(
            (FE, OTHER, ObjectId::new(3, object_kind::DATAWRITER)),
            &body,
            false,
            false,
            0,
        )
        .expect("big endian");
    assert_eq!(t.bus.writers_made.get(), 4);
    // The shared DDS writer lives while one of its XRCE writers does.
    t.worker.remove_subtree((FE, CLIENT, WRITER));
    assert_eq!(t.bus.writers_of(TOPIC), 4);
    t.worker.remove_subtree((FE, OTHER, WRITER));
    assert_eq!(t.bus.writers_of(TOPIC), 3);
    // Only the big-endian writer's entry is left among the shared ones.
    assert_eq!(t.worker.writers.shared.len(), 1);
}

/// A new writer that held `n` samples, released (its first sample alone) while the read of
/// the worker's own reader of the topic, which keeps the last `depth` samples, is paused.
fn released_to_a_paused_reader(n: u64, depth: u32) -> Harness {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    let xml = format!(
        "<dds><data_reader><topic><kind>NO_KEY</kind><name>{TOPIC}</name>\
         <dataType>HelloWorld</dataType></topic><qos><reliability><kind>RELIABLE</kind>\
         </reliability><history><kind>KEEP_LAST</kind><depth>{depth}</depth></history>\
         </qos></data_reader></dds>"
    );
    t.reader(CLIENT, READER, &xml).expect("reader");
    t.writer(CLIENT, WRITER, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
        .expect("writer");
    t.read(CLIENT, READER);
    for i in 0..n {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, 0, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    t.pause_read(true);
    t.matched_long_ago(CLIENT, WRITER);
    t
}

/// Draining writers put at most half the history of this worker's own reader of their
/// topic into it before it took some: a paused read (its client is slow) keeps the rest
/// held, not overwritten in the reader's history.
#[test]
fn a_draining_writer_fills_at_most_half_a_paused_readers_history() {
    let mut t = released_to_a_paused_reader(100, 64);
    assert_eq!(t.bus.samples_on(TOPIC).len(), 1 + RELEASE_BATCH);
    let ms = Duration::from_millis;
    let waiting: Vec<usize> = (0..5).map(|_| t.release_after(ms(100))).collect();
    assert_eq!(waiting, vec![32; 5], "a batch at a time, up to 32");
    // Resumed: each pass takes what waits, and releases a batch more.
    t.pause_read(false);
    let written: Vec<usize> = (0..5).map(|_| t.pass_after(ms(5))).collect();
    assert_eq!(written, vec![48, 64, 80, 96, 100]);
    assert_eq!(t.worker.dropped.get("release_gate_expired"), None);
}

/// Another writer of the topic does not add its own batches to what the paused reader
/// has not taken: the bound is the topic's.
#[test]
fn writers_of_one_topic_share_the_readers_room() {
    let mut t = released_to_a_paused_reader(40, 64);
    t.writer(
        CLIENT,
        OTHER_WRITER,
        &writer_xml(TOPIC, "NO_KEY", "VOLATILE"),
    )
    .expect("writer");
    for i in 0..40 {
        t.worker
            .write_one(
                (FE, CLIENT, OTHER_WRITER),
                i,
                0,
                true,
                &keyed(i as i32, 0),
                false,
            )
            .expect("write");
    }
    t.matched_long_ago(CLIENT, OTHER_WRITER);
    let ms = Duration::from_millis;
    let waiting: Vec<usize> = (0..5).map(|_| t.release_after(ms(100))).collect();
    assert_eq!(waiting.last(), Some(&32), "{waiting:?}");
}

/// A reader whose client takes nothing does not keep the writers' samples held for ever;
/// once it takes again, the bound holds again.
#[test]
fn a_reader_that_takes_nothing_holds_the_release_back_only_so_long() {
    let mut t = released_to_a_paused_reader(40, 2);
    let ms = Duration::from_millis;
    assert_eq!(t.release_after(RELEASE_GATE_MAX - ms(1)), 1);
    assert_eq!(t.release_after(ms(1)), 1 + RELEASE_BATCH);
    assert_eq!(t.worker.dropped.get("release_gate_expired"), Some(&1));
    // Open until that reader takes again.
    assert_eq!(t.release_after(ms(5)), 1 + 2 * RELEASE_BATCH);
    t.pause_read(false);
    assert_eq!(
        t.pass_after(ms(5)),
        1 + 2 * RELEASE_BATCH + 1,
        "one at a time again"
    );
    assert_eq!(t.worker.dropped.get("release_gate_expired"), Some(&1));
}

/// A reader that takes, however slowly, keeps the bound: each take starts the wait again,
/// so the release follows its pace rather than overrunning it.
#[test]
fn a_slow_reader_keeps_the_bound() {
    let mut t = released_to_a_paused_reader(40, 2);
    let ms = Duration::from_millis;
    assert_eq!(t.release_after(ms(600)), 1, "waiting for the paused reader");
    // The reader takes the first sample: the next goes, and the read pauses again.
    t.pause_read(false);
    assert_eq!(t.pass_after(ms(5)), 2);
    t.pause_read(true);
    assert_eq!(t.release_after(ms(0)), 2, "waiting again");
    assert_eq!(t.release_after(ms(600)), 2);
    assert_eq!(
        t.release_after(ms(399)),
        2,
        "a second since its last take, not in all"
    );
    assert_eq!(t.release_after(ms(1)), 2 + RELEASE_BATCH);
    assert_eq!(t.worker.dropped.get("release_gate_expired"), Some(&1));
}

/// A drain waits for a reader that takes slowly only so long in all: then it follows its
/// schedule, so that the writer's other readers and its clients are not held to that
/// reader's pace.
#[test]
fn a_drain_waits_for_a_slow_reader_only_so_long_in_all() {
    let mut t = released_to_a_paused_reader(40, 2);
    let ms = Duration::from_millis;
    let mut written = 1;
    for _ in 0..3 {
        assert_eq!(t.release_after(ms(0)), written);
        assert_eq!(t.release_after(ms(900)), written, "waiting for the reader");
        // It takes one: the next goes.
        t.pause_read(false);
        written += 1;
        assert_eq!(t.pass_after(ms(5)), written);
        t.pause_read(true);
    }
    assert_eq!(t.release_after(ms(0)), written);
    assert_eq!(t.release_after(ms(200)), written, "2.9 s waited");
    assert_eq!(t.release_after(ms(100)), written + RELEASE_BATCH);
    assert_eq!(t.worker.dropped.get("release_gate_outwaited"), Some(&1));
    assert_eq!(t.worker.dropped.get("release_gate_expired"), None);
}
