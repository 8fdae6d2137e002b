//! Session semantics of the agent core: liveliness (hard liveliness and the configured dead
//! time), dialects, GET_INFO about objects and the DataFormats of DATA.

use std::time::{Duration, Instant};

use xrce_common::session::agent::{
    Agent, AgentConfig, DataReply, Operation, OperationSink, Transmit,
};
use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::cdr::CdrReader;
use xrce_common::wire::sample::{decode_samples, SampleInfoDetail};
use xrce_common::wire::*;

#[path = "session_semantics/sizes_and_pacing.rs"]
mod sizes_and_pacing;

#[path = "session_semantics/lifecycle.rs"]
mod lifecycle;

/// What the core asked of the DDS side, owned.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Op {
    Created(ClientKey),
    Deleted(ClientKey),
    GetInfo(BaseObjectRequest, u32),
    Write(Dialect, u8),
    Other,
}

#[derive(Default)]
struct Recorder(Vec<Op>);

impl OperationSink for Recorder {
    fn has_room(&self) -> bool {
        true
    }
    fn operation(&mut self, _now: Instant, op: Operation<'_>) {
        self.0.push(match op {
            Operation::ClientCreated { client, .. } => Op::Created(client),
            Operation::ClientDeleted { client } => Op::Deleted(client),
            Operation::GetInfo {
                request, info_mask, ..
            } => Op::GetInfo(request, info_mask),
            Operation::Write { dialect, data, .. } => Op::Write(dialect, data.format),
            _ => Op::Other,
        });
    }
}

const ADDR: u32 = 7;
const KEY: ClientKey = ClientKey([0xA1, 0xB2, 0xC3, 0xD4]);

fn create_client(vendor_id: [u8; 2], properties: Option<Vec<Property>>) -> Vec<u8> {
    CreateClientPayload {
        vendor_id,
        properties,
        ..CreateClientPayload::eprosima(KEY, 0x01)
    }
    .message()
    .expect("encode")
}

fn in_session(stream: u8, seq: u16, payload: Payload<'_>) -> Vec<u8> {
    let mut b = MessageBuilder::new(MessageHeader::new(0x01, stream, seq, KEY));
    b.push(&payload, true).expect("encode");
    b.finish()
}

fn drain(agent: &mut Agent<u32>) -> Vec<Transmit<u32>> {
    std::iter::from_fn(|| agent.poll_transmit()).collect()
}

/// The payloads of every submessage of every datagram.
fn payloads(out: &[Transmit<u32>]) -> Vec<Payload<'_>> {
    out.iter()
        .flat_map(|t| {
            Message::decode(&t.data)
                .expect("agent output decodes")
                .submessages
                .into_iter()
                .map(|s| s.payload)
        })
        .collect()
}

fn connected(
    config: AgentConfig,
    vendor: [u8; 2],
    props: Option<Vec<Property>>,
) -> (Agent<u32>, Recorder, Instant) {
    let t0 = Instant::now();
    let mut agent = Agent::new(config);
    let mut rec = Recorder::default();
    agent.handle_datagram(t0, ADDR, &create_client(vendor, props), &mut rec);
    assert_eq!(rec.0, [Op::Created(KEY)]);
    drain(&mut agent);
    (agent, rec, t0)
}

/// Runs the core's timers from `from` to `to` in 10 ms steps; returns the probes sent.
fn run_timers(
    agent: &mut Agent<u32>,
    rec: &mut Recorder,
    from: Duration,
    to: Duration,
    t0: Instant,
) -> usize {
    let mut probes = 0;
    let mut t = from;
    while t <= to {
        agent.handle_timeout(t0 + t, rec);
        probes += payloads(&drain(agent))
            .iter()
            .filter(|p| matches!(p, Payload::GetInfo(_)))
            .count();
        t += Duration::from_millis(10);
    }
    probes
}

#[test]
fn hard_liveliness_probes_a_silent_client_then_deletes_its_session() {
    let props = Some(vec![("uxr_hl".to_string(), "000400".to_string())]);
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, props);
    assert!(
        agent.poll_timeout().is_some(),
        "a liveliness timer is armed"
    );
    // Probes (GET_INFO about the agent on stream 0) from a quarter of the timeout on.
    let probes = run_timers(
        &mut agent,
        &mut rec,
        Duration::ZERO,
        Duration::from_millis(250),
        t0,
    );
    assert!((2..=3).contains(&probes), "{probes} probes in 250 ms");
    // The client answers: it is alive again for another 400 ms.
    let info = in_session(
        0,
        0,
        Payload::Info(InfoPayload {
            reply: BaseObjectReply {
                related: BaseObjectRequest::default(),
                result: ResultStatus::OK,
            },
            object_info: &[0, 0],
        }),
    );
    agent.handle_datagram(t0 + Duration::from_millis(260), ADDR, &info, &mut rec);
    run_timers(
        &mut agent,
        &mut rec,
        Duration::from_millis(260),
        Duration::from_millis(640),
        t0,
    );
    assert!(agent.has_client(KEY), "answered probes keep the session");
    run_timers(
        &mut agent,
        &mut rec,
        Duration::from_millis(650),
        Duration::from_millis(700),
        t0,
    );
    assert!(!agent.has_client(KEY), "silent past its timeout: deleted");
    assert_eq!(rec.0.last(), Some(&Op::Deleted(KEY)));
    assert_eq!(agent.stats().dropped("client_dead"), 1);
}

