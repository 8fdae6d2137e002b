//! A measurement, not a product: the agent's front-end and worker composed in one thread
//! of one process (what `tests/tests/e2e/simulation.rs` does in simulated time, here over a
//! real UDP socket and Cyclone DDS), to learn what the two process hops cost a sample on a
//! small gateway (issue 45). It has none of the agent's supervision, session store,
//! shared memory or crash survival, and serves UDP only:
//!
//! ```sh
//! cargo build --release -p xrce-tests --example single_process
//! target/release/examples/single_process udp4 -p PORT --dds-interface 127.0.0.1
//! ```
//!
//! (the arguments after the port are ignored but for `--dds-interface`, so that
//! `benches/scripts/ab.sh` can start it as it starts `xrce-agent`).

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::os::fd::AsRawFd;
use std::time::{Duration, Instant};

use mio::unix::SourceFd;
use mio::{Events, Interest, Poll, Token};
use xrce_common::session::agent::{Agent, AgentConfig};
use xrce_dds_worker::backend::{self, BackendKind, DdsConfig};
use xrce_dds_worker::worker::{MemoryWorkerLink, Worker, WorkerConfig};
use xrce_frontend::relay::link::MemoryLink;
use xrce_frontend::relay::Relay;
use xrce_frontend::transport::{udp, Transport};

/// The one front-end's id.
const FE: u32 = 1;
/// The worker's DDS descriptors.
const DDS: Token = Token(1);
/// The transport's tokens start here.
const TRANSPORT_TOKENS: usize = 16;
const RECV_BATCH: usize = 256;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
    };
    let port: u16 = value("-p").ok_or("-p PORT")?.parse()?;
    let interfaces: Vec<IpAddr> = value("--dds-interface")
        .map(|a| a.parse())
        .transpose()?
        .into_iter()
        .collect();
    let mut transport = udp::open(SocketAddr::new(IpAddr::V4(Ipv4Addr::UNSPECIFIED), port))?;
    let config = AgentConfig {
        max_message_size: transport.max_message_size(),
        ..AgentConfig::default()
    };
    let mut agent: Agent<<udp::UdpTransport as Transport>::Endpoint> = Agent::new(config);
    let mut relay = Relay::new(FE, 1, MemoryLink::default());
    let dds_config = DdsConfig {
        interfaces,
        ..DdsConfig::default()
    };
    let dds = backend::create(BackendKind::default(), &dds_config)?;
    let now = Instant::now();
    let mut worker = Worker::new(
        WorkerConfig {
            instance: format!("single-process-{port}"),
            backend: BackendKind::default(),
            dds: dds_config,
            references: Default::default(),
            ros_graph: false,
            share_writers: false,
            frontend_grace: Duration::from_secs(30),
            domains: Default::default(),
            bounds: Default::default(),
            default_domain: 0,
        },
        dds,
        MemoryWorkerLink::default(),
        0x51,
        now,
    )?;
    let mut poll = Poll::new()?;
    transport.register(poll.registry(), TRANSPORT_TOKENS)?;
    let mut registered = Vec::new();
    let mut events = Events::with_capacity(1024);
    let mut announcements_seen = 0;
    let mut input_left = true;
    loop {
        // The backends' descriptors (made as participants are), level-triggered in the
        // worker's own process: here a pass after every wake-up stands in for that.
        for fd in worker.readiness_fds().iter().map(AsRawFd::as_raw_fd) {
            if !registered.contains(&fd) {
                poll.registry()
                    .register(&mut SourceFd(&fd), DDS, Interest::READABLE)?;
                registered.push(fd);
            }
        }
        let now = Instant::now();
        let timeout = if input_left {
            Duration::ZERO
        } else {
            [
                agent.poll_timeout(),
                relay.poll_timeout(now),
                transport.poll_timeout(),
                worker.poll_timeout(now).map(|d| now + d),
            ]
            .into_iter()
            .flatten()
            .min()
            .map_or(Duration::from_secs(1), |t| {
                t.saturating_duration_since(now).min(Duration::from_secs(1))
            })
        };
        match poll.poll(&mut events, Some(timeout)) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e.into()),
        }
        for event in events.iter() {
            if event.token() != DDS {
                transport.on_event(event);
            }
        }
        let now = Instant::now();
        input_left = transport.receive(now, RECV_BATCH, &mut |from, bytes| {
            agent.handle_datagram(now, from, bytes, &mut relay);
        });
        if transport.poll_timeout().is_some_and(|t| t <= now) {
            transport.handle_timeout(now);
            input_left = true;
        }
        agent.handle_timeout(now, &mut relay);
        relay.pump();
        // Requests to the worker and its replies back until neither side has more (a
        // reply can make the relay send: a replay, a paused read).
        let mut requests = relay.link_mut().take();
        let mut first = true;
        while first || !requests.is_empty() {
            first = false;
            for m in &requests {
                worker.handle_request(m, now);
            }
            worker.pass(now)?;
            let announced = worker.link().announced()[announcements_seen..].to_vec();
            announcements_seen += announced.len();
            for a in announced {
                relay.handle_announcement(&a);
            }
            for m in worker.link_mut().take(FE) {
                relay.handle_reply(now, &m, &mut agent);
            }
            relay.after_replies(now, &mut agent);
            if relay.take_generation_change() {
                agent.announce_streams(now);
            }
            relay.resume_reads(&agent);
            relay.pump();
            requests = relay.link_mut().take();
        }
        while let Some(t) = agent.poll_transmit() {
            transport.send(t.destination, &t.data);
        }
    }
}
