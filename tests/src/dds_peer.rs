//! The independent DDS peer: Cyclone DDS from PyPI (pinned) in a virtual environment, as a
//! process whose samples the tests read, and what was delivered to it.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::mpsc;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use crate::*;

/// A Python virtual environment under `target/` with one pinned PyPI package, created (or
/// repaired) once per test process; returns its interpreter.
fn python_venv(dir: &str, package: &str, version: &str, module: &str) -> PathBuf {
    let venv = target_dir().join(dir);
    let py = venv.join("bin/python");
    let lock = std::fs::File::create(target_dir().join(format!("{dir}.lock"))).expect("lock file");
    let _guard = nix::fcntl::Flock::lock(lock, nix::fcntl::FlockArg::LockExclusive).expect("flock");
    let ready = Command::new(&py)
        .args(["-c", &format!("import {module}, importlib.metadata as m; assert m.version('{package}') == '{version}'")])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ready {
        let st = Command::new("python3")
            .args(["-m", "venv"])
            .arg(&venv)
            .status()
            .expect("python3 -m venv");
        assert!(st.success(), "creating the venv failed");
        let st = Command::new(venv.join("bin/pip"))
            .args([
                "install",
                "--quiet",
                "--only-binary=:all:",
                &format!("{package}=={version}"),
            ])
            .status()
            .expect("pip install");
        assert!(st.success(), "installing {package} {version} failed");
    }
    py
}

/// The Python virtual environment with Cyclone DDS, created once under `target/`.
pub fn cyclone_python() -> PathBuf {
    static PY: OnceLock<PathBuf> = OnceLock::new();
    PY.get_or_init(|| {
        python_venv(
            "cyclonedds-venv",
            "cyclonedds",
            CYCLONEDDS_VERSION,
            "cyclonedds",
        )
    })
    .clone()
}

/// The Python virtual environment with Zenoh (`eclipse-zenoh`), created once under `target/`.
pub fn zenoh_python() -> PathBuf {
    static PY: OnceLock<PathBuf> = OnceLock::new();
    PY.get_or_init(|| python_venv("zenoh-venv", "eclipse-zenoh", ZENOH_PYTHON_VERSION, "zenoh"))
        .clone()
}

/// A running `dds_peer.py` (Cyclone DDS) process with its stdout lines on a channel.
#[derive(Debug)]
pub struct DdsPeer {
    child: Child,
    lines: mpsc::Receiver<String>,
    /// Lines [`wait_for_keeping`](DdsPeer::wait_for_keeping) passed over, read first.
    kept: RefCell<VecDeque<String>>,
}

impl DdsPeer {
    /// Starts `dds_peer.py <args>` pinned to loopback.
    /// Claims its domain for the running test's module ([`crate::domains`]).
    pub fn start(args: &[&str]) -> Self {
        crate::domains::claim(crate::domains::of_peer_arguments(args));
        let xml = workspace().join("tests/python/cyclonedds-loopback.xml");
        let mut command = Command::new(cyclone_python());
        command
            .arg(workspace().join("tests/python/dds_peer.py"))
            .args(args)
            .env("CYCLONEDDS_URI", format!("file://{}", xml.display()));
        Self::spawn(command)
    }

    /// Starts `zenoh_peer.py <args>` (an independent Zenoh peer; its endpoints are loopback
    /// ones, which the script checks).
    pub fn zenoh(args: &[&str]) -> Self {
        let mut command = Command::new(zenoh_python());
        command
            .arg(workspace().join("tests/python/zenoh_peer.py"))
            .args(args);
        Self::spawn(command)
    }

    /// Starts `zenoh_peer.py <args>` in the network namespace `netns` (`ip netns exec`).
    pub fn zenoh_in(netns: &str, args: &[&str]) -> Self {
        let mut command = Command::new("ip");
        command
            .args(["netns", "exec", netns])
            .arg(zenoh_python())
            .arg(workspace().join("tests/python/zenoh_peer.py"))
            .args(args);
        Self::spawn(command)
    }

    /// Runs `command`, its stdout lines on the channel (stdin piped: a peer that waits for
    /// it to close ends with the test).
    fn spawn(mut command: Command) -> Self {
        let mut child = command
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("start a peer");
        let stdout: ChildStdout = child.stdout.take().expect("stdout");
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        DdsPeer {
            child,
            lines,
            kept: RefCell::default(),
        }
    }

    /// The next output line, waiting up to `d`.
    pub fn line(&self, d: Duration) -> Option<String> {
        if let Some(l) = self.kept.borrow_mut().pop_front() {
            return Some(l);
        }
        self.lines.recv_timeout(d).ok()
    }

    /// Waits for a line starting with `prefix`, while `pump` keeps other parties running.
    pub fn wait_for(&self, prefix: &str, d: Duration, pump: impl FnMut()) -> Option<String> {
        self.wait_for_line(prefix, d, pump, false)
    }

