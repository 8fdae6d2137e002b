//! The byte layout of the messages ([`super::message`]'s types): a fixed little-endian
//! 40-byte header (magic, version, kind, flags, the route, the body's length, the data
//! format, a count), then the body. Kinds and flags are private to this module, and
//! [`Header::decode`] is the one place the magic, the version and the length are checked.
//! Decoding is strict: a kind sent the wrong way, a body of the wrong size or a message
//! longer or shorter than its header says is an [`IpcError`], never a guess.

use std::borrow::Cow;

use xrce_common::session::stream::InputPosition;
use xrce_common::wire::{ClientKey, Dialect, ObjectId, RequestId, ResultStatus};

use crate::message::{
    Encode, Reply, ReplyMessage, Request, RequestMessage, Route, Sample, SampleIdentity,
    SampleOrigin, HEADER_LEN, SAMPLE_IDENTITY_LEN, SAMPLE_ORIGIN_LEN,
};
use crate::{IPC_MAGIC, IPC_VERSION};

/// Message kinds on the wire.
mod kind {
    pub(super) const FRONTEND_HELLO: u8 = 1;
    pub(super) const CREATE: u8 = 2;
    pub(super) const DELETE: u8 = 3;
    pub(super) const WRITE: u8 = 4;
    pub(super) const READ: u8 = 5;
    pub(super) const DELETE_CLIENT: u8 = 6;
    pub(super) const PAUSE_READ: u8 = 7;
    pub(super) const RESUME_READ: u8 = 8;
    pub(super) const REPLAY_DONE: u8 = 9;
    pub(super) const WORKER_HELLO: u8 = 16;
    pub(super) const STATUS: u8 = 17;
    pub(super) const SAMPLE: u8 = 18;
    pub(super) const PROGRESS: u8 = 19;
    pub(super) const READ_ENDED: u8 = 20;
    pub(super) const WRITER_MATCHED: u8 = 21;
    pub(super) const EXECUTED: u8 = 22;
}

/// Header flags; which kinds carry each is written beside it.
mod flag {
    /// Create: the client's message was little endian. Write, Sample: the sample is.
    pub(super) const LITTLE_ENDIAN: u8 = 0x01;
    /// Create, Read, and the Status answering them: part of a replay to a new worker.
    /// Write: a resend to a new worker; the body holds the operation number of its first
    /// send after the position (if any).
    pub(super) const REPLAY: u8 = 0x02;
    /// Write: the client expects a STATUS for it, success included.
    pub(super) const STATUS_REQUESTED: u8 = 0x04;
    /// Write: SampleInfos in the data are in the spec dialect (else eProsima's).
    pub(super) const DIALECT_SPEC: u8 = 0x08;
    /// Sample (the bit of STATUS_REQUESTED, which Samples do not carry): the body holds the
    /// sample's origin after its identity.
    pub(super) const ORIGIN: u8 = 0x04;
    /// Sample (the bit of DIALECT_SPEC): its write was resent to this worker.
    pub(super) const RESENT: u8 = 0x08;
    /// Sample: it disposes its instance.
    pub(super) const DISPOSED: u8 = 0x10;
    /// Sample: it unregisters its instance.
    pub(super) const UNREGISTERED: u8 = 0x20;
    /// Any request: see [`crate::RequestMessage::progress_can_wait`].
    pub(super) const PROGRESS_CAN_WAIT: u8 = 0x40;
    /// Write: the body holds the write's [`super::InputPosition`] after its reception time.
    pub(super) const POSITION: u8 = 0x80;
}

/// Bytes of a Write's reception time, at the start of its body (little endian).
const RECEIVED_LEN: usize = 8;

/// Bytes of a resent Write's first operation number (little endian).
const RESEND_OF_LEN: usize = 8;

/// Bytes of an [`InputPosition`] in a body: the stream, then the message's sequence number,
/// the write's index in it and the epoch of the streams, little endian.
const POSITION_LEN: usize = 13;

fn write_position(p: &InputPosition, out: &mut [u8]) {
    out[0] = p.stream_id;
    out[1..3].copy_from_slice(&p.sequence.to_le_bytes());
    out[3..5].copy_from_slice(&p.write_index.to_le_bytes());
    out[5..13].copy_from_slice(&p.epoch.to_le_bytes());
}

