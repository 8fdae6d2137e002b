//! HelloWorld between an XRCE client and Fast DDS, the DDS of the reference agent, through
//! `xrce-agent` with its default backend (and RustDDS when the suite runs against it):
//! `tests/fastdds/hello_pub.cpp` and `hello_sub.cpp` are small Fast DDS 2.9 programs (Debian's
//! `libfastrtps-dev`, installed by `deploy/test-deps`) with a hand-written HelloWorld type,
//! pinned to 127.0.0.1; the test builds them with g++ once. The other independent DDS of the
//! suite is Cyclone DDS from Python (helloworld_e2e.rs and others).

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind, RequestId};
use xrce_tests::{
    adder_request, hello_world, workspace, AgentProcess, Deliveries, TestClient, DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

/// Builds (once per test binary) the Fast DDS programs; the directory holding them.
fn fastdds_programs() -> &'static Path {
    static BUILT: OnceLock<PathBuf> = OnceLock::new();
    BUILT.get_or_init(|| {
        let src = workspace().join("tests/fastdds");
        let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("fastdds");
        std::fs::create_dir_all(&out).expect("output directory");
        for program in ["hello_pub", "hello_sub", "adder_replier"] {
            let result = Command::new("g++")
                .args(["-std=c++14", "-O1", "-Wall", "-o"])
                .arg(out.join(program))
                .arg(src.join(format!("{program}.cpp")))
                .args(["-lfastrtps", "-lfastcdr", "-lpthread"])
                .output()
                .expect("g++ (a C++ compiler) must be installed");
            assert!(
                result.status.success(),
                "building {program} against Fast DDS failed; Debian's libfastrtps-dev and \
                 libfastcdr-dev must be installed (deploy/test-deps):\n{}",
                String::from_utf8_lossy(&result.stderr)
            );
        }
        out
    })
}

/// A running Fast DDS program and the lines it printed (stdout and stderr, in one channel).
struct FastDds {
    child: Child,
    lines: Receiver<String>,
    seen: Vec<String>,
}

impl FastDds {
    fn start(program: &str, args: &[&str]) -> Self {
        let mut child = Command::new(fastdds_programs().join(program))
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start the Fast DDS program");
        let (tx, lines) = channel();
        let out = child.stdout.take().expect("stdout");
        let err = child.stderr.take().expect("stderr");
        let tx2 = tx.clone();
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines().map_while(Result::ok) {
                let _ = tx.send(l);
            }
        });
        std::thread::spawn(move || {
            for l in BufReader::new(err).lines().map_while(Result::ok) {
                let _ = tx2.send(l);
            }
        });
        FastDds {
            child,
            lines,
            seen: Vec::new(),
        }
    }

    /// Takes the lines printed so far.
    fn poll(&mut self) {
        while let Ok(l) = self.lines.try_recv() {
            self.seen.push(l);
        }
    }

    /// Runs `pump` until a line contains `needle` (true) or `d` passes (false).
    fn wait_for(&mut self, needle: &str, d: Duration, mut pump: impl FnMut()) -> bool {
        let end = Instant::now() + d;
        while Instant::now() < end {
            self.poll();
            if self.seen.iter().any(|l| l.contains(needle)) {
                return true;
            }
            pump();
        }
        false
    }

    /// Runs `pump` until the program exits; its exit code (None: still running after `d`,
    /// then killed).
    fn wait(&mut self, d: Duration, mut pump: impl FnMut()) -> Option<i32> {
        let end = Instant::now() + d;
        while Instant::now() < end {
            if let Ok(Some(status)) = self.child.try_wait() {
                std::thread::sleep(Duration::from_millis(50));
                self.poll();
                return status.code();
            }
            pump();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        self.poll();
        None
    }

    /// What it printed, for a failure message.
    fn transcript(&self) -> String {
        self.seen.join("\n")
    }
}