#[test]
fn the_configured_dead_time_applies_to_other_clients_and_is_off_by_default() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    assert_eq!(agent.poll_timeout(), None, "no timer without liveliness");
    run_timers(
        &mut agent,
        &mut rec,
        Duration::ZERO,
        Duration::from_secs(3),
        t0,
    );
    assert!(agent.has_client(KEY));

    let config = AgentConfig {
        client_dead_time: Some(Duration::from_secs(1)),
        ..AgentConfig::default()
    };
    let (mut agent, mut rec, t0) = connected(config, VENDOR_EPROSIMA, None);
    let probes = run_timers(
        &mut agent,
        &mut rec,
        Duration::ZERO,
        Duration::from_millis(990),
        t0,
    );
    assert_eq!(probes, 3, "probed at 250, 500 and 750 ms");
    run_timers(
        &mut agent,
        &mut rec,
        Duration::from_millis(1000),
        Duration::from_millis(1000),
        t0,
    );
    assert!(!agent.has_client(KEY));
}

#[test]
fn the_client_state_machine_answers_probes_and_stays_alive() {
    let config = AgentConfig {
        client_dead_time: Some(Duration::from_millis(400)),
        ..AgentConfig::default()
    };
    let t0 = Instant::now();
    let mut agent = Agent::new(config);
    let mut client = Client::new(ClientConfig {
        hard_liveliness: Some(Duration::from_millis(300)),
        ..ClientConfig::new(KEY)
    });
    let mut rec = Recorder::default();
    client.connect(t0);
    for step in 0..300u64 {
        let now = t0 + Duration::from_millis(step * 10);
        while let Some(d) = client.poll_transmit() {
            agent.handle_datagram(now, ADDR, &d, &mut rec);
        }
        agent.handle_timeout(now, &mut rec);
        while let Some(t) = agent.poll_transmit() {
            client.handle_datagram(now, &t.data);
        }
        client.handle_timeout(now);
    }
    assert!(
        agent.has_client(KEY),
        "3 s of idle but answering: still there"
    );
    assert!(!rec.0.contains(&Op::Deleted(KEY)));
}

#[test]
fn dialect_follows_the_vendor_id_and_shapes_info_and_writes() {
    // A non-eProsima client speaks the spec: INFO has the activity first.
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), [0x0A, 0x0B], None);
    assert_eq!(agent.dialect(KEY), Some(Dialect::Spec));
    let get_info = |object_id| {
        Payload::GetInfo(GetInfoPayload {
            base: BaseObjectRequest {
                request_id: RequestId::from_u16(3),
                object_id,
            },
            info_mask: 0x03,
        })
    };
    agent.handle_datagram(
        t0,
        ADDR,
        &in_session(0, 0, get_info(ObjectId::AGENT)),
        &mut rec,
    );
    let out = drain(&mut agent);
    let Some(Payload::Info(i)) = payloads(&out).into_iter().next() else {
        panic!("no INFO")
    };
    assert_eq!(
        i.object_info[..2],
        [0x01, object_kind::AGENT],
        "activity first"
    );
    assert_eq!(
        &i.object_info[14..16],
        &[0x01, object_kind::AGENT],
        "then config"
    );
    // WRITE_DATA carries the session's dialect to the DDS side.
    let write = in_session(
        0x80,
        0,
        Payload::WriteData(DataPayload {
            base: BaseObjectRequest {
                request_id: RequestId::from_u16(4),
                object_id: ObjectId::new(1, object_kind::DATAWRITER),
            },
            format: data_format::SAMPLE,
            data: &[0, 0, 1, 2],
        }),
    );
    agent.handle_datagram(t0, ADDR, &write, &mut rec);
    assert_eq!(
        rec.0.last(),
        Some(&Op::Write(Dialect::Spec, data_format::SAMPLE))
    );

    // eProsima's own client: config first (the layout the reference agent answers with).
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    agent.handle_datagram(
        t0,
        ADDR,
        &in_session(0, 0, get_info(ObjectId::AGENT)),
        &mut rec,
    );
    let out = drain(&mut agent);
    let Some(Payload::Info(i)) = payloads(&out).into_iter().next() else {
        panic!("no INFO")
    };
    assert_eq!(i.object_info[..2], [0x01, object_kind::AGENT]);
    assert_eq!(&i.object_info[2..6], b"XRCE", "config first");
}

