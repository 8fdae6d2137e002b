//! Keeps DDS to the addresses it was told (`--dds-interface`), whatever its library binds.
//!
//! RustDDS 0.15.1 and Cyclone DDS 11.0.1 announce and send from the configured addresses
//! only, but bind their receiving sockets to the wildcard address (RustDDS: every listener
//! and its sender, in `src/dds/participant.rs` and `src/network/udp_sender.rs`; Cyclone: every
//! receiving socket, `ddsi_udp_create_conn` in `src/core/ddsi/src/ddsi_udp.c`), and neither
//! has a setting for it. So RTPS sent to any other address of the host, through any
//! interface, would reach them: a gateway that restricts DDS to its robot-side interface
//! would still take discovery and data from every other network.
//!
//! After a backend made a participant, [`confine_udp_sockets`] finds every UDP socket of the
//! process bound to a wildcard address and attaches a socket filter to it (classic BPF,
//! `SO_ATTACH_FILTER`) that lets a datagram in only if its destination is one of the
//! configured addresses, or a multicast group and it arrived through an interface that holds
//! one of them (SPDP's multicast discovery). The kernel drops what the filter refuses before
//! the library reads it, and counts it in the socket's drops (`/proc/net/udp`). Sockets bound
//! to one address (Cyclone's senders) and other sockets (iceoryx2's unix sockets) are left
//! alone, and so are sockets that carry a filter already (confined after an earlier
//! participant, or by someone else). An unspecified address among the configured ones means
//! every interface: nothing is confined then.
//!
//! It fails closed. At start, [`check`] decides whether the configured addresses can be
//! confined to at all: each must be held by an interface of this host (an address nothing
//! holds leaves DDS nothing to listen on, and no interface whose multicast to take), there
//! must be few enough for one filter program ([`MAX_NAMED`]), the kernel must take a socket
//! filter (a probe socket, never bound), and the process must be able to list its
//! descriptors; if not, the worker refuses to start, saying why ([`ConfineError`]). Later,
//! a participant whose sockets cannot all be confined is deleted and its creation fails
//! (the client gets `STATUS_ERR_DDS_ERROR`): DDS never runs wider than it was told.
//!
//! Limits: datagrams a socket queued between the library's bind and the filter (a few
//! milliseconds at participant creation) are not filtered; multicast is accepted through the
//! interfaces that held a configured address when the filter was attached (an interface
//! re-created later, a USB adapter plugged again, gets a new index and its multicast is
//! dropped until the worker restarts).
//!
//! The filter program is built by [`Program::allowing`] (pure, unit-tested with an
//! interpreter of the instructions it uses); the `unsafe` code, borrowing a descriptor the
//! DDS library owns, is in `sys`.

use std::net::{IpAddr, SocketAddr};
use std::os::fd::{BorrowedFd, RawFd};

use socket2::{SockFilter, SockRef, Type};

/// Why DDS cannot be confined to the configured addresses (the worker refuses to start, or a
/// participant is refused, rather than let DDS listen wider than it was told).
#[derive(Debug, thiserror::Error)]
pub enum ConfineError {
    /// No interface of this host holds the address.
    #[error(
        "--dds-interface {0}: no interface of this host has this address (is the interface \
         up and configured?)"
    )]
    NotLocal(IpAddr),
    /// More addresses than one filter program can name.
    #[error("at most {MAX_NAMED} DDS interface addresses can be confined to ({0} given)")]
    TooManyAddresses(usize),
    /// The addresses are on more interfaces than one filter program can name.
    #[error(
        "the DDS interface addresses are on {0} interfaces, more than the {MAX_NAMED} one \
         socket filter can name"
    )]
    TooManyInterfaces(usize),
    /// The filter program could not be assembled (a fault of this module).
    #[error("the socket filter program could not be assembled: {0}")]
    Program(&'static str),
    /// The interfaces of this host could not be listed.
    #[error("the interfaces of this host could not be listed: {0}")]
    Interfaces(std::io::Error),
    /// The kernel refused a socket filter on a probe socket.
    #[error("a socket filter (SO_ATTACH_FILTER) cannot be attached here: {0}")]
    FiltersUnavailable(std::io::Error),
    /// `/proc/self/fd` could not be read.
    #[error("this process's descriptors cannot be listed (/proc/self/fd): {0}")]
    Descriptors(std::io::Error),
    /// Some sockets could not be confined.
    #[error("{confined} DDS sockets confined, failed for {failed}")]
    Sockets {
        /// Sockets confined.
        confined: usize,
        /// Which failed, and why.
        failed: String,
    },
}

