//! What a UDP socket's error queue says about its peers: a host that answers a datagram with
//! ICMP "port unreachable" says nothing listens at that port any more.
//!
//! A client that resets comes back from a new port, and its session moves there only once
//! the old endpoint was probed and found silent (a host presenting a live client's key must
//! not take its session). When the client's host is reachable (the same host, a LAN) its
//! kernel or IP stack (lwIP included) answers the probe to the closed port at once with
//! ICMP port unreachable: with `IP_RECVERR` the socket queues it, and the session moves then
//! instead of after the probe wait. Only a port unreachable sent by the endpoint's own host
//! counts: a router's "host unreachable" says nothing about the client.

use std::collections::VecDeque;
use std::io::IoSliceMut;
use std::net::{IpAddr, SocketAddr};
use std::os::fd::{AsRawFd, BorrowedFd};

use nix::sys::socket::{
    recvmsg, setsockopt, sockopt, ControlMessageOwned, MsgFlags, SockaddrStorage,
};

/// Most unreachable endpoints remembered between two looks of the loop.
const MAX_PENDING: usize = 1024;
/// Most errors read per look (the rest waits for the next).
const MAX_READ: usize = 256;

/// ICMPv4 destination unreachable / port unreachable.
const ICMP_DEST_UNREACH: u8 = 3;
const ICMP_PORT_UNREACH: u8 = 3;
/// ICMPv6 destination unreachable / port unreachable.
const ICMP6_DST_UNREACH: u8 = 1;
const ICMP6_PORT_UNREACH: u8 = 4;

/// Asks the kernel to queue ICMP errors for this socket (IPv4 and, for an IPv6 socket, IPv6
/// too: a dual-stack socket gets v4-mapped peers' errors as IPv4 ones). Best effort: without
/// it, sessions move after the probe wait, as before.
pub fn enable(fd: BorrowedFd<'_>, v6: bool) {
    let v4 = setsockopt(&fd, sockopt::Ipv4RecvErr, &true);
    let v6 = if v6 {
        setsockopt(&fd, sockopt::Ipv6RecvErr, &true)
    } else {
        Ok(())
    };
    if let Err(e) = v4.and(v6) {
        tracing::debug!(error = %e, "IP_RECVERR not set: a reset client's session moves after the probe wait");
    }
}

/// Endpoints found unreachable, in the order the errors came.
#[derive(Debug, Default)]
pub struct Unreachable {
    pending: VecDeque<SocketAddr>,
}

impl Unreachable {
    /// Reads the socket's error queue (without blocking) and keeps every endpoint whose own
    /// host answered "port unreachable".
    pub fn read(&mut self, fd: BorrowedFd<'_>) {
        let mut cmsg = nix::cmsg_space!(libc::sock_extended_err, libc::sockaddr_in6);
        // The bytes of the datagram that caused the error are not needed.
        let mut quoted = [0u8; 64];
        for _ in 0..MAX_READ {
            let mut iov = [IoSliceMut::new(&mut quoted)];
            let msg = match recvmsg::<SockaddrStorage>(
                fd.as_raw_fd(),
                &mut iov,
                Some(&mut cmsg),
                MsgFlags::MSG_ERRQUEUE | MsgFlags::MSG_DONTWAIT,
            ) {
                Ok(m) => m,
                Err(_) => break,
            };
            let Some(to) = msg.address.as_ref().and_then(socket_addr) else {
                continue;
            };
            let Ok(cmsgs) = msg.cmsgs() else { continue };
            for c in cmsgs {
                let (origin, kind, code, offender) = match c {
                    ControlMessageOwned::Ipv4RecvErr(e, from) => (
                        (e.ee_origin, libc::SO_EE_ORIGIN_ICMP),
                        (e.ee_type, ICMP_DEST_UNREACH),
                        (e.ee_code, ICMP_PORT_UNREACH),
                        from.map(|a| {
                            IpAddr::from(std::net::Ipv4Addr::from(u32::from_be(a.sin_addr.s_addr)))
                        }),
                    ),
                    ControlMessageOwned::Ipv6RecvErr(e, from) => (
                        (e.ee_origin, libc::SO_EE_ORIGIN_ICMP6),
                        (e.ee_type, ICMP6_DST_UNREACH),
                        (e.ee_code, ICMP6_PORT_UNREACH),
                        from.map(|a| IpAddr::from(std::net::Ipv6Addr::from(a.sin6_addr.s6_addr))),
                    ),
                    _ => continue,
                };
                let port_unreachable = origin.0 == origin.1 && kind.0 == kind.1 && code.0 == code.1;
                let from_its_host = offender.is_some_and(|o| same_host(o, to.ip()));
                if port_unreachable && from_its_host && self.pending.len() < MAX_PENDING {
                    tracing::debug!(%to, "ICMP port unreachable: nothing listens there any more");
                    self.pending.push_back(to);
                }
            }
        }
    }

    /// The next endpoint found unreachable.
    pub fn pop(&mut self) -> Option<SocketAddr> {
        self.pending.pop_front()
    }
}

/// Whether two addresses are one host's (an IPv4 address and its v4-mapped IPv6 form are).
fn same_host(a: IpAddr, b: IpAddr) -> bool {
    a.to_canonical() == b.to_canonical()
}

/// The IP address and port of a datagram's source (or of the destination an ICMP error names).
pub(super) fn socket_addr(a: &SockaddrStorage) -> Option<SocketAddr> {
    if let Some(v4) = a.as_sockaddr_in() {
        return Some(SocketAddr::V4((*v4).into()));
    }
    a.as_sockaddr_in6().map(|v6| SocketAddr::V6((*v6).into()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::fd::AsFd;
    use std::time::{Duration, Instant};

    /// A datagram to a closed port on loopback comes back as ICMP port unreachable, and the
    /// error queue names that endpoint.
    #[test]
    fn a_closed_port_is_reported_unreachable() {
        let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        socket.set_nonblocking(true).expect("non-blocking");
        enable(socket.as_fd(), false);
        let closed = {
            let s = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
            s.local_addr().expect("addr")
        };
        socket.send_to(b"probe", closed).expect("send");
        let mut u = Unreachable::default();
        let end = Instant::now() + Duration::from_secs(2);
        let mut found = None;
        while found.is_none() && Instant::now() < end {
            u.read(socket.as_fd());
            found = u.pop();
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(found, Some(closed));
        assert!(same_host(
            "127.0.0.1".parse().expect("an address"),
            "::ffff:127.0.0.1".parse().expect("an address")
        ));
    }
}
