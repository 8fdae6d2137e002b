//! Multicast discovery and the command line, through real agent processes.
//!
//! Discovery stays on loopback: requests go to 239.255.0.2 out of `lo` (IP_MULTICAST_IF
//! 127.0.0.1, loopback on), and the agent, bound to 127.0.0.1, joins the group there only.

use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket};
use std::process::Command;
use std::time::Duration;

use xrce_common::wire::cdr::CdrReader;
use xrce_common::wire::info::{ActivityInfo, ObjectInfo, TransportLocator};
use xrce_common::wire::{BaseObjectReply, Dialect, Message, Payload};
use xrce_tests::{binaries, free_tcp_port, free_udp_port, AgentProcess};

/// The GET_INFO the eProsima client multicasts (wire-traces/discovery-multicast.txt).
const DISCOVERY_REQUEST: [u8; 16] = [
    0x80, 0, 0, 0, 0x02, 0x01, 0x08, 0x00, 0x00, 0x09, 0xFF, 0xFD, 0x03, 0, 0, 0,
];

/// Sends a discovery request to `to` from loopback and returns the locators of every answer
/// within `wait`.
fn discover(to: SocketAddr, wait: Duration) -> Vec<Vec<TransportLocator>> {
    let socket = socket2::Socket::new(
        socket2::Domain::IPV4,
        socket2::Type::DGRAM,
        Some(socket2::Protocol::UDP),
    )
    .expect("socket");
    socket
        .bind(&SocketAddr::from(([127, 0, 0, 1], 0)).into())
        .expect("bind");
    socket
        .set_multicast_if_v4(&Ipv4Addr::LOCALHOST)
        .expect("multicast interface");
    socket.set_multicast_loop_v4(true).expect("multicast loop");
    let socket: UdpSocket = socket.into();
    socket
        .set_read_timeout(Some(Duration::from_millis(100)))
        .expect("timeout");
    let mut answers = Vec::new();
    let end = std::time::Instant::now() + wait;
    let mut buf = [0u8; 512];
    while std::time::Instant::now() < end {
        socket.send_to(&DISCOVERY_REQUEST, to).expect("send");
        while let Ok(n) = socket.recv(&mut buf) {
            answers.push(locators(&buf[..n]));
        }
        if !answers.is_empty() {
            break;
        }
    }
    answers
}

/// The locators in an INFO answer.
fn locators(bytes: &[u8]) -> Vec<TransportLocator> {
    let m = Message::decode(bytes).expect("an XRCE message");
    for s in &m.submessages {
        if let Payload::Info(i) = &s.payload {
            let mut all = vec![0u8; BaseObjectReply::LEN];
            all.extend_from_slice(i.object_info);
            let r = &mut CdrReader::new(&all, s.little_endian);
            let _ = r.take(BaseObjectReply::LEN);
            let info = ObjectInfo::decode(r, Dialect::Eprosima).expect("ObjectInfo");
            if let Some(ActivityInfo::Agent { locators, .. }) = info.activity {
                return locators;
            }
        }
    }
    panic!("no INFO with an agent activity in {bytes:02x?}");
}

fn group(port: u16) -> SocketAddr {
    SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::new(239, 255, 0, 2), port))
}

#[test]
fn multicast_discovery_answers_with_the_agents_locator() {
    let disc = free_udp_port();
    let port = free_udp_port();
    let agent = AgentProcess::builder("disc")
        .command_line(&[
            "udp4",
            "-p",
            &port.to_string(),
            "--bind",
            "127.0.0.1",
            "-d",
            &disc.to_string(),
        ])
        .launch()
        .expect("agent with discovery");
    let answers = discover(group(disc), Duration::from_secs(10));
    assert_eq!(
        answers,
        vec![vec![TransportLocator::Medium {
            address: [127, 0, 0, 1],
            port
        }]],
        "one answer naming where the agent serves"
    );
    // A request sent straight to the agent's address on the discovery port (the eProsima
    // client's uxr_discovery_agents with a list of agents) is answered the same way.
    assert_eq!(
        discover(
            SocketAddr::from(([127, 0, 0, 1], disc)),
            Duration::from_secs(10)
        ),
        vec![vec![TransportLocator::Medium {
            address: [127, 0, 0, 1],
            port
        }]],
        "one answer to a request sent to 127.0.0.1 on the discovery port"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_tcp_agent_is_discovered_at_its_tcp_port() {
    let disc = free_udp_port();
    let port = free_tcp_port();
    let agent = AgentProcess::builder("disctcp")
        .command_line(&[
            "tcp4",
            "-p",
            &port.to_string(),
            "--bind",
            "127.0.0.1",
            &format!("-d{disc}"),
        ])
        .launch()
        .expect("agent with discovery");
    let answers = discover(group(disc), Duration::from_secs(10));
    assert_eq!(
        answers,
        vec![vec![TransportLocator::Medium {
            address: [127, 0, 0, 1],
            port
        }]]
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// What the reference offers and this agent does not is refused with a clear message and
/// exit status 2, before anything starts.
#[test]
fn unsupported_options_exit_with_status_2() {
    let port = free_udp_port().to_string();
    for (args, says) in [
        (vec!["udp4", "-p", &port, "-m", "ced"], "ced"),
        (vec!["udp4", "-p", &port, "-mrtps"], "rtps"),
        (vec!["udp4", "-p", &port, "-P", "2020"], "p2p"),
        (vec!["canfd", "-D", "can0", "-I", "0x1"], "canfd"),
        (vec!["serial"], "--dev"),
        (vec!["tcp4"], "--port"),
    ] {
        let out = xrce_tests::output_within(
            Command::new(binaries().join("xrce-agent")).args(&args),
            Duration::from_secs(30),
        );
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(
            stderr.contains(says),
            "{args:?} should mention {says}: {stderr}"
        );
    }
}
