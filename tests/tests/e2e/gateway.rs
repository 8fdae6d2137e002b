//! The gateway: several front-ends, one per transport, on one DDS worker from one file
//! (`xrce-agent --config FILE`), with real processes, sockets and ptys, and Cyclone DDS.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use xrce_tests::{
    binaries, free_tcp_port, free_udp_port, hello_world, sigkill, unique_instance, AgentProcess,
    DdsPeer, Deliveries, PtyPair, TestClient, DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

fn scratch(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xrce-gw-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch dir");
    d
}

fn write(dir: &Path, text: &str) -> PathBuf {
    let p = dir.join("gateway.toml");
    std::fs::write(&p, text).expect("write gateway file");
    p
}

/// A gateway file of one UDP front-end, `lan`, on 127.0.0.1:`udp`, DDS on loopback, with
/// `worker` and `frontend` lines added to those tables.
fn lan_gateway(instance: &str, udp: u16, worker: &str, frontend: &str) -> String {
    format!(
        r#"
[agent]
instance = "{instance}"
[worker]
dds_interfaces = ["127.0.0.1"]
{worker}
[[frontend]]
name = "lan"
transport = "udp4"
port = {udp}
bind = "127.0.0.1"
{frontend}
"#
    )
}

fn gateway(path: &Path, instance: &str) -> AgentProcess {
    let p = path.to_str().expect("utf-8 path");
    AgentProcess::exactly(
        &["--config", p],
        "agent ready",
        SocketAddr::new([127, 0, 0, 1].into(), 0),
        instance,
    )
    .launch()
    .expect("the gateway did not become ready")
}

/// Steps every client until each subscriber has `want` distinct samples (then a grace for
/// duplicates), returning what each got.
fn collect_all(
    publishers: &mut [&mut TestClient],
    subscribers: &mut [&mut TestClient],
    want: usize,
    d: Duration,
) -> Vec<Deliveries> {
    let mut got = vec![Deliveries::default(); subscribers.len()];
    let end = Instant::now() + d;
    let mut complete: Option<Instant> = None;
    while Instant::now() < end && complete.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
        for p in publishers.iter_mut() {
            p.step();
        }
        for (s, g) in subscribers.iter_mut().zip(got.iter_mut()) {
            s.step();
            for (i, m) in s.take_samples() {
                assert_eq!(m, "gateway");
                g.record(i);
            }
        }
        if complete.is_none() && got.iter().all(|g| g.distinct() >= want) {
            complete = Some(Instant::now());
        }
    }
    got
}

