//! The kill soak's short version in CI (its own test binary, so that no other load runs
//! beside it): the load generator SIGKILLs the worker and the front-end under paced
//! reliable load and accounts for every kill. The long version and its numbers are in
//! BENCHMARKS.md.

use std::process::Command;

/// Runs `xrce-loadgen` (which starts our agent) with `args` plus a free port and a JSON
/// report; returns the report and the generator's stdout.
fn run_loadgen(name: &str, args: &[&str]) -> (serde_json::Value, String) {
    let json = std::env::temp_dir().join(format!("loadgen-{name}-{}.json", std::process::id()));
    // The generator starts the `xrce-agent` next to it; build it if this run did not.
    let loadgen = std::path::Path::new(env!("CARGO_BIN_EXE_xrce-loadgen"));
    if !loadgen.with_file_name("xrce-agent").exists() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let ok = Command::new(cargo)
            .args(["build", "-p", "xrce-agent", "--bin", "xrce-agent"])
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "building xrce-agent failed");
    }
    // A port found free may still be taken before the agent binds it (by another test):
    // then the agent cannot start and another port is tried.
    let mut out = None;
    for _ in 0..3 {
        let port = xrce_tests::free_port();
        let o = Command::new(loadgen)
            .args(["--port", &port.to_string(), "--duration", "60", "--json"])
            .arg(&json)
            .args(args)
            .output()
            .expect("run xrce-loadgen");
        let retry = !o.status.success()
            && String::from_utf8_lossy(&o.stderr).contains("Address already in use");
        out = Some(o);
        if !retry {
            break;
        }
    }
    let out = out.expect("ran");
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "xrce-loadgen failed: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(&json).expect("JSON report written");
    let _ = std::fs::remove_file(&json);
    (serde_json::from_str(&text).expect("valid JSON"), stdout)
}

/// The kill soak, short: the worker and the front-end SIGKILLed twice each under paced
/// reliable load; the agent recovers from every kill, and nothing comes out of order.
/// A front-end's successor takes its sessions over: DDS gets every sample once; the
/// subscribing client gets nothing twice but may miss the few samples the worker had
/// already taken for it when its front-end died (measured: 0 or 1 of the 500 around a
/// kill; issue 11). A new worker loses nothing, but gets again the reliable writes the
/// front-end retained for 1.5 s (issue 11: a retained write is released after a fixed
/// time, not when DDS readers acknowledged it), so repeats are bounded by that window.
#[test]
fn a_short_kill_soak_recovers_from_every_kill() {
    let rate = 200.0;
    let (v, stdout) = run_loadgen(
        "soak",
        &[
            "--publishers",
            "10",
            "--subscribers",
            "1",
            "--samples",
            "2400",
            "--rate",
            "200",
            "--kills",
            "4",
            "--kill",
            "alternate",
            "--kill-every",
            "2.5",
            "--domain",
            "84",
        ],
    );
    let kills = v["soak"]["kills"].as_array().cloned().unwrap_or_default();
    assert_eq!(kills.len(), 4, "{stdout}");
    for k in &kills {
        assert!(
            k["recovery_ms"].is_number(),
            "a kill never recovered from: {stdout}"
        );
        assert_eq!(k["reordered"], 0, "{stdout}");
        match k["target"].as_str() {
            Some("frontend") => {
                assert_eq!(k["duplicated"], 0, "{stdout}");
                assert!(k["lost"].as_u64().is_some_and(|n| n <= 5), "{stdout}");
            }
            Some("worker") => {
                assert_eq!(k["lost"], 0, "{stdout}");
                assert!(
                    k["duplicated"].as_f64().is_some_and(|d| d <= 2.0 * rate),
                    "{stdout}"
                );
            }
            other => panic!("unexpected target {other:?}"),
        }
    }
    assert_eq!(
        v["soak"]["outside"],
        serde_json::json!([0, 0, 0]),
        "{stdout}"
    );
    // Into DDS nothing is lost across either kind of kill.
    assert_eq!(v["dds"]["lost"], 0, "{stdout}");
}
