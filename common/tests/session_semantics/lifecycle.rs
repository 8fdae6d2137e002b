//! Clients that reset: a CREATE_CLIENT for a known key with the same session id (streams start
//! again, objects stay) or another (a new session, the old one's objects go), a DELETE for a
//! session the agent no longer has, and a session taken over that tells its client where its
//! streams stand.

use super::*;
use xrce_common::session::stream::InputPosition;

fn create_client_with(session_id: u8) -> Vec<u8> {
    CreateClientPayload::eprosima(KEY, session_id)
        .message()
        .expect("encode")
}

/// A WRITE_DATA on reliable stream 0x80 of session 0x01, numbered `seq`.
fn write(seq: u16) -> Vec<u8> {
    in_session(
        stream_id::BUILTIN_RELIABLE,
        seq,
        Payload::WriteData(DataPayload {
            base: BaseObjectRequest {
                request_id: RequestId::from_u16(0x100 + seq),
                object_id: ObjectId::new(1, object_kind::DATAWRITER),
            },
            format: data_format::DATA,
            data: &[1, 2, 3, 4],
        }),
    )
}

fn writes(rec: &Recorder) -> usize {
    rec.0.iter().filter(|o| matches!(o, Op::Write(..))).count()
}

#[test]
fn the_same_session_again_restarts_its_streams_and_keeps_its_objects() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    for seq in 0..5 {
        agent.handle_datagram(t0, ADDR, &write(seq), &mut rec);
    }
    assert_eq!(writes(&rec), 5);
    // The board resets: same key, same session, after the duplicate guard.
    let later = t0 + Duration::from_secs(2);
    agent.handle_datagram(later, ADDR, &create_client_with(0x01), &mut rec);
    drain(&mut agent);
    assert!(
        !rec.0.iter().any(|o| matches!(o, Op::Deleted(_))),
        "the objects stay: {:?}",
        rec.0
    );
    // Its streams start at 0 again: message 0 is new, not a duplicate.
    agent.handle_datagram(later, ADDR, &write(0), &mut rec);
    assert_eq!(
        writes(&rec),
        6,
        "the new incarnation's first write was dropped"
    );
}

#[test]
fn another_session_id_starts_a_new_session_without_the_old_objects() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    agent.handle_datagram(t0, ADDR, &write(0), &mut rec);
    agent.handle_datagram(t0, ADDR, &create_client_with(0x02), &mut rec);
    assert_eq!(
        rec.0[rec.0.len() - 2..],
        [Op::Deleted(KEY), Op::Created(KEY)],
        "the old session's objects go with it"
    );
}

/// eProsima's `uxr_delete_session`: DELETE of the client object on stream 0, request id
/// LOGOUT, retried each second until a STATUS comes.
fn delete_session(session_id: u8) -> Vec<u8> {
    let mut b = MessageBuilder::new(MessageHeader::new(session_id, 0, 0, KEY));
    b.push(
        &Payload::Delete(BaseObjectRequest {
            request_id: RequestId::from_u16(2),
            object_id: ObjectId::CLIENT,
        }),
        true,
    )
    .expect("encode");
    b.finish()
}

