//! Property tests: for generated values of every codec type, decode(encode(v)) == v, in both
//! byte orders and, where the layout depends on it, in both dialects.

use proptest::prelude::*;
use xrce_common::wire::binary::*;
use xrce_common::wire::cdr::{CdrReader, CdrWriter};
use xrce_common::wire::sample::{SampleInfo, SampleInfoDetail};
use xrce_common::wire::*;

fn name() -> impl Strategy<Value = String> {
    "[a-zA-Z0-9_:/<> .-]{0,40}"
}

fn bytes(max: usize) -> impl Strategy<Value = Vec<u8>> {
    proptest::collection::vec(any::<u8>(), 0..max)
}

fn object_id() -> impl Strategy<Value = ObjectId> {
    any::<[u8; 2]>().prop_map(ObjectId)
}

fn base() -> impl Strategy<Value = BaseObjectRequest> {
    (any::<[u8; 2]>(), object_id()).prop_map(|(r, o)| BaseObjectRequest {
        request_id: RequestId(r),
        object_id: o,
    })
}

fn result() -> impl Strategy<Value = ResultStatus> {
    (any::<u8>(), any::<u8>()).prop_map(|(status, implementation_status)| ResultStatus {
        status,
        implementation_status,
    })
}

fn properties() -> impl Strategy<Value = Option<Vec<Property>>> {
    proptest::option::of(proptest::collection::vec((name(), name()), 0..4))
}

fn time() -> impl Strategy<Value = Time> {
    (any::<i32>(), any::<u32>()).prop_map(|(seconds, nanoseconds)| Time {
        seconds,
        nanoseconds,
    })
}

fn variant() -> impl Strategy<Value = ObjectVariant> {
    let kinds = prop_oneof![
        Just(object_kind::PARTICIPANT),
        Just(object_kind::TOPIC),
        Just(object_kind::PUBLISHER),
        Just(object_kind::SUBSCRIBER),
        Just(object_kind::DATAWRITER),
        Just(object_kind::DATAREADER),
        Just(object_kind::TYPE),
        Just(object_kind::QOSPROFILE),
        Just(object_kind::APPLICATION),
    ];
    let repr = prop_oneof![
        name().prop_map(Representation::Reference),
        name().prop_map(Representation::Xml),
        bytes(64).prop_map(Representation::Binary),
    ];
    (kinds, repr, any::<i16>(), object_id()).prop_map(|(kind, representation, d, p)| {
        let extra = match kind {
            object_kind::PARTICIPANT => VariantExtra::DomainId(d),
            object_kind::TYPE | object_kind::QOSPROFILE | object_kind::APPLICATION => {
                VariantExtra::None
            }
            _ => VariantExtra::Parent(p),
        };
        ObjectVariant {
            kind,
            representation,
            extra,
        }
    })
}

fn read_spec() -> impl Strategy<Value = ReadSpecification> {
    let ddc = (any::<u16>(), any::<u16>(), any::<u16>(), any::<u16>()).prop_map(|(a, b, c, d)| {
        DataDeliveryControl {
            max_samples: a,
            max_elapsed_time: b,
            max_bytes_per_second: c,
            min_pace_period: d,
        }
    });
    (
        any::<u8>(),
        data_format_value(),
        proptest::option::of(name()),
        proptest::option::of(ddc),
        any::<bool>(),
    )
        .prop_map(|(s, f, filter, ddc, dheader)| ReadSpecification {
            preferred_stream_id: s,
            data_format: f,
            content_filter_expression: filter,
            delivery_control_dheader: dheader && ddc.is_some(),
            delivery_control: ddc,
        })
}

fn data_format_value() -> impl Strategy<Value = u8> {
    prop_oneof![
        Just(data_format::DATA),
        Just(data_format::SAMPLE),
        Just(data_format::DATA_SEQ),
        Just(data_format::SAMPLE_SEQ),
        Just(data_format::PACKED_SAMPLES),
    ]
}

