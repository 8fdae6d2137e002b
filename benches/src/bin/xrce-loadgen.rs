//! `xrce-loadgen`: a load generator. N publishing XRCE clients and one subscribing client
//! (common's client state machine, one UDP socket and session each) talk through a running
//! agent; it reports session set-up time, the samples/s delivered client → agent → DDS →
//! agent → client, losses, and latency percentiles.
//!
//! Usage: `xrce-loadgen --port 8888 [--publishers 1] [--samples 20000] [--rate 0] [--payload 40]
//! [--domain 42] [--best-effort]` against an agent started separately, e.g.
//! `xrce-agent udp4 -p 8888 --dds-interface 127.0.0.1`. `--rate 0` sends as fast as the
//! reliable windows allow.

use std::collections::HashSet;
use std::net::UdpSocket;
use std::time::{Duration, Instant};

use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind as k, status, stream_id, ClientKey, DataDeliveryControl, ObjectId, ObjectVariant,
    ReadSpecification, Representation, RequestId, VariantExtra,
};

/// One simulated client: its protocol state and its socket.
struct Peer {
    client: Client,
    socket: UdpSocket,
    pending: HashSet<RequestId>,
}

impl Peer {
    fn new(port: u16, key: [u8; 4]) -> std::io::Result<Self> {
        let socket = UdpSocket::bind("127.0.0.1:0")?;
        socket.connect(("127.0.0.1", port))?;
        socket.set_nonblocking(true)?;
        Ok(Peer {
            client: Client::new(ClientConfig::new(ClientKey(key))),
            socket,
            pending: HashSet::new(),
        })
    }

    /// Sends what is due, receives what arrived, and collects events.
    fn pump(&mut self, buf: &mut [u8], events: &mut Vec<ClientEvent>) -> Result<(), String> {
        let now = Instant::now();
        while let Ok(n) = self.socket.recv(buf) {
            self.client.handle_datagram(now, &buf[..n]);
        }
        self.client.handle_timeout(now);
        while let Some(t) = self.client.poll_transmit() {
            let _ = self.socket.send(&t);
        }
        for e in std::iter::from_fn(|| self.client.poll_event()) {
            match e {
                ClientEvent::Status(s) if self.pending.remove(&s.related.request_id) => {
                    if s.result.status != status::OK {
                        return Err(format!(
                            "creation refused with status {:#04x}",
                            s.result.status
                        ));
                    }
                }
                other => events.push(other),
            }
        }
        Ok(())
    }

    /// Queues a CREATE; its STATUS is awaited by [`pump`] through `pending`.
    fn create(
        &mut self,
        id: ObjectId,
        kind: u8,
        xml: &str,
        extra: VariantExtra,
    ) -> Result<(), String> {
        let v = ObjectVariant {
            kind,
            representation: Representation::Xml(xml.into()),
            extra,
        };
        let req = self
            .client
            .create(Instant::now(), id, v, false, true)
            .map_err(|e| e.to_string())?;
        self.pending.insert(req);
        Ok(())
    }
}

