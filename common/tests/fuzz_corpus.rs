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

#[test]
fn session_store_corpus_and_regressions() {
    let all = inputs("session_store");
    assert!(all.len() >= 8, "seed corpus missing: {}", all.len());
    for (path, bytes) in all {
        eprintln!("{}", path.display());
        xrce_common::fuzzing::session_store(&bytes);
    }
}

/// The session_store seeds are the current encodings of representative records: this fails
/// when a record format changes and the corpus was not rewritten (with
/// `XRCE_WRITE_SEEDS=1 cargo test -p xrce-common --test fuzz_corpus session_store_seeds`).
#[test]
fn session_store_seeds_are_current() {
    use std::time::Duration;
    use xrce_common::session::graph::{ActiveRead, DeliveredMarks, GraphObject, ObjectGraph};
    use xrce_common::session::snapshot::{OutputSnapshot, SessionSnapshot};
    use xrce_common::wire::*;
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus/session_store");
    let write = std::env::var_os("XRCE_WRITE_SEEDS").is_some();
    let check = |name: String, bytes: Vec<u8>| {
        let path = dir.join(&name);
        if write {
            std::fs::create_dir_all(&dir).expect("corpus folder");
            std::fs::write(&path, &bytes).expect("write seed");
        } else {
            let committed = std::fs::read(&path)
                .unwrap_or_else(|e| panic!("seed {name} missing ({e}); rewrite the corpus"));
            assert_eq!(committed, bytes, "seed {name} is stale; rewrite the corpus");
        }
    };
    let base = SessionSnapshot {
        key: ClientKey([0xAA, 0xAA, 0xBB, 0xBB]),
        session_id: 0x81,
        endpoint: vec![4, 127, 0, 0, 1, 0x22, 0xB8],
        mtu: 512,
        dialect: Dialect::Eprosima,
        dead_time: Some(Duration::from_millis(2500)),
        reliable_in: vec![(0x80, 17), (0x81, 0xFFFF)],
        best_effort_in: vec![(0x01, 3)],
        reliable_out: vec![
            OutputSnapshot {
                stream_id: 0x80,
                next: 40,
                in_flight: Some(vec![(38, vec![1, 2, 3]), (39, vec![4])]),
                queued: vec![vec![9, 9], vec![8]],
            },
            OutputSnapshot {
                stream_id: 0x81,
                next: 7,
                in_flight: None,
                queued: Vec::new(),
            },
        ],
        best_effort_out: vec![(0x01, 9)],
    };
    let snapshots = [
        base.clone(),
        SessionSnapshot {
            dialect: Dialect::Spec,
            dead_time: None,
            endpoint: vec![6; 19],
            ..base.clone()
        },
        SessionSnapshot {
            reliable_out: Vec::new(),
            reliable_in: Vec::new(),
            best_effort_in: Vec::new(),
            best_effort_out: Vec::new(),
            ..base.clone()
        },
    ];
    for (i, s) in snapshots.iter().enumerate() {
        check(format!("snapshot-{i}"), s.encode());
    }
    let xml = |kind: u8, text: &str, extra: VariantExtra| ObjectVariant {
        kind,
        representation: Representation::Xml(text.into()),
        extra,
    };
    let p = ObjectId::new(1, object_kind::PARTICIPANT);
    let t = ObjectId::new(1, object_kind::TOPIC);
    let sb = ObjectId::new(1, object_kind::SUBSCRIBER);
    let rd = ObjectId::new(1, object_kind::DATAREADER);
    let objects = [
        (
            p,
            xml(
                object_kind::PARTICIPANT,
                "<dds/>",
                VariantExtra::DomainId(7),
            ),
        ),
        (
            t,
            xml(
                object_kind::TOPIC,
                "<dds><topic/></dds>",
                VariantExtra::Parent(p),
            ),
        ),
        (
            sb,
            ObjectVariant {
                kind: object_kind::SUBSCRIBER,
                representation: Representation::Reference("sub".into()),
                extra: VariantExtra::Parent(p),
            },
        ),
        (
            rd,
            xml(object_kind::DATAREADER, "<dds/>", VariantExtra::Parent(sb)),
        ),
    ];
    let mut graphs = vec![ObjectGraph::default()];
    let mut g = ObjectGraph::default();
    for (i, (id, variant)) in objects.into_iter().enumerate() {
        g.insert(GraphObject {
            object_id: id,
            request_id: RequestId::from_u16(10 + i as u16),
            variant,
            little_endian: i % 2 == 0,
            readers_matched: 0,
        });
        graphs.push(g.clone());
    }
    let mut marks = DeliveredMarks::default();
    marks.record([7; 16], 41);
    marks.record([9; 16], 3);
    g.set_read(
        rd,
        ActiveRead {
            request_id: RequestId::from_u16(99),
            spec: ReadSpecification {
                preferred_stream_id: stream_id::BUILTIN_RELIABLE,
                content_filter_expression: Some("index > 3".into()),
                delivery_control: Some(DataDeliveryControl {
                    max_samples: 100,
                    ..Default::default()
                }),
                ..Default::default()
            },
            delivered: 12,
            marks,
        },
    );
    graphs.push(g);
    for (i, g) in graphs.iter().enumerate() {
        let (o, r) = (g.encode_objects(), g.encode_reads());
        let mut seed = u16::try_from(o.len())
            .expect("small")
            .to_le_bytes()
            .to_vec();
        seed.extend_from_slice(&o);
        seed.extend_from_slice(&r);
        check(format!("graph-{i}"), seed);
    }
}
