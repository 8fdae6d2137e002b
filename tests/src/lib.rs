//! End-to-end test harness: real agent processes on loopback, a Rust XRCE client built on
//! `xrce_common`'s client state machine, and Cyclone DDS (Python, pinned) as the independent
//! DDS peer. Everything stays on 127.0.0.1: the agent's DDS is pinned with
//! `--dds-interface 127.0.0.1`, Cyclone with `python/cyclonedds-loopback.xml`.

use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::OnceLock;

mod agent_process;
mod client;
mod dds_peer;
pub mod domains;
pub mod impaired;
pub mod link;
pub mod scenarios;
pub use agent_process::*;
pub use client::*;
pub use dds_peer::*;
pub use link::{Link, PtyPair, SharedLine};
use xrce_common::wire::{stream_id, DataDeliveryControl, ReadSpecification};

/// The Cyclone DDS release the tests pin.
pub const CYCLONEDDS_VERSION: &str = "11.0.1";
/// The independent Zenoh peer's version (PyPI `eclipse-zenoh`; rmw_zenoh 0.2.10/0.6.7 vendor
/// Zenoh 1.8.0, which PyPI has no wheel of: 1.7.2 speaks the same protocol).
pub const ZENOH_PYTHON_VERSION: &str = "1.7.2";

/// The workspace root.
pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace")
        .to_path_buf()
}

/// The target directory the tests run from (…/target).
fn target_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("CARGO_TARGET_DIR") {
        return PathBuf::from(d);
    }
    workspace().join("target")
}

/// The DDS backend the agents under test use (`XRCE_DDS_BACKEND`, default `cyclone`, the
/// agent's own default).
pub fn dds_backend() -> String {
    std::env::var("XRCE_DDS_BACKEND").unwrap_or_else(|_| "cyclone".into())
}

/// Makes sure the agent's binaries are built, once per test process; returns their directory.
///
/// They are those `cargo test --workspace` builds (the command README.md gives): the same
/// invocation again is a no-op after it, and builds them for a test run some other way
/// (`cargo test -p xrce-tests`). Built with the faults tests/fault-check.sh injects (the
/// dev-dependencies of this crate turn the feature on) and both DDS backends;
/// XRCE_DDS_BACKEND=rustdds runs the suite against RustDDS (the agents inherit the variable).
/// With XRCE_TEST_RELEASE set, release builds are made and used instead (benchmarks); with
/// XRCE_TEST_BINARIES set to a directory, the binaries there are used as they are (an older
/// build, to show that a new test fails against it).
pub fn binaries() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        if let Some(dir) = std::env::var_os("XRCE_TEST_BINARIES").filter(|d| !d.is_empty()) {
            return PathBuf::from(dir);
        }
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let release = std::env::var("XRCE_TEST_RELEASE").is_ok();
        let mut cmd = Command::new(cargo);
        cmd.current_dir(workspace());
        // What cargo sets for this test process (CARGO_MANIFEST_DIR, CARGO_PKG_*, …) is not
        // the environment it built the workspace in: `ring`'s build script reruns when
        // CARGO_MANIFEST_DIR changes, so passing them on rebuilt ring, rustls, Zenoh and the
        // agent (about two minutes on 2 cores) in the first test binary of each crate, and
        // again in the next `cargo` CI ran.
        for (key, _) in std::env::vars_os() {
            if key.to_str().is_some_and(set_by_cargo_for_a_test) {
                cmd.env_remove(&key);
            }
        }
        if release {
            cmd.args([
                "build",
                "--release",
                "--bins",
                "-p",
                "xrce-agent",
                "-p",
                "xrce-frontend",
                "-p",
                "xrce-dds-worker",
                "--features",
                "xrce-agent/fault-injection,xrce-frontend/fault-injection,xrce-dds-worker/fault-injection",
            ]);
        } else {
            cmd.args(["test", "--workspace", "--no-run", "--quiet"]);
        }
        let st = cmd.status().expect("run cargo");
        assert!(st.success(), "building the agent binaries failed");
        target_dir().join(if release { "release" } else { "debug" })
    })
}

/// The name libtest knows the test `test` of the module `module` by (`module_path!()` in the
/// test's file: its first segment, the test binary's crate, is not part of the name), for a
/// test that runs itself again in another namespace with `--exact`.
pub fn libtest_name(module: &str, test: &str) -> String {
    match module.split_once("::") {
        Some((_, path)) => format!("{path}::{test}"),
        None => test.to_string(),
    }
}

/// Whether `key` is one of the variables cargo sets for the test binary it runs, which a
/// `cargo` started from the test must not inherit.
fn set_by_cargo_for_a_test(key: &str) -> bool {
    const EXACT: [&str; 7] = [
        "CARGO_MANIFEST_DIR",
        "CARGO_MANIFEST_PATH",
        "CARGO_MANIFEST_LINKS",
        "CARGO_CRATE_NAME",
        "CARGO_PRIMARY_PACKAGE",
        "CARGO_TARGET_TMPDIR",
        "OUT_DIR",
    ];
    EXACT.contains(&key) || key.starts_with("CARGO_PKG_") || key.starts_with("CARGO_BIN_EXE_")
}

/// The address and port named by `-p PORT` / `--bind ADDR` in an agent command line
/// (loopback and 0 when absent).
fn ip_and_port(args: &[impl AsRef<str>]) -> (std::net::IpAddr, u16) {
    let mut ip: std::net::IpAddr = [127, 0, 0, 1].into();
    let mut port = 0;
    for w in args.windows(2) {
        match w[0].as_ref() {
            "-p" | "--port" => port = w[1].as_ref().parse().unwrap_or(0),
            "--bind" => ip = w[1].as_ref().parse().unwrap_or(ip),
            _ => {}
        }
    }
    (ip, port)
}

