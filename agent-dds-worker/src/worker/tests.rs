//! The worker over the fake backend: what it makes, writes, holds and deletes in DDS for the
//! XRCE objects of a client, and what reaches the front-end (through real shared memory).

use super::*;
use crate::backend::fake::{Fake, FakeBus};
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::{DataDeliveryControl, Representation};
use xrce_ipc::shm::ServiceKind;

const FE: u32 = 7;
const CLIENT: ClientKey = ClientKey([0xaa, 0xbb, 0xcc, 0x01]);
const OTHER: ClientKey = ClientKey([0xaa, 0xbb, 0xcc, 0x02]);

const PARTICIPANT: ObjectId = ObjectId::new(1, object_kind::PARTICIPANT);
const PUBLISHER: ObjectId = ObjectId::new(1, object_kind::PUBLISHER);
const SUBSCRIBER: ObjectId = ObjectId::new(1, object_kind::SUBSCRIBER);
const WRITER: ObjectId = ObjectId::new(1, object_kind::DATAWRITER);
const READER: ObjectId = ObjectId::new(1, object_kind::DATAREADER);
const TYPES: ObjectId = ObjectId::new(1, object_kind::TYPE);

const TOPIC: &str = "HelloWorldTopic";

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

/// A worker over a fake backend, and a front-end's end of its reply channel.
struct Harness {
    worker: Worker,
    bus: Rc<FakeBus>,
    replies: xrce_ipc::shm::Receiver,
    _node: IpcNode,
}

impl Harness {
    fn new(share_writers: bool) -> Self {
        Self::with(|c| c.share_writers = share_writers)
    }

