//! Admission in the agent core: no session takeover from another endpoint (unless roaming is
//! allowed), the allow-list of client keys, per-client input rate quotas.

use std::time::{Duration, Instant};

use xrce_common::session::admission::{Admission, RateQuota};
use xrce_common::session::agent::{Agent, AgentConfig, Operation, OperationSink, Transmit};
use xrce_common::wire::*;

/// Counts what reaches the DDS side.
#[derive(Default)]
struct Recorder {
    created: Vec<ClientKey>,
    writes: Vec<Vec<u8>>,
}

impl OperationSink for Recorder {
    fn has_room(&self) -> bool {
        true
    }
    fn operation(&mut self, op: Operation<'_>) {
        match op {
            Operation::ClientCreated { client } => self.created.push(client),
            Operation::Write { data, .. } => self.writes.push(data.data.to_vec()),
            _ => {}
        }
    }
}

const HOME: u32 = 1;
const ELSEWHERE: u32 = 2;
const KEY: ClientKey = ClientKey([0xAA, 0xAA, 0xBB, 0xBB]);

fn create_client(key: ClientKey) -> Vec<u8> {
    let mut b = MessageBuilder::new(MessageHeader::new(0x00, 0, 0, key));
    b.push(
        &Payload::CreateClient(CreateClientPayload {
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id: VENDOR_EPROSIMA,
            client_key: key,
            session_id: 0x01,
            properties: None,
            mtu: Some(512),
        }),
        true,
    )
    .expect("encode");
    b.finish()
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
    // A CREATE_CLIENT moves the session: the client restarted elsewhere.
    agent.handle_datagram(t0, ELSEWHERE, &create_client(KEY), &mut rec);
    assert_eq!(statuses(&drain(&mut agent)), [(ELSEWHERE, status::OK)]);
    agent.handle_datagram(t0, ELSEWHERE, &write(0, b"moved"), &mut rec);
    assert_eq!(rec.writes.len(), 2);
    // Now home is the foreign one.
    agent.handle_datagram(t0, HOME, &write(1, b"stale"), &mut rec);
    assert_eq!(rec.writes.len(), 2);
    assert_eq!(agent.stats().dropped("foreign_endpoint"), 2);
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
        allowed_keys: Some([KEY].into_iter().collect()),
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
