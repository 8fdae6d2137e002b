//! Multicast agent discovery (`-d/--discovery [PORT]`): clients send a session-less GET_INFO
//! to 239.255.0.2 on the discovery port (7400 by default) and every agent answers, to the
//! sender, with INFO listing the locators where it serves clients.
//!
//! The multicast socket is bound to the group address itself, so it receives only datagrams
//! sent to that group: port 7400 is also DDS domain 0's discovery port, and DDS traffic to
//! other groups never reaches it. It joins the group on the front-end's interface, or on
//! every IPv4 interface when the front-end serves all of them.
//!
//! Other sockets take the requests a client sends straight to an agent's address on the
//! discovery port (the eProsima client's `uxr_discovery_agents` with a list of agents; the
//! reference agent answers those too): one bound to each address the front-end serves (each
//! IPv4 address of the machine when it serves all), never to the wildcard, so that a DDS
//! participant's socket on port 7400, bound to the wildcard, does not take them (Linux gives
//! a unicast datagram to one socket, the most specific). On a shared address the agent takes
//! unicast datagrams to that port from DDS (which sends none there by default: they are
//! dropped, counted), and two agents on one address share its requests. They take no
//! multicast.

use std::net::{IpAddr, Ipv4Addr, SocketAddr, SocketAddrV4};

use mio::event::Event;
use mio::{Interest, Registry, Token};
use socket2::{Domain, Protocol, Socket, Type};
use xrce_common::session::discovery::{answer, DISCOVERY_GROUP};
use xrce_common::wire::info::TransportLocator;

use super::TransportStats;

/// Requests answered per wake-up before the sessions get a turn.
const BATCH: usize = 64;

/// The discovery responder of one front-end.
#[derive(Debug)]
pub struct Discovery {
    socket: mio::net::UdpSocket,
    /// Requests sent to the front-end's addresses on the discovery port (one socket per
    /// address where that port could be bound).
    unicast: Vec<mio::net::UdpSocket>,
    /// Answers go out from here (a socket bound to a group address cannot send from it).
    reply: std::net::UdpSocket,
    port: u16,
    vendor_id: [u8; 2],
    locators: Vec<TransportLocator>,
    readable: bool,
    buf: Vec<u8>,
    stats: TransportStats,
}

impl Discovery {
    /// Listens on the discovery group at `port`, on the interface of `served` (every IPv4
    /// interface if it is unspecified or IPv6), answering with `locators`.
    pub fn new(
        port: u16,
        served: Option<IpAddr>,
        vendor_id: [u8; 2],
        locators: Vec<TransportLocator>,
    ) -> std::io::Result<Self> {
        let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
        // Other agents (and DDS, on 7400) may listen on the same port.
        socket.set_reuse_address(true)?;
        socket.set_reuse_port(true)?;
        socket.set_multicast_all_v4(false)?;
        socket.bind(&SocketAddr::V4(SocketAddrV4::new(DISCOVERY_GROUP, port)).into())?;
        let interfaces = match served {
            Some(IpAddr::V4(a)) if !a.is_unspecified() => vec![a],
            _ => ipv4_interfaces(),
        };
        let mut joined = 0;
        for iface in &interfaces {
            match socket.join_multicast_v4(&DISCOVERY_GROUP, iface) {
                Ok(()) => joined += 1,
                Err(e) => {
                    tracing::warn!(interface = %iface, error = %e, "could not join the discovery group")
                }
            }
        }
        if joined == 0 {
            return Err(std::io::Error::other(format!(
                "could not join {DISCOVERY_GROUP} on any of {interfaces:?}"
            )));
        }
        socket.set_nonblocking(true)?;
        let reply_from = match served {
            Some(IpAddr::V4(a)) => a,
            _ => Ipv4Addr::UNSPECIFIED,
        };
        let reply = std::net::UdpSocket::bind((reply_from, 0))?;
        reply.set_nonblocking(true)?;
        let mut unicast = Vec::new();
        for address in &interfaces {
            match unicast_socket(*address, port) {
                Ok(s) => unicast.push(s),
                Err(e) => {
                    tracing::warn!(%address, port, error = %e, "discovery requests sent to this address are not answered: the port is taken there")
                }
            }
        }
        tracing::info!(group = %DISCOVERY_GROUP, port, ?interfaces, ?locators, unicast = unicast.len(), "discovery server listening");
        Ok(Discovery {
            socket: mio::net::UdpSocket::from_std(socket.into()),
            unicast,
            reply,
            port,
            vendor_id,
            locators,
            readable: true,
            buf: vec![0; 2048],
            stats: TransportStats::default(),
        })
    }

    /// The discovery port.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Registers the sockets with `token`.
    pub fn register(&mut self, registry: &Registry, token: Token) -> std::io::Result<()> {
        registry.register(&mut self.socket, token, Interest::READABLE)?;
        for u in self.unicast.iter_mut() {
            registry.register(u, token, Interest::READABLE)?;
        }
        Ok(())
    }

    /// Records readiness.
    pub fn on_event(&mut self, event: &Event) {
        if event.is_readable() || event.is_error() {
            self.readable = true;
        }
    }

