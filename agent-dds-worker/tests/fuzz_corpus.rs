//! Replays the representation fuzz target's seed corpus and past findings on stable Rust.
//! Both folders must exist: a missing one fails the test instead of replaying nothing.

use std::path::PathBuf;

#[test]
fn representation_corpus_and_regressions() {
    let fuzz = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut n = 0;
    for dir in ["corpus/representations", "regressions/representations"] {
        let entries = std::fs::read_dir(fuzz.join(dir))
            .unwrap_or_else(|e| panic!("fuzz/{dir} is missing ({e}): nothing would be replayed"));
        for e in entries.flatten() {
            let path = e.path();
            if path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('.'))
            {
                continue;
            }
            let bytes = std::fs::read(&path).expect("readable corpus file");
            xrce_dds_worker::fuzzing::representations(&bytes);
            n += 1;
        }
    }
    assert!(n >= 5, "seed corpus missing: {n}");
}
