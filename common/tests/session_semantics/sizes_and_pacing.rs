//! Sizes and pacing: fragments, closed endpoints, the MTU, HEARTBEAT back-off, room asked
//! of the DDS side.

use super::*;

#[test]
fn an_info_larger_than_the_mtu_goes_out_in_fragments() {
    let (mut agent, _rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let request = BaseObjectRequest {
        request_id: RequestId::from_u16(4),
        object_id: ObjectId::new(2, object_kind::TOPIC),
    };
    let variant = ObjectVariant {
        kind: object_kind::TOPIC,
        representation: Representation::Xml(format!(
            "<dds><topic>{}</topic></dds>",
            "x".repeat(2000)
        )),
        extra: VariantExtra::Parent(ObjectId::new(1, object_kind::PARTICIPANT)),
    };
    agent
        .send_info(t0, KEY, request, ResultStatus::OK, Some(&variant))
        .expect("queued");
    let mut out = drain(&mut agent);
    // The window sends up to 16 messages at once; ACKNACK the rest out if needed.
    assert!(out.len() > 1, "one INFO of 2 kB in one datagram");
    assert!(
        out.iter().all(|t| t.data.len() <= 512),
        "a datagram beyond the MTU"
    );
    out.retain(|t| t.data[1] == 0x80);
    assert!(payloads(&out)
        .iter()
        .all(|p| matches!(p, Payload::Fragment { .. })));
}

#[test]
fn a_closed_endpoint_keeps_its_session_and_silences_it_until_the_client_returns() {
    let props = Some(vec![("uxr_hl".to_string(), "002000".to_string())]);
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, props);
    let request = BaseObjectRequest {
        request_id: RequestId::from_u16(9),
        object_id: ObjectId::new(1, object_kind::PARTICIPANT),
    };
    assert!(agent.endpoint_closed(t0, ADDR), "a session was there");
    assert!(!agent.endpoint_closed(t0, ADDR), "only once");
    assert!(agent.has_client(KEY), "the session is kept");
    // A reply meanwhile is queued but not sent, and no heartbeat or probe goes out.
    agent
        .send_status(t0, KEY, request, ResultStatus::OK)
        .expect("queued");
    assert!(drain(&mut agent).is_empty(), "sent to a closed endpoint");
    let probes = run_timers(
        &mut agent,
        &mut rec,
        Duration::ZERO,
        Duration::from_millis(1500),
        t0,
    );
    assert_eq!(probes, 0);
    assert!(drain(&mut agent).is_empty());
    let next = agent.poll_timeout().expect("the dead time still runs");
    assert!(next > t0 + Duration::from_millis(1500), "timer in the past");
    // The client reconnecting elsewhere and creating its session again finds it, objects
    // included (no ClientDeleted), and is served there.
    let t1 = t0 + Duration::from_millis(1700);
    agent.handle_datagram(
        t1,
        ADDR + 1,
        &create_client(VENDOR_EPROSIMA, None),
        &mut rec,
    );
    assert_eq!(rec.0, [Op::Created(KEY)], "{:?}", rec.0);
    let out = drain(&mut agent);
    assert!(out.iter().all(|t| t.destination == ADDR + 1));
    assert!(payloads(&out)
        .iter()
        .any(|p| matches!(p, Payload::StatusAgent(_))));
    // Without hard liveliness now, nothing deletes it.
    agent.handle_timeout(t1 + Duration::from_secs(5), &mut rec);
    assert!(agent.has_client(KEY));
}

#[test]
fn a_closed_endpoints_client_is_deleted_after_its_dead_time() {
    let props = Some(vec![("uxr_hl".to_string(), "000400".to_string())]);
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, props);
    agent.endpoint_closed(t0, ADDR);
    run_timers(
        &mut agent,
        &mut rec,
        Duration::ZERO,
        Duration::from_millis(450),
        t0,
    );
    assert!(!agent.has_client(KEY));
    assert_eq!(rec.0.last(), Some(&Op::Deleted(KEY)));
}

