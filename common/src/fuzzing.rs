//! Entry points shared by the coverage-guided fuzz targets (`fuzz/`) and the corpus replay
//! tests that run them on stable Rust in CI. Each takes arbitrary bytes and panics only when
//! an invariant breaks; a panic anywhere in the code under test is a finding.

use std::time::{Duration, Instant};

use crate::session::agent::{Agent, AgentConfig, DataReply, NullSink};
use crate::wire::sample::{decode_samples, encode_samples};
use crate::wire::{
    data_format, BaseObjectRequest, ClientKey, Dialect, Message, MessageBuilder, MessageHeader,
    Payload,
};

/// Decoder oracle: whatever decodes re-encodes to bytes that decode to the same message, and
/// sample representations inside WRITE_DATA/DATA decode in both dialects without panicking
/// and re-encode consistently.
pub fn decode_message(data: &[u8]) {
    let Ok(m) = Message::decode(data) else {
        return;
    };
    let Ok(again) = m.encode() else {
        return;
    };
    let m2 = Message::decode(&again).expect("re-encoded message decodes");
    assert_eq!(m.header, m2.header, "header changed by a round trip");
    assert_eq!(
        m.submessages.len(),
        m2.submessages.len(),
        "submessage count changed by a round trip"
    );
    for (a, b) in m.submessages.iter().zip(&m2.submessages) {
        assert_eq!(a.payload, b.payload, "payload changed by a round trip");
    }
    for s in &m.submessages {
        if let Payload::WriteData(d) | Payload::Data(d) = &s.payload {
            for dialect in [Dialect::Spec, Dialect::Eprosima] {
                samples_round_trip(d.format, d.data, s.little_endian, dialect);
            }
        }
        if let Payload::Info(i) = &s.payload {
            // ObjectInfo follows the 6-byte reply; decoding may fail, never panic, and what
            // decodes re-encodes to something that decodes the same.
            let mut bytes = vec![0u8; crate::wire::BaseObjectReply::LEN];
            bytes.extend_from_slice(i.object_info);
            for dialect in [Dialect::Spec, Dialect::Eprosima] {
                let r = &mut crate::wire::cdr::CdrReader::new(&bytes, s.little_endian);
                let _ = r.take(crate::wire::BaseObjectReply::LEN);
                if let Ok(info) = crate::wire::info::ObjectInfo::decode(r, dialect) {
                    let mut out = Vec::new();
                    {
                        let w = &mut crate::wire::cdr::CdrWriter::new(&mut out, s.little_endian);
                        w.bytes(&[0; crate::wire::BaseObjectReply::LEN]);
                        info.encode(w, dialect);
                    }
                    let r = &mut crate::wire::cdr::CdrReader::new(&out, s.little_endian);
                    let _ = r.take(crate::wire::BaseObjectReply::LEN);
                    let again = crate::wire::info::ObjectInfo::decode(r, dialect);
                    assert_eq!(
                        again.as_ref(),
                        Ok(&info),
                        "ObjectInfo changed by a round trip"
                    );
                }
            }
        }
    }
}

/// Sample-representation oracle: decoded samples re-encode to bytes that decode to the same
/// samples.
pub fn samples_round_trip(format: u8, data: &[u8], little_endian: bool, dialect: Dialect) {
    let Ok(samples) = decode_samples(format, data, little_endian, dialect, None) else {
        return;
    };
    let mut out = Vec::new();
    if encode_samples(format, &samples, little_endian, dialect, &mut out).is_err() {
        return;
    }
    let again =
        decode_samples(format, &out, little_endian, dialect, None).expect("re-encoded samples");
    assert_eq!(samples.len(), again.len());
    for (a, b) in samples.iter().zip(&again) {
        assert_eq!(a.data, b.data);
        assert_eq!(a.info.map(|i| i.state), b.info.map(|i| i.state));
    }
}

