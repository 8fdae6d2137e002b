//! UDP over IPv4 or IPv6: one socket, one XRCE message per datagram, clients known by their
//! source address. A datagram goes from the socket buffer to the session core without a copy.

use std::net::SocketAddr;
use std::time::Instant;

use mio::event::Event;
use mio::{Interest, Registry, Token};
use xrce_common::session::agent::MAX_DATAGRAM;
use xrce_common::wire::info::TransportLocator;

use super::{Transport, TransportStats};

/// Largest datagram received (larger ones are truncated by the kernel and then dropped by
/// the decoder as malformed).
const RECV_BUFFER: usize = 65_536;
/// Socket buffer size requested for each direction: bursts (hundreds of clients starting at
/// once) overflow the default, and a lost datagram costs a retransmission round.
const SOCKET_BUFFER: usize = 4 << 20;

/// The UDP transport.
#[derive(Debug)]
pub struct UdpTransport {
    socket: mio::net::UdpSocket,
    local: SocketAddr,
    buf: Vec<u8>,
    readable: bool,
    stats: TransportStats,
}

impl UdpTransport {
    /// Serves clients on a bound socket.
    pub fn new(socket: std::net::UdpSocket) -> std::io::Result<Self> {
        socket.set_nonblocking(true)?;
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
        Ok(UdpTransport {
            socket: mio::net::UdpSocket::from_std(socket),
            local,
            buf: vec![0; RECV_BUFFER],
            // Datagrams may have arrived before registration: look once.
            readable: true,
            stats: TransportStats::default(),
        })
    }

    /// The address served.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }
}

impl Transport for UdpTransport {
    type Endpoint = SocketAddr;

    fn name(&self) -> &'static str {
        if self.local.is_ipv4() {
            "udp4"
        } else {
            "udp6"
        }
    }

    fn max_message_size(&self) -> u16 {
        MAX_DATAGRAM
    }

    fn register(&mut self, registry: &Registry, first_token: usize) -> std::io::Result<()> {
        registry.register(&mut self.socket, Token(first_token), Interest::READABLE)?;
        tracing::info!(local = %self.local, "UDP front-end listening");
        Ok(())
    }

    fn on_event(&mut self, event: &Event) {
        if event.is_readable() || event.is_error() {
            self.readable = true;
        }
    }

    fn receive(
        &mut self,
        _now: Instant,
        budget: usize,
        deliver: &mut dyn FnMut(SocketAddr, &[u8]),
    ) -> bool {
        if !self.readable {
            return false;
        }
        let mut errors = 0;
        for _ in 0..budget {
            match self.socket.recv_from(&mut self.buf) {
                Ok((n, src)) => {
                    errors = 0;
                    self.stats.messages_in += 1;
                    deliver(src, &self.buf[..n]);
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    self.readable = false;
                    return false;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    // ICMP errors from earlier sends surface here on Linux, one each: keep
                    // reading. Errors that repeat mean the socket itself fails: wait for
                    // the next readiness rather than spin.
                    tracing::debug!(error = %e, "recv_from");
                    errors += 1;
                    if errors >= 16 {
                        self.stats.drop("recv_failed");
                        self.readable = false;
                        return false;
                    }
                }
            }
        }
        true
    }

    fn send(&mut self, to: SocketAddr, message: &[u8]) {
        match self.socket.send_to(message, to) {
            Ok(_) => self.stats.messages_out += 1,
            Err(e) => {
                // The socket buffer is this transport's bounded output buffer: a full one
                // drops the datagram, and the reliable streams repair it.
                let reason = if e.kind() == std::io::ErrorKind::WouldBlock {
                    "send_buffer_full"
                } else {
                    "send_failed"
                };
                let n = self.stats.drop(reason);
                if n.is_power_of_two() {
                    tracing::warn!(error = %e, %to, reason, dropped = n, "datagram not sent");
                }
            }
        }
    }

    fn poll_closed(&mut self) -> Option<SocketAddr> {
        None
    }

    fn poll_timeout(&self) -> Option<Instant> {
        None
    }

    fn handle_timeout(&mut self, _now: Instant) {}

    fn stats(&self) -> &TransportStats {
        &self.stats
    }

    fn locators(&self) -> Vec<TransportLocator> {
        super::discovery::ip_locators(self.local)
    }

    fn serving(&self) -> String {
        self.local.to_string()
    }

    fn describe(&self, endpoint: SocketAddr) -> String {
        endpoint.to_string()
    }

    fn decode_endpoint(&self, bytes: &[u8]) -> Option<SocketAddr> {
        let addr = match bytes.split_first()? {
            (4, rest) if rest.len() == 6 => {
                let o: [u8; 4] = rest[..4].try_into().ok()?;
                let port = u16::from_le_bytes(rest[4..6].try_into().ok()?);
                SocketAddr::new(o.into(), port)
            }
            (6, rest) if rest.len() == 26 => {
                let o: [u8; 16] = rest[..16].try_into().ok()?;
                let port = u16::from_le_bytes(rest[16..18].try_into().ok()?);
                let flow = u32::from_le_bytes(rest[18..22].try_into().ok()?);
                let scope = u32::from_le_bytes(rest[22..26].try_into().ok()?);
                std::net::SocketAddrV6::new(o.into(), port, flow, scope).into()
            }
            _ => return None,
        };
        // Only a peer this socket can reach (the family it serves).
        (addr.is_ipv4() == self.local.is_ipv4()).then_some(addr)
    }
}
