//! The metrics endpoint (`--metrics ADDR:PORT`, `[metrics] listen`): a small HTTP server on
//! its own thread that serves, from the status reports every process of the instance writes
//! ([`xrce_ipc::status`]):
//!
//! * `/metrics`: the Prometheus text exposition (format 0.0.4), encoded by
//!   `prometheus-client` from a collector that reads the reports on each scrape;
//! * `/status`: the same reports as one JSON document ([`AgentStatus`]), which
//!   `xrce-agent status --metrics URL` reads.
//!
//! Nothing is counted here but the endpoint's own refusals
//! (`xrce_metrics_connections_refused_total`): every other number is a process's own
//! counter, so a restarted process's counters start again from zero, which Prometheus's
//! `rate()` handles.
//!
//! The endpoint is bounded ([`Server`]): one thread and no thread per connection, at most
//! [`MAX_CONNECTIONS`] connections at once, a request must arrive whole within
//! [`REQUEST_TIMEOUT`] and fit in [`MAX_REQUEST_BYTES`], a response must be taken within
//! [`WRITE_TIMEOUT`] of progress and [`RESPONSE_TIMEOUT`] in all. Peers that connect and say
//! nothing cost a descriptor for two seconds each and cannot lock a scraper out: the oldest
//! of them makes room for a new connection. It binds where the operator says (there is no
//! default address: the endpoint is off unless `--metrics ADDR:PORT` or `[metrics] listen`
//! is given; the documented address is 127.0.0.1:9464) and warns when that is not loopback.

use std::path::PathBuf;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use serde::{Deserialize, Serialize};
use xrce_ipc::status::{self, ProcessReport};

/// Everything `/status` says: the instance and the reports of its live processes.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct AgentStatus {
    /// The instance name.
    pub instance: String,
    /// Reports of its live processes (supervisor, worker, front-ends).
    pub processes: Vec<ProcessReport>,
}

/// A client key as printed by default: `0x****BBBB` (its last four hex digits); a key in
/// any other form is hidden whole.
pub fn redact_key(key: &str) -> String {
    let hex = key
        .strip_prefix("0x")
        .or_else(|| key.strip_prefix("0X"))
        .unwrap_or(key);
    let tail_ok = |t: &str| t.len() == 4 && t.bytes().all(|b| b.is_ascii_hexdigit());
    if hex.len() == 8 && hex.bytes().all(|b| b.is_ascii_hexdigit()) {
        format!("0x****{}", &hex[4..])
    } else if let Some(tail) = hex.strip_prefix("****").filter(|t| tail_ok(t)) {
        // Already redacted (by the metrics endpoint's /status).
        format!("0x****{tail}")
    } else {
        "0x********".to_string()
    }
}

impl AgentStatus {
    /// Replaces every client key by its redacted form
    /// ([`redact_key`]).
    pub fn redact_keys(&mut self) {
        for p in &mut self.processes {
            if let Some(f) = &mut p.frontend {
                for s in &mut f.sessions {
                    s.client_key = redact_key(&s.client_key);
                }
            }
        }
    }

    /// The reports found now in an instance's status directory.
    pub fn read(instance: &str, dir: &std::path::Path) -> Self {
        AgentStatus {
            instance: instance.to_string(),
            processes: status::read_reports(dir),
        }
    }
}

