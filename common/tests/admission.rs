//! Admission in the agent core: no session takeover from another endpoint (unless roaming is
//! allowed), the allow-list of client keys, per-client input rate quotas, and how a client
//! refused for lack of room is acknowledged.

use std::time::{Duration, Instant};

use xrce_common::session::admission::{Admission, RateQuota};
use xrce_common::session::agent::{Agent, AgentConfig, Operation, OperationSink, Transmit};
use xrce_common::wire::*;

/// Counts what reaches the DDS side.
#[derive(Default)]
struct Recorder {
    created: Vec<ClientKey>,
    writes: Vec<Vec<u8>>,
    /// The DDS side has no room (flow control).
    full: bool,
}

impl OperationSink for Recorder {
    fn has_room(&self) -> bool {
        !self.full
    }
    fn operation(&mut self, _now: Instant, op: Operation<'_>) {
        match op {
            Operation::ClientCreated { client, .. } => self.created.push(client),
            Operation::Write { data, .. } => self.writes.push(data.data.to_vec()),
            _ => {}
        }
    }
}

const HOME: u32 = 1;
const ELSEWHERE: u32 = 2;
const KEY: ClientKey = ClientKey([0xAA, 0xAA, 0xBB, 0xBB]);

fn create_client(key: ClientKey) -> Vec<u8> {
    CreateClientPayload::eprosima(key, 0x01)
        .message()
        .expect("encode")
}

/// A WRITE_DATA of `sample` on the reliable stream 1 (with the key in the header).
fn write(seq: u16, sample: &[u8]) -> Vec<u8> {
    let mut b = MessageBuilder::new(MessageHeader::new(0x01, 0x80, seq, KEY));
    b.push(
        &Payload::WriteData(DataPayload {
            base: BaseObjectRequest {
                request_id: RequestId::from_u16(100 + seq),
                object_id: ObjectId::new(1, object_kind::DATAWRITER),
            },
            format: data_format::DATA,
            data: sample,
        }),
        true,
    )
    .expect("encode");
    b.finish()
}

fn drain(agent: &mut Agent<u32>) -> Vec<Transmit<u32>> {
    std::iter::from_fn(|| agent.poll_transmit()).collect()
}

fn statuses(out: &[Transmit<u32>]) -> Vec<(u32, u8)> {
    out.iter()
        .flat_map(|t| {
            Message::decode(&t.data)
                .expect("agent output decodes")
                .submessages
                .into_iter()
                .filter_map(move |s| match s.payload {
                    Payload::StatusAgent(a) => a.result.map(|r| (t.destination, r.status)),
                    _ => None,
                })
        })
        .collect()
}

fn agent_with(admission: Admission) -> (Agent<u32>, Recorder, Instant) {
    let t0 = Instant::now();
    let mut agent = Agent::new(AgentConfig {
        admission,
        ..AgentConfig::default()
    });
    let mut rec = Recorder::default();
    agent.handle_datagram(t0, HOME, &create_client(KEY), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(HOME, status::OK)]);
    (agent, rec, t0)
}

#[test]
fn a_known_key_from_another_endpoint_does_not_take_the_session_over() {
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    agent.handle_datagram(t0, ELSEWHERE, &write(0, b"intruder"), &mut rec);
    // Nothing reached DDS, nothing was acknowledged to the intruder.
    assert!(rec.writes.is_empty());
    assert!(drain(&mut agent).is_empty(), "answered a foreign endpoint");
    assert_eq!(agent.stats().dropped("foreign_endpoint"), 1);
    // The client at home goes on from where it was: its sequence number 0 is still expected.
    agent.handle_datagram(t0, HOME, &write(0, b"genuine"), &mut rec);
    assert_eq!(rec.writes, [b"genuine".to_vec()]);
    assert!(drain(&mut agent).iter().all(|t| t.destination == HOME));
    // A CREATE_CLIENT from elsewhere is not answered at once: the session's endpoint is
    // probed (a GET_INFO to home) to see whether its client is still there.
    agent.handle_datagram(t0, ELSEWHERE, &create_client(KEY), &mut rec);
    let out = drain(&mut agent);
    assert!(statuses(&out).is_empty(), "answered before probing");
    assert!(!out.is_empty() && out.iter().all(|t| t.destination == HOME));
    assert_eq!(agent.stats().dropped("takeover_probing"), 1);
    // Home stays silent: the client restarted elsewhere, and its retry a second later
    // moves the session.
    let t1 = t0 + Duration::from_secs(1);
    agent.handle_datagram(t1, ELSEWHERE, &create_client(KEY), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(ELSEWHERE, status::OK)]);
    agent.handle_datagram(t1, ELSEWHERE, &write(0, b"moved"), &mut rec);
    assert_eq!(rec.writes.len(), 2);
    // Now home is the foreign one.
    agent.handle_datagram(t1, HOME, &write(1, b"stale"), &mut rec);
    assert_eq!(rec.writes.len(), 2);
    assert_eq!(agent.stats().dropped("foreign_endpoint"), 2);
}