#[test]
fn a_delete_for_a_session_the_agent_no_longer_has_is_answered() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    agent.handle_datagram(t0, ADDR, &delete_session(0x01), &mut rec);
    agent.handle_timeout(t0, &mut rec);
    let first = drain(&mut agent);
    assert!(!agent.has_client(KEY), "the session ended");
    // The first STATUS is lost; the client sends its DELETE again.
    agent.handle_datagram(
        t0 + Duration::from_secs(1),
        ADDR,
        &delete_session(0x01),
        &mut rec,
    );
    let again = drain(&mut agent);
    assert_eq!(again.len(), 1, "one answer");
    // The reference agent's answer: STATUS_OK in the DELETE's own header.
    let m = Message::decode(&again[0].data).expect("decodes");
    assert_eq!(m.header.session_id, 0x01);
    assert_eq!(m.header.stream_id, 0);
    assert_eq!(m.header.client_key, Some(KEY));
    match &m.submessages[..] {
        [s] => match &s.payload {
            Payload::Status(r) => {
                assert_eq!(r.related.object_id, ObjectId::CLIENT);
                assert_eq!(r.related.request_id, RequestId::from_u16(2));
                assert_eq!(r.result.status, status::OK);
            }
            other => panic!("not a STATUS: {other:?}"),
        },
        other => panic!("one submessage expected: {other:?}"),
    }
    assert!(
        again[0].data.len() <= delete_session(0x01).len() + 4,
        "no amplification"
    );
    assert_eq!(agent.stats().dropped("delete_without_session"), 1);
    assert_eq!(
        agent.stats().lost_total,
        0,
        "an answered DELETE loses nothing"
    );
    assert!(!first.is_empty());
    // Without a key in the header and from an endpoint without a session: answered too.
    let mut b = MessageBuilder::new(MessageHeader::new(0x81, 0, 0, KEY));
    b.push(
        &Payload::Delete(BaseObjectRequest {
            request_id: RequestId::from_u16(2),
            object_id: ObjectId::CLIENT,
        }),
        true,
    )
    .expect("encode");
    agent.handle_datagram(t0, 99, &b.finish(), &mut rec);
    assert_eq!(drain(&mut agent).len(), 1);
    // Anything else for no session is dropped, unanswered.
    agent.handle_datagram(t0, 99, &write(7), &mut rec);
    assert!(drain(&mut agent).is_empty());
}

#[test]
fn a_ping_in_a_session_the_agent_does_not_have_says_so_at_once() {
    let mut agent: Agent<u32> = Agent::new(AgentConfig::default());
    let mut rec = Recorder::default();
    let t0 = Instant::now();
    let ping = in_session(
        0,
        0,
        Payload::GetInfo(GetInfoPayload {
            base: BaseObjectRequest {
                request_id: RequestId::from_u16(0x0A),
                object_id: ObjectId::AGENT,
            },
            info_mask: 0x02,
        }),
    );
    agent.handle_datagram(t0, ADDR, &ping, &mut rec);
    let out = drain(&mut agent);
    let infos: Vec<_> = payloads(&out)
        .into_iter()
        .filter_map(|p| match p {
            Payload::Info(i) => Some(i.reply.result.implementation_status),
            _ => None,
        })
        .collect();
    // PX4 and micro-ROS read "no session" (0) and create theirs again.
    assert_eq!(infos, [0]);
}

#[test]
fn a_session_taken_over_tells_its_client_where_its_streams_stand() {
    let (mut agent, mut rec, t0) = connected(
        AgentConfig {
            track_sessions: true,
            ..AgentConfig::default()
        },
        VENDOR_EPROSIMA,
        None,
    );
    for seq in 0..3 {
        agent.handle_datagram(t0, ADDR, &write(seq), &mut rec);
    }
    drain(&mut agent);
    let snapshot = agent
        .snapshot(KEY, |a| a.to_le_bytes().to_vec())
        .expect("a snapshot");
    // A successor front-end takes the session over: an ACKNACK goes out at once.
    let mut next: Agent<u32> = Agent::new(AgentConfig::default());
    assert!(next.restore(t0, &snapshot, ADDR));
    next.handle_timeout(t0, &mut rec);
    let acks: Vec<_> = payloads(&drain(&mut next))
        .into_iter()
        .filter_map(|p| match p {
            Payload::Acknack(a) => Some((a.stream_id, a.first_unacked_seq_num)),
            _ => None,
        })
        .collect();
    assert_eq!(acks, [(stream_id::BUILTIN_RELIABLE, 3)]);
    // And again when a new worker took the replay.
    next.announce_streams(t0 + Duration::from_millis(50));
    assert_eq!(payloads(&drain(&mut next)).len(), 1);
}

