//! The UDP ports DDS binds in a domain, and the agent's own: an XRCE port that is also a
//! well-known DDS port must not cost the clients their DDS.
//!
//! RTPS fixes where a participant listens (RTPS 2.5 §9.6.2.3, the default port mapping every
//! DDS implementation uses): in domain `d`, discovery multicast on `7400 + 250·d`, user-data
//! multicast on `7400 + 250·d + 1`, and for participant index `i` discovery unicast on
//! `7400 + 250·d + 10 + 2·i` and user-data unicast on `7400 + 250·d + 11 + 2·i`. Almost every
//! UDP port from 7400 up is one of them for some domain: RTI's XRCE client defaults to 7401,
//! domain 0's user-data multicast port. A front-end holds its UDP port exclusively (no
//! `SO_REUSEADDR`: datagrams for it must not land on another socket), so a DDS socket that
//! wants the same port fails to bind:
//!
//! * multicast ports (bound by DDS with `SO_REUSEADDR`/`SO_REUSEPORT`, to share them with the
//!   host's other participants): Cyclone DDS fails to create the domain at all, RustDDS goes on
//!   without that listener. Fast DDS (under eProsima's agent) does not clash on 7401 because by
//!   default it listens for user data by unicast only; it binds the discovery multicast port.
//! * unicast ports: every implementation moves on to the next participant index (Cyclone with
//!   `ParticipantIndex auto`, RustDDS, Fast DDS), or takes a port the kernel chooses (Cyclone's
//!   default `none`), so these never fail.
//!
//! What the backends do with a domain ([`plan`]):
//!
//! * The user-data multicast port taken (by a front-end, or by any socket that does not share
//!   it): Cyclone receives user-data multicast on a spare port of the domain instead
//!   (`Discovery/Ports/MulticastDataOffset`, one of offsets 2-9, which no domain uses); its
//!   SPDP announces that locator, and the other participants send there (RTPS writers send to
//!   the locators a reader's participant announces). RustDDS does not listen for user-data
//!   multicast in that domain, as Fast DDS by default: the other participants reach it by
//!   unicast. Either way the domain works and stays interoperable.
//! * The discovery multicast port taken, with multicast in use (DDS not confined to loopback
//!   addresses): the domain's participant could not hear the others' announcements, so it is
//!   refused with a message that names the port and the way out ([`Clash`]); when the port
//!   is one the agent serves, the worker warns at start and refuses that domain's
//!   participants ([`unservable_domains`]), and serves the others. Confined to loopback, DDS
//!   discovers by unicast and binds no multicast port that matters.
//! * The ports the front-ends serve ([`ReservedPorts`], [`crate::DdsConfig::reserved_ports`]) are also
//!   held by the worker while a participant is being made ([`PortGuard`]), so that DDS does
//!   not take one that a front-end let go for a moment (a front-end being restarted): the
//!   front-end could not bind it again while the participant lives.
//!
//! Limits: the arithmetic is that of the default port mapping (a `CYCLONEDDS_URI` that moves
//! the ports, or disables multicast on other interfaces, is not read); RTPS datagrams that
//! other participants on the host send to the well-known unicast ports of the first
//! participant indices (unicast discovery on loopback) reach a front-end served on such a
//! port, which drops them as malformed XRCE, as eProsima's agent does.

use std::collections::BTreeSet;
use std::fmt;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};

/// RTPS 2.5 §9.6.2.3: port base (PB).
pub const PORT_BASE: u32 = 7400;
/// Domain gain (DG).
pub const DOMAIN_GAIN: u32 = 250;
/// Participant gain (PG).
pub const PARTICIPANT_GAIN: u32 = 2;
/// Offset of the discovery multicast port (d0).
pub const D0: u32 = 0;
/// Offset of the discovery unicast ports (d1).
pub const D1: u32 = 10;
/// Offset of the user-data multicast port (d2).
pub const D2: u32 = 1;
/// Offset of the user-data unicast ports (d3).
pub const D3: u32 = 11;
/// Offsets within a domain's 250 ports that no participant of any domain uses by default:
/// where Cyclone's user-data multicast goes when its own port is taken.
pub const SPARE_OFFSETS: std::ops::RangeInclusive<u32> = 2..=9;

