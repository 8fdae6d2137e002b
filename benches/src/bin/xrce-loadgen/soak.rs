//! Kill soak (`--kills N --kill worker|frontend|alternate`): while the scenario runs, the
//! agent's DDS worker or front-end is SIGKILLed every `--kill-every` seconds, and each kill
//! is accounted for: samples lost, delivered twice and out of order (per publisher and
//! subscriber: a reliable stream promises order) among those sent around it, and how long
//! until a sample sent after it reached a subscriber. The agent's memory and descriptors
//! before and after tell whether the restarts leak.

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::agent::{proc_usage, ProcUsage};

/// What to kill.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum KillTarget {
    /// The DDS worker.
    Worker,
    /// The (first) front-end.
    Frontend,
    /// The worker, then the front-end, and so on.
    Alternate,
    /// The one process of an agent run with `--single-process` (front-end and worker).
    Single,
}

/// Samples lost or repeated because of a kill are the ones sent this long before it or
/// after it (until the next kill): the front-end resends to a new worker the reliable
/// writes the old one executed in the last 1.5 s.
const BEFORE: Duration = Duration::from_secs(2);

/// Per sample: when it was sent (ns since the run's base; 0 = not sent) and by whom.
#[derive(Debug)]
pub struct Track {
    sent_at: Vec<AtomicU64>,
    publisher: Vec<AtomicU32>,
}

impl Track {
    /// Room for `samples` samples.
    pub fn new(samples: u32) -> Self {
        Track {
            sent_at: (0..samples).map(|_| AtomicU64::new(0)).collect(),
            publisher: (0..samples).map(|_| AtomicU32::new(0)).collect(),
        }
    }

    /// Records that `publisher` sent sample `seq` at `ns`.
    pub fn sent(&self, seq: u32, publisher: u32, ns: u64) {
        if let (Some(t), Some(p)) = (
            self.sent_at.get(seq as usize),
            self.publisher.get(seq as usize),
        ) {
            t.store(ns.max(1), Ordering::Relaxed);
            p.store(publisher, Ordering::Relaxed);
        }
    }
}

/// One delivery to a subscriber.
#[derive(Debug, Clone, Copy)]
pub struct Receipt {
    /// When (ns since the base).
    pub at: u64,
    /// Which sample.
    pub seq: u32,
    /// To which subscriber.
    pub subscriber: u32,
}

/// A kill done.
#[derive(Debug, Clone, Copy)]
pub struct Kill {
    /// When (ns since the base).
    pub at: u64,
    /// `worker`, `frontend` or `single-process`.
    pub target: &'static str,
}

/// The kills of a run.
#[derive(Debug)]
pub struct Killer {
    target: KillTarget,
    left: u32,
    every: Duration,
    next: Instant,
    agent: u32,
    /// Kills done.
    pub kills: Vec<Kill>,
    /// The agent's use before the first kill.
    pub before: Option<ProcUsage>,
}

impl Killer {
    /// `n` kills of `target`, the first `every` after `start`, in the process tree of
    /// `agent`.
    pub fn new(target: KillTarget, n: u32, every: Duration, start: Instant, agent: u32) -> Self {
        Killer {
            target,
            left: n,
            every,
            next: start + every,
            agent,
            kills: Vec::new(),
            before: proc_usage(agent),
        }
    }

    /// Whether kills are left.
    pub fn pending(&self) -> bool {
        self.left > 0
    }

    /// Kills the next process if it is time.
    pub fn maybe_kill(&mut self, now: Instant, base: Instant) {
        if self.left == 0 || now < self.next {
            return;
        }
        self.next = now + self.every;
        let target = match self.target {
            KillTarget::Worker => "worker",
            KillTarget::Frontend => "frontend",
            KillTarget::Alternate if self.kills.len() % 2 == 0 => "worker",
            KillTarget::Alternate => "frontend",
            KillTarget::Single => "single-process",
        };
        let suffix = match target {
            "worker" => " dds-worker",
            "single-process" => " single-process",
            _ => " frontend",
        };
        let Some(usage) = proc_usage(self.agent) else {
            return;
        };
        let Some(p) = usage.each.iter().find(|p| p.name.ends_with(suffix)) else {
            // Not back yet from the last kill: try again shortly.
            self.next = now + Duration::from_millis(100);
            return;
        };
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(p.pid as i32),
            nix::sys::signal::Signal::SIGKILL,
        );
        self.left -= 1;
        self.kills.push(Kill {
            at: base.elapsed().as_nanos() as u64,
            target,
        });
        eprintln!(
            "soak: killed the {target} (pid {}), {} left",
            p.pid, self.left
        );
    }
}