/// What the configured addresses ask for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Plan {
    /// No address, or an unspecified one: DDS on every interface, nothing to confine.
    Everywhere,
    /// Wildcard sockets get the filter of these addresses (canonical: an IPv4-mapped IPv6
    /// address is its IPv4 address) and of the interfaces (indices) that hold them.
    Confined {
        /// The configured addresses.
        addresses: Vec<IpAddr>,
        /// The indices of the interfaces holding them.
        interfaces: Vec<u32>,
        /// The filter.
        program: Program,
    },
}

/// The decision, from the configured addresses and this host's (address, interface index)
/// pairs: every address must be held by an interface, and the filter must fit.
pub fn plan(addresses: &[IpAddr], host: &[(IpAddr, u32)]) -> Result<Plan, ConfineError> {
    // An IPv4-mapped IPv6 address is the IPv4 address (interfaces, the unspecified check).
    let addresses: Vec<IpAddr> = addresses.iter().map(IpAddr::to_canonical).collect();
    if addresses.is_empty() || addresses.iter().any(IpAddr::is_unspecified) {
        return Ok(Plan::Everywhere);
    }
    let mut interfaces = Vec::new();
    for a in &addresses {
        let mut held = false;
        for (ip, index) in host {
            if ip.to_canonical() == *a {
                held = true;
                if !interfaces.contains(index) {
                    interfaces.push(*index);
                }
            }
        }
        if !held {
            return Err(ConfineError::NotLocal(*a));
        }
    }
    let program = Program::allowing(&addresses, &interfaces)?;
    Ok(Plan::Confined {
        addresses,
        interfaces,
        program,
    })
}

/// The addresses of this host's interfaces, with the interface indices.
pub fn host_interfaces() -> Result<Vec<(IpAddr, u32)>, ConfineError> {
    let ifaddrs = nix::ifaddrs::getifaddrs()
        .map_err(|e| ConfineError::Interfaces(std::io::Error::from(e)))?;
    let mut out = Vec::new();
    for ifa in ifaddrs {
        let ip = ifa.address.as_ref().and_then(|a| {
            a.as_sockaddr_in()
                .map(|s| IpAddr::V4(s.ip()))
                .or_else(|| a.as_sockaddr_in6().map(|s| IpAddr::V6(s.ip())))
        });
        let Some(ip) = ip else { continue };
        if let Ok(index) = nix::net::if_::if_nametoindex(ifa.interface_name.as_str()) {
            out.push((ip, index));
        }
    }
    Ok(out)
}

/// Whether DDS can be confined to `addresses` on this host, checked before the worker
/// serves (it refuses to start otherwise): the plan ([`plan`]), a probe socket that takes
/// the filter, and a readable `/proc/self/fd`.
pub fn check(addresses: &[IpAddr]) -> Result<Plan, ConfineError> {
    let plan = plan(addresses, &host_interfaces()?)?;
    if let Plan::Confined { program, .. } = &plan {
        let probe = socket2::Socket::new(socket2::Domain::IPV4, Type::DGRAM, None)
            .or_else(|_| socket2::Socket::new(socket2::Domain::IPV6, Type::DGRAM, None))
            .map_err(ConfineError::FiltersUnavailable)?;
        probe
            .attach_filter(&program.to_socket2())
            .map_err(ConfineError::FiltersUnavailable)?;
        std::fs::read_dir("/proc/self/fd").map_err(ConfineError::Descriptors)?;
    }
    Ok(plan)
}

