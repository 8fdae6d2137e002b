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

#[test]
fn decode_corpus_and_regressions() {
    let all = inputs("decode");
    assert!(all.len() > 100, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::decode_message(&bytes);
    }
}

#[test]
fn agent_session_corpus_and_regressions() {
    let all = inputs("agent_session");
    assert!(all.len() >= 10, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::agent_session(&bytes);
    }
}

#[test]
fn tcp_framing_corpus_and_regressions() {
    let all = inputs("tcp_framing");
    assert!(all.len() >= 10, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::tcp_framing(&bytes);
    }
}

#[test]
fn serial_framing_corpus_and_regressions() {
    let all = inputs("serial_framing");
    assert!(all.len() >= 10, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::serial_framing(&bytes);
    }
}
