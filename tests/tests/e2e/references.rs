//! Creation by reference: the agent is started with a references file (`-r`), the client
//! creates its participant, topic and writer by profile name, and Cyclone DDS receives every
//! sample. An unknown reference gets STATUS_ERR_UNKNOWN_REFERENCE.

use std::time::Duration;

use xrce_common::wire::{object_kind as k, status, ObjectId, Representation, VariantExtra};
use xrce_tests::{
    free_udp_port, hello_world, unique_instance, workspace, AgentProcess, DdsPeer, TestClient,
};

#[test]
fn entities_created_by_reference_publish_to_cyclone() {
    let refs = workspace().join("tests/data/helloworld.refs");
    let refs = refs.to_str().expect("utf-8 path");
    let agent = AgentProcess::at(([127, 0, 0, 1], free_udp_port()).into())
        .instance(unique_instance("refs"))
        .extra(&["-r", refs])
        .start();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "101",
        "--count",
        "20",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0x4E, 0xF5, 0, 1]);
    c.connect(Duration::from_secs(10));
    let by_ref = |name: &str| Representation::Reference(name.into());
    let p = ObjectId::new(1, k::PARTICIPANT);
    assert_eq!(
        c.create_as(
            p,
            k::PARTICIPANT,
            by_ref("default_xrce_participant"),
            VariantExtra::DomainId(101)
        ),
        status::OK
    );
    let t = ObjectId::new(1, k::TOPIC);
    assert_eq!(
        c.create_as(
            t,
            k::TOPIC,
            by_ref("helloworld_topic"),
            VariantExtra::Parent(p)
        ),
        status::OK
    );
    let pb = ObjectId::new(1, k::PUBLISHER);
    assert_eq!(
        c.create(pb, k::PUBLISHER, "", VariantExtra::Parent(p)),
        status::OK
    );
    // Unknown references, and references to a profile of another kind, are refused.
    let bad = ObjectId::new(2, k::DATAWRITER);
    assert_eq!(
        c.create_as(
            bad,
            k::DATAWRITER,
            by_ref("no_such_profile"),
            VariantExtra::Parent(pb)
        ),
        status::ERR_UNKNOWN_REFERENCE
    );
    assert_eq!(
        c.create_as(
            bad,
            k::DATAWRITER,
            by_ref("helloworld_topic"),
            VariantExtra::Parent(pb)
        ),
        status::ERR_UNKNOWN_REFERENCE
    );
    let w = ObjectId::new(1, k::DATAWRITER);
    assert_eq!(
        c.create_as(
            w,
            k::DATAWRITER,
            by_ref("helloworld_writer"),
            VariantExtra::Parent(pb)
        ),
        status::OK
    );
    assert!(
        reader
            .wait_for("MATCHED", Duration::from_secs(30), || c.step())
            .is_some(),
        "Cyclone never matched"
    );
    for i in 0..20 {
        c.write_reliable(w, &hello_world(i, "by reference"));
    }
    let got = reader.collect_deliveries(20, "by reference", Duration::from_secs(30), || c.step());
    got.assert_exactly_once(0..20, "entities created by reference");
    got.assert_in_order("entities created by reference");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_bad_references_file_is_refused_at_start() {
    let dir = std::env::temp_dir().join(format!("xrce-refs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let bad = dir.join("bad.refs");
    std::fs::write(&bad, "<profiles><topic profile_name=\"a\"></profiles>").expect("write");
    let mut cmd = std::process::Command::new(xrce_tests::binaries().join("xrce-agent"));
    cmd.args([
        "udp4",
        "-p",
        &free_udp_port().to_string(),
        "--bind",
        "127.0.0.1",
        "-r",
    ])
    .arg(&bad)
    .stdout(std::process::Stdio::piped())
    .stderr(std::process::Stdio::piped());
    let out = xrce_tests::output_within(&mut cmd, Duration::from_secs(30));
    let stderr = String::from_utf8_lossy(&out.stderr);
    // An error the agent reports and exits on (status 1), not a crash (a panic exits with
    // 101, a signal with none).
    assert_eq!(
        out.status.code(),
        Some(1),
        "a malformed references file must stop the agent with an error: {stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        stderr.contains("bad.refs"),
        "the error names the file: {stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
