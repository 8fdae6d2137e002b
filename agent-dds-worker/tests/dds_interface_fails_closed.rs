//! `--dds-interface` fails closed (issue 29 item 7): a worker told to keep DDS to an address
//! that no interface of this host has cannot confine DDS to it, so it refuses to start,
//! saying why, with either DDS backend, instead of running DDS on every interface.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// TEST-NET-2 (RFC 5737): documentation only, on no host's interface.
const NOT_HERE: &str = "198.51.100.77";

/// Runs the worker binary with `args`; its exit status and standard error, or None if it
/// was still running after 30 s (then it was killed).
fn run_worker(args: &[&str]) -> Option<(std::process::ExitStatus, String)> {
    let instance = format!("failclosed{}", std::process::id());
    let mut child = Command::new(env!("CARGO_BIN_EXE_xrce-dds-worker"))
        .args(args)
        .args(["--instance", &instance])
        .env_remove("XRCE_DDS_INTERFACES")
        .env_remove("XRCE_DDS_BACKEND")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the worker binary starts");
    let deadline = Instant::now() + Duration::from_secs(30);
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait") {
            break Some(s);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }?;
    let mut stderr = String::new();
    if let Some(mut e) = child.stderr.take() {
        use std::io::Read;
        let _ = e.read_to_string(&mut stderr);
    }
    Some((status, stderr))
}

#[test]
fn the_worker_refuses_to_start_when_dds_cannot_be_confined() {
    let mut backends = vec!["rustdds"];
    if cfg!(feature = "cyclone") {
        backends.push("cyclone");
    }
    for backend in backends {
        let (status, stderr) = run_worker(&["--dds-interface", NOT_HERE, "--dds-backend", backend])
            .unwrap_or_else(|| panic!("{backend}: the worker ran on instead of refusing"));
        assert!(!status.success(), "{backend}: exit status {status}");
        assert!(
            stderr.contains("cannot confine DDS")
                && stderr.contains(NOT_HERE)
                && stderr.contains("no interface of this host has this address"),
            "{backend}: the reason is told: {stderr}"
        );
    }
}

#[test]
fn a_malformed_domain_list_is_refused_at_start() {
    let (status, stderr) = run_worker(&["--domains", "0-300"]).expect("it exits");
    assert!(!status.success());
    assert!(stderr.contains("out of range"), "{stderr}");
    let (status, _) = run_worker(&["--max-domains", "0"]).expect("it exits");
    assert!(!status.success());
}