/// Every payload kind; `data` backs the borrowed ones.
fn payload(data: &'static [u8]) -> impl Strategy<Value = Payload<'static>> {
    prop_oneof![
        (
            any::<[u8; 2]>(),
            any::<[u8; 2]>(),
            any::<[u8; 4]>(),
            1u8..=0xFF,
            properties(),
            proptest::option::of(any::<u16>())
        )
            .prop_map(|(version, vendor_id, key, session_id, properties, mtu)| {
                Payload::CreateClient(CreateClientPayload {
                    cookie: XRCE_COOKIE,
                    version,
                    vendor_id,
                    client_key: ClientKey(key),
                    session_id,
                    properties,
                    mtu,
                })
            }),
        (base(), variant(), any::<bool>(), any::<bool>()).prop_map(
            |(base, variant, reuse, replace)| {
                Payload::Create(CreatePayload {
                    base,
                    variant,
                    reuse,
                    replace,
                })
            }
        ),
        (base(), any::<u32>())
            .prop_map(|(base, info_mask)| Payload::GetInfo(GetInfoPayload { base, info_mask })),
        base().prop_map(Payload::Delete),
        (
            proptest::option::of(result()),
            any::<[u8; 2]>(),
            any::<[u8; 2]>(),
            properties()
        )
            .prop_map(
                |(result, version, vendor_id, properties)| Payload::StatusAgent(
                    StatusAgentPayload {
                        result,
                        cookie: XRCE_COOKIE,
                        version,
                        vendor_id,
                        properties,
                    }
                )
            ),
        (base(), result())
            .prop_map(|(related, result)| Payload::Status(BaseObjectReply { related, result })),
        (base(), result(), 0..data.len()).prop_map(move |(related, result, n)| {
            Payload::Info(InfoPayload {
                reply: BaseObjectReply { related, result },
                object_info: &data[..n],
            })
        }),
        (base(), data_format_value(), 0..data.len(), any::<bool>()).prop_map(
            move |(base, format, n, write)| {
                let d = DataPayload {
                    base,
                    format,
                    data: &data[..n],
                };
                if write {
                    Payload::WriteData(d)
                } else {
                    Payload::Data(d)
                }
            }
        ),
        (base(), read_spec())
            .prop_map(|(base, spec)| Payload::ReadData(ReadDataPayload { base, spec })),
        (any::<u16>(), any::<u16>(), any::<u8>()).prop_map(|(a, b, s)| Payload::Acknack(
            AcknackPayload {
                first_unacked_seq_num: a,
                nack_bitmap: b,
                stream_id: s
            }
        )),
        (any::<u16>(), any::<u16>(), any::<u8>()).prop_map(|(a, b, s)| Payload::Heartbeat(
            HeartbeatPayload {
                first_unacked_seq_num: a,
                last_unacked_seq_num: b,
                stream_id: s
            }
        )),
        Just(Payload::Reset),
        (any::<bool>(), 0..data.len()).prop_map(move |(last, n)| Payload::Fragment {
            last,
            data: &data[..n]
        }),
        time().prop_map(Payload::Timestamp),
        (time(), time(), time()).prop_map(|(transmit, receive, originate)| {
            Payload::TimestampReply(TimestampReplyPayload {
                transmit,
                receive,
                originate,
            })
        }),
        (16u8..=0xFF, any::<u8>(), 0..data.len()).prop_map(move |(id, flags, n)| {
            Payload::Unknown {
                id,
                flags: flags & !1,
                data: &data[..n],
            }
        }),
    ]
}

fn sample_info() -> impl Strategy<Value = SampleInfo> {
    let detail = prop_oneof![
        Just(SampleInfoDetail::Empty),
        any::<u32>().prop_map(SampleInfoDetail::SequenceNumber),
        any::<u32>().prop_map(SampleInfoDetail::SessionTimeOffset),
        (any::<u32>(), any::<u32>()).prop_map(|(s, t)| SampleInfoDetail::Both {
            sequence_number: s,
            session_time_offset: t
        }),
    ];
    (any::<u8>(), detail).prop_map(|(state, detail)| SampleInfo { state, detail })
}

fn endpoint_binary() -> impl Strategy<Value = (EndpointBinary, bool)> {
    let qos = (
        any::<u16>(),
        proptest::option::of(any::<u16>()),
        proptest::option::of(any::<u32>()),
        proptest::option::of(any::<u32>()),
        proptest::option::of(bytes(16)),
        proptest::option::of(any::<u64>()),
        proptest::option::of(any::<u64>()),
        proptest::option::of(name()),
    );
    (object_id(), proptest::option::of(qos), any::<bool>()).prop_map(|(topic_id, qos, writer)| {
        let qos = qos.map(
            |(flags, depth, deadline, lifespan, user, strength, tbf, filter)| EndpointBinaryQos {
                base: EndpointQosBinary {
                    flags,
                    history_depth: depth,
                    deadline_msec: deadline,
                    lifespan_msec: lifespan,
                    user_data: user,
                },
                ownership_strength: if writer { strength } else { None },
                timebasedfilter_msec: if writer { None } else { tbf },
                contentbased_filter: if writer { None } else { filter },
            },
        );
        (EndpointBinary { topic_id, qos }, writer)
    })
}

static DATA: [u8; 96] = {
    let mut d = [0u8; 96];
    let mut i = 0;
    while i < 96 {
        d[i] = (i * 37 + 11) as u8;
        i += 1;
    }
    d
};

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn every_payload_round_trips_in_both_byte_orders(p in payload(&DATA), le in any::<bool>()) {
        let mut b = MessageBuilder::new(MessageHeader::new(0x81, 0x80, 7, ClientKey::INVALID));
        b.push(&p, le).expect("encodes");
        let bytes = b.finish();
        let m = Message::decode(&bytes).expect("decodes");
        prop_assert_eq!(m.submessages.len(), 1);
        prop_assert_eq!(&m.submessages[0].payload, &p);
        prop_assert_eq!(m.submessages[0].little_endian, le);
        prop_assert_eq!(m.encode().expect("re-encodes"), bytes);
    }

    #[test]
    fn sample_infos_round_trip_in_both_dialects(info in sample_info(), le in any::<bool>()) {
        for dialect in [Dialect::Spec, Dialect::Eprosima] {
            let mut out = Vec::new();
            info.encode(&mut CdrWriter::new(&mut out, le), dialect);
            let back = SampleInfo::decode(&mut CdrReader::new(&out, le), dialect);
            prop_assert_eq!(back, Ok(info));
        }
    }

    #[test]
    fn binary_representations_round_trip(
        participant in (proptest::option::of(name()), proptest::option::of(name())),
        topic in (name(), proptest::option::of(name()), proptest::option::of(name())),
        group in (proptest::option::of(name()), proptest::option::of((
            proptest::option::of(proptest::collection::vec(name(), 0..4)),
            proptest::option::of(bytes(16)),
        ))),
        (endpoint, writer) in endpoint_binary(),
        le in any::<bool>(),
    ) {
        let p = ParticipantBinary { domain_reference: participant.0, qos_profile_reference: participant.1 };
        prop_assert_eq!(ParticipantBinary::decode(&p.encode(le), le), Ok(p));
        let t = TopicBinary { topic_name: topic.0, type_reference: topic.1, type_name: topic.2 };
        prop_assert_eq!(TopicBinary::decode(&t.encode(le), le), Ok(t));
        let g = GroupBinary {
            name: group.0,
            qos: group.1.map(|(partitions, group_data)| GroupQosBinary { partitions, group_data }),
        };
        prop_assert_eq!(GroupBinary::decode(&g.encode(le), le), Ok(g));
        prop_assert_eq!(EndpointBinary::decode(&endpoint.encode(writer, le), writer, le), Ok(endpoint));
    }
}