/// Classic BPF: the instruction classes, sizes, modes and operations the program uses
/// (`linux/bpf_common.h`).
mod op {
    pub(super) const LD: u16 = 0x00;
    pub(super) const ALU: u16 = 0x04;
    pub(super) const JMP: u16 = 0x05;
    pub(super) const RET: u16 = 0x06;
    pub(super) const W: u16 = 0x00;
    pub(super) const B: u16 = 0x10;
    pub(super) const ABS: u16 = 0x20;
    pub(super) const AND: u16 = 0x50;
    pub(super) const RSH: u16 = 0x70;
    pub(super) const JA: u16 = 0x00;
    pub(super) const JEQ: u16 = 0x10;
    pub(super) const K: u16 = 0x00;
}

/// Where a load with a negative offset reads (`linux/filter.h`): the network header, and the
/// ancillary data (the receiving interface's index).
const SKF_NET_OFF: i32 = -0x0010_0000;
const SKF_AD_OFF: i32 = -0x1000;
const SKF_AD_IFINDEX: i32 = 8;

/// What a filter returns to keep a datagram whole, or to drop it.
const ACCEPT: u32 = u32::MAX;
const DROP: u32 = 0;

/// Most addresses and interfaces one program names (jump offsets are one octet).
pub const MAX_NAMED: usize = 16;

/// One classic BPF instruction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Insn {
    /// Class, size, mode and operation.
    pub code: u16,
    /// Instructions skipped when a comparison holds.
    pub jt: u8,
    /// Instructions skipped when it does not.
    pub jf: u8,
    /// The constant.
    pub k: u32,
}

/// A socket filter program.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Program(pub Vec<Insn>);

/// A jump target while the program is assembled.
#[derive(Debug, Clone, Copy)]
enum To {
    Next,
    Label(usize),
}

/// Labels are resolved when the program is finished (every jump goes forward).
#[derive(Default)]
struct Assembler {
    insns: Vec<(u16, To, To, u32)>,
    labels: Vec<Option<usize>>,
}

impl Assembler {
    fn label(&mut self) -> usize {
        self.labels.push(None);
        self.labels.len() - 1
    }
    fn here(&mut self, label: usize) {
        self.labels[label] = Some(self.insns.len());
    }
    fn put(&mut self, code: u16, k: u32) {
        self.insns.push((code, To::Next, To::Next, k));
    }
    fn load_net(&mut self, size: u16, offset: i32) {
        self.put(op::LD | size | op::ABS, (SKF_NET_OFF + offset) as u32);
    }
    fn jeq(&mut self, k: u32, jt: To, jf: To) {
        self.insns.push((op::JMP | op::JEQ | op::K, jt, jf, k));
    }
    fn jump(&mut self, to: usize) {
        self.insns
            .push((op::JMP | op::JA, To::Next, To::Next, to as u32 | 1 << 31));
    }
    fn finish(self) -> Result<Program, ConfineError> {
        let at = |i: usize, to: To| -> Result<u32, ConfineError> {
            let target = match to {
                To::Next => return Ok(0),
                To::Label(l) => self
                    .labels
                    .get(l)
                    .copied()
                    .flatten()
                    .ok_or(ConfineError::Program("an unplaced label"))?,
            };
            target
                .checked_sub(i + 1)
                .map(|d| d as u32)
                .ok_or(ConfineError::Program("a backward jump"))
        };
        let mut out = Vec::with_capacity(self.insns.len());
        for (i, &(code, jt, jf, k)) in self.insns.iter().enumerate() {
            let short =
                |d: u32| u8::try_from(d).map_err(|_| ConfineError::Program("a jump too far"));
            let (jt, jf, k) = if code == op::JMP | op::JA && k & 1 << 31 != 0 {
                // An unconditional jump to a label (marked in `k` while assembling).
                (0, 0, at(i, To::Label((k & !(1 << 31)) as usize))?)
            } else {
                (short(at(i, jt)?)?, short(at(i, jf)?)?, k)
            };
            out.push(Insn { code, jt, jf, k });
        }
        Ok(Program(out))
    }
}

