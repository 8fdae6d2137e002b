//! DataFormats end to end with Cyclone DDS: a READ_DATA asking for SAMPLE_SEQ gets each
//! Cyclone sample wrapped with a SampleInfo (numbered per read), and WRITE_DATA in
//! FORMAT_SAMPLE is unwrapped and published.

use std::collections::BTreeSet;
use std::time::Duration;

use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::sample::{decode_samples, SampleInfo, SampleInfoDetail};
use xrce_common::wire::{data_format, stream_id, DataDeliveryControl, Dialect, ReadSpecification};
use xrce_tests::{hello_world, parse_hello_world, AgentProcess, DdsPeer, Deliveries, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn a_read_asking_for_sample_seq_gets_numbered_sample_infos() {
    read_in_format(data_format::SAMPLE_SEQ, 20, 1);
}

/// PACKED_SAMPLES: the SampleInfo is the base the (here absent) deltas would refer to.
#[test]
fn a_read_asking_for_packed_samples_gets_numbered_sample_infos() {
    read_in_format(data_format::PACKED_SAMPLES, 69, 2);
}

/// FORMAT_SAMPLE: one SampleInfo and its sample per DATA.
#[test]
fn a_read_asking_for_sample_gets_numbered_sample_infos() {
    read_in_format(data_format::SAMPLE, 23, 3);
}

/// Cyclone writes five samples; a read in `format` gets each once, in its own DATA, with a
/// SampleInfo numbering it within the read.
fn read_in_format(format: u8, domain: i16, key: u8) {
    let agent = AgentProcess::builder(&format!("fmtsub{format}")).start();
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x4D, 0x00, key]);
    c.connect(10 * SECOND);
    let domain_arg = domain.to_string();
    c.setup_subscriber_with(
        domain,
        ReadSpecification {
            preferred_stream_id: stream_id::BUILTIN_RELIABLE,
            data_format: format,
            delivery_control: Some(DataDeliveryControl {
                max_samples: u16::MAX,
                ..Default::default()
            }),
            ..Default::default()
        },
    );
    let mut writer = DdsPeer::start(&[
        "write",
        "--domain",
        &domain_arg,
        "--count",
        "5",
        "--interval-ms",
        "20",
        "--message",
        "wrapped",
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "3000",
    ]);
    let mut got = Vec::new();
    let mut data = Vec::new();
    let deliveries = Deliveries::collect(5, 60 * SECOND, || {
        c.step();
        let new = c.take_data();
        let indexes = new
            .iter()
            .filter_map(|(f, bytes)| {
                let s = decode_samples(*f, bytes, true, Dialect::Eprosima, None).ok()?;
                parse_hello_world(s.first()?.data).map(|(i, _)| i)
            })
            .collect();
        data.extend(new);
        indexes
    });
    got.extend(data);
    let what = format!("a read in format {format:#x} of Cyclone's samples");
    deliveries.assert_exactly_once(0..5, &what);
    deliveries.assert_in_order(&what);
    let mut seqs = BTreeSet::new();
    let mut indexes = BTreeSet::new();
    for (got_format, bytes) in &got {
        assert_eq!(*got_format, format);
        let samples = decode_samples(format, bytes, true, Dialect::Eprosima, None)
            .expect("samples the eProsima dialect reads");
        assert_eq!(samples.len(), 1);
        let info = samples[0].info.expect("SampleInfo");
        assert_eq!(info.state, 0, "alive");
        let SampleInfoDetail::Both {
            sequence_number, ..
        } = info.detail
        else {
            panic!("detail {:?}", info.detail)
        };
        seqs.insert(sequence_number);
        let (i, m) = parse_hello_world(samples[0].data).expect("HelloWorld");
        assert_eq!(m, "wrapped");
        indexes.insert(i);
    }
    assert_eq!(
        seqs,
        (1..=5).collect(),
        "one SampleInfo number per sample of the read"
    );
    assert_eq!(indexes, (0..5).collect());
    assert_eq!(writer.wait(30 * SECOND, || c.step()), Some(0));
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn write_data_in_format_sample_is_published() {
    let agent = AgentProcess::builder("fmtpub").start();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "21",
        "--count",
        "5",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x4D, 0x00, 0x02]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(21);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the agent's writer"
    );
    for i in 0..5u32 {
        let mut body = Vec::new();
        SampleInfo {
            state: 0,
            detail: SampleInfoDetail::SequenceNumber(i),
        }
        .encode(&mut CdrWriter::new(&mut body, true), Dialect::Eprosima);
        body.extend_from_slice(&hello_world(i, "sampled"));
        c.write_reliable_format(w, data_format::SAMPLE, &body);
    }
    let got = reader.collect_deliveries(5, "sampled", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..5, "WRITE_DATA in FORMAT_SAMPLE");
    got.assert_in_order("WRITE_DATA in FORMAT_SAMPLE");
    assert!(agent.stop(), "agent did not stop cleanly");
}