#[test]
fn a_session_whose_client_answers_the_probe_is_not_taken_over() {
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = |n| t0 + Duration::from_millis(n);
    agent.handle_datagram(ms(0), ELSEWHERE, &create_client(KEY), &mut rec);
    assert!(statuses(&drain(&mut agent)).is_empty());
    // The genuine client is alive: it is heard after the probe.
    agent.handle_datagram(ms(50), HOME, &write(0, b"alive"), &mut rec);
    drain(&mut agent);
    // The intruder's retry a second later is not answered yet: home is probed again (an
    // answer in the first moments may come from a client just given that port).
    agent.handle_datagram(ms(1000), ELSEWHERE, &create_client(KEY), &mut rec);
    let out = drain(&mut agent);
    assert!(statuses(&out).is_empty());
    assert!(
        out.iter().any(|t| t.destination == HOME),
        "home not probed again"
    );
    agent.handle_datagram(ms(1100), HOME, &write(1, b"still mine"), &mut rec);
    assert!(drain(&mut agent).iter().all(|t| t.destination == HOME));
    // Home kept answering for two seconds: the next retry is refused, the session stays.
    agent.handle_datagram(ms(2000), ELSEWHERE, &create_client(KEY), &mut rec);
    assert_eq!(
        statuses(&drain(&mut agent)),
        [(ELSEWHERE, status::ERR_DENIED)]
    );
    assert_eq!(agent.stats().dropped("takeover_refused"), 1);
    assert_eq!(rec.writes, [b"alive".to_vec(), b"still mine".to_vec()]);
    // Nothing the intruder sends reaches DDS.
    agent.handle_datagram(ms(2100), ELSEWHERE, &write(2, b"intruder"), &mut rec);
    assert_eq!(rec.writes.len(), 2);
}

#[test]
fn a_takeover_waits_out_the_probe_even_when_retried_at_once() {
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = |n| t0 + Duration::from_millis(n);
    agent.handle_datagram(ms(0), ELSEWHERE, &create_client(KEY), &mut rec);
    // A retry before the probe had its time is not answered either.
    agent.handle_datagram(ms(100), ELSEWHERE, &create_client(KEY), &mut rec);
    assert!(statuses(&drain(&mut agent)).is_empty());
    agent.handle_datagram(ms(400), ELSEWHERE, &create_client(KEY), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(ELSEWHERE, status::OK)]);
}

#[test]
fn with_roaming_allowed_a_session_follows_its_client() {
    let (mut agent, mut rec, t0) = agent_with(Admission {
        allow_roaming: true,
        ..Admission::default()
    });
    agent.handle_datagram(t0, HOME, &write(0, b"one"), &mut rec);
    drain(&mut agent);
    // A NAT rebinding: the next message comes from a new port.
    agent.handle_datagram(t0, ELSEWHERE, &write(1, b"two"), &mut rec);
    assert_eq!(rec.writes, [b"one".to_vec(), b"two".to_vec()]);
    let out = drain(&mut agent);
    assert!(!out.is_empty() && out.iter().all(|t| t.destination == ELSEWHERE));
    assert_eq!(agent.stats().dropped("foreign_endpoint"), 0);
}

#[test]
fn keys_outside_the_allow_list_are_denied_and_counted() {
    let other = ClientKey([0x01, 0x02, 0x03, 0x04]);
    let (mut agent, mut rec, t0) = agent_with(Admission {
        allowed_keys: Some([(KEY, None)].into_iter().collect()),
        ..Admission::default()
    });
    for _ in 0..3 {
        agent.handle_datagram(t0, ELSEWHERE, &create_client(other), &mut rec);
        assert_eq!(
            statuses(&drain(&mut agent)),
            [(ELSEWHERE, status::ERR_DENIED)]
        );
    }
    assert_eq!(rec.created, [KEY], "only the listed key has a session");
    assert!(!agent.has_client(other));
    assert_eq!(agent.stats().dropped("key_not_allowed"), 3);
}

