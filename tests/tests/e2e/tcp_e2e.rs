//! TCP end to end: Rust XRCE clients on real TCP connections (IPv4 and IPv6 loopback, 2-byte
//! length prefix) ↔ `xrce-agent tcp4|tcp6` ↔ Cyclone DDS. Every sample is counted: each must
//! arrive exactly once.

use std::time::{Duration, Instant};

use xrce_common::session::client::ClientEvent;
use xrce_common::wire::{
    object_kind, status, ObjectId, ObjectVariant, Representation, VariantExtra,
};
use xrce_tests::scenarios;
use xrce_tests::{free_tcp_port, hello_world, xml, AgentProcess, DdsPeer, Link, TestClient};

const SECOND: Duration = Duration::from_secs(1);

fn tcp_agent(tag: &str, transport: &str, bind: &str) -> AgentProcess {
    tcp_agent_with(tag, transport, bind, &[])
}

fn tcp_agent_with(tag: &str, transport: &str, bind: &str, extra: &[&str]) -> AgentProcess {
    for _ in 0..5 {
        let port = free_tcp_port().to_string();
        let mut args = vec![transport, "-p", &port, "--bind", bind];
        args.extend_from_slice(extra);
        if let Some(a) = AgentProcess::builder(tag).command_line(&args).launch() {
            return a;
        }
    }
    panic!("the TCP agent did not start on any of 5 free ports");
}