#[test]
fn the_client_mtu_is_capped_to_the_transports_largest_message() {
    let config = AgentConfig {
        max_message_size: 100,
        ..AgentConfig::default()
    };
    let (mut agent, _rec, t0) = connected(config, VENDOR_EPROSIMA, None);
    let request = BaseObjectRequest {
        request_id: RequestId::from_u16(4),
        object_id: ObjectId::new(2, object_kind::TOPIC),
    };
    let variant = ObjectVariant {
        kind: object_kind::TOPIC,
        representation: Representation::Xml("<dds/>".repeat(40)),
        extra: VariantExtra::Parent(ObjectId::new(1, object_kind::PARTICIPANT)),
    };
    agent
        .send_info(t0, KEY, request, ResultStatus::OK, Some(&variant))
        .expect("queued");
    let out = drain(&mut agent);
    assert!(out.len() > 2);
    assert!(
        out.iter().all(|t| t.data.len() <= 100),
        "beyond the transport"
    );
}

/// HEARTBEATs at the times `run` sees them, for a client that has unacknowledged output.
fn heartbeat_times(
    agent: &mut Agent<u32>,
    rec: &mut Recorder,
    t0: Instant,
    until: Duration,
) -> Vec<Duration> {
    let mut times = Vec::new();
    let mut t = Duration::ZERO;
    while t <= until {
        agent.handle_timeout(t0 + t, rec);
        for p in payloads(&drain(agent)) {
            if matches!(p, Payload::Heartbeat(_)) {
                times.push(t);
            }
        }
        t += Duration::from_millis(10);
    }
    times
}

