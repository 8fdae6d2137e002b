//! Replays the fuzz targets' seed corpora and every past finding (fuzz/regressions) through
//! the same entry points the fuzzer uses, so CI checks them on stable Rust.

use std::path::PathBuf;

/// Every input of a target: its seed corpus (`fuzz/corpus/<target>`, rebuilt by
/// `fuzz/make_corpus.py`) and its past findings (`fuzz/regressions/<target>`). Both folders
/// must exist: a missing one fails the test instead of replaying nothing. Dotfiles (the
/// `.gitkeep` of a target without findings yet) are not inputs.
fn inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let fuzz = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut out = Vec::new();
    for dir in [format!("corpus/{target}"), format!("regressions/{target}")] {
        let path = fuzz.join(&dir);
        let entries = std::fs::read_dir(&path)
            .unwrap_or_else(|e| panic!("fuzz/{dir} is missing ({e}): nothing would be replayed"));
        for e in entries.flatten() {
            let path = e.path();
            let hidden = path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('.'));
            if path.is_file() && !hidden {
                let bytes = std::fs::read(&path).expect("readable corpus file");
                out.push((path, bytes));
            }
        }
    }
    out.sort();
    out
}

/// Runs every input of `target` through `entry`, after checking that its seed corpus has at
/// least `least` inputs (a corpus that went missing would replay nothing).
fn replay(target: &str, least: usize, entry: fn(&[u8])) {
    let all = inputs(target);
    assert!(
        all.len() >= least,
        "seed corpus of {target} missing: {}",
        all.len()
    );
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        entry(&bytes);
    }
}

#[test]
fn decode_corpus_and_regressions() {
    replay("decode", 101, xrce_common::fuzzing::decode_message);
}

#[test]
fn agent_session_corpus_and_regressions() {
    replay("agent_session", 10, xrce_common::fuzzing::agent_session);
}

#[test]
fn tcp_framing_corpus_and_regressions() {
    replay("tcp_framing", 10, xrce_common::fuzzing::tcp_framing);
}

#[test]
fn serial_framing_corpus_and_regressions() {
    replay("serial_framing", 10, xrce_common::fuzzing::serial_framing);
}

#[test]
fn session_store_corpus_and_regressions() {
    replay("session_store", 8, xrce_common::fuzzing::session_store);
}

/// Checks that the committed seeds of `target` are the current encodings `seeds` gives (or
/// rewrites them with `XRCE_WRITE_SEEDS=1`): this fails when a format changes and the corpus
/// was not rewritten.
fn seeds_are_current(target: &str, seeds: Vec<(String, Vec<u8>)>, least: usize) {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!("../fuzz/corpus/{target}"));
    let write = std::env::var_os("XRCE_WRITE_SEEDS").is_some();
    assert!(seeds.len() >= least, "{} seeds", seeds.len());
    for (name, bytes) in seeds {
        let path = dir.join(&name);
        if write {
            std::fs::create_dir_all(&dir).expect("corpus folder");
            std::fs::write(&path, &bytes).expect("write seed");
        } else {
            let committed = std::fs::read(&path)
                .unwrap_or_else(|e| panic!("seed {name} missing ({e}); rewrite the corpus"));
            assert_eq!(committed, bytes, "seed {name} is stale; rewrite the corpus");
        }
    }
}

/// Rewrite with `XRCE_WRITE_SEEDS=1 cargo test -p xrce-common --test fuzz_corpus seeds`.
#[test]
fn session_store_seeds_are_current() {
    seeds_are_current(
        "session_store",
        xrce_common::fuzzing::session_store_seeds(),
        8,
    );
}
