//! What one run measured: for people (a table on stdout) and for machines (JSON).

use crate::agent::ProcOne;

/// What one run measured (also written as JSON).
#[derive(Debug, serde::Serialize)]
pub struct Report {
    /// How the clients reached the agent: `udp`, `tcp` or `serial`.
    pub transport: String,
    /// Serial: each line's raw rate in bytes per second (baud / 10 at 8N1).
    pub line_bytes_per_second: Option<f64>,
    /// Publishing clients.
    pub publishers: u32,
    /// Subscribing clients.
    pub subscribers: u32,
    /// Bytes per sample.
    pub payload_bytes: usize,
    /// Reliable streams and DDS endpoints (else best-effort).
    pub reliable: bool,
    /// How the entities were created: `xml` or `binary`.
    pub creation: String,
    /// Samples per second asked for in total (0 = unpaced).
    pub rate_requested: f64,
    /// Samples sent before the measured phase, not counted.
    pub warmup_samples: u32,
    /// Generator threads sending and receiving in the measured phase.
    pub threads: u32,
    /// From the start to every session established.
    pub sessions_ms: f64,
    /// From the start to every entity created.
    pub setup_ms: f64,
    /// From the start to every publisher heard by every subscriber (DDS matched).
    pub matched_ms: f64,
    /// Publishers some subscriber never heard before the run.
    pub unmatched_writers: usize,
    /// Samples sent (each is expected once at every subscriber).
    pub sent: u32,
    /// Distinct samples received, summed over the subscribers.
    pub received: u64,
    /// Deliveries missing: sent × subscribers − received.
    pub lost: u64,
    /// Samples received again by the same subscriber.
    pub duplicates: u64,
    /// From the first send to the last sample received.
    pub seconds: f64,
    /// Samples per second received, summed over the subscribers.
    pub samples_per_second: f64,
    /// Sample bytes per second received, summed over the subscribers.
    pub bytes_per_second: f64,
    /// What the independent DDS reader counted (client → agent → DDS).
    pub dds: Option<DdsReport>,
    /// Client → agent → DDS → agent → client.
    pub latency_us: Percentiles,
    /// The agent's resource use (None for an agent not started by the generator).
    pub agent: Option<AgentUse>,
    /// The agent with every session set up and silent (`--idle`).
    pub idle: Option<IdleUse>,
    /// The generator's own CPU in the measured phase.
    pub generator: GeneratorUse,
    /// The kill soak's accounting (with `--kills`).
    pub soak: Option<crate::soak::SoakReport>,
}

/// Latency percentiles, µs.
#[derive(Debug, serde::Serialize)]
pub struct Percentiles {
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest.
    pub max: f64,
}

impl Percentiles {
    /// The percentiles of a histogram of nanoseconds.
    pub fn of(h: &hdrhistogram::Histogram<u64>) -> Self {
        let q = |x: f64| h.value_at_quantile(x) as f64 / 1000.0;
        Percentiles {
            p50: q(0.5),
            p90: q(0.9),
            p99: q(0.99),
            p999: q(0.999),
            max: h.max() as f64 / 1000.0,
        }
    }
}

/// What the independent DDS reader counted.
#[derive(Debug, serde::Serialize)]
pub struct DdsReport {
    /// Distinct measured samples received.
    pub received: u64,
    /// Sent but not received.
    pub lost: u64,
    /// Received again.
    pub duplicates: u64,
    /// Received per second, until the last one.
    pub samples_per_second: f64,
    /// Sample payload bytes per second (the serialized samples, without RTPS headers).
    pub bytes_per_second: f64,
    /// Client → agent → DDS.
    pub latency_us: Percentiles,
    /// Who counted: "DDS (independent RustDDS reader)" or "Zenoh (independent Zenoh
    /// subscriber, through its router)".
    pub counted_by: &'static str,
}

/// The agent's resource use in the measured phase.
#[derive(Debug, serde::Serialize)]
pub struct AgentUse {
    /// CPU seconds of the agent's processes during the measured phase.
    pub cpu_seconds: f64,
    /// CPU microseconds per delivered sample.
    pub cpu_us_per_sample: f64,
    /// Summed peak RSS of the agent's processes at the end, KiB.
    pub peak_rss_kib: u64,
    /// Processes of the agent.
    pub processes: usize,
    /// Threads of the agent's processes at the end of the measured phase.
    pub threads: u64,
    /// Open file descriptors of the agent's processes at the end of the measured phase.
    pub fds: u64,
    /// Each process at the end of the measured phase, with its CPU over the phase.
    pub each: Vec<ProcOne>,
    /// What our agent counted (drops by reason), from its status reports.
    pub counters: Option<crate::agent::AgentCounters>,
}

/// The agent's cost with every session and entity set up and no traffic.
#[derive(Debug, serde::Serialize)]
pub struct IdleUse {
    /// Length of the idle period.
    pub seconds: f64,
    /// Agent CPU over the idle period, as a percentage of one core.
    pub cpu_percent: f64,
    /// Resident memory of the agent's processes before any session, KiB.
    pub rss_before_kib: u64,
    /// Resident memory with every session set up, KiB.
    pub rss_idle_kib: u64,
    /// (idle − before) / sessions, bytes.
    pub rss_bytes_per_session: f64,
    /// Each process at the end of the idle period, with its CPU over the period.
    pub each: Vec<ProcOne>,
}

