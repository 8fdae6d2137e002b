//! What silent clients cost: 10,000 sessions each with a reply the client never acknowledges
//! (a client that went away without deleting its session), run for a minute of simulated
//! time through the sans-IO session core. Reports the HEARTBEATs sent per second in the last
//! 30 s and the CPU the timer handling takes per simulated second, with the HEARTBEAT
//! back-off (the default) and with a fixed 100 ms period (the behaviour before it).
//!
//! `cargo bench --bench silent_clients [-- CLIENTS]`

use std::time::{Duration, Instant};

use xrce_common::session::agent::{Agent, AgentConfig, NullSink};
use xrce_common::wire::*;

fn create_client(key: ClientKey) -> Vec<u8> {
    CreateClientPayload::eprosima(key, 0x81)
        .message()
        .unwrap_or_default()
}

struct Outcome {
    heartbeats_per_second: f64,
    timer_cpu_us_per_second: f64,
    timeouts_per_second: f64,
}

fn run(clients: u32, config: AgentConfig) -> Outcome {
    let t0 = Instant::now();
    let mut agent = Agent::new(config);
    let mut sink = NullSink;
    // The clients arrive over the first second (their timers are spread as in life).
    let spacing = Duration::from_secs(1) / clients.max(1);
    let mut now = t0;
    for i in 0..clients {
        now = t0 + spacing * i;
        let key = ClientKey((i + 1).to_be_bytes());
        agent.handle_datagram(now, i, &create_client(key), &mut sink);
        let request = BaseObjectRequest {
            request_id: RequestId::from_u16(9),
            object_id: ObjectId::new(1, object_kind::PARTICIPANT),
        };
        let _ = agent.send_status(now, key, request, ResultStatus::OK);
    }
    while agent.poll_transmit().is_some() {}
    // One minute, driven the way the front-end's event loop drives the core: wake at the
    // core's next timeout.
    let end = t0 + Duration::from_secs(60);
    let steady_from = t0 + Duration::from_secs(30);
    let (mut heartbeats, mut timeouts, mut cpu) = (0u64, 0u64, Duration::ZERO);
    while let Some(due) = agent.poll_timeout() {
        if due > end {
            break;
        }
        now = now.max(due);
        let started = Instant::now();
        agent.handle_timeout(now, &mut sink);
        let mut sent = 0;
        while agent.poll_transmit().is_some() {
            sent += 1;
        }
        if now >= steady_from {
            cpu += started.elapsed();
            heartbeats += sent;
            timeouts += 1;
        }
    }
    Outcome {
        heartbeats_per_second: heartbeats as f64 / 30.0,
        timer_cpu_us_per_second: cpu.as_secs_f64() * 1e6 / 30.0,
        timeouts_per_second: timeouts as f64 / 30.0,
    }
}

fn main() {
    // `cargo bench` passes `--bench`; a number chooses the client count.
    let clients = std::env::args()
        .skip(1)
        .find_map(|a| a.parse::<u32>().ok())
        .unwrap_or(10_000);
    let backoff = run(clients, AgentConfig::default());
    let fixed = run(
        clients,
        AgentConfig {
            max_heartbeat_period: AgentConfig::default().heartbeat_period,
            ..AgentConfig::default()
        },
    );
    println!("{clients} silent clients, seconds 30-60 of a simulated minute:");
    for (name, o) in [("back-off to 3.2 s", &backoff), ("fixed 100 ms", &fixed)] {
        println!(
            "  {name:<18} {:>9.0} HEARTBEATs/s  {:>7.1} timer wake-ups/s  {:>9.0} us CPU per second ({:.2} % of a core)",
            o.heartbeats_per_second,
            o.timeouts_per_second,
            o.timer_cpu_us_per_second,
            o.timer_cpu_us_per_second / 1e4
        );
    }
    println!(
        "  back-off / fixed: {:.3} of the HEARTBEATs, {:.3} of the CPU",
        backoff.heartbeats_per_second / fixed.heartbeats_per_second.max(1.0),
        backoff.timer_cpu_us_per_second / fixed.timer_cpu_us_per_second.max(1.0)
    );
}
