//! `--share-writers`: the data writers of several XRCE clients on one topic with one QoS
//! become one DDS writer. Cyclone DDS reads every client's samples and matches one writer;
//! without the option, it matches one writer per client.

use std::collections::BTreeSet;
use std::time::Duration;

use xrce_common::wire::object_kind as k;
use xrce_tests::{hello_world, xml, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

/// A volatile, reliable HelloWorld writer with a deeper history: shareable, but not with
/// [`VOLATILE_WRITER`].
const DEEPER_VOLATILE_WRITER: &str = "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType><historyQos><kind>KEEP_LAST</kind><depth>50</depth></historyQos></topic><qos><reliability><kind>RELIABLE</kind></reliability><durability><kind>VOLATILE</kind></durability></qos></data_writer></dds>";

/// A volatile, reliable HelloWorld writer: shareable.
const VOLATILE_WRITER: &str = "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic><qos><reliability><kind>RELIABLE</kind></reliability><durability><kind>VOLATILE</kind></durability></qos></data_writer></dds>";

/// Two clients publish 5 samples each through an agent started with `env`; returns the
/// highest matched-writer count Cyclone reported, after checking that every sample arrived.
fn two_clients_publish(
    tag: &str,
    domain: i16,
    env: &[(&str, &str)],
    writer_xml: &str,
    second_writer_xml: &str,
) -> usize {
    let agent = AgentProcess::start_with_env(tag, env);
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
    let mut lines = Vec::new();
    let first = reader.wait_for("MATCHED", 30 * SECOND, || {
        a.step();
        b.step();
    });
    assert!(first.is_some(), "Cyclone never matched a writer");
    lines.extend(first);
    // Discovery of a second DDS writer, if there is one, has time to show.
    let until = std::time::Instant::now() + 3 * SECOND;
    while std::time::Instant::now() < until {
        a.step();
        b.step();
        lines.extend(reader.drain_lines());
    }
    for i in 0..5u32 {
        a.write_reliable(wa, &hello_world(i, "from a"));
        b.write_reliable(wb, &hello_world(100 + i, "from b"));
    }
    let got = reader.collect_samples(10, 30 * SECOND, || {
        a.step();
        b.step();
    });
    let keys: BTreeSet<u32> = got.keys().copied().collect();
    let want: BTreeSet<u32> = (0..5).chain(100..105).collect();
    assert_eq!(keys, want, "{got:?}");
    assert!(
        got.iter().all(|(k, m)| (*k < 100) == (m == "from a")),
        "{got:?}"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
    lines
        .iter()
        .filter_map(|l| l.strip_prefix("MATCHED ")?.trim().parse::<usize>().ok())
        .max()
        .unwrap_or(0)
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
        "with --share-writers Cyclone should see one writer"
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