#[test]
fn a_forced_spec_dialect_drops_the_result_status_from_status_agent() {
    let t0 = Instant::now();
    for (forced, with_result) in [
        (None, true),
        (Some(Dialect::Eprosima), true),
        (Some(Dialect::Spec), false),
    ] {
        let mut agent = Agent::new(AgentConfig {
            dialect: forced,
            ..AgentConfig::default()
        });
        agent.handle_datagram(
            t0,
            ADDR,
            &create_client([1, 2], None),
            &mut Recorder::default(),
        );
        let out = drain(&mut agent);
        let Some(Payload::StatusAgent(s)) = payloads(&out).into_iter().next() else {
            panic!("no STATUS_AGENT")
        };
        assert_eq!(s.result.is_some(), with_result, "{forced:?}");
    }
}

#[test]
fn get_info_about_an_object_goes_to_the_dds_side_and_info_carries_its_config() {
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, None);
    let topic = ObjectId::new(2, object_kind::TOPIC);
    let request = BaseObjectRequest {
        request_id: RequestId::from_u16(9),
        object_id: topic,
    };
    let msg = in_session(
        0x80,
        0,
        Payload::GetInfo(GetInfoPayload {
            base: request,
            info_mask: 0x01,
        }),
    );
    agent.handle_datagram(t0, ADDR, &msg, &mut rec);
    assert_eq!(rec.0.last(), Some(&Op::GetInfo(request, 0x01)));
    drain(&mut agent);
    let variant = ObjectVariant {
        kind: object_kind::TOPIC,
        representation: Representation::Xml("<dds><topic><name>T</name></topic></dds>".into()),
        extra: VariantExtra::Parent(ObjectId::new(1, object_kind::PARTICIPANT)),
    };
    agent
        .send_info(t0, KEY, request, ResultStatus::OK, Some(&variant))
        .expect("queued");
    let out = drain(&mut agent);
    let Some(Payload::Info(i)) = payloads(&out).into_iter().next() else {
        panic!("no INFO")
    };
    assert_eq!(i.reply.related, request);
    // config? present, the variant, then activity? absent. The variant is aligned from the
    // payload start, where the 6-byte reply precedes the ObjectInfo.
    let mut whole = vec![0u8; BaseObjectReply::LEN];
    whole.extend_from_slice(i.object_info);
    let r = &mut CdrReader::new(&whole, true);
    r.take(BaseObjectReply::LEN).expect("reply");
    assert!(r.bool().expect("config flag"));
    assert_eq!(ObjectVariant::decode(r).expect("variant"), variant);
    assert!(!r.bool().expect("activity flag"));
    assert_eq!(r.remaining(), 0);
}

#[test]
fn data_goes_out_in_the_format_the_read_asked_for() {
    for (vendor, dialect) in [
        (VENDOR_EPROSIMA, Dialect::Eprosima),
        ([9, 9], Dialect::Spec),
    ] {
        let (mut agent, _rec, t0) = connected(AgentConfig::default(), vendor, None);
        for format in [
            data_format::DATA,
            data_format::SAMPLE,
            data_format::DATA_SEQ,
            data_format::SAMPLE_SEQ,
            data_format::PACKED_SAMPLES,
        ] {
            let reply = DataReply {
                request: BaseObjectRequest {
                    request_id: RequestId::from_u16(5),
                    object_id: ObjectId::new(3, object_kind::DATAREADER),
                },
                format,
                sample: &[1, 2, 3, 4, 5],
                little_endian: true,
                state: 0,
                sequence_number: 42,
            };
            let later = t0 + Duration::from_millis(1500);
            agent.send_data(later, KEY, 0x80, reply).expect("queued");
            let out = drain(&mut agent);
            let Some(Payload::Data(d)) = payloads(&out).into_iter().next() else {
                panic!("no DATA")
            };
            assert_eq!(d.format, format);
            let samples = decode_samples(format, d.data, true, dialect, None).expect("decodes");
            assert_eq!(samples.len(), 1);
            assert_eq!(samples[0].data, &[1, 2, 3, 4, 5]);
            if let Some(info) = samples[0].info {
                let SampleInfoDetail::Both {
                    sequence_number,
                    session_time_offset,
                } = info.detail
                else {
                    panic!("{:?}", info.detail)
                };
                assert_eq!(sequence_number, 42);
                assert!((1500..1600).contains(&session_time_offset));
            }
        }
    }
}