    /// Answers pending requests; returns whether some are left.
    pub fn answer_pending(&mut self) -> bool {
        if !self.readable {
            return false;
        }
        // The group's socket (0) and the unicast ones (1..) in turn, each until it has nothing.
        let sockets = 1 + self.unicast.len();
        let mut drained = vec![false; sockets];
        let mut next = 0;
        for _ in 0..BATCH {
            let Some(which) = (0..sockets)
                .map(|k| (next + k) % sockets)
                .find(|w| !drained[*w])
            else {
                self.readable = false;
                return false;
            };
            next = which + 1;
            let received = match which {
                0 => self.socket.recv_from(&mut self.buf),
                w => self.unicast[w - 1].recv_from(&mut self.buf),
            };
            let (n, from) = match received {
                Ok(r) => r,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    drained[which] = true;
                    continue;
                }
                Err(e) => {
                    tracing::debug!(error = %e, "discovery recv_from");
                    continue;
                }
            };
            self.stats.messages_in += 1;
            match answer(&self.buf[..n], self.vendor_id, &self.locators) {
                Ok(reply) => match self.reply.send_to(&reply, from) {
                    Ok(_) => {
                        self.stats.messages_out += 1;
                        tracing::debug!(%from, "discovery request answered");
                    }
                    Err(e) => {
                        self.stats.drop("send_failed");
                        tracing::debug!(%from, error = %e, "discovery answer not sent");
                    }
                },
                Err(e) => {
                    self.stats.drop(e.reason());
                    tracing::debug!(%from, reason = e.reason(), "discovery datagram ignored");
                }
            }
        }
        true
    }

    /// Counters.
    pub fn stats(&self) -> &TransportStats {
        &self.stats
    }
}

/// The socket for discovery requests sent to `address` on `port` (SO_REUSEADDR: DDS's own
/// socket on that port, bound to the wildcard, and other agents' may be there too), taking
/// no multicast (those come through the group's socket).
fn unicast_socket(address: Ipv4Addr, port: u16) -> std::io::Result<mio::net::UdpSocket> {
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_reuse_address(true)?;
    socket.set_multicast_all_v4(false)?;
    socket.bind(&SocketAddr::V4(SocketAddrV4::new(address, port)).into())?;
    socket.set_nonblocking(true)?;
    Ok(mio::net::UdpSocket::from_std(socket.into()))
}

/// Every IPv4 address of the machine's interfaces that are up, loopback included.
fn ipv4_interfaces() -> Vec<Ipv4Addr> {
    let mut out = Vec::new();
    if let Ok(addrs) = nix::ifaddrs::getifaddrs() {
        for a in addrs {
            if !a.flags.contains(nix::net::if_::InterfaceFlags::IFF_UP) {
                continue;
            }
            if let Some(sin) = a.address.as_ref().and_then(|s| s.as_sockaddr_in()) {
                let ip = sin.ip();
                if !out.contains(&ip) {
                    out.push(ip);
                }
            }
        }
    }
    out
}

/// Every IPv6 address of the machine's interfaces that are up.
fn ipv6_interfaces() -> Vec<std::net::Ipv6Addr> {
    let mut out = Vec::new();
    if let Ok(addrs) = nix::ifaddrs::getifaddrs() {
        for a in addrs {
            if !a.flags.contains(nix::net::if_::InterfaceFlags::IFF_UP) {
                continue;
            }
            if let Some(sin6) = a.address.as_ref().and_then(|s| s.as_sockaddr_in6()) {
                let ip = sin6.ip();
                if !out.contains(&ip) {
                    out.push(ip);
                }
            }
        }
    }
    out
}

/// Most locators an answer lists: the eProsima client keeps the first four (and reads
/// answers into a 200-byte buffer).
pub const MAX_ANSWER_LOCATORS: usize = 4;

/// The locators of an IP transport served at `local`: that address, or, when it is
/// unspecified, the addresses of its family, as the reference agent lists them, but other
/// than loopback first and at most [`MAX_ANSWER_LOCATORS`] (a client discovering an agent
/// on another machine cannot use 127.0.0.1).
pub fn ip_locators(local: SocketAddr) -> Vec<TransportLocator> {
    let mut all = all_ip_locators(local);
    all.sort_by_key(|l| match l {
        TransportLocator::Medium { address, .. } => address[0] == 127,
        TransportLocator::Large { address, .. } => std::net::Ipv6Addr::from(*address).is_loopback(),
        _ => false,
    });
    all.truncate(MAX_ANSWER_LOCATORS);
    all
}

fn all_ip_locators(local: SocketAddr) -> Vec<TransportLocator> {
    let port = local.port();
    match local.ip() {
        IpAddr::V4(a) if a.is_unspecified() => ipv4_interfaces()
            .into_iter()
            .map(|a| TransportLocator::Medium {
                address: a.octets(),
                port,
            })
            .collect(),
        IpAddr::V4(a) => vec![TransportLocator::Medium {
            address: a.octets(),
            port,
        }],
        IpAddr::V6(a) if a.is_unspecified() => ipv6_interfaces()
            .into_iter()
            .map(|a| TransportLocator::Large {
                address: a.octets(),
                port: port as u32,
            })
            .collect(),
        IpAddr::V6(a) => vec![TransportLocator::Large {
            address: a.octets(),
            port: port as u32,
        }],
    }
}