    /// As [`wait_for`](DdsPeer::wait_for), but the lines before the one found are kept for
    /// [`line`](DdsPeer::line) and [`drain_lines`](DdsPeer::drain_lines): for a peer whose
    /// callbacks may print data before it says READY (a Zenoh transient-local subscription
    /// gets the publishers' history while it is being declared).
    pub fn wait_for_keeping(
        &self,
        prefix: &str,
        d: Duration,
        pump: impl FnMut(),
    ) -> Option<String> {
        self.wait_for_line(prefix, d, pump, true)
    }

    fn wait_for_line(
        &self,
        prefix: &str,
        d: Duration,
        mut pump: impl FnMut(),
        keep: bool,
    ) -> Option<String> {
        // Lines an earlier `wait_for_keeping` passed over come first.
        let mut passed = VecDeque::new();
        loop {
            let Some(l) = self.kept.borrow_mut().pop_front() else {
                break;
            };
            if l.starts_with(prefix) {
                if keep {
                    let mut kept = self.kept.borrow_mut();
                    while let Some(p) = passed.pop_back() {
                        kept.push_front(p);
                    }
                }
                return Some(l);
            }
            passed.push_back(l);
        }
        if keep {
            *self.kept.borrow_mut() = passed;
        }
        let end = Instant::now() + d;
        while Instant::now() < end {
            pump();
            if let Ok(l) = self.lines.recv_timeout(Duration::from_millis(2)) {
                if l.starts_with(prefix) {
                    return Some(l);
                }
                if keep {
                    self.kept.borrow_mut().push_back(l);
                }
            }
        }
        None
    }

    /// Waits for the process to end; returns its exit code.
    pub fn wait(&mut self, d: Duration, mut pump: impl FnMut()) -> Option<i32> {
        let end = Instant::now() + d;
        while Instant::now() < end {
            pump();
            if let Ok(Some(s)) = self.child.try_wait() {
                return s.code();
            }
        }
        None
    }

    /// All lines received so far.
    pub fn drain_lines(&self) -> Vec<String> {
        let mut all: Vec<String> = self.kept.borrow_mut().drain(..).collect();
        all.extend(self.lines.try_iter());
        all
    }
}

impl Drop for DdsPeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Parses a `{"index": i, "message": "..."}` line from the peer.
pub fn parse_sample_line(l: &str) -> Option<(u32, String)> {
    let v: serde_json::Value = serde_json::from_str(l).ok()?;
    let index = u32::try_from(v.get("index")?.as_u64()?).ok()?;
    Some((index, v.get("message")?.as_str()?.to_string()))
}

/// Parses a sample line's index and the DDS writer it came from (Cyclone's publication
/// handle: one per remote writer).
pub fn parse_sample_writer(l: &str) -> Option<(u32, u64)> {
    let v: serde_json::Value = serde_json::from_str(l).ok()?;
    let index = u32::try_from(v.get("index")?.as_u64()?).ok()?;
    Some((index, v.get("writer")?.as_u64()?))
}

/// Every delivery of a HelloWorld sample, by index and in arrival order, so that a sample
/// delivered twice is as visible as one never delivered.
#[derive(Debug, Clone, Default)]
pub struct Deliveries {
    counts: std::collections::BTreeMap<u32, usize>,
    order: Vec<u32>,
}

impl Deliveries {
    /// Records one delivery.
    pub fn record(&mut self, index: u32) {
        *self.counts.entry(index).or_default() += 1;
        self.order.push(index);
    }

    /// Distinct indices delivered.
    pub fn distinct(&self) -> usize {
        self.counts.len()
    }

    /// Deliveries in all, duplicates included.
    pub fn total(&self) -> usize {
        self.order.len()
    }

    /// Deliveries recorded so far, duplicates included (a mark for [`Deliveries::order_from`]).
    pub fn order_len(&self) -> usize {
        self.order.len()
    }

    /// The indices delivered since `mark` (an earlier [`Deliveries::order_len`]), in order.
    pub fn order_from(&self, mark: usize) -> Vec<u32> {
        self.order.get(mark..).unwrap_or_default().to_vec()
    }

    /// The index delivered last (0 if none).
    pub fn order_last(&self) -> u32 {
        self.order.last().copied().unwrap_or(0)
    }

    /// How often `index` was delivered.
    pub fn count(&self, index: u32) -> usize {
        self.counts.get(&index).copied().unwrap_or(0)
    }

    /// The indices delivered more than once, with their counts.
    pub fn repeated(&self) -> Vec<(u32, usize)> {
        self.counts
            .iter()
            .filter(|(_, n)| **n > 1)
            .map(|(i, n)| (*i, *n))
            .collect()
    }

