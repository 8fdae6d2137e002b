//! EXPERIMENT (measured, then removed): the UDP front-end loop on a current-thread tokio
//! runtime, to compare with the mio loop in the latency benchmark.

use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use tokio::io::unix::AsyncFd;
use xrce_common::session::agent::{Agent, AgentConfig};

use crate::bridge::Bridge;
use crate::event_loop::OnServing;

struct Fd(RawFd);
impl AsRawFd for Fd {
    fn as_raw_fd(&self) -> RawFd {
        self.0
    }
}

/// Runs a UDP front-end on tokio until SIGINT/SIGTERM.
pub fn run(
    socket: std::net::UdpSocket,
    mut bridge: Bridge,
    config: AgentConfig,
    mut on_serving: Option<OnServing>,
) -> anyhow::Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    rt.block_on(async move {
        socket.set_nonblocking(true)?;
        let socket = tokio::net::UdpSocket::from_std(socket)?;
        let [r, a] = bridge.raw_fds();
        // SAFETY: the bridge owns these descriptors and outlives the AsyncFds.
        #[allow(unsafe_code)]
        let (replies, announce) = unsafe {
            (
                AsyncFd::register(Fd(r)).map_err(|e| anyhow::anyhow!("{e:?}"))?,
                AsyncFd::register(Fd(a)).map_err(|e| anyhow::anyhow!("{e:?}"))?,
            )
        };
        let mut agent: Agent<std::net::SocketAddr> = Agent::new(config);
        let mut buf = vec![0u8; 65_536];
        bridge.poll_ipc(Instant::now(), &mut agent, true, true);
        bridge.pump();
        loop {
            if bridge.termination_requested() {
                return Ok(());
            }
            if bridge.generation().is_some() {
                if let Some(f) = on_serving.take() {
                    f();
                }
            }
            let now = Instant::now();
            let deadline = [agent.poll_timeout(), bridge.poll_timeout()]
                .into_iter()
                .flatten()
                .min()
                .map_or(now + Duration::from_secs(1), |d| {
                    d.min(now + Duration::from_secs(1))
                });
            let (mut replies_ready, mut announce_ready) = (false, false);
            tokio::select! {
                _ = socket.readable() => {}
                g = replies.readable() => {
                    if let Ok(mut g) = g { g.clear_ready(); }
                    replies_ready = true;
                }
                g = announce.readable() => {
                    if let Ok(mut g) = g { g.clear_ready(); }
                    announce_ready = true;
                }
                _ = tokio::time::sleep_until(tokio::time::Instant::from_std(deadline)) => {}
            }
            let now = Instant::now();
            if let Ok(d) = SystemTime::now().duration_since(UNIX_EPOCH) {
                agent.set_wall_clock(now, d);
            }
            for _ in 0..256 {
                match socket.try_recv_from(&mut buf) {
                    Ok((n, src)) => agent.handle_datagram(now, src, &buf[..n], &mut bridge),
                    Err(_) => break,
                }
            }
            bridge.apply_replies(now, &mut agent);
            bridge.poll_ipc(now, &mut agent, replies_ready, announce_ready);
            bridge.resume_reads(&agent);
            agent.handle_timeout(now, &mut bridge);
            bridge.pump();
            while let Some(t) = agent.poll_transmit() {
                let _ = socket.try_send_to(&t.data, t.destination);
            }
        }
    })
}
