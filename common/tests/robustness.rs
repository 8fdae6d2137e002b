//! Bad input never panics, and never stops the agent core from serving: arbitrary bytes and
//! mutations of real captured datagrams go through the decoder and the agent core, and a
//! ping afterwards is still answered.

use std::time::{Duration, Instant};

use proptest::prelude::*;
use xrce_common::session::agent::{Agent, AgentConfig, NullSink};
use xrce_common::wire::{Message, Payload};

fn captured() -> Vec<Vec<u8>> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/wire-traces");
    let mut out = Vec::new();
    for name in [
        "reliable-xml-helloworld.txt",
        "binary-creation.txt",
        "timesync.txt",
        "ping.txt",
    ] {
        let text = std::fs::read_to_string(dir.join(name)).expect("trace");
        for l in text.lines().filter(|l| l.contains(" C>A ")) {
            let h = l.split_whitespace().nth(3).expect("hex");
            out.push(
                (0..h.len())
                    .step_by(2)
                    .map(|i| u8::from_str_radix(&h[i..i + 2], 16).expect("hex"))
                    .collect(),
            );
        }
    }
    out
}

const PING: [u8; 16] = [
    0x80, 0, 0, 0, 0x02, 0x01, 0x08, 0x00, 0x00, 0x0A, 0xFF, 0xFD, 0x03, 0, 0, 0,
];

fn assert_ping_answered(agent: &mut Agent<u8>, now: Instant) {
    while agent.poll_transmit().is_some() {}
    agent.handle_datagram(now, 200, &PING, &mut NullSink);
    let t = agent.poll_transmit().expect("ping answered");
    let m = Message::decode(&t.data).expect("INFO decodes");
    assert!(matches!(m.submessages[0].payload, Payload::Info(_)));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn decoder_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        let _ = Message::decode(&bytes);
    }

    #[test]
    fn agent_core_survives_arbitrary_datagrams(
        datagrams in proptest::collection::vec((any::<u8>(), proptest::collection::vec(any::<u8>(), 0..300)), 1..20)
    ) {
        let mut agent: Agent<u8> = Agent::new(AgentConfig::default());
        let t0 = Instant::now();
        for (i, (src, d)) in datagrams.iter().enumerate() {
            agent.handle_datagram(t0 + Duration::from_millis(i as u64), *src, d, &mut NullSink);
            agent.handle_timeout(t0 + Duration::from_millis(i as u64 * 50), &mut NullSink);
        }
        assert_ping_answered(&mut agent, t0 + Duration::from_secs(1));
    }

    #[test]
    fn agent_core_survives_mutated_captures(seed in any::<u64>(), flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8), cut in any::<usize>()) {
        let all = captured();
        let mut agent: Agent<u8> = Agent::new(AgentConfig::default());
        let t0 = Instant::now();
        // Open a real session first, so mutations reach the session paths too.
        agent.handle_datagram(t0, 1, &all[0], &mut NullSink);
        let mut d = all[(seed as usize) % all.len()].clone();
        for (pos, v) in &flips {
            let n = d.len();
            d[pos % n] ^= v;
        }
        if cut % 3 == 0 {
            d.truncate(cut % (d.len() + 1));
        }
        let _ = Message::decode(&d);
        agent.handle_datagram(t0, 1, &d, &mut NullSink);
        agent.handle_timeout(t0 + Duration::from_secs(1), &mut NullSink);
        assert_ping_answered(&mut agent, t0 + Duration::from_secs(2));
    }
}

#[test]
fn rejected_inputs_are_counted_by_reason() {
    let mut agent: Agent<u8> = Agent::new(AgentConfig::default());
    let now = Instant::now();
    agent.handle_datagram(now, 1, &[0x81], &mut NullSink);
    agent.handle_datagram(
        now,
        1,
        &[0x81, 0x80, 0, 0, 0x07, 0x01, 0x04, 0x00, 1, 2, 3, 4],
        &mut NullSink,
    );
    assert_eq!(agent.stats().dropped("truncated"), 1);
    assert_eq!(agent.stats().dropped("no_client"), 1);
}

#[test]
fn early_messages_are_bounded_per_client() {
    use xrce_common::wire::{ClientKey, MessageBuilder, MessageHeader, Payload};
    let mut agent: Agent<u8> = Agent::new(AgentConfig {
        max_early_bytes: 4096,
        ..AgentConfig::default()
    });
    let now = Instant::now();
    // A session (0x81, no key in headers), then out-of-order reliable messages of 1 KiB.
    let cc = captured()[0].clone();
    agent.handle_datagram(now, 1, &cc, &mut NullSink);
    for seq in 1..10u16 {
        let mut b = MessageBuilder::new(MessageHeader::new(0x81, 0x80, seq, ClientKey::INVALID));
        b.push(
            &Payload::Unknown {
                id: 0x7F,
                flags: 1,
                data: &[0u8; 1024],
            },
            true,
        )
        .expect("fits");
        agent.handle_datagram(now, 1, &b.finish(), &mut NullSink);
    }
    // Three fit in 4 KiB; the rest were refused (and will be sent again by the client).
    assert_eq!(agent.stats().dropped("early_buffer_full"), 6);
}

#[test]
fn heartbeat_on_a_stream_never_heard_asks_for_everything() {
    use xrce_common::wire::{ClientKey, HeartbeatPayload, MessageBuilder, MessageHeader};
    // Every message the client sent on stream 0x80 was lost; its HEARTBEAT must still get an
    // ACKNACK that asks for them, or the client waits for ever.
    let mut agent: Agent<u8> = Agent::new(AgentConfig::default());
    let now = Instant::now();
    agent.handle_datagram(now, 1, &captured()[0], &mut NullSink);
    while agent.poll_transmit().is_some() {}
    let mut b = MessageBuilder::new(MessageHeader::new(0x81, 0, 0, ClientKey::INVALID));
    let hb = HeartbeatPayload {
        first_unacked_seq_num: 0,
        last_unacked_seq_num: 3,
        stream_id: 0x80,
    };
    b.push(&Payload::Heartbeat(hb), true).expect("fits");
    agent.handle_datagram(now, 1, &b.finish(), &mut NullSink);
    let t = agent.poll_transmit().expect("an ACKNACK");
    let m = Message::decode(&t.data).expect("decode");
    match &m.submessages[0].payload {
        Payload::Acknack(a) => assert_eq!(
            (a.first_unacked_seq_num, a.nack_bitmap, a.stream_id),
            (0, 0b1111, 0x80)
        ),
        p => panic!("expected ACKNACK, got {p:?}"),
    }
}
