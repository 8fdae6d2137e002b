//! `xrce-agent status`: the live sessions and processes of a running agent, as a table
//! (`--watch` redraws it every second) or as JSON (`--json`). The data comes from the
//! running agent: its metrics endpoint's `/status` (`--metrics URL`), or the status
//! reports its processes write on this machine (`--instance NAME`, or every agent of this
//! user found in its private runtime directory: see
//! [`xrce_ipc::runtime_dir`]).
//!
//! What it prints comes from other processes, and partly from the network (a client's
//! peer address, a transport's description), so every string is made printable first
//! ([`printable`]): control characters (escape sequences, carriage returns, ...) and other
//! characters a terminal acts on without printing (bidirectional overrides, zero-width and
//! invisible formatting characters) become `?`, and a string is cut at
//! [`MAX_PRINTED_CHARS`]. Client keys are printed redacted, `0x****BBBB`: a key is what a
//! client's session is bound to (anyone who has it can claim the session), the last four
//! hex digits tell clients apart; `--show-keys` prints them whole (as does the JSON, then).

use std::fmt::Write as _;
use std::time::Duration;

use xrce_ipc::status::{self, ProcessReport};

use crate::metrics::AgentStatus;

/// Options of `xrce-agent status`.
#[derive(Debug, Clone, clap::Args)]
pub struct StatusArgs {
    /// The agent's metrics endpoint (as given to --metrics), e.g. http://127.0.0.1:9464 or
    /// 127.0.0.1:9464; its /status is read.
    #[arg(long, value_name = "URL")]
    pub metrics: Option<String>,
    /// Read the status reports of this local instance (default: every agent on this
    /// machine).
    #[arg(long, conflicts_with = "metrics")]
    pub instance: Option<String>,
    /// Redraw every second until interrupted.
    #[arg(long)]
    pub watch: bool,
    /// Print the status as JSON (the /status document; an array of them for several local
    /// agents) instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Print client keys whole; by default only their last four hex digits are shown
    /// (0x****BBBB), in the table and in the JSON.
    #[arg(long)]
    pub show_keys: bool,
}

/// The longest string printed from a report; a longer one is cut and ends with `…`.
pub const MAX_PRINTED_CHARS: usize = 256;

/// Whether a terminal would act on `c` rather than print it: control characters (C0, DEL,
/// C1) and the format, separator and invisible characters that reorder, hide or break text
/// (bidirectional marks and overrides, zero-width characters, line and paragraph
/// separators, variation selectors, tag characters, the byte-order mark).
pub fn is_unprintable(c: char) -> bool {
    c.is_control()
        || matches!(
            c,
            '\u{00AD}'
                | '\u{034F}'
                | '\u{061C}'
                | '\u{115F}'
                | '\u{1160}'
                | '\u{17B4}'
                | '\u{17B5}'
                | '\u{180B}'..='\u{180F}'
                | '\u{200B}'..='\u{200F}'
                | '\u{2028}'..='\u{202E}'
                | '\u{2060}'..='\u{206F}'
                | '\u{3164}'
                | '\u{FE00}'..='\u{FE0F}'
                | '\u{FEFF}'
                | '\u{FFA0}'
                | '\u{FFF0}'..='\u{FFFB}'
                | '\u{1D173}'..='\u{1D17A}'
                | '\u{E0000}'..='\u{E0FFF}'
        )
}

/// `s` made safe to print: every character a terminal would act on ([`is_unprintable`])
/// becomes `?`, and at most [`MAX_PRINTED_CHARS`] characters are kept.
pub fn printable(s: &str) -> String {
    let mut out = String::with_capacity(s.len().min(MAX_PRINTED_CHARS * 4));
    for (i, c) in s.chars().enumerate() {
        if i == MAX_PRINTED_CHARS {
            out.push('…');
            break;
        }
        out.push(if is_unprintable(c) { '?' } else { c });
    }
    out
}

/// Makes every string of `agent` printable ([`printable`]), map keys included, and redacts
/// its client keys unless `show_keys`.
pub fn sanitize(agent: &mut AgentStatus, show_keys: bool) {
    fn clean(s: &mut String) {
        *s = printable(s);
    }
    fn clean_keys(m: &mut std::collections::BTreeMap<String, u64>) {
        *m = std::mem::take(m)
            .into_iter()
            .map(|(k, v)| (printable(&k), v))
            .collect();
    }
    clean(&mut agent.instance);
    for p in &mut agent.processes {
        clean(&mut p.name);
        clean(&mut p.role);
        if let Some(f) = &mut p.frontend {
            clean(&mut f.transport);
            clean(&mut f.serving);
            clean_keys(&mut f.counters);
            clean_keys(&mut f.dropped);
            for s in &mut f.sessions {
                s.client_key = if show_keys {
                    printable(&s.client_key)
                } else {
                    crate::metrics::redact_key(&s.client_key)
                };
                clean(&mut s.peer);
                clean(&mut s.dialect);
            }
        }
        if let Some(w) = &mut p.worker {
            clean_keys(&mut w.entities);
            clean_keys(&mut w.dropped);
        }
        for c in &mut p.children {
            clean(&mut c.name);
            clean(&mut c.role);
        }
    }
}