fn read_position(b: &[u8; POSITION_LEN]) -> InputPosition {
    InputPosition {
        stream_id: b[0],
        sequence: u16::from_le_bytes([b[1], b[2]]),
        write_index: u16::from_le_bytes([b[3], b[4]]),
        epoch: u64::from_le_bytes([b[5], b[6], b[7], b[8], b[9], b[10], b[11], b[12]]),
    }
}

/// Why an IPC message was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum IpcError {
    /// Shorter than a header.
    #[error("truncated IPC message")]
    Truncated,
    /// Longer or shorter than its header says.
    #[error("IPC message of {actual} bytes declares {declared}")]
    Length {
        /// Header and body as the header says.
        declared: usize,
        /// As received.
        actual: usize,
    },
    /// Not an IPC message.
    #[error("bad IPC magic")]
    BadMagic,
    /// Another contract version.
    #[error("IPC version {0} not supported (this build speaks {IPC_VERSION})")]
    Version(u16),
    /// Unknown kind.
    #[error("unknown IPC message kind {0}")]
    Kind(u8),
    /// A reply kind where requests travel, or the other way round.
    #[error("IPC message kind {0} sent the wrong way")]
    Direction(u8),
    /// A body whose size the kind does not allow.
    #[error("IPC message kind {kind} with a body of {len} bytes")]
    Body {
        /// The kind.
        kind: u8,
        /// The body's size.
        len: usize,
    },
}

impl<'a> RequestMessage<'a> {
    /// `request` on `route`, with progress that wakes.
    pub fn new(route: Route, request: Request<'a>) -> Self {
        RequestMessage {
            route,
            progress_can_wait: false,
            request,
        }
    }

    /// Decodes a message of the request service.
    pub fn decode(buf: &'a [u8]) -> Result<Self, IpcError> {
        let (h, body) = Header::decode(buf)?;
        let empty = |request: Request<'a>| {
            if body.is_empty() {
                Ok(request)
            } else {
                Err(IpcError::Body {
                    kind: h.kind,
                    len: body.len(),
                })
            }
        };
        let has = |f: u8| h.flags & f != 0;
        let request = match h.kind {
            kind::FRONTEND_HELLO => empty(Request::FrontendHello)?,
            kind::CREATE => Request::Create {
                description: Cow::Borrowed(body),
                client_little_endian: has(flag::LITTLE_ENDIAN),
                replay: has(flag::REPLAY),
                readers_matched: h.readers,
            },
            kind::DELETE => empty(Request::Delete)?,
            kind::WRITE => {
                // A body too short for what its flags say it holds.
                let whole = body.len();
                let short = || IpcError::Body {
                    kind: h.kind,
                    len: whole,
                };
                let (received, body) =
                    body.split_first_chunk::<RECEIVED_LEN>().ok_or_else(short)?;
                let (position, data) = if has(flag::POSITION) {
                    let (p, data) = body.split_first_chunk::<POSITION_LEN>().ok_or_else(short)?;
                    (Some(read_position(p)), data)
                } else {
                    (None, body)
                };
                let (resend_of, data) = if has(flag::REPLAY) {
                    let (first, data) = data
                        .split_first_chunk::<RESEND_OF_LEN>()
                        .ok_or_else(short)?;
                    (Some(u64::from_le_bytes(*first)), data)
                } else {
                    (None, data)
                };
                Request::Write {
                    data: Cow::Borrowed(data),
                    data_format: h.data_format,
                    little_endian: has(flag::LITTLE_ENDIAN),
                    dialect: if has(flag::DIALECT_SPEC) {
                        Dialect::Spec
                    } else {
                        Dialect::Eprosima
                    },
                    status_requested: has(flag::STATUS_REQUESTED),
                    position,
                    received_us: u64::from_le_bytes(*received),
                    resend_of,
                }
            }
            kind::READ => Request::Read {
                spec: Cow::Borrowed(body),
                replay: has(flag::REPLAY),
            },
            kind::DELETE_CLIENT => empty(Request::DeleteClient)?,
            kind::PAUSE_READ => empty(Request::PauseRead)?,
            kind::RESUME_READ => empty(Request::ResumeRead)?,
            kind::REPLAY_DONE => empty(Request::ReplayDone)?,
            k if is_reply_kind(k) => return Err(IpcError::Direction(k)),
            k => return Err(IpcError::Kind(k)),
        };
        Ok(RequestMessage {
            route: h.route,
            progress_can_wait: has(flag::PROGRESS_CAN_WAIT),
            request,
        })
    }

    /// A copy that borrows nothing.
    pub fn into_owned(self) -> RequestMessage<'static> {
        RequestMessage {
            route: self.route,
            progress_can_wait: self.progress_can_wait,
            request: self.request.into_owned(),
        }
    }

    fn header(&self) -> Header {
        let mut h = Header::new(0, self.route);
        let set = |h: &mut Header, f: u8, on: bool| {
            if on {
                h.flags |= f;
            }
        };
        h.kind = match &self.request {
            Request::FrontendHello => kind::FRONTEND_HELLO,
            Request::Create {
                client_little_endian,
                replay,
                readers_matched,
                ..
            } => {
                set(&mut h, flag::LITTLE_ENDIAN, *client_little_endian);
                set(&mut h, flag::REPLAY, *replay);
                h.readers = *readers_matched;
                kind::CREATE
            }
            Request::Delete => kind::DELETE,
            Request::Write {
                data_format,
                little_endian,
                dialect,
                status_requested,
                position,
                resend_of,
                ..
            } => {
                set(&mut h, flag::LITTLE_ENDIAN, *little_endian);
                set(&mut h, flag::DIALECT_SPEC, *dialect == Dialect::Spec);
                set(&mut h, flag::STATUS_REQUESTED, *status_requested);
                set(&mut h, flag::POSITION, position.is_some());
                set(&mut h, flag::REPLAY, resend_of.is_some());
                h.data_format = *data_format;
                kind::WRITE
            }
            Request::Read { replay, .. } => {
                set(&mut h, flag::REPLAY, *replay);
                kind::READ
            }
            Request::DeleteClient => kind::DELETE_CLIENT,
            Request::PauseRead => kind::PAUSE_READ,
            Request::ResumeRead => kind::RESUME_READ,
            Request::ReplayDone => kind::REPLAY_DONE,
        };
        set(&mut h, flag::PROGRESS_CAN_WAIT, self.progress_can_wait);
        h
    }
}

