//! DataDeliveryControl pacing with Cyclone DDS: `min_pace_period` spaces the DATA a client
//! gets, and `max_bytes_per_second` caps the sample bytes per second; the samples held back
//! wait in the DDS reader and all arrive.

use std::time::{Duration, Instant};

use xrce_common::wire::sample::{decode_samples, SampleInfo, SampleInfoDetail};
use xrce_common::wire::{
    data_format, object_kind, stream_id, DataDeliveryControl, Dialect, ReadSpecification,
};
use xrce_tests::{parse_hello_world, xml, AgentProcess, DdsPeer, Deliveries, TestClient};

const SECOND: Duration = Duration::from_secs(1);

/// Subscribes with `ddc` in FORMAT_SAMPLE, lets Cyclone write `count` samples of `message`
/// back to back, and returns when the agent sent each (its SampleInfo's session time offset,
/// in milliseconds: the agent's clock, which a busy test process cannot skew).
fn paced_sends(
    name: &str,
    domain: i16,
    ddc: DataDeliveryControl,
    count: u32,
    message: &str,
) -> Vec<u32> {
    let agent = AgentProcess::builder(name).start();
    let mut c = TestClient::new(agent.addr(), [0xDD, 0xC0, 0x00, domain as u8]);
    c.connect(10 * SECOND);
    c.setup_subscriber_with(
        domain,
        ReadSpecification {
            preferred_stream_id: stream_id::BUILTIN_RELIABLE,
            data_format: data_format::SAMPLE,
            delivery_control: Some(ddc),
            ..Default::default()
        },
    );
    let domain_arg = domain.to_string();
    let count_arg = count.to_string();
    let mut writer = DdsPeer::start(&[
        "write",
        "--domain",
        &domain_arg,
        "--count",
        &count_arg,
        "--interval-ms",
        "1",
        "--message",
        message,
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "8000",
    ]);
    let mut sent_at = Vec::new();
    let got = Deliveries::collect(count as usize, 60 * SECOND, || {
        c.step();
        c.take_data()
            .into_iter()
            .map(|(format, bytes)| {
                assert_eq!(format, data_format::SAMPLE);
                let samples = decode_samples(format, &bytes, true, Dialect::Eprosima, None)
                    .expect("a SAMPLE");
                assert_eq!(samples.len(), 1);
                let Some(SampleInfo {
                    detail:
                        SampleInfoDetail::Both {
                            session_time_offset,
                            ..
                        },
                    ..
                }) = samples[0].info
                else {
                    panic!("a SampleInfo with a time offset: {:?}", samples[0].info)
                };
                let (i, m) = parse_hello_world(samples[0].data).expect("a HelloWorld");
                assert_eq!(m, message);
                sent_at.push(session_time_offset);
                i
            })
            .collect()
    });
    got.assert_exactly_once(0..count, "paced samples");
    got.assert_in_order("paced samples");
    assert_eq!(writer.wait(30 * SECOND, || c.step()), Some(0));
    assert!(agent.stop(), "agent did not stop cleanly");
    sent_at
}

#[test]
fn min_pace_period_spaces_the_samples_and_loses_none() {
    let ddc = DataDeliveryControl {
        max_samples: u16::MAX,
        min_pace_period: 200,
        ..Default::default()
    };
    let t = paced_sends("pace", 26, ddc, 5, "paced");
    // On the agent's clock: the worker paces, the front-end stamps the offset (whole
    // milliseconds) when it queues the DATA, so a gap is 200 ms give or take how much longer
    // one sample than the next took between the two (50 ms allowed, a loaded machine); the
    // span of four gaps has that slack once. Unpaced, the gaps would be about 0.
    let gaps: Vec<u32> = t.windows(2).map(|w| w[1].saturating_sub(w[0])).collect();
    assert!(
        gaps.iter().all(|g| *g >= 150) && t[4] - t[0] >= 750,
        "samples sent closer than the 200 ms min_pace_period: gaps (ms) {gaps:?}"
    );
}

