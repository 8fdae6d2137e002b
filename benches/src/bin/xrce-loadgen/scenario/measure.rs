//! The measurements around the measured phase: per-process CPU, the idle agent, latency
//! probes, the warm-up.

use std::time::{Duration, Instant};

use xrce_common::session::client::ClientEvent;

use crate::agent::{AgentUnderTest, ProcOne, ProcUsage};
use crate::dds_reader::DdsReader;
use crate::peer::Group;
use crate::report::IdleUse;
use crate::Args;

use super::*;

/// Each process of `after`, with the CPU it used since `before`.
pub(super) fn per_process_delta(before: &ProcUsage, after: &ProcUsage) -> Vec<ProcOne> {
    after
        .each
        .iter()
        .map(|p| {
            let b = before
                .each
                .iter()
                .find(|q| q.pid == p.pid)
                .map_or(0.0, |q| q.cpu_seconds);
            ProcOne {
                cpu_seconds: p.cpu_seconds - b,
                ..p.clone()
            }
        })
        .collect()
}

/// Keeps every session open and silent for `seconds` (the clients still answer what the
/// agent sends) and reads the agent's CPU and memory.
pub(super) fn measure_idle(
    seconds: f64,
    all: &mut Group,
    agent: Option<&AgentUnderTest>,
    empty: Option<&ProcUsage>,
    sessions: usize,
) -> Result<Option<IdleUse>, String> {
    let Some(agent) = agent else {
        return Ok(None);
    };
    // Let the set-up settle (discovery, held samples) before measuring.
    all.pump_until(Duration::from_secs(1), |_| false)?;
    let before = agent.usage();
    let t = Instant::now();
    all.pump_until(Duration::from_secs_f64(seconds), |_| false)?;
    let after = agent.usage();
    let secs = t.elapsed().as_secs_f64();
    Ok(match (empty, before, after) {
        (Some(empty), Some(b), Some(e)) => Some(IdleUse {
            seconds: secs,
            cpu_percent: 100.0 * (e.cpu_seconds - b.cpu_seconds) / secs,
            rss_before_kib: empty.rss_kib,
            rss_idle_kib: e.rss_kib,
            rss_bytes_per_session: (e.rss_kib.saturating_sub(empty.rss_kib) as f64 * 1024.0)
                / sessions.max(1) as f64,
            each: per_process_delta(&b, &e),
        }),
        _ => None,
    })
}

/// Each publisher writes a probe (tag `u32::MAX - j`) until every subscriber and the
/// independent DDS reader heard it. Returns when that was done and how many publishers were
/// never heard by some subscriber.
pub(super) fn probe(
    all: &mut Group,
    subscribers: usize,
    publishers: usize,
    stream: u8,
    payload: usize,
    base: Instant,
    dds: &Option<DdsReader>,
) -> Result<(Instant, usize), String> {
    // heard[s][j]: subscriber s got publisher j's probe (j from 1).
    let mut heard = vec![vec![false; publishers + 1]; subscribers];
    let mut missing = subscribers * publishers;
    let mut events = Vec::new();
    let end = Instant::now() + Duration::from_secs(60);
    let dds_pending = || dds.as_ref().is_some_and(|d| d.probes_heard() < publishers);
    let mut round = 0u64;
    // A publisher probes again only after this: the agent holds writes until DDS matched
    // their writer, and a probe every round would release thousands at once when it does.
    let probe_every = Duration::from_millis(100);
    let mut probed: Vec<Option<Instant>> = vec![None; publishers + 1];
    while (missing > 0 || dds_pending()) && Instant::now() < end {
        round += 1;
        // The DDS reader may still miss some: every publisher probes again now and then.
        let again = dds_pending() && round % 20 == 0;
        for j in 1..=publishers {
            let unheard = heard.iter().any(|h| !h[j]);
            let i = subscribers + j - 1;
            let due = probed[j].is_none_or(|t| t.elapsed() >= probe_every);
            if (unheard || again) && due && all.peers[i].client.can_send_reliable(stream) {
                probed[j] = Some(Instant::now());
                all.write(
                    i,
                    stream,
                    WRITER,
                    &sample(payload, u32::MAX - j as u32, base),
                );
            }
        }
        all.pump(&mut events, Duration::ZERO)?;
        for (i, e) in events.drain(..) {
            let ClientEvent::Data { data, .. } = e else {
                continue;
            };
            let Some((seq, _)) = tag(&data) else { continue };
            let j = (u32::MAX - seq) as usize;
            if let Some(slot) = heard.get_mut(i).and_then(|h| h.get_mut(j)) {
                if j >= 1 && !*slot {
                    *slot = true;
                    missing -= 1;
                }
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let matched = Instant::now();
    if dds_pending() {
        eprintln!(
            "the DDS reader heard {} of {publishers} publishers before the run",
            dds.as_ref().map_or(0, |d| d.probes_heard())
        );
    }
    let unmatched = (1..=publishers)
        .filter(|&j| heard.iter().any(|h| !h[j]))
        .count();
    // Late probes and their acknowledgements settle before the run.
    all.pump_until(Duration::from_millis(200), |_| false)?;
    Ok((matched, unmatched))
}

/// Sends `--warmup` samples (not counted) at the run's rate, then lets them drain.
pub(super) fn warm_up(
    a: &Args,
    all: &mut Group,
    subscribers: usize,
    rate: f64,
    stream: u8,
    payload: usize,
    base: Instant,
) -> Result<(), String> {
    let mut share = Share {
        next: WARMUP_TAG,
        step: 1,
        samples: WARMUP_TAG + a.warmup,
        rate,
        sent: 0,
        next_pub: subscribers,
    };
    let n = all.peers.len();
    let t0 = Instant::now();
    let end = t0 + Duration::from_secs(a.duration);
    let mut events = Vec::new();
    while !share.done() && Instant::now() < end {
        let form = super::traffic::SampleForm {
            stream,
            payload,
            base,
        };
        share.send_due(all, subscribers..n, t0, form, None);
        all.pump(&mut events, share.wait(t0))?;
        events.clear();
    }
    all.pump_until(Duration::from_millis(500), |_| false)?;
    eprintln!("warm-up: {} samples sent", share.sent);
    Ok(())
}

/// The MTU the simulated clients announce: the eProsima client's default (512), or, on
/// best-effort streams, enough for one sample of `payload` bytes in a message, as a client
/// built for such samples would be configured (the agent drops a best-effort sample bigger
/// than its client's MTU, as the reference agent does). Reliable runs keep 512, so their
/// large samples are fragmented as in earlier measurements.
pub(super) fn client_mtu(payload: usize, best_effort: bool) -> u16 {
    const DEFAULT: usize = 512;
    const HEADROOM: usize = 64;
    /// Below the largest UDP datagram (65,507 bytes).
    const MOST: usize = 65_000;
    let mtu = if best_effort {
        payload.saturating_add(HEADROOM).clamp(DEFAULT, MOST)
    } else {
        DEFAULT
    };
    u16::try_from(mtu).unwrap_or(u16::MAX)
}
