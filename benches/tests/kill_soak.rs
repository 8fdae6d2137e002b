//! The kill soak's short version in CI (its own test binary, so that no other load runs
//! beside it): the load generator SIGKILLs the worker and the front-end under paced
//! reliable load and accounts for every kill. The long version and its numbers are in
//! docs/benchmarks/history.md.

mod common;

use common::run_loadgen;

/// The kill soak, short: the worker and the front-end SIGKILLed twice each under paced
/// reliable load; the agent recovers from every kill, and nothing comes out of order.
/// A front-end's successor takes its sessions over: DDS and the subscribing client get
/// every sample once (the worker hands the successor again what it had taken for the dead
/// front-end, which drops what its predecessor had delivered; frontend_restart checks the
/// same one kill at a time). A new worker loses nothing and repeats only the writes DDS readers had
/// not acknowledged when the worker died (the front-end keeps a write until they did):
/// readers acknowledge within milliseconds here (0 or 1 repeat per kill measured in this
/// debug build), so the bound, a quarter of a second of writes, leaves room for a loaded
/// machine.
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
                assert_eq!(k["lost"], 0, "{stdout}");
            }
            Some("worker") => {
                assert_eq!(k["lost"], 0, "{stdout}");
                assert!(
                    k["duplicated"].as_f64().is_some_and(|d| d <= 0.25 * rate),
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
