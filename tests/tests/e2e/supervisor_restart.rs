//! The whole agent restarted under its clients: the supervisor SIGKILLed mid-stream (as a
//! crash, or systemd's watchdog) and started again with the same command line, and a stop
//! and start of the whole group (as `systemctl restart` for an upgrade). The clients do not
//! create anything again: the new front-end takes their sessions over from the store the
//! old one left and replays their objects to the new worker. Every reliable sample written
//! reaches an independent DDS reader (Cyclone DDS) exactly once; a best-effort client's
//! samples flow again after the restart.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use xrce_common::wire::ObjectId;
use xrce_tests::{
    free_udp_port, hello_world, parse_sample_line, sigkill, AgentProcess, DdsPeer, Deliveries,
    PtyPair, TestClient,
};

const SECOND: Duration = Duration::from_secs(1);

/// How the agent goes away before it is started again.
#[derive(Clone, Copy, Debug)]
enum Ending {
    /// SIGKILL of the supervisor (its children are told by the kernel and stop).
    Kill,
    /// SIGTERM of the supervisor and a wait for the group to stop (`systemctl stop`).
    Stop,
}

fn reader(domain: i16) -> DdsPeer {
    DdsPeer::start(&[
        "read",
        "--domain",
        &domain.to_string(),
        "--count",
        "100000",
        "--reliable",
        "--timeout",
        "180",
    ])
}

fn collect(reader: &DdsPeer, got: &mut Deliveries, others: &mut Vec<u32>) {
    while let Some(l) = reader.line(Duration::ZERO) {
        if let Some((i, m)) = parse_sample_line(&l) {
            match m.as_str() {
                "reliable" => got.record(i),
                _ => others.push(i),
            }
        }
    }
}

/// Writes `n` reliable samples from `rel`'s writer (and one best-effort sample from `be`'s
/// every fifth), ending the agent after `end_at` of them and starting it again with
/// `restart`; returns what the reader got: the reliable indices, and the best-effort ones.
fn stream_through_restart(
    agent: AgentProcess,
    restart: impl FnOnce() -> AgentProcess,
    ending: Ending,
    (rel, w): (&mut TestClient, ObjectId),
    (be, bw): (&mut TestClient, ObjectId),
    reader: &DdsPeer,
    (n, end_at): (u32, u32),
) -> (AgentProcess, Deliveries, Vec<u32>) {
    let mut got = Deliveries::default();
    let mut best_effort = Vec::new();
    let mut agent = Some(agent);
    let mut restart = Some(restart);
    let mut restarted_at = None;
    for i in 0..n {
        if i == end_at {
            let old = agent.take().expect("agent");
            match ending {
                Ending::Kill => {
                    sigkill(old.pid() as i32);
                    drop(old);
                }
                Ending::Stop => assert!(old.stop_keeping_sessions(), "did not stop cleanly"),
            }
            let start = restart.take().expect("restart once");
            agent = Some(start());
            restarted_at = Some(i);
        }
        rel.write_reliable(w, &hello_world(i, "reliable"));
        if i % 5 == 0 {
            be.write_best_effort(bw, &hello_world(i, "best-effort"));
        }
        let t = Instant::now() + Duration::from_millis(10);
        while Instant::now() < t {
            rel.step();
            be.step();
        }
        collect(reader, &mut got, &mut best_effort);
    }
    assert!(restarted_at.is_some());
    // Until every reliable sample is in, then a grace for late duplicates.
    let end = Instant::now() + 60 * SECOND;
    let mut complete: Option<Instant> = None;
    while Instant::now() < end && complete.is_none_or(|t| t.elapsed() < 2 * SECOND) {
        rel.step();
        be.step();
        collect(reader, &mut got, &mut best_effort);
        if complete.is_none() && got.distinct() == n as usize {
            complete = Some(Instant::now());
        }
    }
    (agent.expect("agent"), got, best_effort)
}

