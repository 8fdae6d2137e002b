//! Keyed topics and content filters end to end with Cyclone DDS.
//!
//! The type comes from a TYPE object (DDS-XML `<types>`) the client creates; with it the
//! worker extracts the key of every sample (KeyHash per XTypes), keeps a history per
//! instance, publishes disposes, delivers Cyclone's disposes with their SampleInfo state, and
//! evaluates content filters on samples.

use std::collections::BTreeMap;
use std::time::Duration;

use xrce_common::session::client::ClientEvent;
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::sample::{
    decode_samples, encode_samples, sample_state, SampleInfo, SampleInfoDetail, SampleRef,
};
use xrce_common::wire::{
    data_format, object_kind, status, stream_id, DataDeliveryControl, Dialect, ObjectId,
    ReadSpecification, VariantExtra,
};
use xrce_tests::{AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

const TYPES: &str = r#"<dds><types><module name="ShapesDemoTypes">
  <struct name="ShapeType">
    <member name="color" key="true" type="string" stringMaxLength="128"/>
    <member name="x" type="int32"/>
    <member name="y" type="int32"/>
    <member name="shapesize" type="int32"/>
  </struct></module></types></dds>"#;

/// A ShapeType sample, XCDR1 little endian.
fn shape(color: &str, x: i32) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend((color.len() as u32 + 1).to_le_bytes());
    b.extend(color.as_bytes());
    b.push(0);
    while b.len() % 4 != 0 {
        b.push(0);
    }
    for v in [x, 2 * x, 30] {
        b.extend(v.to_le_bytes());
    }
    b
}

/// Decodes a ShapeType sample or key payload: (color, x if present).
fn parse_shape(b: &[u8]) -> Option<(String, Option<i32>)> {
    let n = u32::from_le_bytes(b.get(..4)?.try_into().ok()?) as usize;
    let color = std::str::from_utf8(b.get(4..4 + n.checked_sub(1)?)?).ok()?;
    let at = (4 + n).div_ceil(4) * 4;
    let x = b
        .get(at..at + 4)
        .map(|v| i32::from_le_bytes(v.try_into().unwrap_or_default()));
    Some((color.to_string(), x))
}

/// `{"color": "RED", "x": 3, "state": "alive"}` from dds_peer.py read --keyed.
fn parse_keyed_line(l: &str) -> Option<(String, Option<i64>, String)> {
    let v: serde_json::Value = serde_json::from_str(l).ok()?;
    Some((
        v["color"].as_str()?.to_string(),
        v["x"].as_i64(),
        v["state"].as_str()?.to_string(),
    ))
}

/// Participant, TYPE, topic "Square" and the group in `domain`; returns the participant.
fn setup(c: &mut TestClient, domain: i16, group: u8) -> ObjectId {
    let p = ObjectId::new(1, object_kind::PARTICIPANT);
    let participant = "<dds><participant><rtps><name>keyed</name></rtps></participant></dds>";
    assert_eq!(
        c.create(
            p,
            object_kind::PARTICIPANT,
            participant,
            VariantExtra::DomainId(domain)
        ),
        status::OK
    );
    let ty = ObjectId::new(1, object_kind::TYPE);
    assert_eq!(
        c.create(ty, object_kind::TYPE, TYPES, VariantExtra::None),
        status::OK,
        "TYPE object"
    );
    let topic = "<dds><topic><kind>WITH_KEY</kind><name>Square</name><dataType>ShapesDemoTypes::ShapeType</dataType></topic></dds>";
    let t = ObjectId::new(1, object_kind::TOPIC);
    assert_eq!(
        c.create(t, object_kind::TOPIC, topic, VariantExtra::Parent(p)),
        status::OK
    );
    let g = ObjectId::new(1, group);
    assert_eq!(c.create(g, group, "", VariantExtra::Parent(p)), status::OK);
    p
}

/// An agent, a connected client (key `F04E00nn`), and its keyed writer or reader with `qos`
/// in `domain` (after [`setup`]).
fn keyed_endpoint(
    tag: &str,
    client: u8,
    domain: i16,
    endpoint: u8,
    qos: &str,
) -> (AgentProcess, TestClient, ObjectId) {
    let agent = AgentProcess::builder(tag).start();
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x4E, 0x00, client]);
    c.connect(10 * SECOND);
    let (group, element) = if endpoint == object_kind::DATAWRITER {
        (object_kind::PUBLISHER, "data_writer")
    } else {
        (object_kind::SUBSCRIBER, "data_reader")
    };
    setup(&mut c, domain, group);
    let id = ObjectId::new(1, endpoint);
    let parent = VariantExtra::Parent(ObjectId::new(1, group));
    let xml = endpoint_xml(element, qos);
    assert_eq!(
        c.create(id, endpoint, &xml, parent),
        status::OK,
        "{element}"
    );
    (agent, c, id)
}