    /// Asserts that every index of `expected` arrived exactly once and nothing else did.
    pub fn assert_exactly_once(&self, expected: impl IntoIterator<Item = u32>, what: &str) {
        let expected: std::collections::BTreeSet<u32> = expected.into_iter().collect();
        let missing: Vec<u32> = expected
            .iter()
            .copied()
            .filter(|i| !self.counts.contains_key(i))
            .collect();
        let repeated: Vec<(u32, usize)> = self
            .counts
            .iter()
            .filter(|(_, n)| **n > 1)
            .map(|(i, n)| (*i, *n))
            .collect();
        let unexpected: Vec<u32> = self
            .counts
            .keys()
            .copied()
            .filter(|i| !expected.contains(i))
            .collect();
        assert!(
            missing.is_empty() && repeated.is_empty() && unexpected.is_empty(),
            "{what}: missing {missing:?}, delivered more than once {repeated:?}, unexpected {unexpected:?}"
        );
    }

    /// Records the HelloWorld samples `reader` printed so far, each of which must say
    /// `message`.
    pub fn collect_from(&mut self, reader: &DdsPeer, message: &str) {
        while let Some(l) = reader.line(Duration::ZERO) {
            if let Some((i, m)) = parse_sample_line(&l) {
                assert_eq!(m, message);
                self.record(i);
            }
        }
    }

    /// Asserts what a crash of the process holding a DDS writer may do to `0..n` written
    /// about 100 a second with the crash at `crash_at`: nothing lost; at most 20 samples
    /// (200 ms of writes on a loaded machine) twice, written shortly before the crash: what
    /// DDS readers had not acknowledged is sent again by the new writer, whose copies are new
    /// samples to readers.
    pub fn assert_none_lost_repeats_near(&self, n: u32, crash_at: u32, what: &str) {
        let repeated = self.repeated();
        eprintln!(
            "{what}: {} of {n} delivered, {} duplicates (samples {:?} to {:?})",
            self.distinct(),
            self.total() - self.distinct(),
            repeated.first().map(|r| r.0),
            repeated.last().map(|r| r.0),
        );
        let missing: Vec<u32> = (0..n).filter(|i| self.count(*i) == 0).collect();
        assert!(missing.is_empty(), "{what}: samples lost: {missing:?}");
        assert!(
            repeated.len() <= 20,
            "{what}: {} samples repeated",
            repeated.len()
        );
        for (i, times) in repeated {
            assert!(times <= 2, "{what}: sample {i} delivered {times} times");
            assert!(
                (crash_at.saturating_sub(20)..crash_at + 5).contains(&i),
                "{what}: sample {i}, far from the crash at {crash_at}, delivered twice"
            );
        }
    }

    /// Asserts that the deliveries came in increasing index order (what a reliable stream
    /// from one writer promises).
    pub fn assert_in_order(&self, what: &str) {
        let inversions: Vec<(u32, u32)> = self
            .order
            .windows(2)
            .filter(|w| w[1] <= w[0])
            .map(|w| (w[0], w[1]))
            .collect();
        assert!(
            inversions.is_empty(),
            "{what}: out of order: {inversions:?}"
        );
    }
}

impl Deliveries {
    /// Runs `pump` (which returns the indices delivered in that round) until `want`
    /// distinct ones arrived and [`DUPLICATE_GRACE`] passed, or `d` passed.
    pub fn collect(want: usize, d: Duration, mut pump: impl FnMut() -> Vec<u32>) -> Self {
        let mut got = Deliveries::default();
        let end = Instant::now() + d;
        let mut complete_at: Option<Instant> = None;
        while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
            for i in pump() {
                got.record(i);
            }
            if complete_at.is_none() && got.distinct() >= want {
                complete_at = Some(Instant::now());
            }
        }
        got
    }
}

/// How long collections keep listening after the last expected sample, so that a duplicate
/// arriving just after it is seen too.
pub const DUPLICATE_GRACE: Duration = Duration::from_millis(500);

impl DdsPeer {
    /// Records the HelloWorld samples a `read` peer prints (checking each message is
    /// `message`) until `want` distinct ones arrived and [`DUPLICATE_GRACE`] passed, or `d`
    /// passed, while `pump` keeps other parties running.
    pub fn collect_deliveries(
        &self,
        want: usize,
        message: &str,
        d: Duration,
        mut pump: impl FnMut(),
    ) -> Deliveries {
        let mut got = Deliveries::default();
        let end = Instant::now() + d;
        let mut complete_at: Option<Instant> = None;
        while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
            pump();
            while let Some(l) = self.line(Duration::from_millis(1)) {
                if let Some((i, m)) = parse_sample_line(&l) {
                    assert_eq!(m, message, "sample {i} carries another message");
                    got.record(i);
                }
            }
            if complete_at.is_none() && got.distinct() >= want {
                complete_at = Some(Instant::now());
            }
        }
        got
    }
}