/// Ports XRCE clients bind by default on the agent's host (SITL, a developer's laptop), which
/// the spare user-data multicast port must not take: RTI's nano-client binds 7402
/// (`NANO_XRCE_TRANSPORT_UDP_CLIENT_PORT_DEFAULT`) beside its agent's 7401, and its examples
/// a second client on 7403. A Cyclone socket there (shared, with `SO_REUSEADDR`) makes the
/// client's own exclusive bind fail. The spare offsets are also tried from the top (9 down
/// to 2), away from the start of the range where such defaults sit.
pub const CLIENT_DEFAULT_PORTS: [u16; 2] = [7402, 7403];

/// What a well-known port is to its domain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortRole {
    /// SPDP: every participant of the domain listens here to discover the others.
    DiscoveryMulticast,
    /// User data sent by multicast.
    UserMulticast,
    /// Discovery unicast of the participant with this index.
    DiscoveryUnicast(u16),
    /// User-data unicast of the participant with this index.
    UserUnicast(u16),
}

/// A UDP port as the default RTPS port mapping assigns it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WellKnownPort {
    /// The UDP port.
    pub port: u16,
    /// The domain whose range (`7400 + 250·d` to `+ 249`) holds it.
    pub domain: u16,
    /// What it is there.
    pub role: PortRole,
}

impl WellKnownPort {
    /// What `port` is to DDS, if anything: every port from 7400 to 65535 lies in the range
    /// of exactly one domain (0-232), where offsets 0, 1 and 10 onwards are taken (2-9 are
    /// not).
    pub fn of(port: u16) -> Option<Self> {
        let above = u32::from(port).checked_sub(PORT_BASE)?;
        let domain = u16::try_from(above / DOMAIN_GAIN).ok()?;
        let offset = above % DOMAIN_GAIN;
        let role = match offset {
            D0 => PortRole::DiscoveryMulticast,
            D2 => PortRole::UserMulticast,
            o if o >= D3 && (o - D3) % PARTICIPANT_GAIN == 0 => {
                PortRole::UserUnicast(u16::try_from((o - D3) / PARTICIPANT_GAIN).ok()?)
            }
            o if o >= D1 && (o - D1) % PARTICIPANT_GAIN == 0 => {
                PortRole::DiscoveryUnicast(u16::try_from((o - D1) / PARTICIPANT_GAIN).ok()?)
            }
            _ => return None,
        };
        Some(WellKnownPort { port, domain, role })
    }
}

impl fmt::Display for WellKnownPort {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let d = self.domain;
        match self.role {
            PortRole::DiscoveryMulticast => write!(
                f,
                "DDS domain {d}'s discovery multicast port (RTPS: 7400 + 250 × domain)"
            ),
            PortRole::UserMulticast => write!(
                f,
                "DDS domain {d}'s user-data multicast port (RTPS: 7400 + 250 × domain + 1)"
            ),
            PortRole::DiscoveryUnicast(i) => write!(
                f,
                "the discovery unicast port of DDS participant index {i} in domain {d} (RTPS: \
                 7400 + 250 × domain + 10 + 2 × index)"
            ),
            PortRole::UserUnicast(i) => write!(
                f,
                "the user-data unicast port of DDS participant index {i} in domain {d} (RTPS: \
                 7400 + 250 × domain + 11 + 2 × index)"
            ),
        }
    }
}

/// A domain's discovery multicast port.
pub fn discovery_multicast_port(domain: u16) -> Option<u16> {
    port_at(domain, D0)
}

