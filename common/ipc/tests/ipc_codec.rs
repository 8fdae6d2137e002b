//! The IPC contract's codec: every request and reply survives a round trip, the layout is
//! the one both ends have spoken since version 7, and what is not a message of the right
//! direction, version, kind and size is refused.

use std::borrow::Cow;

use xrce_common::session::stream::InputPosition;
use xrce_common::wire::{ClientKey, Dialect, ObjectId, RequestId, ResultStatus};
use xrce_ipc::{
    Encode, IpcError, Reply, ReplyMessage, Request, RequestMessage, Route, Sample, SampleIdentity,
    SampleOrigin, WriteOrigin, HEADER_LEN,
};

use proptest::prelude::*;

fn route() -> impl Strategy<Value = Route> {
    (
        any::<u32>(),
        any::<u16>(),
        any::<u32>(),
        any::<u64>(),
        any::<[u8; 4]>(),
        any::<[u8; 2]>(),
        any::<[u8; 2]>(),
    )
        .prop_map(|(f, i, g, s, c, r, o)| Route {
            frontend_id: f,
            incarnation: i,
            generation: g,
            op_seq: s,
            client_key: ClientKey(c),
            request_id: RequestId(r),
            object_id: ObjectId(o),
        })
}

fn bytes() -> impl Strategy<Value = Cow<'static, [u8]>> {
    proptest::collection::vec(any::<u8>(), 0..64).prop_map(Cow::Owned)
}

fn request() -> impl Strategy<Value = Request<'static>> {
    prop_oneof![
        Just(Request::FrontendHello),
        (bytes(), any::<bool>(), any::<bool>(), any::<u8>()).prop_map(|(d, le, r, n)| {
            Request::Create {
                description: d,
                client_little_endian: le,
                replay: r,
                readers_matched: n,
            }
        }),
        Just(Request::Delete),
        (
            bytes(),
            any::<u8>(),
            any::<bool>(),
            any::<bool>(),
            any::<bool>(),
            proptest::option::of(position()),
            any::<u64>(),
            proptest::option::of(any::<u64>()),
        )
            .prop_map(|(d, f, le, spec, st, p, r, first)| Request::Write {
                data: d,
                data_format: f,
                little_endian: le,
                dialect: if spec {
                    Dialect::Spec
                } else {
                    Dialect::Eprosima
                },
                status_requested: st,
                position: p,
                received_us: r,
                resend_of: first,
            }),
        (bytes(), any::<bool>()).prop_map(|(s, r)| Request::Read { spec: s, replay: r }),
        Just(Request::DeleteClient),
        Just(Request::PauseRead),
        Just(Request::ResumeRead),
        Just(Request::ReplayDone),
    ]
}

fn reply() -> impl Strategy<Value = Reply<'static>> {
    prop_oneof![
        Just(Reply::WorkerHello),
        (any::<u8>(), any::<u8>(), any::<bool>()).prop_map(|(s, i, r)| Reply::Status {
            result: ResultStatus {
                status: s,
                implementation_status: i
            },
            replay: r,
        }),
        (
            any::<[u8; 16]>(),
            any::<i64>(),
            bytes(),
            any::<bool>(),
            any::<bool>(),
            any::<bool>(),
            proptest::option::of((
                any::<u32>(),
                any::<u16>(),
                any::<u64>(),
                any::<u32>(),
                any::<bool>()
            )),
        )
            .prop_map(|(w, n, d, le, dis, unr, o)| Reply::Sample(Sample {
                identity: SampleIdentity {
                    writer: w,
                    sequence_number: n,
                },
                origin: o.map(
                    |(frontend, incarnation, write, index, resent)| SampleOrigin {
                        write: WriteOrigin {
                            frontend,
                            incarnation,
                            write,
                            index,
                        },
                        resent,
                    }
                ),
                data: d,
                little_endian: le,
                disposed: dis,
                unregistered: unr,
            })),
        (any::<u64>(), any::<u64>()).prop_map(|(e, a)| Reply::Progress {
            executed: e,
            acknowledged: a
        }),
        Just(Reply::ReadEnded),
        any::<u8>().prop_map(|n| Reply::WriterMatched { readers: n }),
        position().prop_map(Reply::Executed),
    ]
}

