//! Transient-local late joiner: samples a client published before any reader existed reach a
//! Cyclone DDS reader that joins later with TRANSIENT_LOCAL durability (the agent's writers
//! are transient-local by default, as Fast DDS's).

use std::time::Duration;

use xrce_tests::{hello_world, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn a_late_transient_local_reader_gets_the_history() {
    // The worker says (at debug level) when a new writer stops holding its samples.
    let agent = AgentProcess::builder("late")
        .env(&[(
            "XRCE_LOG",
            "info,rustdds=error,xrce_dds_worker::worker::writes=debug",
        )])
        .start();
    let mut c = TestClient::new(agent.addr(), [0x1A, 0x7E, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(24);
    for i in 0..8 {
        c.write_reliable(w, &hello_world(i, "before you came"));
    }
    // Every write taken by the agent (its worker may still hold them until its writer has
    // matched a reader: they reach the history then, which the late joiner gets either way).
    assert!(c.run_until(10 * SECOND, |c| c
        .client
        .unacked(xrce_common::wire::stream_id::BUILTIN_RELIABLE)
        == 0));
    // Join after the worker's hold for an unmatched new writer (1 s) is over: the samples are
    // then in the writer's history, not held, and the late joiner must get that history
    // whole (with Cyclone DDS it got only the last sample until its durability service kept
    // the writer's depth).
    let (_, line) = agent
        .output()
        .wait_for(0, "holding writer resumes", 10 * SECOND)
        .expect("the worker never released its new writer's hold");
    assert!(
        plain(&line).contains("matched=false"),
        "the hold ended by a match, with no reader: {line}"
    );
    agent
        .output()
        .wait_for(0, "holding writer drained", 10 * SECOND)
        .expect("the worker never published what its new writer held");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "24",
        "--count",
        "8",
        "--reliable",
        "--transient-local",
        "--timeout",
        "60",
    ]);
    let got = reader.collect_deliveries(8, "before you came", 45 * SECOND, || c.step());
    got.assert_exactly_once(0..8, "a late transient-local reader's history");
    got.assert_in_order("a late transient-local reader's history");
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// A log line without its terminal colours.
fn plain(line: &str) -> String {
    let mut out = String::new();
    let mut chars = line.chars();
    while let Some(ch) = chars.next() {
        if ch == '\u{1b}' {
            // ESC [ ... m
            for c in chars.by_ref() {
                if c == 'm' {
                    break;
                }
            }
        } else {
            out.push(ch);
        }
    }
    out
}
