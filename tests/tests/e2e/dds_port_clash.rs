//! An XRCE port that is also a well-known DDS port (issue 31, item 3). RTI's XRCE client
//! defaults to port 7401, domain 0's user-data multicast port (RTPS: 7400 + 250 × domain + 1):
//! served there, the agent's DDS used to fail to bind it at the first publisher
//! (STATUS_ERR_DDS_ERROR), while eProsima's agent, whose Fast DDS listens for user data by
//! unicast only, works. Now the port is served in both directions, and DDS's spare port for
//! it stays off the ports nano-client binds by default (7402, 7403), so that client and agent
//! share one host. A port DDS cannot do without (a domain's discovery multicast port: 7400,
//! or `-p 22150`, domain 59's) costs that domain only, as with MicroXRCEAgent: the agent
//! starts, says why at start, and refuses that domain's participants.
//!
//! The clash exists only where DDS uses multicast, which the rest of the suite never lets it
//! do (DDS pinned to loopback). So each test runs its body in a private network namespace
//! (`unshare -n`, the test binary started again inside it; needs CAP_SYS_ADMIN, else the test
//! says so and passes without running): there the agent's DDS runs as it would on a LAN,
//! multicast included, on a loopback interface that nothing outside the namespace sees, and
//! domain 0 with the real port numbers is this test's alone.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind, status, ObjectId, VariantExtra};
use xrce_tests::{
    binaries, cyclone_python, dds_backend, hello_world, libtest_name, output_within,
    parse_sample_line, unique_instance, workspace, xml, AgentProcess, DdsPeer, Deliveries,
    TestClient,
};

const SECOND: Duration = Duration::from_secs(1);

/// Set in the environment of the test binary started inside the namespace.
const INSIDE: &str = "XRCE_TEST_PRIVATE_NETNS";

