//! Sessions survive a worker kill: the DDS worker is SIGKILLed while a client publishes on a
//! reliable stream; the supervisor restarts it, the front-end replays the session, and an
//! independent Cyclone DDS reader still receives every sample. The client never re-creates
//! its session.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use xrce_common::session::client::ClientEvent;
use xrce_tests::{hello_world, parse_sample_line, sigkill, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn worker_sigkill_mid_stream_loses_no_reliable_sample() {
    const N: u32 = 300;
    const KILL_AT: u32 = 100;
    let agent = AgentProcess::start("kill");
    // The reader counts duplicates too, so let it run past N; the test ends it.
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "14",
        "--count",
        &(10 * N).to_string(),
        "--reliable",
        "--timeout",
        "120",
    ]);
    let mut c = TestClient::new(agent.addr(), [0xAB, 0xCD, 0xEF, 0x04]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(14);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched"
    );
    let old_workers = agent.child_pids("dds-worker");
    assert_eq!(
        old_workers.len(),
        1,
        "expected one worker, got {old_workers:?}"
    );

    let mut got: BTreeMap<u32, u32> = BTreeMap::new();
    let collect = |reader: &DdsPeer, got: &mut BTreeMap<u32, u32>| {
        while let Some(l) = reader.line(Duration::ZERO) {
            if let Some((i, _)) = parse_sample_line(&l) {
                *got.entry(i).or_default() += 1;
            }
        }
    };
    let mut killed_at = None;
    for i in 0..N {
        if i == KILL_AT {
            sigkill(old_workers[0]);
            killed_at = Some(Instant::now());
        }
        c.write_reliable(w, &hello_world(i, "through a crash"));
        // ~100 samples/s, so the outage falls in the middle of the stream.
        c.run_until(Duration::from_millis(10), |_| false);
        collect(&reader, &mut got);
    }
    let done = c.run_until(60 * SECOND, |_| {
        collect(&reader, &mut got);
        got.len() as u32 == N
    });
    let killed_at = killed_at.expect("killed");
    let missing: Vec<u32> = (0..N).filter(|i| !got.contains_key(i)).collect();
    let duplicates: u32 = got.values().map(|n| n - 1).sum();
    eprintln!(
        "worker restart: {} of {N} delivered, {duplicates} duplicates, {:?} since the kill",
        got.len(),
        killed_at.elapsed()
    );
    assert!(
        done && missing.is_empty(),
        "samples lost across the worker restart: {missing:?}"
    );

    let new_workers = agent.child_pids("dds-worker");
    assert_eq!(
        new_workers.len(),
        1,
        "the supervisor should run exactly one new worker: {new_workers:?}"
    );
    assert_ne!(new_workers, old_workers, "the worker was not restarted");
    let session_events = c
        .events
        .iter()
        .filter(|e| matches!(e, ClientEvent::SessionStatus(_)))
        .count();
    assert_eq!(
        session_events, 1,
        "the client had to re-create its session (only the first STATUS_AGENT is expected)"
    );
    assert!(agent.stop(), "agent did not stop cleanly after the restart");
}