impl RequestMessage<'_> {
    /// What a Write's body carries in front of its data: when it was received, its
    /// position if it has one, and the first operation number of a resend.
    fn write_prefix(&self) -> Option<(u64, Option<&InputPosition>, Option<u64>)> {
        match &self.request {
            Request::Write {
                position,
                received_us,
                resend_of,
                ..
            } => Some((*received_us, position.as_ref(), *resend_of)),
            _ => None,
        }
    }

    fn prefix_len(&self) -> usize {
        self.write_prefix().map_or(0, |(_, p, r)| {
            RECEIVED_LEN + p.map_or(0, |_| POSITION_LEN) + r.map_or(0, |_| RESEND_OF_LEN)
        })
    }
}

impl Encode for RequestMessage<'_> {
    fn encoded_len(&self) -> usize {
        HEADER_LEN + self.prefix_len() + self.request.body().len()
    }

    fn encode_into(&self, out: &mut [u8]) {
        let body = self.request.body();
        let prefix = self.prefix_len();
        self.header().write(out, prefix + body.len());
        if let Some((received, position, resend_of)) = self.write_prefix() {
            let mut at = HEADER_LEN + RECEIVED_LEN;
            out[HEADER_LEN..at].copy_from_slice(&received.to_le_bytes());
            if let Some(p) = position {
                write_position(p, &mut out[at..at + POSITION_LEN]);
                at += POSITION_LEN;
            }
            if let Some(first) = resend_of {
                out[at..at + RESEND_OF_LEN].copy_from_slice(&first.to_le_bytes());
            }
        }
        out[HEADER_LEN + prefix..].copy_from_slice(body);
    }
}

impl<'a> ReplyMessage<'a> {
    /// `reply` on `route`.
    pub fn new(route: Route, reply: Reply<'a>) -> Self {
        ReplyMessage { route, reply }
    }