#[test]
fn the_client_state_machine_asks_for_hard_liveliness_in_the_eprosima_format() {
    let mut client = Client::new(ClientConfig {
        hard_liveliness: Some(Duration::from_secs(10)),
        ..ClientConfig::new(KEY)
    });
    client.connect(Instant::now());
    let d = client.poll_transmit().expect("CREATE_CLIENT");
    let m = Message::decode(&d).expect("decodes");
    let Payload::CreateClient(c) = &m.submessages[0].payload else {
        panic!()
    };
    assert_eq!(
        c.properties,
        Some(vec![("uxr_hl".to_string(), "010000".to_string())])
    );
    assert!(
        client.poll_event().is_none()
            || matches!(client.poll_event(), Some(ClientEvent::SessionStatus(_)))
    );
}

#[test]
fn a_create_client_longer_than_its_declared_length_is_read_whole() {
    // eProsima's client declares 16 bytes for CREATE_CLIENT even when it appends the
    // hard-liveliness property and then its MTU (seen with UCLIENT_HARD_LIVELINESS_CHECK).
    let props = Some(vec![("uxr_hl".to_string(), "002000".to_string())]);
    let mut bytes = create_client(VENDOR_EPROSIMA, props);
    let declared = u16::from_le_bytes([bytes[10], bytes[11]]);
    assert!(declared > 16);
    bytes[10..12].copy_from_slice(&16u16.to_le_bytes());
    let t0 = Instant::now();
    let mut agent = Agent::new(AgentConfig::default());
    let mut rec = Recorder::default();
    agent.handle_datagram(t0, ADDR, &bytes, &mut rec);
    assert_eq!(rec.0, [Op::Created(KEY)]);
    assert!(
        agent.poll_timeout().is_some(),
        "hard liveliness armed from the property"
    );
    let out = drain(&mut agent);
    assert!(matches!(payloads(&out)[0], Payload::StatusAgent(_)));
}

#[test]
fn eprosimas_bare_answer_to_a_probe_is_recognised_not_dropped() {
    let props = Some(vec![("uxr_hl".to_string(), "000400".to_string())]);
    let (mut agent, mut rec, t0) = connected(AgentConfig::default(), VENDOR_EPROSIMA, props);
    agent.handle_timeout(t0 + Duration::from_millis(150), &mut rec);
    let out = drain(&mut agent);
    let Some(Payload::GetInfo(probe)) = payloads(&out).into_iter().next() else {
        panic!("no probe")
    };
    // What eProsima's client sends back: the message header, then the INFO payload with no
    // submessage header (request id echoed, object id and result zero, both optionals absent).
    let mut reply = Vec::new();
    MessageHeader::new(0x01, 0, 0, KEY).encode(&mut reply);
    reply.extend_from_slice(&probe.base.request_id.0);
    reply.extend_from_slice(&[0, 0, 0, 0, 0, 0]);
    agent.handle_datagram(t0 + Duration::from_millis(300), ADDR, &reply, &mut rec);
    assert!(
        agent.stats().dropped.is_empty(),
        "{:?}",
        agent.stats().dropped
    );
    agent.handle_timeout(t0 + Duration::from_millis(650), &mut rec);
    assert!(
        agent.has_client(KEY),
        "the answer counted as a sign of life"
    );
}

#[test]
fn ping_replies_match_the_reference_agent_byte_for_byte() {
    // From wire-traces/ping.txt: PingAgentUDP without, then within, a session.
    let unhex = |s: &str| -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
            .collect()
    };
    let t0 = Instant::now();
    let mut agent: Agent<u32> = Agent::new(AgentConfig::default());
    let mut rec = Recorder::default();
    let exchange = [
        (
            "8000000002010800000afffd02000000",
            "8000000006011c00000afffd0000010d585243450100010f00010d000100000000000000",
        ),
        (
            "8000000000011000585243450100010faaaabbbb8100fc01",
            "8100000004010b000000585243450100010f00",
        ),
        (
            "8100000002010800000afffd02000000",
            "8100000006011c00000afffd0001010d585243450100010f00010d000100000000000000",
        ),
    ];
    for (c2a, a2c) in exchange {
        agent.handle_datagram(t0, ADDR, &unhex(c2a), &mut rec);
        let out = drain(&mut agent);
        assert_eq!(out.len(), 1);
        assert_eq!(hex(&out[0].data), a2c);
    }
}
