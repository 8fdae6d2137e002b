//! The UDP/IPv4 (or IPv6) transport: one socket, one thread, no busy polling.
//!
//! The loop blocks in `poll(2)` on the socket and the two IPC event descriptors, with the
//! earliest protocol timer as timeout; after each wake-up it drains everything ready.

use std::net::{SocketAddr, UdpSocket};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use xrce_common::session::agent::{Agent, AgentConfig};

use crate::bridge::Bridge;

/// Largest datagram accepted.
const MAX_DATAGRAM: usize = 65_536;
/// Socket buffer size requested for each direction.
const SOCKET_BUFFER: usize = 4 << 20;
/// Datagrams handled per wake-up before IPC and timers get a turn.
const RECV_BATCH: usize = 256;

/// Runs a UDP front-end until SIGINT/SIGTERM.
pub fn run(socket: UdpSocket, mut bridge: Bridge, config: AgentConfig) -> anyhow::Result<()> {
    socket.set_nonblocking(true)?;
    // Bursts (hundreds of clients starting at once) overflow the default buffer; a lost
    // datagram costs a retransmission round, so ask for room (the kernel may cap it).
    let sock = socket2::SockRef::from(&socket);
    for (what, result) in [
        ("receive", sock.set_recv_buffer_size(SOCKET_BUFFER)),
        ("send", sock.set_send_buffer_size(SOCKET_BUFFER)),
    ] {
        if let Err(e) = result {
            tracing::warn!(error = %e, "could not enlarge the socket {what} buffer");
        }
    }
    tracing::debug!(recv = ?sock.recv_buffer_size(), send = ?sock.send_buffer_size(), "socket buffers");
    let local = socket.local_addr()?;
    tracing::info!(%local, "UDP front-end listening");
    let mut agent: Agent<SocketAddr> = Agent::new(config);
    let mut buf = vec![0u8; MAX_DATAGRAM];
    let sock_fd = std::os::fd::AsRawFd::as_raw_fd(&socket);
    let [replies_fd, announce_fd] = bridge.raw_fds();
    let mut send_errors = 0u64;
    let mut report = StatsReport::new(Instant::now());
    // Pick up a worker that announced itself before we started.
    bridge.poll_ipc(Instant::now(), &mut agent, true, true);
    bridge.pump();
    loop {
        if bridge.termination_requested() {
            tracing::info!("termination requested");
            return Ok(());
        }
        let now = Instant::now();
        let deadline = [
            agent.poll_timeout(),
            bridge.poll_timeout(),
            report.due(&agent, &bridge),
        ]
        .into_iter()
        .flatten()
        .min();
        let timeout = match deadline {
            Some(d) => d.saturating_duration_since(now).as_millis().min(60_000) as i32 + 1,
            None => -1,
        };
        let ready =
            xrce_common::ipc::shm::wait_readable(&[sock_fd, replies_fd, announce_fd], timeout)?;
        let now = Instant::now();
        if let Ok(d) = SystemTime::now().duration_since(UNIX_EPOCH) {
            agent.set_wall_clock(now, d);
        }
        // Only what is readable: each check is a system call, and the loop runs per sample
        // under load.
        let batch = if ready & 1 != 0 { RECV_BATCH } else { 0 };
        for _ in 0..batch {
            match socket.recv_from(&mut buf) {
                Ok((n, src)) => {
                    agent.handle_datagram(now, src, &buf[..n], &mut bridge);
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    // ICMP errors from earlier sends surface here on Linux; keep serving.
                    tracing::debug!(error = %e, "recv_from");
                    break;
                }
            }
        }
        bridge.apply_replies(now, &mut agent);
        bridge.poll_ipc(now, &mut agent, ready & 0b10 != 0, ready & 0b100 != 0);
        bridge.resume_reads(&agent);
        agent.handle_timeout(now, &mut bridge);
        // After the timers: what they hand over (a dead client's deletion) goes out now.
        bridge.pump();
        report.maybe_log(now, &agent, &bridge);
        while let Some(t) = agent.poll_transmit() {
            if let Err(e) = socket.send_to(&t.data, t.destination) {
                send_errors += 1;
                if send_errors.is_power_of_two() {
                    tracing::warn!(error = %e, to = %t.destination, send_errors, "send_to failed");
                }
            }
        }
    }
}

/// Logs the drop counters at info when they changed, at most every [`STATS_PERIOD`], so that
/// counted drops are visible without debug logging (and an idle agent stays silent).
#[derive(Debug)]
struct StatsReport {
    last: Instant,
    last_dropped: u64,
}

/// How often changed drop counters are reported.
const STATS_PERIOD: std::time::Duration = std::time::Duration::from_secs(10);

impl StatsReport {
    fn new(now: Instant) -> Self {
        StatsReport {
            last: now,
            last_dropped: 0,
        }
    }

    /// Everything counted as not delivered: the core's drops by reason and the bridge's.
    fn total(agent: &Agent<SocketAddr>, bridge: &Bridge) -> u64 {
        let b = bridge.stats();
        agent.stats().dropped.values().sum::<u64>()
            + b.ops_dropped
            + b.samples_dropped
            + b.ipc_dropped
            + b.instance_ends_skipped
            + b.reads_paused
    }

    /// A deadline only while there is something new to report.
    fn due(&self, agent: &Agent<SocketAddr>, bridge: &Bridge) -> Option<Instant> {
        (Self::total(agent, bridge) != self.last_dropped).then_some(self.last + STATS_PERIOD)
    }

    fn maybe_log(&mut self, now: Instant, agent: &Agent<SocketAddr>, bridge: &Bridge) {
        let total = Self::total(agent, bridge);
        if total == self.last_dropped || now < self.last + STATS_PERIOD {
            return;
        }
        let s = agent.stats();
        let mut reasons: Vec<_> = s.dropped.iter().collect();
        reasons.sort();
        tracing::info!(
            sessions = agent.client_count(),
            datagrams_in = s.datagrams_in,
            datagrams_out = s.datagrams_out,
            retransmissions = s.retransmissions,
            dropped = ?reasons,
            replays = bridge.stats().replays,
            ops_dropped = bridge.stats().ops_dropped,
            samples_dropped = bridge.stats().samples_dropped,
            reads_paused = bridge.stats().reads_paused,
            instance_ends_skipped = bridge.stats().instance_ends_skipped,
            "front-end counters"
        );
        self.last = now;
        self.last_dropped = total;
    }
}
