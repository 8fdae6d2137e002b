//! Replays the IPC fuzz target's seed corpus and past findings (`fuzz/corpus/ipc_messages`,
//! `fuzz/regressions/ipc_messages`) through the entry point the fuzzer uses, and checks the
//! committed seeds are the current encodings (rewrite them with
//! `XRCE_WRITE_SEEDS=1 cargo test -p xrce-ipc --test fuzz_corpus`).

use std::path::PathBuf;

use xrce_common::fuzzing::corpus::{replay, seeds_are_current};

/// The repository's `fuzz/` folder.
fn fuzz_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz")
}

#[test]
fn ipc_seeds_are_current() {
    seeds_are_current(
        &fuzz_dir(),
        "ipc_messages",
        xrce_ipc::fuzzing::ipc_seeds(),
        15,
    );
}

#[test]
fn ipc_messages_corpus_and_regressions() {
    replay(
        &fuzz_dir(),
        "ipc_messages",
        15,
        xrce_ipc::fuzzing::ipc_messages,
    );
}