/// The port at `offset` in a domain's range (`None` above 65535).
pub fn port_at(domain: u16, offset: u32) -> Option<u16> {
    u16::try_from(PORT_BASE + DOMAIN_GAIN * u32::from(domain) + offset).ok()
}

/// The UDP ports the agent's front-ends serve, which DDS must leave to them.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReservedPorts(BTreeSet<u16>);

impl std::str::FromStr for ReservedPorts {
    type Err = String;
    fn from_str(list: &str) -> Result<Self, String> {
        Self::parse(list)
    }
}

/// The comma-separated list [`ReservedPorts::parse`] reads (empty for none).
impl fmt::Display for ReservedPorts {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, p) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            write!(f, "{p}")?;
        }
        Ok(())
    }
}

impl ReservedPorts {
    /// Ports from a comma-separated list (`7401,8888`; blanks and empty items ignored).
    pub fn parse(list: &str) -> Result<Self, String> {
        let mut ports = BTreeSet::new();
        for item in list.split(',').map(str::trim).filter(|i| !i.is_empty()) {
            match item.parse::<u16>() {
                Ok(p) if p != 0 => {
                    ports.insert(p);
                }
                _ => return Err(format!("{list:?}: {item:?} is not a UDP port (1-65535)")),
            }
        }
        Ok(ReservedPorts(ports))
    }

    /// These ports.
    pub fn new(ports: impl IntoIterator<Item = u16>) -> Self {
        ReservedPorts(ports.into_iter().filter(|p| *p != 0).collect())
    }

    /// Whether `port` is one of them.
    pub fn contains(&self, port: u16) -> bool {
        self.0.contains(&port)
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The ports, in increasing order.
    pub fn iter(&self) -> impl Iterator<Item = u16> + '_ {
        self.0.iter().copied()
    }

    /// Those that are well-known ports of `domain`.
    pub fn in_domain(&self, domain: u16) -> Vec<WellKnownPort> {
        self.iter()
            .filter_map(WellKnownPort::of)
            .filter(|w| w.domain == domain)
            .collect()
    }
}

/// Whether DDS, configured with these `--dds-interface` addresses, uses multicast: both
/// backends do unless every address is a loopback one (Cyclone is then configured without
/// multicast; RustDDS joins no group, loopback interfaces having no multicast).
pub fn multicast_possible(interfaces: &[IpAddr]) -> bool {
    interfaces.is_empty() || !interfaces.iter().all(IpAddr::is_loopback)
}

/// Why a domain cannot have its participant: its discovery multicast port is taken.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Clash {
    /// The port.
    pub port: WellKnownPort,
    /// Whether an XRCE front-end of this agent serves it (else another socket holds it).
    pub ours: bool,
}

impl fmt::Display for Clash {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (p, d) = (self.port.port, self.port.domain);
        if self.ours {
            write!(
                f,
                "UDP port {p}, which this agent serves XRCE on, is {}",
                self.port
            )?;
        } else {
            write!(
                f,
                "UDP port {p}, {}, is held by a socket that does not share it (another \
                 program, or an XRCE agent: `ss -ulpn sport = :{p}` names it)",
                self.port
            )?;
        }
        let spare = port_at(d, *SPARE_OFFSETS.end()).unwrap_or(7409);
        write!(
            f,
            ": a DDS participant in domain {d} must listen there to discover the others by \
             multicast, so domain {d} cannot be served. Serve XRCE on another port (-p; e.g. \
             {spare}, which no DDS domain uses), or confine DDS to loopback, where discovery \
             goes by unicast (--dds-interface 127.0.0.1), or keep clients out of domain {d} \
             (--domains)"
        )
    }
}