fn udp_through_restart(ending: Ending, domain: i16, keys: ([u8; 4], [u8; 4])) {
    const N: u32 = 200;
    const END_AT: u32 = 60;
    let addr: SocketAddr = ([127, 0, 0, 1], free_udp_port()).into();
    // No --instance: the same command line must find its own store again.
    let agent = AgentProcess::at(addr).start();
    let instance = agent.instance().to_string();
    let reader = reader(domain);
    let mut rel = TestClient::new(addr, keys.0);
    rel.connect(10 * SECOND);
    let w = rel.setup_publisher(domain);
    let mut be = TestClient::new(addr, keys.1);
    be.connect(10 * SECOND);
    let bw = be.setup_publisher(domain);
    assert!(
        reader
            .wait_for("MATCHED 2", 30 * SECOND, || {
                rel.step();
                be.step();
            })
            .is_some(),
        "Cyclone never matched both writers"
    );
    let (agent, got, best_effort) = stream_through_restart(
        agent,
        move || AgentProcess::at(addr).start(),
        ending,
        (&mut rel, w),
        (&mut be, bw),
        &reader,
        (N, END_AT),
    );
    assert_eq!(
        agent.instance(),
        instance,
        "the restarted agent took another instance"
    );
    got.assert_exactly_once(0..N, &format!("reliable through a supervisor {ending:?}"));
    assert!(
        best_effort.iter().any(|i| *i > END_AT + 20),
        "no best-effort sample after the restart: {best_effort:?}"
    );
    let out = agent.output().clone();
    assert!(
        out.count("sessions taken over from the previous front-end") >= 1,
        "the new front-end took no session over"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn the_supervisor_killed_mid_stream_and_started_again_loses_no_reliable_sample() {
    udp_through_restart(Ending::Kill, 125, (*b"SKR1", *b"SKB1"));
}

#[test]
fn a_stop_and_start_of_the_whole_agent_loses_no_reliable_sample() {
    udp_through_restart(Ending::Stop, 94, (*b"SSR1", *b"SSB1"));
}

#[test]
fn a_serial_client_goes_on_after_the_supervisor_is_killed_and_started_again() {
    const N: u32 = 120;
    const END_AT: u32 = 40;
    let domain = 95;
    let pty = PtyPair::open();
    let dev = pty.slave_path.display().to_string();
    let instance = xrce_tests::unique_instance("sersup");
    let args: Vec<String> = [
        "serial",
        "--dev",
        dev.as_str(),
        "-b",
        "921600",
        "--dds-interface",
        "127.0.0.1",
        "--instance",
        instance.as_str(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let launch = {
        let args = args.clone();
        let instance = instance.clone();
        move || {
            let a: Vec<&str> = args.iter().map(String::as_str).collect();
            AgentProcess::exactly(
                &a,
                "agent ready",
                SocketAddr::new([127, 0, 0, 1].into(), 0),
                &instance,
            )
            .launch()
            .expect("the serial agent did not become ready")
        }
    };
    let agent = launch.clone()();
    let reader = reader(domain);
    let mut rel = TestClient::serial(pty.master, 1, *b"SER1");
    rel.connect(10 * SECOND);
    let w = rel.setup_publisher(domain);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || rel.step())
            .is_some(),
        "Cyclone never matched the serial client's writer"
    );
    let mut got = Deliveries::default();
    let mut others = Vec::new();
    let mut agent = Some(agent);
    for i in 0..N {
        if i == END_AT {
            let old = agent.take().expect("agent");
            sigkill(old.pid() as i32);
            drop(old);
            agent = Some(launch.clone()());
        }
        rel.write_reliable(w, &hello_world(i, "reliable"));
        let t = Instant::now() + Duration::from_millis(10);
        while Instant::now() < t {
            rel.step();
        }
        collect(&reader, &mut got, &mut others);
    }
    let end = Instant::now() + 60 * SECOND;
    let mut complete: Option<Instant> = None;
    while Instant::now() < end && complete.is_none_or(|t| t.elapsed() < 2 * SECOND) {
        rel.step();
        collect(&reader, &mut got, &mut others);
        if complete.is_none() && got.distinct() == N as usize {
            complete = Some(Instant::now());
        }
    }
    got.assert_exactly_once(0..N, "a serial client through a supervisor kill");
    let agent = agent.expect("agent");
    assert!(
        agent
            .output()
            .count("sessions taken over from the previous front-end")
            >= 1
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
