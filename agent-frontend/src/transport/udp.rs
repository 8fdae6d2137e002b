//! UDP over IPv4 or IPv6: one socket, one XRCE message per datagram, clients known by their
//! source address. A datagram goes from the socket buffer to the session core without a copy.
//!
//! Datagrams are read `RECV_BATCH` at a time with one `recvmmsg(2)`: under load that is one
//! system call for many clients' messages, and a batch that comes back short says the socket
//! is empty, so the loop does not make the extra read that would only find it so (mio's
//! readiness is edge-triggered, and every datagram that arrives later raises a new edge).
//! What the kernel dropped because the socket's buffer was full is read each second
//! (`SO_MEMINFO`) and counted as `socket_overflow`.

use std::io::IoSliceMut;
use std::net::SocketAddr;
use std::os::fd::AsRawFd;
use std::time::Instant;

use mio::event::Event;
use mio::{Interest, Registry, Token};
use nix::sys::socket::{recvmmsg, MsgFlags, MultiHeaders, SockaddrStorage};
use xrce_common::session::agent::MAX_DATAGRAM;
use xrce_common::wire::info::TransportLocator;

use super::{Transport, TransportStats};

/// Largest datagram received (larger ones are truncated by the kernel, then counted and
/// dropped as `truncated`).
const RECV_BUFFER: usize = 65_536;
/// Datagrams read by one system call. The buffers take `RECV_BATCH` times [`RECV_BUFFER`] of
/// address space, but only the pages datagrams were written to take memory.
const RECV_BATCH: usize = 32;
/// Socket buffer size requested for each direction: bursts (hundreds of clients starting at
/// once) overflow the default, and a lost datagram costs a retransmission round.
const SOCKET_BUFFER: usize = 4 << 20;
/// How often the kernel's count of what it dropped at the socket is read.
const KERNEL_DROPS_PERIOD: std::time::Duration = std::time::Duration::from_secs(1);

/// The UDP transport.
#[derive(Debug)]
pub struct UdpTransport {
    socket: mio::net::UdpSocket,
    local: SocketAddr,
    /// [`RECV_BATCH`] receive buffers of [`RECV_BUFFER`] bytes, back to back.
    bufs: Vec<u8>,
    /// The kernel's message headers for `recvmmsg`, kept between calls.
    headers: MultiHeaders<SockaddrStorage>,
    /// What the last batch read: length and source of each datagram.
    got: Vec<(usize, Result<SocketAddr, &'static str>)>,
    readable: bool,
    /// The error queue has something to read ([`super::icmp`]).
    errors_pending: bool,
    unreachable: super::icmp::Unreachable,
    stats: TransportStats,
    /// The kernel's count of the socket's drops as last seen (`None`: unknown yet, for a
    /// socket inherited from a predecessor, which may have counted some of them).
    kernel_drops: Option<u32>,
    /// When that count is read next ([`KERNEL_DROPS_PERIOD`], from the first loop pass on;
    /// never again where the kernel did not answer).
    next_drops_check: Option<Instant>,
    /// The kernel did not answer for this socket's drops.
    drops_unreported: bool,
}

impl UdpTransport {
    /// Counts what the kernel dropped at the socket since its count was last seen
    /// (`socket_overflow`; the count is 32 bits and wraps), logged at powers of two. The
    /// first count seen on an inherited socket is the baseline: it is logged as dropped
    /// since the socket was made, not counted (a predecessor counted part of it).
    fn kernel_dropped(&mut self, count: u32) {
        match self.kernel_drops.replace(count) {
            None if count > 0 => tracing::info!(
                dropped = count,
                "the kernel dropped datagrams at this socket since it was made, before this \
                 process served it or while it did (its receive buffer was full)"
            ),
            Some(before) if count != before => {
                let new = u64::from(count.wrapping_sub(before));
                let total = self.stats.dropped("socket_overflow") + new;
                self.stats.dropped.insert("socket_overflow", total);
                if (total - new).leading_zeros() != total.leading_zeros() || total == new {
                    tracing::warn!(
                        dropped = new,
                        total,
                        "the kernel dropped datagrams at this socket: its receive buffer was \
                         full (a flood, or this process fell behind); reliable clients send \
                         them again"
                    );
                }
            }
            _ => {}
        }
    }

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
        super::icmp::enable(std::os::fd::AsFd::as_fd(&socket), local.is_ipv6());
        Ok(UdpTransport {
            socket: mio::net::UdpSocket::from_std(socket),
            local,
            bufs: vec![0; RECV_BATCH * RECV_BUFFER],
            headers: MultiHeaders::preallocate(RECV_BATCH, None),
            got: Vec::with_capacity(RECV_BATCH),
            // Datagrams may have arrived before registration: look once.
            readable: true,
            errors_pending: false,
            unreachable: Default::default(),
            stats: TransportStats::default(),
            // A socket of its own: nothing dropped before it was served.
            kernel_drops: Some(0),
            next_drops_check: None,
            drops_unreported: false,
        })
    }

