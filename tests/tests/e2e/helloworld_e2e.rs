//! HelloWorld end to end: a Rust XRCE client ↔ `xrce-agent` (real processes, UDP on
//! loopback, iceoryx2 between front-end and worker) ↔ Cyclone DDS (independent DDS).
//! Each test uses its own DDS domain so they can run in parallel.

use std::time::Duration;

use xrce_tests::scenarios;
use xrce_tests::{hello_world, AgentProcess, Deliveries, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn client_publishes_cyclone_reads_every_sample() {
    let agent = AgentProcess::builder("pub").start();
    let mut c = TestClient::new(agent.addr(), [0xAA, 0xAA, 0xBB, 0x01]);
    c.connect(10 * SECOND);
    scenarios::client_publishes_cyclone_reads(&mut c, 11, 50, "Hello DDS world!", "a client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn cyclone_publishes_client_reads() {
    let agent = AgentProcess::builder("sub").start();
    let mut c = TestClient::new(agent.addr(), [0xCC, 0xCC, 0xDD, 0x02]);
    c.connect(10 * SECOND);
    scenarios::cyclone_publishes_client_reads(&mut c, 12, 20, "from cyclone", "a client");
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