fn endpoint_xml(element: &str, qos: &str) -> String {
    format!(
        "<dds><{element}><topic><kind>WITH_KEY</kind><name>Square</name>\
         <dataType>ShapesDemoTypes::ShapeType</dataType></topic><qos>{qos}</qos></{element}></dds>"
    )
}

fn sample_with_state(state: u8, data: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    SampleInfo {
        state,
        detail: SampleInfoDetail::SequenceNumber(0),
    }
    .encode(&mut CdrWriter::new(&mut body, true), Dialect::Eprosima);
    body.extend_from_slice(data);
    body
}

#[test]
fn a_keyed_writer_publishes_instances_and_disposes_them() {
    let (agent, mut c, w) = keyed_endpoint(
        "keyedpub",
        1,
        40,
        object_kind::DATAWRITER,
        "<reliability><kind>RELIABLE</kind></reliability>\
         <durability><kind>TRANSIENT_LOCAL</kind></durability>\
         <history><kind>KEEP_LAST</kind><depth>1</depth></history>",
    );
    // Three rounds over three instances.
    for round in 0..3 {
        for (i, color) in ["RED", "GREEN", "BLUE"].iter().enumerate() {
            c.write_reliable(w, &shape(color, round * 10 + i as i32));
        }
    }
    // A sequence of two samples in one WRITE_DATA: the worker splits it with the type.
    let mut seq = 2u32.to_le_bytes().to_vec();
    seq.extend(shape("RED", 30));
    seq.extend(shape("BLUE", 32));
    c.write_reliable_format(w, data_format::DATA_SEQ, &seq);
    // GREEN is disposed by a WRITE_DATA whose SampleInfo says so.
    c.write_reliable_format(
        w,
        data_format::SAMPLE,
        &sample_with_state(sample_state::INSTANCE_DISPOSED, &shape("GREEN", 0)),
    );
    assert!(
        c.run_until(10 * SECOND, |c| c
            .client
            .unacked(stream_id::BUILTIN_RELIABLE)
            == 0),
        "the agent did not take every write"
    );
    // A late joiner with KEEP_LAST 1 per instance gets the writer's history and ends with
    // the last value of each live instance (from the sequence) and GREEN disposed: distinct instances, so the
    // keys were extracted and the dispose carried GREEN's key. (RustDDS keeps a writer's
    // history per writer, not per instance, so superseded samples may arrive first.)
    let reader = DdsPeer::start(&[
        "read",
        "--keyed",
        "--topic",
        "Square",
        "--domain",
        "40",
        "--count",
        "100",
        "--history",
        "1",
        "--reliable",
        "--transient-local",
        "--timeout",
        "40",
    ]);
    // Everything each instance showed, in order.
    let mut seen: BTreeMap<String, Vec<(Option<i64>, String)>> = BTreeMap::new();
    let mut lines = Vec::new();
    let want = |seen: &BTreeMap<String, Vec<(Option<i64>, String)>>| {
        let last = |k: &str| seen.get(k).and_then(|v| v.last());
        last("RED") == Some(&(Some(30), "alive".to_string()))
            && last("BLUE") == Some(&(Some(32), "alive".to_string()))
            && last("GREEN").is_some_and(|(_, st)| st == "disposed")
    };
    // Until the last values arrived, then a while longer, so that a sample delivered twice
    // shows.
    let end = std::time::Instant::now() + 45 * SECOND;
    let mut complete_at: Option<std::time::Instant> = None;
    while std::time::Instant::now() < end
        && complete_at.is_none_or(|t| t.elapsed() < xrce_tests::DUPLICATE_GRACE)
    {
        while let Some(l) = reader.line(Duration::from_millis(1)) {
            lines.push(l.clone());
            if let Some((color, x, state)) = parse_keyed_line(&l) {
                seen.entry(color).or_default().push((x, state));
            }
        }
        c.step();
        if complete_at.is_none() && want(&seen) {
            complete_at = Some(std::time::Instant::now());
        }
    }
    assert!(want(&seen), "late joiner saw {lines:?}");
    // Each instance's values in the order written, none twice. (Superseded values may come
    // first: RustDDS keeps its history per writer, not per instance, and with Cyclone DDS
    // the late joiner was seen to get RED 0 before RED 30 once, a second sample of an
    // instance under KEEP_LAST 1, not explained yet.)
    for (color, values) in &seen {
        let xs: Vec<i64> = values
            .iter()
            .filter_map(|(x, st)| x.filter(|_| st == "alive"))
            .collect();
        assert!(
            xs.windows(2).all(|w| w[0] < w[1]),
            "{color}: values out of order or repeated: {values:?}"
        );
        let disposals = values.iter().filter(|(_, st)| st == "disposed").count();
        assert!(
            disposals <= 1
                && values.iter().skip_while(|(_, st)| st != "disposed").count() == disposals,
            "{color}: disposed more than once, or alive after its dispose: {values:?}"
        );
    }
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn cyclone_disposes_reach_a_sample_read_and_filters_select_samples() {
    // A history deep enough that no sample is replaced before the read takes it (KEEP_LAST
    // 1 would make BLUE 8 depend on the worker reading within the 30 ms before BLUE 11).
    let (agent, mut c, r) = keyed_endpoint(
        "keyedsub",
        2,
        41,
        object_kind::DATAREADER,
        "<reliability><kind>RELIABLE</kind></reliability>\
         <historyQos><kind>KEEP_LAST</kind><depth>16</depth></historyQos>",
    );
    // A malformed filter is refused with INVALID_DATA.
    let read = |filter: &str| ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        data_format: data_format::SAMPLE,
        content_filter_expression: Some(filter.to_string()),
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    let bad = c
        .client
        .read(std::time::Instant::now(), r, read("x >> 3"))
        .expect("read");
    assert_eq!(c.wait_status(bad, 10 * SECOND), status::ERR_INVALID_DATA);
    let good = c
        .client
        .read(
            std::time::Instant::now(),
            r,
            read("(color = 'RED' OR color LIKE 'BL%') AND x >= 6"),
        )
        .expect("read");
    let mut writer = DdsPeer::start(&[
        "write",
        "--keyed",
        "--topic",
        "Square",
        "--domain",
        "41",
        "--count",
        "12",
        "--interval-ms",
        "10",
        "--dispose",
        "BLUE",
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "3000",
    ]);
    // x = 0..11 round robin RED, GREEN, BLUE: RED 6, 9; BLUE 8, 11; then BLUE's dispose.
    let mut got = Vec::new();
    let take = |c: &mut TestClient, got: &mut Vec<_>| {
        for (format, bytes) in c.take_data() {
            assert_eq!(format, data_format::SAMPLE);
            let s = decode_samples(format, &bytes, true, Dialect::Eprosima, None).expect("SAMPLE");
            let state = s[0].info.map(|i| i.state).unwrap_or(0xFF);
            got.push((parse_shape(s[0].data).expect("ShapeType"), state));
        }
    };
    let ok = c.run_until(60 * SECOND, |c| {
        take(c, &mut got);
        got.len() >= 5
    });
    assert!(ok, "client got {got:?}");
    // A repeated or an extra sample would show within the grace.
    c.run_until(xrce_tests::DUPLICATE_GRACE, |c| {
        take(c, &mut got);
        false
    });
    // The valid filter's read was accepted: answered with DATA and no error STATUS (a read
    // that succeeds gets no STATUS, as from the reference agent).
    let refused: Vec<_> = c
        .events
        .iter()
        .filter(|e| {
            matches!(e, ClientEvent::Status(st)
                if st.related.request_id == good && st.result.status != status::OK)
        })
        .collect();
    assert!(
        refused.is_empty(),
        "the valid filter's read was refused: {refused:?}"
    );
    let alive: Vec<(String, i32)> = got
        .iter()
        .filter(|(_, st)| *st == 0)
        .map(|((c, x), _)| (c.clone(), x.unwrap_or(-1)))
        .collect();
    assert_eq!(
        alive,
        vec![
            ("RED".to_string(), 6),
            ("BLUE".to_string(), 8),
            ("RED".to_string(), 9),
            ("BLUE".to_string(), 11)
        ],
        "exactly the samples the filter selects, in order: {got:?}"
    );
    let ends: Vec<_> = got.iter().filter(|(_, st)| *st != 0).collect();
    assert_eq!(ends.len(), 1, "{got:?}");
    assert_eq!(ends[0].0 .0, "BLUE", "the disposed instance's key");
    assert_eq!(ends[0].1, sample_state::INSTANCE_DISPOSED);
    assert_eq!(writer.wait(30 * SECOND, || c.step()), Some(0));
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_filter_on_a_topic_of_unknown_type_is_refused() {
    let agent = AgentProcess::builder("keyednotype").start();
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x4E, 0x00, 0x03]);
    c.connect(10 * SECOND);
    let r = c.setup_subscriber_with(
        42,
        ReadSpecification {
            preferred_stream_id: stream_id::BUILTIN_RELIABLE,
            data_format: data_format::DATA,
            delivery_control: Some(DataDeliveryControl {
                max_samples: 1,
                ..Default::default()
            }),
            ..Default::default()
        },
    );
    let req = c
        .client
        .read(
            std::time::Instant::now(),
            r,
            ReadSpecification {
                preferred_stream_id: stream_id::BUILTIN_RELIABLE,
                data_format: data_format::DATA,
                content_filter_expression: Some("index > 3".into()),
                ..Default::default()
            },
        )
        .expect("read");
    assert_eq!(c.wait_status(req, 10 * SECOND), status::ERR_INCOMPATIBLE);
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_keep_last_reader_keeps_one_sample_per_instance() {
    let (agent, mut c, r) = keyed_endpoint(
        "keyedhist",
        4,
        43,
        object_kind::DATAREADER,
        "<reliability><kind>RELIABLE</kind></reliability>\
         <history><kind>KEEP_LAST</kind><depth>1</depth></history>",
    );
    // Twelve samples over three instances arrive while no read is active; they wait in
    // the DDS reader, whose KEEP_LAST 1 applies per instance (by the key the worker
    // extracts).
    let mut writer = DdsPeer::start(&[
        "write",
        "--keyed",
        "--topic",
        "Square",
        "--domain",
        "43",
        "--count",
        "12",
        "--interval-ms",
        "5",
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "4000",
    ]);
    // Every sample in the agent's DDS reader before the read starts.
    assert!(
        writer.wait_for("ACKED", 60 * SECOND, || c.step()).is_some(),
        "Cyclone's samples were not acknowledged by the agent's reader"
    );
    c.read_unlimited(r);
    let mut got = Vec::new();
    let mut complete: Option<std::time::Instant> = None;
    let end = std::time::Instant::now() + 30 * SECOND;
    while std::time::Instant::now() < end
        && complete.is_none_or(|t| t.elapsed() < xrce_tests::DUPLICATE_GRACE)
    {
        c.step();
        got.extend(c.take_data());
        if complete.is_none() && got.len() >= 3 {
            complete = Some(std::time::Instant::now());
        }
    }
    let mut shapes: Vec<(String, i32)> = got
        .iter()
        .map(|(_, b)| {
            let (color, x) = parse_shape(b).expect("ShapeType");
            (color, x.unwrap_or(-1))
        })
        .collect();
    shapes.sort();
    assert_eq!(
        shapes,
        vec![
            ("BLUE".to_string(), 11),
            ("GREEN".to_string(), 10),
            ("RED".to_string(), 9)
        ],
        "the last sample of each instance"
    );
    assert_eq!(writer.wait(30 * SECOND, || c.step()), Some(0));
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// PACKED_SAMPLES with SampleInfoDeltas, as a client writes several samples under one
/// SampleInfo: the worker splits them with the type and publishes each once, in order.
#[test]
fn a_packed_write_with_deltas_publishes_each_sample() {
    let (agent, mut c, w) = keyed_endpoint(
        "keyedpacked",
        5,
        76,
        object_kind::DATAWRITER,
        "<reliability><kind>RELIABLE</kind></reliability>",
    );
    let reader = DdsPeer::start(&[
        "read",
        "--keyed",
        "--topic",
        "Square",
        "--domain",
        "76",
        "--count",
        "3",
        "--reliable",
        "--timeout",
        "40",
    ]);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the keyed writer"
    );
    let samples = [shape("RED", 50), shape("GREEN", 51), shape("BLUE", 52)];
    let refs: Vec<SampleRef<'_>> = samples
        .iter()
        .zip(1u32..)
        .map(|(data, n)| SampleRef {
            info: Some(SampleInfo {
                state: 0,
                detail: SampleInfoDetail::Both {
                    sequence_number: n,
                    session_time_offset: 100 * n,
                },
            }),
            data: data.as_slice(),
        })
        .collect();
    let mut packed = Vec::new();
    encode_samples(
        data_format::PACKED_SAMPLES,
        &refs,
        true,
        Dialect::Eprosima,
        &mut packed,
    )
    .expect("packed samples");
    c.write_reliable_format(w, data_format::PACKED_SAMPLES, &packed);
    let mut seen = Vec::new();
    let end = std::time::Instant::now() + 30 * SECOND;
    let mut complete_at: Option<std::time::Instant> = None;
    while std::time::Instant::now() < end
        && complete_at.is_none_or(|t| t.elapsed() < xrce_tests::DUPLICATE_GRACE)
    {
        while let Some(l) = reader.line(Duration::from_millis(1)) {
            if let Some((color, x, state)) = parse_keyed_line(&l) {
                seen.push((color, x, state));
            }
        }
        c.step();
        if complete_at.is_none() && seen.len() >= 3 {
            complete_at = Some(std::time::Instant::now());
        }
    }
    let want: Vec<(String, Option<i64>, String)> = [("RED", 50), ("GREEN", 51), ("BLUE", 52)]
        .iter()
        .map(|(c, x)| (c.to_string(), Some(*x), "alive".to_string()))
        .collect();
    assert_eq!(seen, want, "what Cyclone read of one PACKED_SAMPLES write");
    assert!(agent.stop(), "agent did not stop cleanly");
}