/// How a backend makes the participant of one domain.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DomainPorts {
    /// The domain.
    pub domain: u16,
    /// The domain's user-data multicast port, when it is taken and multicast is in use.
    pub user_multicast_taken: Option<u16>,
    /// The spare offset where Cyclone receives user-data multicast instead (with
    /// `user_multicast_taken`).
    pub data_multicast_offset: Option<u32>,
    /// The reserved ports in the domain's range, held while the participant is made.
    pub guarded: Vec<u16>,
}

impl DomainPorts {
    /// Holds the [`guarded`](Self::guarded) ports that nobody holds now, on the wildcard
    /// address of the family DDS binds (`v6`), until the guard is dropped.
    pub fn guard(&self, v6: bool) -> PortGuard {
        PortGuard::hold(&self.guarded, v6)
    }
}

/// Decides how the participant of `domain` is made, given the ports the front-ends serve and
/// whether a port can be shared with a multicast socket (`shareable`, [`shareable`] but for
/// tests): refused if its discovery multicast port is taken while multicast is in use; its
/// user-data multicast moved to a spare port (Cyclone) or left out (RustDDS) if that one is.
pub fn plan(
    domain: u16,
    reserved: &ReservedPorts,
    interfaces: &[IpAddr],
    shareable: impl Fn(u16) -> bool,
) -> Result<DomainPorts, Clash> {
    let guarded: Vec<u16> = reserved.in_domain(domain).iter().map(|w| w.port).collect();
    let mut out = DomainPorts {
        domain,
        user_multicast_taken: None,
        data_multicast_offset: None,
        guarded,
    };
    if !multicast_possible(interfaces) {
        return Ok(out);
    }
    let taken = |p: u16| reserved.contains(p) || !shareable(p);
    if let Some(spdp) = discovery_multicast_port(domain).filter(|p| taken(*p)) {
        return Err(Clash {
            port: WellKnownPort {
                port: spdp,
                domain,
                role: PortRole::DiscoveryMulticast,
            },
            ours: reserved.contains(spdp),
        });
    }
    if let Some(data) = port_at(domain, D2).filter(|p| taken(*p)) {
        out.user_multicast_taken = Some(data);
        out.data_multicast_offset = SPARE_OFFSETS.rev().find(|o| {
            port_at(domain, *o).is_some_and(|p| !taken(p) && !CLIENT_DEFAULT_PORTS.contains(&p))
        });
    }
    Ok(out)
}

/// The domains DDS cannot serve while the front-ends hold these reserved ports, with why:
/// those whose discovery multicast port is one of them, while DDS uses multicast with these
/// `interfaces`. The worker refuses their participants with STATUS_ERR_DENIED
/// (its `DomainRefusal::PortClash`) and serves every other domain, as
/// MicroXRCEAgent does on such a port (`-p 22150` costs domain 59 only); it warns at start
/// ([`log_reserved`]). Other clashes cost no domain: [`plan`] serves them.
pub fn unservable_domains(
    reserved: &ReservedPorts,
    interfaces: &[IpAddr],
) -> std::collections::BTreeMap<u16, String> {
    if !multicast_possible(interfaces) {
        return Default::default();
    }
    reserved
        .iter()
        .filter_map(WellKnownPort::of)
        .filter(|w| w.role == PortRole::DiscoveryMulticast)
        .map(|w| {
            let clash = Clash {
                port: w,
                ours: true,
            };
            (w.domain, clash.to_string())
        })
        .collect()
}

/// Whether a DDS multicast socket could bind `port` on the wildcard address of its family
/// (`v6`) now: a probe socket with `SO_REUSEADDR` and `SO_REUSEPORT`, as Cyclone DDS and
/// RustDDS bind theirs, which fails only if a socket that does not share the port holds it
/// (a front-end, or another program). Any other failure says nothing about the port (true):
/// DDS then tries and reports for itself.
pub fn shareable(port: u16, v6: bool) -> bool {
    use socket2::{Domain, Protocol, Socket, Type};
    let (domain, addr) = if v6 {
        (
            Domain::IPV6,
            SocketAddr::from((Ipv6Addr::UNSPECIFIED, port)),
        )
    } else {
        (
            Domain::IPV4,
            SocketAddr::from((Ipv4Addr::UNSPECIFIED, port)),
        )
    };
    let Ok(s) = Socket::new(domain, Type::DGRAM, Some(Protocol::UDP)) else {
        return true;
    };
    if s.set_reuse_address(true).is_err() || s.set_reuse_port(true).is_err() {
        return true;
    }
    match s.bind(&addr.into()) {
        Ok(()) => true,
        Err(e) => e.kind() != std::io::ErrorKind::AddrInUse,
    }
}

