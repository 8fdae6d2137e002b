//! Sessions outlive their front-end process: a front-end SIGKILLed mid-stream is restarted
//! by the supervisor, takes its clients' sessions, objects and reads over, and the clients
//! go on without re-creating anything, every sample once.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use xrce_common::wire::object_kind;
use xrce_tests::{
    free_tcp_port, hello_world, parse_sample_line, parse_sample_writer, sigkill,
    unlimited_reliable_read, AgentProcess, DdsPeer, Deliveries, PtyPair, TestClient,
    DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn a_front_end_killed_mid_stream_is_taken_over_and_every_sample_arrives_once() {
    takeover_mid_stream("fe-kill", Signal::SIGKILL, 79);
}

/// A front-end stopped on purpose (SIGTERM: how a new binary is rolled out, one front-end
/// at a time) hands its sessions over the same way.
#[test]
fn a_front_end_stopped_for_an_upgrade_hands_its_sessions_over() {
    takeover_mid_stream("fe-term", Signal::SIGTERM, 82);
}

fn takeover_mid_stream(tag: &str, signal: Signal, domain: i16) {
    const N: u32 = 300;
    const KILL_AT: u32 = 100;
    let agent = AgentProcess::builder(tag).start();
    let d = domain.to_string();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &d,
        "--count",
        &(10 * N).to_string(),
        "--reliable",
        "--timeout",
        "120",
    ]);
    let mut sub = TestClient::new(agent.addr(), [0x55, 0x66, 0x77, 0x79]);
    sub.connect(10 * SECOND);
    sub.setup_subscriber(domain);
    let mut publ = TestClient::new(agent.addr(), [0x11, 0x22, 0x33, 0x79]);
    publ.connect(10 * SECOND);
    let w = publ.setup_publisher(domain);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || {
                publ.step();
                sub.step();
            })
            .is_some(),
        "Cyclone never matched"
    );
    let frontend = agent
        .child_pid_with("frontend", "udp4")
        .expect("front-end pid");
    let out = agent.output().clone();
    let mark = out.len();

    let mut dds = Deliveries::default();
    let mut client = Deliveries::default();
    let mut writers = BTreeSet::new();
    let collect = |publ: &mut TestClient,
                   sub: &mut TestClient,
                   dds: &mut Deliveries,
                   client: &mut Deliveries,
                   writers: &mut BTreeSet<u64>| {
        publ.step();
        sub.step();
        for (i, m) in sub.take_samples() {
            assert_eq!(m, "through a front-end crash");
            client.record(i);
        }
        while let Some(l) = reader.line(Duration::ZERO) {
            if let Some((i, m)) = parse_sample_line(&l) {
                assert_eq!(m, "through a front-end crash");
                dds.record(i);
                writers.extend(parse_sample_writer(&l).map(|(_, w)| w));
            }
        }
    };
    for i in 0..N {
        if i == KILL_AT {
            kill(Pid::from_raw(frontend), signal).expect("signal the front-end");
        }
        publ.write_reliable(w, &hello_world(i, "through a front-end crash"));
        // ~100 samples/s, so the outage falls in the middle of the stream.
        let end = Instant::now() + Duration::from_millis(10);
        while Instant::now() < end {
            collect(&mut publ, &mut sub, &mut dds, &mut client, &mut writers);
        }
    }
    let end = Instant::now() + 60 * SECOND;
    while Instant::now() < end && (dds.distinct() < N as usize || client.distinct() < N as usize) {
        collect(&mut publ, &mut sub, &mut dds, &mut client, &mut writers);
    }
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        collect(&mut publ, &mut sub, &mut dds, &mut client, &mut writers);
    }
    out.wait_for(
        mark,
        "sessions taken over from the previous front-end",
        5 * SECOND,
    )
    .expect("the new front-end did not take the sessions over");
    assert_ne!(
        agent.child_pid_with("frontend", "udp4"),
        Some(frontend),
        "the front-end was not restarted"
    );
    dds.assert_exactly_once(0..N, "Cyclone reading a client across a front-end crash");
    // The worker kept the client's DDS writer: the new front-end took it back rather than
    // have it deleted (with what its readers had not acknowledged) and created again.
    assert_eq!(
        writers.len(),
        1,
        "Cyclone saw the samples come from {} DDS writers",
        writers.len()
    );
    let (_, line) = out
        .wait_for(mark, "front-end replay complete", 5 * SECOND)
        .expect("the worker did not report the replay complete");
    // Both clients' participant, topic, publisher or subscriber, and writer or reader.
    assert!(
        line.contains("adopted=8") && line.contains("removed=0"),
        "not every entity was taken back: {line}"
    );
    // The subscribing client: every sample once and in order. Samples the worker had
    // handed to the dead front-end and that never reached the client are offered again to
    // the successor's replayed read, which drops those its predecessor had delivered.
    let missing: Vec<u32> = (0..N).filter(|i| client.count(*i) == 0).collect();
    assert!(
        missing.is_empty(),
        "samples missing at the subscribing client: {missing:?}"
    );
    assert!(
        client.repeated().is_empty(),
        "samples delivered twice: {:?}",
        client.repeated()
    );
    client.assert_in_order("a client reading a client across a front-end crash");
    // Neither client had to create its session again.
    assert_eq!(
        publ.session_statuses(),
        1,
        "the publisher re-created its session"
    );
    assert_eq!(
        sub.session_statuses(),
        1,
        "the subscriber re-created its session"
    );
    assert_eq!(
        out.count("session created"),
        2,
        "a session was created again"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// Over a serial line: the restarted front-end opens the device again and takes the
/// session of the client on it over (its endpoint is the line and its address).
#[test]
fn a_serial_front_end_killed_mid_stream_is_taken_over() {
    const N: u32 = 150;
    const KILL_AT: u32 = 50;
    let pty = PtyPair::open();
    let dev = pty.slave_path.to_str().expect("utf-8 path").to_string();
    let agent = AgentProcess::builder("fe-kill-serial")
        .command_line(&["serial", "--dev", &dev, "-b", "921600"])
        .launch()
        .expect("the serial agent did not become ready");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "81",
        "--count",
        &(10 * N).to_string(),
        "--reliable",
        "--timeout",
        "120",
    ]);
    let mut c = TestClient::serial(pty.master, 1, [0x5E, 0x81, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(81);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched"
    );
    let frontend = agent
        .child_pid_with("frontend", "serial")
        .expect("front-end pid");
    let out = agent.output().clone();
    let mark = out.len();
    let mut got = Deliveries::default();
    let collect = |c: &mut TestClient, got: &mut Deliveries| {
        c.step();
        while let Some(l) = reader.line(Duration::ZERO) {
            if let Some((i, m)) = parse_sample_line(&l) {
                assert_eq!(m, "serial crash");
                got.record(i);
            }
        }
    };
    for i in 0..N {
        if i == KILL_AT {
            sigkill(frontend);
        }
        c.write_reliable(w, &hello_world(i, "serial crash"));
        let end = Instant::now() + Duration::from_millis(10);
        while Instant::now() < end {
            collect(&mut c, &mut got);
        }
    }
    let end = Instant::now() + 60 * SECOND;
    while Instant::now() < end && got.distinct() < N as usize {
        collect(&mut c, &mut got);
    }
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        collect(&mut c, &mut got);
    }
    out.wait_for(
        mark,
        "sessions taken over from the previous front-end",
        5 * SECOND,
    )
    .expect("the new front-end did not take the session over");
    got.assert_exactly_once(
        0..N,
        "Cyclone reading a serial client across a front-end crash",
    );
    assert_eq!(c.session_statuses(), 1, "the client re-created its session");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// A TCP client's session ends with its connection, so a restarted front-end has nothing of
