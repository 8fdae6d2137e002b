//! CI smoke runs of the load generator (tests, not benchmarks: no timing thresholds): 50
//! publishing clients through our agent for a few seconds; every session is established,
//! every writer matched, and every reliable sample delivered to every subscriber.

mod common;

use common::run_loadgen;

#[test]
fn fifty_clients_deliver_every_reliable_sample_to_two_subscribers() {
    // Two generator threads, two subscribers, a warm-up: 1,000 measured samples each
    // subscriber must get once.
    let (v, stdout) = run_loadgen(
        "xml",
        &[
            "--publishers",
            "50",
            "--subscribers",
            "2",
            "--threads",
            "2",
            "--samples",
            "1000",
            "--warmup",
            "100",
            // Two subscribers double the worker's work, and the front-end stores every
            // session as it changes: a debug build keeps up at this rate (beyond it the
            // backlog outgrows the readers' KEEP_LAST 1000 history; 250/s lost 3 of 2,000
            // once the session store came in, sixth session).
            "--rate",
            "150",
            "--domain",
            "23",
        ],
    );
    assert_eq!(v["unmatched_writers"], 0, "{stdout}");
    assert_eq!(v["sent"], 1000, "{stdout}");
    assert_eq!(v["received"], 2000, "{stdout}");
    assert_eq!(v["lost"], 0, "{stdout}");
    assert_eq!(v["duplicates"], 0, "{stdout}");
    plausible_latency(&v["latency_us"], &stdout);
    paced(&v, 150.0, &stdout);
    // The independent DDS reader (best-effort, may lose under load) saw the traffic.
    assert!(
        v["dds"]["received"].as_u64().is_some_and(|n| n > 0),
        "{stdout}"
    );
    assert!(
        v["agent"]["processes"].as_u64().is_some_and(|n| n >= 3),
        "{stdout}"
    );
    assert!(
        v["generator"]["cpu_seconds"]
            .as_f64()
            .is_some_and(|s| s > 0.0),
        "{stdout}"
    );
}

#[test]
fn binary_creation_with_shared_writers_delivers_every_sample_and_measures_idle() {
    // The agent maps the 50 clients' writers onto one DDS writer (`--share-writers`).
    let (v, stdout) = run_loadgen(
        "binary",
        &[
            "--publishers",
            "50",
            "--creation",
            "binary",
            "--samples",
            "1000",
            "--rate",
            "500",
            "--domain",
            "29",
            "--idle",
            "1",
            "--agent-args",
            "--share-writers true",
        ],
    );
    assert_eq!(v["unmatched_writers"], 0, "{stdout}");
    assert_eq!(v["received"], 1000, "{stdout}");
    assert_eq!(v["lost"], 0, "{stdout}");
    assert_eq!(v["duplicates"], 0, "{stdout}");
    let idle = &v["idle"];
    assert!(
        idle["seconds"]
            .as_f64()
            .is_some_and(|s| (1.0..5.0).contains(&s)),
        "the idle period was not measured over about a second: {stdout}"
    );
    // Fifty sessions with their entities cost memory, and a bounded amount of it.
    let before = idle["rss_before_kib"].as_u64().unwrap_or(0);
    let during = idle["rss_idle_kib"].as_u64().unwrap_or(0);
    assert!(before > 0 && during >= before, "{stdout}");
    let per_session = idle["rss_bytes_per_session"].as_f64().unwrap_or(-1.0);
    assert!(
        (0.0..1e6).contains(&per_session),
        "{per_session} bytes per idle session: {stdout}"
    );
    plausible_latency(&v["latency_us"], &stdout);
    paced(&v, 500.0, &stdout);
    // Every process of the agent is listed, the worker among them.
    let names: Vec<&str> = idle["each"]
        .as_array()
        .map(|a| a.iter().filter_map(|p| p["name"].as_str()).collect())
        .unwrap_or_default();
    assert!(names.iter().any(|n| n.contains("dds-worker")), "{names:?}");
}

#[test]
fn null_agent_carries_every_sample_without_dds() {
    // The generator's ceiling check: the session core alone, in the generator's process.
    let (v, stdout) = run_loadgen(
        "null",
        &[
            "--null-agent",
            "--publishers",
            "20",
            "--subscribers",
            "2",
            "--samples",
            "2000",
            "--rate",
            "2000",
        ],
    );
    assert_eq!(v["unmatched_writers"], 0, "{stdout}");
    assert_eq!(v["received"], 4000, "{stdout}");
    assert_eq!(v["lost"], 0, "{stdout}");
    assert_eq!(v["duplicates"], 0, "{stdout}");
    assert!(v["dds"].is_null(), "no DDS reader against the null agent");
    plausible_latency(&v["latency_us"], &stdout);
    paced(&v, 2000.0, &stdout);
    assert!(v["agent"].is_null(), "no agent process to measure");
}

/// Latency percentiles that a broken clock or tag would not give: ordered, and between a
/// microsecond and a minute (the generator records at least 1 µs, so p50 > 0 alone could
/// not fail).
fn plausible_latency(l: &serde_json::Value, stdout: &str) {
    let q = |k: &str| l[k].as_f64().unwrap_or(f64::NAN);
    let (p50, p90, p99, p999, max) = (q("p50"), q("p90"), q("p99"), q("p999"), q("max"));
    assert!(
        p50 <= p90 && p90 <= p99 && p99 <= p999 && p999 <= max,
        "percentiles out of order: {l}\n{stdout}"
    );
    assert!(
        p50 > 1.0 && max < 60e6,
        "implausible latencies (µs): {l}\n{stdout}"
    );
}

/// The paced rate was kept: the run did not go faster than asked (more than a tenth above
/// it, counting the first second's burst), and its rate agrees with its sample count and
/// duration.
fn paced(v: &serde_json::Value, rate: f64, stdout: &str) {
    let per_second = v["samples_per_second"].as_f64().unwrap_or(f64::NAN);
    let received = v["received"].as_f64().unwrap_or(f64::NAN);
    let seconds = v["seconds"].as_f64().unwrap_or(f64::NAN);
    let subscribers = v["subscribers"].as_f64().unwrap_or(1.0).max(1.0);
    assert!(
        (per_second - received / seconds).abs() <= 0.01 * per_second,
        "samples/s {per_second} disagrees with {received} in {seconds} s: {stdout}"
    );
    assert!(
        per_second / subscribers <= rate * 1.1 + 50.0,
        "faster than the {rate}/s asked: {per_second}/s over {subscribers} subscribers: {stdout}"
    );
}
