//! The agent as a whole, through real processes: the supervisor's restart back-off, a
//! client silent past the dead time, UDP over IPv6, and memory held within its bounds while
//! a subscriber that stopped reading is flooded.

use std::time::{Duration, Instant};

use xrce_common::session::client::ClientConfig;
use xrce_common::wire::ClientKey;
use xrce_tests::{
    free_udp_port, hello_world, rss_kib, sigkill, AgentProcess, DdsPeer, Deliveries, TestClient,
};

const SECOND: Duration = Duration::from_secs(1);

/// The `restart_in=` of every "child exited" line from `from` on, in milliseconds.
fn restart_delays(agent: &AgentProcess, from: usize) -> Vec<u64> {
    let mut out = Vec::new();
    let mut at = from;
    while let Some((i, line)) =
        agent
            .output()
            .wait_for(at, "child exited; restarting", Duration::ZERO)
    {
        at = i + 1;
        let d = line
            .split("restart_in=")
            .nth(1)
            .and_then(|r| r.split_whitespace().next())
            .unwrap_or("");
        let ms = if let Some(v) = d.strip_suffix("ms") {
            v.parse::<f64>().ok()
        } else {
            d.strip_suffix('s')
                .and_then(|v| v.parse::<f64>().ok())
                .map(|s| s * 1e3)
        };
        out.extend(ms.map(|m| m.round() as u64));
    }
    out
}

