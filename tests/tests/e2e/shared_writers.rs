//! `--share-writers`: the data writers of several XRCE clients on one topic with one QoS
//! become one DDS writer. Cyclone DDS reads every client's samples and matches one writer;
//! without the option, it matches one writer per client.

use std::collections::BTreeSet;
use std::time::Duration;

use xrce_common::wire::object_kind as k;
use xrce_tests::{
    hello_world, parse_sample_line, parse_sample_writer, xml, AgentProcess, DdsPeer, Deliveries,
    TestClient,
};

const SECOND: Duration = Duration::from_secs(1);

/// A volatile, reliable HelloWorld writer with a deeper history: shareable, but not with
/// [`VOLATILE_WRITER`].
const DEEPER_VOLATILE_WRITER: &str = "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType><historyQos><kind>KEEP_LAST</kind><depth>50</depth></historyQos></topic><qos><reliability><kind>RELIABLE</kind></reliability><durability><kind>VOLATILE</kind></durability></qos></data_writer></dds>";

/// A volatile, reliable HelloWorld writer: shareable.
const VOLATILE_WRITER: &str = "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic><qos><reliability><kind>RELIABLE</kind></reliability><durability><kind>VOLATILE</kind></durability></qos></data_writer></dds>";

/// Two clients publish 5 samples each through an agent started with `env`; returns how many
/// DDS writers Cyclone received them from (its publication handles), after checking that
/// every sample arrived exactly once with its client's message.
fn two_clients_publish(
    tag: &str,
    domain: i16,
    env: &[(&str, &str)],
    writer_xml: &str,
    second_writer_xml: &str,
) -> usize {
    let agent = AgentProcess::builder(tag).env(env).start();
    let d = domain.to_string();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &d,
        "--count",
        "10",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut a = TestClient::new(agent.addr(), [0xF0, 0x5A, 0x00, 0x01]);
    let mut b = TestClient::new(agent.addr(), [0xF0, 0x5A, 0x00, 0x02]);
    a.connect(10 * SECOND);
    b.connect(10 * SECOND);
    let wa = a.setup_chain(domain, k::PUBLISHER, k::DATAWRITER, writer_xml);
    let wb = b.setup_chain(domain, k::PUBLISHER, k::DATAWRITER, second_writer_xml);
    let first = reader.wait_for("MATCHED", 30 * SECOND, || {
        a.step();
        b.step();
    });
    assert!(first.is_some(), "Cyclone never matched a writer");
    for i in 0..5u32 {
        a.write_reliable(wa, &hello_world(i, "from a"));
        b.write_reliable(wb, &hello_world(100 + i, "from b"));
    }
    let mut writers = BTreeSet::new();
    let got = Deliveries::collect(10, 30 * SECOND, || {
        a.step();
        b.step();
        let mut out = Vec::new();
        while let Some(l) = reader.line(Duration::from_millis(1)) {
            if let (Some((i, m)), Some((_, w))) = (parse_sample_line(&l), parse_sample_writer(&l)) {
                assert_eq!(m, if i < 100 { "from a" } else { "from b" }, "{l}");
                writers.insert(w);
                out.push(i);
            }
        }
        out
    });
    got.assert_exactly_once((0..5).chain(100..105), "two clients' samples");
    assert!(agent.stop(), "agent did not stop cleanly");
    writers.len()
}

#[test]
fn clients_on_one_topic_share_one_dds_writer() {
    let matched = two_clients_publish(
        "sharew",
        30,
        &[("XRCE_SHARE_WRITERS", "true")],
        VOLATILE_WRITER,
        VOLATILE_WRITER,
    );
    assert_eq!(
        matched, 1,
        "with --share-writers Cyclone should get every sample from one writer"
    );
}

#[test]
fn transient_local_writers_are_not_shared() {
    // A shared transient-local writer would keep its history over all clients together.
    let matched = two_clients_publish(
        "tlw",
        32,
        &[("XRCE_SHARE_WRITERS", "true")],
        xml::WRITER,
        xml::WRITER,
    );
    assert_eq!(
        matched, 2,
        "transient-local writers must keep their own DDS writer"
    );
}

#[test]
fn without_sharing_every_client_has_its_own_dds_writer() {
    let matched = two_clients_publish(
        "ownw",
        31,
        &[("XRCE_SHARE_WRITERS", "false")],
        VOLATILE_WRITER,
        VOLATILE_WRITER,
    );
    assert_eq!(
        matched, 2,
        "without --share-writers Cyclone should see two writers"
    );
}

#[test]
fn writers_with_different_qos_are_not_shared() {
    let matched = two_clients_publish(
        "qosw",
        33,
        &[("XRCE_SHARE_WRITERS", "true")],
        VOLATILE_WRITER,
        DEEPER_VOLATILE_WRITER,
    );
    assert_eq!(
        matched, 2,
        "writers of different QoS must keep their own DDS writer"
    );
}
