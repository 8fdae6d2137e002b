//! The agent core's limits against hostile clients: the memory budget shared between
//! hosts and sessions, reassemblies that stall, session caps per host and per front-end.

use std::time::{Duration, Instant};

use xrce_common::session::agent::{Agent, AgentConfig, NullSink, Transmit};
use xrce_common::session::budget::Limits;
use xrce_common::wire::*;

/// An endpoint: (host, port). Sessions and memory are shared by host.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct Ep(u32, u16);

impl xrce_common::session::budget::Origin for Ep {
    fn origin(&self) -> xrce_common::session::budget::OriginId {
        xrce_common::session::budget::OriginId(u128::from(self.0))
    }
    fn ip(&self) -> Option<std::net::IpAddr> {
        None
    }
}

fn key(n: u32) -> ClientKey {
    ClientKey((0x1000_0000 + n).to_be_bytes())
}

fn create_client(k: ClientKey) -> Vec<u8> {
    CreateClientPayload::eprosima(k, 0x01)
        .message()
        .expect("encode")
}

/// A reliable message (stream 0x80) holding one FRAGMENT of `len` bytes, not the last.
fn fragment(k: ClientKey, seq: u16, len: usize) -> Vec<u8> {
    let mut v = Vec::new();
    MessageHeader::new(0x01, 0x80, seq, k).encode(&mut v);
    v.extend_from_slice(&[submessage_id::FRAGMENT, flags::LITTLE_ENDIAN]);
    v.extend_from_slice(&(len as u16).to_le_bytes());
    v.resize(v.len() + len, 0x5A);
    v
}

fn drain(agent: &mut Agent<Ep>) -> Vec<Transmit<Ep>> {
    std::iter::from_fn(|| agent.poll_transmit()).collect()
}

/// The result of the STATUS_AGENT sent to `to`, if any.
fn create_status(out: &[Transmit<Ep>], to: Ep) -> Option<u8> {
    out.iter().filter(|t| t.destination == to).find_map(|t| {
        Message::decode(&t.data)
            .ok()?
            .submessages
            .into_iter()
            .find_map(|s| match s.payload {
                Payload::StatusAgent(a) => a.result.map(|r| r.status),
                _ => None,
            })
    })
}

/// The first unacknowledged sequence number of the ACKNACK sent to `to` for stream 0x80.
fn acked_up_to(out: &[Transmit<Ep>], to: Ep) -> Option<u16> {
    out.iter()
        .rev()
        .filter(|t| t.destination == to)
        .filter_map(|t| Message::decode(&t.data).ok())
        .flat_map(|m| m.submessages)
        .find_map(|s| match s.payload {
            Payload::Acknack(a) if a.stream_id == 0x80 => Some(a.first_unacked_seq_num),
            _ => None,
        })
}

fn agent(limits: Limits, max_clients: usize) -> Agent<Ep> {
    Agent::new(AgentConfig {
        limits,
        max_clients,
        ..AgentConfig::default()
    })
}

fn connect(a: &mut Agent<Ep>, now: Instant, ep: Ep, k: ClientKey) -> Option<u8> {
    a.handle_datagram(now, ep, &create_client(k), &mut NullSink);
    create_status(&drain(a), ep)
}

#[test]
fn a_fragment_flood_from_many_sessions_stays_within_the_budget() {
    let budget = 4 << 20;
    let mut a = agent(
        Limits {
            memory_budget: budget,
            ..Limits::default()
        },
        10_000,
    );
    let t0 = Instant::now();
    let attacker = |i: u32| Ep(1, i as u16);
    // 160 sessions from one host, each sending 64 KiB of fragments that never end.
    for i in 0..160 {
        assert_eq!(connect(&mut a, t0, attacker(i), key(i)), Some(status::OK));
        for seq in 0..16u16 {
            a.handle_datagram(t0, attacker(i), &fragment(key(i), seq, 4096), &mut NullSink);
        }
        drain(&mut a);
    }
    let (held, limit) = a.memory_held();
    assert_eq!(limit, budget);
    assert!(held <= budget, "{held} bytes held over a {budget} budget");
    assert!(
        a.stats().dropped("memory_budget") > 0,
        "the budget never bit"
    );
    // A client from another host gets its session and its fragments are taken.
    let victim = Ep(2, 1);
    let vk = key(10_000);
    assert_eq!(connect(&mut a, t0, victim, vk), Some(status::OK));
    for seq in 0..8u16 {
        a.handle_datagram(t0, victim, &fragment(vk, seq, 4096), &mut NullSink);
        let out = drain(&mut a);
        assert_eq!(
            acked_up_to(&out, victim),
            Some(seq + 1),
            "fragment {seq} refused"
        );
    }
    let (held, _) = a.memory_held();
    assert!(held <= budget, "{held} bytes held over a {budget} budget");
    assert!(a.stats().dropped("reassembly_evicted") > 0);
}