/// Agent-core oracle: the input is a sequence of datagrams (`u16` little-endian length, then
/// bytes) from a few source addresses, fed with advancing time and timers; replies are pushed
/// back through `send_data` in every format. Afterwards a ping must still be answered.
pub fn agent_session(data: &[u8]) {
    let t0 = Instant::now();
    let mut agent: Agent<u8> = Agent::new(AgentConfig {
        max_clients: 8,
        client_dead_time: Some(Duration::from_secs(2)),
        ..AgentConfig::default()
    });
    agent.set_wall_clock(t0, Duration::from_secs(1_700_000_000));
    let mut sink = NullSink;
    let mut rest = data;
    let mut now = t0;
    let mut i = 0u8;
    while rest.len() >= 3 {
        let len = usize::from(u16::from_le_bytes([rest[0], rest[1]]));
        let src = rest[2] % 4;
        rest = &rest[3..];
        let take = len.min(rest.len());
        let (datagram, tail) = rest.split_at(take);
        rest = tail;
        agent.handle_datagram(now, src, datagram, &mut sink);
        now += Duration::from_millis(u64::from(i % 64) * 7);
        agent.handle_timeout(now, &mut sink);
        if let Some(key) = datagram
            .get(4..8)
            .map(|k| ClientKey([k[0], k[1], k[2], k[3]]))
        {
            let format = [
                data_format::DATA,
                data_format::SAMPLE,
                data_format::DATA_SEQ,
                data_format::SAMPLE_SEQ,
                data_format::PACKED_SAMPLES,
            ][usize::from(i % 5)];
            let _ = agent.send_data(
                now,
                key,
                datagram.first().copied().unwrap_or(0x80),
                DataReply {
                    request: BaseObjectRequest::default(),
                    format,
                    sample: datagram,
                    little_endian: i % 2 == 0,
                    state: i,
                    sequence_number: u32::from(i),
                },
            );
        }
        while agent.poll_transmit().is_some() {}
        i = i.wrapping_add(1);
    }
    // The agent still answers a ping (GET_INFO without a session).
    let mut ping = MessageBuilder::new(MessageHeader::new(0x80, 0, 0, ClientKey::INVALID));
    ping.push(
        &Payload::GetInfo(crate::wire::GetInfoPayload {
            base: BaseObjectRequest {
                request_id: crate::wire::RequestId::from_u16(0x00AA),
                object_id: crate::wire::ObjectId::AGENT,
            },
            info_mask: 0x02,
        }),
        true,
    )
    .expect("ping encodes");
    agent.handle_datagram(now, 200, &ping.finish(), &mut sink);
    let answered = std::iter::from_fn(|| agent.poll_transmit()).any(|t| {
        t.destination == 200
            && Message::decode(&t.data)
                .is_ok_and(|m| matches!(m.submessages[0].payload, Payload::Info(_)))
    });
    assert!(answered, "ping not answered after the fuzz input");
}

/// Splits `data` into the chunks a byte-stream reader might see: the first byte seeds the
/// chunk lengths (1 to 64 bytes each), the rest is the stream.
fn chunks(data: &[u8]) -> impl Iterator<Item = &[u8]> {
    let (seed, mut rest) = data.split_first().map_or((0u8, &[][..]), |(s, r)| (*s, r));
    let mut state = u32::from(seed) | 1;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        let n = (state as usize % 64 + 1).min(rest.len());
        let (head, tail) = rest.split_at(n);
        rest = tail;
        Some(head)
    })
}

