//! Serial lines end to end: Rust XRCE clients on pseudoterminal pairs made by the test (the
//! agent opens the slave as its serial device; the client talks on the master, eProsima's
//! stream framing) ↔ `xrce-agent serial|multiserial|pseudoterminal` ↔ Cyclone DDS. Also the
//! device life cycle: a device unplugged while the agent runs and plugged back under the
//! same path, with the client's session continuing. Every sample is counted: each must
//! arrive exactly once.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use xrce_common::wire::stream_id;
use xrce_tests::scenarios;
use xrce_tests::{hello_world, AgentProcess, DdsPeer, Link, PtyPair, SharedLine, TestClient};

const SECOND: Duration = Duration::from_secs(1);

fn agent(tag: &str, args: &[&str]) -> AgentProcess {
    AgentProcess::builder(tag)
        .command_line(args)
        .launch()
        .expect("the serial agent did not become ready")
}

fn path(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

#[test]
fn serial_client_publishes_cyclone_reads_each_sample_once() {
    let pty = PtyPair::open();
    let agent = agent(
        "serpub",
        &["serial", "--dev", path(&pty.slave_path), "-b", "921600"],
    );
    let mut c = TestClient::serial(pty.master, 1, [0x5E, 0x41, 0, 1]);
    c.connect(10 * SECOND);
    scenarios::client_publishes_cyclone_reads(&mut c, 54, 30, "over serial", "a serial client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// Two clients share one line (addresses 1 and 2): one publishes, the other reads it through
/// the agent, and Cyclone's samples reach the reader too; garbage on the line between frames
/// (noise, a bad CRC, a frame for another node) is dropped without harm.
#[test]
fn two_clients_on_one_line_are_separate_sessions() {
    let pty = PtyPair::open();
    let agent = agent("ser2", &["serial", "--dev", path(&pty.slave_path)]);
    let noise = pty.master.try_clone().expect("clone");
    let line = SharedLine::new(pty.master);
    let config = |k: u8| {
        xrce_common::session::client::ClientConfig::new(xrce_common::wire::ClientKey([
            0x5E, 0x42, 0, k,
        ]))
    };
    let mut publisher = TestClient::on_link(line.link(1), config(1));
    let mut subscriber = TestClient::on_link(line.link(2), config(2));
    publisher.connect(10 * SECOND);
    subscriber.connect(10 * SECOND);
    subscriber.setup_subscriber(55);
    let w = publisher.setup_publisher(55);
    let mut bad = b"boot banner\r\n".to_vec();
    let mut frame = Vec::new();
    xrce_common::framing::serial::encode(1, 0, &[1, 2, 3, 4], &mut frame).expect("fits");
    let last = frame.len() - 1;
    frame[last] ^= 0x55;
    bad.extend(&frame);
    xrce_common::framing::serial::encode(1, 9, &[1, 2, 3, 4], &mut bad).expect("fits");
    for i in 0..20 {
        publisher.write_reliable(w, &hello_world(i, "line mate"));
        if i == 10 {
            use std::io::Write;
            (&noise).write_all(&bad).expect("noise");
        }
        subscriber.step();
    }
    let end = Instant::now() + 30 * SECOND;
    let mut got = xrce_tests::Deliveries::default();
    let mut complete: Option<Instant> = None;
    while Instant::now() < end && complete.is_none_or(|t| t.elapsed() < xrce_tests::DUPLICATE_GRACE)
    {
        publisher.step();
        subscriber.step();
        for (i, m) in subscriber.take_samples() {
            assert_eq!(m, "line mate");
            got.record(i);
        }
        if complete.is_none() && got.distinct() == 20 {
            complete = Some(Instant::now());
        }
    }
    got.assert_exactly_once(0..20, "a client reading its line mate");
    got.assert_in_order("a client reading its line mate");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// multiserial: one front-end, two lines, each with a client at address 1: separate clients
/// that read each other's samples through the agent.
#[test]
fn multiserial_clients_on_two_lines_read_each_other() {
    let a = PtyPair::open();
    let b = PtyPair::open();
    let devs = format!("{} {}", path(&a.slave_path), path(&b.slave_path));
    let agent = agent("mser", &["multiserial", "--devs", &devs, "-b", "115200"]);
    let mut publisher = TestClient::serial(a.master, 1, [0x5E, 0x43, 0, 1]);
    let mut subscriber = TestClient::serial(b.master, 1, [0x5E, 0x43, 0, 2]);
    publisher.connect(10 * SECOND);
    subscriber.connect(10 * SECOND);
    subscriber.setup_subscriber(56);
    let w = publisher.setup_publisher(56);
    for i in 0..20 {
        publisher.write_reliable(w, &hello_world(i, "across lines"));
        subscriber.step();
    }
    let mut got = xrce_tests::Deliveries::default();
    let end = Instant::now() + 30 * SECOND;
    let mut complete: Option<Instant> = None;
    while Instant::now() < end && complete.is_none_or(|t| t.elapsed() < xrce_tests::DUPLICATE_GRACE)
    {
        publisher.step();
        subscriber.step();
        for (i, m) in subscriber.take_samples() {
            assert_eq!(m, "across lines");
            got.record(i);
        }
        if complete.is_none() && got.distinct() == 20 {
            complete = Some(Instant::now());
        }
    }
    got.assert_exactly_once(0..20, "a client on the other line");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// Points `link` at the slave of `pty` (a device node that comes and goes under one path).
fn plug(link: &Path, pty: &PtyPair) {
    let _ = std::fs::remove_file(link);
    std::os::unix::fs::symlink(&pty.slave_path, link).expect("symlink");
}

fn scratch_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xrce-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch dir");
    d
}

/// The device is not there when the agent starts (waited for), appears, is unplugged while
/// the client publishes, and comes back under the same path: the client continues its
/// session without re-creating anything, and Cyclone gets every sample exactly once.
#[test]
fn a_serial_device_unplugged_and_plugged_back_keeps_the_session() {
    let dir = scratch_dir("replug");
    let dev = dir.join("ttyACM0");
    let agent = agent("replug", &["serial", "--dev", path(&dev), "-b", "921600"]);
    let out = agent.output().clone();
    assert!(
        out.wait_for(0, "waiting for it to appear", 10 * SECOND)
            .is_some(),
        "a missing device is not waited for"
    );
    let first = PtyPair::open();
    plug(&dev, &first);
    let (opened, _) = out
        .wait_for(0, "serial device opened", 10 * SECOND)
        .expect("the device was not opened when it appeared");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "57",
        "--count",
        "20",
        "--reliable",
        "--timeout",
        "90",
    ]);
    let mut c = TestClient::serial(first.master, 1, [0x5E, 0x44, 0, 1]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(57);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    for i in 0..10 {
        c.write_reliable(w, &hello_world(i, "replug"));
    }
    assert!(c.run_until(10 * SECOND, |c| c
        .client
        .unacked(stream_id::BUILTIN_RELIABLE)
        == 0));
    // Unplug: the device node goes away, and the other end of the line with it (the link
    // first, so the agent cannot open a /dev/pts number a parallel test reuses).
    let _ = std::fs::remove_file(&dev);
    let unplugged = std::mem::replace(&mut c.link, Link::udp("127.0.0.1:9".parse().expect("addr")));
    drop(unplugged);
    let (gone, _) = out
        .wait_for(opened, "serial device gone", 10 * SECOND)
        .expect("the agent did not notice the device going away");
    // Written while unplugged: the reliable stream keeps them for the repair.
    let mut i = 10;
    let deadline = Instant::now() + 10 * SECOND;
    while i < 15 {
        assert!(
            Instant::now() < deadline,
            "the reliable window stayed full while unplugged"
        );
        if c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE) {
            c.client
                .write(
                    Instant::now(),
                    stream_id::BUILTIN_RELIABLE,
                    w,
                    &hello_world(i, "replug"),
                )
                .expect("write");
            i += 1;
        }
        c.client.handle_timeout(Instant::now());
        while c.client.poll_transmit().is_some() {}
    }
    let second = PtyPair::open();
    plug(&dev, &second);
    out.wait_for(gone, "serial device back", 10 * SECOND)
        .expect("the agent did not reopen the device");
    c.link = Link::serial(second.master, 1);
    for i in 15..20 {
        c.write_reliable(w, &hello_world(i, "replug"));
    }
    let got = reader.collect_deliveries(20, "replug", 40 * SECOND, || c.step());
    got.assert_exactly_once(0..20, "samples around an unplug");
    got.assert_in_order("samples around an unplug");
    assert_eq!(
        out.count("session created"),
        1,
        "the session was created anew"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
    let _ = std::fs::remove_dir_all(&dir);
}

/// pseudoterminal: the agent prints the path of its pty; a client opens it, publishes, and
/// closes it; another client opens it afterwards and is served too.
#[test]
fn the_agents_pseudoterminal_serves_one_client_after_another() {
    let agent = agent("pty", &["pseudoterminal", "-b", "115200"]);
    let (_, line) = agent
        .output()
        .wait_for(0, "Pseudoterminal opened at ", 10 * SECOND)
        .expect("the pty path was not printed");
    let pts = line
        .rsplit("Pseudoterminal opened at ")
        .next()
        .and_then(|rest| rest.split_whitespace().next())
        .expect("path")
        .to_string();
    assert!(line.contains(&format!("(dev: {pts})")), "{line}");
    assert!(pts.starts_with("/dev/pts/"), "{pts}");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "58",
        "--count",
        "10",
        "--reliable",
        "--timeout",
        "60",
    ]);
    for (round, key) in [(0u32, 1u8), (1, 2)] {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&pts)
            .expect("open the agent's pseudoterminal");
        let mut c = TestClient::serial(file, 1, [0x5E, 0x45, 0, key]);
        c.connect(10 * SECOND);
        let w = c.setup_publisher(58);
        if round == 0 {
            assert!(reader
                .wait_for("MATCHED 1", 30 * SECOND, || c.step())
                .is_some());
        }
        for i in 0..5 {
            c.write_reliable(w, &hello_world(round * 5 + i, "pty"));
        }
        // Each client stays until its samples are in DDS: a session that ends deletes its
        // writer, and DDS does not deliver for a deleted writer.
        let got = reader.collect_deliveries(5, "pty", 30 * SECOND, || c.step());
        got.assert_exactly_once(
            round * 5..round * 5 + 5,
            "a client of the agent's pseudoterminal",
        );
        drop(c);
    }
    assert!(agent.stop(), "agent did not stop cleanly");
}
