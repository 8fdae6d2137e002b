//! Replays the IPC fuzz target's seed corpus and past findings (`fuzz/corpus/ipc_messages`,
//! `fuzz/regressions/ipc_messages`) through the entry point the fuzzer uses, and checks the
//! committed seeds are the current encodings (rewrite them with
//! `XRCE_WRITE_SEEDS=1 cargo test -p xrce-ipc --test fuzz_corpus`).

use std::path::PathBuf;

fn fuzz_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz")
}

#[test]
fn ipc_seeds_are_current() {
    let dir = fuzz_dir().join("corpus/ipc_messages");
    let write = std::env::var_os("XRCE_WRITE_SEEDS").is_some();
    let seeds = xrce_ipc::fuzzing::ipc_seeds();
    assert!(seeds.len() >= 15, "{} seeds", seeds.len());
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

#[test]
fn ipc_messages_corpus_and_regressions() {
    let mut replayed = 0;
    for folder in ["corpus/ipc_messages", "regressions/ipc_messages"] {
        let path = fuzz_dir().join(folder);
        let entries = std::fs::read_dir(&path).unwrap_or_else(|e| {
            panic!("fuzz/{folder} is missing ({e}): nothing would be replayed")
        });
        for e in entries.flatten() {
            let p = e.path();
            let hidden = p
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('.'));
            if p.is_file() && !hidden {
                eprintln!("{}", p.display());
                xrce_ipc::fuzzing::ipc_messages(&std::fs::read(&p).expect("readable input"));
                replayed += 1;
            }
        }
    }
    assert!(
        replayed >= 15,
        "seed corpus of ipc_messages missing: {replayed}"
    );
}