impl Drop for FastDds {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn a_client_publishes_and_fast_dds_reads_every_sample() {
    let agent = AgentProcess::builder("fastdds-pub").start();
    let mut reader = FastDds::start("hello_sub", &["-d", "91", "-n", "30", "-t", "90"]);
    let mut c = TestClient::new(agent.addr(), [0xFA, 0x57, 0xDD, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(91);
    assert!(
        reader.wait_for("subscription matched: current_count=1", 30 * SECOND, || c
            .step()),
        "Fast DDS never matched the agent's writer:\n{}",
        reader.transcript()
    );
    for i in 0..30 {
        c.write_reliable(w, &hello_world(i, "Hello DDS world!"));
    }
    let code = reader.wait(60 * SECOND, || c.step());
    let mut got = Deliveries::default();
    for l in &reader.seen {
        let Some(rest) = l.strip_prefix("index=") else {
            continue;
        };
        let (index, message) = rest.split_once(" message=").expect("a sample line");
        assert_eq!(message, "Hello DDS world!", "{l}");
        got.record(index.parse().expect("an index"));
    }
    assert_eq!(
        code,
        Some(0),
        "Fast DDS got only part:\n{}",
        reader.transcript()
    );
    got.assert_exactly_once(0..30, "Fast DDS reading a client");
    got.assert_in_order("Fast DDS reading a client");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn fast_dds_publishes_and_a_client_reads_every_sample() {
    let agent = AgentProcess::builder("fastdds-sub").start();
    let mut c = TestClient::new(agent.addr(), [0xFA, 0x57, 0xDD, 0x02]);
    c.connect(10 * SECOND);
    c.setup_subscriber(92);
    // It waits for a matched reader (10 s at most), writes 20 samples 100 ms apart, then
    // waits for their acknowledgement.
    let mut writer = FastDds::start("hello_pub", &["-d", "92", "-n", "20"]);
    let got = c.collect_deliveries(20, "Hello DDS world!", 60 * SECOND);
    got.assert_exactly_once(1..21, "a client reading Fast DDS");
    got.assert_in_order("a client reading Fast DDS");
    assert_eq!(
        writer.wait(30 * SECOND, || c.step()),
        Some(0),
        "{}",
        writer.transcript()
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// The service side with an independent DDS: an XRCE requester and Fast DDS replying as
/// eProsima's agent does (the reply carries the request's SampleIdentity as its related
/// sample identity). Each request reaches Fast DDS once and each reply the requester once,
/// matched to its request.
#[test]
fn an_xrce_requester_gets_each_reply_of_a_fast_dds_replier_once() {
    let agent = AgentProcess::builder("fastdds-rpc").start();
    let mut replier = FastDds::start("adder_replier", &["-d", "93", "-n", "100000", "-t", "90"]);
    // Its participant holds its ports before the agent makes one in the domain: two
    // implementations picking participant ids at once can both take id 0, and then one
    // never hears the other's unicast discovery (seen once: requests matched at Fast DDS,
    // none delivered in 30 s).
    let serving = replier.wait_for("[replier] serving", 30 * SECOND, || {
        std::thread::sleep(Duration::from_millis(10))
    });
    assert!(
        serving,
        "the replier did not start:\n{}",
        replier.transcript()
    );
    let mut c = TestClient::new(agent.addr(), [0xFA, 0x57, 0xDD, 0x03]);
    c.connect(10 * SECOND);
    let req = c.setup_adder(93, object_kind::REQUESTER);
    // Requests are volatile: probe until a reply shows both directions matched.
    let mut answered: HashMap<RequestId, Vec<u32>> = HashMap::new();
    let mut probes: HashMap<RequestId, u32> = HashMap::new();
    let end = Instant::now() + 30 * SECOND;
    while answered.is_empty() && Instant::now() < end {
        probes.insert(c.write_reliable_id(req, &adder_request(100, 1)), 101);
        let until = Instant::now() + Duration::from_millis(200);
        while Instant::now() < until {
            c.step();
            c.take_adder_replies(req, &mut answered);
        }
    }
    replier.poll();
    assert!(
        !answered.is_empty(),
        "no reply from Fast DDS within 30 s:\n{}",
        replier.transcript()
    );
    let mut expected = HashMap::new();
    for i in 0..10u32 {
        expected.insert(c.write_reliable_id(req, &adder_request(i, 1000)), i + 1000);
    }
    let end = Instant::now() + 30 * SECOND;
    while expected.keys().any(|id| !answered.contains_key(id)) && Instant::now() < end {
        c.step();
        c.take_adder_replies(req, &mut answered);
    }
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        c.step();
        c.take_adder_replies(req, &mut answered);
    }
    replier.poll();
    for (id, sum) in &expected {
        assert_eq!(
            answered.get(id).map(Vec::as_slice),
            Some(&[*sum][..]),
            "replies to request {id:?} (exactly one expected):\n{}",
            replier.transcript()
        );
    }
    for (id, sums) in &answered {
        let asked = expected.get(id).or(probes.get(id));
        assert!(
            asked.is_some() && sums.len() == 1 && Some(&sums[0]) == asked,
            "replies {sums:?} to request {id:?}, which asked {asked:?}"
        );
    }
    // Fast DDS took each of the ten requests once.
    for i in 0..10u32 {
        let line = format!(" a={i} b=1000");
        let n = replier.seen.iter().filter(|l| l.ends_with(&line)).count();
        assert_eq!(
            n,
            1,
            "Fast DDS got request {i} {n} times:\n{}",
            replier.transcript()
        );
    }
    assert!(agent.stop(), "agent did not stop cleanly");
}