/// TCP framing oracle: the stream, cut anywhere, gives messages no longer than the maximum,
/// never empty; their re-encoding is what the decoder consumed minus skipped zero lengths;
/// the buffer stays bounded; and after an over-long length nothing more comes out.
pub fn tcp_framing(data: &[u8]) {
    use crate::framing::length_prefix::{encode, LengthPrefixDecoder, PREFIX_LEN};
    const MAX: usize = 300;
    let mut d = LengthPrefixDecoder::new(MAX);
    let mut messages: Vec<Vec<u8>> = Vec::new();
    let mut failed = false;
    for chunk in chunks(data) {
        let r = d.push(chunk, |m| {
            assert!(
                !m.is_empty() && m.len() <= MAX,
                "message of {} bytes",
                m.len()
            );
            messages.push(m.to_vec());
        });
        assert!(
            d.capacity() <= MAX + PREFIX_LEN + 2048,
            "buffer grew to {}",
            d.capacity()
        );
        if r.is_err() {
            failed = true;
            break;
        }
    }
    if failed {
        assert!(
            d.next_message().is_some_and(|m| m.is_err()),
            "failure not sticky"
        );
        return;
    }
    // Re-encoded, the messages and the leftover are the input without its zero lengths.
    let stream: Vec<u8> = data.iter().skip(1).copied().collect();
    let mut again = Vec::new();
    for m in &messages {
        encode(m, &mut again).expect("fits");
    }
    let mut cleaned = Vec::new();
    let mut i = 0;
    while i + PREFIX_LEN <= stream.len() {
        let len = usize::from(u16::from_le_bytes([stream[i], stream[i + 1]]));
        if len == 0 {
            i += PREFIX_LEN;
            continue;
        }
        if i + PREFIX_LEN + len > stream.len() {
            break;
        }
        cleaned.extend_from_slice(&stream[i..i + PREFIX_LEN + len]);
        i += PREFIX_LEN + len;
    }
    assert_eq!(again, cleaned, "messages differ from the stream");
}

/// Serial framing oracle: the stream, cut anywhere, gives the same frames as whole; every
/// frame is addressed to the agent, no longer than the maximum, and re-encodes to a frame
/// that decodes to itself; and the encoder's output always decodes back (the data, read as
/// a payload, round-trips).
pub fn serial_framing(data: &[u8]) {
    use crate::framing::serial::{encode, SerialDecoder, AGENT_ADDRESS};
    const MAX: usize = 512;
    let decode = |pieces: &mut dyn Iterator<Item = &[u8]>| {
        let mut d = SerialDecoder::new(AGENT_ADDRESS, MAX);
        let mut out = Vec::new();
        for p in pieces {
            d.push(p, |f| {
                if let Ok(f) = f {
                    assert_eq!(f.destination, AGENT_ADDRESS);
                    assert!(f.payload.len() <= MAX);
                    out.push((f.source, f.payload.to_vec()));
                }
            });
        }
        out
    };
    let stream = data.get(1..).unwrap_or_default();
    let whole = decode(&mut std::iter::once(stream));
    let split = decode(&mut chunks(data));
    assert_eq!(whole, split, "frames depend on how the stream was cut");
    for (source, payload) in &whole {
        let mut wire = Vec::new();
        encode(*source, AGENT_ADDRESS, payload, &mut wire).expect("fits");
        assert_eq!(
            decode(&mut std::iter::once(&wire[..])),
            [(*source, payload.clone())]
        );
    }
    let payload = &stream[..stream.len().min(MAX)];
    let mut wire = Vec::new();
    encode(7, AGENT_ADDRESS, payload, &mut wire).expect("fits");
    assert_eq!(
        decode(&mut chunks(
            &[&[data.first().copied().unwrap_or(0)][..], &wire].concat()
        )),
        [(7, payload.to_vec())],
        "an encoded frame did not decode back"
    );
}

