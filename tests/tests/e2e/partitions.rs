//! Partitions of an XRCE publisher, against two independent Cyclone DDS readers of the topic,
//! one in the publisher's partition and one in another: with the Cyclone DDS backend the
//! first gets every sample and the second none; with RustDDS, which has no partitions, the
//! publisher is refused (rather than publishing to readers outside its partition).

use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind as k, status, ObjectId, VariantExtra};
use xrce_tests::{hello_world, parse_sample_line, xml, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);
const N: u32 = 10;

const PUBLISHER_IN_ROBOT_A: &str = "<dds><publisher><qos><partition><names><name>robot_a</name>\
    </names></partition></qos></publisher></dds>";

#[test]
fn a_publishers_partition_reaches_only_readers_of_that_partition() {
    let agent = AgentProcess::builder("partitions").start();
    let mut c = TestClient::new(agent.addr(), [0x9A, 0x27, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let p = ObjectId::new(1, k::PARTICIPANT);
    let t = ObjectId::new(1, k::TOPIC);
    let g = ObjectId::new(1, k::PUBLISHER);
    let w = ObjectId::new(1, k::DATAWRITER);
    assert_eq!(
        c.create(
            p,
            k::PARTICIPANT,
            xml::PARTICIPANT,
            VariantExtra::DomainId(47)
        ),
        0
    );
    assert_eq!(
        c.create(t, k::TOPIC, xml::TOPIC, VariantExtra::Parent(p)),
        0
    );
    let created = c.create(
        g,
        k::PUBLISHER,
        PUBLISHER_IN_ROBOT_A,
        VariantExtra::Parent(p),
    );
    if xrce_tests::dds_backend() != "cyclone" {
        assert_eq!(
            created,
            status::ERR_INCOMPATIBLE,
            "RustDDS has no partitions: the publisher must be refused"
        );
        assert!(agent.stop(), "agent did not stop cleanly");
        return;
    }
    assert_eq!(created, 0, "creating the publisher in partition robot_a");
    let peer = |partition: &str| {
        DdsPeer::start(&[
            "read",
            "--domain",
            "47",
            "--partition",
            partition,
            "--count",
            &N.to_string(),
            "--reliable",
            "--timeout",
            "60",
        ])
    };
    let inside = peer("robot_a");
    let outside = peer("robot_b");
    // The default partition: where a writer that lost its partition would publish.
    let default = peer("");
    for (name, p) in [
        ("robot_a", &inside),
        ("robot_b", &outside),
        ("default", &default),
    ] {
        assert!(
            p.wait_for("READY", 30 * SECOND, || c.step()).is_some(),
            "the reader in {name} never started"
        );
    }
    assert_eq!(
        c.create(w, k::DATAWRITER, xml::WRITER, VariantExtra::Parent(g)),
        0
    );
    assert!(
        inside
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "the reader in robot_a never matched"
    );
    for i in 0..N {
        c.write_reliable(w, &hello_world(i, "in robot_a"));
    }
    let mut got = Vec::new();
    let mut elsewhere = Vec::new();
    let end = Instant::now() + 30 * SECOND;
    let grace = xrce_tests::DUPLICATE_GRACE;
    let mut complete_at = None;
    while Instant::now() < end && complete_at.is_none_or(|t: Instant| t.elapsed() < grace) {
        c.step();
        while let Some(l) = inside.line(Duration::ZERO) {
            got.extend(parse_sample_line(&l).map(|(i, _)| i));
        }
        for p in [&outside, &default] {
            while let Some(l) = p.line(Duration::ZERO) {
                assert!(
                    !l.starts_with("MATCHED 1"),
                    "a reader outside robot_a matched: {l}"
                );
                elsewhere.extend(parse_sample_line(&l).map(|(i, _)| i));
            }
        }
        if complete_at.is_none() && got.len() >= N as usize {
            complete_at = Some(Instant::now());
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(got, (0..N).collect::<Vec<_>>(), "the reader in robot_a");
    assert!(
        elsewhere.is_empty(),
        "readers outside robot_a got {elsewhere:?}"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
