//! Sessions survive a worker kill: the DDS worker is SIGKILLed while a client publishes on a
//! reliable stream; the supervisor restarts it, the front-end replays the session, and an
//! independent Cyclone DDS reader still receives every sample. The client never re-creates
//! its session.

use std::time::{Duration, Instant};

use xrce_common::session::client::ClientEvent;
use xrce_common::wire::ObjectId;
use xrce_tests::{
    hello_world, sigkill, AgentProcess, DdsPeer, Deliveries, TestClient, DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

/// An agent, a reliable Cyclone DDS reader of HelloWorld in `domain` (ended by the test or
/// after 120 s), a client with key `key` whose writer it matched (the writer's id), and the
/// agent's worker (its pid).
fn publisher_and_reader(
    tag: &str,
    domain: i16,
    key: [u8; 4],
) -> (AgentProcess, DdsPeer, TestClient, ObjectId, i32) {
    let agent = AgentProcess::builder(tag).start();
    // The reader counts duplicates too, so let it run past what is written.
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &domain.to_string(),
        "--count",
        "100000",
        "--reliable",
        "--timeout",
        "120",
    ]);
    let mut client = TestClient::new(agent.addr(), key);
    client.connect(10 * SECOND);
    let writer = client.setup_publisher(domain);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || client.step())
            .is_some(),
        "Cyclone never matched"
    );
    let workers = agent.child_pids("dds-worker");
    assert_eq!(workers.len(), 1, "expected one worker, got {workers:?}");
    (agent, reader, client, writer, workers[0])
}

