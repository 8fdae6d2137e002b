//! One UDP port served by several front-end processes (`processes` in a gateway file,
//! `--processes` on the command line).
//!
//! The supervisor binds one socket per front-end on the port with `SO_REUSEPORT` and keeps
//! them for the agent's life; each front-end serves its own (handed over like a
//! pseudoterminal), and a restarted one gets the same socket back. The kernel picks the
//! socket of each datagram with a classic BPF program attached to the group
//! ([`steering_program`]): a hash of the **source address alone**, so a client stays on one
//! front-end when its port changes (a board that resets binds a new ephemeral port, and its
//! session and entities are where it left them), and an address's session limits and fair
//! shares, which each front-end keeps, still see all of that address's clients. Clients
//! behind one address (a NAT, or one host running many) are served by one front-end.
//!
//! The mapping is fixed: member `i` of `n` gets the addresses whose hash is `i` modulo `n`
//! ([`member_for`]), and the kernel numbers the sockets of a group in the order they were
//! bound, which is the members' order, here, once the port is free. Since the sockets are
//! held for the group's life, a front-end that dies does not move its clients to the
//! others: their datagrams wait in its socket until its successor reads them, and the
//! successor takes its sessions over. A new agent of the instance binds again in the same
//! order once the previous agent's processes have let the port go, so its front-ends find
//! their clients where their stored sessions say.

