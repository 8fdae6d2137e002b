//! `xrce-agent --single-process`: the front-end and the DDS worker in one child of the
//! supervisor. Samples go both ways through it (a client to Cyclone DDS and to another
//! client), it stops cleanly, and a SIGKILL of it mid-stream is survived as a worker crash
//! is: the supervisor starts it again, its front-end takes the sessions over from the store
//! and re-creates their entities in its new worker, and the client goes on without creating
//! its session again, no reliable sample lost.

use std::time::{Duration, Instant};

use xrce_tests::{
    hello_world, sigkill, AgentProcess, DdsPeer, Deliveries, TestClient, DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

/// A reliable Cyclone DDS reader of HelloWorld in `domain` that reads up to `count`.
fn reader(domain: i16, count: u32) -> DdsPeer {
    DdsPeer::start(&[
        "read",
        "--domain",
        &domain.to_string(),
        "--count",
        &count.to_string(),
        "--reliable",
        "--timeout",
        "120",
    ])
}

#[test]
fn one_process_carries_samples_to_dds_and_to_clients_and_stops_cleanly() {
    const N: u32 = 200;
    const DOMAIN: i16 = 171;
    let agent = AgentProcess::builder("single")
        .extra(&["--single-process"])
        .start();
    assert_eq!(
        agent.child_pids("single-process").len(),
        1,
        "one process serves"
    );
    assert!(
        agent.child_pids("dds-worker").is_empty() && agent.child_pids("frontend").is_empty(),
        "no worker or front-end of their own"
    );
    let dds = reader(DOMAIN, 10 * N);
    let mut sub = TestClient::new(agent.addr(), [0x51, 0x52, 0x53, 0x01]);
    sub.connect(10 * SECOND);
    sub.setup_subscriber(DOMAIN);
    let mut publ = TestClient::new(agent.addr(), [0x51, 0x52, 0x53, 0x02]);
    publ.connect(10 * SECOND);
    let w = publ.setup_publisher(DOMAIN);
    assert!(
        dds.wait_for("MATCHED 1", 30 * SECOND, || {
            publ.step();
            sub.step();
        })
        .is_some(),
        "Cyclone never matched"
    );
    let mut in_dds = Deliveries::default();
    let mut at_client = Deliveries::default();
    let step = |publ: &mut TestClient,
                sub: &mut TestClient,
                in_dds: &mut Deliveries,
                at_client: &mut Deliveries| {
        publ.step();
        sub.step();
        for (i, m) in sub.take_samples() {
            assert_eq!(m, "in one process");
            at_client.record(i);
        }
        in_dds.collect_from(&dds, "in one process");
    };
    for i in 0..N {
        publ.write_reliable(w, &hello_world(i, "in one process"));
        let end = Instant::now() + Duration::from_millis(2);
        while Instant::now() < end {
            step(&mut publ, &mut sub, &mut in_dds, &mut at_client);
        }
    }
    let end = Instant::now() + 30 * SECOND;
    while Instant::now() < end
        && (in_dds.distinct() < N as usize || at_client.distinct() < N as usize)
    {
        step(&mut publ, &mut sub, &mut in_dds, &mut at_client);
    }
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        step(&mut publ, &mut sub, &mut in_dds, &mut at_client);
    }
    in_dds.assert_exactly_once(0..N, "Cyclone reading a client of a single-process agent");
    at_client.assert_exactly_once(0..N, "a client reading a client of a single-process agent");
    at_client.assert_in_order("a client reading a client of a single-process agent");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_single_process_killed_mid_stream_is_restarted_and_loses_no_reliable_sample() {
    const N: u32 = 300;
    const KILL_AT: u32 = 100;
    const DOMAIN: i16 = 172;
    let agent = AgentProcess::builder("single-kill")
        .extra(&["--single-process"])
        .start();
    let dds = reader(DOMAIN, 100_000);
    let mut c = TestClient::new(agent.addr(), [0x51, 0x52, 0x53, 0x03]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(DOMAIN);
    assert!(
        dds.wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched"
    );
    let old = agent.child_pids("single-process");
    assert_eq!(old.len(), 1, "one process serves: {old:?}");
    let out = agent.output().clone();
    let mark = out.len();
    let mut got = Deliveries::default();
    for i in 0..N {
        if i == KILL_AT {
            sigkill(old[0]);
        }
        c.write_reliable(w, &hello_world(i, "through a crash"));
        // ~100 samples/s, so the outage falls in the middle of the stream.
        c.run_until(Duration::from_millis(10), |_| false);
        got.collect_from(&dds, "through a crash");
    }
    c.run_until(60 * SECOND, |_| {
        got.collect_from(&dds, "through a crash");
        got.distinct() as u32 >= N
    });
    c.run_until(DUPLICATE_GRACE, |_| {
        got.collect_from(&dds, "through a crash");
        false
    });
    out.wait_for(
        mark,
        "sessions taken over from the previous front-end",
        5 * SECOND,
    )
    .expect("the restarted process did not take the session over");
    let new = agent.child_pids("single-process");
    assert_eq!(new.len(), 1, "one process serves again: {new:?}");
    assert_ne!(new, old, "the process was not restarted");
    // As after a worker crash: what the process had written and Cyclone had not yet
    // acknowledged may come twice, near the kill only.
    got.assert_none_lost_repeats_near(N, KILL_AT, "a reader across a single-process restart");
    assert_eq!(c.session_statuses(), 1, "the client re-created its session");
    assert_eq!(
        out.count("session created"),
        1,
        "a session was created again"
    );
    assert!(agent.stop(), "agent did not stop cleanly after the restart");
}