/// JSON text with every unprintable character ([`is_unprintable`]) written as a `\u`
/// escape: serde_json escapes only C0 controls, and a string field this view does not know
/// yet (sanitized by [`sanitize`] or not) must not reach the terminal raw either. Valid
/// JSON stays valid (raw unprintables occur only inside strings; the structural line
/// breaks of pretty printing are kept).
fn escape_unprintables(json: &str) -> String {
    let mut out = String::with_capacity(json.len());
    for c in json.chars() {
        if c != '\n' && is_unprintable(c) {
            let mut units = [0u16; 2];
            for u in c.encode_utf16(&mut units) {
                let _ = write!(out, "\\u{u:04x}");
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// The stores of stopped agents: how many clients, how big, and when they go.
fn render_left(left: &[crate::sweep::Left], now_ms: u64) -> String {
    let window = xrce_frontend::session_store::TAKE_OVER_WITHIN.as_secs();
    let mut out = String::new();
    if left.is_empty() {
        return out;
    }
    out.push_str("\nstored sessions of stopped agents (kept for a restart to take over):\n");
    for l in left {
        let since = l
            .stored
            .last_alive_ms
            .map(|ms| now_ms.saturating_sub(ms) / 1000);
        let when = match since {
            Some(s) if s <= window => format!("stopped {s} s ago, removed after {window} s"),
            Some(s) => {
                format!("stopped {s} s ago, past the {window} s window: removed by the next sweep")
            }
            None => "never alive: removed by the next sweep".to_string(),
        };
        let _ = writeln!(
            out,
            "  {}: {} client(s), {} KiB ({when})",
            printable(&l.instance),
            l.stored.clients,
            l.stored.bytes.div_ceil(1024)
        );
    }
    out
}

/// Runs `xrce-agent status`.
pub fn run(args: &StatusArgs) -> anyhow::Result<()> {
    let local = args.metrics.is_none() && args.instance.is_none();
    loop {
        // What stopped agents of this user left in memory (their stored sessions), shown
        // under the table of the running ones.
        let left = if local && !args.json {
            crate::sweep::stopped_instances(None)
        } else {
            Vec::new()
        };
        let mut agents = match fetch(args) {
            Ok(a) => a,
            Err(_) if !left.is_empty() => Vec::new(),
            Err(e) => return Err(e),
        };
        for a in &mut agents {
            sanitize(a, args.show_keys);
        }
        let out = if args.json {
            escape_unprintables(&if agents.len() == 1
                && (args.metrics.is_some() || args.instance.is_some())
            {
                serde_json::to_string_pretty(&agents[0])?
            } else {
                serde_json::to_string_pretty(&agents)?
            })
        } else {
            let mut out = agents
                .iter()
                .map(|a| render(a, status::unix_ms()))
                .collect::<Vec<_>>()
                .join("\n");
            out.push_str(&render_left(&left, status::unix_ms()));
            out
        };
        if !args.watch {
            println!("{out}");
            return Ok(());
        }
        // Home the cursor and clear the screen, then draw.
        println!("\x1b[H\x1b[2J{out}");
        std::thread::sleep(Duration::from_secs(1));
    }
}

/// The status of the agent(s) asked for.
fn fetch(args: &StatusArgs) -> anyhow::Result<Vec<AgentStatus>> {
    if let Some(url) = &args.metrics {
        return Ok(vec![fetch_url(url, args.show_keys)?]);
    }
    if let Some(instance) = &args.instance {
        if !xrce_ipc::shm::valid_instance(instance) {
            anyhow::bail!(
                "instance name {:?} must be 1-32 characters of [A-Za-z0-9_-]",
                printable(instance)
            );
        }
        // A runtime or instance directory planted by another user is reported, not read.
        xrce_ipc::runtime_dir::check_instance_dir(instance)?;
        let dir = status::status_dir(instance);
        let s = AgentStatus::read(instance, &dir);
        if s.processes.is_empty() {
            anyhow::bail!(
                "no running agent with instance {instance:?} of this user on this machine (no \
                 live reports in {}); an agent of another user (or under systemd's \
                 RuntimeDirectory=) keeps them in its own runtime directory: run this as that \
                 user with the same XRCE_RUNTIME_DIR, or pass --metrics URL",
                dir.display()
            );
        }
        return Ok(vec![s]);
    }
    let found: Vec<AgentStatus> = xrce_ipc::runtime_dir::list_instances()?
        .into_iter()
        .map(|(name, dir)| AgentStatus::read(&name, &dir))
        .filter(|s| !s.processes.is_empty())
        .collect();
    if found.is_empty() {
        anyhow::bail!(
            "no running agent of this user found in {}; for an agent of another user, run \
             this as that user (with its XRCE_RUNTIME_DIR, if set), and for an agent \
             elsewhere, pass --metrics URL",
            xrce_ipc::runtime_dir::runtime_root().0.display()
        );
    }
    Ok(found)
}

/// `/status` of a metrics endpoint (which redacts client keys unless asked to show them).
fn fetch_url(url: &str, show_keys: bool) -> anyhow::Result<AgentStatus> {
    let base = if url.contains("://") {
        url.trim_end_matches('/').to_string()
    } else {
        format!("http://{}", url.trim_end_matches('/'))
    };
    let base = base
        .strip_suffix("/metrics")
        .or_else(|| base.strip_suffix("/status"))
        .unwrap_or(&base);
    let target = if show_keys {
        format!("{base}/status?keys=show")
    } else {
        format!("{base}/status")
    };
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .timeout_global(Some(Duration::from_secs(5)))
        .build()
        .into();
    let body = agent
        .get(&target)
        .call()
        .map_err(|e| anyhow::anyhow!("{target}: {e}"))?
        .body_mut()
        .with_config()
        .limit(64 << 20)
        .read_to_string()
        .map_err(|e| anyhow::anyhow!("{target}: {e}"))?;
    serde_json::from_str(&body).map_err(|e| anyhow::anyhow!("{target}: not an agent's status: {e}"))
}

/// A duration in seconds as `1h02m`, `3m05s` or `4.2s`.
fn human_duration(seconds: f64) -> String {
    let s = seconds.max(0.0);
    if s < 60.0 {
        format!("{s:.1}s")
    } else if s < 3600.0 {
        format!("{}m{:02}s", (s / 60.0) as u64, (s % 60.0) as u64)
    } else if s < 86_400.0 {
        format!(
            "{}h{:02}m",
            (s / 3600.0) as u64,
            ((s % 3600.0) / 60.0) as u64
        )
    } else {
        format!(
            "{}d{:02}h",
            (s / 86_400.0) as u64,
            ((s % 86_400.0) / 3600.0) as u64
        )
    }
}

/// Bytes as `12.3 MiB`.
fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= (1u64 << 30) as f64 {
        format!("{:.1} GiB", b / (1u64 << 30) as f64)
    } else if b >= (1u64 << 20) as f64 {
        format!("{:.1} MiB", b / (1u64 << 20) as f64)
    } else {
        format!("{:.0} KiB", b / 1024.0)
    }
}

/// Lays rows out in columns of the widest cell (every cell made [`printable`]).
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let rows: Vec<Vec<String>> = rows
        .iter()
        .map(|r| r.iter().map(|c| printable(c)).collect())
        .collect();
    let rows = &rows[..];
    let mut widths: Vec<usize> = header.iter().map(|h| h.len()).collect();
    for r in rows {
        for (i, c) in r.iter().enumerate() {
            if i < widths.len() {
                widths[i] = widths[i].max(c.chars().count());
            }
        }
    }
    let mut out = String::new();
    let line = |cells: Vec<String>, out: &mut String| {
        let mut l = String::new();
        for (i, c) in cells.iter().enumerate() {
            if i + 1 == cells.len() {
                l.push_str(c);
            } else {
                let _ = write!(l, "{c:<w$}  ", w = widths[i]);
            }
        }
        out.push_str(l.trim_end());
        out.push('\n');
    };
    line(header.iter().map(|h| h.to_string()).collect(), &mut out);
    for r in rows {
        line(r.clone(), &mut out);
    }
    out
}

/// The table of one agent as of `now_ms`.
pub fn render(agent: &AgentStatus, now_ms: u64) -> String {
    let supervisor = agent.processes.iter().find(|p| p.role == "supervisor");
    let restarts_of = |p: &ProcessReport| -> String {
        supervisor
            .and_then(|s| s.children.iter().find(|c| c.pid == Some(p.pid)))
            .map_or("-".into(), |c| c.restarts.to_string())
    };
    let sessions: usize = agent
        .processes
        .iter()
        .filter_map(|p| p.frontend.as_ref())
        .map(|f| f.sessions.len())
        .sum();
    let processes = agent
        .processes
        .iter()
        .filter(|p| p.runs_inside(&agent.processes).is_none())
        .count();
    let mut out = format!(
        "agent {}: {} processes, {} sessions\n\n",
        printable(&agent.instance),
        processes,
        sessions
    );
    let rows: Vec<Vec<String>> = agent
        .processes
        .iter()
        .map(|p| {
            let what = match (&p.frontend, &p.worker) {
                (Some(f), _) => format!(
                    "{} {}, {} sessions{}",
                    f.transport,
                    f.serving,
                    f.sessions.len(),
                    if f.connected { "" } else { ", no worker" }
                ),
                (_, Some(w)) => {
                    let n: u64 = w.entities.values().sum();
                    format!("{n} entities, {} front-ends", w.frontends)
                }
                _ => String::new(),
            };
            // A worker inside a front-end's process: its CPU and memory are the front-end's
            // row's.
            let (cpu, memory) = match p.runs_inside(&agent.processes) {
                Some(host) => (format!("in {}", printable(&host.name)), String::new()),
                None => (
                    format!("{:.1}s", p.cpu_seconds),
                    human_bytes(p.resident_bytes),
                ),
            };
            vec![
                p.name.clone(),
                p.role.clone(),
                p.pid.to_string(),
                human_duration(now_ms.saturating_sub(p.started_unix_ms) as f64 / 1000.0),
                restarts_of(p),
                cpu,
                memory,
                what,
            ]
        })
        .collect();
    out.push_str(&table(
        &[
            "PROCESS", "ROLE", "PID", "UPTIME", "RESTARTS", "CPU", "MEMORY", "SERVING",
        ],
        &rows,
    ));
    let mut rows: Vec<Vec<String>> = Vec::new();
    for p in &agent.processes {
        let Some(f) = &p.frontend else { continue };
        // The report is up to a second old: ages count from now.
        let behind = now_ms.saturating_sub(p.updated_unix_ms) as f64 / 1000.0;
        for s in &f.sessions {
            rows.push(vec![
                s.client_key.clone(),
                format!("0x{:02X}", s.session_id),
                format!("{}/{}", p.name, f.transport),
                if s.detached {
                    format!("{} (gone)", s.peer)
                } else {
                    s.peer.clone()
                },
                human_duration(s.age_seconds + behind),
                s.entities.to_string(),
                s.samples_in.to_string(),
                s.samples_out.to_string(),
                s.dropped.to_string(),
                format!("{} ago", human_duration(s.last_heard_seconds + behind)),
            ]);
        }
    }
    out.push('\n');
    if rows.is_empty() {
        out.push_str("no sessions\n");
    } else {
        out.push_str(&table(
            &[
                "CLIENT KEY",
                "SESSION",
                "FRONT-END",
                "PEER",
                "AGE",
                "ENTITIES",
                "SAMPLES IN",
                "SAMPLES OUT",
                "DROPS",
                "LAST HEARD",
            ],
            &rows,
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_ipc::status::{ChildStatus, FrontendStatus, SessionStatus};

    #[test]
    fn the_table_lists_processes_and_sessions() {
        let now = 1_000_000_000;
        let agent = AgentStatus {
            instance: "gw".into(),
            processes: vec![
                ProcessReport {
                    name: "supervisor".into(),
                    role: "supervisor".into(),
                    pid: 10,
                    started_unix_ms: now - 65_000,
                    children: vec![ChildStatus {
                        name: "xrce-frontend-eth".into(),
                        role: "frontend".into(),
                        pid: Some(12),
                        restarts: 3,
                        ..Default::default()
                    }],
                    ..Default::default()
                },
                ProcessReport {
                    name: "eth".into(),
                    role: "frontend".into(),
                    pid: 12,
                    started_unix_ms: now - 5_000,
                    updated_unix_ms: now,
                    resident_bytes: 5 << 20,
                    frontend: Some(FrontendStatus {
                        transport: "udp4".into(),
                        serving: "0.0.0.0:8888".into(),
                        connected: true,
                        sessions: vec![SessionStatus {
                            client_key: "0xAAAABBBB".into(),
                            session_id: 0x81,
                            peer: "127.0.0.1:40000".into(),
                            entities: 6,
                            samples_in: 10,
                            ..Default::default()
                        }],
                        ..Default::default()
                    }),
                    ..Default::default()
                },
            ],
        };
        let text = render(&agent, now);
        assert!(
            text.starts_with("agent gw: 2 processes, 1 sessions"),
            "{text}"
        );
        let eth = text
            .lines()
            .find(|l| l.starts_with("eth "))
            .expect("front-end row");
        assert!(eth.contains(" 3 "), "restarts: {eth}");
        assert!(
            eth.contains("5.0 MiB") && eth.contains("udp4 0.0.0.0:8888, 1 sessions"),
            "{eth}"
        );
        let session = text
            .lines()
            .find(|l| l.starts_with("0xAAAABBBB"))
            .expect("session row");
        for cell in ["0x81", "eth/udp4", "127.0.0.1:40000", " 6 ", " 10 "] {
            assert!(session.contains(cell), "{cell:?} in {session}");
        }
    }

    /// `--single-process`: the worker's report comes from the front-end's process, which
    /// is counted and shown once.
    #[test]
    fn a_worker_inside_a_front_end_is_not_a_process_of_its_own() {
        let front_end = ProcessReport {
            name: "eth".into(),
            role: "frontend".into(),
            pid: 12,
            cpu_seconds: 2.0,
            resident_bytes: 30 << 20,
            frontend: Some(FrontendStatus::default()),
            ..Default::default()
        };
        let worker = ProcessReport {
            name: "worker".into(),
            role: "worker".into(),
            worker: Some(Default::default()),
            frontend: None,
            ..front_end.clone()
        };
        let agent = AgentStatus {
            instance: "gw".into(),
            processes: vec![worker, front_end],
        };
        let text = render(&agent, 0);
        assert!(text.starts_with("agent gw: 1 processes"), "{text}");
        let row = text
            .lines()
            .find(|l| l.starts_with("worker "))
            .expect("worker row");
        assert!(row.contains("in eth") && !row.contains("MiB"), "{row}");
    }

    #[test]
    fn strings_from_reports_cannot_drive_the_terminal_and_keys_are_redacted() {
        let hostile = "eth\x1b]0;owned\x07\x1b[2J\r\u{202E}gnp.exe\u{200B}\u{9B}31m";
        let mut agent = AgentStatus {
            instance: hostile.into(),
            processes: vec![ProcessReport {
                name: hostile.into(),
                role: "frontend".into(),
                frontend: Some(FrontendStatus {
                    transport: hostile.into(),
                    serving: hostile.into(),
                    dropped: [(hostile.to_string(), 1)].into(),
                    sessions: vec![SessionStatus {
                        client_key: "0xAAAABBBB".into(),
                        peer: hostile.into(),
                        dialect: hostile.into(),
                        ..Default::default()
                    }],
                    ..Default::default()
                }),
                ..Default::default()
            }],
        };
        let mut shown = agent.clone();
        sanitize(&mut agent, false);
        let text = render(&agent, 0);
        let json = escape_unprintables(&serde_json::to_string_pretty(&agent).expect("json"));
        for out in [&text, &json] {
            assert!(
                !out.chars().any(|c| c != '\n' && is_unprintable(c)),
                "{out:?}"
            );
            assert!(out.contains("0x****BBBB"), "{out}");
            assert!(!out.contains("AAAA"), "{out}");
        }
        assert!(text.contains("eth?]0;owned??[2J??gnp.exe??31m"), "{text}");
        // Shown whole when asked; the JSON stays valid, with its escapes.
        sanitize(&mut shown, true);
        assert!(render(&shown, 0).contains("0xAAAABBBB"));
        let escaped = escape_unprintables("{\"a\": \"x\u{202E}\u{E0041}\"}");
        assert_eq!(escaped, "{\"a\": \"x\\u202e\\udb40\\udc41\"}");
        let back: serde_json::Value = serde_json::from_str(&escaped).expect("valid JSON");
        assert_eq!(back["a"], "x\u{202E}\u{E0041}");
        // Odd keys are hidden whole; long strings are cut.
        assert_eq!(crate::metrics::redact_key("0xAB"), "0x********");
        assert_eq!(crate::metrics::redact_key("0XaaaaBBBB"), "0x****BBBB");
        assert_eq!(
            crate::metrics::redact_key("0x****BBBB"),
            "0x****BBBB",
            "redacted once is enough"
        );
        assert_eq!(crate::metrics::redact_key("0x****\u{1b}[2J"), "0x********");
        let long = printable(&"x".repeat(1000));
        assert_eq!(long.chars().count(), MAX_PRINTED_CHARS + 1);
        assert!(long.ends_with('…'));
    }

    #[test]
    fn durations_read_well() {
        assert_eq!(human_duration(4.25), "4.2s");
        assert_eq!(human_duration(185.0), "3m05s");
        assert_eq!(human_duration(3720.0), "1h02m");
    }
}