/// A board that resets right after it connected sends a CREATE_CLIENT the agent cannot tell
/// from a network duplicate (same endpoint, same session, within the duplicate guard): its
/// next message, numbered from the start again, tells.
#[test]
fn a_restart_right_after_the_session_began_is_told_from_a_duplicate_by_what_follows() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let ms = |n| t0 + Duration::from_millis(n);
    for seq in 0..3 {
        agent.handle_datagram(ms(10), ADDR, &write(seq), &mut rec);
    }
    // A duplicate: the client goes on numbering from 3, and a late copy of 0 stays a copy.
    agent.handle_datagram(ms(100), ADDR, &create_client_with(0x01), &mut rec);
    agent.handle_datagram(ms(110), ADDR, &write(3), &mut rec);
    agent.handle_datagram(ms(120), ADDR, &write(0), &mut rec);
    assert_eq!(
        writes(&rec),
        4,
        "a duplicate CREATE_CLIENT reset the streams"
    );
    // A restart: the next message is numbered 0 again, behind what was taken.
    agent.handle_datagram(ms(200), ADDR, &create_client_with(0x01), &mut rec);
    agent.handle_datagram(ms(210), ADDR, &write(0), &mut rec);
    agent.handle_datagram(ms(220), ADDR, &write(1), &mut rec);
    assert_eq!(
        writes(&rec),
        6,
        "the restarted client's messages were taken for copies"
    );
    assert!(!rec.0.iter().any(|o| matches!(o, Op::Deleted(_))));
}

/// What a successor's core hands over: the data of each write, and where it stood.
#[derive(Default)]
struct Positions(Vec<(Vec<u8>, Option<InputPosition>)>);

impl OperationSink for Positions {
    fn has_room(&self) -> bool {
        true
    }
    fn operation(&mut self, _now: Instant, op: Operation<'_>) {
        if let Operation::Write { data, position, .. } = op {
            self.0.push((data.data.to_vec(), position));
        }
    }
}

/// One reliable message numbered `seq` carrying a WRITE_DATA of each sample of `samples`.
fn message_of_writes(seq: u16, samples: &[u8]) -> Vec<u8> {
    let mut b = MessageBuilder::new(MessageHeader::new(
        0x01,
        stream_id::BUILTIN_RELIABLE,
        seq,
        KEY,
    ));
    for s in samples {
        let w = Payload::WriteData(DataPayload {
            base: BaseObjectRequest {
                request_id: RequestId::from_u16(0x200 + u16::from(*s)),
                object_id: ObjectId::new(1, object_kind::DATAWRITER),
            },
            format: data_format::DATA,
            data: std::slice::from_ref(s),
        });
        b.push(&w, true).expect("encode");
    }
    b.finish()
}

fn at(epoch: u64, sequence: u16, write_index: u16) -> InputPosition {
    InputPosition {
        epoch,
        stream_id: stream_id::BUILTIN_RELIABLE,
        sequence,
        write_index,
    }
}

/// A core keeping sessions for a successor, drawing its epochs from `seed`.
fn keeping(config: &AgentConfig, seed: u64) -> AgentConfig {
    AgentConfig {
        track_sessions: true,
        epoch_seed: seed,
        ..config.clone()
    }
}

/// A session taken over from a predecessor that stored it before message 3, handed two of
/// its three writes to the worker, and died; and the epoch of its streams.
fn taken_over_before_message_3(config: AgentConfig) -> (Agent<u32>, Instant, u64) {
    let (mut agent, mut rec, t0) = connected(keeping(&config, 1), VENDOR_EPROSIMA, None);
    for seq in 0..3 {
        agent.handle_datagram(t0, ADDR, &write(seq), &mut rec);
    }
    let snapshot = agent
        .snapshot(KEY, |a| a.to_le_bytes().to_vec())
        .expect("a snapshot");
    let mut next: Agent<u32> = Agent::new(keeping(&config, 2));
    assert!(next.restore(t0, &snapshot, ADDR));
    drain(&mut next);
    (next, t0, snapshot.epoch)
}

/// The writes of the message a predecessor handed over in part are not handed over again
/// when the client resends it: only those the worker did not execute go, and the message is
/// acknowledged; the messages after it go whole, with their positions.
#[test]
fn writes_the_worker_executed_for_a_predecessor_are_not_handed_over_again() {
    let (mut agent, t0, epoch) = taken_over_before_message_3(AgentConfig::default());
    // Message 2 was stored as taken: what the worker says of it changes nothing.
    agent.skip_executed(KEY, at(epoch, 2, 0));
    agent.skip_executed(KEY, at(epoch, 3, 1));
    let mut sink = Positions::default();
    agent.handle_datagram(t0, ADDR, &message_of_writes(3, &[30, 31, 32]), &mut sink);
    assert_eq!(sink.0, [(vec![32], Some(at(epoch, 3, 2)))]);
    assert_eq!(agent.stats().dropped("executed_before_takeover"), 2);
    let acks: Vec<_> = payloads(&drain(&mut agent))
        .into_iter()
        .filter_map(|p| match p {
            Payload::Acknack(a) => Some(a.first_unacked_seq_num),
            _ => None,
        })
        .collect();
    assert_eq!(acks, [4], "the message is taken");
    agent.handle_datagram(t0, ADDR, &message_of_writes(4, &[40, 41]), &mut sink);
    assert_eq!(
        sink.0[1..],
        [
            (vec![40], Some(at(epoch, 4, 0))),
            (vec![41], Some(at(epoch, 4, 1)))
        ]
    );
}

