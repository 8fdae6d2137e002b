//! Replays the representation fuzz target's seed corpus and past findings on stable Rust.

use std::path::PathBuf;

#[test]
fn representation_corpus_and_regressions() {
    let fuzz = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut n = 0;
    for dir in [
        "corpus/xml",
        "corpus/representations",
        "regressions/representations",
    ] {
        let Ok(entries) = std::fs::read_dir(fuzz.join(dir)) else {
            continue;
        };
        for e in entries.flatten() {
            let bytes = std::fs::read(e.path()).expect("readable corpus file");
            xrce_dds_worker::fuzzing::representations(&bytes);
            n += 1;
        }
    }
    assert!(n >= 5, "seed corpus missing: {n}");
}