impl Program {
    /// The filter that accepts a datagram sent to one of `addresses`, or to a multicast
    /// group through one of the interfaces `interfaces` (their indices), and drops the rest.
    /// The same program serves IPv4 sockets and IPv6 ones (which may take IPv4 datagrams
    /// too): it looks at the IP version first.
    pub fn allowing(addresses: &[IpAddr], interfaces: &[u32]) -> Result<Program, ConfineError> {
        if addresses.len() > MAX_NAMED {
            return Err(ConfineError::TooManyAddresses(addresses.len()));
        }
        if interfaces.len() > MAX_NAMED {
            return Err(ConfineError::TooManyInterfaces(interfaces.len()));
        }
        let mut a = Assembler::default();
        let (v6, multicast, drop, accept) = (a.label(), a.label(), a.label(), a.label());
        // IP version: the high nibble of the first octet.
        a.load_net(op::B, 0);
        a.put(op::ALU | op::RSH | op::K, 4);
        a.jeq(6, To::Label(v6), To::Next);
        // IPv4: the destination address is at octet 16. An IPv4-mapped IPv6 address is the
        // IPv4 address a dual-stack socket receives.
        a.load_net(op::W, 16);
        for ip in addresses {
            let v4 = match ip {
                IpAddr::V4(v4) => Some(*v4),
                IpAddr::V6(v6) => v6.to_ipv4_mapped(),
            };
            if let Some(v4) = v4 {
                a.jeq(u32::from(v4), To::Label(accept), To::Next);
            }
        }
        a.put(op::ALU | op::AND | op::K, 0xf000_0000);
        a.jeq(0xe000_0000, To::Label(multicast), To::Label(drop));
        // IPv6: the destination address is at octets 24..40, compared a word at a time.
        a.here(v6);
        for ip in addresses {
            if let IpAddr::V6(v6) = ip {
                let next = a.label();
                let octets = v6.octets();
                for (i, word) in octets.chunks_exact(4).enumerate() {
                    let word = u32::from_be_bytes([word[0], word[1], word[2], word[3]]);
                    a.load_net(op::W, 24 + 4 * i as i32);
                    let on_match = if i == 3 { To::Label(accept) } else { To::Next };
                    a.jeq(word, on_match, To::Label(next));
                }
                a.here(next);
            }
        }
        a.load_net(op::B, 24);
        a.jeq(0xff, To::Label(multicast), To::Label(drop));
        // A multicast group: only through the interfaces of the configured addresses.
        a.here(multicast);
        a.put(
            op::LD | op::W | op::ABS,
            (SKF_AD_OFF + SKF_AD_IFINDEX) as u32,
        );
        for index in interfaces {
            a.jeq(*index, To::Label(accept), To::Next);
        }
        a.jump(drop);
        a.here(drop);
        a.put(op::RET | op::K, DROP);
        a.here(accept);
        a.put(op::RET | op::K, ACCEPT);
        a.finish()
    }

    fn to_socket2(&self) -> Vec<SockFilter> {
        self.0
            .iter()
            .map(|i| SockFilter::new(i.code, i.jt, i.jf, i.k))
            .collect()
    }
}

/// Attaches the filter of `addresses` to every UDP socket of this process bound to a
/// wildcard address; returns how many it confined. Does nothing without addresses (DDS on
/// every interface). Call it from the thread that creates and deletes the DDS participants,
/// right after creating one (see `sys::with_socket` for why); on an error, delete that
/// participant (its sockets may listen unconfined).
pub fn confine_udp_sockets(addresses: &[IpAddr]) -> Result<usize, ConfineError> {
    let program = match plan(addresses, &host_interfaces()?)? {
        Plan::Everywhere => return Ok(0),
        Plan::Confined { program, .. } => program.to_socket2(),
    };
    let dir = std::fs::read_dir("/proc/self/fd").map_err(ConfineError::Descriptors)?;
    let mut confined = 0;
    let mut failures = Vec::new();
    for entry in dir.flatten() {
        let Some(fd) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<RawFd>().ok())
        else {
            continue;
        };
        let is_socket = std::fs::read_link(entry.path())
            .is_ok_and(|t| t.to_string_lossy().starts_with("socket:"));
        if !is_socket {
            continue;
        }
        if sys::has_filter(fd) {
            continue;
        }
        match confine_socket(fd, &program) {
            Ok(true) => confined += 1,
            Ok(false) => {}
            // Closed, or its number reused for a file, meanwhile (another thread's
            // descriptor): nothing to confine.
            Err(e) if gone(&e) => {}
            Err(e) => failures.push(format!("socket {fd}: {e}")),
        }
    }
    if failures.is_empty() {
        Ok(confined)
    } else {
        Err(ConfineError::Sockets {
            confined,
            failed: failures.join(", "),
        })
    }
}

