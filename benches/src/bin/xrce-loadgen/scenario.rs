//! One run of a scenario: start the agent, set up every client's session and entities,
//! optionally measure the idle agent, match, warm up, then the measured phase, where groups
//! of publishing clients send from their own threads and the subscribing clients record
//! every sample once.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::time::{Duration, Instant};

use xrce_common::session::client::ClientEvent;
use xrce_common::wire::{
    object_kind as k, stream_id, DataDeliveryControl, ReadSpecification, VariantExtra,
};

use crate::agent::{wait_for_agent, wait_for_tcp_agent, AgentUnderTest};
use crate::dds_reader::DdsReader;
use crate::peer::{Group, Peer};
use crate::report::{AgentUse, DdsReport, GeneratorUse, Percentiles, Report};
use crate::soak::{self, Killer, Track};
use crate::{Args, TransportArg};

mod measure;
mod traffic;

use measure::*;
use traffic::*;

/// Runs the scenario of `a` against the agent `agent_cmd` (ours when None).
pub fn run(a: &Args, agent_cmd: Option<&str>) -> Result<Report, String> {
    let (port, publishers, subscribers, samples, payload) = (
        a.port,
        a.publishers as usize,
        a.subscribers as usize,
        a.samples,
        a.payload.max(12),
    );
    let domain =
        u16::try_from(a.domain).map_err(|_| format!("domain {} is not a DDS domain", a.domain))?;
    // One flag per (subscriber, sample): bounded so that a typo cannot exhaust memory.
    if u64::from(samples) * subscribers as u64 > 1 << 32 {
        return Err("--samples × --subscribers must stay within 2^32".into());
    }
    let rate = match a.client_rate {
        Some(r) => r * publishers as f64,
        None => a.rate,
    };
    if a.subscriber_port.is_some() {
        if a.transport == TransportArg::Serial || a.null_agent {
            return Err("--subscriber-port is for an agent over UDP or TCP".into());
        }
        if agent_cmd.is_none() && !a.no_agent {
            return Err(
                "--subscriber-port needs an agent that serves it: --agent-cmd (a gateway \
                 config) or --no-agent"
                    .into(),
            );
        }
    }
    let stream = if a.best_effort {
        stream_id::BUILTIN_BEST_EFFORT
    } else {
        stream_id::BUILTIN_RELIABLE
    };
    let _null = if a.null_agent {
        Some(crate::null_agent::NullAgent::start(port)?)
    } else {
        None
    };
    let total = subscribers + publishers;
    // Serial: one pty pair per client, made before the agent starts (it opens the slaves).
    let mut lines = Vec::new();
    if a.transport == TransportArg::Serial {
        if a.null_agent {
            return Err("--null-agent serves UDP only".into());
        }
        for _ in 0..total {
            lines.push(crate::link::pty_pair()?);
        }
    }
    let device_file =
        std::env::temp_dir().join(format!("xrce-loadgen-devs-{}", std::process::id()));
    if !lines.is_empty() {
        let list: Vec<String> = lines.iter().map(|(_, p)| p.display().to_string()).collect();
        std::fs::write(&device_file, list.join("\n"))
            .map_err(|e| format!("writing {}: {e}", device_file.display()))?;
    }
    let mut agent = if a.no_agent || a.null_agent {
        None
    } else {
        let cmd = match agent_cmd {
            Some(c) => c.to_string(),
            None => {
                let exe = std::env::current_exe().map_err(|e| e.to_string())?;
                let ours = exe.with_file_name("xrce-agent");
                let transport = match a.transport {
                    TransportArg::Udp => "udp4 -p {port} --bind 127.0.0.1".to_string(),
                    TransportArg::Tcp => "tcp4 -p {port} --bind 127.0.0.1".to_string(),
                    TransportArg::Serial => format!("multiserial -f {{device_file}} -b {}", a.baud),
                };
                format!(
                    "{} {transport} --dds-interface 127.0.0.1 -v 3 {}",
                    ours.display(),
                    a.agent_args
                )
            }
        };
        let devices: Vec<String> = lines.iter().map(|(_, p)| p.display().to_string()).collect();
        let cmd = cmd
            .replace("{device_file}", &device_file.display().to_string())
            .replace("{devices}", &devices.join(" "));
        Some(AgentUnderTest::start(&cmd, port)?)
    };
    for port in std::iter::once(port).chain(a.subscriber_port) {
        let ready = match a.transport {
            TransportArg::Udp => wait_for_agent(port, Duration::from_secs(30), &mut agent),
            TransportArg::Tcp => wait_for_tcp_agent(port, Duration::from_secs(30), &mut agent),
            // Serial clients retry their CREATE_CLIENT until the agent opened their line.
            TransportArg::Serial => true,
        };
        if !ready {
            return Err(format!("no agent answers a ping on port {port}"));
        }
    }
    let usage_empty = agent
        .as_ref()
        .and_then(|a| a.settled_usage(Duration::from_secs(5)));
    let bodies = Bodies::new(a);
    let base = Instant::now();
    let dds = if let (Some(endpoint), false) = (&a.zenoh_router, a.null_agent) {
        Some(DdsReader::start_zenoh(
            endpoint, domain, samples, publishers, base,
        )?)
    } else if a.dds_reader && !a.null_agent {
        Some(DdsReader::start(
            domain,
            "LoadTopic",
            "Load",
            samples,
            publishers,
            base,
        )?)
    } else {
        None
    };

    // Peers 0..subscribers subscribe, the others publish (publisher j is peer
    // subscribers + j - 1, its probe tag u32::MAX - j).
    let mut peers = Vec::with_capacity(total);
    let mut lines = lines.into_iter();
    let mtu = client_mtu(payload, a.best_effort);
    for i in 0..total {
        let key = u32::try_from(i)
            .ok()
            .and_then(|i| a.first_client_key.checked_add(i))
            .ok_or("--first-client-key leaves no room for every client's key")?
            .to_be_bytes();
        let port = match a.subscriber_port {
            Some(p) if i < subscribers => p,
            _ => port,
        };
        let peer = match a.transport {
            TransportArg::Udp => {
                let host = 1 + (i % usize::from(a.source_addresses)) as u8;
                let source = std::net::Ipv4Addr::new(127, 0, 0, host);
                Peer::new(source, port, key, mtu).map_err(|e| format!("client socket: {e}"))?
            }
            TransportArg::Tcp => {
                Peer::tcp(port, key, mtu).map_err(|e| format!("client connection: {e}"))?
            }
            TransportArg::Serial => {
                let (line, _) = lines.next().ok_or("no pty for a client")?;
                Peer::serial(line, a.baud, key, mtu)
            }
        };
        peers.push(peer);
    }
    let mut all = Group::new(peers)?;
    let t_start = Instant::now();
    for i in 0..total {
        all.peers[i].client.connect(Instant::now());
        all.touch(i);
    }
    if !all.pump_until(Duration::from_secs(60), |ps| {
        ps.iter().all(|p| p.client.is_connected())
    })? {
        return Err("not every session was established within 60 s".into());
    }
    let sessions_at = t_start.elapsed();
    let extra = VariantExtra::Parent;
    for (i, p) in all.peers.iter_mut().enumerate() {
        p.create(
            PARTICIPANT,
            k::PARTICIPANT,
            bodies.participant.clone(),
            VariantExtra::DomainId(a.domain),
        )?;
        p.create(TOPIC, k::TOPIC, bodies.topic.clone(), extra(PARTICIPANT))?;
        if i < subscribers {
            p.create(
                SUBSCRIBER,
                k::SUBSCRIBER,
                bodies.group.clone(),
                extra(PARTICIPANT),
            )?;
            p.create(
                READER,
                k::DATAREADER,
                bodies.reader.clone(),
                extra(SUBSCRIBER),
            )?;
        } else {
            p.create(
                PUBLISHER,
                k::PUBLISHER,
                bodies.group.clone(),
                extra(PARTICIPANT),
            )?;
            p.create(
                WRITER,
                k::DATAWRITER,
                bodies.writer.clone(),
                extra(PUBLISHER),
            )?;
        }
    }
    (0..total).for_each(|i| all.touch(i));
    if !all.pump_until(Duration::from_secs(120), |ps| {
        ps.iter().all(|p| p.pending.is_empty())
    })? {
        return Err("not every entity was created within 120 s".into());
    }
    let setup = t_start.elapsed();
    eprintln!(
        "{total} sessions in {:.0} ms, their {} entities in {:.0} ms ({:.0} sessions/s)",
        sessions_at.as_secs_f64() * 1e3,
        total * 4,
        setup.as_secs_f64() * 1e3,
        total as f64 / setup.as_secs_f64()
    );
    let idle = if a.idle > 0.0 {
        measure_idle(
            a.idle,
            &mut all,
            agent.as_ref(),
            usage_empty.as_ref(),
            total,
        )?
    } else {
        None
    };

    let spec = ReadSpecification {
        preferred_stream_id: stream,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    for i in 0..subscribers {
        all.peers[i]
            .client
            .read(Instant::now(), READER, spec.clone())
            .map_err(|e| e.to_string())?;
        all.touch(i);
    }

    // Probe until DDS matched every writer with every reader: each publisher's probe comes
    // back to every subscriber (and reaches the independent DDS reader).
    let (matched, unmatched) = probe(
        &mut all,
        subscribers,
        publishers,
        stream,
        payload,
        base,
        &dds,
    )?;
    let matched = matched.saturating_duration_since(t_start);
    if a.warmup > 0 {
        warm_up(a, &mut all, subscribers, rate, stream, payload, base)?;
    }

    // The measured phase: the publishers are split into groups, one per thread; the first
    // group also holds the subscribers and is pumped by this thread.
    let threads = (a.threads as usize).clamp(1, publishers);
    let mut sizes = vec![0usize; threads];
    for j in 0..publishers {
        sizes[j * threads / publishers] += 1;
    }
    sizes[0] += subscribers;
    let mut groups = all.split(&sizes)?;
    let stop = AtomicBool::new(false);
    let sent_total = AtomicU32::new(0);
    let shares: Vec<Share> = (0..threads)
        .map(|t| Share {
            next: t as u32,
            step: threads as u32,
            samples,
            rate: rate / threads as f64,
            sent: 0,
            next_pub: 0,
        })
        .collect();
    let mut latencies = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 60_000_000_000, 3)
        .map_err(|e| e.to_string())?;
    let (mut received, mut duplicates) = (0u64, 0u64);
    // Kill soak: what was sent when and by whom, what arrived when, and the kills.
    let track = (a.kills > 0).then(|| Track::new(samples));
    let (mut receipts, mut repeated) = (Vec::new(), Vec::new());
    let mut seen = vec![false; samples as usize * subscribers];
    let usage_before = agent.as_ref().and_then(AgentUnderTest::usage);
    // CPU of the threads that drive the clients (not the DDS reader's nor a null agent's).
    let mut generator_cpu = 0.0;
    let form = SampleForm {
        stream,
        payload,
        base,
    };
    let t0 = Instant::now();
    let deadline = t0 + Duration::from_secs(a.duration);
    let mut killer = match (&track, agent.as_ref()) {
        (Some(_), Some(ag)) => Some(Killer::new(
            a.kill,
            a.kills,
            Duration::from_secs_f64(a.kill_every.max(0.1)),
            t0,
            ag.pid(),
        )),
        (Some(_), None) => {
            return Err("--kills needs an agent the generator starts (not --no-agent)".into())
        }
        _ => None,
    };
    let mut last_rx = t0;
    let expected = u64::from(samples) * subscribers as u64;
    let mut shares = shares.into_iter();
    let mut first_share = shares.next().ok_or("no generator thread")?;
    let (first, others) = groups.split_first_mut().ok_or("no client group")?;
    std::thread::scope(|scope| -> Result<(), String> {
        let mut handles = Vec::new();
        for (t, (g, mut share)) in others.iter_mut().zip(shares).enumerate() {
            let (stop, sent_total) = (&stop, &sent_total);
            let track = track.as_ref().map(|k| (k, t as u32 + 1));
            handles.push(scope.spawn(move || -> Result<f64, String> {
                let cpu = thread_cpu_seconds();
                let mut events = Vec::new();
                let n = g.peers.len();
                let mut counted = 0;
                // Keeps pumping after its share is sent: reliable streams still need their
                // acknowledgements and repairs.
                while !stop.load(Ordering::Relaxed) {
                    share.send_due(g, 0..n, t0, form, track);
                    if share.sent > counted {
                        sent_total.fetch_add(share.sent - counted, Ordering::Relaxed);
                        counted = share.sent;
                    }
                    if let Err(e) = g.pump(&mut events, share.wait(t0)) {
                        // The others stop too, rather than waiting out the duration.
                        stop.store(true, Ordering::Relaxed);
                        return Err(e);
                    }
                    events.clear();
                }
                Ok(thread_cpu_seconds() - cpu)
            }));
        }
        let cpu = thread_cpu_seconds();
        let n = first.peers.len();
        let mut events = Vec::new();
        let mut counted = 0;
        let mut last_report = t0;
        let result = loop {
            if received >= expected || Instant::now() >= deadline || stop.load(Ordering::Relaxed) {
                break Ok(());
            }
            // Everything sent and nothing more for a while: the rest is lost. Reliable samples
            // are still coming while the agent works through a backlog, so they get longer.
            let quiet = if stream == stream_id::BUILTIN_RELIABLE {
                Duration::from_secs(10)
            } else {
                Duration::from_secs(2)
            };
            if sent_total.load(Ordering::Relaxed) >= samples && last_rx.elapsed() > quiet {
                break Ok(());
            }
            first_share.send_due(
                first,
                subscribers..n,
                t0,
                form,
                track.as_ref().map(|k| (k, 0)),
            );
            if let Some(k) = killer.as_mut() {
                k.maybe_kill(Instant::now(), base);
            }
            if first_share.sent > counted {
                sent_total.fetch_add(first_share.sent - counted, Ordering::Relaxed);
                counted = first_share.sent;
            }
            if let Err(e) = first.pump(&mut events, first_share.wait(t0)) {
                break Err(e);
            }
            let now_ns = base.elapsed().as_nanos() as u64;
            for (i, e) in events.drain(..) {
                let ClientEvent::Data { data, .. } = e else {
                    continue;
                };
                let Some((seq, ts)) = tag(&data) else {
                    continue;
                };
                if i >= subscribers || seq >= samples {
                    continue;
                }
                let slot = &mut seen[i * samples as usize + seq as usize];
                let receipt = soak::Receipt {
                    at: now_ns,
                    seq,
                    subscriber: i as u32,
                };
                if *slot {
                    duplicates += 1;
                    if track.is_some() {
                        repeated.push(receipt);
                    }
                    continue;
                }
                *slot = true;
                if track.is_some() {
                    receipts.push(receipt);
                }
                received += 1;
                last_rx = Instant::now();
                let ns = now_ns.saturating_sub(ts).max(1);
                let _ = latencies.record(ns.min(60_000_000_000));
            }
            if last_report.elapsed() > Duration::from_secs(1) {
                last_report = Instant::now();
                eprintln!(
                    "progress: sent {}, received {received}",
                    sent_total.load(Ordering::Relaxed)
                );
            }
        };
        stop.store(true, Ordering::Relaxed);
        generator_cpu = thread_cpu_seconds() - cpu;
        for h in handles {
            generator_cpu += h.join().map_err(|_| "a generator thread panicked")??;
        }
        result
    })?;
    let sent = sent_total.load(Ordering::Relaxed);
    // Throughput over the time until the last sample arrived.
    let elapsed = last_rx
        .saturating_duration_since(t0)
        .max(Duration::from_millis(1));
    let wall = t0.elapsed().as_secs_f64();
    let usage_after = agent.as_ref().and_then(AgentUnderTest::usage);
    let counters = agent
        .as_ref()
        .and_then(|g| g.counters(xrce_ipc::status::unix_ms()));
    let soak_after = killer.as_ref().and_then(|_| usage_after.clone());
    if killer.as_ref().is_some_and(Killer::pending) {
        eprintln!("soak: the run ended before every kill was done (more --samples or a lower --kill-every)");
    }
    let mut dds_seen = None;
    let dds = match dds {
        Some(d) => {
            std::thread::sleep(Duration::from_millis(300));
            let mut c = d.finish()?;
            dds_seen = Some(std::mem::take(&mut c.seen));
            let secs = c
                .last_rx
                .map_or(Duration::from_millis(1), |l| {
                    l.saturating_duration_since(t0)
                })
                .max(Duration::from_millis(1))
                .as_secs_f64();
            Some(DdsReport {
                received: c.received,
                lost: u64::from(sent).saturating_sub(c.received),
                duplicates: c.duplicates,
                samples_per_second: c.received as f64 / secs,
                bytes_per_second: c.received as f64 * payload as f64 / secs,
                latency_us: Percentiles::of(&c.latencies),
                counted_by: if a.zenoh_router.is_some() {
                    "Zenoh (independent Zenoh subscriber, through its router)"
                } else {
                    "DDS (independent RustDDS reader)"
                },
            })
        }
        None => None,
    };
    if let (Some(path), Some(t)) = (a.lost_list.as_deref(), track.as_ref()) {
        soak::write_lost_list(path, t, &receipts, subscribers as u32, dds_seen.as_deref())
            .map_err(|e| format!("--lost-list {}: {e}", path.display()))?;
    }
    let report = Report {
        transport: format!("{:?}", a.transport).to_lowercase(),
        line_bytes_per_second: (a.transport == TransportArg::Serial)
            .then(|| f64::from(a.baud) / crate::link::BITS_PER_BYTE),
        publishers: publishers as u32,
        subscribers: subscribers as u32,
        payload_bytes: payload,
        reliable: stream == stream_id::BUILTIN_RELIABLE,
        creation: format!("{:?}", a.creation).to_lowercase(),
        rate_requested: rate,
        warmup_samples: a.warmup,
        threads: threads as u32,
        sessions_ms: sessions_at.as_secs_f64() * 1e3,
        setup_ms: setup.as_secs_f64() * 1e3,
        matched_ms: matched.as_secs_f64() * 1e3,
        unmatched_writers: unmatched,
        sent,
        received,
        lost: (u64::from(sent) * subscribers as u64).saturating_sub(received),
        duplicates,
        seconds: elapsed.as_secs_f64(),
        samples_per_second: received as f64 / elapsed.as_secs_f64(),
        bytes_per_second: (received as f64 * payload as f64) / elapsed.as_secs_f64(),
        dds,
        latency_us: Percentiles::of(&latencies),
        agent: match (usage_before, usage_after) {
            (Some(b), Some(e)) => Some(AgentUse {
                cpu_seconds: e.cpu_seconds - b.cpu_seconds,
                cpu_us_per_sample: (e.cpu_seconds - b.cpu_seconds) * 1e6 / (received.max(1) as f64),
                peak_rss_kib: e.peak_rss_kib,
                processes: e.processes,
                threads: e.threads,
                fds: e.fds,
                each: per_process_delta(&b, &e),
                counters,
            }),
            _ => None,
        },
        idle,
        generator: GeneratorUse {
            cpu_seconds: generator_cpu,
            busy_percent: 100.0 * generator_cpu / (wall * threads as f64).max(1e-3),
        },
        soak: match (&killer, &track) {
            (Some(k), Some(t)) => Some(soak::analyse(
                &k.kills,
                t,
                &receipts,
                &repeated,
                subscribers as u32,
                k.before.as_ref(),
                soak_after.as_ref(),
            )),
            _ => None,
        },
    };
    drop(agent);
    let _ = std::fs::remove_file(&device_file);
    Ok(report)
}