#[test]
fn captured_binary_bodies_decode_to_their_values() {
    // From binary-creation.txt (the real eProsima client).
    let unhex = |s: &str| -> Vec<u8> {
        let s: String = s.split_whitespace().collect();
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
            .collect()
    };
    let topic =
        unhex("0d000000 4578616d706c65546f70696300 00 01 00 0c000000 4578616d706c655479706500");
    let t = TopicBinary::decode(&topic, true).expect("topic");
    assert_eq!(t.topic_name, "ExampleTopic");
    assert_eq!(t.type_name.as_deref(), Some("ExampleType"));
    assert_eq!(t.encode(true), topic, "re-encodes byte for byte");
    let writer = unhex("0012 01 00 0b00 00 00 00 00 00");
    let w = EndpointBinary::decode(&writer, true, true).expect("writer");
    assert_eq!(w.topic_id, ObjectId([0x00, 0x12]));
    let q = w.qos.clone().expect("qos");
    assert_eq!(
        q.base.flags,
        qos_flags::RELIABLE | qos_flags::HISTORY_KEEP_LAST | qos_flags::DURABILITY_TRANSIENT_LOCAL
    );
    assert_eq!(w.encode(true, true), writer);
}

fn object_info() -> impl Strategy<Value = xrce_common::wire::info::ObjectInfo> {
    use xrce_common::wire::info::*;
    let locator = prop_oneof![
        (any::<[u8; 2]>(), any::<u8>())
            .prop_map(|(address, port)| TransportLocator::Small { address, port }),
        (any::<[u8; 4]>(), any::<u16>())
            .prop_map(|(address, port)| TransportLocator::Medium { address, port }),
        (any::<[u8; 16]>(), any::<u32>())
            .prop_map(|(address, port)| TransportLocator::Large { address, port }),
        name().prop_map(TransportLocator::String),
    ];
    let activity = prop_oneof![
        (any::<i16>(), proptest::collection::vec(locator, 0..4)).prop_map(
            |(availability, locators)| ActivityInfo::Agent {
                availability,
                locators
            }
        ),
        (any::<u64>(), any::<i16>()).prop_map(|(sample_seq_num, stream_seq_num)| {
            ActivityInfo::DataWriter {
                sample_seq_num,
                stream_seq_num,
            }
        }),
        any::<i16>().prop_map(|highest_acked_num| ActivityInfo::DataReader { highest_acked_num }),
    ];
    let config = prop_oneof![
        (any::<[u8; 2]>(), any::<[u8; 2]>(), properties()).prop_map(
            |(version, vendor_id, properties)| {
                ObjectConfig::Agent(AgentRepresentation {
                    cookie: XRCE_COOKIE,
                    version,
                    vendor_id,
                    properties,
                })
            }
        ),
        variant().prop_map(ObjectConfig::Object),
    ];
    (proptest::option::of(activity), proptest::option::of(config))
        .prop_map(|(activity, config)| ObjectInfo { activity, config })
}

proptest! {
    #[test]
    fn object_infos_round_trip_in_both_dialects_and_byte_orders(
        info in object_info(),
        le in any::<bool>(),
        lead in 0usize..8,
    ) {
        for dialect in [Dialect::Spec, Dialect::Eprosima] {
            // Preceded by `lead` bytes, as the 6-byte reply precedes it in INFO.
            let mut out = Vec::new();
            {
                let w = &mut CdrWriter::new(&mut out, le);
                w.bytes(&vec![0u8; lead]);
                info.encode(w, dialect);
            }
            let full = out;
            let r = &mut CdrReader::new(&full, le);
            r.take(lead).expect("lead");
            let back = xrce_common::wire::info::ObjectInfo::decode(r, dialect);
            prop_assert_eq!(back, Ok(info.clone()));
        }
    }
}
