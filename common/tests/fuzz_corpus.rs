//! Replays the fuzz targets' seed corpora and every past finding (fuzz/regressions) through
//! the same entry points the fuzzer uses, so CI checks them on stable Rust.

use xrce_common::fuzzing::corpus::{replay, seeds_are_current};

/// The repository's `fuzz/` folder.
fn fuzz_dir() -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz")
}

#[test]
fn decode_corpus_and_regressions() {
    replay(
        &fuzz_dir(),
        "decode",
        101,
        xrce_common::fuzzing::decode_message,
    );
}

#[test]
fn agent_session_corpus_and_regressions() {
    replay(
        &fuzz_dir(),
        "agent_session",
        10,
        xrce_common::fuzzing::agent_session,
    );
}

#[test]
fn tcp_framing_corpus_and_regressions() {
    replay(
        &fuzz_dir(),
        "tcp_framing",
        10,
        xrce_common::fuzzing::tcp_framing,
    );
}

#[test]
fn serial_framing_corpus_and_regressions() {
    replay(
        &fuzz_dir(),
        "serial_framing",
        10,
        xrce_common::fuzzing::serial_framing,
    );
}

#[test]
fn session_store_corpus_and_regressions() {
    replay(
        &fuzz_dir(),
        "session_store",
        8,
        xrce_common::fuzzing::session_store,
    );
}

/// Rewrite with `XRCE_WRITE_SEEDS=1 cargo test -p xrce-common --test fuzz_corpus seeds`.
#[test]
fn session_store_seeds_are_current() {
    seeds_are_current(
        &fuzz_dir(),
        "session_store",
        xrce_common::fuzzing::session_store_seeds(),
        8,
    );
}
