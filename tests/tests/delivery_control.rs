//! DataDeliveryControl pacing with Cyclone DDS: `min_pace_period` spaces the DATA a client
//! gets, and `max_bytes_per_second` caps the sample bytes per second; the samples held back
//! wait in the DDS reader and all arrive.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use xrce_common::wire::{stream_id, DataDeliveryControl, ReadSpecification};
use xrce_tests::{AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

/// Subscribes with `ddc`, lets Cyclone write `count` samples of `message` back to back, and
/// returns the arrival times of the distinct samples.
fn paced_arrivals(
    name: &str,
    domain: i16,
    ddc: DataDeliveryControl,
    count: u32,
    message: &str,
) -> Vec<Instant> {
    let agent = AgentProcess::start(name);
    let mut c = TestClient::new(agent.addr(), [0xDD, 0xC0, 0x00, domain as u8]);
    c.connect(10 * SECOND);
    c.setup_subscriber_with(
        domain,
        ReadSpecification {
            preferred_stream_id: stream_id::BUILTIN_RELIABLE,
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
    let mut seen = BTreeSet::new();
    let mut arrivals = Vec::new();
    let ok = c.run_until(60 * SECOND, |c| {
        for (i, m) in c.take_samples() {
            assert_eq!(m, message);
            if seen.insert(i) {
                arrivals.push(Instant::now());
            }
        }
        seen.len() as u32 == count
    });
    assert!(ok, "client got {} of {count} paced samples", seen.len());
    assert_eq!(writer.wait(30 * SECOND, || c.step()), Some(0));
    assert!(agent.stop(), "agent did not stop cleanly");
    arrivals
}

#[test]
fn min_pace_period_spaces_the_samples_and_loses_none() {
    let ddc = DataDeliveryControl {
        max_samples: u16::MAX,
        min_pace_period: 200,
        ..Default::default()
    };
    let t = paced_arrivals("pace", 26, ddc, 5, "paced");
    // Four gaps of at least 200 ms (with slack for timer granularity).
    let span = t[4].duration_since(t[0]);
    assert!(
        span >= Duration::from_millis(700),
        "5 samples within {span:?}"
    );
}

#[test]
fn max_bytes_per_second_caps_the_rate_and_loses_none() {
    // Each HelloWorld sample here is 4 + 4 + 6 = 14 bytes: at most 7 per second at 100 B/s,
    // so 20 samples need at least two full windows after the first.
    let ddc = DataDeliveryControl {
        max_samples: u16::MAX,
        max_bytes_per_second: 100,
        ..Default::default()
    };
    let t = paced_arrivals("bps", 27, ddc, 20, "bytes");
    let span = t[19].duration_since(t[0]);
    assert!(
        span >= Duration::from_millis(1800),
        "20 samples within {span:?}"
    );
}