/// Session-store oracle: the records a successor front-end reads back (a session snapshot,
/// and a client's objects and reads) decode or fail cleanly, whatever the bytes (a record torn
/// by a crash, a file from another build), and what decodes re-encodes to bytes that decode to
/// the same. The whole input is tried as a snapshot; after a 2-byte little-endian length, as a
/// client's objects (that many bytes) and reads (the rest).
pub fn session_store(data: &[u8]) {
    use crate::session::graph::ObjectGraph;
    use crate::session::snapshot::SessionSnapshot;
    if let Ok(s) = SessionSnapshot::decode(data) {
        let again = SessionSnapshot::decode(&s.encode()).expect("re-encoded snapshot decodes");
        assert_eq!(again, s, "snapshot changed by a round trip");
    }
    let Some((len, rest)) = data.split_first_chunk::<2>() else {
        return;
    };
    let split = usize::from(u16::from_le_bytes(*len)).min(rest.len());
    let (objects, reads) = rest.split_at(split);
    if let Ok(g) = ObjectGraph::decode(objects, reads) {
        let (o, r) = (g.encode_objects(), g.encode_reads());
        let g2 = ObjectGraph::decode(&o, &r).expect("re-encoded graph decodes");
        assert_eq!(g2.encode_objects(), o, "objects changed by a round trip");
        assert_eq!(g2.encode_reads(), r, "reads changed by a round trip");
    }
}

/// A representative session snapshot (every kind of stream, unacknowledged and queued output,
/// a dead time): the fuzz seeds' and the snapshot unit tests' example.
pub fn example_snapshot() -> crate::session::snapshot::SessionSnapshot {
    use crate::session::snapshot::{OutputSnapshot, SessionSnapshot};
    SessionSnapshot {
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
        epoch: 0x0123_4567_89AB_CDEF,
    }
}

/// The session_store target's seeds, by file name: snapshots, and a client's objects and
/// reads as [`session_store`] takes them (2-byte length of the objects first).
pub fn session_store_seeds() -> Vec<(String, Vec<u8>)> {
    use crate::session::graph::{ActiveRead, DeliveredMarks, GraphObject, ObjectGraph};
    use crate::session::snapshot::SessionSnapshot;
    use crate::wire::{
        object_kind, stream_id, DataDeliveryControl, ObjectId, ObjectVariant, ReadSpecification,
        Representation, RequestId, VariantExtra,
    };
    let mut seeds = Vec::new();
    let base = example_snapshot();
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
        seeds.push((format!("snapshot-{i}"), s.encode()));
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
            .unwrap_or(u16::MAX)
            .to_le_bytes()
            .to_vec();
        seed.extend_from_slice(&o);
        seed.extend_from_slice(&r);
        seeds.push((format!("graph-{i}"), seed));
    }
    seeds
}

/// The corpus tests' helpers: every crate with fuzz targets replays their committed inputs
/// and checks their generated seeds with these (test support: they read and write files and
/// panic on what is wrong).
pub mod corpus {
    use std::path::{Path, PathBuf};

    /// Every input of `target` under the `fuzz` folder: its seed corpus (`corpus/<target>`,
    /// rebuilt by `fuzz/make_corpus.py` or the seed tests) and its past findings
    /// (`regressions/<target>`). Both folders must exist: a missing one fails the test instead
    /// of replaying nothing. Dotfiles (the `.gitkeep` of a target without findings yet) are not
    /// inputs.
    pub fn inputs(fuzz: &Path, target: &str) -> Vec<(PathBuf, Vec<u8>)> {
        let mut out = Vec::new();
        for dir in [format!("corpus/{target}"), format!("regressions/{target}")] {
            let path = fuzz.join(&dir);
            let entries = std::fs::read_dir(&path).unwrap_or_else(|e| {
                panic!("fuzz/{dir} is missing ({e}): nothing would be replayed")
            });
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

    /// Runs every input of `target` through `entry`, after checking that there are at least
    /// `least` (a corpus that went missing would replay nothing).
    pub fn replay(fuzz: &Path, target: &str, least: usize, entry: fn(&[u8])) {
        let all = inputs(fuzz, target);
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

    /// Checks that the committed seeds of `target` are the current encodings `seeds` gives
    /// (or rewrites them when `XRCE_WRITE_SEEDS` is set): this fails when a format changes
    /// and the corpus was not rewritten.
    pub fn seeds_are_current(
        fuzz: &Path,
        target: &str,
        seeds: Vec<(String, Vec<u8>)>,
        least: usize,
    ) {
        let dir = fuzz.join(format!("corpus/{target}"));
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
}