/// The generator's own CPU in the measured phase: the threads that drive the clients
/// (not its DDS reader's, nor a null agent's).
#[derive(Debug, serde::Serialize)]
pub struct GeneratorUse {
    /// CPU seconds of those threads.
    pub cpu_seconds: f64,
    /// CPU seconds over (seconds × threads): near 100 % means the generator was the limit.
    pub busy_percent: f64,
}

/// Prints a run's results for people.
pub fn print_report(report: &Report) {
    println!(
        "{} {} publishers + {} subscribers, {} B {}, {} creation, {} generator threads: set-up {:.0} ms (sessions {:.0} ms), writers matched at {:.0} ms ({} never)",
        report.transport,
        report.publishers,
        report.subscribers,
        report.payload_bytes,
        if report.reliable { "reliable" } else { "best-effort" },
        report.creation,
        report.threads,
        report.setup_ms,
        report.sessions_ms,
        report.matched_ms,
        report.unmatched_writers
    );
    if let Some(i) = &report.idle {
        println!(
            "  idle {:.0} s with every session set up: agent CPU {:.2} % of a core, RSS {:.1} MiB (before sessions {:.1} MiB) = {:.1} KiB per session",
            i.seconds,
            i.cpu_percent,
            i.rss_idle_kib as f64 / 1024.0,
            i.rss_before_kib as f64 / 1024.0,
            i.rss_bytes_per_session / 1024.0
        );
        for p in &i.each {
            println!(
                "    {:<22} RSS {:>8.1} MiB  {:>3} threads  {:>5} fds  CPU {:.2} s",
                p.name,
                p.rss_kib as f64 / 1024.0,
                p.threads,
                p.fds,
                p.cpu_seconds
            );
        }
    }
    println!(
        "  {} of {} samples in {:.2} s = {:.0} samples/s ({:.1} MB/s), {} lost, {} duplicates",
        report.received,
        u64::from(report.sent) * u64::from(report.subscribers),
        report.seconds,
        report.samples_per_second,
        report.bytes_per_second / 1e6,
        report.lost,
        report.duplicates
    );
    let l = &report.latency_us;
    println!(
        "  latency us: p50 {:.0}  p90 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}",
        l.p50, l.p90, l.p99, l.p999, l.max
    );
    if let Some(d) = &report.dds {
        println!(
            "  into {}: {} of {} = {:.0} samples/s ({:.1} MB/s), {} lost, {} duplicates; latency us: p50 {:.0}  p90 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}",
            d.counted_by,
            d.received,
            report.sent,
            d.samples_per_second,
            d.bytes_per_second / 1e6,
            d.lost,
            d.duplicates,
            d.latency_us.p50,
            d.latency_us.p90,
            d.latency_us.p99,
            d.latency_us.p999,
            d.latency_us.max
        );
    }
    if let (Some(line), Some(d)) = (report.line_bytes_per_second, &report.dds) {
        let per_line = d.bytes_per_second / f64::from(report.publishers.max(1));
        println!(
            "  serial: each publisher's line carries {:.0} B/s raw; {:.0} sample payload B/s per line reached DDS = {:.1} % of the line",
            line,
            per_line,
            100.0 * per_line / line
        );
    }
    if let Some(u) = &report.agent {
        println!(
            "  agent ({} processes, {} threads, {} fds): {:.2} CPU s = {:.1} us/sample, peak RSS {:.1} MiB",
            u.processes,
            u.threads,
            u.fds,
            u.cpu_seconds,
            u.cpu_us_per_sample,
            u.peak_rss_kib as f64 / 1024.0
        );
        for p in &u.each {
            println!(
                "    {:<22} CPU {:>6.2} s  peak RSS {:>8.1} MiB  {:>3} threads  {:>5} fds",
                p.name,
                p.cpu_seconds,
                p.peak_rss_kib as f64 / 1024.0,
                p.threads,
                p.fds
            );
        }
        if let Some(c) = &u.counters {
            let list = |m: &std::collections::BTreeMap<String, u64>| {
                let v: Vec<String> = m
                    .iter()
                    .filter(|(_, n)| **n > 0)
                    .map(|(k, n)| format!("{k} {n}"))
                    .collect();
                if v.is_empty() {
                    "none".to_string()
                } else {
                    v.join(", ")
                }
            };
            println!(
                "    agent drops: {}; front-end counters: {}{}",
                list(&c.dropped),
                list(&c.frontend),
                if c.stale { " (some report stale)" } else { "" }
            );
        }
    }
    println!(
        "  generator: {:.2} CPU s, {:.0} % busy",
        report.generator.cpu_seconds, report.generator.busy_percent
    );
    if let Some(soak) = &report.soak {
        crate::soak::print(soak);
    }
}
