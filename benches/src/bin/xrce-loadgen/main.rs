//! `xrce-loadgen`: a load generator. N publishing and S subscribing XRCE clients (common's
//! client state machine, one UDP socket and session each, entities created by XML or
//! binary) talk through an agent; it reports session set-up time, the agent's idle cost,
//! the samples/s delivered client → agent → DDS → agent → client, losses, latency
//! percentiles (HdrHistogram), the agent's CPU time and memory per process (from /proc),
//! and its own CPU, so that a saturated generator shows.
//!
//! By default it starts our agent (`xrce-agent` next to this binary) on `--port`;
//! `--agent-cmd 'CMD {port}'` starts any other agent with a shell, and `--no-agent` uses one
//! already running. `--json FILE` writes the results for machines.
//!
//! An independent DDS reader (RustDDS, its own participant, pinned to loopback) counts what
//! reaches DDS and its latency client → agent → DDS (`--dds-reader false` leaves it out).
//!
//! `--compare-with 'OTHER-AGENT {port}'` runs the same scenario alternately against ours (or
//! `--agent-cmd`) and the other agent, `--rounds` times each, and prints medians and ratios.
//! `--sweep 1,10,100` runs it per publisher count and `--svg` plots the sweep.
//!
//! Example: `xrce-loadgen --publishers 100 --samples 50000 --best-effort --json run.json`.

mod agent;
mod dds_reader;
mod link;
mod null_agent;
mod peer;
mod plot;
mod report;
mod scenario;
mod soak;

use clap::Parser;

use peer::raise_fd_limit;
use report::{print_report, Report};
use scenario::run;

/// How the clients create their entities.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Creation {
    /// XML strings (REPRESENTATION_AS_XML_STRING), as `uxr_buffer_create_*_xml`.
    Xml,
    /// Binary objects (REPRESENTATION_IN_BINARY), as `uxr_buffer_create_*_bin`.
    Binary,
}

/// How the simulated clients reach the agent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TransportArg {
    /// A UDP socket each.
    Udp,
    /// A TCP connection each.
    Tcp,
    /// A serial line each (a pty pair; the agent serves them all with `multiserial`),
    /// paced at `--baud`.
    Serial,
}

