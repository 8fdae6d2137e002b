//! Fifty sessions through one agent: every client opens its own session and DDS writer on a
//! shared topic, and one subscribing client receives every reliable sample of all of them,
//! each exactly once.
//!
//! The measured samples start once DDS has matched every writer with the subscriber's
//! reader (each publisher probes until the subscriber heard it). Fifty writers created
//! within 150 ms are matched by the worker's reading participant later than the writers
//! match it, and a volatile reader does not get what was written before it matched: the
//! worker holds a new writer's first samples until the writer matched plus 500 ms, which
//! covers one new writer but not the tail of such a burst (seen once the front-end set
//! sessions up in 3 ms each; an open problem of the DDS data path, noted on its issue).

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use xrce_tests::{hello_world, AgentProcess, Deliveries, TestClient, DUPLICATE_GRACE};

#[test]
fn fifty_publishing_sessions_one_subscriber() {
    const CLIENTS: u32 = 50;
    const EACH: u32 = 10;
    const PROBE: u32 = 1_000_000;
    let agent = AgentProcess::builder("many").start();
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
    // Probe until the subscriber heard every publisher.
    let mut heard = BTreeSet::new();
    let end = Instant::now() + Duration::from_secs(60);
    let mut last_probe = Instant::now() - Duration::from_secs(1);
    while heard.len() < CLIENTS as usize && Instant::now() < end {
        if last_probe.elapsed() > Duration::from_millis(200) {
            last_probe = Instant::now();
            for (i, (c, w)) in pubs.iter_mut().enumerate() {
                if !heard.contains(&(i as u32)) {
                    c.write_reliable(*w, &hello_world(PROBE + i as u32, "probe"));
                }
            }
        }
        for (c, _) in pubs.iter_mut() {
            c.step();
        }
        sub.step();
        for (i, m) in sub.take_samples() {
            assert_eq!(m, "probe", "sample {i} before the measured ones");
            heard.insert(i - PROBE);
        }
    }
    assert_eq!(heard.len(), CLIENTS as usize, "publishers never heard");
    let mut expected = BTreeSet::new();
    for k in 0..EACH {
        for (i, (c, w)) in pubs.iter_mut().enumerate() {
            let index = i as u32 * 1000 + k;
            c.write_reliable(*w, &hello_world(index, "many"));
            expected.insert(index);
        }
        sub.step();
    }
    let mut got = Deliveries::default();
    let mut complete: Option<Instant> = None;
    let end = Instant::now() + Duration::from_secs(60);
    while Instant::now() < end && complete.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
        for (c, _) in pubs.iter_mut() {
            c.step();
        }
        sub.step();
        for (i, m) in sub.take_samples() {
            if m == "probe" {
                // A late copy of a probe resent before its first copy arrived.
                continue;
            }
            assert_eq!(m, "many");
            got.record(i);
        }
        if complete.is_none() && got.distinct() == expected.len() {
            complete = Some(Instant::now());
        }
    }
    got.assert_exactly_once(expected, "fifty publishers to one subscriber");
    assert!(agent.stop(), "agent did not stop cleanly");
}
