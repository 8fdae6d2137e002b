//! Micro-benchmarks of the protocol core: decode/encode of captured datagrams by submessage
//! kind, and the agent session core handling a reliable WRITE_DATA datagram.

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use xrce_common::session::agent::{Agent, AgentConfig, NullSink};
use xrce_common::wire::Message;

fn first_with(datagrams: &[Vec<u8>], id: u8) -> Vec<u8> {
    datagrams
        .iter()
        .find(|d| d.len() > 8 && d[4] == id)
        .cloned()
        .unwrap_or_default()
}

fn codec(c: &mut Criterion) {
    let to_agent = xrce_benches::captured("reliable-xml-helloworld.txt", true);
    let to_client = xrce_benches::captured("reliable-xml-helloworld.txt", false);
    let cases = [
        ("create_x4_xml", first_with(&to_agent, 0x01)),
        ("write_data", first_with(&to_agent, 0x07)),
        ("read_data", first_with(&to_agent, 0x08)),
        ("acknack", first_with(&to_agent, 0x0A)),
        ("data", first_with(&to_client, 0x09)),
        ("status", first_with(&to_client, 0x05)),
    ];
    let mut g = c.benchmark_group("decode");
    for (name, bytes) in &cases {
        g.throughput(Throughput::Bytes(bytes.len() as u64));
        g.bench_function(*name, |b| {
            b.iter(|| Message::decode(black_box(bytes)).map(|m| m.submessages.len()))
        });
    }
    g.finish();
    let mut g = c.benchmark_group("encode");
    for (name, bytes) in &cases {
        let Ok(m) = Message::decode(bytes) else {
            continue;
        };
        g.bench_function(*name, |b| {
            b.iter(|| black_box(&m).encode().map(|v| v.len()))
        });
    }
    g.finish();
}

fn session_core(c: &mut Criterion) {
    let to_agent = xrce_benches::captured("reliable-xml-helloworld.txt", true);
    let create_client = to_agent[0].clone();
    let write = first_with(&to_agent, 0x07);
    c.bench_function("agent_core/reliable_write_datagram", |b| {
        let mut agent: Agent<u16> = Agent::new(AgentConfig::default());
        let now = Instant::now();
        agent.handle_datagram(now, 1, &create_client, &mut NullSink);
        let mut msg = write.clone();
        let mut seq: u16 = 0;
        b.iter(|| {
            // Each datagram is the next in sequence, so every one is delivered and acknowledged.
            msg[2..4].copy_from_slice(&seq.to_le_bytes());
            seq = seq.wrapping_add(1);
            agent.handle_datagram(now, 1, black_box(&msg), &mut NullSink);
            while agent.poll_transmit().is_some() {}
        })
    });
}

criterion_group!(benches, codec, session_core);
criterion_main!(benches);
