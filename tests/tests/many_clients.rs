//! Fifty sessions through one agent: every client opens its own session and DDS writer on a
//! shared topic, and one subscribing client receives every reliable sample of all of them.

use std::collections::BTreeSet;
use std::time::Duration;

use xrce_tests::{hello_world, AgentProcess, TestClient};

#[test]
fn fifty_publishing_sessions_one_subscriber() {
    const CLIENTS: u32 = 50;
    const EACH: u32 = 10;
    let agent = AgentProcess::start("many");
    let mut sub = TestClient::new(agent.addr(), [0x5B, 0, 0, 0]);
    sub.connect(Duration::from_secs(10));
    sub.setup_subscriber(15);
    let mut pubs: Vec<(TestClient, _)> = (0..CLIENTS)
        .map(|i| {
            let mut c = TestClient::new(agent.addr(), [0x50, 0, (i >> 8) as u8, i as u8]);
            c.connect(Duration::from_secs(10));
            let w = c.setup_publisher(15);
            (c, w)
        })
        .collect();
    let mut expected = BTreeSet::new();
    for k in 0..EACH {
        for (i, (c, w)) in pubs.iter_mut().enumerate() {
            let index = i as u32 * 1000 + k;
            c.write_reliable(*w, &hello_world(index, "many"));
            expected.insert(index);
        }
        sub.step();
    }
    let mut got = BTreeSet::new();
    let all = sub.run_until(Duration::from_secs(60), |s| {
        for (c, _) in pubs.iter_mut() {
            c.step();
        }
        got.extend(s.take_samples().into_iter().map(|(i, _)| i));
        got.len() == expected.len()
    });
    let missing: Vec<_> = expected.difference(&got).take(20).collect();
    assert!(
        all,
        "{} of {} samples arrived; first missing: {missing:?}",
        got.len(),
        expected.len()
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