#[test]
fn a_client_over_its_rate_quota_is_slowed_and_loses_no_reliable_message() {
    let (mut agent, mut rec, t0) = agent_with(Admission {
        rate: RateQuota {
            messages_per_second: Some(20),
            bytes_per_second: None,
        },
        ..Admission::default()
    });
    // The client sends 100 reliable writes at once, then sends every one not yet
    // acknowledged again every 100 ms, as a client does on its HEARTBEAT/ACKNACK cycle.
    let mut acked = 0u16;
    let mut t = t0;
    let end = t0 + Duration::from_secs(10);
    while acked < 100 && t < end {
        for seq in acked..100 {
            agent.handle_datagram(t, HOME, &write(seq, &seq.to_be_bytes()), &mut rec);
        }
        for out in drain(&mut agent) {
            let Ok(m) = Message::decode(&out.data) else {
                continue;
            };
            for s in m.submessages {
                if let Payload::Acknack(a) = s.payload {
                    acked = acked.max(a.first_unacked_seq_num);
                }
            }
        }
        t += Duration::from_millis(100);
    }
    // Every write reached DDS once, in order, at about the quota's pace: the first second's
    // burst of 20, then 20 a second.
    let expected: Vec<Vec<u8>> = (0..100u16).map(|s| s.to_be_bytes().to_vec()).collect();
    assert_eq!(rec.writes, expected);
    let took = t.duration_since(t0);
    assert!(
        (Duration::from_secs(3)..Duration::from_secs(5)).contains(&took),
        "{took:?}"
    );
    assert!(agent.stats().dropped("rate_quota") > 100);
}

/// The (first unacknowledged, nack bitmap) of every ACKNACK in `out`.
fn acknacks(out: &[Transmit<u32>]) -> Vec<(u16, u16)> {
    out.iter()
        .flat_map(|t| Message::decode(&t.data).expect("decodes").submessages)
        .filter_map(|s| match s.payload {
            Payload::Acknack(a) => Some((a.first_unacked_seq_num, a.nack_bitmap)),
            _ => None,
        })
        .collect()
}

fn heartbeat(first: u16, last: u16) -> Vec<u8> {
    let mut b = MessageBuilder::new(MessageHeader::new(0x01, stream_id::NONE, 0, KEY));
    b.push(
        &Payload::Heartbeat(HeartbeatPayload {
            first_unacked_seq_num: first,
            last_unacked_seq_num: last,
            stream_id: 0x80,
        }),
        true,
    )
    .expect("encode");
    b.finish()
}

#[test]
fn a_message_refused_for_room_is_asked_for_again_only_when_the_client_heartbeats() {
    // The eProsima client resends its whole window on any ACKNACK that asks for a message:
    // an ACKNACK asking for each refused message would keep a full agent busy with resends.
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = Duration::from_millis;
    rec.full = true;
    agent.handle_datagram(t0, HOME, &write(0, b"zero"), &mut rec);
    assert_eq!(
        acknacks(&drain(&mut agent)),
        [(0, 0)],
        "acknowledged, nothing asked for"
    );
    // Its resend, refused again: the same ACKNACK is not repeated at once.
    agent.handle_datagram(t0 + ms(1), HOME, &write(0, b"zero"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), []);
    assert_eq!(agent.stats().dropped("backpressure"), 2);
    // The client's HEARTBEAT is always answered, and that ACKNACK asks for message 0.
    agent.handle_datagram(t0 + ms(2), HOME, &heartbeat(0, 0), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), [(0, 1)]);
    rec.full = false;
    agent.handle_datagram(t0 + ms(3), HOME, &write(0, b"zero"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), [(1, 0)]);
    assert_eq!(rec.writes, [b"zero".to_vec()]);
    // A duplicate within the repeat interval gets no second, unchanged ACKNACK; one later does
    // (our first may have been lost).
    agent.handle_datagram(t0 + ms(4), HOME, &write(0, b"zero"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), []);
    let later = t0 + ms(3) + xrce_common::session::agent::ACKNACK_REPEAT_INTERVAL;
    agent.handle_datagram(later, HOME, &write(0, b"zero"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), [(1, 0)]);
    // A lost message: the first later arrival asks for it, the next ones within the
    // interval do not ask again (each would make the client resend everything again).
    agent.handle_datagram(later, HOME, &write(2, b"two"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), [(1, 1)]);
    agent.handle_datagram(later + ms(1), HOME, &write(3, b"three"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), []);
    agent.handle_datagram(later + ms(2), HOME, &write(1, b"one"), &mut rec);
    assert_eq!(acknacks(&drain(&mut agent)), [(4, 0)]);
    assert_eq!(
        rec.writes,
        [
            b"zero".to_vec(),
            b"one".to_vec(),
            b"two".to_vec(),
            b"three".to_vec()
        ]
    );
}

