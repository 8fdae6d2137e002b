//! The exchanges every transport's tests make, written once: a client's samples read by an
//! independent Cyclone DDS reader, and a Cyclone writer's samples read by a client. A test
//! brings the agent and a connected client of its transport (UDP, TCP, serial); the scenario
//! asserts that each sample arrives once and in order.

use std::time::Duration;

use crate::{hello_world, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

/// `count` reliable samples of `message` written by `client` (connected, its publisher set up
/// here in `domain`) reach an independent Cyclone reader each once, in order. `who` names
/// the client in a failure ("Cyclone reading {who}").
pub fn client_publishes_cyclone_reads(
    client: &mut TestClient,
    domain: i16,
    count: u32,
    message: &str,
    who: &str,
) {
    let domain_arg = domain.to_string();
    let count_arg = count.to_string();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &domain_arg,
        "--count",
        &count_arg,
        "--reliable",
        "--timeout",
        "60",
    ]);
    let w = client.setup_publisher(domain);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || client.step())
            .is_some(),
        "Cyclone never matched the agent's writer"
    );
    for i in 0..count {
        client.write_reliable(w, &hello_world(i, message));
    }
    let got = reader.collect_deliveries(count as usize, message, 30 * SECOND, || client.step());
    let what = format!("Cyclone reading {who}");
    got.assert_exactly_once(0..count, &what);
    got.assert_in_order(&what);
}

/// `count` reliable samples of `message` from an independent Cyclone writer in `domain` reach
/// `client` (connected, its subscriber set up here) each once, in order; the writer then
/// ends cleanly. `who` names the client in a failure ("{who} reading Cyclone").
pub fn cyclone_publishes_client_reads(
    client: &mut TestClient,
    domain: i16,
    count: u32,
    message: &str,
    who: &str,
) {
    client.setup_subscriber(domain);
    let domain_arg = domain.to_string();
    let count_arg = count.to_string();
    let mut writer = DdsPeer::start(&[
        "write",
        "--domain",
        &domain_arg,
        "--count",
        &count_arg,
        "--interval-ms",
        "10",
        "--message",
        message,
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "3000",
    ]);
    let got = client.collect_deliveries(count as usize, message, 60 * SECOND);
    let what = format!("{who} reading Cyclone");
    got.assert_exactly_once(0..count, &what);
    got.assert_in_order(&what);
    assert_eq!(writer.wait(30 * SECOND, || client.step()), Some(0));
}