/// One datagram can hand several messages over before the front-end stores anything (a
/// resend that fills a gap delivers the messages kept as early): the worker's last position
/// is then some messages ahead of the stored session, and every write up to it (all of the
/// messages before its own) is not handed over again, whatever order the client's resends
/// come in; the messages are taken and the writes after it go.
#[test]
fn writes_of_several_messages_the_worker_executed_are_not_handed_over_again() {
    for order in [[3, 4, 5, 6], [5, 6, 4, 3]] {
        let (mut agent, t0, epoch) = taken_over_before_message_3(AgentConfig::default());
        agent.skip_executed(KEY, at(epoch, 5, 1));
        let mut sink = Positions::default();
        for seq in order {
            let samples: &[u8] = match seq {
                3 => &[30, 31],
                4 => &[40],
                5 => &[50, 51, 52],
                _ => &[60],
            };
            agent.handle_datagram(t0, ADDR, &message_of_writes(seq, samples), &mut sink);
        }
        assert_eq!(
            sink.0,
            [
                (vec![52], Some(at(epoch, 5, 2))),
                (vec![60], Some(at(epoch, 6, 0)))
            ],
            "resent in the order {order:?}"
        );
        assert_eq!(agent.stats().dropped("executed_before_takeover"), 5);
        let last_ack = payloads(&drain(&mut agent))
            .into_iter()
            .filter_map(|p| match p {
                Payload::Acknack(a) => Some(a.first_unacked_seq_num),
                _ => None,
            })
            .next_back();
        assert_eq!(last_ack, Some(7), "every message taken");
    }
}

/// A position of another run of the client's streams is not believed, however close: the
/// board reset since the worker's last write (CREATE_CLIENT of the same session, its new
/// run's messages 0 to 2 taken and stored, then the front-end died), and taking it would
/// drop the new run's writes. Nor is one further ahead than the window (no datagram hands
/// that much over).
#[test]
fn a_position_of_another_run_of_the_streams_is_not_believed() {
    let config = AgentConfig::default();
    let (mut agent, mut rec, t0) = connected(keeping(&config, 1), VENDOR_EPROSIMA, None);
    let mut handed = Positions::default();
    for seq in 0..7u8 {
        let m = message_of_writes(u16::from(seq), &[seq]);
        agent.handle_datagram(t0, ADDR, &m, &mut handed);
    }
    let old = handed.0.last().and_then(|(_, p)| *p).expect("a position");
    let later = t0 + Duration::from_secs(2);
    agent.handle_datagram(later, ADDR, &create_client_with(0x01), &mut rec);
    for seq in 0..3 {
        agent.handle_datagram(later, ADDR, &write(seq), &mut rec);
    }
    let snapshot = agent
        .snapshot(KEY, |a| a.to_le_bytes().to_vec())
        .expect("a snapshot");
    assert_ne!(snapshot.epoch, old.epoch, "the restart started another run");
    let mut next: Agent<u32> = Agent::new(keeping(&config, 2));
    assert!(next.restore(later, &snapshot, ADDR));
    drain(&mut next);
    // Message 6 of the old run: three ahead of the 3 the new run expects.
    next.skip_executed(KEY, old);
    let mut sink = Positions::default();
    for (seq, samples) in [(3, &[30][..]), (4, &[40, 41]), (5, &[50]), (6, &[60])] {
        next.handle_datagram(later, ADDR, &message_of_writes(seq, samples), &mut sink);
    }
    assert_eq!(
        sink.0.iter().map(|(d, _)| d[0]).collect::<Vec<_>>(),
        [30, 40, 41, 50, 60],
        "every write handed over"
    );
    assert_eq!(next.stats().dropped("executed_before_takeover"), 0);

    let (mut agent, t0, epoch) = taken_over_before_message_3(AgentConfig::default());
    agent.skip_executed(KEY, at(epoch, 3 + 16, 0));
    let mut sink = Positions::default();
    agent.handle_datagram(t0, ADDR, &message_of_writes(3, &[30]), &mut sink);
    assert_eq!(sink.0.len(), 1, "beyond the window: ignored");
}