#[test]
fn tcp4_client_publishes_cyclone_reads_each_sample_once() {
    let agent = tcp_agent("tcp4pub", "tcp4", "127.0.0.1");
    let mut c = TestClient::tcp(agent.addr(), [0x7C, 0x90, 0, 1]);
    c.connect(10 * SECOND);
    scenarios::client_publishes_cyclone_reads(&mut c, 50, 50, "over tcp", "a TCP client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn cyclone_publishes_tcp6_client_reads_each_sample_once() {
    let agent = tcp_agent("tcp6sub", "tcp6", "::1");
    assert!(agent.addr().is_ipv6());
    let mut c = TestClient::tcp(agent.addr(), [0x7C, 0x90, 0, 2]);
    c.connect(10 * SECOND);
    scenarios::cyclone_publishes_client_reads(&mut c, 51, 20, "to tcp6", "a TCP/IPv6 client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// A client whose connection breaks reconnects and creates its session again with the same
/// key: its objects are still there (creating them again says so), and its writer publishes
/// without being re-created.
#[test]
fn a_reconnecting_client_gets_its_objects_back() {
    let agent = tcp_agent("tcprecon", "tcp4", "127.0.0.1");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "52",
        "--count",
        "10",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let key = [0x7C, 0x90, 0, 3];
    let mut c = TestClient::tcp(agent.addr(), key);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(52);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    for i in 0..5 {
        c.write_reliable(w, &hello_world(i, "reconnect"));
    }
    // Every sample acknowledged before the connection goes.
    assert!(c.run_until(10 * SECOND, |c| c
        .client
        .unacked(xrce_common::wire::stream_id::BUILTIN_RELIABLE)
        == 0));
    drop(c);
    let mut c = TestClient::tcp(agent.addr(), key);
    c.connect(10 * SECOND);
    // Created again without REUSE or REPLACE: refused because it still exists.
    let participant = ObjectVariant {
        kind: object_kind::PARTICIPANT,
        representation: Representation::Xml(xml::PARTICIPANT.into()),
        extra: VariantExtra::DomainId(52),
    };
    let p = ObjectId::new(1, object_kind::PARTICIPANT);
    let req = c
        .client
        .create(Instant::now(), p, participant, false, false)
        .expect("create");
    assert_eq!(
        c.wait_status(req, 10 * SECOND),
        status::ERR_ALREADY_EXISTS,
        "the participant did not survive the reconnection"
    );
    for i in 5..10 {
        c.write_reliable(w, &hello_world(i, "reconnect"));
    }
    let got = reader.collect_deliveries(10, "reconnect", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..10, "samples around a reconnection");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// Hundreds of clients connected and in session at once; the agent keeps serving a new one.
#[test]
fn hundreds_of_tcp_sessions_at_once() {
    // All from 127.0.0.1: more than the default 256 connections from one address.
    let agent = tcp_agent_with(
        "tcpmany",
        "tcp4",
        "127.0.0.1",
        &["--max-connections-per-address", "400"],
    );
    let mut clients: Vec<TestClient> = (0..300u16)
        .map(|i| {
            let [a, b] = i.to_be_bytes();
            let mut c = TestClient::on_link(
                Link::tcp(agent.addr()).expect("connect"),
                xrce_common::session::client::ClientConfig::new(xrce_common::wire::ClientKey([
                    0x7D, 0, a, b,
                ])),
            );
            c.client.connect(std::time::Instant::now());
            c
        })
        .collect();
    let end = std::time::Instant::now() + 60 * SECOND;
    while clients.iter().any(|c| !c.client.is_connected()) && std::time::Instant::now() < end {
        for c in clients.iter_mut().filter(|c| !c.client.is_connected()) {
            c.step();
        }
    }
    let connected = clients.iter().filter(|c| c.client.is_connected()).count();
    assert_eq!(connected, 300, "sessions established");
    // One more, publishing, while all the others stay connected.
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "53",
        "--count",
        "5",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::tcp(agent.addr(), [0x7C, 0x90, 0, 4]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(53);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    for i in 0..5 {
        c.write_reliable(w, &hello_world(i, "one of many"));
    }
    let got = reader.collect_deliveries(5, "one of many", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..5, "a client among 300 others");
    // And the 300 are still served: each one's session answers a request (a DELETE of an
    // object it never created).
    let now = std::time::Instant::now();
    let requests: Vec<_> = clients
        .iter_mut()
        .map(|c| {
            c.client
                .delete(now, ObjectId::new(9, object_kind::DATAWRITER))
                .expect("delete")
        })
        .collect();
    let mut answers: Vec<Option<u8>> = vec![None; clients.len()];
    let end = now + 60 * SECOND;
    while answers.iter().any(Option::is_none) && std::time::Instant::now() < end {
        for (i, c) in clients.iter_mut().enumerate() {
            if answers[i].is_some() {
                continue;
            }
            c.step();
            answers[i] = c.events.iter().find_map(|e| match e {
                ClientEvent::Status(s) if s.related.request_id == requests[i] => {
                    Some(s.result.status)
                }
                _ => None,
            });
        }
    }
    let unanswered = answers.iter().filter(|a| a.is_none()).count();
    assert_eq!(unanswered, 0, "sessions of the 300 that no longer answer");
    assert!(
        answers
            .iter()
            .all(|a| *a == Some(status::ERR_UNKNOWN_REFERENCE)),
        "{answers:?}"
    );
    drop(clients);
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// `--tcp-idle-timeout`: a connection with nothing in or out for that long is closed (its
/// session then waits out the closed-session grace), and one whose client keeps talking
/// stays open.
#[test]
fn an_idle_tcp_connection_is_closed_and_a_talking_one_kept() {
    use std::io::Read;
    let agent = tcp_agent_with("tcpidle", "tcp4", "127.0.0.1", &["--tcp-idle-timeout", "1"]);
    let mut idle = TestClient::tcp(agent.addr(), [0x7C, 0x1D, 0, 1]);
    // Idle from its last message at the latest (the agent's answer may come later).
    let idle_since = Instant::now();
    idle.connect(10 * SECOND);
    let mut talking = TestClient::tcp(agent.addr(), [0x7C, 0x1D, 0, 2]);
    talking.connect(10 * SECOND);
    let mut closed_at = None;
    let mut buf = [0u8; 1024];
    let mut last_ping = Instant::now();
    while closed_at.is_none() && idle_since.elapsed() < 30 * SECOND {
        // The talking client pings every 200 ms (GET_INFO, answered with INFO).
        if last_ping.elapsed() >= Duration::from_millis(200) {
            talking.client.ping();
            last_ping = Instant::now();
        }
        talking.step();
        // The idle one only watches its connection for the agent's close.
        let Link::Tcp { stream, .. } = &mut idle.link else {
            panic!("a TCP link")
        };
        match stream.read(&mut buf) {
            Ok(0) => closed_at = Some(Instant::now()),
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            Err(_) => closed_at = Some(Instant::now()),
        }
    }
    let closed_at = closed_at.expect("the idle connection was never closed");
    // Its CREATE_CLIENT went out at `idle_since` at the earliest: closed no sooner than a
    // second after.
    assert!(
        closed_at.duration_since(idle_since) >= SECOND,
        "closed after {:?}, before its idle timeout (1 s)",
        closed_at.duration_since(idle_since)
    );
    // The talking client is still connected and served: a request of its session answered.
    assert!(
        talking.session_answers(10 * SECOND),
        "the talking client's connection was closed too"
    );
    assert!(
        agent
            .output()
            .logged("tcp_idle_connection", 1, xrce_tests::LOG_WAIT),
        "the close was not logged"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