#[test]
fn a_claim_answered_by_a_client_new_at_the_old_port_goes_through_once_it_creates_its_session() {
    // The session's client restarted from another port, and its old port went to another
    // client, which answers the agent's probe before it creates its own session there.
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = |n| t0 + Duration::from_millis(n);
    agent.handle_datagram(ms(0), ELSEWHERE, &create_client(KEY), &mut rec);
    drain(&mut agent);
    agent.handle_datagram(ms(50), HOME, &write(0, b"from the newcomer"), &mut rec);
    drain(&mut agent);
    let newcomer = ClientKey([0x0C, 0x0C, 0x0C, 0x0C]);
    agent.handle_datagram(ms(300), HOME, &create_client(newcomer), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(HOME, status::OK)]);
    // The old session went with its address: the claim goes through at its next retry.
    agent.handle_datagram(ms(1000), ELSEWHERE, &create_client(KEY), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(ELSEWHERE, status::OK)]);
    assert_eq!(agent.stats().dropped("takeover_refused"), 0);
}

/// A board that reset and came back from a new port asks once and waits (eProsima's client:
/// a second for STATUS_AGENT): once the probe of the session's old endpoint went unanswered
/// for the probe wait, the core answers that CREATE_CLIENT itself, without waiting for the
/// client's next attempt.
#[test]
fn a_claim_whose_probe_goes_unanswered_is_granted_without_a_retry() {
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = |n| t0 + Duration::from_millis(n);
    agent.handle_datagram(ms(0), ELSEWHERE, &create_client(KEY), &mut rec);
    assert!(
        statuses(&drain(&mut agent)).is_empty(),
        "answered before probing"
    );
    let due = agent.poll_timeout().expect("the claim's timer");
    assert!(due <= ms(300), "due {:?} after the claim", due - t0);
    agent.handle_timeout(ms(200), &mut rec);
    assert!(
        statuses(&drain(&mut agent)).is_empty(),
        "answered too early"
    );
    agent.handle_timeout(ms(300), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(ELSEWHERE, status::OK)]);
    // The session moved: the client's writes from its new port are taken.
    agent.handle_datagram(ms(310), ELSEWHERE, &write(0, b"after the reset"), &mut rec);
    assert_eq!(rec.writes, [b"after the reset".to_vec()]);
}

#[test]
fn a_claim_whose_probe_is_answered_is_not_granted_by_the_timer() {
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = |n| t0 + Duration::from_millis(n);
    agent.handle_datagram(ms(0), ELSEWHERE, &create_client(KEY), &mut rec);
    drain(&mut agent);
    agent.handle_datagram(ms(50), HOME, &write(0, b"alive"), &mut rec);
    drain(&mut agent);
    agent.handle_timeout(ms(300), &mut rec);
    let out = drain(&mut agent);
    assert!(
        statuses(&out).is_empty(),
        "the session moved from a live client"
    );
    // And the claim's timer does not fire again and again.
    assert!(agent.poll_timeout().is_none_or(|t| t > ms(300)));
}

/// The session's old endpoint is a closed port: its host answers the probe with ICMP port
/// unreachable, and the claim is granted then, not after the probe wait.
#[test]
fn a_claim_on_a_session_whose_port_is_closed_is_granted_at_once() {
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    let ms = |n| t0 + Duration::from_millis(n);
    agent.handle_datagram(ms(0), ELSEWHERE, &create_client(KEY), &mut rec);
    assert!(statuses(&drain(&mut agent)).is_empty());
    // Another endpoint's ICMP says nothing about this session.
    agent.endpoint_unreachable(ms(1), 99, &mut rec);
    assert!(statuses(&drain(&mut agent)).is_empty());
    agent.endpoint_unreachable(ms(2), HOME, &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(ELSEWHERE, status::OK)]);
    // Without a claim, the session stays where it is (its client may come back).
    let (mut agent, mut rec, t0) = agent_with(Admission::default());
    agent.endpoint_unreachable(t0, HOME, &mut rec);
    agent.handle_datagram(t0, HOME, &write(0, b"still here"), &mut rec);
    assert_eq!(rec.writes, [b"still here".to_vec()]);
}