/// Writes that follow a RESET in the same message belong to the new run of the streams but
/// carry the old run's message number: they get no position, which a successor could
/// otherwise take for the new run's.
#[test]
fn writes_after_a_reset_in_the_same_message_have_no_position() {
    let (mut agent, t0, _) = taken_over_before_message_3(AgentConfig::default());
    let mut b = MessageBuilder::new(MessageHeader::new(
        0x01,
        stream_id::BUILTIN_RELIABLE,
        3,
        KEY,
    ));
    b.push(&Payload::Reset, true).expect("encode");
    let w = Payload::WriteData(DataPayload {
        base: BaseObjectRequest {
            request_id: RequestId::from_u16(0x233),
            object_id: ObjectId::new(1, object_kind::DATAWRITER),
        },
        format: data_format::DATA,
        data: &[33],
    });
    b.push(&w, true).expect("encode");
    let mut sink = Positions::default();
    agent.handle_datagram(t0, ADDR, &b.finish(), &mut sink);
    assert_eq!(sink.0, [(vec![33], None)]);
}

/// What the worker executed for a predecessor means nothing to a session made since (the
/// board reset while the front-end was taken over: its streams start again) nor once the
/// taken-over session processed a message.
#[test]
fn executed_writes_are_applied_only_to_a_session_just_taken_over() {
    let (mut agent, t0, epoch) = taken_over_before_message_3(AgentConfig::default());
    let later = t0 + Duration::from_secs(2);
    let mut sink = Positions::default();
    agent.handle_datagram(later, ADDR, &create_client_with(0x01), &mut sink);
    agent.skip_executed(KEY, at(epoch, 0, 0));
    agent.handle_datagram(later, ADDR, &message_of_writes(0, &[1]), &mut sink);
    let [(data, Some(position))] = &sink.0[..] else {
        panic!("one write with a position: {:?}", sink.0);
    };
    assert_eq!(data, &[1], "the new stream's write goes");
    assert_eq!((position.sequence, position.write_index), (0, 0));
    assert_ne!(position.epoch, epoch, "in a new run of the streams");

    let (mut agent, t0, epoch) = taken_over_before_message_3(AgentConfig::default());
    let mut sink = Positions::default();
    agent.handle_datagram(t0, ADDR, &message_of_writes(3, &[30]), &mut sink);
    agent.skip_executed(KEY, at(epoch, 4, 0));
    agent.handle_datagram(t0, ADDR, &message_of_writes(4, &[40]), &mut sink);
    assert_eq!(sink.0.len(), 2, "told too late: ignored");
}

/// A client that asks a STATUS for each write (the spec's dialect) gets one for a write
/// not handed over again: its answer went to the process that died.
#[test]
fn a_write_not_handed_over_again_is_still_answered_where_the_client_asks() {
    let (mut agent, mut rec, t0) = connected(
        AgentConfig {
            track_sessions: true,
            ..AgentConfig::default()
        },
        [9, 9],
        None,
    );
    agent.handle_datagram(t0, ADDR, &write(0), &mut rec);
    let snapshot = agent
        .snapshot(KEY, |a| a.to_le_bytes().to_vec())
        .expect("a snapshot");
    let mut next: Agent<u32> = Agent::new(AgentConfig::default());
    assert!(next.restore(t0, &snapshot, ADDR));
    drain(&mut next);
    next.skip_executed(KEY, at(snapshot.epoch, 1, 0));
    let mut sink = Positions::default();
    next.handle_datagram(t0, ADDR, &message_of_writes(1, &[10]), &mut sink);
    next.handle_timeout(t0, &mut sink);
    assert!(sink.0.is_empty());
    let statuses: Vec<_> = payloads(&drain(&mut next))
        .into_iter()
        .filter_map(|p| match p {
            Payload::Status(s) => Some((s.related.request_id, s.result.status)),
            _ => None,
        })
        .collect();
    assert_eq!(statuses, [(RequestId::from_u16(0x200 + 10), status::OK)]);
}
