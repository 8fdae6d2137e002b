//! Requesters and repliers, partitions and fairness between readers over the fake backend.

use super::*;

const SERVICE: &str = "<dds><{e} profile_name=\"adder\" service_name=\"/add\" \
    request_type=\"AddRequest\" reply_type=\"AddReply\">\
    <request_topic_name>rq/addRequest</request_topic_name>\
    <reply_topic_name>rr/addReply</reply_topic_name></{e}></dds>";

impl Harness {
    /// Takes what every reader with data has and sends it to the front-end.
    fn pump_ready(&mut self) {
        self.worker
            .dds
            .ready_readers(&mut self.worker.readers.ready)
            .expect("ready");
        let keys: Vec<EntityKey> = self
            .worker
            .readers
            .ready
            .drain(..)
            .filter_map(|t| self.worker.readers.by_token.get(&t).copied())
            .collect();
        for k in keys {
            self.worker.pump(k);
        }
        self.worker.flush();
    }

    /// The Sample messages the front-end got: (client, request id, body after the identity).
    fn samples_by_client(&mut self) -> Vec<(ClientKey, [u8; 2], Vec<u8>)> {
        self.replies()
            .into_iter()
            .filter_map(|m| match m.reply {
                Reply::Sample(s) => {
                    Some((m.route.client_key, m.route.request_id.0, s.data.to_vec()))
                }
                _ => None,
            })
            .collect()
    }

    fn write(&mut self, client: ClientKey, id: ObjectId, request: [u8; 2], body: &[u8]) {
        let route = Route::object(FE, client, xrce_common::wire::RequestId(request), id);
        self.worker
            .write(
                (FE, client, id),
                &route,
                WriteData {
                    data_format: xrce_common::wire::data_format::DATA,
                    little_endian: true,
                    dialect: Dialect::Eprosima,
                    body,
                    received_us: 0,
                    origin: None,
                },
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
            .write_one((FE, CLIENT, WRITER), i, 0, true, &keyed(i as i32, 0), false)
            .expect("write");
    }
    // A first round fills the front-end's queue with the flood alone.
    t.worker.pump_readers().expect("pump");
    t.worker.flush();
    t.worker
        .write_one((FE, OTHER, WRITER), 0, 0, true, &keyed(-1, 7), false)
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