/// Command line.
#[derive(Debug, Clone, Parser)]
#[command(name = "xrce-loadgen", about = "Load generator for XRCE agents")]
pub struct Args {
    /// UDP or TCP port of the agent.
    #[arg(long, default_value_t = 8888)]
    pub port: u16,
    /// Port of the subscribing clients, when not `--port`: another front-end of a gateway
    /// (`xrce-agent --config`), so that the publishers' front-end hears from the worker
    /// only about its own operations.
    #[arg(long)]
    pub subscriber_port: Option<u16>,
    /// How the clients reach the agent.
    #[arg(long, value_enum, default_value_t = TransportArg::Udp)]
    pub transport: TransportArg,
    /// UDP: the clients' source addresses, 127.0.0.1 up to 127.0.0.N, client `i` on the
    /// `i mod N`th: as clients on N hosts, for an agent whose port several front-end
    /// processes serve (`--processes`), which each address's clients share.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=254))]
    pub source_addresses: u8,
    /// Serial transport: the line rate in bits per second (8N1, 10 bits a byte) at which each
    /// client's output is paced, as a UART would send it.
    #[arg(long, default_value_t = 921_600)]
    pub baud: u32,
    /// Publishing clients (each its own session and socket).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=60_000))]
    pub publishers: u32,
    /// Subscribing clients; each is to receive every sample.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1_000))]
    pub subscribers: u32,
    /// How the clients create their entities.
    #[arg(long, value_enum, default_value_t = Creation::Xml)]
    pub creation: Creation,
    /// Samples to send in the measured phase.
    #[arg(long, default_value_t = 20_000, value_parser = clap::value_parser!(u32).range(1..=100_000_000))]
    pub samples: u32,
    /// Samples per second in total (0 = as fast as the windows allow).
    #[arg(long, default_value_t = 0.0)]
    pub rate: f64,
    /// Samples per second per publishing client (instead of `--rate`).
    #[arg(long, conflicts_with = "rate")]
    pub client_rate: Option<f64>,
    /// Samples sent (at the run's rate) before the measured phase, not counted.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=100_000_000))]
    pub warmup: u32,
    /// Seconds to keep every session set up and silent before the traffic, measuring the
    /// agent's idle CPU and memory per session (0 = skip).
    #[arg(long, default_value_t = 0.0)]
    pub idle: f64,
    /// Generator threads in the measured phase, each sending for its share of the
    /// publishers (the first also receives for the subscribers).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub threads: u32,
    /// Sample size in bytes (at least 12: sequence number and send time).
    #[arg(long, default_value_t = 40)]
    pub payload: usize,
    /// DDS domain of the clients' participants.
    #[arg(long, default_value_t = 42)]
    pub domain: i16,
    /// Client key of the first simulated client (the others follow it), so that two
    /// generators can share one agent (`--no-agent`) without taking over each other's
    /// sessions: a CREATE_CLIENT with a key already in use replaces that session.
    #[arg(long, default_value = "0x10000000", value_parser = parse_client_key)]
    pub first_client_key: u32,
    /// Best-effort streams (default: reliable).
    #[arg(long)]
    pub best_effort: bool,
    /// History depth of the DDS writers and reader (0 = KEEP_ALL).
    #[arg(long, default_value_t = 1000)]
    pub history: u32,
    /// Longest measured phase in seconds.
    #[arg(long, default_value_t = 60)]
    pub duration: u64,
    /// Kill soak: SIGKILL the agent's worker or front-end this many times during the
    /// measured phase and account for each kill (lost, duplicated, reordered, recovery).
    #[arg(long, default_value_t = 0)]
    pub kills: u32,
    /// What the soak kills.
    #[arg(long, value_enum, default_value_t = soak::KillTarget::Alternate)]
    pub kill: soak::KillTarget,
    /// Seconds between kills.
    #[arg(long, default_value_t = 3.0)]
    pub kill_every: f64,
    /// Kill soak: write every sample some subscriber did not get to this file, a line each:
    /// its sequence number, its publisher, when it was sent (ms from the start of the
    /// measured phase), and whether the independent DDS reader got it (`dds`, `-`, or `?`
    /// without one). Lost in both points before DDS; at the subscriber only, after it.
    #[arg(long)]
    pub lost_list: Option<std::path::PathBuf>,
    /// Command starting the agent under test, `{port}` replaced (run with `sh -c`); with
    /// `--transport serial`, `{devices}` (space-separated) and `{device_file}` (one a line)
    /// name the pty slaves the agent is to serve.
    #[arg(long)]
    pub agent_cmd: Option<String>,
    /// Extra arguments for our agent when the generator starts it (e.g.
    /// `--share-writers true`); not used with `--agent-cmd`.
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub agent_args: String,
    /// Run against a null agent in this process (the XRCE session core, no DDS): measures
    /// the generator's own ceiling. Leaves out the DDS reader.
    #[arg(long, conflicts_with_all = ["agent_cmd", "no_agent", "compare_with"])]
    pub null_agent: bool,
    /// Use an agent that is already running on `--port`.
    #[arg(long, conflicts_with = "agent_cmd")]
    pub no_agent: bool,
    /// Write the results as JSON to this file.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    /// Compare mode: also run the scenario against this agent command (`{port}` replaced),
    /// alternating with ours (or `--agent-cmd`), and print the medians and ratios.
    #[arg(long = "compare-with")]
    pub compare_with: Option<String>,
    /// Sweep mode: run the scenario once per publisher count in this list (e.g.
    /// `1,10,100,1000`), print a table, and with `--svg` plot it.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=60_000))]
    pub sweep: Vec<u32>,
    /// Sweep mode: write an SVG plot of throughput and latency against client count.
    #[arg(long)]
    pub svg: Option<std::path::PathBuf>,
    /// Rounds per agent in compare mode.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub rounds: u32,
    /// Count the samples that reach DDS with an independent RustDDS reader in this process.
    #[arg(long = "dds-reader", default_value_t = true, action = clap::ArgAction::Set)]
    pub dds_reader: bool,
    /// Count the samples that reach Zenoh instead, for an agent on `-m zenoh` (give it with
    /// `--agent-args "-m zenoh"`): the generator runs a Zenoh router listening on this
    /// endpoint (e.g. `tcp/127.0.0.1:7447`), which the agent is told to connect to
    /// (`ZENOH_CONFIG_OVERRIDE`, unless set already), and subscribes there.
    #[arg(long = "zenoh-router", value_name = "ENDPOINT")]
    pub zenoh_router: Option<String>,
}

