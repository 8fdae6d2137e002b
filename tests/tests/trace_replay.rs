//! Interop with the real eProsima client: the datagrams its HelloWorld subscriber and
//! publisher sent to the reference agent (captured in `reliable-xml-helloworld.txt`) are
//! replayed to our agent, and our replies are compared with the reference agent's.

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use xrce_common::wire::{hex, Message, Payload};
use xrce_tests::{workspace, AgentProcess};

struct Line {
    to_agent: bool,
    port: u16,
    bytes: Vec<u8>,
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
        .collect()
}

fn trace(name: &str) -> Vec<Line> {
    let path = workspace().join("common/tests/data/wire-traces").join(name);
    std::fs::read_to_string(path)
        .expect("trace")
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            Line {
                to_agent: f[1] == "C>A",
                port: f[2].parse().expect("port"),
                bytes: unhex(f[3]),
            }
        })
        .collect()
}

/// Replies on streams (STATUS and DATA) in stream and sequence order, deduplicated.
fn reliable_replies(all: &[Vec<u8>]) -> Vec<Vec<u8>> {
    let mut v: Vec<Vec<u8>> = all
        .iter()
        .filter(|d| d.len() > 4 && d[1] != 0)
        .cloned()
        .collect();
    v.sort_by_key(|d| (d[1], u16::from_le_bytes([d[2], d[3]])));
    v.dedup();
    v
}

#[test]
fn reliable_helloworld_gets_the_reference_agents_replies() {
    replay("reliable-xml-helloworld.txt");
}

#[test]
fn best_effort_helloworld_gets_the_reference_agents_replies() {
    replay("besteffort-xml-helloworld.txt");
}

/// Binary representations (what micro-ROS sends); the client then reads its own samples.
#[test]
fn binary_creation_gets_the_reference_agents_replies() {
    replay("binary-creation.txt");
}

/// 50,000-byte samples: the client's FRAGMENTs are reassembled, and the DATA to the
/// subscriber is fragmented to its MTU exactly as the reference agent does it.
#[test]
fn big_fragmented_samples_get_the_reference_agents_replies() {
    replay("big-fragmented.txt");
}

/// The captures use DDS domain 0 and the same topic: one replay at a time.
static DOMAIN_0: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn replay(name: &str) {
    let _domain = DOMAIN_0.lock().unwrap_or_else(|p| p.into_inner());
    let lines = trace(name);
    let agent = AgentProcess::start(&name[..8]);
    // One socket per client of the capture, in order of appearance.
    let mut ports: Vec<u16> = Vec::new();
    for l in &lines {
        if !ports.contains(&l.port) {
            ports.push(l.port);
        }
    }
    let clients: Vec<(u16, UdpSocket)> = ports
        .iter()
        .map(|p| {
            let s = UdpSocket::bind("127.0.0.1:0").expect("bind");
            s.connect(agent.addr()).expect("connect");
            s.set_read_timeout(Some(Duration::from_millis(1)))
                .expect("timeout");
            (*p, s)
        })
        .collect();
    let mut rx: Vec<Vec<Vec<u8>>> = vec![Vec::new(); clients.len()];
    let receive = |rx: &mut Vec<Vec<Vec<u8>>>, wait: Duration| {
        let end = Instant::now() + wait;
        loop {
            let mut buf = [0u8; 2048];
            for (i, (_, s)) in clients.iter().enumerate() {
                // Read timeout 1 ms: drain what is there, then move on.
                while let Ok(n) = s.recv(&mut buf) {
                    rx[i].push(buf[..n].to_vec());
                }
            }
            if Instant::now() >= end {
                break;
            }
        }
    };
    // The client's first sample follows its writer's creation within milliseconds, as in the
    // capture: the reference agent delivers it inside one Fast DDS process, ours holds it
    // until the new DDS writer has matched the subscriber's reader, so it is not lost either.
    for l in lines.iter().filter(|l| l.to_agent) {
        let (_, s) = clients
            .iter()
            .find(|(p, _)| *p == l.port)
            .expect("client socket");
        s.send(&l.bytes).expect("send");
        // Creations need the worker's answer before the client's next step.
        let wait = if l.bytes.get(8) == Some(&0x01) {
            1500
        } else if l.bytes.get(8) == Some(&0x0D) || l.bytes.get(1) == Some(&0) {
            // FRAGMENTs and acknowledgements: the client sends them back to back.
            4
        } else {
            60
        };
        receive(&mut rx, Duration::from_millis(wait));
    }
    receive(&mut rx, Duration::from_millis(500));

    // STATUS_AGENT: byte for byte.
    let ref_sa = lines
        .iter()
        .find(|l| !l.to_agent && l.bytes.get(4) == Some(&0x04))
        .map(|l| l.bytes.clone());
    // DATA: RustDDS pads serialized samples to a multiple of 4 and does not pass the padding
    // count on, so our DATA may carry up to 3 extra zero bytes; everything else is identical.
    let unpad = |d: &Vec<u8>, reference: &Vec<u8>| -> Vec<u8> {
        let extra = d.len().saturating_sub(reference.len());
        if d.get(4) == Some(&0x09) && extra <= 3 && d[reference.len()..].iter().all(|b| *b == 0) {
            let mut v = d[..reference.len()].to_vec();
            let len = u16::from_le_bytes([v[6], v[7]]) - extra as u16;
            v[6..8].copy_from_slice(&len.to_le_bytes());
            v
        } else {
            d.clone()
        }
    };
    for (i, (port, _)) in clients.iter().enumerate() {
        let status_agent = rx[i].iter().find(|d| d.get(4) == Some(&0x04)).cloned();
        assert_eq!(status_agent, ref_sa, "client {port}: STATUS_AGENT differs");
        // STATUS for every creation, then DATA for every sample: byte for byte, with the
        // same stream sequence numbers.
        let ours = reliable_replies(&rx[i]);
        let reference = reliable_replies(
            &lines
                .iter()
                .filter(|l| !l.to_agent && l.port == *port)
                .map(|l| l.bytes.clone())
                .collect::<Vec<_>>(),
        );
        assert_eq!(
            ours.len(),
            reference.len(),
            "client {port}: {} replies, reference {}:\nours {:?}",
            ours.len(),
            reference.len(),
            ours.iter().map(|d| hex(d)).collect::<Vec<_>>()
        );
        for (o, r) in ours.iter().zip(&reference) {
            assert_eq!(
                hex(&unpad(o, r)),
                hex(r),
                "client {port}: a STATUS/DATA differs from the reference agent's"
            );
        }
        // Every reply decodes with our codec too.
        for d in &rx[i] {
            let m = Message::decode(d).expect("decode reply");
            assert!(!m
                .submessages
                .iter()
                .any(|s| matches!(s.payload, Payload::Unknown { .. })));
        }
    }
}