/// A port free for both TCP and UDP on 127.0.0.1, below every DDS port (RTPS puts domain
/// `d` at 7400 + 250 d and up) and so below the kernel's ephemeral range too.
///
/// A port the kernel hands out for `bind(0)` would be fine but for two things: between the
/// test learning it and the agent binding it, any client socket of any test running in
/// parallel (the load generator opens hundreds) may be given the same ephemeral port; and a
/// port of the DDS range may be the one a DDS participant of another test's domain wants
/// next. Ports from 2000 to 7399 are neither, so only another test choosing the same one
/// could race, and the candidates are spread by process id and a counter.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let (low, high) = (FREE_PORTS.start, FREE_PORTS.end);
    let span = high - low;
    let seed = std::process::id().wrapping_mul(2_654_435_761);
    for _ in 0..span {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let port = (low + seed.wrapping_add(n.wrapping_mul(7919)) % span) as u16;
        let udp = UdpSocket::bind(("127.0.0.1", port));
        let tcp = std::net::TcpListener::bind(("127.0.0.1", port));
        if udp.is_ok() && tcp.is_ok() {
            return port;
        }
    }
    panic!("no free port in {FREE_PORTS:?}")
}

/// Where [`free_port`] looks: above the well-known ports, below RTPS's first (7400).
pub const FREE_PORTS: std::ops::Range<u32> = 2_000..7_400;

/// A free TCP port on 127.0.0.1 (see [`free_port`]).
pub fn free_tcp_port() -> u16 {
    free_port()
}

/// A free UDP port on 127.0.0.1 (see [`free_port`]).
pub fn free_udp_port() -> u16 {
    free_port()
}

/// A unique instance name for this test process.
pub fn unique_instance(tag: &str) -> String {
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "t{}-{}-{}",
        std::process::id() % 100_000,
        tag,
        N.fetch_add(1, Ordering::Relaxed)
    )
}

/// The HelloWorld sample of the eProsima examples: `unsigned long index; string message;`
/// in little-endian CDR.
pub fn hello_world(index: u32, message: &str) -> Vec<u8> {
    let mut v = index.to_le_bytes().to_vec();
    v.extend_from_slice(&(message.len() as u32 + 1).to_le_bytes());
    v.extend_from_slice(message.as_bytes());
    v.push(0);
    v
}

/// The HelloWorld sample in big-endian CDR (what a big-endian microcontroller writes).
pub fn hello_world_be(index: u32, message: &str) -> Vec<u8> {
    let mut v = index.to_be_bytes().to_vec();
    v.extend_from_slice(&(message.len() as u32 + 1).to_be_bytes());
    v.extend_from_slice(message.as_bytes());
    v.push(0);
    v
}

/// Decodes a HelloWorld sample (little-endian CDR).
pub fn parse_hello_world(b: &[u8]) -> Option<(u32, String)> {
    let index = u32::from_le_bytes(b.get(0..4)?.try_into().ok()?);
    let len = u32::from_le_bytes(b.get(4..8)?.try_into().ok()?) as usize;
    let s = b.get(8..8 + len.checked_sub(1)?)?;
    Some((index, String::from_utf8(s.to_vec()).ok()?))
}

/// XML of the reference client's HelloWorld examples.
pub mod xml {
    /// Participant.
    pub const PARTICIPANT: &str =
        "<dds><participant><rtps><name>default_xrce_participant</name></rtps></participant></dds>";
    /// Topic.
    pub const TOPIC: &str =
        "<dds><topic><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic></dds>";
    /// Data writer.
    pub const WRITER: &str = "<dds><data_writer><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic></data_writer></dds>";
    /// Data reader (reliable, so the tests can demand every sample).
    pub const READER: &str = "<dds><data_reader><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name><dataType>HelloWorld</dataType></topic><qos><reliability><kind>RELIABLE</kind></reliability></qos></data_reader></dds>";
    /// The adder service (requests `{a, b}` on `rq/addRequest`, replies `{sum}` on
    /// `rr/addReply`) as a requester or replier: `{e}` is `requester` or `replier`.
    pub const ADDER_SERVICE: &str = "<dds><{e} profile_name=\"adder\" service_name=\"/add\" \
        request_type=\"AddRequest\" reply_type=\"AddReply\">\
        <request_topic_name>rq/addRequest</request_topic_name>\
        <reply_topic_name>rr/addReply</reply_topic_name></{e}></dds>";
}

/// An adder request (`a`, `b`, little endian) as a requester writes it.
pub fn adder_request(a: u32, b: u32) -> Vec<u8> {
    [a.to_le_bytes(), b.to_le_bytes()].concat()
}

/// An unlimited READ_DATA on the built-in reliable stream, samples as plain data.
pub fn unlimited_reliable_read() -> ReadSpecification {
    ReadSpecification {
        preferred_stream_id: stream_id::BUILTIN_RELIABLE,
        data_format: 0,
        delivery_control: Some(DataDeliveryControl {
            max_samples: u16::MAX,
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// Resident memory of process `pid`, in KiB (0 if it cannot be read).
pub fn rss_kib(pid: i32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.split_whitespace().next()?.parse().ok())
        })
        .unwrap_or(0)
}