    /// Decodes a message of a reply or the announce service.
    pub fn decode(buf: &'a [u8]) -> Result<Self, IpcError> {
        let (h, body) = Header::decode(buf)?;
        let wrong_body = || IpcError::Body {
            kind: h.kind,
            len: body.len(),
        };
        let empty = |reply: Reply<'a>| {
            if body.is_empty() {
                Ok(reply)
            } else {
                Err(wrong_body())
            }
        };
        let has = |f: u8| h.flags & f != 0;
        let reply = match h.kind {
            kind::WORKER_HELLO => empty(Reply::WorkerHello)?,
            kind::STATUS => {
                let [status, implementation_status] = *body else {
                    return Err(wrong_body());
                };
                Reply::Status {
                    result: ResultStatus {
                        status,
                        implementation_status,
                    },
                    replay: has(flag::REPLAY),
                }
            }
            kind::SAMPLE => {
                let (id, data) = body
                    .split_first_chunk::<SAMPLE_IDENTITY_LEN>()
                    .ok_or_else(wrong_body)?;
                if has(flag::RESENT) && !has(flag::ORIGIN) {
                    return Err(wrong_body());
                }
                let (origin, data) = if has(flag::ORIGIN) {
                    let (o, data) = data
                        .split_first_chunk::<SAMPLE_ORIGIN_LEN>()
                        .ok_or_else(wrong_body)?;
                    (Some(SampleOrigin::read(o, has(flag::RESENT))), data)
                } else {
                    (None, data)
                };
                Reply::Sample(Sample {
                    identity: SampleIdentity::read(id),
                    origin,
                    data: Cow::Borrowed(data),
                    little_endian: has(flag::LITTLE_ENDIAN),
                    disposed: has(flag::DISPOSED),
                    unregistered: has(flag::UNREGISTERED),
                })
            }
            kind::PROGRESS => {
                if body.len() != 16 {
                    return Err(wrong_body());
                }
                let word = |at: usize| {
                    let mut w = [0u8; 8];
                    w.copy_from_slice(&body[at..at + 8]);
                    u64::from_le_bytes(w)
                };
                Reply::Progress {
                    executed: word(0),
                    acknowledged: word(8),
                }
            }
            kind::READ_ENDED => empty(Reply::ReadEnded)?,
            kind::WRITER_MATCHED => empty(Reply::WriterMatched { readers: h.readers })?,
            kind::EXECUTED => {
                let p: &[u8; POSITION_LEN] = body.try_into().map_err(|_| wrong_body())?;
                Reply::Executed(read_position(p))
            }
            k if is_request_kind(k) => return Err(IpcError::Direction(k)),
            k => return Err(IpcError::Kind(k)),
        };
        Ok(ReplyMessage {
            route: h.route,
            reply,
        })
    }

    /// A copy that borrows nothing.
    pub fn into_owned(self) -> ReplyMessage<'static> {
        ReplyMessage {
            route: self.route,
            reply: self.reply.into_owned(),
        }
    }

    fn header(&self) -> Header {
        let mut h = Header::new(0, self.route);
        h.kind = match &self.reply {
            Reply::WorkerHello => kind::WORKER_HELLO,
            Reply::Status { replay, .. } => {
                if *replay {
                    h.flags |= flag::REPLAY;
                }
                kind::STATUS
            }
            Reply::Sample(s) => {
                for (on, f) in [
                    (s.little_endian, flag::LITTLE_ENDIAN),
                    (s.disposed, flag::DISPOSED),
                    (s.unregistered, flag::UNREGISTERED),
                    (s.origin.is_some(), flag::ORIGIN),
                    (s.origin.is_some_and(|o| o.resent), flag::RESENT),
                ] {
                    if on {
                        h.flags |= f;
                    }
                }
                kind::SAMPLE
            }
            Reply::Progress { .. } => kind::PROGRESS,
            Reply::ReadEnded => kind::READ_ENDED,
            Reply::WriterMatched { readers } => {
                h.readers = *readers;
                kind::WRITER_MATCHED
            }
            Reply::Executed(_) => kind::EXECUTED,
        };
        h
    }

    fn body_len(&self) -> usize {
        match &self.reply {
            Reply::Status { .. } => 2,
            Reply::Sample(s) => s.body_len(),
            Reply::Progress { .. } => 16,
            Reply::Executed(_) => POSITION_LEN,
            _ => 0,
        }
    }
}