/// What one kill cost.
#[derive(Debug, Clone, serde::Serialize)]
pub struct KillReport {
    /// `worker`, `frontend` or `single-process`.
    pub target: &'static str,
    /// Seconds into the run.
    pub at_seconds: f64,
    /// Deliveries missing (sample, subscriber) among the samples sent around it.
    pub lost: u64,
    /// Deliveries repeated.
    pub duplicated: u64,
    /// Deliveries that came after a later sample of the same publisher.
    pub reordered: u64,
    /// From the kill until a sample sent after it reached a subscriber, ms.
    pub recovery_ms: Option<f64>,
    /// When the lost samples were sent, ms from the kill (negative: before it): the earliest
    /// and the latest.
    pub lost_sent_ms: Option<(f64, f64)>,
}

/// The soak's result.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SoakReport {
    /// Every kill.
    pub kills: Vec<KillReport>,
    /// Losses, repeats and reorderings outside any kill's window.
    pub outside: (u64, u64, u64),
    /// The agent's resident memory (KiB) and descriptors before the first kill and after.
    pub rss_kib: (u64, u64),
    /// Descriptors before and after.
    pub fds: (u64, u64),
}

/// For each sample, by sequence number, the subscribers (a bit each, up to 64) that did not
/// receive it.
fn missed_by(track: &Track, receipts: &[Receipt], subscribers: u32) -> Vec<u64> {
    let all = if subscribers >= 64 {
        u64::MAX
    } else {
        (1u64 << subscribers) - 1
    };
    let mut missed = vec![all; track.sent_at.len()];
    for r in receipts {
        if let Some(m) = missed.get_mut(r.seq as usize) {
            *m &= !(1 << r.subscriber.min(63));
        }
    }
    missed
}

/// Writes every sample some subscriber did not get, a line each: its sequence number, its
/// publisher, when it was sent (ms from the start), and whether the independent DDS reader
/// got it (`dds`, `-`, or `?` without that reader): `--lost-list`.
pub fn write_lost_list(
    path: &std::path::Path,
    track: &Track,
    receipts: &[Receipt],
    subscribers: u32,
    dds_seen: Option<&[bool]>,
) -> std::io::Result<()> {
    use std::io::Write as _;
    let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(out, "# seq publisher sent_ms dds")?;
    for (seq, missed) in missed_by(track, receipts, subscribers).iter().enumerate() {
        let sent = track.sent_at[seq].load(Ordering::Relaxed);
        if sent == 0 || *missed == 0 {
            continue;
        }
        let publisher = track.publisher[seq].load(Ordering::Relaxed);
        let dds = match dds_seen.map(|s| s.get(seq).copied().unwrap_or(false)) {
            Some(true) => "dds",
            Some(false) => "-",
            None => "?",
        };
        writeln!(out, "{seq} {publisher} {} {dds}", sent / 1_000_000)?;
    }
    out.flush()
}

