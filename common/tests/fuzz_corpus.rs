//! Replays the fuzz targets' seed corpora and every past finding (fuzz/regressions) through
//! the same entry points the fuzzer uses, so CI checks them on stable Rust.

use std::path::PathBuf;

fn inputs(target_dirs: &[&str]) -> Vec<(PathBuf, Vec<u8>)> {
    let fuzz = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut out = Vec::new();
    for dir in target_dirs {
        let Ok(entries) = std::fs::read_dir(fuzz.join(dir)) else {
            continue;
        };
        for e in entries.flatten() {
            let path = e.path();
            if path.is_file() {
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
    let all = inputs(&["corpus/decode", "regressions/decode"]);
    assert!(all.len() > 100, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::decode_message(&bytes);
    }
}

#[test]
fn agent_session_corpus_and_regressions() {
    let all = inputs(&[
        "corpus/agent",
        "corpus/agent_session",
        "regressions/agent_session",
    ]);
    assert!(all.len() >= 10, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::agent_session(&bytes);
    }
}

#[test]
fn tcp_framing_corpus_and_regressions() {
    let all = inputs(&["corpus/tcp_framing", "regressions/tcp_framing"]);
    assert!(all.len() >= 10, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::tcp_framing(&bytes);
    }
}

#[test]
fn serial_framing_corpus_and_regressions() {
    let all = inputs(&["corpus/serial_framing", "regressions/serial_framing"]);
    assert!(all.len() >= 10, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::serial_framing(&bytes);
    }
}