#[test]
fn a_reassembly_that_stalls_is_dropped_and_its_memory_returned() {
    let mut a = agent(Limits::default(), 100);
    let t0 = Instant::now();
    let ep = Ep(1, 1);
    let k = key(1);
    assert_eq!(connect(&mut a, t0, ep, k), Some(status::OK));
    a.handle_datagram(t0, ep, &fragment(k, 0, 10_000), &mut NullSink);
    assert!(a.memory_held().0 >= 10_000);
    let due = a.poll_timeout().expect("a timer for the reassembly");
    assert!(due <= t0 + Limits::default().reassembly_timeout);
    a.handle_timeout(t0 + Duration::from_secs(6), &mut NullSink);
    assert_eq!(a.stats().dropped("reassembly_stale"), 1);
    assert!(a.memory_held().0 < 1000, "held {}", a.memory_held().0);
    assert!(a.has_client(k), "the session itself stays");
}

#[test]
fn sessions_per_host_are_capped_and_silent_empty_ones_make_room() {
    let mut a = agent(
        Limits {
            max_sessions_per_origin: 4,
            ..Limits::default()
        },
        100,
    );
    let t0 = Instant::now();
    for i in 0..4 {
        assert_eq!(
            connect(&mut a, t0, Ep(1, i as u16), key(i)),
            Some(status::OK)
        );
    }
    // A fifth at once: the four are not silent yet, so it is refused.
    assert_eq!(
        connect(&mut a, t0, Ep(1, 4), key(4)),
        Some(status::ERR_RESOURCES)
    );
    assert_eq!(a.stats().dropped("session_cap_per_address"), 1);
    // Another host is not concerned.
    assert_eq!(connect(&mut a, t0, Ep(2, 1), key(100)), Some(status::OK));
    // Two seconds later the most silent of the four makes room.
    let t1 = t0 + Duration::from_secs(2);
    assert_eq!(connect(&mut a, t1, Ep(1, 4), key(4)), Some(status::OK));
    assert_eq!(a.stats().dropped("session_evicted"), 1);
    assert_eq!(a.client_count(), 5);
}

#[test]
fn the_front_end_cap_evicts_from_the_busiest_host_not_the_newcomer() {
    let mut a = agent(Limits::default(), 10);
    let t0 = Instant::now();
    for i in 0..10 {
        assert_eq!(
            connect(&mut a, t0, Ep(1, i as u16), key(i)),
            Some(status::OK)
        );
    }
    // Full, and all fresh: refused.
    assert_eq!(
        connect(&mut a, t0, Ep(2, 1), key(50)),
        Some(status::ERR_RESOURCES)
    );
    assert_eq!(a.stats().dropped("session_cap"), 1);
    // Once they are silent, a newcomer from another host takes the place of one of them.
    let t1 = t0 + Duration::from_secs(2);
    assert_eq!(connect(&mut a, t1, Ep(2, 1), key(50)), Some(status::OK));
    assert!(a.has_client(key(50)));
    assert_eq!(a.client_count(), 10);
}

#[test]
fn a_closed_connection_s_session_expires_after_the_grace() {
    let mut a = agent(
        Limits {
            detached_grace: Some(Duration::from_secs(3)),
            ..Limits::default()
        },
        100,
    );
    let t0 = Instant::now();
    let k = key(1);
    assert_eq!(connect(&mut a, t0, Ep(1, 1), k), Some(status::OK));
    assert!(a.endpoint_closed(t0, Ep(1, 1)));
    a.handle_timeout(t0 + Duration::from_secs(2), &mut NullSink);
    assert!(a.has_client(k), "gone before the grace");
    a.handle_timeout(t0 + Duration::from_secs(4), &mut NullSink);
    assert!(!a.has_client(k));
    assert_eq!(a.stats().dropped("detached_expired"), 1);
    // One that comes back in time keeps its session and its dead time (none).
    let k2 = key(2);
    let t2 = t0 + Duration::from_secs(10);
    assert_eq!(connect(&mut a, t2, Ep(1, 2), k2), Some(status::OK));
    assert!(a.endpoint_closed(t2, Ep(1, 2)));
    // Reconnecting from a new connection: the old endpoint is closed, so no probe wait.
    assert_eq!(
        connect(&mut a, t2 + Duration::from_secs(1), Ep(1, 3), k2),
        Some(status::OK)
    );
    a.handle_timeout(t2 + Duration::from_secs(60), &mut NullSink);
    assert!(a.has_client(k2));
}

