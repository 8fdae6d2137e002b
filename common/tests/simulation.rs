//! Deterministic simulation: the client and agent state machines over a link that drops,
//! duplicates and reorders. Every reliable message must arrive exactly once and in order,
//! in both directions, across sequence-number wrap-around.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use xrce_common::session::agent::{Agent, AgentConfig, DataReply, Operation, OperationSink};
use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    data_format, stream_id, BaseObjectRequest, ClientKey, ObjectId, RequestId,
};

/// xorshift64*: a tiny deterministic generator, enough for a simulated link.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn chance(&mut self, p: f64) -> bool {
        ((self.next() >> 11) as f64 / (1u64 << 53) as f64) < p
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
struct Addr(u32);

impl xrce_common::session::budget::Origin for Addr {
    fn origin(&self) -> xrce_common::session::budget::OriginId {
        self.0.origin()
    }
    fn ip(&self) -> Option<std::net::IpAddr> {
        None
    }
}

/// Echoes every write back to the client as DATA, and counts what it saw.
#[derive(Default)]
struct EchoSink {
    writes: Vec<(ClientKey, Vec<u8>)>,
    room: bool,
}
impl OperationSink for EchoSink {
    fn has_room(&self) -> bool {
        self.room
    }
    fn operation(&mut self, _now: Instant, op: Operation<'_>) {
        if let Operation::Write { client, data, .. } = op {
            self.writes.push((client, data.data.to_vec()));
        }
    }
}

struct Link {
    rng: Rng,
    loss: f64,
    dup: f64,
    max_delay_us: u64,
    /// (delivery time in µs, tie-breaker) -> (to agent?, bytes)
    in_flight: BTreeMap<(u64, u64), (bool, Vec<u8>)>,
    counter: u64,
}
impl Link {
    fn send(&mut self, now_us: u64, to_agent: bool, bytes: Vec<u8>) {
        if self.rng.chance(self.loss) {
            return;
        }
        let copies = if self.rng.chance(self.dup) { 2 } else { 1 };
        for _ in 0..copies {
            let at = now_us + 1 + self.rng.next() % self.max_delay_us;
            self.counter += 1;
            self.in_flight
                .insert((at, self.counter), (to_agent, bytes.clone()));
        }
    }
}

fn sample(i: u32, size: usize) -> Vec<u8> {
    let mut v = i.to_le_bytes().to_vec();
    v.extend((0..size.saturating_sub(4)).map(|k| (k as u32 ^ i) as u8));
    v
}

/// Runs one scenario; returns (samples the agent took, samples echoed back to the client).
fn run(seed: u64, n: u32, loss: f64, backpressure_every: u64) -> (Vec<u32>, Vec<u32>) {
    run_sized(seed, n, loss, backpressure_every, 12)
}

