//! `impaired-relay`: the test suite's impaired UDP link as a program, to put between any
//! client and any agent by hand or in a benchmark (the unmodified eProsima examples against
//! this agent and against MicroXRCEAgent alike).
//!
//! ```text
//! impaired-relay --listen-port 9999 --agent 127.0.0.1:8888 --loss 0.3 [--duplicate 0.2]
//!                [--reorder 0.2] [--seed N] [--drop-first-delete-status]
//! ```
//!
//! Clients send to `127.0.0.1:<listen-port>`; each client endpoint reaches the agent from a
//! port of its own. On SIGINT/SIGTERM (or stdin closing) it prints what it did and exits.

use std::io::Read;
use std::net::SocketAddr;
use std::time::Duration;

use xrce_tests::impaired::{Direction, ImpairedUdp, Impairment};

fn value<T: std::str::FromStr>(args: &[String], name: &str) -> Option<T> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(agent) = value::<SocketAddr>(&args, "--agent") else {
        eprintln!(
            "usage: impaired-relay --agent HOST:PORT [--listen-port P] [--loss F] \
             [--duplicate F] [--reorder F] [--seed N] [--drop-first-delete-status]"
        );
        std::process::exit(2);
    };
    let impairment = Impairment {
        loss: value(&args, "--loss").unwrap_or(0.0),
        duplicate: value(&args, "--duplicate").unwrap_or(0.0),
        reorder: value(&args, "--reorder").unwrap_or(0.0),
        hold: Duration::from_millis(30),
        seed: value(&args, "--seed").unwrap_or(1),
    };
    let relay = ImpairedUdp::start_on(
        agent,
        value(&args, "--listen-port").unwrap_or(0),
        impairment,
    );
    if args.iter().any(|a| a == "--drop-first-delete-status") {
        let mut dropped = false;
        relay.drop_when(move |dir, b| {
            let hit = dir == Direction::ToClient && b.len() > 8 && b[1] == 0 && b[4] == 0x05;
            let first = hit && !dropped;
            dropped |= hit;
            first
        });
    }
    println!("listening on {}", relay.addr());
    // Runs until stdin closes (a pipe from the script that started it) or a signal ends it.
    let mut sink = Vec::new();
    let _ = std::io::stdin().read_to_end(&mut sink);
    println!("{:?}", relay.counts());
}
