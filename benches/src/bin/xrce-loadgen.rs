//! `xrce-loadgen`: a first load generator. One publishing and one subscribing XRCE client
//! (common's client state machine over UDP) talk through an agent; it reports the samples/s
//! delivered client → agent → DDS → agent → client and the latency percentiles.
//!
//! Usage: `xrce-loadgen --port 8888 [--samples 20000] [--rate 0] [--payload 40] [--domain 42] [--best-effort]`
//! against an agent started separately (e.g. `xrce-agent udp4 -p 8888 --dds-interface 127.0.0.1`).

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind as k, stream_id, ClientKey, DataDeliveryControl, ObjectId, ObjectVariant,
    ReadSpecification, Representation, VariantExtra,
};

struct Peer {
    client: Client,
    socket: UdpSocket,
    buf: Vec<u8>,
}

impl Peer {
    fn new(port: u16, key: [u8; 4]) -> std::io::Result<Self> {
        let socket = UdpSocket::bind("127.0.0.1:0")?;
        socket.connect(("127.0.0.1", port))?;
        socket.set_nonblocking(true)?;
        Ok(Peer {
            client: Client::new(ClientConfig::new(ClientKey(key))),
            socket,
            buf: vec![0; 65_536],
        })
    }

    fn pump(&mut self, events: &mut Vec<ClientEvent>) {
        let now = Instant::now();
        while let Ok(n) = self.socket.recv(&mut self.buf) {
            self.client.handle_datagram(now, &self.buf[..n]);
        }
        self.client.handle_timeout(now);
        while let Some(t) = self.client.poll_transmit() {
            let _ = self.socket.send(&t);
        }
        events.extend(std::iter::from_fn(|| self.client.poll_event()));
    }

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
        let end = Instant::now() + Duration::from_secs(20);
        let mut ev = Vec::new();
        while Instant::now() < end {
            self.pump(&mut ev);
            for e in ev.drain(..) {
                if let ClientEvent::Status(s) = e {
                    if s.related.request_id == req {
                        return if s.result.status == 0 {
                            Ok(())
                        } else {
                            Err(format!("status {:#x}", s.result.status))
                        };
                    }
                }
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        Err("no STATUS".into())
    }
}

fn arg(args: &[String], name: &str, default: u64) -> u64 {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().collect();
    let port = arg(&args, "--port", 8888) as u16;
    let samples = arg(&args, "--samples", 20_000) as u32;
    let payload = arg(&args, "--payload", 40).max(12) as usize;
    let domain = arg(&args, "--domain", 42) as i16;
    // Samples per second; 0 = as fast as the reliable window allows.
    let rate = arg(&args, "--rate", 0) as f64;
    let stream = if args.iter().any(|a| a == "--best-effort") {
        stream_id::BUILTIN_BEST_EFFORT
    } else {
        stream_id::BUILTIN_RELIABLE
    };
    let topic = "<dds><topic><name>LoadTopic</name><dataType>Load</dataType></topic></dds>";
    let endpoint = |e: &str| {
        format!("<dds><{e}><topic><kind>NO_KEY</kind><name>LoadTopic</name><dataType>Load</dataType></topic><qos><reliability><kind>RELIABLE</kind></reliability><durability><kind>VOLATILE</kind></durability><historyQos><kind>KEEP_LAST</kind><depth>1000</depth></historyQos></qos></{e}></dds>")
    };
    let mut sub = Peer::new(port, [0x10, 0xAD, 0, 1]).map_err(|e| e.to_string())?;
    let mut publ = Peer::new(port, [0x10, 0xAD, 0, 2]).map_err(|e| e.to_string())?;
    let t_start = Instant::now();
    for p in [&mut sub, &mut publ] {
        p.client.connect(Instant::now());
        let end = Instant::now() + Duration::from_secs(10);
        while !p.client.is_connected() && Instant::now() < end {
            p.pump(&mut Vec::new());
            std::thread::sleep(Duration::from_millis(1));
        }
        if !p.client.is_connected() {
            return Err("no session".into());
        }
        let part = ObjectId::new(1, k::PARTICIPANT);
        p.create(
            part,
            k::PARTICIPANT,
            "<dds><participant><rtps><name>load</name></rtps></participant></dds>",
            VariantExtra::DomainId(domain),
        )?;
        p.create(
            ObjectId::new(1, k::TOPIC),
            k::TOPIC,
            topic,
            VariantExtra::Parent(part),
        )?;
    }
    let part = ObjectId::new(1, k::PARTICIPANT);
    sub.create(
        ObjectId::new(1, k::SUBSCRIBER),
        k::SUBSCRIBER,
        "",
        VariantExtra::Parent(part),
    )?;
    let reader = ObjectId::new(1, k::DATAREADER);
    sub.create(
        reader,
        k::DATAREADER,
        &endpoint("data_reader"),
        VariantExtra::Parent(ObjectId::new(1, k::SUBSCRIBER)),
    )?;
    publ.create(
        ObjectId::new(1, k::PUBLISHER),
        k::PUBLISHER,
        "",
        VariantExtra::Parent(part),
    )?;
    let writer = ObjectId::new(1, k::DATAWRITER);
    publ.create(
        writer,
        k::DATAWRITER,
        &endpoint("data_writer"),
        VariantExtra::Parent(ObjectId::new(1, k::PUBLISHER)),
    )?;
    let spec = ReadSpecification {
        preferred_stream_id: stream,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    };
    sub.client
        .read(Instant::now(), reader, spec)
        .map_err(|e| e.to_string())?;
    let setup = t_start.elapsed();
    // Probe until the DDS endpoints matched: the first sample that comes back.
    let base = Instant::now();
    let sample = |seq: u32| {
        let mut v = vec![0u8; payload];
        v[0..4].copy_from_slice(&seq.to_le_bytes());
        v[4..12].copy_from_slice(&(base.elapsed().as_nanos() as u64).to_le_bytes());
        v
    };
    let mut events = Vec::new();
    let probe_end = Instant::now() + Duration::from_secs(30);
    let mut matched = None;
    while matched.is_none() && Instant::now() < probe_end {
        if publ.client.can_send_reliable(stream) {
            let _ = publ
                .client
                .write(Instant::now(), stream, writer, &sample(u32::MAX));
        }
        publ.pump(&mut Vec::new());
        sub.pump(&mut events);
        if events.iter().any(|e| matches!(e, ClientEvent::Data { .. })) {
            matched = Some(t_start.elapsed());
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let matched = matched.ok_or("DDS endpoints never matched")?;
    eprintln!("matched after {matched:?}");
    std::thread::sleep(Duration::from_millis(200));
    sub.pump(&mut Vec::new());
    events.clear();
    // The run.
    let (mut sent, mut latencies, mut seen) = (
        0u32,
        Vec::with_capacity(samples as usize),
        vec![false; samples as usize],
    );
    let t0 = Instant::now();
    let mut last_report = t0;
    let deadline = t0 + Duration::from_secs(60);
    while (latencies.len() as u32) < samples && Instant::now() < deadline {
        let allowed = if rate > 0.0 {
            ((t0.elapsed().as_secs_f64() * rate) as u32).min(samples)
        } else {
            samples
        };
        while sent < allowed
            && (stream != stream_id::BUILTIN_RELIABLE || publ.client.can_send_reliable(stream))
        {
            let _ = publ
                .client
                .write(Instant::now(), stream, writer, &sample(sent));
            sent += 1;
            if sent % 64 == 0 {
                break;
            }
        }
        publ.pump(&mut Vec::new());
        sub.pump(&mut events);
        if last_report.elapsed() > Duration::from_secs(1) {
            last_report = Instant::now();
            eprintln!(
                "progress: sent {sent}, received {}, publisher unacked {}",
                latencies.len(),
                publ.client.unacked(stream)
            );
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
    }
    let elapsed = t0.elapsed();
    eprintln!("sent {sent}, received {}", latencies.len());
    latencies.sort_unstable();
    let pct = |p: f64| {
        latencies
            .get(((latencies.len() as f64 * p) as usize).min(latencies.len().saturating_sub(1)))
            .map_or(0.0, |n| *n as f64 / 1000.0)
    };
    println!(
        "setup {:.0} ms, first sample through DDS at {:.0} ms; {} of {} samples of {} B in {:.2} s = {:.0} samples/s; latency us p50 {:.0} p90 {:.0} p99 {:.0} max {:.0}",
        setup.as_secs_f64() * 1e3,
        matched.as_secs_f64() * 1e3,
        latencies.len(),
        samples,
        payload,
        elapsed.as_secs_f64(),
        latencies.len() as f64 / elapsed.as_secs_f64(),
        pct(0.5),
        pct(0.9),
        pct(0.99),
        pct(1.0)
    );
    Ok(())
}