fn main() -> Result<(), String> {
    let a = Args::parse();
    raise_fd_limit();
    if let Some(endpoint) = &a.zenoh_router {
        if std::env::var_os("ZENOH_CONFIG_OVERRIDE").is_none() {
            // Before any thread starts: the agents this process starts inherit it.
            std::env::set_var(
                "ZENOH_CONFIG_OVERRIDE",
                format!(
                    "connect/endpoints=[\"{endpoint}\"];listen/endpoints=[\"tcp/127.0.0.1:0\"]"
                ),
            );
        }
    }
    if let Some(other) = &a.compare_with {
        return compare(&a, other);
    }
    if !a.sweep.is_empty() {
        return sweep(&a);
    }
    let report = run(&a, a.agent_cmd.as_deref())?;
    print_report(&report);
    if let Some(path) = &a.json {
        let text = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    Ok(())
}

/// Runs the scenario alternately against our agent (or `--agent-cmd`) and `other`,
/// `--rounds` times each, and prints the medians and their ratios.
fn compare(a: &Args, other: &str) -> Result<(), String> {
    if a.no_agent {
        return Err("--compare-with starts both agents; it cannot use --no-agent".into());
    }
    let mut runs: [Vec<Report>; 2] = [Vec::new(), Vec::new()];
    for round in 0..a.rounds {
        for (side, cmd) in [a.agent_cmd.as_deref(), Some(other)]
            .into_iter()
            .enumerate()
        {
            eprintln!(
                "round {} of {}, agent {}",
                round + 1,
                a.rounds,
                ["A", "B"][side]
            );
            let r = run(a, cmd)?;
            print_report(&r);
            runs[side].push(r);
        }
    }
    let median = |side: usize, f: &dyn Fn(&Report) -> f64| {
        let mut v: Vec<f64> = runs[side].iter().map(f).filter(|x| x.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    type Metric = (&'static str, Box<dyn Fn(&Report) -> f64>);
    let metrics: Vec<Metric> = vec![
        ("set-up ms", Box::new(|r| r.setup_ms)),
        ("samples/s", Box::new(|r| r.samples_per_second)),
        ("lost", Box::new(|r| r.lost as f64)),
        ("p50 us", Box::new(|r| r.latency_us.p50)),
        ("p99 us", Box::new(|r| r.latency_us.p99)),
        (
            "into DDS samples/s",
            Box::new(|r| r.dds.as_ref().map_or(f64::NAN, |d| d.samples_per_second)),
        ),
        (
            "agent CPU us/sample",
            Box::new(|r| r.agent.as_ref().map_or(f64::NAN, |u| u.cpu_us_per_sample)),
        ),
        (
            "agent peak RSS MiB",
            Box::new(|r| {
                r.agent
                    .as_ref()
                    .map_or(f64::NAN, |u| u.peak_rss_kib as f64 / 1024.0)
            }),
        ),
    ];
    println!(
        "\nmedians of {} rounds; A = {}, B = {other}",
        a.rounds,
        a.agent_cmd.as_deref().unwrap_or("our xrce-agent")
    );
    println!("{:<22} {:>12} {:>12} {:>8}", "metric", "A", "B", "B / A");
    let mut table = Vec::new();
    for (name, f) in &metrics {
        let (x, y) = (median(0, f), median(1, f));
        println!("{name:<22} {x:>12.1} {y:>12.1} {:>8.2}", y / x);
        table.push(serde_json::json!({"metric": name, "a": x, "b": y, "ratio_b_over_a": y / x}));
    }
    if let Some(path) = &a.json {
        let doc = serde_json::json!({"a": runs[0], "b": runs[1], "medians": table});
        let text = serde_json::to_string_pretty(&doc).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    Ok(())
}

/// Runs the scenario for each publisher count of `--sweep`, prints a table, and writes the
/// SVG plot and the JSON of every run when asked.
fn sweep(a: &Args) -> Result<(), String> {
    let mut points = Vec::new();
    let mut reports = Vec::new();
    for &n in &a.sweep {
        let mut one = a.clone();
        one.publishers = n;
        eprintln!("sweep: {n} publishing clients");
        let r = run(&one, a.agent_cmd.as_deref())?;
        print_report(&r);
        points.push(plot::SweepPoint {
            clients: n,
            samples_per_second: r.samples_per_second,
            into_dds_per_second: r.dds.as_ref().map(|d| d.samples_per_second),
            p50_us: r.latency_us.p50,
            p99_us: r.latency_us.p99,
            // Deliveries: every sample is expected once at each subscriber.
            lost_fraction: r.lost as f64 / (f64::from(r.sent) * f64::from(r.subscribers)).max(1.0),
        });
        reports.push(r);
    }
    println!(
        "\n{:>8} {:>12} {:>12} {:>8} {:>10} {:>10}",
        "clients", "samples/s", "into DDS/s", "lost %", "p50 us", "p99 us"
    );
    for p in &points {
        println!(
            "{:>8} {:>12.0} {:>12} {:>8.2} {:>10.0} {:>10.0}",
            p.clients,
            p.samples_per_second,
            p.into_dds_per_second
                .map_or("-".to_string(), |v| format!("{v:.0}")),
            p.lost_fraction * 100.0,
            p.p50_us,
            p.p99_us
        );
    }
    if let Some(path) = &a.svg {
        let title = format!(
            "xrce-loadgen sweep: {} B {} samples, {} in total{}",
            a.payload.max(12),
            if a.best_effort {
                "best-effort"
            } else {
                "reliable"
            },
            a.samples,
            if a.rate > 0.0 {
                format!(" at {:.0}/s", a.rate)
            } else {
                ", unpaced".to_string()
            }
        );
        plot::write_svg(path, &title, &points)?;
        eprintln!("plot written to {}", path.display());
    }
    if let Some(path) = &a.json {
        let doc = serde_json::json!({"points": points, "runs": reports});
        let text = serde_json::to_string_pretty(&doc).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("writing {}: {e}", path.display()))?;
    }
    Ok(())
}

/// A client key in hexadecimal (`0x` optional) or decimal.
fn parse_client_key(text: &str) -> Result<u32, String> {
    let t = text.trim();
    match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
        Some(hex) => u32::from_str_radix(hex, 16),
        None => t.parse(),
    }
    .map_err(|e| format!("{text:?} is not a client key: {e}"))
}