    /// A worker over a fake backend with the settings `configure` makes of the defaults.
    fn with(configure: impl FnOnce(&mut WorkerConfig)) -> Self {
        static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let instance = format!(
            "wt{}-{}",
            std::process::id() % 100_000,
            N.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        );
        let (fake, bus) = Fake::new().expect("fake backend");
        let mut config = WorkerConfig {
            instance: instance.clone(),
            dds: DdsConfig::default(),
            references: Default::default(),
            ros_graph: false,
            share_writers: false,
            frontend_grace: Duration::from_secs(30),
            domains: DomainPolicy::default(),
        };
        configure(&mut config);
        let worker = Worker::with_backend(config, Box::new(fake)).expect("worker");
        let node = IpcNode::new(&instance, "test-frontend").expect("node");
        let replies = node
            .receiver(&ipc::reply_service(&instance, FE), ServiceKind::Reply)
            .expect("reply channel");
        Harness {
            worker,
            bus,
            replies,
            _node: node,
        }
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
        let mut body = Vec::new();
        ReadSpecification {
            data_format: xrce_common::wire::data_format::DATA,
            delivery_control: Some(DataDeliveryControl {
                max_samples: u16::MAX,
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
        let mut out = Vec::new();
        self.replies
            .drain(|m| {
                let m = ReplyMessage::decode(m).expect("reply");
                if let Reply::Sample(s) = m.reply {
                    out.push((
                        s.identity.writer,
                        s.identity.sequence_number,
                        s.data.to_vec(),
                    ));
                }
            })
            .expect("drain");
        out
    }
}

/// A client's participant with a reader and a new volatile writer of one topic.
fn reader_and_new_writer() -> Harness {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.reader(CLIENT, READER, &reader_xml(TOPIC, "NO_KEY"))
        .expect("reader");
    t.writer(CLIENT, WRITER, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
        .expect("writer");
    t
}

/// A new writer that held `n` samples, matched long enough ago and released, with its
/// readers not acknowledging.
fn released_unacknowledged(n: u64) -> Harness {
    let mut t = reader_and_new_writer();
    for i in 0..n {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, true, &keyed(i as i32, 0), false)
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
    while !t.worker.holding.is_empty() {
        t.worker.release_rematched();
    }
    assert_eq!(
        t.bus.samples_on(TOPIC),
        (0..40).map(|i| keyed(i, 0)).collect::<Vec<_>>()
    );
}

/// A reader that never acknowledges holds the release up only so long.
#[test]
fn an_unacknowledged_first_sample_holds_the_rest_back_only_briefly() {
    let mut t = released_unacknowledged(3);
    assert_eq!(t.bus.samples_on(TOPIC).len(), 1);
    std::thread::sleep(RELEASE_FIRST_ACK_WAIT);
    t.worker.release_rematched();
    assert_eq!(t.bus.samples_on(TOPIC).len(), 3);
    assert!(t.worker.holding.is_empty());
}

#[test]
fn a_writer_holds_until_matched_then_its_samples_reach_a_reader_in_order() {
    let mut t = reader_and_new_writer();
    assert_eq!(t.bus.domains.borrow().as_slice(), &[3]);
    t.read(CLIENT, READER);
    for i in 0..3 {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    // New writers hold their first samples until their readers matched a while.
    assert!(t.bus.written.borrow().is_empty());
    assert!(t.worker.holding.contains(&(FE, CLIENT, WRITER)));
    t.matched_long_ago(CLIENT, WRITER);
    assert!(t.worker.holding.is_empty());
    assert_eq!(
        t.bus.samples_on(TOPIC),
        (0..3).map(|i| keyed(i, 0)).collect::<Vec<_>>()
    );
    // What the reader took goes to the front-end with the writer's identity, in order.
    t.worker
        .dds
        .ready_readers(&mut t.worker.ready)
        .expect("ready");
    let tokens: Vec<ReaderToken> = t.worker.ready.drain(..).collect();
    assert!(!tokens.is_empty());
    for k in tokens {
        if let Some(k) = t.worker.readers.get(&k).copied() {
            t.worker.pump(k);
        }
    }
    t.worker.flush();
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
    assert_eq!(t.worker.readers.len(), 1);
    assert_eq!(t.worker.reads.len(), 1);
    assert!(t.worker.entities.iter().all(|(k, _)| k.1 == OTHER));
    t.worker.remove_subtree((FE, OTHER, PARTICIPANT));
    assert_eq!((t.bus.readers_of(TOPIC), t.bus.writers_of(TOPIC)), (0, 0));
    assert!(t.worker.readers.is_empty() && t.worker.reads.is_empty());
    assert!(t.worker.holding.is_empty());
    // The client's TYPE object has no parent and stays until the client goes.
    assert_eq!(t.worker.entities.len(), 1);
}

#[test]
fn a_replaced_reader_is_deleted_in_the_backend_and_its_token_forgotten() {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.reader(CLIENT, READER, &reader_xml(TOPIC, "NO_KEY"))
        .expect("first");
    let first: Vec<ReaderToken> = t.worker.readers.keys().copied().collect();
    t.reader(CLIENT, READER, &reader_xml("Other", "NO_KEY"))
        .expect("replacement");
    assert_eq!(t.bus.readers_made.get(), 2);
    assert_eq!((t.bus.readers_of(TOPIC), t.bus.readers_of("Other")), (0, 1));
    assert_eq!(t.worker.readers.len(), 1);
    assert!(!t.worker.readers.contains_key(&first[0]));
}

#[test]
fn disposes_need_a_key_and_reach_the_backend_in_order_with_writes() {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.writer(CLIENT, WRITER, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
        .expect("keyless");
    let err = t
        .worker
        .write_one((FE, CLIENT, WRITER), 1, true, &keyed(1, 1), true)
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
        .write_one(key, 2, true, &[1, 2], false)
        .expect_err("not a Keyed");
    assert_eq!(err.status(), status::ERR_INVALID_DATA);
    t.worker
        .write_one(key, 3, true, &keyed(5, 50), false)
        .expect("write");
    t.worker
        .write_one(key, 4, true, &keyed(5, 0), true)
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
    assert_eq!(t.worker.shared_writers.len(), 1);
}

const SERVICE: &str = "<dds><{e} profile_name=\"adder\" service_name=\"/add\" \
    request_type=\"AddRequest\" reply_type=\"AddReply\">\
    <request_topic_name>rq/addRequest</request_topic_name>\
    <reply_topic_name>rr/addReply</reply_topic_name></{e}></dds>";

impl Harness {
    /// Takes what every reader with data has and sends it to the front-end.
    fn pump_ready(&mut self) {
        self.worker
            .dds
            .ready_readers(&mut self.worker.ready)
            .expect("ready");
        let keys: Vec<EntityKey> = self
            .worker
            .ready
            .drain(..)
            .filter_map(|t| self.worker.readers.get(&t).copied())
            .collect();
        for k in keys {
            self.worker.pump(k);
        }
        self.worker.flush();
    }

    /// The Sample messages the front-end got: (client, request id, body after the identity).
    fn samples_by_client(&mut self) -> Vec<(ClientKey, [u8; 2], Vec<u8>)> {
        let mut out = Vec::new();
        self.replies
            .drain(|m| {
                let m = ReplyMessage::decode(m).expect("reply");
                if let Reply::Sample(s) = m.reply {
                    out.push((m.route.client_key, m.route.request_id.0, s.data.to_vec()));
                }
            })
            .expect("drain");
        out
    }

    fn write(&mut self, client: ClientKey, id: ObjectId, request: [u8; 2], body: &[u8]) {
        let route = Route::object(FE, client, xrce_common::wire::RequestId(request), id);
        self.worker
            .write(
                (FE, client, id),
                &route,
                xrce_common::wire::data_format::DATA,
                true,
                Dialect::Eprosima,
                body,
            )
            .expect("write");
    }
}

#[test]
fn a_reply_reaches_the_requester_that_asked_and_no_other() {
    let mut t = Harness::new(false);
    t.participant(CLIENT);
    t.participant(OTHER);
    let requester = ObjectId::new(1, object_kind::REQUESTER);
    let replier = ObjectId::new(1, object_kind::REPLIER);
    for (client, id, element) in [
        (CLIENT, requester, "requester"),
        (OTHER, replier, "replier"),
    ] {
        let xml = SERVICE.replace("{e}", element);
        let kind = id.kind();
        t.create(
            client,
            id,
            &variant(kind, &xml, VariantExtra::Parent(PARTICIPANT)),
        )
        .expect("service endpoint");
        t.read(client, id);
    }
    // Both sides of RPC over DDS are reliable and volatile.
    for (topic, qos) in t.bus.endpoints.borrow().iter() {
        assert!(
            topic.starts_with("rq/") || topic.starts_with("rr/"),
            "{topic}"
        );
        assert_eq!(
            qos.reliability,
            crate::backend::policies::Reliability::Reliable
        );
        assert_eq!(
            qos.durability,
            crate::backend::policies::Durability::Volatile
        );
    }
    assert_eq!(t.bus.endpoints.borrow().len(), 4);
    t.write(CLIENT, requester, [0, 0x41], &[1, 0, 0, 0, 2, 0, 0, 0]);
    t.pump_ready();
    // The replier gets the request behind its SampleIdentity (in the sample's byte order).
    let got = t.samples_by_client();
    assert_eq!(got.len(), 1);
    let (client, read_id, body) = &got[0];
    assert_eq!((*client, *read_id), (OTHER, [0, 9]));
    assert_eq!(&body[24..], &[1, 0, 0, 0, 2, 0, 0, 0]);
    let identity = backend::decode_sample_identity(body, true).expect("identity");
    let requester_writer = match &t
        .worker
        .entities
        .value(&(FE, CLIENT, requester))
        .expect("r")
        .kind
    {
        EntityKind::Service(s) => s.writer.guid(),
        _ => unreachable!("a requester"),
    };
    assert_eq!(
        (identity.writer, identity.sequence_number),
        (requester_writer, 1)
    );
    // Its reply carries that identity; the requester gets it with its own request id.
    let mut reply = body[..24].to_vec();
    reply.extend([3, 0, 0, 0]);
    t.write(OTHER, replier, [0, 0x42], &reply);
    // A reply to another requester's request is not handed to this one.
    let mut stranger = identity;
    stranger.writer[0] ^= 0xff;
    let mut foreign = backend::encode_sample_identity(&stranger, true).to_vec();
    foreign.extend([9, 9, 9, 9]);
    t.write(OTHER, replier, [0, 0x43], &foreign);
    t.pump_ready();
    let got = t.samples_by_client();
    assert_eq!(got.len(), 1, "{got:?}");
    let (client, _, body) = &got[0];
    assert_eq!(*client, CLIENT);
    // BaseObjectRequest of the request (its request id, the requester's id), then the reply.
    assert_eq!(body[..2], [0, 0x41]);
    assert_eq!(body[2..4], requester.0);
    assert_eq!(&body[4..], &[3, 0, 0, 0]);
}

#[test]
fn partitions_are_refused_by_a_backend_without_them_and_on_endpoints() {
    let mut h = Harness::new(false);
    h.participant(CLIENT);
    let with_partition = variant(
        object_kind::PUBLISHER,
        "<dds><publisher><qos><partition><names><name>robot_a</name></names></partition>\
         </qos></publisher></dds>",
        VariantExtra::Parent(PARTICIPANT),
    );
    let err = h
        .create(
            CLIENT,
            ObjectId::new(9, object_kind::PUBLISHER),
            &with_partition,
        )
        .expect_err("partitions refused");
    assert_eq!(err.status(), status::ERR_INCOMPATIBLE);
    assert!(err.to_string().contains("PARTITION"), "{}", err);
    // An empty partition list is the default partition: accepted.
    let empty = variant(
        object_kind::PUBLISHER,
        "<dds><publisher><qos><partition><names/></partition></qos></publisher></dds>",
        VariantExtra::Parent(PARTICIPANT),
    );
    h.create(CLIENT, ObjectId::new(10, object_kind::PUBLISHER), &empty)
        .expect("default partition");
    let err = h
        .writer(
            CLIENT,
            ObjectId::new(11, object_kind::DATAWRITER),
            "<dds><data_writer><topic><kind>NO_KEY</kind><name>t</name><dataType>Keyed</dataType>\
             </topic><qos><partition><names><name>x</name></names></partition></qos>\
             </data_writer></dds>",
        )
        .expect_err("endpoint partitions refused");
    assert_eq!(err.status(), status::ERR_INCOMPATIBLE);
}

#[test]
fn a_flooded_reader_does_not_keep_the_reader_of_another_client_waiting() {
    // Two clients of one front-end: one reads a topic with a backlog of samples, the other a
    // topic with one. The front-end takes what reaches it each round (its queue holds
    // CHANNEL_DEPTH): the quiet reader's sample must not wait behind the whole flood.
    let mut t = Harness::new(false);
    for (client, topic) in [(CLIENT, "Flood"), (OTHER, "Quiet")] {
        t.participant(client);
        t.reader(client, READER, &reader_xml(topic, "NO_KEY"))
            .expect("reader");
        t.writer(client, WRITER, &writer_xml(topic, "NO_KEY", "VOLATILE"))
            .expect("writer");
        t.read(client, READER);
        t.matched_long_ago(client, WRITER);
    }
    let flood = 8 * PUMP_BATCH as u64;
    for i in 0..flood {
        t.worker
            .write_one((FE, CLIENT, WRITER), i, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    // A first round fills the front-end's queue with the flood alone.
    t.worker.pump_readers().expect("pump");
    t.worker.flush();
    t.worker
        .write_one((FE, OTHER, WRITER), 0, true, &keyed(-1, 7), false)
        .expect("write");
    let mut got: Vec<Vec<u8>> = Vec::new();
    for _ in 0..64 {
        t.worker.pump_readers().expect("pump");
        t.worker.flush();
        got.extend(t.samples().into_iter().map(|(_, _, body)| body));
        if got.len() as u64 > flood {
            break;
        }
    }
    assert_eq!(
        got.len() as u64,
        flood + 1,
        "every sample reaches the front-end"
    );
    let quiet = got
        .iter()
        .position(|b| *b == keyed(-1, 7))
        .expect("the quiet reader's sample");
    // Behind what filled the front-end's queue before it was written, not behind the rest
    // of the flood (served in hash order, the flood's reader could come first every pass and
    // refill the queue before the quiet one's turn: 768 here when it did).
    assert!(
        quiet <= ipc::CHANNEL_DEPTH,
        "the quiet sample came after {quiet} of {flood} flood samples"
    );
    // The flood itself arrives whole and in order.
    let rest: Vec<Vec<u8>> = got.into_iter().filter(|b| *b != keyed(-1, 7)).collect();
    assert_eq!(
        rest,
        (0..flood).map(|i| keyed(i as i32, 0)).collect::<Vec<_>>()
    );
}

/// A little-endian WRITE_DATA of one bare sample.
fn write(sample: &[u8]) -> Request<'_> {
    Request::Write {
        data: sample.into(),
        data_format: xrce_common::wire::data_format::DATA,
        little_endian: true,
        dialect: Dialect::Eprosima,
        status_requested: false,
    }
}

impl Harness {
    /// Hands the worker a request of the front-end (its current process) and ends the pass.
    fn request(&mut self, request: Request<'_>, seq: u64, progress_can_wait: bool) {
        let route = Route {
            op_seq: seq,
            ..Route::object(FE, CLIENT, Default::default(), WRITER)
        };
        self.worker.process_request(RequestMessage {
            route,
            progress_can_wait,
            request,
        });
        self.worker.flush();
    }

    /// What the front-end was told executed since the last call (each progress message's
    /// first number), and whether it was woken for it.
    fn progress(&mut self) -> (Vec<u64>, bool) {
        let mut executed = Vec::new();
        self.replies
            .drain(|m| {
                let m = ReplyMessage::decode(m).expect("reply");
                if let Reply::Progress { executed: e, .. } = m.reply {
                    executed.push(e);
                }
            })
            .expect("drain");
        (executed, self.replies.take_events())
    }
}

/// Progress of an operation whose progress can wait goes out without waking the
/// front-end; progress that covers any other operation wakes it.
#[test]
fn progress_wakes_the_front_end_only_for_operations_that_wait_for_it() {
    let mut t = Harness::new(false);
    // Operations that need no reply (a pause of a read that is not there).
    t.request(Request::PauseRead, 1, true);
    assert_eq!(t.progress(), (vec![1], false));
    t.request(Request::PauseRead, 2, true);
    t.request(Request::PauseRead, 3, false);
    assert_eq!(t.progress(), (vec![2, 3], true));
    // Nothing new: no message, no wake-up.
    t.worker.flush();
    assert_eq!(t.progress(), (vec![], false));
    // A reply always wakes (a write to a writer that does not exist fails with a STATUS).
    t.request(write(&keyed(1, 1)), 4, true);
    assert_eq!(t.progress(), (vec![4], true));
}

/// A write the worker holds (its writer waits for its readers to match again) is not
/// executed yet: progress that stops short of it still owes the front-end a wake-up, paid
/// when the write is released; nothing is sent while nothing changes.
#[test]
fn progress_owed_for_a_held_write_wakes_when_the_write_is_executed() {
    let mut t = reader_and_new_writer();
    // No acknowledgement by DDS readers, which would wake the front-end by itself.
    t.bus.acknowledged.set(false);
    let _ = t.progress();
    t.request(write(&keyed(1, 1)), 10, false);
    assert!(t.bus.written.borrow().is_empty(), "held");
    assert_eq!(t.progress(), (vec![9], true));
    t.worker.flush();
    assert_eq!(t.progress(), (vec![], false), "nothing new while held");
    t.matched_long_ago(CLIENT, WRITER);
    assert_eq!(t.bus.samples_on(TOPIC), vec![keyed(1, 1)]);
    t.worker.flush();
    assert_eq!(t.progress(), (vec![10], true), "executed: the owed wake-up");
    t.worker.flush();
    assert_eq!(t.progress(), (vec![], false));
}

/// Held writes whose progress can wait: their progress goes out when they are released,
/// without a wake-up.
#[test]
fn progress_of_released_writes_that_can_wait_goes_out_without_a_wake_up() {
    let mut t = reader_and_new_writer();
    t.bus.acknowledged.set(false);
    let _ = t.progress();
    t.request(write(&keyed(1, 1)), 1, true);
    t.request(write(&keyed(2, 1)), 2, true);
    assert_eq!(t.progress(), (vec![0, 0], false), "both held");
    // The first held sample goes alone (the second waits for its acknowledgement).
    t.matched_long_ago(CLIENT, WRITER);
    assert_eq!(t.bus.samples_on(TOPIC), vec![keyed(1, 1)]);
    t.worker.flush();
    assert_eq!(t.progress(), (vec![1], false));
}

// ---- Bounds: DDS domains (issue 29 item 2) ----

/// A participant object of `client` in `domain`, named `name`.
fn participant_in(domain: i16, name: &str) -> Vec<u8> {
    variant(
        object_kind::PARTICIPANT,
        &format!("<dds><participant><rtps><name>{name}</name></rtps></participant></dds>"),
        VariantExtra::DomainId(domain),
    )
}

impl Harness {
    /// A participant of `client` in `domain` with a publisher and a writer of `topic`.
    fn publisher_in(&mut self, client: ClientKey, domain: i16, topic: &str) {
        self.create(client, PARTICIPANT, &participant_in(domain, "talker"))
            .expect("participant");
        let g = variant(
            object_kind::PUBLISHER,
            "",
            VariantExtra::Parent(PARTICIPANT),
        );
        self.create(client, PUBLISHER, &g).expect("publisher");
        self.writer(client, WRITER, &writer_xml(topic, "NO_KEY", "VOLATILE"))
            .expect("writer");
    }

    /// The backend's domains with a participant now.
    fn backend_domains(&self) -> Vec<u16> {
        self.worker.dds.participant_domains()
    }
}

fn client(n: u8) -> ClientKey {
    ClientKey([0xd0, 0, 0, n])
}

/// The DDS participant of a domain goes when the last XRCE participant in it is deleted
/// (and not before): its threads and sockets go back. The ROS graph writer it had goes too.
#[test]
fn the_last_participant_of_a_domain_releases_the_domains_dds_participant() {
    let mut t = Harness::with(|c| c.ros_graph = true);
    // Two clients in domain 5, one in domain 6; ROS nodes (an rt/ topic), so the graph
    // writer of domain 5 exists too.
    t.publisher_in(CLIENT, 5, "rt/chatter");
    t.publisher_in(OTHER, 5, "rt/chatter");
    t.publisher_in(client(9), 6, "rt/other");
    std::thread::sleep(crate::ros_graph::REFRESH);
    t.worker.publish_graph();
    assert_eq!(t.bus.writers_of("ros_discovery_info"), 2, "one per domain");
    assert_eq!(t.backend_domains(), vec![5, 6]);

    t.worker.remove_where(|c| c.1 == CLIENT);
    assert_eq!(t.backend_domains(), vec![5, 6], "domain 5 still has a user");
    assert!(t.bus.released.borrow().is_empty());

    // The last user of domain 5 deletes its participant (a DELETE of the object).
    t.worker.greeted.insert((FE, 0));
    t.worker.process_request(RequestMessage::new(
        Route::object(FE, OTHER, Default::default(), PARTICIPANT),
        Request::Delete,
    ));
    assert_eq!(t.backend_domains(), vec![6], "no participant for domain 5");
    assert_eq!(t.bus.released.borrow().as_slice(), &[5]);
    assert_eq!(
        t.bus.endpoints_in(5),
        0,
        "nothing of the worker is left in domain 5 (graph writer included)"
    );
    assert_eq!(t.worker.domains.in_use().collect::<Vec<_>>(), vec![6]);
    // The graph of domain 5 is not published again (no writer, no node).
    std::thread::sleep(crate::ros_graph::REFRESH);
    t.worker.publish_graph();
    assert_eq!(t.backend_domains(), vec![6]);

    // Used again, the domain gets a new participant.
    t.publisher_in(CLIENT, 5, "rt/chatter");
    assert_eq!(t.backend_domains(), vec![5, 6]);
    t.worker.remove_where(|_| true);
    assert!(t.backend_domains().is_empty());
    let mut released = t.bus.released.borrow().clone();
    released.sort_unstable();
    assert_eq!(released, vec![5, 5, 6]);
    assert!(t.worker.domains.in_use().next().is_none());
}

/// By default at most 8 distinct domains are in use at once: a 9th is refused with
/// STATUS_ERR_RESOURCES and counted, a domain in use still takes participants, and a domain
/// released makes room.
#[test]
fn a_ninth_distinct_domain_is_refused_for_resources_until_one_is_released() {
    let mut t = Harness::new(false);
    for d in 0..8u8 {
        t.publisher_in(client(d), i16::from(d) + 10, "T");
    }
    let refused = t
        .create(client(8), PARTICIPANT, &participant_in(30, "p"))
        .expect_err("a 9th domain");
    assert_eq!(refused.status(), status::ERR_RESOURCES, "{}", refused);
    assert_eq!(t.worker.dropped.get("domains_refused"), Some(&1));
    assert!(!t
        .worker
        .entities
        .contains_key(&(FE, client(8), PARTICIPANT)));
    // Refused again: counted, and the episode's one log line is behind us.
    assert!(t
        .create(client(8), PARTICIPANT, &participant_in(31, "p"))
        .is_err());
    assert_eq!(t.worker.dropped.get("domains_refused"), Some(&2));
    // A domain in use takes more participants.
    t.create(client(8), PARTICIPANT, &participant_in(12, "p"))
        .expect("a domain in use");
    // Released, domain 10 makes room for domain 30.
    t.worker.remove_where(|c| c.1 == client(0));
    assert!(!t.backend_domains().contains(&10));
    t.create(client(9), PARTICIPANT, &participant_in(30, "p"))
        .expect("room again");
    assert_eq!(t.worker.domains.in_use().count(), 8);
}

/// With `--domains`, a domain outside the list is refused with STATUS_ERR_DENIED (and the
/// list replaces the default cap).
#[test]
fn a_domain_outside_the_allowed_list_is_denied() {
    let mut t = Harness::with(|c| {
        c.domains = DomainPolicy::from_options(Some("0-10,42".parse().expect("list")), None)
    });
    for d in (0..=10).chain([42]) {
        t.create(client(d as u8), PARTICIPANT, &participant_in(d, "p"))
            .expect("an allowed domain");
    }
    let refused = t
        .create(client(50), PARTICIPANT, &participant_in(11, "p"))
        .expect_err("not in the list");
    assert_eq!(refused.status(), status::ERR_DENIED, "{}", refused);
    assert_eq!(t.worker.dropped.get("domain_denied"), Some(&1));
    // The reply status is the refusal's.
    t.worker.greeted.insert((FE, 0));
    t.worker.process_request(RequestMessage::new(
        Route::object(FE, client(51), Default::default(), PARTICIPANT),
        Request::Create {
            description: participant_in(200, "p").into(),
            client_little_endian: true,
            replay: false,
            readers_matched: 0,
        },
    ));
    t.worker.flush();
    let mut statuses = Vec::new();
    t.replies
        .drain(|m| {
            let m = ReplyMessage::decode(m).expect("reply");
            if let Reply::Status { result, .. } = m.reply {
                statuses.push(result.status);
            }
        })
        .expect("drain");
    assert_eq!(statuses, vec![status::ERR_DENIED]);
}

/// A restarted worker gets the object graphs replayed: the domains in use before (within the
/// cap, since the old worker kept to it) are all admitted again.
#[test]
fn a_replay_to_a_new_worker_recreates_every_domain_in_use() {
    let mut before = Harness::new(false);
    for d in 0..8u8 {
        before.publisher_in(client(d), i16::from(d), "T");
    }
    assert_eq!(before.backend_domains().len(), 8);
    let mut after = Harness::new(false);
    for d in 0..8u8 {
        for (id, body) in [
            (PARTICIPANT, participant_in(i16::from(d), "talker")),
            (
                PUBLISHER,
                variant(
                    object_kind::PUBLISHER,
                    "",
                    VariantExtra::Parent(PARTICIPANT),
                ),
            ),
            (
                WRITER,
                variant(
                    object_kind::DATAWRITER,
                    &writer_xml("T", "NO_KEY", "VOLATILE"),
                    VariantExtra::Parent(PUBLISHER),
                ),
            ),
        ] {
            after
                .worker
                .create((FE, client(d), id), &body, true, true, 0)
                .expect("replayed");
        }
    }
    assert_eq!(after.backend_domains(), before.backend_domains());
    assert_eq!(after.bus.writers_of("T"), 8);
}

// ---- Bounds: content filters (issue 29 item 2) ----

const NAMED_TYPE: &str = r#"<dds><types><struct name="Named">
    <member name="id" type="int32"/>
    <member name="name" type="string"/>
  </struct></types></dds>"#;
const NAMED_TYPES: ObjectId = ObjectId::new(2, object_kind::TYPE);

/// A `Named` sample, little endian.
fn named(id: i32, name: &str) -> Vec<u8> {
    let mut b = id.to_le_bytes().to_vec();
    b.extend((name.len() as u32 + 1).to_le_bytes());
    b.extend(name.as_bytes());
    b.push(0);
    b
}

fn filtered_reader_xml(topic: &str, expression: &str) -> String {
    format!(
        "<dds><data_reader><topic><kind>NO_KEY</kind><name>{topic}</name>\
         <dataType>Named</dataType></topic>\
         <content_filter><expression>{expression}</expression></content_filter>\
         </data_reader></dds>"
    )
}

/// A LIKE that takes |name|·|pattern| steps on a name of `a`s: over any budget.
const QUADRATIC: &str = "name LIKE '%aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaab'";

impl Harness {
    /// A participant (domain 3) whose client defines `Named`, with a subscriber.
    fn named_participant(&mut self, client: ClientKey) {
        self.participant(client);
        let types = variant(object_kind::TYPE, NAMED_TYPE, VariantExtra::None);
        self.create(client, NAMED_TYPES, &types).expect("types");
    }

    /// Injects `n` samples from outside the agent on `topic` (domain 3).
    fn inject(&self, topic: &str, n: usize, body: impl Fn(usize) -> Vec<u8>) {
        for i in 0..n {
            let b = body(i);
            self.bus.inject(3, topic, || backend::Taken {
                sample: Sample::cdr(true, &b),
                identity: backend::SampleIdentity {
                    writer: [0x77; 16],
                    sequence_number: i as i64 + 1,
                },
                related: None,
                disposed: false,
                unregistered: false,
            });
        }
    }

    fn dropped(&self, reason: &str) -> u64 {
        self.worker.dropped.get(reason).copied().unwrap_or(0)
    }
}

/// A filter of more clauses than MAX_CLAUSES is refused with STATUS_ERR_RESOURCES, on a
/// reader's XML and on a READ_DATA; one at the cap is accepted.
#[test]
fn a_filter_with_too_many_clauses_is_refused_for_resources() {
    let mut t = Harness::new(false);
    t.named_participant(CLIENT);
    let clauses = |n: usize| vec!["id = 1"; n].join(" OR ");
    let at_cap = clauses(crate::filter::MAX_CLAUSES);
    t.reader(CLIENT, READER, &filtered_reader_xml("F", &at_cap))
        .expect("at the cap");
    let over = clauses(crate::filter::MAX_CLAUSES + 1);
    let refused = t
        .reader(
            CLIENT,
            ObjectId::new(2, object_kind::DATAREADER),
            &filtered_reader_xml("F", &over),
        )
        .expect_err("over the cap");
    assert_eq!(refused.status(), status::ERR_RESOURCES, "{}", refused);
    assert!(refused.to_string().contains("clauses"), "{}", refused);
    assert_eq!(t.dropped("filters_refused"), 1);
    // On a READ_DATA of the accepted reader.
    let mut body = Vec::new();
    ReadSpecification {
        data_format: xrce_common::wire::data_format::DATA,
        content_filter_expression: Some(over),
        ..Default::default()
    }
    .encode(&mut CdrWriter::new(&mut body, true));
    let refused = t
        .worker
        .start_read((FE, CLIENT, READER), Default::default(), false, &body)
        .expect_err("over the cap");
    assert_eq!(refused.status(), status::ERR_RESOURCES);
    assert_eq!(t.dropped("filters_refused"), 2);
}

/// A sample whose evaluation runs out of the evaluation budget is treated as not matching:
/// not delivered, counted as `content_filter_over_budget`, and the samples after it are
/// judged on their own.
#[test]
fn a_sample_over_the_evaluation_budget_does_not_match_and_is_counted() {
    let mut t = Harness::new(false);
    t.named_participant(CLIENT);
    let expression = format!("id = 7 OR {QUADRATIC}");
    t.reader(CLIENT, READER, &filtered_reader_xml("F", &expression))
        .expect("reader");
    t.read(CLIENT, READER);
    let long = "a".repeat(4000);
    t.inject("F", 3, |i| match i {
        0 => named(1, &long),   // over budget
        1 => named(7, &long),   // matches by its first clause (OR short-cuts)
        _ => named(2, "short"), // no match, cheaply
    });
    t.worker.pump_readers().expect("pump");
    t.worker.flush();
    let got: Vec<Vec<u8>> = t.samples().into_iter().map(|(_, _, b)| b).collect();
    assert_eq!(got, vec![named(7, &long)]);
    assert_eq!(t.dropped("content_filter_over_budget"), 1);
    assert_eq!(t.dropped("content_filtered"), 1);
}

/// The worst case of the walk to a field (filter.rs measures it with the others): a field
/// behind a sequence of one-octet structures, each two steps to skip.
const WALK_TYPE: &str = r#"<dds><types><struct name="E"><member name="x" type="int8"/></struct>
    <struct name="Walk"><member name="items" type="nonBasic" nonBasicTypeName="E"
      sequenceMaxLength="-1"/><member name="id" type="int32"/></struct></types></dds>"#;

/// A `Walk` sample of `n` elements and id 1.
fn walk(n: u32) -> Vec<u8> {
    let mut b = n.to_le_bytes().to_vec();
    b.resize(4 + n as usize, 7);
    while b.len() % 4 != 0 {
        b.push(0);
    }
    b.extend(1i32.to_le_bytes());
    b
}

/// A reader whose evaluations spend its budget for the pass takes the rest of its samples
/// next pass (nothing is lost, nothing judged on a budget cut short), and all readers
/// together stop at the pass's budget: those left go first next pass. With the worst
/// filters within the caps (a quadratic LIKE, the walk to a field), each sample costing a
/// whole evaluation's budget; the passes' times are printed (not asserted: release mode
/// and `--nocapture` for numbers worth reading).
#[test]
fn filter_work_per_reader_and_per_pass_is_bounded_and_the_rest_waits() {
    let long = "a".repeat(4000);
    bounded_passes("LIKE", "Named", QUADRATIC, &|_| named(1, &long));
    bounded_passes("walk", "Walk", "id = 1 AND id = 1", &|_| walk(40_000));
}

fn bounded_passes(what: &str, ty: &str, expression: &str, sample: &dyn Fn(usize) -> Vec<u8>) {
    use crate::filter::{EVAL_BUDGET, PASS_BUDGET, READER_PASS_BUDGET};
    let per_reader = READER_PASS_BUDGET / EVAL_BUDGET;
    let readers_per_pass = (PASS_BUDGET / READER_PASS_BUDGET) as usize;
    let mut t = Harness::new(false);
    t.named_participant(CLIENT);
    let types = variant(object_kind::TYPE, WALK_TYPE, VariantExtra::None);
    t.create(CLIENT, ObjectId::new(3, object_kind::TYPE), &types)
        .expect("types");
    let n_readers = readers_per_pass + 1;
    let ids: Vec<ObjectId> = (0..n_readers)
        .map(|i| ObjectId::new(10 + i as u16, object_kind::DATAREADER))
        .collect();
    let xml = filtered_reader_xml("W", expression).replace("Named", ty);
    for id in &ids {
        t.reader(CLIENT, *id, &xml).expect("reader");
        t.read(CLIENT, *id);
    }
    // Each sample costs a whole evaluation budget (and does not match).
    let samples = 2 * per_reader as usize + 3;
    t.inject("W", samples, sample);

    let start = Instant::now();
    t.worker.pump_readers().expect("pump");
    let took = start.elapsed();
    let first = per_reader * readers_per_pass as u64;
    assert_eq!(
        t.dropped("content_filter_over_budget"),
        first,
        "{what}: {per_reader} evaluations per reader, {readers_per_pass} readers per pass"
    );
    eprintln!(
        "{what}: a pass of {readers_per_pass} readers full of the worst samples took {:.1} ms \
         ({:.2} ms per reader, {:.3} ms per evaluation)",
        took.as_secs_f64() * 1e3,
        took.as_secs_f64() * 1e3 / readers_per_pass as f64,
        took.as_secs_f64() * 1e3 / first as f64
    );
    let last = (FE, CLIENT, ids[n_readers - 1]);
    assert!(
        t.worker.over_budget.contains(&last),
        "{what}: the reader without a turn goes first next pass"
    );
    assert_eq!(
        t.dropped("filter_budget_deferrals"),
        readers_per_pass as u64
    );

    t.worker.pump_readers().expect("pump");
    // The reader left out went first and got its full share.
    let second = t.dropped("content_filter_over_budget") - first;
    assert_eq!(second, per_reader * readers_per_pass as u64);
    for _ in 0..8 {
        t.worker.pump_readers().expect("pump");
    }
    assert_eq!(
        t.dropped("content_filter_over_budget"),
        (samples * n_readers) as u64,
        "{what}: every sample was evaluated once, none lost or skipped"
    );
    assert!(t.worker.over_budget.is_empty() && t.worker.pump_again.is_empty());
}