/// Runs the test `inner` of this file again, in a private network namespace (where, seeing
/// [`INSIDE`], it runs its body), and fails unless it passed there.
fn in_private_network(inner: &str) {
    // Built (and Cyclone's Python installed) out here, where the network is.
    binaries();
    cyclone_python();
    let probe = Command::new("unshare")
        .args(["-n", "true"])
        .stderr(Stdio::null())
        .status();
    assert!(
        probe.is_ok_and(|s| s.success()),
        "{inner}: `unshare -n` is not available here (it needs CAP_SYS_ADMIN, as root has); the \
         DDS port clash needs DDS with multicast, which only a private network namespace keeps \
         off the real network"
    );
    let exe = std::env::current_exe().expect("the test binary");
    let out = output_within(
        Command::new("unshare")
            .arg("-n")
            .arg("--")
            .arg(exe)
            .arg(libtest_name(module_path!(), inner))
            .args(["--exact", "--nocapture", "--test-threads", "1"])
            .env(INSIDE, "1"),
        Duration::from_secs(300),
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("{stdout}\n{stderr}");
    assert!(out.status.success(), "{inner} failed in its namespace");
    assert!(
        stdout.contains("1 passed"),
        "{inner} did not run in its namespace"
    );
}

/// Inside the namespace: its loopback interface up, with multicast (as a LAN interface has
/// it), so that both DDS implementations use multicast there. False outside one.
fn namespace_ready() -> bool {
    assert!(
        std::env::var_os(INSIDE).is_some(),
        "a test body meant for a private network namespace ran outside one"
    );
    for args in [
        &["link", "set", "lo", "up"][..],
        &["link", "set", "lo", "multicast", "on"],
        &["route", "add", "224.0.0.0/4", "dev", "lo"],
    ] {
        let st = Command::new("ip").args(args).status().expect("run ip");
        assert!(st.success(), "ip {args:?} failed");
    }
    true
}

/// A Cyclone DDS peer (`dds_peer.py`) with multicast discovery on the namespace's loopback
/// interface, as an independent DDS application on a LAN would run. It shares the agent's
/// host, so domain 0's user-data multicast port is the XRCE port for it too: like any Cyclone
/// DDS application beside an agent served on 7401, it receives user-data multicast on another
/// port (offset 5: 7405 in domain 0; the agent's Cyclone takes offset 9, and 7402-7403 stay
/// free for nano-client), which it announces.
struct MulticastPeer {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl MulticastPeer {
    fn start(args: &[&str]) -> Self {
        let xml = "<CycloneDDS><Domain id=\"any\"><General><Interfaces>\
                   <NetworkInterface name=\"lo\" multicast=\"true\"/></Interfaces>\
                   <AllowMulticast>true</AllowMulticast></General><Discovery><Ports>\
                   <MulticastDataOffset>5</MulticastDataOffset></Ports></Discovery>\
                   </Domain></CycloneDDS>";
        let mut child = Command::new(cyclone_python())
            .arg(workspace().join("tests/python/dds_peer.py"))
            .args(args)
            .env("CYCLONEDDS_URI", xml)
            .stdout(Stdio::piped())
            .spawn()
            .expect("start dds_peer.py");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        MulticastPeer { child, lines }
    }

    /// Waits for a line starting with `prefix` while `pump` runs the client.
    fn wait_for(&self, prefix: &str, d: Duration, mut pump: impl FnMut()) -> bool {
        let end = Instant::now() + d;
        while Instant::now() < end {
            pump();
            if let Ok(l) = self.lines.recv_timeout(Duration::from_millis(2)) {
                if l.starts_with(prefix) {
                    return true;
                }
            }
        }
        false
    }

    /// The HelloWorld samples it printed, by index.
    fn samples(&self, message: &str) -> Vec<u32> {
        self.lines
            .try_iter()
            .filter_map(|l| parse_sample_line(&l))
            .map(|(i, m)| {
                assert_eq!(m, message, "sample {i} carries another message");
                i
            })
            .collect()
    }

    /// Waits for the process to end while `pump` runs the client; its exit code.
    fn wait(&mut self, d: Duration, mut pump: impl FnMut()) -> Option<i32> {
        let end = Instant::now() + d;
        while Instant::now() < end {
            pump();
            if let Ok(Some(s)) = self.child.try_wait() {
                return s.code();
            }
        }
        None
    }
}

impl Drop for MulticastPeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `xrce-agent udp4 -p <port>` with the suite's DDS backend and nothing else: DDS on every
/// interface (the namespace's loopback, with multicast), as a user starts it.
fn agent_on(port: u16, extra: &[&str]) -> AgentProcess {
    let instance = unique_instance("clash");
    let backend = dds_backend();
    let port_s = port.to_string();
    let mut args = vec![
        "udp4",
        "-p",
        &port_s,
        "--dds-backend",
        &backend,
        "--instance",
        &instance,
    ];
    args.extend_from_slice(extra);
    AgentProcess::exactly(
        &args,
        "agent ready",
        SocketAddr::new([127, 0, 0, 1].into(), port),
        &instance,
    )
    .launch()
    .unwrap_or_else(|| panic!("xrce-agent {args:?} did not start"))
}

#[test]
fn rti_default_port_7401_serves_a_publisher_and_a_subscriber() {
    if std::env::var_os(INSIDE).is_some() {
        inner_rti_default_port_7401_serves_a_publisher_and_a_subscriber();
    } else {
        in_private_network("rti_default_port_7401_serves_a_publisher_and_a_subscriber");
    }
}

fn inner_rti_default_port_7401_serves_a_publisher_and_a_subscriber() {
    if namespace_ready() {
        serves_a_publisher_and_a_subscriber(7401, 0);
    }
}

#[test]
fn domain_3_user_multicast_port_8151_serves_a_publisher_and_a_subscriber() {
    if std::env::var_os(INSIDE).is_some() {
        inner_domain_3_user_multicast_port_8151_serves_a_publisher_and_a_subscriber();
    } else {
        in_private_network("domain_3_user_multicast_port_8151_serves_a_publisher_and_a_subscriber");
    }
}

fn inner_domain_3_user_multicast_port_8151_serves_a_publisher_and_a_subscriber() {
    if namespace_ready() {
        // 7400 + 250 × 3 + 1: each domain's ports move by 250.
        serves_a_publisher_and_a_subscriber(8151, 3);
    }
}

/// An agent served on `port`, the user-data multicast port of `domain`: a client's publisher
/// and subscriber in that domain are created (every STATUS OK) and exchange samples with an
/// independent Cyclone DDS application.
fn serves_a_publisher_and_a_subscriber(port: u16, domain: i16) {
    let agent = agent_on(port, &[]);
    let d = domain.to_string();
    let mut reader = MulticastPeer::start(&[
        "read",
        "--domain",
        &d,
        "--count",
        "20",
        "--reliable",
        "--timeout",
        "90",
    ]);
    let mut publ = TestClient::new(agent.addr(), [0x74, 0x01, 0x00, 0x01]);
    publ.connect(10 * SECOND);
    // Every creation answered STATUS_OK (asserted inside), the writer included.
    let w = publ.setup_publisher(domain);
    assert!(
        reader.wait_for("MATCHED 1", 30 * SECOND, || publ.step()),
        "the Cyclone reader never matched the agent's writer"
    );
    // With the agent's DDS in the domain, the ports a nano-client on this host binds by
    // default are free for it (exclusively, as it binds them).
    if port == 7401 {
        for client_port in [7402, 7403] {
            let bound = std::net::UdpSocket::bind(("0.0.0.0", client_port));
            assert!(
                bound.is_ok(),
                "UDP port {client_port}, nano-client's default, is taken: {bound:?}"
            );
        }
    }
    let message = format!("on {port}");
    for i in 0..20 {
        publ.write_reliable(w, &hello_world(i, &message));
    }
    let got = Deliveries::collect(20, 30 * SECOND, || {
        publ.step();
        reader.samples(&message)
    });
    got.assert_exactly_once(0..20, "Cyclone reading a client served on a DDS port");
    // The reader goes on listening a second past its count (for a late duplicate): it must be
    // gone before the Cyclone writer below waits for a match, or it would match that reader
    // and write before the agent's reader is matched.
    assert_eq!(reader.wait(30 * SECOND, || publ.step()), Some(0));

    let mut sub = TestClient::new(agent.addr(), [0x74, 0x01, 0x00, 0x02]);
    sub.connect(10 * SECOND);
    sub.setup_subscriber(domain);
    let message = format!("to {port}");
    let mut writer = MulticastPeer::start(&[
        "write",
        "--domain",
        &d,
        "--count",
        "20",
        "--interval-ms",
        "10",
        "--message",
        &message,
        "--wait-match",
        "--reliable",
        "--timeout",
        "90",
        "--linger-ms",
        "3000",
    ]);
    let got = sub.collect_deliveries(20, &message, 60 * SECOND);
    got.assert_exactly_once(0..20, "a client served on a DDS port reading Cyclone");
    assert_eq!(writer.wait(30 * SECOND, || sub.step()), Some(0));

    let out = agent.output();
    assert_eq!(out.count("failed to bind"), 0, "DDS failed to bind a port");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// `-p 22150` is domain 59's discovery multicast port: MicroXRCEAgent serves every domain
/// but 59 there, and so does this agent (it used to refuse to start). It warns at start,
/// naming the clash and the ways out, and answers a participant in domain 59 STATUS_ERR_DENIED.
#[test]
fn a_discovery_port_serves_every_domain_but_its_own() {
    if std::env::var_os(INSIDE).is_some() {
        inner_a_discovery_port_serves_every_domain_but_its_own();
    } else {
        in_private_network("a_discovery_port_serves_every_domain_but_its_own");
    }
}

fn inner_a_discovery_port_serves_every_domain_but_its_own() {
    if !namespace_ready() {
        return;
    }
    let agent = agent_on(22150, &[]);
    let warning = agent
        .output()
        .wait_for(
            0,
            "DDS participants in domain 59 will be refused",
            10 * SECOND,
        )
        .map(|(_, l)| l)
        .expect("no warning at start about domain 59");
    for part in [
        "UDP port 22150",
        "domain 59's discovery multicast port",
        "--dds-interface 127.0.0.1",
        "--domains",
    ] {
        assert!(warning.contains(part), "{part:?} missing from: {warning}");
    }
    let mut c = TestClient::new(agent.addr(), [0x74, 0x02, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let refused = c.create(
        ObjectId::new(9, object_kind::PARTICIPANT),
        object_kind::PARTICIPANT,
        xml::PARTICIPANT,
        VariantExtra::DomainId(59),
    );
    assert_eq!(refused, status::ERR_DENIED, "a participant in domain 59");
    // Every other domain is served: a whole publisher in domain 1 (each STATUS asserted OK).
    c.setup_publisher(1);
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn discovery_port_7400_is_served_where_dds_does_without_it() {
    if std::env::var_os(INSIDE).is_some() {
        inner_discovery_port_7400_is_served_where_dds_does_without_it();
    } else {
        in_private_network("discovery_port_7400_is_served_where_dds_does_without_it");
    }
}

fn inner_discovery_port_7400_is_served_where_dds_does_without_it() {
    if !namespace_ready() {
        return;
    }
    // Clients kept out of domain 0: no clash.
    let agent = agent_on(7400, &["--domains", "1-232"]);
    assert!(agent.stop(), "agent did not stop cleanly");

    // DDS confined to loopback discovers by unicast: served, domain 0 included.
    let agent = agent_on(7400, &["--dds-interface", "127.0.0.1"]);
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "0",
        "--count",
        "5",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0x74, 0x00, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(0);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "the Cyclone reader never matched the agent's writer"
    );
    for i in 0..5 {
        c.write_reliable(w, &hello_world(i, "on 7400"));
    }
    let got = reader.collect_deliveries(5, "on 7400", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..5, "Cyclone reading a client served on 7400");
    assert!(agent.stop(), "agent did not stop cleanly");
}