#[test]
fn worker_sigkill_mid_stream_loses_no_reliable_sample() {
    const N: u32 = 300;
    const KILL_AT: u32 = 100;
    let (agent, reader, mut c, w, old_worker) =
        publisher_and_reader("kill", 14, [0xAB, 0xCD, 0xEF, 0x04]);
    let old_workers = vec![old_worker];
    let mut got = Deliveries::default();
    let collect =
        |reader: &DdsPeer, got: &mut Deliveries| got.collect_from(reader, "through a crash");
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
    c.run_until(60 * SECOND, |_| {
        collect(&reader, &mut got);
        got.distinct() as u32 >= N
    });
    // Late copies would show within the grace.
    c.run_until(DUPLICATE_GRACE, |_| {
        collect(&reader, &mut got);
        false
    });
    let killed_at = killed_at.expect("killed");
    eprintln!("worker restart: {:?} since the kill", killed_at.elapsed());
    // The front-end keeps a reliable write only until the worker reports every matched
    // reliable reader acknowledged it, and resends what it kept to the new worker. Readers
    // acknowledge within milliseconds here (0 repeats measured).
    got.assert_none_lost_repeats_near(N, KILL_AT, "a reader across a worker restart");

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

/// The worker is SIGKILLed while a client publishes on its best-effort stream: what was
/// written while no worker ran may be lost, but the stream resumes on the new worker's
/// writer, nothing comes twice, and everything written once the new worker runs arrives
/// (its writes wait for the Cyclone DDS reader to match again, and the front-end's window
/// does not stay filled with operations whose progress it was never told of).
#[test]
fn worker_sigkill_mid_best_effort_stream_resumes_it() {
    // Written after the front-end saw the new worker, at least.
    const AFTER: u32 = 300;
    // At most (the restart would have taken a minute).
    const N: u32 = 6_000;
    const KILL_AT: u32 = 100;
    let (agent, reader, mut c, w, old_worker) =
        publisher_and_reader("kill-be", 100, [0xAB, 0xCD, 0xEF, 0x05]);
    let mut got = Deliveries::default();
    let collect = |reader: &DdsPeer, got: &mut Deliveries| got.collect_from(reader, "best effort");
    // The first sample written once a new worker serves (the supervisor restarts it).
    let mut first_after_restart = None;
    let mut written = 0;
    while written < N && first_after_restart.is_none_or(|f| written < f + AFTER) {
        let i = written;
        if i == KILL_AT {
            sigkill(old_worker);
        }
        // Once the front-end saw the new worker (what it sent before went to the dead one).
        if i > KILL_AT
            && first_after_restart.is_none()
            && agent.output().count("worker generation seen") >= 2
        {
            first_after_restart = Some(i);
        }
        c.write_best_effort(w, &hello_world(i, "best effort"));
        // ~100 samples/s.
        c.run_until(Duration::from_millis(10), |_| false);
        collect(&reader, &mut got);
        written += 1;
    }
    let first = first_after_restart.expect("the front-end never saw a new worker");
    c.run_until(30 * SECOND, |_| {
        collect(&reader, &mut got);
        (first..written).all(|i| got.count(i) > 0)
    });
    c.run_until(DUPLICATE_GRACE, |_| {
        collect(&reader, &mut got);
        false
    });
    eprintln!(
        "best-effort stream across a worker restart: {} of {written} delivered, new worker from sample {first}",
        got.distinct()
    );
    let missing: Vec<u32> = (first..written).filter(|i| got.count(*i) == 0).collect();
    assert!(
        missing.is_empty(),
        "written after the new worker started, lost: {missing:?}"
    );
    assert!(
        (0..KILL_AT).all(|i| got.count(i) > 0),
        "written before the kill, lost"
    );
    assert!(got.repeated().is_empty(), "repeated: {:?}", got.repeated());
    assert!(agent.stop(), "agent did not stop cleanly after the restart");
}

/// The worker is SIGKILLed while a client reads: the front-end replays the read on the new
/// worker, samples resume, and none is delivered twice (the reader is volatile: what Cyclone
/// wrote while no worker ran is not replayed to it).
#[test]
fn worker_sigkill_while_a_client_reads_resumes_its_samples_none_twice() {
    // 10 s of samples: the restart, the replay and DDS matching again have about 9 s.
    const N: u32 = 500;
    let agent = AgentProcess::builder("killread").start();
    let mut c = TestClient::new(agent.addr(), [0xAB, 0xCD, 0xEF, 0x05]);
    c.connect(10 * SECOND);
    c.setup_subscriber(36);
    let count = N.to_string();
    let writer = DdsPeer::start(&[
        "write",
        "--domain",
        "36",
        "--count",
        &count,
        "--interval-ms",
        "20",
        "--message",
        "read through a crash",
        "--wait-match",
        "--reliable",
        "--timeout",
        "90",
        "--linger-ms",
        "3000",
    ]);
    let workers = agent.child_pids("dds-worker");
    assert_eq!(workers.len(), 1);
    let mut got = Deliveries::default();
    let take = |c: &mut TestClient, got: &mut Deliveries| {
        for (i, m) in c.take_samples() {
            assert_eq!(m, "read through a crash");
            got.record(i);
        }
    };
    // A second of samples, then the kill.
    c.run_until(30 * SECOND, |c| {
        take(c, &mut got);
        got.distinct() >= 40
    });
    assert!(got.distinct() >= 40, "no samples before the kill");
    let before = got.order_last();
    sigkill(workers[0]);
    c.run_until(60 * SECOND, |c| {
        take(c, &mut got);
        got.count(N - 1) > 0
    });
    c.run_until(DUPLICATE_GRACE, |c| {
        take(c, &mut got);
        false
    });
    assert!(
        got.repeated().is_empty(),
        "samples delivered twice after the worker restart: {:?}",
        got.repeated()
    );
    got.assert_in_order("a read across a worker restart");
    // One gap at most, at the outage: every sample up to the last one before the kill, then
    // every one from the first after it to the end (a burst lost later would be a second gap).
    let delivered: Vec<u32> = (0..N).filter(|i| got.count(*i) > 0).collect();
    let gaps: Vec<(u32, u32)> = delivered
        .windows(2)
        .filter(|w| w[1] != w[0] + 1)
        .map(|w| (w[0] + 1, w[1] - 1))
        .collect();
    assert_eq!(delivered.first(), Some(&0), "the first samples are missing");
    assert_eq!(
        delivered.last(),
        Some(&(N - 1)),
        "the last samples are missing"
    );
    assert!(
        gaps.len() <= 1 && gaps.iter().all(|(from, _)| *from > before),
        "samples missing other than those written during the outage (after {before}): {gaps:?}"
    );
    // And it ends where the new worker's reader matched Cyclone's writer: the writer reports
    // each change of its match count between the samples it writes (the new reader shows as
    // a rise: MATCHED 2 while the killed one's lease runs, or MATCHED 1 after MATCHED 0), and
    // every sample written once matched again must arrive (a read replayed late, or one that
    // skipped samples on resuming, would lose some).
    let mut lines = Vec::new();
    while let Some(l) = writer.line(Duration::ZERO) {
        lines.push(l);
    }
    let counts: Vec<(usize, u32)> = lines
        .iter()
        .enumerate()
        .filter_map(|(at, l)| Some((at, l.strip_prefix("MATCHED ")?.trim().parse().ok()?)))
        .collect();
    // The first count is the old worker's reader; the first rise after it, the new one's.
    let rematched = counts
        .windows(2)
        .find(|w| w[1].1 > w[0].1)
        .map(|w| w[1].0)
        .unwrap_or_else(|| {
            panic!("Cyclone's writer never matched the new worker's reader: {counts:?}")
        });
    let first_matched: u32 = lines[rematched..]
        .iter()
        .find_map(|l| l.strip_prefix("SENT ")?.parse().ok())
        .expect("nothing written after the new worker's reader matched");
    // A volatile reader may still miss what was written before it, in turn, matched the
    // writer (it starts from the writer's next HEARTBEAT): half a second of samples is left
    // for that.
    let resumed = first_matched + 25;
    let lost_after: Vec<u32> = (resumed..N).filter(|i| got.count(*i) == 0).collect();
    assert!(
        lost_after.is_empty(),
        "written after the new worker's reader matched ({first_matched}; checked from {resumed}), lost: {lost_after:?}"
    );
    assert_ne!(
        agent.child_pids("dds-worker"),
        workers,
        "the worker was not restarted"
    );
    assert!(agent.stop(), "agent did not stop cleanly after the restart");
}