/// Runs one scenario with samples of `size` bytes; checks every sample's bytes on both sides.
fn run_sized(
    seed: u64,
    n: u32,
    loss: f64,
    backpressure_every: u64,
    size: usize,
) -> (Vec<u32>, Vec<u32>) {
    let t0 = Instant::now();
    let at = |us: u64| t0 + Duration::from_micros(us);
    let mut link = Link {
        rng: Rng(seed | 1),
        loss,
        dup: 0.1,
        max_delay_us: 3_000,
        in_flight: BTreeMap::new(),
        counter: 0,
    };
    let mut agent: Agent<Addr> = Agent::new(AgentConfig {
        heartbeat_period: Duration::from_millis(20),
        ..AgentConfig::default()
    });
    let mut client = Client::new(ClientConfig {
        heartbeat_period: Duration::from_millis(20),
        ..ClientConfig::new(ClientKey([1, 2, 3, 4]))
    });
    let mut sink = EchoSink {
        room: true,
        ..Default::default()
    };
    let writer = ObjectId::new(1, 5);
    let reader_req = BaseObjectRequest {
        request_id: RequestId::from_u16(7),
        object_id: ObjectId::new(1, 6),
    };
    let (mut now, mut written, mut echoed_upto, mut received) = (0u64, 0u32, 0usize, Vec::new());
    client.connect(at(0));
    let limit_us = 3_600_000_000u64;
    while (received.len() as u32) < n {
        assert!(
            now < limit_us,
            "seed {seed}: stalled with {} of {n} received",
            received.len()
        );
        // The client writes as fast as its window allows.
        while client.is_connected()
            && written < n
            && client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        {
            client
                .write(
                    at(now),
                    stream_id::BUILTIN_RELIABLE,
                    writer,
                    &sample(written, size),
                )
                .expect("room");
            written += 1;
        }
        while let Some(t) = client.poll_transmit() {
            link.send(now, true, t);
        }
        // The DDS side answers every write with a DATA back to the client.
        while echoed_upto < sink.writes.len() {
            let (key, data) = sink.writes[echoed_upto].clone();
            agent
                .send_data(
                    at(now),
                    key,
                    stream_id::BUILTIN_RELIABLE,
                    DataReply {
                        request: reader_req,
                        format: data_format::DATA,
                        sample: &data,
                        little_endian: true,
                        state: 0,
                        sequence_number: 0,
                    },
                )
                .expect("send_data");
            echoed_upto += 1;
        }
        while let Some(t) = agent.poll_transmit() {
            link.send(now, false, t.data);
        }
        while let Some(e) = client.poll_event() {
            if let ClientEvent::Data { data, .. } = e {
                let i = u32::from_le_bytes([data[0], data[1], data[2], data[3]]);
                assert_eq!(
                    data,
                    sample(i, size),
                    "seed {seed}: sample {i} corrupted on the way to the client"
                );
                received.push(i);
            }
        }
        // Next event: a delivery or a timer.
        let next_timer = [client.poll_timeout(), agent.poll_timeout()]
            .into_iter()
            .flatten()
            .map(|t| t.duration_since(t0).as_micros() as u64)
            .min();
        let next_msg = link.in_flight.keys().next().map(|k| k.0);
        now = match (next_msg, next_timer) {
            (Some(a), Some(b)) => a.min(b).max(now),
            (a, b) => a.or(b).expect("something must be pending").max(now),
        };
        while let Some((&k, _)) = link.in_flight.iter().next() {
            if k.0 > now {
                break;
            }
            let (to_agent, bytes) = link.in_flight.remove(&k).expect("present");
            if to_agent {
                // Some deliveries find the DDS side without room: flow control must hold them.
                sink.room = backpressure_every == 0 || k.1 % backpressure_every != 0;
                agent.handle_datagram(at(now), Addr(1), &bytes, &mut sink);
            } else {
                client.handle_datagram(at(now), &bytes);
            }
        }
        client.handle_timeout(at(now));
        agent.handle_timeout(at(now), &mut sink);
    }
    for (_, d) in &sink.writes {
        let i = u32::from_le_bytes([d[0], d[1], d[2], d[3]]);
        assert_eq!(
            *d,
            sample(i, size),
            "seed {seed}: sample {i} corrupted on the way to the agent"
        );
    }
    let taken = sink
        .writes
        .iter()
        .map(|(_, d)| u32::from_le_bytes([d[0], d[1], d[2], d[3]]))
        .collect();
    (taken, received)
}

fn assert_exactly_once_in_order(seq: &[u32], n: u32, what: &str, seed: u64) {
    assert_eq!(seq.len() as u32, n, "seed {seed}: {what}: count");
    for (i, v) in seq.iter().enumerate() {
        assert_eq!(*v, i as u32, "seed {seed}: {what}: position {i}");
    }
}

#[test]
fn reliable_both_ways_over_a_bad_link_many_seeds() {
    for seed in 1..=40u64 {
        let (taken, received) = run(seed * 7919, 300, 0.3, 0);
        assert_exactly_once_in_order(&taken, 300, "agent side", seed);
        assert_exactly_once_in_order(&received, 300, "client side", seed);
    }
}

#[test]
fn flow_control_loses_nothing() {
    for seed in 1..=10u64 {
        let (taken, received) = run(seed, 300, 0.1, 3);
        assert_exactly_once_in_order(&taken, 300, "agent side", seed);
        assert_exactly_once_in_order(&received, 300, "client side", seed);
    }
}

#[test]
fn sequence_numbers_wrap_around() {
    // 70,000 messages each way: both 16-bit stream sequences wrap.
    let (taken, received) = run(42, 70_000, 0.05, 0);
    assert_exactly_once_in_order(&taken, 70_000, "agent side", 42);
    assert_exactly_once_in_order(&received, 70_000, "client side", 42);
}

#[test]
fn samples_larger_than_the_mtu_are_fragmented_both_ways() {
    // 3,000-byte samples with a 512-byte MTU: 7 FRAGMENTs each, over a link losing 20%.
    for seed in 1..=8u64 {
        let (taken, received) = run_sized(seed * 31, 60, 0.2, 0, 3000);
        assert_exactly_once_in_order(&taken, 60, "agent side", seed);
        assert_exactly_once_in_order(&received, 60, "client side", seed);
    }
}

#[test]
fn samples_beyond_64_kib_cross_in_fragments_both_ways() {
    // 200,000-byte samples: the WRITE_DATA and DATA carry submessageLength 0 (eProsima's
    // convention for payloads a 16-bit length cannot describe) and ~400 FRAGMENTs each.
    for seed in 1..=2u64 {
        let (taken, received) = run_sized(seed * 17, 3, 0.1, 0, 200_000);
        assert_exactly_once_in_order(&taken, 3, "agent side", seed);
        assert_exactly_once_in_order(&received, 3, "client side", seed);
    }
}