/// it to take over: the worker, which kept the client's entities for the new front-end's
/// replay, removes them once that replay is done (the Cyclone reader sees the writer go),
/// and the client that connects again creates its session anew.
#[test]
fn a_tcp_front_end_killed_leaves_no_entity_behind() {
    let mut agent = None;
    for _ in 0..5 {
        let port = free_tcp_port().to_string();
        agent = AgentProcess::builder("fe-kill-tcp")
            .command_line(&["tcp4", "-p", &port])
            .launch();
        if agent.is_some() {
            break;
        }
    }
    let agent = agent.expect("the TCP agent did not start on any of 5 free ports");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "86",
        "--count",
        "100",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::tcp(agent.addr(), [0x7C, 0x86, 0, 1]);
    c.connect(10 * SECOND);
    c.setup_publisher(86);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched"
    );
    let frontend = agent
        .child_pid_with("frontend", "tcp4")
        .expect("front-end pid");
    let out = agent.output().clone();
    let mark = out.len();
    sigkill(frontend);
    let (_, line) = out
        .wait_for(mark, "front-end replay complete", 20 * SECOND)
        .expect("the worker did not report the new front-end's replay");
    let removed: usize = line
        .split("removed=")
        .nth(1)
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    assert!(
        line.contains("adopted=0") && removed > 0,
        "the TCP client's entities were not removed, or were taken back: {line}"
    );
    assert!(
        reader.wait_for("MATCHED 0", 20 * SECOND, || {}).is_some(),
        "the client's DDS writer was left behind"
    );
    drop(c);
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// The data a client reads keeps coming from DDS while its front-end is down. The worker
/// takes those samples from the DDS reader and hands them to the dead process, or holds
/// them for it; the successor's replayed read gets them again (those the dead process had
/// delivered are dropped by identity): the client reads every sample once, in order.
#[test]
fn a_front_end_killed_while_dds_data_flows_to_its_client_loses_none() {
    read_through_takeover("fe-kill-read", Signal::SIGKILL, 88);
}

