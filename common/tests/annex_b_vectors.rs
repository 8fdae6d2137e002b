//! The corrected Annex B examples (spec digest §11) and the derived vectors decode to the
//! values the spec describes and re-encode to the same bytes.

use xrce_common::wire::*;

fn unhex(s: &str) -> Vec<u8> {
    let s: String = s.split_whitespace().collect();
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
        .collect()
}

fn round_trip(hex: &str) -> Message<'static> {
    let bytes: &'static [u8] = Box::leak(unhex(hex).into_boxed_slice());
    let m = Message::decode(bytes).expect("decode");
    assert_eq!(m.encode().expect("encode"), bytes, "re-encoding differs");
    m
}

fn only(m: &Message<'static>) -> Payload<'static> {
    assert_eq!(m.submessages.len(), 1);
    m.submessages[0].payload.clone()
}

#[test]
fn b1_create_client() {
    let m = round_trip("80 00 00 00 00 01 0E 00 58 52 43 45 01 00 0F 0F 22 33 44 55 DD 00");
    let Payload::CreateClient(c) = only(&m) else {
        panic!()
    };
    assert_eq!(c.client_key, ClientKey([0x22, 0x33, 0x44, 0x55]));
    assert_eq!(
        (c.session_id, c.vendor_id, c.mtu, c.properties),
        (0xDD, [0x0F, 0x0F], None, None)
    );
    assert_eq!(m.header.client_key, None);
}

#[test]
fn b2_1_create_participant_by_reference() {
    let m = round_trip(
        "81 80 07 00 01 07 28 00 AA 01 DD D1 01 01 00 00 19 00 00 00 4D 79 4C 69 62 72 61 72 79 3A 3A 4D
         79 50 61 72 74 69 63 69 70 61 6E 74 00 00 00 00",
    );
    assert_eq!(
        (
            m.header.session_id,
            m.header.stream_id,
            m.header.sequence_nr
        ),
        (0x81, 0x80, 7)
    );
    let Payload::Create(c) = only(&m) else {
        panic!()
    };
    assert!(c.reuse && c.replace);
    assert_eq!(c.base.request_id, RequestId([0xAA, 0x01]));
    assert_eq!(c.base.object_id.kind(), object_kind::PARTICIPANT);
    assert_eq!(
        c.variant.representation,
        Representation::Reference("MyLibrary::MyParticipant".into())
    );
    assert_eq!(c.variant.extra, VariantExtra::DomainId(0));
}

#[test]
fn b2_5_create_datawriter_xml() {
    let m = round_trip(
        "81 80 07 00 01 07 C3 00 AA 01 DD D5 05 02 00 00 B5 00 00 00 3C 64 61 74 61 5F 77 72 69 74 65 72
         20 6E 61 6D 65 3D 22 4D 79 57 72 69 74 65 72 22 20 74 6F 70 69 63 5F 72 65 66 3D 22 53 71 75 61
         72 65 22 3E 3C 64 61 74 61 5F 77 72 69 74 65 72 5F 71 6F 73 20 62 61 73 65 5F 6E 61 6D 65 3D 22
         4D 79 51 6F 73 4C 69 62 3A 4D 79 50 72 6F 66 69 6C 65 22 3E 3C 64 65 61 64 6C 69 6E 65 3E 3C 70
         65 72 69 6F 64 3E 3C 73 65 63 3E 31 32 30 3C 2F 73 65 63 3E 3C 2F 70 65 72 69 6F 64 3E 3C 2F 64
         65 61 64 6C 69 6E 65 3E 3C 2F 64 61 74 61 5F 77 72 69 74 65 72 5F 71 6F 73 3E 3C 2F 64 61 74 61
         5F 77 72 69 74 65 72 3E 00 BB B3",
    );
    let Payload::Create(c) = only(&m) else {
        panic!()
    };
    assert_eq!(c.variant.kind, object_kind::DATAWRITER);
    assert_eq!(c.variant.parent(), Some(ObjectId([0xBB, 0xB3])));
    let Representation::Xml(x) = &c.variant.representation else {
        panic!()
    };
    assert_eq!(x.len(), 180);
    assert!(x.starts_with("<data_writer name=\"MyWriter\""));
}

#[test]
fn b3_1_write_data_format_data() {
    let m = round_trip("DD 80 01 00 07 01 06 00 AA 01 44 05 19 00");
    let Payload::WriteData(d) = only(&m) else {
        panic!()
    };
    assert_eq!(
        (d.format, d.data, d.base.object_id),
        (
            data_format::DATA,
            &[0x19u8, 0x00][..],
            ObjectId([0x44, 0x05])
        )
    );
}

#[test]
fn b3_2_to_b3_4_write_data_other_formats_keep_their_bytes() {
    let m = round_trip("DD 80 01 00 07 09 10 00 AA 01 44 05 04 00 00 00 14 00 11 00 1A 00 28 00");
    let Payload::WriteData(d) = only(&m) else {
        panic!()
    };
    assert_eq!(d.format, data_format::DATA_SEQ);
    assert_eq!(d.data.len(), 12);
    let m = round_trip("DD 80 01 00 07 03 0E 00 AA 01 44 05 00 02 00 00 E8 03 00 00 19 00");
    let Payload::WriteData(d) = only(&m) else {
        panic!()
    };
    assert_eq!(d.format, data_format::SAMPLE);
    let m = round_trip("DD 80 01 00 07 03 0C 00 AA 01 44 05 02 00 11 22 33 64 19 00");
    let Payload::WriteData(d) = only(&m) else {
        panic!()
    };
    assert_eq!(d.data[0], 0x02, "disposed state");
}

#[test]
fn b4_1_read_data_single() {
    let m = round_trip("DD 80 01 00 08 01 08 00 AA 01 44 06 00 00 00 00");
    let Payload::ReadData(r) = only(&m) else {
        panic!()
    };
    assert_eq!(r.spec, ReadSpecification::default());
}

#[test]
fn b4_2_read_data_with_filter_and_delivery_control_both_forms() {
    let expect = DataDeliveryControl {
        max_samples: 100,
        max_elapsed_time: 30,
        max_bytes_per_second: 1024,
        min_pace_period: 1000,
    };
    let strict = round_trip(
        "DD 80 01 00 08 01 20 00 AA 01 44 06 00 08 01 00 06 00 00 00 78 3E 31 30 30 00 01 00 08 00 00 00
         64 00 1E 00 00 04 E8 03",
    );
    let Payload::ReadData(r) = only(&strict) else {
        panic!()
    };
    assert_eq!(r.spec.content_filter_expression.as_deref(), Some("x>100"));
    assert_eq!(r.spec.delivery_control, Some(expect));
    assert!(r.spec.delivery_control_dheader);
    let plain = round_trip(
        "DD 80 01 00 08 01 1C 00 AA 01 44 06 00 08 01 00 06 00 00 00 78 3E 31 30 30 00 01 00 64 00 1E 00
         00 04 E8 03",
    );
    let Payload::ReadData(r) = only(&plain) else {
        panic!()
    };
    assert_eq!(r.spec.data_format, data_format::DATA_SEQ);
    assert_eq!(r.spec.delivery_control, Some(expect));
    assert!(!r.spec.delivery_control_dheader);
}

#[test]
fn b5_1_data_big_endian() {
    let m = round_trip("DD 01 01 00 09 00 08 00 AA 01 44 06 00 00 00 13");
    assert!(!m.submessages[0].little_endian);
    let Payload::Data(d) = only(&m) else { panic!() };
    assert_eq!(d.data, &[0, 0, 0, 0x13]);
}

#[test]
fn acknack_heartbeat_and_derived_vectors() {
    let m = round_trip("DD 00 00 00 0A 01 05 00 64 00 40 09 80");
    assert_eq!(
        only(&m),
        Payload::Acknack(AcknackPayload {
            first_unacked_seq_num: 100,
            nack_bitmap: 0x4009,
            stream_id: 0x80
        })
    );
    let m = round_trip("DD 00 00 00 0B 01 05 00 05 00 09 00 80");
    assert_eq!(
        only(&m),
        Payload::Heartbeat(HeartbeatPayload {
            first_unacked_seq_num: 5,
            last_unacked_seq_num: 9,
            stream_id: 0x80
        })
    );
    let m = round_trip("81 80 00 00 05 01 06 00 AA 01 DD D5 00 00");
    assert!(matches!(only(&m), Payload::Status(s) if s.result == ResultStatus::OK));
    let m = round_trip("DD 00 00 00 04 01 09 00 58 52 43 45 01 00 01 0F 00");
    assert!(matches!(only(&m), Payload::StatusAgent(s) if s.result.is_none()));
    let m = round_trip("DD 00 00 00 04 01 0B 00 00 00 58 52 43 45 01 00 01 0F 00");
    assert!(matches!(only(&m), Payload::StatusAgent(s) if s.result == Some(ResultStatus::OK)));
    let m = round_trip("80 00 00 00 02 01 08 00 AA 02 FF FD 03 00 00 00");
    assert!(
        matches!(only(&m), Payload::GetInfo(g) if g.info_mask == 3 && g.base.object_id == ObjectId::AGENT)
    );
    let m = round_trip("DD 00 00 00 0E 01 08 00 8C AA 88 5A 00 65 CD 1D");
    assert_eq!(
        only(&m),
        Payload::Timestamp(Time {
            seconds: 1518905996,
            nanoseconds: 500000000
        })
    );
    let m = round_trip("DD 00 00 00 0C 01 00 00");
    assert_eq!(only(&m), Payload::Reset);
    let m = round_trip("DD 80 02 00 03 01 04 00 AA 05 FF FE");
    assert!(matches!(only(&m), Payload::Delete(d) if d.object_id == ObjectId::CLIENT));
}

#[test]
fn header_with_client_key() {
    let m = round_trip("01 80 00 00 AA BB CC DD 0C 01 00 00");
    assert_eq!(
        m.header.client_key,
        Some(ClientKey([0xAA, 0xBB, 0xCC, 0xDD]))
    );
}

#[test]
fn malformed_inputs_are_errors_not_panics() {
    for bad in [
        "",
        "81",
        "01 80 00 00 AA",
        "81 80 00 00 01 01 FF 00 00",
        "81 80 00 00 01 01 08 00 AA 01 DD D1 01 09 00 00",
    ] {
        assert!(Message::decode(&unhex(bad)).is_err(), "{bad}");
    }
}

/// Decodes the samples of a WRITE_DATA/DATA vector with a fixed-size type, checks them, and
/// re-encodes them to the same bytes.
fn samples_round_trip(hex: &str, type_size: usize) -> Vec<(Option<sample::SampleInfo>, Vec<u8>)> {
    let m = round_trip(hex);
    let (Payload::WriteData(d) | Payload::Data(d)) = only(&m) else {
        panic!("not a data submessage")
    };
    let le = m.submessages[0].little_endian;
    let sizer = move |b: &[u8], _: usize| (b.len() >= type_size).then_some(type_size);
    let samples = sample::decode_samples(d.format, d.data, le, Dialect::Spec, Some(&sizer))
        .expect("samples decode");
    let mut again = Vec::new();
    sample::encode_samples(d.format, &samples, le, Dialect::Spec, &mut again).expect("encode");
    assert_eq!(again, d.data, "samples re-encode differently");
    samples.iter().map(|s| (s.info, s.data.to_vec())).collect()
}

#[test]
fn b3_and_b5_sample_representations_decode_to_their_values() {
    use sample::{sample_state, SampleInfo, SampleInfoDetail};
    let alive = |detail| Some(SampleInfo { state: 0, detail });
    // B.3.2: four Temperature values.
    let s = samples_round_trip(
        "DD 80 01 00 07 09 10 00 AA 01 44 05 04 00 00 00 14 00 11 00 1A 00 28 00",
        2,
    );
    let values: Vec<i16> = s
        .iter()
        .map(|(_, d)| i16::from_le_bytes([d[0], d[1]]))
        .collect();
    assert_eq!(values, [20, 17, 26, 40]);
    // B.3.3: timestamped sample.
    let s = samples_round_trip(
        "DD 80 01 00 07 03 0E 00 AA 01 44 05 00 02 00 00 E8 03 00 00 19 00",
        2,
    );
    assert_eq!(
        s,
        [(
            alive(SampleInfoDetail::SessionTimeOffset(1000)),
            vec![0x19, 0]
        )]
    );
    // B.3.4: disposed instance, empty detail.
    let s = samples_round_trip(
        "DD 80 01 00 07 03 0C 00 AA 01 44 05 02 00 11 22 33 64 19 00",
        6,
    );
    assert_eq!(
        s[0].0.map(|i| i.state),
        Some(sample_state::INSTANCE_DISPOSED)
    );
    assert_eq!(s[0].1, [0x11, 0x22, 0x33, 0x64, 0x19, 0x00]);
    // B.5.2: two big-endian FooType samples.
    let s = samples_round_trip(
        "DD 01 01 00 09 08 10 00 AA 02 44 06 00 00 00 02 00 00 00 01 00 00 00 01",
        4,
    );
    assert_eq!(s.len(), 2);
    // B.5.3: one sample with sequence number and time.
    let both = |sequence_number, session_time_offset| {
        alive(SampleInfoDetail::Both {
            sequence_number,
            session_time_offset,
        })
    };
    let s = samples_round_trip(
        "DD 01 01 00 09 02 14 00 AA 02 44 06 00 03 00 00 00 00 00 01 00 00 03 E8 00 00 00 01",
        4,
    );
    assert_eq!(s, [(both(1, 1000), vec![0, 0, 0, 1])]);
    // B.5.4: two samples with infos.
    let s = samples_round_trip(
        "DD 01 01 00 09 0A 28 00 AA 02 44 06 00 00 00 02 00 03 00 00 00 00 00 01 00 00 03 E8 00 00 00 01
         00 03 00 00 00 00 00 02 00 00 04 4C 00 00 00 01",
        4,
    );
    assert_eq!(
        s.iter().map(|x| x.0).collect::<Vec<_>>(),
        [both(1, 1000), both(2, 1100)]
    );
    // B.5.5: packed: base (1, 1000 ms), deltas (0, 0) and (1, 1 decisecond).
    let s = samples_round_trip(
        "DD 80 01 00 09 0E 24 00 AA 03 44 06 00 03 00 00 00 00 00 01 00 00 03 E8 00 00 00 02 00 00 00 00
         00 00 00 01 00 01 00 01 00 00 00 01",
        4,
    );
    assert_eq!(
        s.iter().map(|x| x.0).collect::<Vec<_>>(),
        [both(1, 1000), both(2, 1100)]
    );
}