fn position() -> impl Strategy<Value = InputPosition> {
    (any::<u8>(), any::<u16>(), any::<u16>(), any::<u64>()).prop_map(|(s, q, i, e)| InputPosition {
        epoch: e,
        stream_id: s,
        sequence: q,
        write_index: i,
    })
}

proptest! {
    #[test]
    fn requests_round_trip(route in route(), wait in any::<bool>(), request in request()) {
        let m = RequestMessage { route, progress_can_wait: wait, request };
        let bytes = m.encode();
        prop_assert_eq!(bytes.len(), m.encoded_len());
        prop_assert_eq!(RequestMessage::decode(&bytes), Ok(m));
        let refused = matches!(ReplyMessage::decode(&bytes), Err(IpcError::Direction(_)));
        prop_assert!(refused);
        for cut in [0, HEADER_LEN - 1, bytes.len() - 1] {
            prop_assert!(RequestMessage::decode(&bytes[..cut]).is_err());
        }
    }

    #[test]
    fn replies_round_trip(route in route(), reply in reply()) {
        let m = ReplyMessage { route, reply };
        let bytes = m.encode();
        prop_assert_eq!(bytes.len(), m.encoded_len());
        prop_assert_eq!(ReplyMessage::decode(&bytes), Ok(m));
        let refused = matches!(RequestMessage::decode(&bytes), Err(IpcError::Direction(_)));
        prop_assert!(refused);
        let mut longer = bytes.clone();
        longer.push(0);
        let refused = matches!(ReplyMessage::decode(&longer), Err(IpcError::Length { .. }));
        prop_assert!(refused);
    }

    #[test]
    fn any_bytes_decode_or_fail_cleanly(buf in proptest::collection::vec(any::<u8>(), 0..128)) {
        xrce_ipc::fuzzing::ipc_messages(&buf);
    }
}

