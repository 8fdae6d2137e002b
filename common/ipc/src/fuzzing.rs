//! Entry points of the IPC fuzz target (`fuzz/fuzz_targets/ipc_messages.rs`) and its seeds,
//! shared with the tests that replay the corpus on stable Rust.

/// IPC oracle: whatever the bytes (a message from another build, a stale or a hostile
/// process), decoding as a request and as a reply returns a message or an error, never
/// panics, and a decoded message re-encodes to bytes that decode to the same message.
pub fn ipc_messages(data: &[u8]) {
    use crate::{Encode, ReplyMessage, RequestMessage};
    if let Ok(m) = RequestMessage::decode(data) {
        let bytes = m.encode();
        assert_eq!(bytes.len(), m.encoded_len());
        assert_eq!(
            RequestMessage::decode(&bytes).as_ref(),
            Ok(&m),
            "request changed by a round trip"
        );
    }
    if let Ok(m) = ReplyMessage::decode(data) {
        let bytes = m.encode();
        assert_eq!(bytes.len(), m.encoded_len());
        assert_eq!(
            ReplyMessage::decode(&bytes).as_ref(),
            Ok(&m),
            "reply changed by a round trip"
        );
    }
}

/// The ipc_messages target's seeds, by file name: one message of every kind, as the front-end
/// and the worker encode them.
pub fn ipc_seeds() -> Vec<(String, Vec<u8>)> {
    use crate::{
        Encode, Reply, ReplyMessage, Request, RequestMessage, Route, Sample, SampleIdentity,
    };
    use std::borrow::Cow;
    use xrce_common::wire::{ClientKey, Dialect, ObjectId, RequestId, ResultStatus};
    let route = Route {
        frontend_id: 3,
        incarnation: 7,
        generation: 0x1234_5678,
        op_seq: 42,
        client_key: ClientKey([0xAA, 0xAA, 0xBB, 0xBB]),
        request_id: RequestId::from_u16(5),
        object_id: ObjectId::new(1, xrce_common::wire::object_kind::DATAWRITER),
    };
    let requests = [
        Request::FrontendHello,
        Request::Create {
            description: Cow::Borrowed(&[0x05, 0x01, 0, 0, 3, 0, 0, 0, b'a', b'b', 0][..]),
            client_little_endian: true,
            replay: true,
            readers_matched: 2,
        },
        Request::Delete,
        Request::Write {
            data: Cow::Borrowed(&[1, 2, 3, 4][..]),
            data_format: 0x02,
            little_endian: true,
            dialect: Dialect::Spec,
            status_requested: true,
            position: Some(xrce_common::session::stream::InputPosition {
                stream_id: 0x80,
                sequence: 0xFFFE,
                write_index: 3,
                epoch: 0x0001_0002_0003_0004,
            }),
            received_us: 0x0102_0304_0506,
            resend_of: Some(40),
        },
        Request::Read {
            spec: Cow::Borrowed(&[0x80, 0x00, 0x00, 0x00][..]),
            replay: false,
        },
        Request::DeleteClient,
        Request::PauseRead,
        Request::ResumeRead,
        Request::ReplayDone,
    ];
    let replies = [
        Reply::WorkerHello,
        Reply::Status {
            result: ResultStatus::new(0x85),
            replay: true,
        },
        Reply::Sample(Sample {
            identity: SampleIdentity {
                writer: [9; 16],
                sequence_number: 77,
            },
            origin: Some(crate::SampleOrigin {
                write: crate::WriteOrigin {
                    frontend: 3,
                    incarnation: 2,
                    write: 40,
                    index: 1,
                },
                resent: true,
            }),
            data: Cow::Borrowed(&[0, 1, 0, 0, 5, 0, 0, 0][..]),
            little_endian: true,
            disposed: true,
            unregistered: false,
        }),
        Reply::Progress {
            executed: 40,
            acknowledged: 39,
        },
        Reply::ReadEnded,
        Reply::WriterMatched { readers: 4 },
        Reply::Executed(xrce_common::session::stream::InputPosition {
            stream_id: 0x81,
            sequence: 12,
            write_index: 0,
            epoch: u64::MAX,
        }),
    ];
    let mut seeds = Vec::new();
    for r in requests {
        let name = format!("request-{}", r.name());
        let m = RequestMessage {
            route,
            progress_can_wait: r.is_write(),
            request: r,
        };
        seeds.push((name, m.encode()));
    }
    for (i, r) in replies.into_iter().enumerate() {
        seeds.push((format!("reply-{i}"), ReplyMessage::new(route, r).encode()));
    }
    seeds
}