/// Accounts each kill from what was sent and received.
pub fn analyse(
    kills: &[Kill],
    track: &Track,
    receipts: &[Receipt],
    duplicates: &[Receipt],
    subscribers: u32,
    before: Option<&ProcUsage>,
    after: Option<&ProcUsage>,
) -> SoakReport {
    let before_ns = BEFORE.as_nanos() as u64;
    // The window of kill k: sent in [at_k - BEFORE, at_{k+1} - BEFORE).
    let window_of = |sent: u64| -> Option<usize> {
        let i = kills.partition_point(|k| k.at.saturating_sub(before_ns) <= sent);
        i.checked_sub(1)
    };
    let n = kills.len();
    let (mut lost, mut dup, mut reord) = (vec![0u64; n], vec![0u64; n], vec![0u64; n]);
    let mut lost_span: Vec<Option<(u64, u64)>> = vec![None; n];
    let mut outside = (0u64, 0u64, 0u64);
    let mut bump = |w: Option<usize>, which: u8| {
        let slot = match (w, which) {
            (Some(i), 0) => &mut lost[i],
            (Some(i), 1) => &mut dup[i],
            (Some(i), _) => &mut reord[i],
            (None, 0) => &mut outside.0,
            (None, 1) => &mut outside.1,
            (None, _) => &mut outside.2,
        };
        *slot += 1;
    };
    let sent_at = |seq: u32| -> u64 {
        track
            .sent_at
            .get(seq as usize)
            .map_or(0, |t| t.load(Ordering::Relaxed))
    };
    // Lost: sent, and not received by a subscriber.
    for (seq, missed) in missed_by(track, receipts, subscribers).iter().enumerate() {
        let s = sent_at(seq as u32);
        if s == 0 {
            continue;
        }
        let missing = missed.count_ones();
        if missing > 0 {
            if let Some(span) = window_of(s).and_then(|w| lost_span.get_mut(w)) {
                let (a, b) = span.get_or_insert((s, s));
                *a = (*a).min(s);
                *b = (*b).max(s);
            }
        }
        for _ in 0..missing {
            bump(window_of(s), 0);
        }
    }
    for d in duplicates {
        bump(window_of(sent_at(d.seq)), 1);
    }
    // Reordered: per (subscriber, publisher), a delivery below the highest delivered yet.
    let mut sorted: Vec<&Receipt> = receipts.iter().collect();
    sorted.sort_by_key(|r| r.at);
    let mut highest: std::collections::HashMap<(u32, u32), u32> = Default::default();
    for r in &sorted {
        let publisher = track
            .publisher
            .get(r.seq as usize)
            .map_or(0, |p| p.load(Ordering::Relaxed));
        let h = highest.entry((r.subscriber, publisher)).or_insert(r.seq);
        if r.seq < *h {
            bump(window_of(sent_at(r.seq)), 2);
        } else {
            *h = r.seq;
        }
    }
    // Recovery: the first delivery of a sample sent after the kill.
    let kills_out = kills
        .iter()
        .enumerate()
        .map(|(i, k)| {
            let recovery = sorted
                .iter()
                .filter(|r| sent_at(r.seq) > k.at)
                .map(|r| r.at)
                .min()
                .map(|t| t.saturating_sub(k.at) as f64 / 1e6);
            KillReport {
                target: k.target,
                at_seconds: k.at as f64 / 1e9,
                lost: lost[i],
                duplicated: dup[i],
                reordered: reord[i],
                recovery_ms: recovery,
                lost_sent_ms: lost_span[i].map(|(a, b)| {
                    let rel = |t: u64| (t as f64 - k.at as f64) / 1e6;
                    (rel(a), rel(b))
                }),
            }
        })
        .collect();
    SoakReport {
        kills: kills_out,
        outside,
        rss_kib: (
            before.map_or(0, |u| u.rss_kib),
            after.map_or(0, |u| u.rss_kib),
        ),
        fds: (before.map_or(0, |u| u.fds), after.map_or(0, |u| u.fds)),
    }
}

/// Prints the soak's summary: totals and recovery percentiles per target, and every kill
/// that lost, repeated or reordered something.
pub fn print(r: &SoakReport) {
    for target in ["worker", "frontend", "single-process"] {
        let ks: Vec<&KillReport> = r.kills.iter().filter(|k| k.target == target).collect();
        if ks.is_empty() {
            continue;
        }
        let mut rec: Vec<f64> = ks.iter().filter_map(|k| k.recovery_ms).collect();
        rec.sort_by(f64::total_cmp);
        let pct = |p: f64| -> f64 {
            if rec.is_empty() {
                return f64::NAN;
            }
            rec[((rec.len() - 1) as f64 * p).round() as usize]
        };
        let sum = |f: fn(&KillReport) -> u64| ks.iter().map(|k| f(k)).sum::<u64>();
        let affected = ks
            .iter()
            .filter(|k| k.lost + k.duplicated + k.reordered > 0)
            .count();
        println!(
            "  soak: {} kills of the {target}: lost {}, duplicated {}, reordered {} ({} kills with any); recovery ms p50 {:.0} p99 {:.0} max {:.0}; {} never recovered",
            ks.len(),
            sum(|k| k.lost),
            sum(|k| k.duplicated),
            sum(|k| k.reordered),
            affected,
            pct(0.5),
            pct(0.99),
            rec.last().copied().unwrap_or(f64::NAN),
            ks.len() - rec.len(),
        );
        for k in ks
            .iter()
            .filter(|k| k.lost + k.duplicated + k.reordered > 0)
        {
            let span = k.lost_sent_ms.map_or(String::new(), |(a, b)| {
                format!(" (the lost sent {a:+.0} to {b:+.0} ms from the kill)")
            });
            println!(
                "    at {:.1} s: lost {}, duplicated {}, reordered {}{span}",
                k.at_seconds, k.lost, k.duplicated, k.reordered
            );
        }
    }
    println!(
        "  soak: outside the kills' windows: lost {}, duplicated {}, reordered {}",
        r.outside.0, r.outside.1, r.outside.2
    );
    println!(
        "  soak: agent RSS {:.1} -> {:.1} MiB, descriptors {} -> {}",
        r.rss_kib.0 as f64 / 1024.0,
        r.rss_kib.1 as f64 / 1024.0,
        r.fds.0,
        r.fds.1
    );
}
