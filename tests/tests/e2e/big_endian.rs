//! A big-endian client: its CREATE and WRITE_DATA are big endian, and its samples reach
//! Cyclone DDS with the CDR_BE encapsulation, decoded to the right values.

use std::time::Duration;

use xrce_common::session::client::ClientConfig;
use xrce_common::wire::ClientKey;
use xrce_tests::{hello_world_be, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn a_big_endian_client_publishes_values_cyclone_reads_correctly() {
    let agent = AgentProcess::builder("bigend").start();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "22",
        "--count",
        "10",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::with_config(
        agent.addr(),
        ClientConfig {
            little_endian: false,
            ..ClientConfig::new(ClientKey([0xBE, 0xBE, 0x00, 0x01]))
        },
    );
    c.connect(10 * SECOND);
    let w = c.setup_publisher(22);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the agent's writer"
    );
    // Indexes whose byte order matters (a swapped 0x01000000 would show).
    let indexes: Vec<u32> = (0..10).map(|i| 1 + i * 0x0101).collect();
    for i in &indexes {
        c.write_reliable(w, &hello_world_be(*i, "big end"));
    }
    let got = reader.collect_deliveries(indexes.len(), "big end", 30 * SECOND, || c.step());
    got.assert_exactly_once(indexes, "Cyclone reading a big-endian client");
    got.assert_in_order("Cyclone reading a big-endian client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_big_endian_client_creates_its_entities_in_binary() {
    use xrce_common::wire::binary::{
        qos_flags, EndpointBinary, EndpointBinaryQos, EndpointQosBinary, GroupBinary,
        ParticipantBinary, TopicBinary,
    };
    use xrce_common::wire::{object_kind as k, ObjectId, Representation, VariantExtra};
    let agent = AgentProcess::builder("bigendbin").start();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "25",
        "--count",
        "3",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::with_config(
        agent.addr(),
        ClientConfig {
            little_endian: false,
            ..ClientConfig::new(ClientKey([0xBE, 0xBE, 0x00, 0x02]))
        },
    );
    c.connect(10 * SECOND);
    let (p, t) = (ObjectId::new(1, k::PARTICIPANT), ObjectId::new(1, k::TOPIC));
    let (g, w) = (
        ObjectId::new(1, k::PUBLISHER),
        ObjectId::new(1, k::DATAWRITER),
    );
    let topic = TopicBinary {
        topic_name: "HelloWorldTopic".into(),
        type_reference: None,
        type_name: Some("HelloWorld".into()),
    };
    let writer = EndpointBinary {
        topic_id: t,
        qos: Some(EndpointBinaryQos {
            base: EndpointQosBinary {
                flags: qos_flags::RELIABLE | qos_flags::DURABILITY_TRANSIENT_LOCAL,
                history_depth: Some(0x0102),
                ..EndpointQosBinary::default()
            },
            ownership_strength: Some(0),
            ..EndpointBinaryQos::default()
        }),
    };
    let steps = [
        (
            p,
            k::PARTICIPANT,
            ParticipantBinary::default().encode(false),
            VariantExtra::DomainId(25),
        ),
        (t, k::TOPIC, topic.encode(false), VariantExtra::Parent(p)),
        (
            g,
            k::PUBLISHER,
            GroupBinary::default().encode(false),
            VariantExtra::Parent(p),
        ),
        (
            w,
            k::DATAWRITER,
            writer.encode(true, false),
            VariantExtra::Parent(g),
        ),
    ];
    for (id, kind, body, extra) in steps {
        assert_eq!(
            c.create_as(id, kind, Representation::Binary(body), extra),
            0,
            "creating {id:?} from a big-endian binary body"
        );
    }
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the agent's writer"
    );
    for i in [7u32, 0x0100, 0x010000] {
        c.write_reliable(w, &hello_world_be(i, "binary big end"));
    }
    let got = reader.collect_deliveries(3, "binary big end", 30 * SECOND, || c.step());
    got.assert_exactly_once([7u32, 0x0100, 0x010000], "binary big-endian entities");
    got.assert_in_order("binary big-endian entities");
    assert!(agent.stop(), "agent did not stop cleanly");
}