/// A connected client with one STATUS sent to it on its reliable stream and not yet
/// acknowledged (so HEARTBEATs are due).
fn with_unacknowledged_output() -> (Agent<u32>, Recorder, Instant) {
    let (mut agent, rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let request = BaseObjectRequest {
        request_id: RequestId::from_u16(9),
        object_id: ObjectId::new(1, object_kind::PARTICIPANT),
    };
    agent
        .send_status(t0, KEY, request, ResultStatus::OK)
        .expect("queued");
    drain(&mut agent);
    (agent, rec, t0)
}

#[test]
fn heartbeats_to_a_client_that_is_heard_do_not_back_off_when_its_acknacks_are_lost() {
    // A flooded socket drops datagrams whatever their kind: a client that keeps talking
    // (here its own HEARTBEATs every 50 ms) but whose ACKNACKs never arrive is alive, and
    // is probed at the base period, not less and less (its reliable output would stall).
    let (mut agent, mut rec, t0) = with_unacknowledged_output();
    let talk = in_session(
        0,
        0,
        Payload::Heartbeat(HeartbeatPayload {
            first_unacked_seq_num: 0,
            last_unacked_seq_num: 0,
            stream_id: stream_id::BUILTIN_RELIABLE,
        }),
    );
    let mut times = Vec::new();
    let mut t = Duration::ZERO;
    while t <= Duration::from_secs(2) {
        if t.as_millis() % 50 == 0 {
            agent.handle_datagram(t0 + t, ADDR, &talk, &mut rec);
        }
        agent.handle_timeout(t0 + t, &mut rec);
        if payloads(&drain(&mut agent))
            .iter()
            .any(|p| matches!(p, Payload::Heartbeat(_)))
        {
            times.push(t.as_millis());
        }
        t += Duration::from_millis(10);
    }
    // Every 100 ms while it is heard.
    assert_eq!(times.len(), 20, "{times:?}");
    assert!(times.windows(2).all(|w| w[1] - w[0] == 100), "{times:?}");
    // Once it falls silent, the back-off starts.
    let times = heartbeat_times(&mut agent, &mut rec, t0 + t, Duration::from_secs(4));
    let ms: Vec<u128> = times.iter().map(|d| d.as_millis()).collect();
    assert!(ms.windows(2).any(|w| w[1] - w[0] >= 400), "{ms:?}");
}

#[test]
fn heartbeats_to_a_client_that_does_not_answer_back_off_and_reset_when_it_does() {
    let (mut agent, mut rec, t0) = with_unacknowledged_output();
    let times = heartbeat_times(&mut agent, &mut rec, t0, Duration::from_secs(20));
    let ms: Vec<u128> = times.iter().map(|d| d.as_millis()).collect();
    // 100, then 200, 400, 800, 1600 ms later, then every 3.2 s: 10 in 20 s, not 200.
    assert_eq!(&ms[..5], [100, 300, 700, 1500, 3100], "{ms:?}");
    assert!(ms.windows(2).skip(4).all(|w| w[1] - w[0] == 3200), "{ms:?}");
    assert_eq!(ms.len(), 10, "{ms:?}");
    // The client acknowledges nothing new but answers: the period starts again at 100 ms.
    let ack = in_session(
        0,
        0,
        Payload::Acknack(AcknackPayload {
            first_unacked_seq_num: 0,
            nack_bitmap: 0,
            stream_id: stream_id::BUILTIN_RELIABLE,
        }),
    );
    let t1 = t0 + Duration::from_millis(20_005);
    agent.handle_datagram(t1, ADDR, &ack, &mut rec);
    drain(&mut agent);
    // Answering every HEARTBEAT at once keeps the period at 100 ms; the first unanswered one
    // doubles it again.
    let mut next = Vec::new();
    let mut t = Duration::ZERO;
    while t <= Duration::from_secs(4) && next.len() < 6 {
        agent.handle_timeout(t1 + t, &mut rec);
        if payloads(&drain(&mut agent))
            .iter()
            .any(|p| matches!(p, Payload::Heartbeat(_)))
        {
            next.push(t.as_millis());
            if next.len() < 5 {
                agent.handle_datagram(t1 + t, ADDR, &ack, &mut rec);
                drain(&mut agent);
            }
        }
        t += Duration::from_millis(10);
    }
    assert_eq!(next, [100, 200, 300, 400, 500, 700], "after ACKNACKs");
}

#[test]
fn a_best_effort_sample_larger_than_the_client_mtu_is_dropped_without_a_sequence_number() {
    // The client announced 512 bytes (CREATE_CLIENT's MTU property): a best-effort stream
    // cannot fragment, so a bigger sample is dropped, counted, as the reference agent does;
    // the next one that fits takes the sequence number it would have used.
    let (mut agent, _rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let reply = |sample: &'static [u8]| DataReply {
        request: BaseObjectRequest {
            request_id: RequestId::from_u16(5),
            object_id: ObjectId::new(3, object_kind::DATAREADER),
        },
        format: data_format::DATA,
        sample,
        little_endian: true,
        state: 0,
        sequence_number: 1,
    };
    static BIG: [u8; 1000] = [7; 1000];
    agent
        .send_data(t0, KEY, stream_id::BUILTIN_BEST_EFFORT, reply(&BIG))
        .expect("dropped and counted by the core, not an error to count again");
    assert!(drain(&mut agent).is_empty(), "nothing sent");
    assert_eq!(agent.stats().dropped("over_mtu"), 1);
    agent
        .send_data(
            t0,
            KEY,
            stream_id::BUILTIN_BEST_EFFORT,
            reply(&[1, 2, 3, 4]),
        )
        .expect("fits");
    let out = drain(&mut agent);
    assert_eq!(out.len(), 1);
    assert!(out[0].data.len() <= 512);
    let m = Message::decode(&out[0].data).expect("decodes");
    assert_eq!(m.header.stream_id, stream_id::BUILTIN_BEST_EFFORT);
    assert_eq!(
        m.header.sequence_nr, 0,
        "the dropped sample used no sequence number"
    );
    // A reliable read of the same sample is fragmented, not dropped.
    agent
        .send_data(t0, KEY, stream_id::BUILTIN_RELIABLE, reply(&BIG))
        .expect("fragments");
    let frags = payloads(&drain(&mut agent))
        .into_iter()
        .filter(|p| matches!(p, Payload::Fragment { .. }))
        .count();
    assert!(frags >= 2, "{frags} fragments");
    // A client that announces no MTU (a spec client): only the transport bounds its
    // best-effort messages.
    let mut spec = Agent::new(AgentConfig::default());
    let message = CreateClientPayload {
        vendor_id: [9, 9],
        mtu: None,
        ..CreateClientPayload::eprosima(KEY, 0x01)
    }
    .message()
    .expect("encode");
    spec.handle_datagram(t0, ADDR, &message, &mut Recorder::default());
    drain(&mut spec);
    spec.send_data(t0, KEY, stream_id::BUILTIN_BEST_EFFORT, reply(&BIG))
        .expect("sent");
    let out = drain(&mut spec);
    assert_eq!(out.len(), 1);
    assert!(out[0].data.len() > 1000);
    assert_eq!(spec.stats().dropped("over_mtu"), 0);
}

/// A sink with room for a small message but not for the largest one.
#[derive(Default)]
struct RoomForSmall(Recorder);

impl OperationSink for RoomForSmall {
    fn has_room(&self) -> bool {
        false
    }
    fn has_room_for(&self, submessages: usize) -> bool {
        submessages <= 2
    }
    fn operation(&mut self, now: Instant, op: Operation<'_>) {
        self.0.operation(now, op)
    }
}

#[test]
fn a_reliable_message_asks_room_for_its_submessages() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let mut sink = RoomForSmall(std::mem::take(&mut rec));
    // One WRITE_DATA: room for it is enough, where the largest message's room is lacking.
    agent.handle_datagram(
        t0,
        ADDR,
        &in_session(0x80, 0, write(0, data_format::DATA)),
        &mut sink,
    );
    assert_eq!(
        sink.0 .0.last(),
        Some(&Op::Write(Dialect::Eprosima, data_format::DATA))
    );
    // Three submessages are more than this sink has room for: refused, for the client to
    // send again.
    let mut b = MessageBuilder::new(MessageHeader::new(0x01, 0x80, 1, KEY));
    for i in 1..4 {
        b.push(&write(i, data_format::DATA), true).expect("encode");
    }
    let taken = sink.0 .0.len();
    agent.handle_datagram(t0, ADDR, &b.finish(), &mut sink);
    assert_eq!(sink.0 .0.len(), taken, "{:?}", sink.0 .0);
    assert_eq!(agent.stats().dropped("backpressure"), 1);
}