#[test]
fn the_layout_is_the_contract() {
    // A Write as a version-7 front-end lays it out, byte by byte.
    let m = RequestMessage {
        route: Route {
            frontend_id: 7,
            incarnation: 0xBEEF,
            generation: 3,
            op_seq: 1 << 40,
            client_key: ClientKey([1, 2, 3, 4]),
            request_id: RequestId([0, 9]),
            object_id: ObjectId::new(1, 5),
        },
        progress_can_wait: true,
        request: Request::Write {
            data: Cow::Borrowed(b"body"),
            data_format: 0x0A,
            little_endian: true,
            dialect: Dialect::Spec,
            status_requested: true,
            position: Some(InputPosition {
                epoch: 0x0102_0304_0506_0708,
                stream_id: 0x80,
                sequence: 0x1234,
                write_index: 2,
            }),
            received_us: 0x1122_3344_5566,
            resend_of: None,
        },
    };
    let mut expected = b"XRIP".to_vec();
    expected.extend_from_slice(&[10, 0, 4, 0x01 | 0x04 | 0x08 | 0x40 | 0x80]);
    expected.extend_from_slice(&7u32.to_le_bytes());
    expected.extend_from_slice(&3u32.to_le_bytes());
    expected.extend_from_slice(&(1u64 << 40).to_le_bytes());
    expected.extend_from_slice(&[1, 2, 3, 4, 0, 9]);
    expected.extend_from_slice(&ObjectId::new(1, 5).0);
    expected.extend_from_slice(&25u32.to_le_bytes());
    expected.extend_from_slice(&[0x0A, 0, 0xEF, 0xBE]);
    expected.extend_from_slice(&0x1122_3344_5566u64.to_le_bytes());
    expected.extend_from_slice(&[0x80, 0x34, 0x12, 2, 0, 8, 7, 6, 5, 4, 3, 2, 1]);
    expected.extend_from_slice(b"body");
    assert_eq!(m.encode(), expected);
    // A Write flagged with a position too short to hold one is refused, and so is one too
    // short for its reception time.
    for len in [11, 3] {
        let mut short = expected[..HEADER_LEN + len].to_vec();
        short[32..36].copy_from_slice(&(len as u32).to_le_bytes());
        let refused = RequestMessage::decode(&short);
        assert!(
            matches!(refused, Err(IpcError::Body { kind: 4, .. })),
            "{len}: {refused:?}"
        );
    }
    // Resent, it carries the number of its first send after the position.
    let mut resent = m.clone();
    if let Request::Write { resend_of, .. } = &mut resent.request {
        *resend_of = Some(0x0A0B);
    }
    let mut expected_resent = expected.clone();
    expected_resent[7] |= 0x02;
    expected_resent[32..36].copy_from_slice(&33u32.to_le_bytes());
    let at = HEADER_LEN + 8 + 13;
    expected_resent.splice(at..at, 0x0A0Bu64.to_le_bytes());
    assert_eq!(resent.encode(), expected_resent);
    assert_eq!(RequestMessage::decode(&expected_resent), Ok(resent));
    // A Sample with its origin: identity, origin, data; resent only with an origin.
    let sample = ReplyMessage::new(
        Route::frontend(7),
        Reply::Sample(Sample {
            identity: SampleIdentity {
                writer: [5; 16],
                sequence_number: 9,
            },
            origin: Some(SampleOrigin {
                write: WriteOrigin {
                    frontend: 7,
                    incarnation: 0xBEEF,
                    write: 0x0A0B,
                    index: 1,
                },
                resent: true,
            }),
            data: Cow::Borrowed(b"xy"),
            little_endian: true,
            disposed: false,
            unregistered: false,
        }),
    );
    let bytes = sample.encode();
    assert_eq!(bytes[7], 0x01 | 0x04 | 0x08);
    let body = &bytes[HEADER_LEN..];
    assert_eq!(body.len(), 24 + 18 + 2);
    assert_eq!(&body[24..28], &7u32.to_le_bytes());
    assert_eq!(&body[28..30], &0xBEEFu16.to_le_bytes());
    assert_eq!(&body[30..38], &0x0A0Bu64.to_le_bytes());
    assert_eq!(&body[38..42], &1u32.to_le_bytes());
    assert_eq!(&body[42..], b"xy");
    assert_eq!(ReplyMessage::decode(&bytes), Ok(sample));
    let mut resent_without_origin = bytes.clone();
    resent_without_origin[7] &= !0x04;
    assert!(matches!(
        ReplyMessage::decode(&resent_without_origin),
        Err(IpcError::Body { kind: 18, .. })
    ));
}

#[test]
fn other_versions_kinds_and_bodies_are_refused() {
    let hello = RequestMessage::new(Route::frontend(1), Request::FrontendHello).encode();
    let mut other = hello.clone();
    other[4] = 1;
    assert_eq!(RequestMessage::decode(&other), Err(IpcError::Version(1)));
    let mut bad = hello.clone();
    bad[0] = b'Y';
    assert_eq!(RequestMessage::decode(&bad), Err(IpcError::BadMagic));
    let mut unknown = hello.clone();
    unknown[6] = 99;
    assert_eq!(RequestMessage::decode(&unknown), Err(IpcError::Kind(99)));
    assert_eq!(ReplyMessage::decode(&unknown), Err(IpcError::Kind(99)));
    // A hello with a body, a Status of one byte, a Progress of 8.
    let mut with_body = hello.clone();
    with_body[32] = 1;
    with_body.push(0);
    assert_eq!(
        RequestMessage::decode(&with_body),
        Err(IpcError::Body { kind: 1, len: 1 })
    );
    let status = ReplyMessage::new(
        Route::frontend(1),
        Reply::Status {
            result: ResultStatus::default(),
            replay: false,
        },
    )
    .encode();
    let mut short = status[..status.len() - 1].to_vec();
    short[32] = 1;
    assert_eq!(
        ReplyMessage::decode(&short),
        Err(IpcError::Body { kind: 17, len: 1 })
    );
    let progress = ReplyMessage::new(
        Route::frontend(1),
        Reply::Progress {
            executed: 1,
            acknowledged: 1,
        },
    )
    .encode();
    let mut short = progress[..progress.len() - 8].to_vec();
    short[32] = 8;
    assert_eq!(
        ReplyMessage::decode(&short),
        Err(IpcError::Body { kind: 19, len: 8 })
    );
}
