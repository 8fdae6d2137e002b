//! `xrce-agent status`: the live sessions and processes of a running agent, as a table
//! (`--watch` redraws it every second) or as JSON (`--json`). The data comes from the
//! running agent: its metrics endpoint's `/status` (`--metrics URL`), or the status
//! reports its processes write on this machine (`--instance NAME`, or every agent found).

use std::fmt::Write as _;
use std::time::Duration;

use xrce_common::ipc::status::{self, ProcessReport};

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
}

/// Runs `xrce-agent status`.
pub fn run(args: &StatusArgs) -> anyhow::Result<()> {
    loop {
        let agents = fetch(args)?;
        let out = if args.json {
            if agents.len() == 1 && (args.metrics.is_some() || args.instance.is_some()) {
                serde_json::to_string_pretty(&agents[0])?
            } else {
                serde_json::to_string_pretty(&agents)?
            }
        } else {
            agents
                .iter()
                .map(|a| render(a, status::unix_ms()))
                .collect::<Vec<_>>()
                .join("\n")
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
        return Ok(vec![fetch_url(url)?]);
    }
    if let Some(instance) = &args.instance {
        let dir = status::status_dir(instance);
        let s = AgentStatus::read(instance, &dir);
        if s.processes.is_empty() {
            anyhow::bail!(
                "no running agent with instance {instance:?} on this machine (no live reports in {})",
                dir.display()
            );
        }
        return Ok(vec![s]);
    }
    let found: Vec<AgentStatus> = status::instance_dirs()
        .into_iter()
        .map(|(name, dir)| AgentStatus::read(&name, &dir))
        .filter(|s| !s.processes.is_empty())
        .collect();
    if found.is_empty() {
        anyhow::bail!(
            "no running agent found on this machine; for an agent elsewhere, pass --metrics URL"
        );
    }
    Ok(found)
}

/// `/status` of a metrics endpoint.
fn fetch_url(url: &str) -> anyhow::Result<AgentStatus> {
    let base = if url.contains("://") {
        url.trim_end_matches('/').to_string()
    } else {
        format!("http://{}", url.trim_end_matches('/'))
    };
    let base = base
        .strip_suffix("/metrics")
        .or_else(|| base.strip_suffix("/status"))
        .unwrap_or(&base);
    let target = format!("{base}/status");
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

/// Lays rows out in columns of the widest cell.
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
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
    let mut out = format!(
        "agent {}: {} processes, {} sessions\n\n",
        agent.instance,
        agent.processes.len(),
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
            vec![
                p.name.clone(),
                p.role.clone(),
                p.pid.to_string(),
                human_duration(now_ms.saturating_sub(p.started_unix_ms) as f64 / 1000.0),
                restarts_of(p),
                format!("{:.1}s", p.cpu_seconds),
                human_bytes(p.resident_bytes),
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
    use xrce_common::ipc::status::{ChildStatus, FrontendStatus, SessionStatus};

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

    #[test]
    fn durations_read_well() {
        assert_eq!(human_duration(4.25), "4.2s");
        assert_eq!(human_duration(185.0), "3m05s");
        assert_eq!(human_duration(3720.0), "1h02m");
    }
}