use std::net::{IpAddr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use nix::sys::socket::{setsockopt, sockopt};

/// Most processes one port may be served by.
pub const MAX_PROCESSES: u16 = 64;

/// Multiplier of the source-address hash (2^32 divided by the golden ratio): neighbouring
/// addresses land on different members.
const HASH_MULTIPLIER: u32 = 0x9E37_79B1;

/// The member of `members` that serves clients from `source` (what [`steering_program`]
/// computes in the kernel). An IPv4 client of a dual-stack IPv6 socket is hashed as IPv4,
/// as its datagrams carry an IPv4 header.
pub fn member_for(source: IpAddr, members: u16) -> u16 {
    let folded = match source {
        IpAddr::V4(a) => u32::from_be_bytes(a.octets()),
        IpAddr::V6(a) => match a.to_ipv4_mapped() {
            Some(v4) => u32::from_be_bytes(v4.octets()),
            None => a
                .octets()
                .chunks_exact(4)
                .map(|w| u32::from_be_bytes([w[0], w[1], w[2], w[3]]))
                .fold(0, |acc, w| acc ^ w),
        },
    };
    let mixed = folded.wrapping_mul(HASH_MULTIPLIER) >> 16;
    (mixed % u32::from(members.max(1))) as u16
}

/// Offset of the network header in a socket filter's loads (`SKF_NET_OFF`): a reuseport
/// program sees the datagram from its UDP payload on, and reaches the IP header from here.
const NET: u32 = libc::SKF_NET_OFF as u32;

fn op(code: u32, jt: u8, jf: u8, k: u32) -> libc::sock_filter {
    libc::sock_filter {
        code: code as u16,
        jt,
        jf,
        k,
    }
}

/// The classic BPF program that returns, for a datagram, the index of the member socket
/// that receives it: [`member_for`] its source address. (An index the group does not have,
/// which cannot happen here, would make the kernel fall back to its own 4-tuple hash.)
pub fn steering_program(members: u16) -> Vec<libc::sock_filter> {
    use libc::{
        BPF_A, BPF_ABS, BPF_ALU, BPF_B, BPF_JA, BPF_JEQ, BPF_JMP, BPF_K, BPF_LD, BPF_MISC, BPF_MOD,
        BPF_MUL, BPF_RET, BPF_RSH, BPF_TAX, BPF_W, BPF_X, BPF_XOR,
    };
    let ld_word = |offset: u32| op(BPF_LD | BPF_W | BPF_ABS, 0, 0, NET + offset);
    let tax = op(BPF_MISC | BPF_TAX, 0, 0, 0);
    let xor_x = op(BPF_ALU | BPF_XOR | BPF_X, 0, 0, 0);
    vec![
        // The IP version, from the header's first octet.
        op(BPF_LD | BPF_B | BPF_ABS, 0, 0, NET),
        op(BPF_ALU | BPF_RSH | BPF_K, 0, 0, 4),
        // IPv6: go on; else to the IPv4 load, 11 instructions below the next.
        op(BPF_JMP | BPF_JEQ | BPF_K, 0, 11, 6),
        // IPv6: the source address's four words (octets 8-23), XORed together.
        ld_word(8),
        tax,
        ld_word(12),
        xor_x,
        tax,
        ld_word(16),
        xor_x,
        tax,
        ld_word(20),
        xor_x,
        op(BPF_JMP | BPF_JA, 0, 0, 1),
        // IPv4: the source address (octets 12-15).
        ld_word(12),
        // The mix and the member.
        op(BPF_ALU | BPF_MUL | BPF_K, 0, 0, HASH_MULTIPLIER),
        op(BPF_ALU | BPF_RSH | BPF_K, 0, 0, 16),
        op(BPF_ALU | BPF_MOD | BPF_K, 0, 0, u32::from(members.max(1))),
        op(BPF_RET | BPF_A, 0, 0, 0),
    ]
}

/// Why the sockets of a shared port could not be made.
#[derive(Debug, thiserror::Error)]
pub enum SharedPortError {
    /// Another socket kept the port (another program, or the previous agent's processes
    /// past the wait).
    #[error("UDP {listen} stays in use ({error}): the sockets of its {members} front-ends are bound only once it is free, so each gets the same clients as before")]
    InUse {
        /// The address and port.
        listen: SocketAddr,
        /// How many front-ends share it.
        members: u16,
        /// The last error of binding it.
        error: std::io::Error,
    },
    /// A socket could not be made, bound or steered.
    #[error("UDP {listen}, socket {member} of {members}: {what}: {error}")]
    Socket {
        /// The address and port.
        listen: SocketAddr,
        /// Which member's socket.
        member: u16,
        /// How many front-ends share it.
        members: u16,
        /// What failed.
        what: &'static str,
        /// The error.
        error: std::io::Error,
    },
}

/// Binds `members` sockets on `listen` with `SO_REUSEPORT`, in the members' order, steered
/// by source address ([`steering_program`]). First waits up to `wait` for the port to be
/// free (a socket of the previous agent would otherwise join the group and take datagrams it
/// no longer reads, and the members' order would not be the one the clients' stored
/// sessions expect).
pub fn bind(
    listen: SocketAddr,
    members: u16,
    wait: Duration,
) -> Result<Vec<UdpSocket>, SharedPortError> {
    let end = Instant::now() + wait;
    loop {
        // A plain socket binds only a port nobody holds, with or without SO_REUSEPORT.
        match UdpSocket::bind(listen) {
            Ok(probe) => {
                drop(probe);
                break;
            }
            Err(error) if Instant::now() >= end => {
                return Err(SharedPortError::InUse {
                    listen,
                    members,
                    error,
                })
            }
            Err(_) => std::thread::sleep(Duration::from_millis(20)),
        }
    }
    let failed = |member: u16, what: &'static str| {
        move |error: std::io::Error| SharedPortError::Socket {
            listen,
            member,
            members,
            what,
            error,
        }
    };
    let mut sockets = Vec::with_capacity(usize::from(members));
    for member in 0..members {
        let domain = socket2::Domain::for_address(listen);
        let s = socket2::Socket::new(domain, socket2::Type::DGRAM, Some(socket2::Protocol::UDP))
            .map_err(failed(member, "creating it"))?;
        s.set_reuse_port(true)
            .map_err(failed(member, "setting SO_REUSEPORT"))?;
        s.bind(&listen.into())
            .map_err(failed(member, "binding it"))?;
        sockets.push(UdpSocket::from(s));
    }
    if let Some(first) = sockets.first() {
        let mut program = steering_program(members);
        let fprog = libc::sock_fprog {
            len: program.len() as u16,
            filter: program.as_mut_ptr(),
        };
        // The kernel copies the program during the call; `program` outlives it.
        setsockopt(first, sockopt::AttachReusePortCbpf, &fprog)
            .map_err(|e| failed(0, "attaching the steering program")(e.into()))?;
    }
    // Until the program was attached the kernel spread datagrams by its own hash: those
    // may wait in a socket whose front-end does not have their client's session. Dropped
    // (the clients send again); from here on each lands where it belongs.
    let mut buf = [0u8; 1];
    for (member, s) in sockets.iter().enumerate() {
        let member = member as u16;
        s.set_nonblocking(true)
            .map_err(failed(member, "making it non-blocking"))?;
        while s.recv(&mut buf).is_ok() {}
    }
    Ok(sockets)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::{Ipv4Addr, Ipv6Addr};

    /// Which member sockets received a datagram (all non-blocking, read once each).
    fn receivers(sockets: &[UdpSocket]) -> Vec<u16> {
        let mut buf = [0u8; 16];
        let mut got = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(2);
        while got.is_empty() && Instant::now() < deadline {
            for (i, s) in sockets.iter().enumerate() {
                while s.recv(&mut buf).is_ok() {
                    got.push(i as u16);
                }
            }
        }
        got
    }

    /// A group of `members` on a free port of `ip` (IPv6 loopback included: the end-to-end
    /// suite needs it too).
    fn group_on(ip: IpAddr, members: u16) -> (u16, Vec<UdpSocket>) {
        let probe = UdpSocket::bind((ip, 0)).expect("a free port");
        let port = probe.local_addr().expect("its address").port();
        drop(probe);
        let sockets = bind(SocketAddr::new(ip, port), members, Duration::from_secs(1));
        (port, sockets.expect("bind"))
    }

    /// Datagrams from `source` (new sockets each) to `target` all reach the member
    /// [`member_for`] names.
    fn steered(sockets: &[UdpSocket], source: IpAddr, target: SocketAddr, members: u16) -> u16 {
        let expected = member_for(source, members);
        for _ in 0..3 {
            let client = UdpSocket::bind((source, 0)).expect("client");
            client.send_to(b"x", target).expect("send");
            assert_eq!(receivers(sockets), vec![expected], "from {source}");
        }
        expected
    }

    #[test]
    fn a_client_stays_on_its_member_whatever_its_port() {
        let members = 4;
        let localhost = IpAddr::V4(Ipv4Addr::LOCALHOST);
        let (port, sockets) = group_on(localhost, members);
        let mut seen = std::collections::HashSet::new();
        for last in 1..=16u8 {
            let source = IpAddr::V4(Ipv4Addr::new(127, 0, 0, last));
            seen.insert(steered(&sockets, source, (localhost, port).into(), members));
        }
        assert!(seen.len() > 1, "sixteen addresses spread over the members");
    }

    /// IPv4 clients of a dual-stack IPv6 group are steered by their IPv4 address.
    #[test]
    fn ipv4_clients_of_a_dual_stack_port_are_steered_as_ipv4() {
        let (port, sockets) = group_on(IpAddr::V6(Ipv6Addr::UNSPECIFIED), 4);
        if socket2::SockRef::from(&sockets[0])
            .only_v6()
            .unwrap_or(true)
        {
            // IPv4 clients cannot reach an IPv6 socket here (net.ipv6.bindv6only = 1).
            eprintln!("skipped: IPv6 sockets are IPv6-only on this host");
            return;
        }
        let target = SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), port);
        for last in 1..=8u8 {
            steered(
                &sockets,
                IpAddr::V4(Ipv4Addr::new(127, 0, 0, last)),
                target,
                4,
            );
        }
    }

    #[test]
    fn ipv6_clients_are_steered_by_their_address_too() {
        let localhost = IpAddr::V6(Ipv6Addr::LOCALHOST);
        let (port, sockets) = group_on(localhost, 3);
        steered(&sockets, localhost, (localhost, port).into(), 3);
    }

    #[test]
    fn a_port_held_by_another_socket_is_refused_after_the_wait() {
        let holder = UdpSocket::bind("127.0.0.1:0").expect("bind");
        let listen = holder.local_addr().expect("addr");
        let started = Instant::now();
        let err = bind(listen, 2, Duration::from_millis(100)).expect_err("port in use");
        assert!(started.elapsed() >= Duration::from_millis(100));
        assert!(matches!(err, SharedPortError::InUse { .. }), "{err}");
    }

    #[test]
    fn an_ipv4_mapped_source_is_hashed_as_ipv4() {
        let v4 = Ipv4Addr::new(192, 168, 1, 20);
        for n in 1..=8 {
            assert_eq!(
                member_for(IpAddr::V6(v4.to_ipv6_mapped()), n),
                member_for(IpAddr::V4(v4), n)
            );
        }
    }

    #[test]
    fn neighbouring_addresses_spread_evenly() {
        let members = 4;
        let mut counts = [0u32; 4];
        for i in 0..1_000u32 {
            let a = Ipv4Addr::from(u32::from(Ipv4Addr::new(10, 0, 0, 0)) + i);
            counts[usize::from(member_for(IpAddr::V4(a), members))] += 1;
        }
        for c in counts {
            assert!((200..=300).contains(&c), "{counts:?}");
        }
    }
}