    /// The address served.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Reads up to `want` (at most [`RECV_BATCH`]) datagrams into the buffers; for each,
    /// its length and source, or why it is to be dropped (`truncated`, `unknown_source`).
    ///
    /// nix leaves each header's address length at what the kernel returned last time
    /// instead of resetting it to the buffer's size; that is right here because a UDP
    /// socket's sources all have its family's one length (16 bytes for IPv4, 28 for IPv6,
    /// v4-mapped sources included).
    fn recv_batch(
        &mut self,
        want: usize,
        got: &mut Vec<(usize, Result<SocketAddr, &'static str>)>,
    ) -> nix::Result<()> {
        got.clear();
        let mut slices: Vec<[IoSliceMut<'_>; 1]> = self
            .bufs
            .chunks_mut(RECV_BUFFER)
            .take(want.min(RECV_BATCH))
            .map(|b| [IoSliceMut::new(b)])
            .collect();
        let results = recvmmsg(
            self.socket.as_raw_fd(),
            &mut self.headers,
            slices.iter_mut(),
            MsgFlags::MSG_DONTWAIT,
            None,
        )?;
        for m in results {
            let src = if m.flags.contains(MsgFlags::MSG_TRUNC) {
                Err("truncated")
            } else {
                m.address
                    .as_ref()
                    .and_then(super::icmp::socket_addr)
                    .ok_or("unknown_source")
            };
            got.push((m.bytes, src));
        }
        Ok(())
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
        if event.is_error() {
            self.errors_pending = true;
        }
    }

    fn receive(
        &mut self,
        now: Instant,
        budget: usize,
        deliver: &mut dyn FnMut(SocketAddr, &[u8]),
    ) -> bool {
        if self.next_drops_check.is_none() && !self.drops_unreported {
            // The first reading at once, then one a period.
            self.next_drops_check = Some(now);
        }
        if std::mem::take(&mut self.errors_pending) {
            self.unreachable
                .read(std::os::fd::AsFd::as_fd(&self.socket));
        }
        if !self.readable {
            return false;
        }
        let mut errors = 0;
        let mut handled = 0;
        let mut got = std::mem::take(&mut self.got);
        while handled < budget {
            let want = (budget - handled).min(RECV_BATCH);
            match self.recv_batch(want, &mut got) {
                Ok(()) => {
                    errors = 0;
                    for (i, &(n, src)) in got.iter().enumerate() {
                        handled += 1;
                        let src = match src {
                            Ok(src) => src,
                            Err(reason) => {
                                self.stats.drop(reason);
                                continue;
                            }
                        };
                        self.stats.messages_in += 1;
                        let at = i * RECV_BUFFER;
                        deliver(src, &self.bufs[at..at + n.min(RECV_BUFFER)]);
                    }
                    if got.len() < want {
                        // Short: the socket is empty now (an empty batch is EAGAIN).
                        self.readable = false;
                        break;
                    }
                }
                Err(nix::errno::Errno::EAGAIN) => {
                    self.readable = false;
                    break;
                }
                Err(nix::errno::Errno::EINTR) => {}
                Err(
                    nix::errno::Errno::ECONNREFUSED
                    | nix::errno::Errno::EHOSTUNREACH
                    | nix::errno::Errno::ENETUNREACH,
                ) => {
                    // An ICMP error (IP_RECVERR reports it once on the next read too): what
                    // it says is in the error queue.
                    self.unreachable
                        .read(std::os::fd::AsFd::as_fd(&self.socket));
                }
                Err(e) => {
                    // Not expected, but keep reading past a stray one. Errors that repeat
                    // mean the socket itself fails: wait for the next readiness rather
                    // than spin.
                    tracing::debug!(error = %e, "recvmmsg");
                    errors += 1;
                    if errors >= 16 {
                        self.stats.drop("recv_failed");
                        self.readable = false;
                        break;
                    }
                }
            }
        }
        self.got = got;
        self.readable
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

    fn poll_unreachable(&mut self) -> Option<SocketAddr> {
        self.unreachable.pop()
    }

    fn poll_timeout(&self) -> Option<Instant> {
        self.next_drops_check
    }

    fn handle_timeout(&mut self, now: Instant) {
        if self.next_drops_check.is_some_and(|t| t <= now) {
            self.next_drops_check = Some(now + KERNEL_DROPS_PERIOD);
            let socket = std::os::fd::AsFd::as_fd(&self.socket);
            match crate::sys::socket_drops::dropped_at(socket) {
                Some(count) => self.kernel_dropped(count),
                None => {
                    self.next_drops_check = None;
                    self.drops_unreported = true;
                    tracing::debug!("the kernel does not report this socket's drops");
                }
            }
        }
    }

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

/// `udp4` and `udp6`: a socket bound to `addr`.
pub fn open(addr: SocketAddr) -> std::io::Result<UdpTransport> {
    let socket = std::net::UdpSocket::bind(addr)
        .map_err(|e| std::io::Error::new(e.kind(), format!("binding UDP {addr}: {e}")))?;
    UdpTransport::new(socket)
}

/// Serves the UDP socket the parent process bound and left open at descriptor `fd` (a port
/// several front-ends share), after checking that it is one: a datagram socket bound to
/// exactly `listen` (address, wildcard or not, and port).
pub fn inherited(fd: std::os::fd::RawFd, listen: SocketAddr) -> std::io::Result<UdpTransport> {
    let file = crate::sys::owned_fd::inherited(fd)?;
    let socket = std::net::UdpSocket::from(std::os::fd::OwnedFd::from(file));
    let kind = socket2::SockRef::from(&socket).r#type()?;
    if kind != socket2::Type::DGRAM {
        return Err(std::io::Error::other(format!(
            "descriptor {fd} is not a datagram socket"
        )));
    }
    let local = socket.local_addr()?;
    if local != listen {
        return Err(std::io::Error::other(format!(
            "descriptor {fd} is a socket bound to {local}, not {listen}"
        )));
    }
    let mut t = UdpTransport::new(socket)?;
    // What its predecessor's drops were, this process cannot tell.
    t.kernel_drops = None;
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair() -> (UdpTransport, std::net::UdpSocket) {
        let server = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let client = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        client
            .connect(server.local_addr().expect("addr"))
            .expect("connect");
        (UdpTransport::new(server).expect("transport"), client)
    }

    fn receive_all(t: &mut UdpTransport, budget: usize) -> (Vec<(SocketAddr, Vec<u8>)>, bool) {
        let mut got = Vec::new();
        let left = t.receive(Instant::now(), budget, &mut |from, bytes| {
            got.push((from, bytes.to_vec()))
        });
        (got, left)
    }

    /// Datagrams the kernel dropped at a full socket are counted (`socket_overflow`) at
    /// the next reading of its count, once each.
    #[test]
    fn what_the_kernel_drops_at_a_full_socket_is_counted() {
        let (mut t, client) = pair();
        socket2::SockRef::from(&t.socket)
            .set_recv_buffer_size(4096)
            .expect("a small buffer");
        assert_eq!(
            t.poll_timeout(),
            None,
            "not armed before the first loop pass"
        );
        receive_all(&mut t, 1_000);
        let first = t.poll_timeout().expect("armed by the first loop pass");
        t.handle_timeout(first);
        for _ in 0..200 {
            client.send(&[0u8; 512]).expect("send");
        }
        t.readable = true; // as its readiness event would say
        let (got, _) = receive_all(&mut t, 1_000);
        assert!(got.len() < 200, "some were dropped");
        let next = t.poll_timeout().expect("the next reading");
        assert_eq!(next, first + KERNEL_DROPS_PERIOD);
        t.handle_timeout(next);
        let counted = t.stats.dropped("socket_overflow");
        assert_eq!(counted, 200 - got.len() as u64, "every drop");
        // The count is the kernel's total: read again, nothing more is counted.
        t.handle_timeout(next + KERNEL_DROPS_PERIOD);
        assert_eq!(
            t.stats.dropped("socket_overflow"),
            counted,
            "each drop once"
        );
        // It is 32 bits and wraps.
        t.kernel_drops = Some(u32::MAX);
        t.kernel_dropped(2);
        assert_eq!(t.stats.dropped("socket_overflow"), counted + 3);
    }

    /// An inherited descriptor is served only if it is a datagram socket on the port (and
    /// address) the settings name.
    #[test]
    fn an_inherited_socket_must_be_the_one_the_settings_name() {
        use std::os::fd::IntoRawFd;
        let good = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let listen = good.local_addr().expect("addr");
        // All open at once: a descriptor number is taken once per process.
        let other = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let tcp = std::net::TcpListener::bind(listen).expect("listen");
        let wildcard = std::net::UdpSocket::bind("0.0.0.0:0").expect("bind");
        let wildcard_listen =
            SocketAddr::new(listen.ip(), wildcard.local_addr().expect("a").port());
        let e = inherited(other.into_raw_fd(), listen).expect_err("another port");
        assert!(e.to_string().contains("not 127.0.0.1"), "{e}");
        let e = inherited(tcp.into_raw_fd(), listen).expect_err("a stream socket");
        assert!(e.to_string().contains("not a datagram socket"), "{e}");
        // The port named, but on every address rather than the one named.
        let e = inherited(wildcard.into_raw_fd(), wildcard_listen).expect_err("wildcard");
        assert!(e.to_string().contains("bound to 0.0.0.0"), "{e}");
        let t = inherited(good.into_raw_fd(), listen).expect("the socket named");
        assert_eq!(t.local, listen);
    }

    #[test]
    fn datagrams_beyond_one_batch_arrive_whole_in_order_with_their_source() {
        let (mut t, client) = pair();
        let n = RECV_BATCH * 2 + 5;
        for i in 0..n {
            // Lengths vary, so a datagram read into the wrong buffer or with the wrong
            // length shows.
            client.send(&vec![i as u8; 1 + i * 7]).expect("send");
        }
        let (got, left) = receive_all(&mut t, 1_000);
        assert!(!left, "a short batch means the socket is empty");
        assert_eq!(got.len(), n);
        for (i, (from, bytes)) in got.iter().enumerate() {
            assert_eq!(*from, client.local_addr().expect("addr"));
            assert_eq!(bytes, &vec![i as u8; 1 + i * 7]);
        }
        assert_eq!(t.stats().messages_in, n as u64);
        // Empty and marked so: nothing is read until the next readiness.
        assert_eq!(receive_all(&mut t, 1_000), (Vec::new(), false));
    }

    #[test]
    fn the_budget_bounds_one_call_and_the_rest_waits_for_the_next() {
        let (mut t, client) = pair();
        for i in 0..10u8 {
            client.send(&[i]).expect("send");
        }
        let (first, left) = receive_all(&mut t, 4);
        assert!(left, "input is left");
        assert_eq!(first.len(), 4);
        let (rest, left) = receive_all(&mut t, 100);
        assert!(!left);
        let order: Vec<u8> = first.iter().chain(&rest).map(|(_, b)| b[0]).collect();
        assert_eq!(order, (0..10).collect::<Vec<u8>>());
    }

    #[test]
    fn an_ipv6_source_is_read_with_its_address_and_port() {
        let server = std::net::UdpSocket::bind("[::1]:0").expect("IPv6 loopback");
        let client = std::net::UdpSocket::bind("[::1]:0").expect("bind");
        let mut t = UdpTransport::new(server).expect("transport");
        client.send_to(b"six", t.local_addr()).expect("send");
        let (got, _) = receive_all(&mut t, 10);
        assert_eq!(
            got,
            vec![(client.local_addr().expect("addr"), b"six".to_vec())]
        );
    }

    #[test]
    fn the_largest_datagram_gets_through() {
        let (mut t, client) = pair();
        let big = vec![0xA5; 65_507];
        client.send(&big).expect("send");
        client.send(b"after").expect("send");
        let (got, _) = receive_all(&mut t, 10);
        assert_eq!(got.len(), 2);
        assert_eq!(got[0].1, big);
        assert_eq!(got[1].1, b"after");
    }
}
