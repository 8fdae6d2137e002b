//! HEARTBEATs to a client that has gone silent back off: the agent's reliable output to a
//! client that stopped answering (asleep, out of range, rebooting) is announced less and less
//! often, up to `max_heartbeat_period` (3.2 s), instead of ten times a second for as long as
//! the session lives. A client that keeps talking keeps the base period (100 ms), which the
//! core's unit tests cover.

use std::time::{Duration, Instant};

use xrce_common::wire::{Message, Payload};
use xrce_tests::{hello_world, AgentProcess, TestClient};

const SECOND: Duration = Duration::from_secs(1);

/// How long HEARTBEATs are counted from the first: a back-off doubling from 100 ms sends the
/// next ones 0.2, 0.6, 1.4 and 3.0 s after it (5 in 6 s, the next at 6.2 s); without one,
/// about 60 come.
const WATCH: Duration = Duration::from_secs(6);

#[test]
fn heartbeats_to_a_silent_client_back_off() {
    let agent = AgentProcess::builder("hbbackoff").start();
    let domain = 68;
    let mut sub = TestClient::new(agent.addr(), [0x4B, 0xB0, 0x00, 0x01]);
    sub.connect(10 * SECOND);
    sub.setup_subscriber(domain);
    let mut publ = TestClient::new(agent.addr(), [0x4B, 0xB0, 0x00, 0x02]);
    publ.connect(10 * SECOND);
    let w = publ.setup_publisher(domain);
    // Both sessions settled: the subscriber's READ_DATA acknowledged, and one sample through
    // shows the two endpoints matched.
    let mut through = false;
    let end = Instant::now() + 30 * SECOND;
    let mut i = 0;
    while !through && Instant::now() < end {
        publ.write_reliable(w, &hello_world(i, "warm-up"));
        i += 1;
        let until = Instant::now() + Duration::from_millis(200);
        while Instant::now() < until {
            publ.step();
            sub.step();
            through |= !sub.take_samples().is_empty();
        }
    }
    assert!(through, "no sample reached the subscriber within 30 s");
    // Let the last acknowledgements settle, then the subscriber goes silent: it reads what
    // arrives without handing it to its session, so it never acknowledges.
    let settle = Instant::now() + SECOND;
    while Instant::now() < settle {
        publ.step();
        sub.step();
        sub.take_samples();
    }
    for k in 0..5 {
        publ.write_reliable(w, &hello_world(1000 + k, "unacknowledged"));
    }
    let mut data = 0;
    let mut heartbeats: Vec<Instant> = Vec::new();
    let mut buf = vec![0u8; 65536];
    let start = Instant::now();
    while heartbeats
        .first()
        .map_or(start.elapsed() < 30 * SECOND, |t| t.elapsed() < WATCH)
    {
        publ.step();
        for m in sub.link.receive(Duration::from_millis(5), &mut buf) {
            let Ok(msg) = Message::decode(&m) else {
                continue;
            };
            for s in &msg.submessages {
                match s.payload {
                    Payload::Heartbeat(_) => heartbeats.push(Instant::now()),
                    Payload::Data(_) => data += 1,
                    _ => {}
                }
            }
        }
    }
    assert!(
        data >= 5,
        "the unacknowledged samples never reached the subscriber ({data} DATA)"
    );
    let gaps: Vec<u128> = heartbeats
        .windows(2)
        .map(|w| (w[1] - w[0]).as_millis())
        .collect();
    // With the back-off 5 (fewer on a loaded machine, whose late timers only stretch the
    // gaps); without, about 60.
    assert!(
        heartbeats.len() >= 3,
        "a silent client with unacknowledged output is not told about it: {} HEARTBEATs in {WATCH:?}",
        heartbeats.len()
    );
    assert!(
        heartbeats.len() <= 9,
        "HEARTBEATs to a silent client do not back off: {} in {WATCH:?}, gaps (ms) {gaps:?}",
        heartbeats.len()
    );
    // Starting near the base period and growing past a second: no fixed period does both.
    let (first, last) = (gaps[0], gaps[gaps.len() - 1]);
    assert!(
        first < 1000 && last >= 1200,
        "the HEARTBEAT period did not start short and grow past a second: gaps (ms) {gaps:?}"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