/// Ports the worker holds (exclusively, like a front-end) while a DDS participant is being
/// made, so that DDS does not take a front-end's port that happens to be free at that moment;
/// released when dropped. A port someone holds already is left alone (DDS cannot take it
/// either).
#[derive(Debug)]
pub struct PortGuard {
    held: Vec<std::net::UdpSocket>,
}

impl PortGuard {
    /// Binds each of `ports` on the wildcard address of the family DDS uses (`v6`: `[::]`,
    /// which also takes the IPv4 port, as DDS's own dual-stack sockets would).
    pub fn hold(ports: &[u16], v6: bool) -> Self {
        let held = ports
            .iter()
            .filter_map(|&p| {
                let addr: SocketAddr = if v6 {
                    (Ipv6Addr::UNSPECIFIED, p).into()
                } else {
                    (Ipv4Addr::UNSPECIFIED, p).into()
                };
                match std::net::UdpSocket::bind(addr) {
                    Ok(s) => {
                        tracing::debug!(
                            port = p,
                            "a front-end's UDP port is free: held while DDS binds its sockets"
                        );
                        Some(s)
                    }
                    Err(_) => None,
                }
            })
            .collect();
        PortGuard { held }
    }

    /// How many ports it holds.
    pub fn len(&self) -> usize {
        self.held.len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }
}

