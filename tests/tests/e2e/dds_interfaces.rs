//! `--dds-interface` keeps DDS where it is told: every UDP socket of the DDS worker is bound
//! to a configured address, or takes no datagram sent to any other (issue 16 item 5).
//!
//! Both DDS libraries bind their receiving sockets to the wildcard address whatever they are
//! told, so the worker confines those with a socket filter. The test reads the worker's UDP
//! sockets from `/proc` (its descriptors, and the kernel's UDP tables with each socket's
//! drop count), sends one datagram to 127.0.0.1 at each wildcard socket while DDS is
//! restricted to ::1, and checks that the kernel dropped it there. Without the confinement
//! DDS reads those datagrams (the drop count stays put) and the test fails. Every test socket
//! stays on 127.0.0.1 and ::1.

use std::collections::HashSet;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind as k, ObjectId, VariantExtra};
use xrce_tests::{free_udp_port, unique_instance, xml, AgentProcess, TestClient};

/// One UDP socket from `/proc/<pid>/net/udp{,6}`.
#[derive(Debug, Clone)]
struct UdpEntry {
    local: SocketAddr,
    inode: u64,
    drops: u64,
}

/// Parses `/proc/<pid>/net/udp` or `udp6` (addresses in hex, in the kernel's byte order).
fn udp_table(pid: i32, v6: bool) -> Vec<UdpEntry> {
    let path = format!("/proc/{pid}/net/{}", if v6 { "udp6" } else { "udp" });
    let text = std::fs::read_to_string(&path).unwrap_or_default();
    text.lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let (addr, port) = f.get(1)?.split_once(':')?;
            let port = u16::from_str_radix(port, 16).ok()?;
            let ip = if v6 {
                let mut o = [0u8; 16];
                for (i, chunk) in o.chunks_exact_mut(4).enumerate() {
                    let w = u32::from_str_radix(addr.get(8 * i..8 * i + 8)?, 16).ok()?;
                    chunk.copy_from_slice(&w.to_ne_bytes());
                }
                IpAddr::V6(Ipv6Addr::from(o))
            } else {
                let w = u32::from_str_radix(addr, 16).ok()?;
                IpAddr::V4(Ipv4Addr::from(w.to_ne_bytes()))
            };
            Some(UdpEntry {
                local: SocketAddr::new(ip, port),
                inode: f.get(9)?.parse().ok()?,
                drops: f.last()?.parse().ok()?,
            })
        })
        .collect()
}

/// The inodes of the sockets process `pid` holds.
fn socket_inodes(pid: i32) -> HashSet<u64> {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let t = std::fs::read_link(e.path()).ok()?;
            let t = t.to_string_lossy();
            t.strip_prefix("socket:[")?.strip_suffix(']')?.parse().ok()
        })
        .collect()
}

/// The UDP sockets of process `pid`.
fn udp_sockets(pid: i32) -> Vec<UdpEntry> {
    let mine = socket_inodes(pid);
    [false, true]
        .into_iter()
        .flat_map(|v6| udp_table(pid, v6))
        .filter(|e| mine.contains(&e.inode))
        .collect()
}

/// Starts an agent whose DDS is restricted to `dds_interface` (and nothing else).
fn agent_with_dds_on(tag: &str, dds_interface: &str) -> AgentProcess {
    for _ in 0..5 {
        let port = free_udp_port();
        let instance = unique_instance(tag);
        let p = port.to_string();
        let args = [
            "udp4",
            "-p",
            &p,
            "--bind",
            "127.0.0.1",
            "--dds-interface",
            dds_interface,
            "--instance",
            &instance,
        ];
        if let Some(a) = AgentProcess::exactly(
            &args,
            "agent ready",
            SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), port),
            &instance,
        )
        .launch()
        {
            return a;
        }
    }
    panic!("the agent did not start on any of 5 free ports");
}

/// A client that makes the worker create a DDS participant with a writer and a reader.
fn create_dds_entities(agent: &AgentProcess) -> TestClient {
    let mut c = TestClient::new(agent.addr(), [0x1F, 0xAC, 0x00, 0x01]);
    c.connect(Duration::from_secs(10));
    c.setup_publisher(27);
    let participant = ObjectId::new(1, k::PARTICIPANT);
    let subscriber = ObjectId::new(2, k::SUBSCRIBER);
    let reader = ObjectId::new(2, k::DATAREADER);
    let steps = [
        (
            subscriber,
            k::SUBSCRIBER,
            "",
            VariantExtra::Parent(participant),
        ),
        (
            reader,
            k::DATAREADER,
            xml::READER,
            VariantExtra::Parent(subscriber),
        ),
    ];
    for (id, kind, x, extra) in steps {
        assert_eq!(c.create(id, kind, x, extra), 0, "creating {id:?}");
    }
    c
}

/// How many datagrams the sockets of `pid` on `port` dropped (two sockets may share a
/// port with SO_REUSEADDR, RustDDS's multicast listeners, and one of them gets a datagram).
fn drops_on_port(pid: i32, port: u16) -> u64 {
    udp_sockets(pid)
        .into_iter()
        .filter(|e| e.local.port() == port)
        .map(|e| e.drops)
        .sum()
}

/// Waits until the sockets of `pid` on `port` dropped more than `before` datagrams.
fn dropped_since(pid: i32, port: u16, before: u64, d: Duration) -> bool {
    let end = Instant::now() + d;
    while Instant::now() < end {
        if drops_on_port(pid, port) > before {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}

#[test]
fn dds_sockets_take_no_datagram_for_an_address_dds_was_not_given() {
    let agent = agent_with_dds_on("ddsif", "::1");
    let _client = create_dds_entities(&agent);
    let worker = *agent
        .child_pids("dds-worker")
        .first()
        .expect("the agent runs a DDS worker");
    let sockets = udp_sockets(worker);
    assert!(
        !sockets.is_empty(),
        "the worker's DDS participant has UDP sockets"
    );
    let configured = IpAddr::V6(Ipv6Addr::LOCALHOST);
    let sender = UdpSocket::bind("127.0.0.1:0").expect("sender on 127.0.0.1");
    let mut ports = std::collections::BTreeSet::new();
    for s in &sockets {
        if s.local.ip() == configured {
            continue;
        }
        assert!(
            s.local.ip().is_unspecified(),
            "a DDS socket bound to an address it was not given: {s:?}"
        );
        ports.insert(s.local.port());
    }
    for &port in &ports {
        let before = drops_on_port(worker, port);
        // Not RTPS: if it got through, DDS would read and discard it, and count no drop.
        sender
            .send_to(b"not for DDS", ("127.0.0.1", port))
            .expect("send to 127.0.0.1");
        assert!(
            dropped_since(worker, port, before, Duration::from_secs(5)),
            "a DDS socket on port {port} took a datagram sent to 127.0.0.1 though DDS was \
             given only ::1"
        );
    }
    let wildcard = ports.len();
    eprintln!(
        "{} UDP sockets, {wildcard} ports bound to the wildcard address, all confined",
        sockets.len()
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