#[test]
fn the_grace_of_a_closed_connection_counts_from_the_close_not_from_the_last_message() {
    let mut a = agent(
        Limits {
            detached_grace: Some(Duration::from_secs(60)),
            ..Limits::default()
        },
        100,
    );
    let t0 = Instant::now();
    let k = key(1);
    assert_eq!(connect(&mut a, t0, Ep(1, 1), k), Some(status::OK));
    // Silent for five minutes (a subscriber with nothing to read), then its connection closes.
    let closed = t0 + Duration::from_secs(300);
    assert!(a.endpoint_closed(closed, Ep(1, 1)));
    a.handle_timeout(closed + Duration::from_secs(1), &mut NullSink);
    assert!(a.has_client(k), "deleted at once after a long silence");
    a.handle_timeout(closed + Duration::from_secs(59), &mut NullSink);
    assert!(a.has_client(k), "deleted before the grace ran out");
    a.handle_timeout(closed + Duration::from_secs(61), &mut NullSink);
    assert!(!a.has_client(k));
}

#[test]
fn fragments_after_a_stalled_reassembly_are_not_taken_for_a_message() {
    let mut a = agent(Limits::default(), 100);
    let t0 = Instant::now();
    let ep = Ep(1, 1);
    let k = key(1);
    assert_eq!(connect(&mut a, t0, ep, k), Some(status::OK));
    a.handle_datagram(t0, ep, &fragment(k, 0, 100), &mut NullSink);
    a.handle_timeout(t0 + Duration::from_secs(6), &mut NullSink);
    assert_eq!(a.stats().dropped("reassembly_stale"), 1);
    // The rest of that message comes late, up to its last fragment: dropped with it.
    let t1 = t0 + Duration::from_secs(7);
    a.handle_datagram(t1, ep, &fragment(k, 1, 100), &mut NullSink);
    let mut last = fragment(k, 2, 8);
    last[9] |= flags::LAST_FRAGMENT; // the submessage flags, after the 8-octet header
    a.handle_datagram(t1, ep, &last, &mut NullSink);
    assert_eq!(a.stats().dropped("reassembly_discarded"), 2);
}

/// A reliable message (stream 0x80, sequence `seq`) asking for participant `n`.
fn create_participant(k: ClientKey, seq: u16, n: u16) -> (Vec<u8>, BaseObjectRequest) {
    let base = BaseObjectRequest {
        request_id: RequestId(n.to_be_bytes()),
        object_id: ObjectId::new(n, object_kind::PARTICIPANT),
    };
    let mut b = MessageBuilder::new(MessageHeader::new(0x01, 0x80, seq, k));
    b.push(
        &Payload::Create(CreatePayload {
            base,
            variant: ObjectVariant {
                kind: object_kind::PARTICIPANT,
                representation: Representation::Reference("default_xrce_participant".into()),
                extra: VariantExtra::DomainId(0),
            },
            reuse: false,
            replace: false,
        }),
        true,
    )
    .expect("encode");
    (b.finish(), base)
}

#[test]
fn thousands_of_hosts_with_one_silent_session_each_cannot_lock_a_new_host_out() {
    let mut a = agent(Limits::default(), 64);
    let t0 = Instant::now();
    for host in 0..64 {
        assert_eq!(
            connect(&mut a, t0, Ep(host, 7000), key(host)),
            Some(status::OK)
        );
    }
    // Every host holds one session, as many as the newcomer's would: only the rule of the
    // most silent session anywhere makes room.
    let later = t0 + Duration::from_secs(2);
    assert_eq!(
        connect(&mut a, later, Ep(1000, 7000), key(1000)),
        Some(status::OK)
    );
    assert_eq!(a.stats().dropped("session_evicted"), 1);
    assert!(
        !a.has_client(key(0)),
        "the most silent (then lowest key) went"
    );
    assert_eq!(a.client_count(), 64);
}

