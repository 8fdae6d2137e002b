//! Interop with the real eProsima client: the datagrams its HelloWorld subscriber and
//! publisher sent to the reference agent (captured in `reliable-xml-helloworld.txt`) are
//! replayed to our agent, and our replies are compared with the reference agent's.

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use xrce_common::wire::{hex, Message, Payload};
use xrce_tests::{workspace, AgentProcess};

struct Line {
    /// Seconds since the capture's first datagram.
    at: f64,
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
                at: f[0].parse().expect("time"),
                to_agent: f[1] == "C>A",
                port: f[2].parse().expect("port"),
                bytes: unhex(f[3]),
            }
        })
        .collect()
}

/// Replies on streams (STATUS and DATA) in stream and sequence order, each once: a message
/// seen again under the same stream and sequence number is a retransmission, which must carry
/// the same bytes (a sample sent twice as two messages has two numbers and stays twice).
fn reliable_replies(all: &[Vec<u8>]) -> Vec<Vec<u8>> {
    let mut by_number: std::collections::BTreeMap<(u8, u16), Vec<u8>> = Default::default();
    for d in all.iter().filter(|d| d.len() > 4 && d[1] != 0) {
        let number = (d[1], u16::from_le_bytes([d[2], d[3]]));
        match by_number.entry(number) {
            std::collections::btree_map::Entry::Vacant(v) => {
                v.insert(d.clone());
            }
            std::collections::btree_map::Entry::Occupied(o) => assert_eq!(
                hex(o.get()),
                hex(d),
                "stream {} message {} sent again with other contents",
                number.0,
                number.1
            ),
        }
    }
    by_number.into_values().collect()
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

/// micro-ROS's creation pattern (binary, REPLACE|REUSE, a replier), a reset without DELETE,
/// and the same objects created again from a new port with the same key and session, with
/// other bytes in their padding: every CREATE of the second round answered STATUS_OK_MATCHED,
/// byte for byte as the reference agent answered.
#[test]
fn a_micro_ros_reset_gets_the_reference_agents_replies() {
    replay("microros-reset.txt");
}

/// The captures use DDS domain 0 and the same topic: one replay at a time.
static DOMAIN_0: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn replay(name: &str) {
    let _domain = DOMAIN_0.lock().unwrap_or_else(|p| p.into_inner());
    let lines = trace(name);
    let agent = AgentProcess::builder(&name[..8]).start();
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
    //
    // Paced as the real client was: never before the capture's own time for the message
    // (the HelloWorld examples write once a second), and never before our agent has sent
    // what caused it: the STATUS replies the reference had sent to each client by that
    // point of the capture (a client creates after its previous creation's answer), and,
    // for an ACKNACK, every stream message it acknowledges.
    let start = Instant::now();
    type Keys = std::collections::BTreeSet<(u8, u16)>;
    let index = |port: u16| clients.iter().position(|(p, _)| *p == port);
    let key =
        |d: &Vec<u8>| (d.len() > 4 && d[1] != 0).then(|| (d[1], u16::from_le_bytes([d[2], d[3]])));
    let is_status = |d: &Vec<u8>| d.get(4) == Some(&0x05);
    let mut statuses: Vec<Keys> = vec![Keys::new(); clients.len()];
    let mut everything: Vec<Keys> = vec![Keys::new(); clients.len()];
    let ours = |rx: &Vec<Vec<u8>>| -> Keys { rx.iter().filter_map(key).collect() };
    let wait_for = |rx: &mut Vec<Vec<Vec<u8>>>, want: &[Keys], what: &str| {
        let end = Instant::now() + Duration::from_secs(30);
        while !want
            .iter()
            .enumerate()
            .all(|(i, w)| w.is_subset(&ours(&rx[i])))
        {
            assert!(
                Instant::now() < end,
                "{name}: the agent never sent {what}: want {want:?}"
            );
            receive(rx, Duration::from_millis(1));
        }
    };
    for l in &lines {
        let Some(i) = index(l.port) else { continue };
        if !l.to_agent {
            if let Some(k) = key(&l.bytes) {
                everything[i].insert(k);
                if is_status(&l.bytes) {
                    statuses[i].insert(k);
                }
            }
            continue;
        }
        let due = start + Duration::from_secs_f64(l.at);
        while Instant::now() < due {
            receive(&mut rx, Duration::from_millis(1));
        }
        wait_for(
            &mut rx,
            &statuses,
            "the STATUS replies that came before this message",
        );
        // ACKNACK: first unacknowledged sequence number at 8, stream id at 12.
        if l.bytes.len() >= 13 && l.bytes[4] == 0x0A {
            let first = u16::from_le_bytes([l.bytes[8], l.bytes[9]]);
            let mut want = vec![Keys::new(); clients.len()];
            want[i] = (0..first).map(|s| (l.bytes[12], s)).collect();
            wait_for(&mut rx, &want, "the messages this ACKNACK acknowledges");
        }
        clients[i].1.send(&l.bytes).expect("send");
        receive(&mut rx, Duration::ZERO);
        // CREATE_CLIENT: as the real client, sent again each second until STATUS_AGENT
        // comes (a session at another endpoint is probed before it moves).
        if l.bytes.get(4) == Some(&0x00) {
            let is_agent_status = |d: &Vec<u8>| d.get(4) == Some(&0x04);
            let before = rx[i].iter().filter(|d| is_agent_status(d)).count();
            let mut attempts = 1;
            loop {
                let wait = Instant::now() + Duration::from_secs(1);
                let answered = |rx: &Vec<Vec<Vec<u8>>>| {
                    rx[i].iter().filter(|d| is_agent_status(d)).count() > before
                };
                while !answered(&rx) && Instant::now() < wait {
                    receive(&mut rx, Duration::from_millis(5));
                }
                if answered(&rx) {
                    break;
                }
                assert!(attempts < 10, "{name}: CREATE_CLIENT never answered");
                attempts += 1;
                clients[i].1.send(&l.bytes).expect("send");
            }
        }
    }
    wait_for(
        &mut rx,
        &everything,
        "every stream reply the reference sent",
    );
    // A reply the reference did not send would show within this grace.
    receive(&mut rx, xrce_tests::DUPLICATE_GRACE);

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