/// An error that means the descriptor is no longer the socket it was.
fn gone(e: &std::io::Error) -> bool {
    [nix::errno::Errno::EBADF, nix::errno::Errno::ENOTSOCK]
        .iter()
        .any(|n| e.raw_os_error() == Some(*n as i32))
}

/// Attaches `program` to the socket behind `fd` if it is a datagram socket bound to a
/// wildcard address; says whether it did.
fn confine_socket(fd: RawFd, program: &[SockFilter]) -> std::io::Result<bool> {
    sys::with_socket(fd, |s| {
        if s.r#type()? != Type::DGRAM {
            return Ok(false);
        }
        let wildcard = s
            .local_addr()?
            .as_socket()
            .is_some_and(|a: SocketAddr| a.ip().is_unspecified());
        if wildcard {
            s.attach_filter(program)?;
        }
        Ok(wildcard)
    })
}

/// The module's `unsafe` code: system calls on descriptors it does not own.
///
/// Invariant (why using them is sound): a descriptor was listed in `/proc/self/fd` just
/// before and is used only for the duration of one call here, on the thread that creates and
/// deletes the DDS participants; the DDS libraries close their sockets only when a
/// participant is deleted, so none of theirs closes meanwhile. A descriptor of another kind
/// that another thread closes meanwhile (in the worker: iceoryx2's; in a unit-test binary:
/// other tests' sockets) makes the calls fail with EBADF or ENOTSOCK, or, if its number was
/// reused at once, be read by `getsockopt`/`getsockname`, which change nothing; only a
/// datagram socket bound to a wildcard address and without a filter ever gets one. Nothing
/// here touches memory but the locals passed to the calls.
#[allow(unsafe_code)]
mod sys {
    use super::*;