#[test]
fn a_refused_create_does_not_pin_a_session_but_a_created_object_does() {
    let mut a = agent(Limits::default(), 2);
    let t0 = Instant::now();
    let (refused, holder) = (key(1), key(2));
    assert_eq!(connect(&mut a, t0, Ep(1, 1), refused), Some(status::OK));
    assert_eq!(connect(&mut a, t0, Ep(2, 1), holder), Some(status::OK));
    // One asks for an object and is refused; the other's is created.
    let (m, base) = create_participant(refused, 0, 1);
    a.handle_datagram(t0, Ep(1, 1), &m, &mut NullSink);
    a.send_status(t0, refused, base, ResultStatus::new(status::ERR_RESOURCES))
        .expect("session");
    let (m, base) = create_participant(holder, 0, 1);
    a.handle_datagram(t0, Ep(2, 1), &m, &mut NullSink);
    // Still waiting for its STATUS: not evictable either.
    assert_eq!(
        connect(&mut a, t0 + Duration::from_secs(2), Ep(3, 1), key(3)),
        Some(status::OK),
        "the refused one's session makes room"
    );
    assert!(!a.has_client(refused));
    assert!(a.has_client(holder));
    a.send_status(t0, holder, base, ResultStatus::new(status::OK))
        .expect("session");
    // Now the newcomer's session (no objects) is the one that goes, never the holder's.
    assert_eq!(
        connect(&mut a, t0 + Duration::from_secs(4), Ep(4, 1), key(4)),
        Some(status::OK)
    );
    assert!(a.has_client(holder));
    assert!(!a.has_client(key(3)));
}

#[test]
fn a_datagram_packed_with_create_clients_gets_one_reply() {
    let mut a = agent(Limits::default(), 8192);
    let t0 = Instant::now();
    let mut packed = create_client(key(0));
    for i in 1..2000 {
        let one = create_client(key(i));
        packed.extend_from_slice(&one[8..]);
    }
    a.handle_datagram(t0, Ep(1, 1), &packed, &mut NullSink);
    let out = drain(&mut a);
    assert_eq!(out.len(), 1, "one datagram in, one reply out");
    assert!(out[0].data.len() <= 64, "{} bytes", out[0].data.len());
    assert_eq!(a.client_count(), 1);
    assert_eq!(a.stats().dropped("overpacked_datagram"), 1);
}

#[test]
fn an_address_starts_new_sessions_at_a_bounded_rate() {
    let mut a = agent(
        Limits {
            new_sessions_per_second: 100,
            ..Limits::default()
        },
        8192,
    );
    let t0 = Instant::now();
    // 150 clients of one host at once: a second's worth is served, the rest unanswered.
    let answered = (0..150)
        .filter(|i| connect(&mut a, t0, Ep(1, *i as u16), key(*i)) == Some(status::OK))
        .count();
    assert_eq!(answered, 100);
    assert_eq!(a.stats().dropped("session_creation_rate"), 50);
    // Another host is not concerned; an existing session's retry is not a new session.
    assert_eq!(connect(&mut a, t0, Ep(2, 1), key(500)), Some(status::OK));
    assert_eq!(connect(&mut a, t0, Ep(1, 0), key(0)), Some(status::OK));
    // Half a second later, half a second's worth more.
    let later = t0 + Duration::from_millis(500);
    let answered = (100..150)
        .filter(|i| connect(&mut a, later, Ep(1, *i as u16), key(*i)) == Some(status::OK))
        .count();
    assert_eq!(answered, 50);
}

#[test]
fn what_the_session_store_takes_for_a_client_counts_in_its_share() {
    let budget = 1 << 20;
    let mut a = agent(
        Limits {
            memory_budget: budget,
            ..Limits::default()
        },
        100,
    );
    let t0 = Instant::now();
    let (ea, eb) = (Ep(1, 1), Ep(2, 1));
    let (ka, kb) = (key(1), key(2));
    assert_eq!(connect(&mut a, t0, ea, ka), Some(status::OK));
    assert_eq!(connect(&mut a, t0, eb, kb), Some(status::OK));
    // A's stored records and objects take 700 KiB: past half the budget, and over its
    // half share.
    a.set_stored_bytes(ka, 700 << 10);
    assert_eq!(a.memory_held().0, 700 << 10);
    a.handle_datagram(t0, ea, &fragment(ka, 0, 4096), &mut NullSink);
    assert_eq!(
        acked_up_to(&drain(&mut a), ea),
        Some(0),
        "A over its share: not taken"
    );
    assert_eq!(a.stats().dropped("memory_budget"), 1);
    a.handle_datagram(t0, eb, &fragment(kb, 0, 4096), &mut NullSink);
    assert_eq!(
        acked_up_to(&drain(&mut a), eb),
        Some(1),
        "B within its share"
    );
    // Its store shrank: A is served again.
    a.set_stored_bytes(ka, 0);
    a.handle_datagram(t0, ea, &fragment(ka, 0, 4096), &mut NullSink);
    assert_eq!(acked_up_to(&drain(&mut a), ea), Some(1));
}