fn arg(args: &[String], name: &str, default: u64) -> u64 {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Pumps every peer until `done` holds or `limit` passes.
fn pump_until(
    peers: &mut [Peer],
    limit: Duration,
    mut done: impl FnMut(&[Peer]) -> bool,
) -> Result<bool, String> {
    let end = Instant::now() + limit;
    let mut buf = vec![0u8; 65_536];
    let mut ignored = Vec::new();
    let mut last_report = Instant::now();
    while Instant::now() < end {
        for p in peers.iter_mut() {
            p.pump(&mut buf, &mut ignored)?;
        }
        ignored.clear();
        if done(peers) {
            return Ok(true);
        }
        if last_report.elapsed() > Duration::from_secs(1) {
            last_report = Instant::now();
            let connected = peers.iter().filter(|p| p.client.is_connected()).count();
            let pending: usize = peers.iter().map(|p| p.pending.len()).sum();
            eprintln!(
                "set-up: {connected} of {} sessions, {pending} creations pending",
                peers.len()
            );
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    Ok(false)
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().collect();
    let port = arg(&args, "--port", 8888) as u16;
    let publishers = arg(&args, "--publishers", 1).clamp(1, 60_000) as usize;
    let samples = arg(&args, "--samples", 20_000) as u32;
    let payload = arg(&args, "--payload", 40).max(12) as usize;
    let domain = arg(&args, "--domain", 42) as i16;
    let rate = arg(&args, "--rate", 0) as f64;
    let stream = if args.iter().any(|a| a == "--best-effort") {
        stream_id::BUILTIN_BEST_EFFORT
    } else {
        stream_id::BUILTIN_RELIABLE
    };
    let topic = "<dds><topic><name>LoadTopic</name><dataType>Load</dataType></topic></dds>";
    let endpoint = |e: &str| {
        format!(
            "<dds><{e}><topic><kind>NO_KEY</kind><name>LoadTopic</name><dataType>Load</dataType></topic><qos><reliability><kind>RELIABLE</kind></reliability><durability><kind>VOLATILE</kind></durability><historyQos><kind>KEEP_LAST</kind><depth>1000</depth></historyQos></qos></{e}></dds>"
        )
    };
    // Peer 0 subscribes, the others publish.
    let mut peers = Vec::with_capacity(publishers + 1);
    for i in 0..=publishers {
        peers.push(
            Peer::new(port, [0x10, 0xAD, (i >> 8) as u8, i as u8]).map_err(|e| e.to_string())?,
        );
    }
    let t_start = Instant::now();
    for p in peers.iter_mut() {
        p.client.connect(Instant::now());
    }
    if !pump_until(&mut peers, Duration::from_secs(60), |ps| {
        ps.iter().all(|p| p.client.is_connected())
    })? {
        return Err("not every session was established within 60 s".into());
    }
    let sessions_at = t_start.elapsed();
    let (part, tp) = (ObjectId::new(1, k::PARTICIPANT), ObjectId::new(1, k::TOPIC));
    let (subscriber, reader) = (
        ObjectId::new(1, k::SUBSCRIBER),
        ObjectId::new(1, k::DATAREADER),
    );
    let (publisher, writer) = (
        ObjectId::new(1, k::PUBLISHER),
        ObjectId::new(1, k::DATAWRITER),
    );
    for (i, p) in peers.iter_mut().enumerate() {
        p.create(
            part,
            k::PARTICIPANT,
            "<dds><participant><rtps><name>load</name></rtps></participant></dds>",
            VariantExtra::DomainId(domain),
        )?;
        p.create(tp, k::TOPIC, topic, VariantExtra::Parent(part))?;
        if i == 0 {
            p.create(subscriber, k::SUBSCRIBER, "", VariantExtra::Parent(part))?;
            p.create(
                reader,
                k::DATAREADER,
                &endpoint("data_reader"),
                VariantExtra::Parent(subscriber),
            )?;
        } else {
            p.create(publisher, k::PUBLISHER, "", VariantExtra::Parent(part))?;
            p.create(
                writer,
                k::DATAWRITER,
                &endpoint("data_writer"),
                VariantExtra::Parent(publisher),
            )?;
        }
    }
    if !pump_until(&mut peers, Duration::from_secs(120), |ps| {
        ps.iter().all(|p| p.pending.is_empty())
    })? {
        return Err("not every entity was created within 120 s".into());
    }
    let setup = t_start.elapsed();
    eprintln!(
        "{} sessions in {:.0} ms, their {} entities in {:.0} ms ({:.0} sessions/s)",
        peers.len(),
        sessions_at.as_secs_f64() * 1e3,
        peers.len() * 4,
        setup.as_secs_f64() * 1e3,
        peers.len() as f64 / setup.as_secs_f64()
    );
    let spec = ReadSpecification {
        preferred_stream_id: stream,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    peers[0]
        .client
        .read(Instant::now(), reader, spec)
        .map_err(|e| e.to_string())?;

    let base = Instant::now();
    let sample = |seq: u32| {
        let mut v = vec![0u8; payload];
        v[0..4].copy_from_slice(&seq.to_le_bytes());
        v[4..12].copy_from_slice(&(base.elapsed().as_nanos() as u64).to_le_bytes());
        v
    };
    let mut buf = vec![0u8; 65_536];
    let mut events = Vec::new();
    // Probe until DDS matched every writer with the reader: each publisher's probe comes back.
    let mut heard = vec![false; peers.len()];
    heard[0] = true;
    let probe_end = Instant::now() + Duration::from_secs(60);
    while heard.iter().any(|h| !h) && Instant::now() < probe_end {
        for (i, p) in peers.iter_mut().enumerate().skip(1) {
            if !heard[i] && p.client.can_send_reliable(stream) {
                let _ =
                    p.client
                        .write(Instant::now(), stream, writer, &sample(u32::MAX - i as u32));
            }
        }
        for p in peers.iter_mut() {
            p.pump(&mut buf, &mut events)?;
        }
        for e in events.drain(..) {
            if let ClientEvent::Data { data, .. } = e {
                let tag = u32::from_le_bytes([data[0], data[1], data[2], data[3]]);
                if let Some(i) = u32::MAX
                    .checked_sub(tag)
                    .map(|i| i as usize)
                    .filter(|i| *i < heard.len())
                {
                    heard[i] = true;
                }
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let matched = t_start.elapsed();
    let unmatched = heard.iter().filter(|h| !**h).count();
    std::thread::sleep(Duration::from_millis(200));
    for p in peers.iter_mut() {
        p.pump(&mut buf, &mut Vec::new())?;
    }

    // The run: publishers take turns; the subscriber records each sample once.
    let (mut sent, mut next_pub) = (0u32, 1usize);
    let mut latencies = Vec::with_capacity(samples as usize);
    let mut seen = vec![false; samples as usize];
    let t0 = Instant::now();
    let mut last_report = t0;
    let deadline = t0 + Duration::from_secs(60);
    while (latencies.len() as u32) < samples && Instant::now() < deadline {
        let allowed = if rate > 0.0 {
            ((t0.elapsed().as_secs_f64() * rate) as u32).min(samples)
        } else {
            samples
        };
        let mut tries = 0;
        while sent < allowed && tries < publishers {
            let p = &mut peers[next_pub];
            next_pub = if next_pub == publishers {
                1
            } else {
                next_pub + 1
            };
            if stream == stream_id::BUILTIN_RELIABLE && !p.client.can_send_reliable(stream) {
                tries += 1;
                continue;
            }
            tries = 0;
            let _ = p
                .client
                .write(Instant::now(), stream, writer, &sample(sent));
            sent += 1;
            if sent % 64 == 0 {
                break;
            }
        }
        for p in peers.iter_mut() {
            p.pump(&mut buf, &mut events)?;
        }
        let now_ns = base.elapsed().as_nanos() as u64;
        for e in events.drain(..) {
            if let ClientEvent::Data { data, .. } = e {
                let seq = u32::from_le_bytes([data[0], data[1], data[2], data[3]]) as usize;
                if seq < seen.len() && !seen[seq] {
                    seen[seq] = true;
                    let mut ts = [0u8; 8];
                    ts.copy_from_slice(&data[4..12]);
                    latencies.push(now_ns.saturating_sub(u64::from_le_bytes(ts)));
                }
            }
        }
        if last_report.elapsed() > Duration::from_secs(1) {
            last_report = Instant::now();
            eprintln!("progress: sent {sent}, received {}", latencies.len());
        }
    }
    let elapsed = t0.elapsed();
    latencies.sort_unstable();
    let pct = |p: f64| {
        latencies
            .get(((latencies.len() as f64 * p) as usize).min(latencies.len().saturating_sub(1)))
            .map_or(0.0, |n| *n as f64 / 1000.0)
    };
    println!(
        "{} publishers + 1 subscriber: set-up {:.0} ms, all writers matched at {:.0} ms ({unmatched} never); {} of {} samples of {} B in {:.2} s = {:.0} samples/s, {} lost; latency us p50 {:.0} p90 {:.0} p99 {:.0} p99.9 {:.0} max {:.0}",
        publishers,
        setup.as_secs_f64() * 1e3,
        matched.as_secs_f64() * 1e3,
        latencies.len(),
        sent,
        payload,
        elapsed.as_secs_f64(),
        latencies.len() as f64 / elapsed.as_secs_f64(),
        sent as usize - latencies.len(),
        pct(0.5),
        pct(0.9),
        pct(0.99),
        pct(0.999),
        pct(1.0)
    );
    Ok(())
}