    /// Runs `f` on the socket behind descriptor `fd`.
    pub(super) fn with_socket<R>(fd: RawFd, f: impl FnOnce(SockRef<'_>) -> R) -> R {
        // SAFETY: see the module's invariant; the borrow does not outlive this call.
        let borrowed = unsafe { BorrowedFd::borrow_raw(fd) };
        f(SockRef::from(&borrowed))
    }

    /// Whether the socket behind `fd` has a socket filter (SO_GET_FILTER with no buffer
    /// answers the number of instructions; an eBPF filter, which it cannot show, answers
    /// EACCES); false on any other error.
    pub(super) fn has_filter(fd: RawFd) -> bool {
        let mut len: libc::socklen_t = 0;
        // SAFETY: a null buffer with a zero length asks only for the count, written to
        // `len`, a live local; see the module's invariant for `fd`.
        let rc = unsafe {
            libc::getsockopt(
                fd,
                libc::SOL_SOCKET,
                libc::SO_GET_FILTER,
                std::ptr::null_mut(),
                &mut len,
            )
        };
        (rc == 0 && len > 0)
            || (rc != 0 && std::io::Error::last_os_error().raw_os_error() == Some(libc::EACCES))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::{Ipv4Addr, Ipv6Addr};

    /// Runs a program the way the kernel does, over a datagram's network header and the index
    /// of the interface it came through (only the instructions [`Program::allowing`] emits).
    fn run(p: &Program, header: &[u8], ifindex: u32) -> u32 {
        let (mut a, mut pc) = (0u32, 0usize);
        let load = |k: u32, size: usize| -> Option<u32> {
            let k = k as i32;
            if k == SKF_AD_OFF + SKF_AD_IFINDEX {
                return Some(ifindex);
            }
            let at = usize::try_from(k - SKF_NET_OFF).ok()?;
            let b = header.get(at..at + size)?;
            Some(b.iter().fold(0u32, |acc, x| acc << 8 | u32::from(*x)))
        };
        loop {
            let i = p.0[pc];
            pc += 1;
            match i.code {
                c if c == op::LD | op::W | op::ABS => match load(i.k, 4) {
                    Some(v) => a = v,
                    None => return 0,
                },
                c if c == op::LD | op::B | op::ABS => match load(i.k, 1) {
                    Some(v) => a = v,
                    None => return 0,
                },
                c if c == op::ALU | op::RSH | op::K => a >>= i.k,
                c if c == op::ALU | op::AND | op::K => a &= i.k,
                c if c == op::JMP | op::JEQ | op::K => {
                    pc += usize::from(if a == i.k { i.jt } else { i.jf })
                }
                c if c == op::JMP | op::JA => pc += i.k as usize,
                c if c == op::RET | op::K => return i.k,
                other => panic!("an instruction the interpreter does not know: {other:#x}"),
            }
        }
    }

    fn v4_header(dst: Ipv4Addr) -> Vec<u8> {
        let mut h = vec![0u8; 20];
        h[0] = 0x45;
        h[16..20].copy_from_slice(&dst.octets());
        h
    }

    fn v6_header(dst: Ipv6Addr) -> Vec<u8> {
        let mut h = vec![0u8; 40];
        h[0] = 0x60;
        h[24..40].copy_from_slice(&dst.octets());
        h
    }

    const LO: u32 = 1;
    const ETH: u32 = 2;

    #[test]
    fn only_the_configured_ipv4_address_and_multicast_through_its_interface_pass() {
        let p = Program::allowing(&["192.168.1.10".parse().expect("an address")], &[ETH])
            .expect("a program");
        let to = |a: &str, i| run(&p, &v4_header(a.parse().expect("an address")), i);
        assert_eq!(to("192.168.1.10", ETH), ACCEPT);
        assert_eq!(to("192.168.1.10", LO), ACCEPT, "sent from this host");
        assert_eq!(to("10.0.0.5", ETH), DROP, "another address of the host");
        assert_eq!(to("127.0.0.1", LO), DROP);
        assert_eq!(to("192.168.1.11", ETH), DROP);
        assert_eq!(to("239.255.0.1", ETH), ACCEPT, "SPDP through the interface");
        assert_eq!(to("239.255.0.1", 3), DROP, "SPDP through another interface");
        assert_eq!(
            run(&p, &v6_header("::1".parse().expect("an address")), LO),
            DROP,
            "no IPv6 address was configured"
        );
    }

    #[test]
    fn ipv6_addresses_are_compared_whole() {
        let a: Ipv6Addr = "fd00::1:2:3:4".parse().expect("an address");
        let p = Program::allowing(
            &[IpAddr::V6(a), "::1".parse().expect("an address")],
            &[ETH, LO],
        )
        .expect("a program");
        let to = |a: Ipv6Addr, i| run(&p, &v6_header(a), i);
        assert_eq!(to(a, ETH), ACCEPT);
        assert_eq!(to(Ipv6Addr::LOCALHOST, LO), ACCEPT);
        for differs_in in [0, 5, 11, 15] {
            let mut o = a.octets();
            o[differs_in] ^= 1;
            assert_eq!(
                to(Ipv6Addr::from(o), ETH),
                DROP,
                "octet {differs_in} differs"
            );
        }
        assert_eq!(to("ff02::1".parse().expect("an address"), LO), ACCEPT);
        assert_eq!(to("ff02::1".parse().expect("an address"), 7), DROP);
        assert_eq!(run(&p, &v4_header(Ipv4Addr::LOCALHOST), LO), DROP);
    }

    #[test]
    fn a_dual_stack_socket_checks_ipv4_datagrams_against_the_ipv4_addresses() {
        let p = Program::allowing(
            &[
                IpAddr::V4(Ipv4Addr::LOCALHOST),
                IpAddr::V6(Ipv6Addr::LOCALHOST),
            ],
            &[LO],
        )
        .expect("a program");
        assert_eq!(run(&p, &v4_header(Ipv4Addr::LOCALHOST), LO), ACCEPT);
        assert_eq!(run(&p, &v6_header(Ipv6Addr::LOCALHOST), LO), ACCEPT);
        assert_eq!(run(&p, &v4_header(Ipv4Addr::new(127, 0, 0, 2)), LO), DROP);
        assert_eq!(run(&p, &v4_header(Ipv4Addr::new(224, 0, 0, 1)), LO), ACCEPT);
    }

    #[test]
    fn an_ipv4_mapped_address_is_checked_against_ipv4_datagrams() {
        let p = Program::allowing(&["::ffff:10.0.0.1".parse().expect("an address")], &[])
            .expect("a program");
        assert_eq!(run(&p, &v4_header(Ipv4Addr::new(10, 0, 0, 1)), ETH), ACCEPT);
        assert_eq!(run(&p, &v4_header(Ipv4Addr::new(10, 0, 0, 2)), ETH), DROP);
    }

    #[test]
    fn an_unspecified_address_means_every_interface() {
        assert!(matches!(
            confine_udp_sockets(&[IpAddr::V4(Ipv4Addr::UNSPECIFIED)]),
            Ok(0)
        ));
        assert!(matches!(confine_udp_sockets(&[]), Ok(0)));
        assert!(matches!(
            confine_udp_sockets(&["::ffff:0.0.0.0".parse().expect("an address")]),
            Ok(0)
        ));
        assert!(matches!(plan(&[], &[]), Ok(Plan::Everywhere)));
    }

    fn ip(a: &str) -> IpAddr {
        a.parse().expect("an address")
    }

    /// The decision: an address no interface of the host holds cannot be confined to, and
    /// is refused (the worker does not start) rather than run DDS unconfined.
    #[test]
    fn addresses_the_host_does_not_hold_are_refused_and_held_ones_planned() {
        let host = [
            (ip("127.0.0.1"), LO),
            (ip("::1"), LO),
            (ip("192.168.1.10"), ETH),
            (ip("fe80::1"), ETH),
        ];
        match plan(&[ip("192.168.1.10"), ip("::1")], &host) {
            Ok(Plan::Confined {
                addresses,
                interfaces,
                ..
            }) => {
                assert_eq!(addresses, vec![ip("192.168.1.10"), ip("::1")]);
                assert_eq!(interfaces, vec![ETH, LO]);
            }
            other => panic!("expected a confinement, got {other:?}"),
        }
        match plan(&[ip("::ffff:127.0.0.1")], &host) {
            Ok(Plan::Confined { addresses, .. }) => assert_eq!(addresses, vec![ip("127.0.0.1")]),
            other => panic!("expected a confinement, got {other:?}"),
        }
        let refused = plan(&[ip("192.168.1.10"), ip("198.51.100.77")], &host);
        assert!(
            matches!(refused, Err(ConfineError::NotLocal(a)) if a == ip("198.51.100.77")),
            "{refused:?}"
        );
        let message = ConfineError::NotLocal(ip("198.51.100.77")).to_string();
        assert!(
            message.contains("--dds-interface 198.51.100.77"),
            "{message}"
        );
        assert!(matches!(
            plan(&[ip("10.0.0.1")], &[]),
            Err(ConfineError::NotLocal(_))
        ));
        let many: Vec<(IpAddr, u32)> = (0..=MAX_NAMED as u8)
            .map(|i| (IpAddr::V4(Ipv4Addr::new(10, 0, 0, i)), u32::from(i) + 10))
            .collect();
        let all: Vec<IpAddr> = many.iter().map(|(a, _)| *a).collect();
        assert!(matches!(
            plan(&all, &many),
            Err(ConfineError::TooManyAddresses(17))
        ));
        assert!(matches!(
            plan(&all[..MAX_NAMED], &many),
            Ok(Plan::Confined { .. })
        ));
        // One address held by two interfaces: one interface too many.
        let mut twice = many.clone();
        twice.push((all[0], 99));
        assert!(matches!(
            plan(&all[..MAX_NAMED], &twice),
            Err(ConfineError::TooManyInterfaces(n)) if n == MAX_NAMED + 1
        ));
    }

    /// On this host: loopback can be confined to (the probe takes the filter), an address
    /// nothing holds cannot.
    #[test]
    fn the_start_check_passes_for_loopback_and_fails_for_an_address_not_here() {
        assert!(matches!(
            check(&[IpAddr::V4(Ipv4Addr::LOCALHOST)]),
            Ok(Plan::Confined { .. })
        ));
        assert!(matches!(check(&[]), Ok(Plan::Everywhere)));
        // TEST-NET-2: documentation only, on no host's interface.
        assert!(matches!(
            check(&[ip("198.51.100.77")]),
            Err(ConfineError::NotLocal(_))
        ));
        assert!(matches!(
            confine_udp_sockets(&[ip("198.51.100.77")]),
            Err(ConfineError::NotLocal(_))
        ));
    }

    #[test]
    fn too_many_addresses_are_refused_not_truncated() {
        let many: Vec<IpAddr> = (0..=MAX_NAMED as u8)
            .map(|i| IpAddr::V4(Ipv4Addr::new(10, 0, 0, i)))
            .collect();
        assert!(Program::allowing(&many, &[]).is_err());
        let p = Program::allowing(&many[..MAX_NAMED], &[1; MAX_NAMED]).expect("socket");
        assert_eq!(
            run(&p, &v4_header(Ipv4Addr::new(10, 0, 0, 15)), 9),
            ACCEPT,
            "the last of the most addresses is reachable (jump offsets fit)"
        );
    }

    #[test]
    fn a_wildcard_socket_is_confined_and_one_bound_to_an_address_left_alone() {
        use std::os::fd::AsRawFd;
        // The wildcard socket under test drops everything from before its bind (a filter
        // that refuses all), so it never takes a datagram from beyond loopback; confining
        // replaces that filter with the one of the configured address, ::1.
        let wild = socket2::Socket::new(socket2::Domain::IPV4, Type::DGRAM, None).expect("socket");
        wild.attach_filter(&[SockFilter::new(op::RET | op::K, 0, 0, DROP)])
            .expect("socket");
        wild.bind(&SocketAddr::from(([0, 0, 0, 0], 0)).into())
            .expect("socket");
        let bound = std::net::UdpSocket::bind("127.0.0.1:0").expect("socket");
        let program = Program::allowing(&[IpAddr::V6(Ipv6Addr::LOCALHOST)], &[])
            .expect("a program")
            .to_socket2();
        assert!(sys::has_filter(wild.as_raw_fd()), "the refuse-all filter");
        assert!(confine_socket(wild.as_raw_fd(), &program).expect("socket"));
        assert!(!confine_socket(bound.as_raw_fd(), &program).expect("socket"));
        assert!(!sys::has_filter(bound.as_raw_fd()), "left alone");
        let tcp = std::net::TcpListener::bind("127.0.0.1:0").expect("socket");
        assert!(
            !confine_socket(tcp.as_raw_fd(), &program).expect("socket"),
            "not UDP"
        );

        // The bound socket takes a datagram to 127.0.0.1; the confined one refuses it (not
        // a configured address), though it would take it without a filter.
        let port = wild
            .local_addr()
            .expect("socket")
            .as_socket()
            .expect("socket")
            .port();
        let sender = std::net::UdpSocket::bind("127.0.0.1:0").expect("socket");
        sender.send_to(b"x", ("127.0.0.1", port)).expect("socket");
        sender
            .send_to(b"y", bound.local_addr().expect("socket"))
            .expect("socket");
        bound
            .set_read_timeout(Some(std::time::Duration::from_secs(2)))
            .expect("socket");
        let mut buf = [0u8; 4];
        assert_eq!(bound.recv(&mut buf).expect("socket"), 1);
        std::thread::sleep(std::time::Duration::from_millis(50));
        let wild = std::net::UdpSocket::from(wild);
        wild.set_nonblocking(true).expect("socket");
        assert!(
            wild.recv(&mut buf).is_err(),
            "the filtered datagram arrived"
        );

        // Confined to 127.0.0.1 instead, the same socket takes the same datagram.
        let program = Program::allowing(&[IpAddr::V4(Ipv4Addr::LOCALHOST)], &[])
            .expect("a program")
            .to_socket2();
        assert!(confine_socket(wild.as_raw_fd(), &program).expect("socket"));
        sender.send_to(b"z", ("127.0.0.1", port)).expect("socket");
        wild.set_nonblocking(false).expect("socket");
        wild.set_read_timeout(Some(std::time::Duration::from_secs(2)))
            .expect("socket");
        assert_eq!(wild.recv(&mut buf).expect("socket"), 1);
        assert_eq!(buf[0], b'z');
    }
}