/// Labels of one sample.
type Labels = Vec<(&'static str, String)>;

/// A sample's value: counts stay integers in the exposition.
#[derive(Debug, Clone, Copy)]
enum Value {
    Count(u64),
    Real(f64),
}

/// One metric family being filled in.
struct Family {
    name: &'static str,
    help: &'static str,
    kind: MetricType,
    samples: Vec<(Labels, Value)>,
}

impl Family {
    fn new(name: &'static str, kind: MetricType, help: &'static str) -> Self {
        Family {
            name,
            help,
            kind,
            samples: Vec::new(),
        }
    }

    fn add(&mut self, labels: Labels, value: u64) {
        self.samples.push((labels, Value::Count(value)));
    }

    fn add_real(&mut self, labels: Labels, value: f64) {
        self.samples.push((labels, Value::Real(value)));
    }

    fn encode(&self, encoder: &mut DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        if self.samples.is_empty() {
            return Ok(());
        }
        let mut metric = encoder.encode_descriptor(self.name, self.help, None, self.kind)?;
        for (labels, value) in &self.samples {
            let family = metric.encode_family(labels)?;
            match (self.kind, *value) {
                (MetricType::Counter, Value::Count(v)) => ConstCounter::new(v).encode(family)?,
                (MetricType::Counter, Value::Real(v)) => ConstCounter::new(v).encode(family)?,
                (_, Value::Count(v)) => {
                    ConstGauge::new(i64::try_from(v).unwrap_or(i64::MAX)).encode(family)?
                }
                (_, Value::Real(v)) => ConstGauge::new(v).encode(family)?,
            }
        }
        Ok(())
    }
}

/// The metric families of a status snapshot. Counter names are given without `_total`,
/// which the encoder appends.
fn families(s: &AgentStatus) -> Vec<Family> {
    use MetricType::{Counter, Gauge};
    let mut sessions = Family::new("xrce_sessions", Gauge, "Live XRCE sessions of a front-end.");
    let mut connected = Family::new(
        "xrce_frontend_connected",
        Gauge,
        "1 while the front-end serves the running DDS worker's generation, else 0 (no worker, \
         or it died and its successor has not been seen yet).",
    );
    // The generation of the worker that runs now (its report is read only while it lives).
    let live_generation = s
        .processes
        .iter()
        .find_map(|p| p.worker.as_ref().map(|w| w.generation));
    let per_frontend: [(&str, &'static str, &'static str); 11] = [
        (
            "messages_received",
            "xrce_messages_received",
            "XRCE messages received from clients.",
        ),
        (
            "messages_sent",
            "xrce_messages_sent",
            "XRCE messages sent to clients (retransmissions included).",
        ),
        (
            "samples_written",
            "xrce_samples_written",
            "Samples clients wrote (WRITE_DATA handed to DDS).",
        ),
        (
            "samples_delivered",
            "xrce_samples_delivered",
            "Samples from DDS queued for clients (DATA).",
        ),
        (
            "retransmissions",
            "xrce_retransmissions",
            "Reliable messages sent again to clients.",
        ),
        (
            "reads_paused",
            "xrce_reads_paused",
            "Times a read was paused because its client did not keep up.",
        ),
        (
            "best_effort_sheds",
            "xrce_best_effort_sheds",
            "Times a client's best-effort writes overflowed their wait for the worker, shared by the clients (an overload: that client's are then shed, not queued, for 200 ms).",
        ),
        (
            "replays",
            "xrce_replays",
            "Object graphs replayed to a new DDS worker.",
        ),
        (
            "link_refusals",
            "xrce_ipc_link_refusals",
            "Sends and wake-ups the shared-memory link to the worker refused (each retried, with back-off; nothing dropped).",
        ),
        (
            "transport_opened",
            "xrce_transport_connections_opened",
            "Connections accepted or devices opened.",
        ),
        (
            "transport_closed",
            "xrce_transport_connections_closed",
            "Connections or devices closed.",
        ),
    ];
    let mut counters: Vec<Family> = per_frontend
        .iter()
        .map(|(_, name, help)| Family::new(name, Counter, help))
        .collect();
    let mut dropped = Family::new(
        "xrce_dropped",
        Counter,
        "Input, output and operations dropped, by process and reason.",
    );
    let mut worker_entities = Family::new(
        "xrce_worker_entities",
        Gauge,
        "DDS-side entities the worker holds, by kind.",
    );
    let mut worker_written = Family::new(
        "xrce_worker_samples_written",
        Counter,
        "Samples the worker accepted for DDS writers.",
    );
    let mut worker_taken = Family::new(
        "xrce_worker_samples_taken",
        Counter,
        "Samples the worker took from DDS readers for clients.",
    );
    let mut worker_restarts = Family::new(
        "xrce_worker_restarts",
        Counter,
        "Times the supervisor restarted the DDS worker.",
    );
    let mut frontend_restarts = Family::new(
        "xrce_frontend_restarts",
        Counter,
        "Times the supervisor restarted a front-end.",
    );
    let mut watchdog_kills = Family::new(
        "xrce_watchdog_kills",
        Counter,
        "Children killed (and restarted) because their event loop stopped reporting.",
    );
    let mut memory_kills = Family::new(
        "xrce_memory_limit_kills",
        Counter,
        "Children killed (and restarted) because their private resident memory (RssAnon) exceeded --memory-limit.",
    );
    let mut cpu = Family::new(
        "xrce_process_cpu_seconds",
        Counter,
        "User and system CPU time of each process of the agent.",
    );
    let mut memory = Family::new(
        "xrce_process_resident_memory_bytes",
        Gauge,
        "Resident memory of each process of the agent.",
    );
    let mut start = Family::new(
        "xrce_process_start_time_seconds",
        Gauge,
        "Start time of each process of the agent, in seconds since the Unix epoch.",
    );
    for p in &s.processes {
        let process: Labels = vec![("process", p.name.clone())];
        // A worker inside a front-end's process: that process is counted once, as the
        // front-end.
        if p.runs_inside(&s.processes).is_none() {
            cpu.add_real(process.clone(), p.cpu_seconds);
            memory.add(process.clone(), p.resident_bytes);
            start.add_real(process.clone(), p.started_unix_ms as f64 / 1000.0);
        }
        if let Some(f) = &p.frontend {
            let labels: Labels = vec![
                ("frontend", p.name.clone()),
                ("transport", f.transport.clone()),
            ];
            sessions.add(labels.clone(), f.sessions.len() as u64);
            // Reports older than the generation field count as connected while a worker runs.
            let serves_live = f.connected
                && live_generation.is_some()
                && f.generation.is_none_or(|g| Some(g) == live_generation);
            connected.add(labels.clone(), u64::from(serves_live));
            for ((key, _, _), family) in per_frontend.iter().zip(counters.iter_mut()) {
                family.add(labels.clone(), f.counters.get(*key).copied().unwrap_or(0));
            }
            for (reason, n) in &f.dropped {
                dropped.add(
                    vec![("process", p.name.clone()), ("reason", reason.clone())],
                    *n,
                );
            }
        }
        if let Some(w) = &p.worker {
            for (kind, n) in &w.entities {
                worker_entities.add(vec![("kind", kind.clone())], *n);
            }
            worker_written.add(Vec::new(), w.samples_written);
            worker_taken.add(Vec::new(), w.samples_taken);
            for (reason, n) in &w.dropped {
                dropped.add(
                    vec![("process", p.name.clone()), ("reason", reason.clone())],
                    *n,
                );
            }
        }
        for c in &p.children {
            let name = process_name(&c.name);
            match c.role.as_str() {
                "worker" => worker_restarts.add(Vec::new(), c.restarts),
                _ => frontend_restarts.add(vec![("frontend", name.clone())], c.restarts),
            }
            watchdog_kills.add(vec![("process", name.clone())], c.watchdog_kills);
            memory_kills.add(vec![("process", name)], c.memory_kills);
        }
    }
    let mut out = vec![sessions, connected];
    out.extend(counters);
    out.extend([
        dropped,
        worker_entities,
        worker_written,
        worker_taken,
        worker_restarts,
        frontend_restarts,
        watchdog_kills,
        memory_kills,
        cpu,
        memory,
        start,
    ]);
    out
}

/// A supervisor child's name (`xrce-dds-worker`, `xrce-frontend-<name>`) as the process
/// reports itself (`worker`, `<name>`).
pub fn process_name(child: &str) -> String {
    if child == "xrce-dds-worker" {
        return "worker".into();
    }
    child
        .strip_prefix("xrce-frontend-")
        .unwrap_or(child)
        .to_string()
}

/// Reads the reports on each scrape.
#[derive(Debug)]
struct StatusCollector {
    instance: String,
    dir: PathBuf,
}

impl Collector for StatusCollector {
    fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        let snapshot = AgentStatus::read(&self.instance, &self.dir);
        for f in families(&snapshot) {
            f.encode(&mut encoder)?;
        }
        Ok(())
    }
}

/// The Prometheus text exposition of a snapshot.
pub fn render(snapshot: &AgentStatus) -> Result<String, std::fmt::Error> {
    #[derive(Debug)]
    struct Fixed(AgentStatus);
    impl Collector for Fixed {
        fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
            for f in families(&self.0) {
                f.encode(&mut encoder)?;
            }
            Ok(())
        }
    }
    let mut registry = Registry::default();
    registry.register_collector(Box::new(Fixed(snapshot.clone())));
    let mut out = String::new();
    prometheus_client::encoding::prometheus_text::encode(&mut out, &registry)?;
    Ok(out)
}

mod server;
pub use server::{
    serve, Refusal, Server, ServerStats, MAX_CONNECTIONS, MAX_REQUEST_BYTES, REQUEST_TIMEOUT,
    RESPONSE_TIMEOUT, WRITE_TIMEOUT,
};

#[cfg(test)]
mod tests;