/// The same for a front-end stopped on purpose (its queue goes with it, and what the worker
/// held for it is offered to the successor's read).
#[test]
fn a_front_end_stopped_while_dds_data_flows_to_its_client_loses_none() {
    read_through_takeover("fe-term-read", Signal::SIGTERM, 87);
}

fn read_through_takeover(tag: &str, signal: Signal, domain: i16) {
    const N: u32 = 600;
    let agent = AgentProcess::builder(tag).start();
    let d = domain.to_string();
    let mut sub = TestClient::new(agent.addr(), [0x5E, 0x87, 0x00, 0x01]);
    sub.connect(10 * SECOND);
    // KEEP_ALL: samples wait in the DDS reader while the front-end is away, however many.
    let reader_xml = "<dds><data_reader><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name>\
        <dataType>HelloWorld</dataType></topic><qos><reliability><kind>RELIABLE</kind>\
        </reliability><historyQos><kind>KEEP_ALL</kind></historyQos></qos></data_reader></dds>";
    let r = sub.setup_chain(
        domain,
        object_kind::SUBSCRIBER,
        object_kind::DATAREADER,
        reader_xml,
    );
    sub.client
        .read(Instant::now(), r, unlimited_reliable_read())
        .expect("read");
    let writer = DdsPeer::start(&[
        "write",
        "--domain",
        &d,
        "--count",
        &N.to_string(),
        "--interval-ms",
        "3",
        "--reliable",
        "--wait-match",
        "--message",
        "read through a crash",
        "--timeout",
        "120",
    ]);
    let frontend = agent
        .child_pid_with("frontend", "udp4")
        .expect("front-end pid");
    let out = agent.output().clone();
    let mark = out.len();
    let mut got = Deliveries::default();
    let end = Instant::now() + 90 * SECOND;
    let mut killed = false;
    while Instant::now() < end && got.distinct() < N as usize {
        sub.step();
        for (i, m) in sub.take_samples() {
            assert_eq!(m, "read through a crash");
            got.record(i);
        }
        while writer.line(Duration::ZERO).is_some() {}
        if !killed && got.distinct() >= 150 {
            // Mid-stream: the writer goes on at about 300 samples/s meanwhile.
            kill(Pid::from_raw(frontend), signal).expect("signal the front-end");
            killed = true;
        }
    }
    assert!(killed, "the stream never got going");
    // The path under test ran: the worker offered the successor's read what it had kept.
    assert!(
        out.wait_for(mark, "recent samples offered again", 5 * SECOND)
            .is_some(),
        "the worker offered the replayed read nothing"
    );
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        sub.step();
        for (i, _) in sub.take_samples() {
            got.record(i);
        }
    }
    got.assert_exactly_once(0..N, "a client reading DDS data across a front-end crash");
    got.assert_in_order("a client reading DDS data across a front-end crash");
    assert_eq!(
        sub.session_statuses(),
        1,
        "the subscriber re-created its session"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
