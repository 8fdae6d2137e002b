//! HelloWorld end to end: a Rust XRCE client ↔ `xrce-agent` (real processes, UDP on
//! loopback, iceoryx2 between front-end and worker) ↔ Cyclone DDS (independent DDS).
//! Each test uses its own DDS domain so they can run in parallel.

use std::time::Duration;

use xrce_tests::{hello_world, AgentProcess, DdsPeer, Deliveries, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn client_publishes_cyclone_reads_every_sample() {
    let agent = AgentProcess::builder("pub").start();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "11",
        "--count",
        "50",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0xAA, 0xAA, 0xBB, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(11);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the agent's writer"
    );
    for i in 0..50 {
        c.write_reliable(w, &hello_world(i, "Hello DDS world!"));
    }
    let got = reader.collect_deliveries(50, "Hello DDS world!", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..50, "Cyclone reading a client");
    got.assert_in_order("Cyclone reading a client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn cyclone_publishes_client_reads() {
    let agent = AgentProcess::builder("sub").start();
    let mut c = TestClient::new(agent.addr(), [0xCC, 0xCC, 0xDD, 0x02]);
    c.connect(10 * SECOND);
    c.setup_subscriber(12);
    let mut writer = DdsPeer::start(&[
        "write",
        "--domain",
        "12",
        "--count",
        "20",
        "--interval-ms",
        "10",
        "--message",
        "from cyclone",
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "3000",
    ]);
    let got = c.collect_deliveries(20, "from cyclone", 60 * SECOND);
    got.assert_exactly_once(0..20, "a client reading Cyclone");
    got.assert_in_order("a client reading Cyclone");
    assert_eq!(writer.wait(30 * SECOND, || c.step()), Some(0));
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn client_to_client_through_the_agent() {
    let agent = AgentProcess::builder("c2c").start();
    let mut sub = TestClient::new(agent.addr(), [0x11, 0x11, 0x11, 0x03]);
    sub.connect(10 * SECOND);
    sub.setup_subscriber(13);
    let mut publ = TestClient::new(agent.addr(), [0x22, 0x22, 0x22, 0x03]);
    publ.connect(10 * SECOND);
    let w = publ.setup_publisher(13);
    // The writer is transient-local (the reference agent's default), so samples written
    // before the two RustDDS endpoints matched are still delivered.
    for i in 0..30 {
        publ.write_reliable(w, &hello_world(i, "c2c"));
        sub.step();
    }
    let got = Deliveries::collect(30, 30 * SECOND, || {
        publ.step();
        sub.step();
        sub.take_samples()
            .into_iter()
            .map(|(i, m)| {
                assert_eq!(m, "c2c");
                i
            })
            .collect()
    });
    got.assert_exactly_once(0..30, "a client reading another through the agent");
    got.assert_in_order("a client reading another through the agent");
    assert!(agent.stop(), "agent did not stop cleanly");
}
