//! Interop with the real eProsima client: the datagrams its HelloWorld subscriber and
//! publisher sent to the reference agent (captured in `reliable-xml-helloworld.txt`) are
//! replayed to our agent, and our replies are compared with the reference agent's.

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use xrce_common::wire::{hex, Message, Payload};
use xrce_tests::{workspace, AgentProcess};

struct Line {
    t: f64,
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
                t: f[0].parse().expect("time"),
                to_agent: f[1] == "C>A",
                port: f[2].parse().expect("port"),
                bytes: unhex(f[3]),
            }
        })
        .collect()
}

fn recv_all(s: &UdpSocket, out: &mut Vec<Vec<u8>>, wait: Duration) {
    let end = Instant::now() + wait;
    let mut buf = [0u8; 2048];
    while Instant::now() < end {
        if let Ok(n) = s.recv(&mut buf) {
            out.push(buf[..n].to_vec());
        }
    }
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
    let sub_port = lines[0].port;
    let pub_port = lines
        .iter()
        .find(|l| l.port != sub_port)
        .expect("publisher")
        .port;
    let agent = AgentProcess::start(&name[..8]);
    let sock = |_: u16| {
        let s = UdpSocket::bind("127.0.0.1:0").expect("bind");
        s.connect(agent.addr()).expect("connect");
        s.set_read_timeout(Some(Duration::from_millis(2)))
            .expect("timeout");
        s
    };
    let (sub, publ) = (sock(sub_port), sock(pub_port));
    let (mut sub_rx, mut pub_rx) = (Vec::new(), Vec::new());
    // The client's first sample follows its writer's creation within milliseconds, as in the
    // capture: the reference agent delivers it inside one Fast DDS process, ours holds it
    // until the new DDS writer has matched the subscriber's reader, so it is not lost either.
    for l in lines.iter().filter(|l| l.to_agent) {
        let s = if l.port == sub_port { &sub } else { &publ };
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
        recv_all(&sub, &mut sub_rx, Duration::from_millis(wait / 2));
        recv_all(&publ, &mut pub_rx, Duration::from_millis(wait / 2));
        let _ = l.t;
    }
    recv_all(&sub, &mut sub_rx, Duration::from_millis(500));

    let reference = |port: u16| -> Vec<Vec<u8>> {
        reliable_replies(
            &lines
                .iter()
                .filter(|l| !l.to_agent && l.port == port)
                .map(|l| l.bytes.clone())
                .collect::<Vec<_>>(),
        )
    };
    // STATUS_AGENT: byte for byte.
    let status_agent = |rx: &[Vec<u8>]| rx.iter().find(|d| d.get(4) == Some(&0x04)).cloned();
    let ref_sa = lines
        .iter()
        .find(|l| !l.to_agent && l.bytes.get(4) == Some(&0x04))
        .map(|l| l.bytes.clone());
    assert_eq!(status_agent(&sub_rx), ref_sa, "STATUS_AGENT differs");
    assert_eq!(
        status_agent(&pub_rx),
        ref_sa,
        "STATUS_AGENT differs (publisher)"
    );
    // STATUS for every creation, then DATA for every sample: byte for byte, same sequence numbers.
    let ours_pub = reliable_replies(&pub_rx);
    assert_eq!(
        ours_pub,
        reference(pub_port),
        "publisher's reliable replies differ:\nours {:?}",
        ours_pub.iter().map(|d| hex(d)).collect::<Vec<_>>()
    );
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
    let ours_sub = reliable_replies(&sub_rx);
    let ref_sub = reference(sub_port);
    assert_eq!(
        ours_sub.len(),
        ref_sub.len(),
        "subscriber: {} replies, reference {}",
        ours_sub.len(),
        ref_sub.len()
    );
    for (o, r) in ours_sub.iter().zip(&ref_sub) {
        assert_eq!(
            hex(&unpad(o, r)),
            hex(r),
            "subscriber's STATUS/DATA differs from the reference agent's"
        );
    }
    // Every reply decodes with our codec too.
    for d in sub_rx.iter().chain(&pub_rx) {
        let m = Message::decode(d).expect("decode reply");
        assert!(!m
            .submessages
            .iter()
            .any(|s| matches!(s.payload, Payload::Unknown { .. })));
    }
}