#[test]
fn a_child_that_keeps_dying_is_restarted_with_growing_back_off() {
    let port = free_udp_port().to_string();
    let agent = AgentProcess::builder("backoff")
        .command_line(&["udp4", "-p", &port, "--bind", "127.0.0.1"])
        .launch()
        .expect("agent");
    let out = agent.output().clone();
    let mark = out.len();
    for round in 0..4 {
        let pid = agent
            .child_pid_with("frontend", "udp4")
            .expect("the front-end's pid");
        let seen = out.len();
        sigkill(pid);
        out.wait_for(seen, "restarted name=xrce-frontend", 20 * SECOND)
            .unwrap_or_else(|| panic!("not restarted after kill {round}"));
        // The new one must be running (forked and exec'd: on a loaded machine the fork can
        // be seen before its command line is the front-end's) before it is killed again.
        let end = Instant::now() + 10 * SECOND;
        while Instant::now() < end {
            match agent.child_pid_with("frontend", "udp4") {
                Some(p) if p != pid => break,
                _ => std::thread::sleep(Duration::from_millis(5)),
            }
        }
    }
    // Each crash within 10 s of the last start doubles the wait: 50, 100, 200, 400 ms.
    assert_eq!(restart_delays(&agent, mark), [50, 100, 200, 400]);
    assert!(agent.ping(10 * SECOND), "not serving after the restarts");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_client_silent_past_the_dead_time_loses_its_session_and_entities() {
    let port = free_udp_port().to_string();
    let agent = AgentProcess::builder("deadtime")
        .command_line(&[
            "udp4",
            "-p",
            &port,
            "--bind",
            "127.0.0.1",
            "--client-dead-time",
            "1",
        ])
        .launch()
        .expect("agent");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "37",
        "--count",
        "100",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let key = [0xDE, 0xAD, 0x00, 0x01];
    let mut c = TestClient::new(agent.addr(), key);
    c.connect(10 * SECOND);
    c.setup_publisher(37);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    let out = agent.output().clone();
    let mark = out.len();
    // Silent: the client stops answering (its socket stays open, probes go unanswered).
    // (When exactly, relative to its last message, is the session core's unit tests'.)
    out.wait_for(mark, "client silent past its dead time", 10 * SECOND)
        .expect("the silent client was not deleted");
    // Its DDS writer went with it.
    assert!(
        reader.wait_for("MATCHED 0", 30 * SECOND, || {}).is_some(),
        "the deleted client's writer is still matched"
    );
    // Coming back it creates a new session (logged by then or soon after: the log is read
    // from a pipe by another thread).
    let mark = out.len();
    let mut again = TestClient::new(agent.addr(), key);
    again.connect(10 * SECOND);
    out.wait_for(mark, "session created", 10 * SECOND)
        .expect("no new session for the returning client");
    assert_eq!(out.count("session created"), 2);
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn udp6_client_publishes_cyclone_reads_each_sample_once() {
    let port = free_udp_port().to_string();
    let agent = AgentProcess::builder("udp6")
        .command_line(&["udp6", "-p", &port, "--bind", "::1"])
        .launch()
        .expect("agent on ::1");
    assert!(agent.addr().is_ipv6());
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "38",
        "--count",
        "20",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0x06, 0x06, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(38);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    for i in 0..20 {
        c.write_reliable(w, &hello_world(i, "over udp6"));
    }
    let got = reader.collect_deliveries(20, "over udp6", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..20, "a UDP/IPv6 client");
    got.assert_in_order("a UDP/IPv6 client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// Samples of the flood: about 1 KB each, 117 MiB in all, more than either bound below, so
/// that an agent holding the whole flood fails the test.
const FLOOD_SAMPLES: u32 = 120_000;

/// A subscriber stops reading (and acknowledging) while Cyclone floods its topic with 117 MiB:
/// its read is paused, the samples wait in the DDS reader's bounded history, the agent's
/// memory grows by no more than its configured queues, and another client is served
/// meanwhile.
#[test]
fn a_flood_to_a_stalled_subscriber_stays_within_the_agents_bounds() {
    let port = free_udp_port().to_string();
    let agent = AgentProcess::builder("flood")
        .command_line(&["udp4", "-p", &port, "--bind", "127.0.0.1"])
        .launch()
        .expect("agent");
    let mut stalled = TestClient::new(agent.addr(), [0xF1, 0x00, 0x00, 0x01]);
    stalled.connect(10 * SECOND);
    stalled.setup_subscriber(39);
    // Its READ_DATA reaches the agent; from now on it neither reads nor acknowledges.
    stalled.run_until(SECOND, |_| false);
    let frontend = agent.child_pid_with("frontend", "udp4").expect("front-end");
    let worker = agent.child_pids("dds-worker")[0];
    let (fe0, w0) = (rss_kib(frontend), rss_kib(worker));
    let writer = DdsPeer::start(&[
        "write",
        "--domain",
        "39",
        "--count",
        &FLOOD_SAMPLES.to_string(),
        "--interval-ms",
        "0",
        "--message",
        "0123456789",
        "--message-repeat",
        "100",
        "--wait-match",
        "--reliable",
        "--timeout",
        "300",
        "--linger-ms",
        "1000",
    ]);
    // Another client, on another topic's domain, is served through the flood.
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "46",
        "--count",
        "20",
        "--reliable",
        "--timeout",
        "120",
    ]);
    let mut other = TestClient::new(agent.addr(), [0xF1, 0x00, 0x00, 0x02]);
    other.connect(10 * SECOND);
    let w = other.setup_publisher(46);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || other.step())
        .is_some());
    let mut peak = (fe0, w0);
    let mut sent = 0;
    let mut got = Deliveries::default();
    let end = Instant::now() + 300 * SECOND;
    let mut flooded = false;
    while Instant::now() < end && !(flooded && got.distinct() == 20) {
        if sent < 20 && other.client.can_send_reliable(0x80) {
            other.write_reliable(w, &hello_world(sent, "served"));
            sent += 1;
        }
        other.step();
        while let Some(l) = reader.line(Duration::ZERO) {
            if let Some((i, _)) = xrce_tests::parse_sample_line(&l) {
                got.record(i);
            }
        }
        while let Some(l) = writer.line(Duration::ZERO) {
            flooded |= l.starts_with(&format!("SENT {}", FLOOD_SAMPLES - 1));
        }
        peak = (peak.0.max(rss_kib(frontend)), peak.1.max(rss_kib(worker)));
    }
    assert!(flooded, "Cyclone did not finish the flood");
    got.assert_exactly_once(0..20, "a client served during the flood");
    // The front-end queues at most 4 MiB per stream and 64 MiB of operations; the worker
    // holds a congested front-end's replies up to 64 MiB, the rest stays in DDS.
    let (fe_growth, w_growth) = (peak.0.saturating_sub(fe0), peak.1.saturating_sub(w0));
    eprintln!("flood: front-end grew {fe_growth} KiB, worker {w_growth} KiB");
    assert!(
        fe_growth < 32 << 10,
        "the front-end grew by {fe_growth} KiB"
    );
    assert!(w_growth < 96 << 10, "the worker grew by {w_growth} KiB");
    drop(stalled);
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// Hard liveliness (eProsima's `uxr_hl` property in CREATE_CLIENT): a client that asks for it
/// is dropped after that much silence even though the agent has no `--client-dead-time`; a
/// client that did not ask keeps its session however long it is silent.
#[test]
fn a_client_asking_for_hard_liveliness_is_dropped_when_silent_and_only_it() {
    let port = free_udp_port().to_string();
    let agent = AgentProcess::builder("hardlive")
        .command_line(&["udp4", "-p", &port, "--bind", "127.0.0.1"])
        .launch()
        .expect("agent");
    let mut config = ClientConfig::new(ClientKey([0x4C, 0x1F, 0x00, 0x01]));
    config.hard_liveliness = Some(SECOND);
    let mut watched = TestClient::with_config(agent.addr(), config);
    watched.connect(10 * SECOND);
    let mut other = TestClient::new(agent.addr(), [0x4C, 0x1F, 0x00, 0x02]);
    other.connect(10 * SECOND);
    let out = agent.output().clone();
    // Both go silent (their sockets stay open; probes go unanswered). From the start of the
    // log: the watched one may be gone before the other has connected.
    let (_, line) = out
        .wait_for(0, "client silent past its dead time", 15 * SECOND)
        .expect("the client with hard liveliness was not dropped");
    assert!(
        line.contains("4C1F0001"),
        "another client was dropped: {line}"
    );
    // Three more of its timeouts: the other one is still there, and answers.
    std::thread::sleep(3 * SECOND);
    assert_eq!(
        out.count("client silent past its dead time"),
        1,
        "a client without hard liveliness was dropped"
    );
    assert!(
        other.session_answers(10 * SECOND),
        "the silent client without hard liveliness lost its session"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