#[test]
fn max_bytes_per_second_caps_the_rate_and_loses_none() {
    // Each HelloWorld sample here is 4 + 4 + 6 = 14 bytes: 7 or 8 per one-second window at
    // 100 B/s (measured: 7). The first window opens with the read (before the first sample),
    // so 20 samples take three windows and the first and the last are sent more than a
    // second apart (less the front-end's stamping jitter, 50 ms allowed); unpaced they would
    // all go within milliseconds.
    let ddc = DataDeliveryControl {
        max_samples: u16::MAX,
        max_bytes_per_second: 100,
        ..Default::default()
    };
    let t = paced_sends("bps", 102, ddc, 20, "bytes");
    let span = t[19] - t[0];
    assert!(span >= 950, "20 samples sent within {span} ms: {t:?}");
    // Any second of the agent's clock overlaps two windows at most (16 samples), one more
    // for the jitter; twice the rate would put up to 32 there.
    for (k, start) in t.iter().enumerate() {
        let within = t[k..].iter().take_while(|x| **x < start + 1000).count();
        assert!(
            within <= 17,
            "{within} samples sent within a second from {start} ms: {t:?}"
        );
    }
}

/// A client reads through the agent with `ddc` while Cyclone writes `count` samples `every`
/// ms; returns what it got and when, relative to the read, until `listen` after it.
fn limited_read(
    name: &str,
    domain: i16,
    ddc: DataDeliveryControl,
    count: u32,
    every: u32,
    listen: Duration,
) -> Vec<(u32, Duration)> {
    let agent = AgentProcess::builder(name).start();
    let mut c = TestClient::new(agent.addr(), [0xDD, 0xC1, 0x00, domain as u8]);
    c.connect(10 * SECOND);
    let domain_arg = domain.to_string();
    let (count_arg, every_arg) = (count.to_string(), every.to_string());
    let writer = DdsPeer::start(&[
        "write",
        "--domain",
        &domain_arg,
        "--count",
        &count_arg,
        "--interval-ms",
        &every_arg,
        "--message",
        "limited",
        "--wait-match",
        "--reliable",
        "--timeout",
        "60",
        "--linger-ms",
        "3000",
    ]);
    let reader = c.setup_chain(
        domain,
        object_kind::SUBSCRIBER,
        object_kind::DATAREADER,
        xml::READER,
    );
    // The read's clock (max_elapsed_time) starts with its READ_DATA.
    let started = Instant::now();
    let spec = ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        delivery_control: Some(ddc),
        ..Default::default()
    };
    c.client.read(started, reader, spec).expect("read");
    c.step();
    assert!(
        writer
            .wait_for("MATCHED", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the agent's reader"
    );
    let mut got = Vec::new();
    c.run_until(listen, |c| {
        for (i, m) in c.take_samples() {
            assert_eq!(m, "limited");
            got.push((i, started.elapsed()));
        }
        false
    });
    drop(writer);
    assert!(agent.stop(), "agent did not stop cleanly");
    got
}

#[test]
fn max_samples_ends_the_read_after_that_many() {
    let ddc = DataDeliveryControl {
        max_samples: 3,
        ..Default::default()
    };
    // Cyclone writes 10; the read takes the first 3 and ends.
    let got = limited_read("maxs", 34, ddc, 10, 50, 5 * SECOND);
    let indices: Vec<u32> = got.iter().map(|(i, _)| *i).collect();
    assert_eq!(
        indices,
        [0, 1, 2],
        "a read of max_samples 3 got {indices:?}"
    );
}

#[test]
fn max_elapsed_time_ends_the_read() {
    let ddc = DataDeliveryControl {
        max_samples: u16::MAX,
        // Seconds (spec Table 9, eProsima's documentation).
        max_elapsed_time: 2,
        ..Default::default()
    };
    // A sample every 100 ms for 6 s: the read gets those of its first 2 s, none after.
    let got = limited_read("maxt", 35, ddc, 60, 100, 7 * SECOND);
    assert!(
        !got.is_empty(),
        "nothing delivered before the read's deadline"
    );
    let mut seen = Deliveries::default();
    for (i, _) in &got {
        seen.record(*i);
    }
    assert_eq!(
        seen.total(),
        seen.distinct(),
        "a sample delivered twice: {got:?}"
    );
    assert!(
        got.len() < 60,
        "the read went on past its max_elapsed_time: {} samples",
        got.len()
    );
    let last = got.last().map(|(_, t)| *t).unwrap_or_default();
    // The deadline counts from the READ_DATA (sent at `started`, before Cyclone matched); a
    // second of slack for the last delivery pass.
    assert!(
        last < 3 * SECOND,
        "a sample arrived {last:?} after the read started, past its 2 s"
    );
}
