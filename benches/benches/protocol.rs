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
    let trace = |name: &str, to_agent: bool| xrce_benches::captured(name, to_agent);
    let to_agent = trace("reliable-xml-helloworld.txt", true);
    let to_client = trace("reliable-xml-helloworld.txt", false);
    let (big_in, big_out) = (
        trace("big-fragmented.txt", true),
        trace("big-fragmented.txt", false),
    );
    let (ping_in, ping_out) = (trace("ping.txt", true), trace("ping.txt", false));
    let (time_in, time_out) = (trace("timesync.txt", true), trace("timesync.txt", false));
    // Every submessage kind the real client and agent exchange, from the captured traces.
    let cases = [
        ("create_client", first_with(&to_agent, 0x00)),
        ("create_x4_xml", first_with(&to_agent, 0x01)),
        ("get_info", first_with(&ping_in, 0x02)),
        ("delete", first_with(&to_agent, 0x03)),
        ("status_agent", first_with(&to_client, 0x04)),
        ("status", first_with(&to_client, 0x05)),
        ("info", first_with(&ping_out, 0x06)),
        ("write_data", first_with(&to_agent, 0x07)),
        ("read_data", first_with(&to_agent, 0x08)),
        ("data", first_with(&to_client, 0x09)),
        ("acknack", first_with(&to_agent, 0x0A)),
        ("heartbeat", first_with(&big_out, 0x0B)),
        ("fragment", first_with(&big_in, 0x0D)),
        ("timestamp", first_with(&time_in, 0x0E)),
        ("timestamp_reply", first_with(&time_out, 0x0F)),
    ];
    let mut g = c.benchmark_group("decode");
    for (name, bytes) in &cases {
        assert!(!bytes.is_empty(), "no {name} datagram in the traces");
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

/// The session core handling a client's WRITE_DATA datagrams, each the next in sequence
/// (so every one is delivered and, on a reliable stream, acknowledged).
fn write_datagrams(c: &mut Criterion, name: &str, trace: &str) {
    let to_agent = xrce_benches::captured(trace, true);
    let create_client = first_with(&to_agent, 0x00);
    let write = first_with(&to_agent, 0x07);
    c.bench_function(name, |b| {
        let mut agent: Agent<u16> = Agent::new(AgentConfig::default());
        let now = Instant::now();
        agent.handle_datagram(now, 1, &create_client, &mut NullSink);
        let mut msg = write.clone();
        let mut seq: u16 = 0;
        b.iter(|| {
            msg[2..4].copy_from_slice(&seq.to_le_bytes());
            seq = seq.wrapping_add(1);
            agent.handle_datagram(now, 1, black_box(&msg), &mut NullSink);
            while agent.poll_transmit().is_some() {}
        })
    });
}

fn session_core(c: &mut Criterion) {
    write_datagrams(
        c,
        "agent_core/reliable_write_datagram",
        "reliable-xml-helloworld.txt",
    );
    write_datagrams(
        c,
        "agent_core/best_effort_write_datagram",
        "besteffort-xml-helloworld.txt",
    );
}

criterion_group!(benches, codec, session_core);
criterion_main!(benches);