#[test]
fn a_heartbeat_inside_a_reliable_message_delivers_buffered_messages_after_it() {
    // The message was given room for its own operations: buffered messages its HEARTBEAT
    // makes deliverable come after them, not in its middle (where they could take that room
    // and leave the rest of the message behind after it was acknowledged).
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let early = in_session(0x80, 2, write(2, data_format::SAMPLE));
    agent.handle_datagram(t0, ADDR, &early, &mut rec);
    assert_eq!(rec.0.len(), 1, "held for the gap: {:?}", rec.0);
    let mut b = MessageBuilder::new(MessageHeader::new(0x01, 0x80, 0, KEY));
    b.push(
        &Payload::Heartbeat(HeartbeatPayload {
            // The client gave up on message 1: message 2 is next after this one.
            first_unacked_seq_num: 2,
            last_unacked_seq_num: 2,
            stream_id: stream_id::BUILTIN_RELIABLE,
        }),
        true,
    )
    .expect("encode");
    b.push(&write(0, data_format::DATA), true).expect("encode");
    agent.handle_datagram(t0, ADDR, &b.finish(), &mut rec);
    assert_eq!(
        rec.0[1..],
        [
            Op::Write(Dialect::Eprosima, data_format::DATA),
            Op::Write(Dialect::Eprosima, data_format::SAMPLE)
        ]
    );
}

/// A WRITE_DATA of request `n` in `format`.
fn write(n: u16, format: u8) -> Payload<'static> {
    Payload::WriteData(DataPayload {
        base: BaseObjectRequest {
            request_id: RequestId::from_u16(n + 4),
            object_id: ObjectId::new(1, object_kind::DATAWRITER),
        },
        format,
        data: &[0, 1, 0, 0, 7, 7, 7, 7],
    })
}