/// A UDP client publishes; a TCP client, a serial client and Cyclone DDS each get every
/// sample exactly once, through three front-ends on one worker.
#[test]
fn udp_tcp_and_serial_clients_share_one_worker() {
    let dir = scratch("three");
    let pty = PtyPair::open();
    let (udp, tcp) = (free_udp_port(), free_tcp_port());
    let instance = unique_instance("gw3");
    let path = write(
        &dir,
        &format!(
            r#"
[agent]
instance = "{instance}"
[worker]
dds_interfaces = ["127.0.0.1"]
[[frontend]]
name = "lan"
transport = "udp4"
port = {udp}
bind = "127.0.0.1"
[[frontend]]
name = "companion"
transport = "tcp4"
port = {tcp}
bind = "127.0.0.1"
[[frontend]]
name = "fmu"
transport = "serial"
device = "{}"
baudrate = 921600
"#,
            pty.slave_path.display()
        ),
    );
    let agent = gateway(&path, &instance);
    let cyclone = DdsPeer::start(&[
        "read",
        "--domain",
        "60",
        "--count",
        "30",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut publisher = TestClient::new(([127, 0, 0, 1], udp).into(), [0x6A, 0, 0, 1]);
    let mut tcp_sub = TestClient::tcp(([127, 0, 0, 1], tcp).into(), [0x6A, 0, 0, 2]);
    let mut serial_sub = TestClient::serial(pty.master, 1, [0x6A, 0, 0, 3]);
    for c in [&mut publisher, &mut tcp_sub, &mut serial_sub] {
        c.connect(10 * SECOND);
    }
    tcp_sub.setup_subscriber(60);
    serial_sub.setup_subscriber(60);
    let w = publisher.setup_publisher(60);
    assert!(cyclone
        .wait_for("MATCHED 1", 30 * SECOND, || publisher.step())
        .is_some());
    for i in 0..30 {
        publisher.write_reliable(w, &hello_world(i, "gateway"));
        tcp_sub.step();
        serial_sub.step();
    }
    let got = collect_all(
        &mut [&mut publisher],
        &mut [&mut tcp_sub, &mut serial_sub],
        30,
        60 * SECOND,
    );
    got[0].assert_exactly_once(0..30, "the TCP client");
    got[1].assert_exactly_once(0..30, "the serial client");
    let dds = cyclone.collect_deliveries(30, "gateway", 30 * SECOND, || {
        publisher.step();
        tcp_sub.step();
        serial_sub.step();
    });
    dds.assert_exactly_once(0..30, "Cyclone DDS");
    assert!(agent.stop(), "gateway did not stop cleanly");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A UDP port of two processes (`processes = 2`): a client steered to the first publishes,
/// one steered to the second subscribes, and every sample crosses from one process to the
/// other through the worker once; each session is where its client's address says.
#[test]
fn a_udp_port_of_two_processes_carries_samples_between_them() {
    use xrce_agent::shared_port::member_for;
    let dir = scratch("processes");
    let udp = free_udp_port();
    let instance = unique_instance("gwp");
    let path = write(&dir, &lan_gateway(&instance, udp, "", "processes = 2"));
    let agent = gateway(&path, &instance);
    // The first address of 127.0.0.0/8 each process is given.
    let of = |member: u16| {
        (1..=254u8)
            .map(|last| std::net::IpAddr::from([127, 0, 0, last]))
            .find(|a| member_for(*a, 2) == member)
            .expect("an address")
    };
    let port: SocketAddr = ([127, 0, 0, 1], udp).into();
    let client = |member: u16, key: [u8; 4]| {
        let link = xrce_tests::link::Link::udp_from(port, of(member));
        let config =
            xrce_common::session::client::ClientConfig::new(xrce_common::wire::ClientKey(key));
        TestClient::on_link(link, config)
    };
    let mut publisher = client(0, [0x6B, 0, 0, 1]);
    let mut subscriber = client(1, [0x6B, 0, 0, 2]);
    for c in [&mut publisher, &mut subscriber] {
        c.connect(10 * SECOND);
    }
    subscriber.setup_subscriber(83);
    let w = publisher.setup_publisher(83);
    for i in 0..30 {
        publisher.write_reliable(w, &hello_world(i, "gateway"));
        subscriber.step();
    }
    let got = collect_all(
        &mut [&mut publisher],
        &mut [&mut subscriber],
        30,
        60 * SECOND,
    );
    got[0].assert_exactly_once(0..30, "the subscriber on the other process");
    // Which process created each session (the front-end's name is in its log lines).
    let out = agent.output();
    let served_by = |key: &str| {
        let mut from = 0;
        while let Some((i, line)) = out.wait_for(from, "session created", Duration::ZERO) {
            if line.contains(key) {
                return line.contains("lan-2");
            }
            from = i + 1;
        }
        panic!("no session created for {key}");
    };
    assert!(
        !served_by("6B000001"),
        "the publisher is the first process's"
    );
    assert!(
        served_by("6B000002"),
        "the subscriber is the second process's"
    );
    assert!(agent.stop(), "gateway did not stop cleanly");
    let _ = std::fs::remove_dir_all(&dir);
}

/// One front-end killed: the supervisor restarts it on its own while the other keeps
/// serving its clients, and the restarted one serves new ones.
#[test]
fn a_killed_frontend_restarts_while_the_others_keep_serving() {
    let dir = scratch("kill");
    let (udp, tcp) = (free_udp_port(), free_tcp_port());
    let instance = unique_instance("gwkill");
    let path = write(
        &dir,
        &format!(
            r#"
[agent]
instance = "{instance}"
[worker]
dds_interfaces = ["127.0.0.1"]
[[frontend]]
transport = "udp4"
port = {udp}
bind = "127.0.0.1"
[[frontend]]
transport = "tcp4"
port = {tcp}
bind = "127.0.0.1"
"#
        ),
    );
    let agent = gateway(&path, &instance);
    let udp_addr = ([127, 0, 0, 1], udp).into();
    let mut publisher = TestClient::new(udp_addr, [0x6B, 0, 0, 1]);
    let mut subscriber = TestClient::new(udp_addr, [0x6B, 0, 0, 2]);
    publisher.connect(10 * SECOND);
    subscriber.connect(10 * SECOND);
    subscriber.setup_subscriber(103);
    let w = publisher.setup_publisher(103);
    let mut tcp_client = TestClient::tcp(([127, 0, 0, 1], tcp).into(), [0x6B, 0, 0, 3]);
    tcp_client.connect(10 * SECOND);
    let tcp_pid = agent
        .child_pid_with("frontend", "tcp4")
        .expect("the TCP front-end's pid");
    let out = agent.output().clone();
    let mark = out.len();
    // Kill the TCP front-end in the middle of the UDP clients' traffic.
    for i in 0..40 {
        if i == 10 {
            sigkill(tcp_pid);
        }
        publisher.write_reliable(w, &hello_world(i, "gateway"));
        subscriber.step();
    }
    let got = collect_all(
        &mut [&mut publisher],
        &mut [&mut subscriber],
        40,
        60 * SECOND,
    );
    got[0].assert_exactly_once(0..40, "UDP clients while the TCP front-end restarts");
    out.wait_for(mark, "restarted name=xrce-frontend-tcp4", 20 * SECOND)
        .expect("the TCP front-end was not restarted");
    out.wait_for(mark, "front-end serving again", 20 * SECOND)
        .expect("the restarted front-end did not report serving");
    let new_pid = agent
        .child_pid_with("frontend", "tcp4")
        .expect("the restarted TCP front-end's pid");
    assert_ne!(new_pid, tcp_pid);
    assert!(
        agent.child_pid_with("frontend", "udp4").is_some(),
        "the UDP front-end went too"
    );
    // The restarted one serves: a client (reconnecting, as the old connection is gone)
    // creates its session and reads what the UDP client publishes.
    drop(tcp_client);
    let mut tcp_client = TestClient::tcp(([127, 0, 0, 1], tcp).into(), [0x6B, 0, 0, 3]);
    tcp_client.connect(10 * SECOND);
    tcp_client.setup_subscriber(103);
    // Until DDS matched the new reader: probes, not counted.
    let end = Instant::now() + 30 * SECOND;
    let mut matched = false;
    while !matched && Instant::now() < end {
        publisher.write_reliable(w, &hello_world(1_000, "probe"));
        let t = Instant::now();
        while t.elapsed() < Duration::from_millis(200) {
            publisher.step();
            tcp_client.step();
            subscriber.step();
            matched |= tcp_client.take_samples().iter().any(|(i, _)| *i == 1_000);
        }
        subscriber.take_samples();
    }
    assert!(
        matched,
        "the restarted front-end's client never heard the publisher"
    );
    for i in 100..110 {
        publisher.write_reliable(w, &hello_world(i, "gateway"));
    }
    let got = Deliveries::collect(10, 30 * SECOND, || {
        publisher.step();
        subscriber.step();
        tcp_client.step();
        tcp_client
            .take_samples()
            .into_iter()
            .filter(|(_, m)| m == "gateway")
            .map(|(i, _)| i)
            .collect()
    });
    got.assert_exactly_once(100..110, "the restarted front-end's client");
    assert!(agent.stop(), "gateway did not stop cleanly");
    let _ = std::fs::remove_dir_all(&dir);
}

fn check(path: &Path) -> (Option<i32>, String, String) {
    let out = xrce_tests::output_within(
        Command::new(binaries().join("xrce-agent")).args([
            "--config",
            path.to_str().expect("utf-8"),
            "--check",
        ]),
        Duration::from_secs(30),
    );
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `--check` accepts the shipped example and refuses bad files with the key and the line;
/// starting with a bad file is refused the same way.
#[test]
fn gateway_files_are_checked_with_the_key_and_line() {
    let example = xrce_tests::workspace().join("deploy/gateway.example.toml");
    let (code, stdout, stderr) = check(&example);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stdout.contains("valid"), "{stdout}");
    assert!(stdout.contains("serial"), "{stdout}");
    let dir = scratch("check");
    for (text, line, says) in [
        (
            "[[frontend]]\ntransport = \"udp4\"\nport = 1\n\n[[frontend]]\ntransport = \"tcp4\"\nport = 2\nid = 0\n",
            8,
            "`id` 0 is also frontend 1's",
        ),
        (
            "[worker]\nref = \"x.xml\"\n[[frontend]]\ntransport = \"udp4\"\nport = 1\n",
            2,
            "unknown field `ref`",
        ),
        (
            "[[frontend]]\ntransport = \"serial\"\nbaudrate = 921600\n",
            1,
            "`device` is required",
        ),
        (
            "[metrics]\nlisten = \"localhost\"\n[[frontend]]\ntransport = \"udp4\"\nport = 1\n",
            2,
            "metrics.listen \"localhost\" is not an address and port",
        ),
        (
            "[[frontend]]\ntransport = \"udp4\"\nport = 1\nname = \"metrics\"\n",
            4,
            "names another process of the agent",
        ),
    ] {
        let path = write(&dir, text);
        let (code, _, stderr) = check(&path);
        assert_eq!(code, Some(1), "{text}: {stderr}");
        assert!(stderr.contains(&format!("gateway.toml:{line}:")), "{text}: {stderr}");
        assert!(stderr.contains(says), "{text}: {stderr}");
        let run = xrce_tests::output_within(Command::new(binaries().join("xrce-agent"))
            .args(["--config", path.to_str().expect("utf-8")]), Duration::from_secs(30));
        assert_eq!(run.status.code(), Some(1));
        assert!(String::from_utf8_lossy(&run.stderr).contains(says));
    }
    // A key the file leaves to the environment, with a value the worker refuses, refuses the
    // gateway (it confines DDS: never dropped in favour of the built-in defaults).
    let path = write(
        &dir,
        "[[frontend]]\ntransport = \"udp4\"\nport = 1\nbind = \"127.0.0.1\"\n",
    );
    let run = xrce_tests::output_within(
        Command::new(binaries().join("xrce-agent"))
            .args(["--config", path.to_str().expect("utf-8")])
            .env("XRCE_DOMAINS", "not-a-domain"),
        Duration::from_secs(30),
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("XRCE_DOMAINS") && stderr.contains("not-a-domain"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Each process of the gateway as its own service (`--process`, as the systemd units run
/// them): a second front-end with an id already served is refused, and when a front-end is
/// gone for good the worker deletes its clients' entities after the grace period.
#[test]
fn processes_run_on_their_own_and_a_gone_frontend_is_cleaned_up() {
    let dir = scratch("process");
    let udp = free_udp_port();
    let instance = unique_instance("gwproc");
    let path = write(&dir, &lan_gateway(&instance, udp, "frontend_grace = 2", ""));
    let p = path.to_str().expect("utf-8");
    let localhost = [127, 0, 0, 1].into();
    let worker = AgentProcess::exactly(
        &["--config", p, "--process", "worker"],
        "worker serving",
        SocketAddr::new(localhost, 0),
        &instance,
    )
    .launch()
    .expect("the worker did not start");
    let frontend = AgentProcess::exactly(
        &["--config", p, "--process", "lan"],
        "worker generation seen",
        SocketAddr::new(localhost, udp),
        &instance,
    )
    .launch()
    .expect("the front-end did not start");
    let mut c = TestClient::new(([127, 0, 0, 1], udp).into(), [0x6C, 0, 0, 1]);
    c.connect(10 * SECOND);
    c.setup_publisher(104);
    // A second front-end with the same id on another port (another file naming the same
    // instance, say): it would take the first one's clients' entities; it is refused.
    let other = format!("127.0.0.1:{}", free_udp_port());
    let second = xrce_tests::output_within(
        Command::new(binaries().join("xrce-agent"))
            .args(["frontend", "--instance", &instance, "--frontend-id", "0"])
            .args(["--transport", "udp4", "--listen", &other])
            .env("XRCE_LOG", "info"),
        Duration::from_secs(30),
    );
    assert!(!second.status.success());
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert!(stderr.contains("already runs"), "{stderr}");
    // The first one still serves.
    assert!(
        frontend.ping(5 * SECOND),
        "the first front-end stopped serving"
    );
    // Gone for good: the worker keeps its clients' entities for the grace period, then
    // deletes them.
    let out = worker.output().clone();
    let mark = out.len();
    sigkill(frontend.pid() as i32);
    let (gone_at, _) = out
        .wait_for(mark, "front-end process gone", 10 * SECOND)
        .expect("the worker did not notice the front-end going");
    let (at, line) = out
        .wait_for(mark, "front-end did not come back", 10 * SECOND)
        .expect("the worker did not delete the gone front-end's entities");
    assert!(line.contains("clients=1"), "{line}");
    assert!(
        at > gone_at,
        "the entities were deleted before the front-end was seen gone"
    );
    drop(frontend);
    assert!(worker.stop_process(), "worker did not stop cleanly");
    xrce_ipc::shm::remove_instance_leftovers(&instance);
    let _ = std::fs::remove_dir_all(&dir);
}
