//! What the load generator's test binaries share.

use std::process::Command;

/// Runs `xrce-loadgen` (which starts our agent) with `args` plus a free port and a JSON
/// report; returns the report and the generator's stdout.
pub fn run_loadgen(name: &str, args: &[&str]) -> (serde_json::Value, String) {
    let json = std::env::temp_dir().join(format!("loadgen-{name}-{}.json", std::process::id()));
    // The generator starts the `xrce-agent` next to it: built now from the sources under
    // test (a no-op when current), as the end-to-end tests build it, not whatever binary an
    // earlier build left there.
    let loadgen = std::path::Path::new(env!("CARGO_BIN_EXE_xrce-loadgen"));
    let built = xrce_tests::binaries();
    assert_eq!(
        loadgen.parent(),
        Some(built),
        "xrce-loadgen and the agent it starts are in one folder"
    );
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