impl Encode for ReplyMessage<'_> {
    fn encoded_len(&self) -> usize {
        HEADER_LEN + self.body_len()
    }

    fn encode_into(&self, out: &mut [u8]) {
        let len = self.body_len();
        self.header().write(out, len);
        let body = &mut out[HEADER_LEN..];
        match &self.reply {
            Reply::Status { result, .. } => {
                body.copy_from_slice(&[result.status, result.implementation_status])
            }
            Reply::Sample(s) => {
                s.identity.write(body);
                let mut at = SAMPLE_IDENTITY_LEN;
                if let Some(o) = &s.origin {
                    o.write_to(&mut body[at..at + SAMPLE_ORIGIN_LEN]);
                    at += SAMPLE_ORIGIN_LEN;
                }
                body[at..].copy_from_slice(&s.data);
            }
            Reply::Progress {
                executed,
                acknowledged,
            } => {
                body[..8].copy_from_slice(&executed.to_le_bytes());
                body[8..].copy_from_slice(&acknowledged.to_le_bytes());
            }
            Reply::Executed(p) => write_position(p, body),
            _ => {}
        }
    }
}

fn is_request_kind(k: u8) -> bool {
    (kind::FRONTEND_HELLO..=kind::REPLAY_DONE).contains(&k)
}

fn is_reply_kind(k: u8) -> bool {
    (kind::WORKER_HELLO..=kind::EXECUTED).contains(&k)
}

/// The fixed header of every message (private: users see [`Route`] and the enums).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Header {
    kind: u8,
    flags: u8,
    route: Route,
    data_format: u8,
    readers: u8,
}

impl Header {
    fn new(kind: u8, route: Route) -> Self {
        Header {
            kind,
            flags: 0,
            route,
            data_format: 0,
            readers: 0,
        }
    }

    /// Writes the header for a body of `body_len` bytes into `out[..HEADER_LEN]`.
    fn write(&self, out: &mut [u8], body_len: usize) {
        let r = &self.route;
        let o = &mut out[..HEADER_LEN];
        o[0..4].copy_from_slice(&IPC_MAGIC);
        o[4..6].copy_from_slice(&IPC_VERSION.to_le_bytes());
        o[6] = self.kind;
        o[7] = self.flags;
        o[8..12].copy_from_slice(&r.frontend_id.to_le_bytes());
        o[12..16].copy_from_slice(&r.generation.to_le_bytes());
        o[16..24].copy_from_slice(&r.op_seq.to_le_bytes());
        o[24..28].copy_from_slice(&r.client_key.0);
        o[28..30].copy_from_slice(&r.request_id.0);
        o[30..32].copy_from_slice(&r.object_id.0);
        // Bodies are bounded by MAX_BODY long before u32 overflows.
        o[32..36].copy_from_slice(&(body_len as u32).to_le_bytes());
        o[36] = self.data_format;
        o[37] = self.readers;
        o[38..40].copy_from_slice(&r.incarnation.to_le_bytes());
    }

    /// Splits a message into its header and body: the one place the magic, the version and
    /// the length are checked.
    fn decode(buf: &[u8]) -> Result<(Self, &[u8]), IpcError> {
        let Some((h, body)) = buf.split_first_chunk::<HEADER_LEN>() else {
            return Err(IpcError::Truncated);
        };
        if h[0..4] != IPC_MAGIC {
            return Err(IpcError::BadMagic);
        }
        let version = u16::from_le_bytes([h[4], h[5]]);
        if version != IPC_VERSION {
            return Err(IpcError::Version(version));
        }
        let u32_at = |i: usize| u32::from_le_bytes([h[i], h[i + 1], h[i + 2], h[i + 3]]);
        let mut seq = [0u8; 8];
        seq.copy_from_slice(&h[16..24]);
        let declared = u32_at(32) as usize;
        if declared != body.len() {
            return Err(IpcError::Length {
                declared: HEADER_LEN.saturating_add(declared),
                actual: buf.len(),
            });
        }
        let header = Header {
            kind: h[6],
            flags: h[7],
            route: Route {
                frontend_id: u32_at(8),
                incarnation: u16::from_le_bytes([h[38], h[39]]),
                generation: u32_at(12),
                op_seq: u64::from_le_bytes(seq),
                client_key: ClientKey([h[24], h[25], h[26], h[27]]),
                request_id: RequestId([h[28], h[29]]),
                object_id: ObjectId([h[30], h[31]]),
            },
            data_format: h[36],
            readers: h[37],
        };
        Ok((header, body))
    }
}