/// Logs, once at start, what each reserved port is to DDS and what the backends will do
/// about it (info: nothing is wrong unless a refusal is announced).
pub fn log_reserved(reserved: &ReservedPorts, interfaces: &[IpAddr]) {
    let multicast = multicast_possible(interfaces);
    for w in reserved.iter().filter_map(WellKnownPort::of) {
        match w.role {
            PortRole::DiscoveryMulticast if multicast => tracing::warn!(
                "{}; DDS participants in domain {} will be refused",
                Clash {
                    port: w,
                    ours: true
                },
                w.domain
            ),
            PortRole::UserMulticast if multicast => tracing::info!(
                "UDP port {} served by XRCE is {}: in that domain Cyclone DDS receives \
                 user-data multicast on a spare port it announces, and RustDDS, like Fast DDS \
                 by default, receives user data by unicast only",
                w.port,
                w
            ),
            PortRole::DiscoveryMulticast | PortRole::UserMulticast => tracing::debug!(
                "UDP port {} served by XRCE is {}, which DDS confined to loopback does not use",
                w.port,
                w
            ),
            PortRole::DiscoveryUnicast(_) | PortRole::UserUnicast(_) => tracing::info!(
                "UDP port {} served by XRCE is {}: DDS takes the next participant index there",
                w.port,
                w
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(a: &str) -> IpAddr {
        a.parse().expect("address")
    }

    #[test]
    fn every_port_from_7400_is_placed_in_its_domain() {
        let of = |p| WellKnownPort::of(p).map(|w| (w.domain, w.role));
        assert_eq!(of(7399), None);
        assert_eq!(of(7400), Some((0, PortRole::DiscoveryMulticast)));
        assert_eq!(of(7401), Some((0, PortRole::UserMulticast)));
        for spare in 7402..=7409 {
            assert_eq!(of(spare), None, "{spare}");
        }
        assert_eq!(of(7410), Some((0, PortRole::DiscoveryUnicast(0))));
        assert_eq!(of(7411), Some((0, PortRole::UserUnicast(0))));
        assert_eq!(of(7413), Some((0, PortRole::UserUnicast(1))));
        assert_eq!(of(7649), Some((0, PortRole::UserUnicast(119))));
        assert_eq!(of(7650), Some((1, PortRole::DiscoveryMulticast)));
        assert_eq!(of(8151), Some((3, PortRole::UserMulticast)));
        // eProsima's default agent port: an index no participant gets in practice.
        assert_eq!(of(8888), Some((5, PortRole::DiscoveryUnicast(114))));
        assert_eq!(of(65400), Some((232, PortRole::DiscoveryMulticast)));
        assert_eq!(of(65535), Some((232, PortRole::UserUnicast(62))));
        assert_eq!(discovery_multicast_port(3), Some(8150));
        assert_eq!(discovery_multicast_port(232), Some(65400));
        assert_eq!(port_at(232, 249), None);
        let w = WellKnownPort::of(7401).expect("well known");
        assert!(
            w.to_string().contains("domain 0's user-data multicast"),
            "{w}"
        );
    }

    #[test]
    fn reserved_port_lists() {
        let r = ReservedPorts::parse(" 7401, 8888,,7401 ").expect("valid");
        assert_eq!(r.iter().collect::<Vec<_>>(), vec![7401, 8888]);
        assert!(r.contains(7401) && !r.contains(7400));
        assert!(ReservedPorts::parse("").expect("valid").is_empty());
        assert_eq!(r.to_string().parse::<ReservedPorts>(), Ok(r.clone()));
        for bad in ["x", "0", "70000", "7401;8888", "-1"] {
            let e = ReservedPorts::parse(bad).expect_err(bad);
            assert!(e.contains("is not a UDP port"), "{e}");
        }
        let r = ReservedPorts::new([7401, 7411, 8151, 9000]);
        let d0: Vec<_> = r.in_domain(0).iter().map(|w| w.port).collect();
        assert_eq!(d0, vec![7401, 7411]);
        assert_eq!(r.in_domain(3).len(), 1);
        assert!(r.in_domain(7).is_empty());
    }

    #[test]
    fn multicast_unless_confined_to_loopback() {
        assert!(multicast_possible(&[]));
        assert!(multicast_possible(&[ip("192.0.2.7")]));
        assert!(multicast_possible(&[ip("127.0.0.1"), ip("192.0.2.7")]));
        assert!(!multicast_possible(&[ip("127.0.0.1")]));
        assert!(!multicast_possible(&[ip("::1")]));
    }

    #[test]
    fn user_multicast_port_taken_moves_to_a_spare_offset() {
        let free = |_| true;
        let r = ReservedPorts::new([7401]);
        let p = plan(0, &r, &[], free).expect("served");
        assert_eq!(p.user_multicast_taken, Some(7401));
        // From the top of the spare offsets: 7409, away from nano-client's 7402 and 7403.
        assert_eq!(p.data_multicast_offset, Some(9));
        assert_eq!(p.guarded, vec![7401]);
        // The spare port taken too: the next one down.
        let r = ReservedPorts::new([8151, 8159]);
        let p = plan(3, &r, &[ip("192.0.2.7")], free).expect("served");
        assert_eq!(
            (p.user_multicast_taken, p.data_multicast_offset),
            (Some(8151), Some(8))
        );
        // Held by someone else (not reserved): found by the probe.
        let p = plan(4, &ReservedPorts::default(), &[], |port| port != 8401).expect("served");
        assert_eq!(
            (p.user_multicast_taken, p.data_multicast_offset),
            (Some(8401), Some(9))
        );
        assert!(p.guarded.is_empty());
        // In domain 0 the clients' default ports are never the spare, even when it is the
        // last one left.
        let r = ReservedPorts::new([7401, 7404, 7405, 7406, 7407, 7408, 7409]);
        let p = plan(0, &r, &[], free).expect("served");
        assert_eq!(
            (p.user_multicast_taken, p.data_multicast_offset),
            (Some(7401), None)
        );
        // Other domains are untouched, and so is every domain confined to loopback.
        let r = ReservedPorts::new([7401]);
        let p = plan(1, &r, &[], free).expect("served");
        assert_eq!(
            (p.user_multicast_taken, p.data_multicast_offset),
            (None, None)
        );
        assert!(p.guarded.is_empty());
        let p = plan(0, &r, &[ip("127.0.0.1")], |_| false).expect("served");
        assert_eq!(
            (p.user_multicast_taken, p.data_multicast_offset),
            (None, None)
        );
        assert_eq!(p.guarded, vec![7401], "held while made, loopback or not");
        // No spare left: left out (Cyclone then fails to bind and says so).
        let every = ReservedPorts::new(7401..=7409);
        let p = plan(0, &every, &[], free).expect("served");
        assert_eq!(
            (p.user_multicast_taken, p.data_multicast_offset),
            (Some(7401), None)
        );
    }

    #[test]
    fn discovery_multicast_port_taken_refuses_the_domain_with_the_way_out() {
        let r = ReservedPorts::new([7400]);
        let e = plan(0, &r, &[], |_| true).expect_err("refused");
        assert!(e.ours);
        let m = e.to_string();
        for part in [
            "UDP port 7400",
            "serves XRCE",
            "domain 0's discovery multicast port",
            "-p",
            "7409",
            "--dds-interface 127.0.0.1",
            "--domains",
        ] {
            assert!(m.contains(part), "{part:?} in {m}");
        }
        let e = plan(2, &ReservedPorts::default(), &[], |p| p != 7900).expect_err("refused");
        assert!(
            !e.ours && e.to_string().contains("ss -ulpn sport = :7900"),
            "{e}"
        );
        // Confined to loopback, discovery goes by unicast: served.
        assert!(plan(0, &r, &[ip("127.0.0.1")], |_| false).is_ok());
        // The worker's start: that domain only is unservable, and none confined to loopback.
        let r = ReservedPorts::new([7400, 22150, 7401, 7411]);
        let unservable = unservable_domains(&r, &[]);
        assert_eq!(unservable.keys().copied().collect::<Vec<_>>(), vec![0, 59]);
        assert!(unservable[&59].contains("UDP port 22150"), "{unservable:?}");
        assert!(unservable_domains(&r, &[ip("127.0.0.1")]).is_empty());
    }

    #[test]
    fn a_probe_and_a_guard_see_exclusive_holders() {
        // A port the kernel picks, free again once its socket is closed.
        let port = std::net::UdpSocket::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .expect("ephemeral port")
            .port();
        assert!(shareable(port, false));
        {
            let guard = PortGuard::hold(&[port], false);
            assert_eq!(guard.len(), 1);
            assert!(
                std::net::UdpSocket::bind(("0.0.0.0", port)).is_err(),
                "held by the guard"
            );
            assert!(!shareable(port, false), "not shareable while held");
        }
        let holder = std::net::UdpSocket::bind(("127.0.0.1", port)).expect("free again");
        assert!(
            !shareable(port, false),
            "an exclusive holder on one address"
        );
        assert!(
            PortGuard::hold(&[port], false).is_empty(),
            "left to its holder"
        );
        drop(holder);
        // Shared multicast sockets do not count as taken.
        let shared = {
            let s = socket2::Socket::new(
                socket2::Domain::IPV4,
                socket2::Type::DGRAM,
                Some(socket2::Protocol::UDP),
            )
            .expect("socket");
            s.set_reuse_address(true).expect("reuse");
            s.set_reuse_port(true).expect("reuse");
            s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, port)).into())
                .expect("bind");
            s
        };
        assert!(shareable(port, false));
        drop(shared);
    }
}
