//! The messages of the contract as types, and their one codec.
//!
//! Front-ends send [`Request`]s, the worker answers with [`Reply`]s; each travels with its
//! [`Route`] (which front-end process, operation, client and XRCE object it concerns). Both
//! ends and the tests' fake worker encode and decode through [`RequestMessage`] and
//! [`ReplyMessage`] only, so a change of a message is a change of a type that the compiler
//! follows to every user. The byte layout (a fixed 40-byte header, then the body) and its
//! flags are private to this module; the version is checked in one place, [`Header::decode`].
//!
//! Decoding is strict: a kind sent the wrong way, a body of the wrong size or a message
//! longer or shorter than its header says is an [`IpcError`], never a guess.

use std::borrow::Cow;

use crate::{IPC_MAGIC, IPC_VERSION};
use xrce_common::wire::{ClientKey, Dialect, ObjectId, RequestId, ResultStatus};

/// Bytes in front of every Sample's data: the DDS identity of the sample ([`SampleIdentity`]).
const SAMPLE_IDENTITY_LEN: usize = 24;

/// Bytes of the header in front of every body.
pub const HEADER_LEN: usize = 40;

/// Message kinds on the wire.
mod kind {
    pub const FRONTEND_HELLO: u8 = 1;
    pub const CREATE: u8 = 2;
    pub const DELETE: u8 = 3;
    pub const WRITE: u8 = 4;
    pub const READ: u8 = 5;
    pub const DELETE_CLIENT: u8 = 6;
    pub const PAUSE_READ: u8 = 7;
    pub const RESUME_READ: u8 = 8;
    pub const REPLAY_DONE: u8 = 9;
    pub const WORKER_HELLO: u8 = 16;
    pub const STATUS: u8 = 17;
    pub const SAMPLE: u8 = 18;
    pub const PROGRESS: u8 = 19;
    pub const READ_ENDED: u8 = 20;
    pub const WRITER_MATCHED: u8 = 21;
}

/// Header flags; which kinds carry each is written beside it.
mod flag {
    /// Create: the client's message was little endian. Write, Sample: the sample is.
    pub const LITTLE_ENDIAN: u8 = 0x01;
    /// Create, Read, and the Status answering them: part of a replay to a new worker.
    pub const REPLAY: u8 = 0x02;
    /// Write: the client expects a STATUS for it, success included.
    pub const STATUS_REQUESTED: u8 = 0x04;
    /// Write: SampleInfos in the data are in the spec dialect (else eProsima's).
    pub const DIALECT_SPEC: u8 = 0x08;
    /// Sample: it disposes its instance.
    pub const DISPOSED: u8 = 0x10;
    /// Sample: it unregisters its instance.
    pub const UNREGISTERED: u8 = 0x20;
    /// Any request: see [`crate::RequestMessage::progress_can_wait`].
    pub const PROGRESS_CAN_WAIT: u8 = 0x40;
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

/// Which front-end process, operation, client and XRCE object a message concerns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub struct Route {
    /// The front-end the message comes from or goes to.
    pub frontend_id: u32,
    /// Which process of the front-end (it changes with every restart): on requests, the
    /// sender's; on replies, the one they are for. A restarted front-end ignores replies
    /// meant for its predecessor, and the worker finishes the predecessor's queued operations
    /// before it serves the successor. 0 on announcements.
    pub incarnation: u16,
    /// The worker generation (set by the worker; 0 from front-ends).
    pub generation: u32,
    /// Requests: the front-end's operation sequence number. Status: the one answered.
    /// Progress: every operation up to it has left the worker's queue.
    pub op_seq: u64,
    /// The client concerned.
    pub client_key: ClientKey,
    /// The XRCE request id to echo.
    pub request_id: RequestId,
    /// The XRCE object concerned.
    pub object_id: ObjectId,
}

impl Route {
    /// A route to or from front-end `frontend_id` that concerns no client.
    pub fn frontend(frontend_id: u32) -> Self {
        Route {
            frontend_id,
            ..Route::default()
        }
    }

    /// A route concerning object `object_id` of `client_key`, for XRCE request `request_id`.
    pub fn object(
        frontend_id: u32,
        client_key: ClientKey,
        request_id: RequestId,
        object_id: ObjectId,
    ) -> Self {
        Route {
            frontend_id,
            client_key,
            request_id,
            object_id,
            ..Route::default()
        }
    }
}

/// What a front-end asks of the worker.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request<'a> {
    /// I (re)started; the entities you hold for me are mine to take back by replaying their
    /// CREATEs (see [`Request::ReplayDone`]).
    FrontendHello,
    /// Create an object.
    Create {
        /// Its XRCE ObjectVariant, little endian.
        description: Cow<'a, [u8]>,
        /// The byte order of the client's message, in which the binary representations
        /// inside the description are written.
        client_little_endian: bool,
        /// Part of a replay to a new worker: answered, but no client waits for the answer.
        replay: bool,
        /// A replayed data writer: how many DDS readers its writer had matched (the new one
        /// holds its samples until as many match again, or a bound passes). Saturates at
        /// 255; 0 otherwise.
        readers_matched: u8,
    },
    /// Delete an object and its children.
    Delete,
    /// Write the samples of one WRITE_DATA.
    Write {
        /// The bytes after the WRITE_DATA's BaseObjectRequest.
        data: Cow<'a, [u8]>,
        /// Its XRCE DataFormat (0 = FORMAT_DATA, a bare sample).
        data_format: u8,
        /// The samples' byte order.
        little_endian: bool,
        /// How SampleInfos in the data are laid out.
        dialect: Dialect,
        /// The client expects a STATUS for it, success included.
        status_requested: bool,
    },
    /// Start or replace a read.
    Read {
        /// Its XRCE ReadSpecification, little endian.
        spec: Cow<'a, [u8]>,
        /// Part of a replay to a new worker (samples the predecessor may not have delivered
        /// are offered again).
        replay: bool,
    },
    /// A session ended; delete all its objects.
    DeleteClient,
    /// The client is not keeping up with this read; leave its samples in the DDS reader
    /// (whose history QoS applies) until [`Request::ResumeRead`].
    PauseRead,
    /// Deliver the read's samples again.
    ResumeRead,
    /// The replay that follows my hello is complete; entities of mine it did not take back
    /// can go.
    ReplayDone,
}

impl Request<'_> {
    /// A copy that borrows nothing.
    pub fn into_owned(self) -> Request<'static> {
        let own = |c: Cow<'_, [u8]>| Cow::Owned(c.into_owned());
        match self {
            Request::FrontendHello => Request::FrontendHello,
            Request::Create {
                description,
                client_little_endian,
                replay,
                readers_matched,
            } => Request::Create {
                description: own(description),
                client_little_endian,
                replay,
                readers_matched,
            },
            Request::Delete => Request::Delete,
            Request::Write {
                data,
                data_format,
                little_endian,
                dialect,
                status_requested,
            } => Request::Write {
                data: own(data),
                data_format,
                little_endian,
                dialect,
                status_requested,
            },
            Request::Read { spec, replay } => Request::Read {
                spec: own(spec),
                replay,
            },
            Request::DeleteClient => Request::DeleteClient,
            Request::PauseRead => Request::PauseRead,
            Request::ResumeRead => Request::ResumeRead,
            Request::ReplayDone => Request::ReplayDone,
        }
    }

    /// A view of this request that borrows its bytes (to send a queued request without
    /// copying it).
    pub fn borrowed(&self) -> Request<'_> {
        fn view(c: &[u8]) -> Cow<'_, [u8]> {
            Cow::Borrowed(c)
        }
        match self {
            Request::Create {
                description,
                client_little_endian,
                replay,
                readers_matched,
            } => Request::Create {
                description: view(description),
                client_little_endian: *client_little_endian,
                replay: *replay,
                readers_matched: *readers_matched,
            },
            Request::Write {
                data,
                data_format,
                little_endian,
                dialect,
                status_requested,
            } => Request::Write {
                data: view(data),
                data_format: *data_format,
                little_endian: *little_endian,
                dialect: *dialect,
                status_requested: *status_requested,
            },
            Request::Read { spec, replay } => Request::Read {
                spec: view(spec),
                replay: *replay,
            },
            Request::FrontendHello => Request::FrontendHello,
            Request::Delete => Request::Delete,
            Request::DeleteClient => Request::DeleteClient,
            Request::PauseRead => Request::PauseRead,
            Request::ResumeRead => Request::ResumeRead,
            Request::ReplayDone => Request::ReplayDone,
        }
    }

    /// Whether this is a write (the only kind whose progress may wait, and the kind a
    /// restarted worker gets again).
    pub fn is_write(&self) -> bool {
        matches!(self, Request::Write { .. })
    }

    /// The kind's name, for logs.
    pub fn name(&self) -> &'static str {
        match self {
            Request::FrontendHello => "FrontendHello",
            Request::Create { .. } => "Create",
            Request::Delete => "Delete",
            Request::Write { .. } => "Write",
            Request::Read { .. } => "Read",
            Request::DeleteClient => "DeleteClient",
            Request::PauseRead => "PauseRead",
            Request::ResumeRead => "ResumeRead",
            Request::ReplayDone => "ReplayDone",
        }
    }

    fn body(&self) -> &[u8] {
        match self {
            Request::Create { description, .. } => description,
            Request::Write { data, .. } => data,
            Request::Read { spec, .. } => spec,
            _ => &[],
        }
    }
}

/// A sample the worker took for an active read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Sample<'a> {
    /// Which DDS writer wrote it, and its sequence number there.
    pub identity: SampleIdentity,
    /// The serialized sample.
    pub data: Cow<'a, [u8]>,
    /// Its byte order.
    pub little_endian: bool,
    /// It disposes its instance.
    pub disposed: bool,
    /// It unregisters its instance.
    pub unregistered: bool,
}

impl Sample<'_> {
    /// Whether it fits in a message ([`crate::MAX_BODY`]); a larger one is not sent.
    pub fn fits(&self) -> bool {
        SAMPLE_IDENTITY_LEN + self.data.len() <= crate::MAX_BODY
    }

    /// A copy that borrows nothing.
    pub fn into_owned(self) -> Sample<'static> {
        Sample {
            data: Cow::Owned(self.data.into_owned()),
            ..self
        }
    }
}

/// What the worker tells a front-end.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reply<'a> {
    /// A new worker generation is serving (on the announce service, and in answer to every
    /// [`Request::FrontendHello`]).
    WorkerHello,
    /// The result of a Create, Delete, Read, or of a Write that failed or asked for one.
    Status {
        /// The XRCE result.
        result: ResultStatus,
        /// It answers a replayed operation.
        replay: bool,
    },
    /// A sample for an active read.
    Sample(Sample<'a>),
    /// Every operation up to the route's `op_seq` has left the queue.
    Progress {
        /// Up to which operation they have all been executed (writes held by a writer that
        /// waits for its readers are taken but not executed yet).
        executed: u64,
        /// Up to which operation every write was acknowledged by all the matched reliable
        /// readers of its DDS writer (the front-end stops keeping those for a resend to a
        /// restarted worker).
        acknowledged: u64,
    },
    /// A read finished (its delivery limits were reached).
    ReadEnded,
    /// How many DDS readers the DDS writer of this data writer matched now (saturating at
    /// 255); sent when it changes.
    WriterMatched {
        /// The count.
        readers: u8,
    },
}

impl Reply<'_> {
    /// A copy that borrows nothing.
    pub fn into_owned(self) -> Reply<'static> {
        match self {
            Reply::WorkerHello => Reply::WorkerHello,
            Reply::Status { result, replay } => Reply::Status { result, replay },
            Reply::Sample(s) => Reply::Sample(s.into_owned()),
            Reply::Progress {
                executed,
                acknowledged,
            } => Reply::Progress {
                executed,
                acknowledged,
            },
            Reply::ReadEnded => Reply::ReadEnded,
            Reply::WriterMatched { readers } => Reply::WriterMatched { readers },
        }
    }
}

/// Which DDS writer wrote a sample, and its sequence number there: what a front-end
/// remembers per read so that a replayed read does not hand a client a sample again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct SampleIdentity {
    /// The writer's GUID (all zero: unknown).
    pub writer: [u8; 16],
    /// The writer's sequence number of the sample.
    pub sequence_number: i64,
}

impl SampleIdentity {
    /// Whether the identity is known.
    pub fn is_known(&self) -> bool {
        self.writer != [0; 16]
    }

    fn write(&self, out: &mut [u8]) {
        out[..16].copy_from_slice(&self.writer);
        out[16..SAMPLE_IDENTITY_LEN].copy_from_slice(&self.sequence_number.to_le_bytes());
    }

    fn read(b: &[u8; SAMPLE_IDENTITY_LEN]) -> Self {
        let mut writer = [0u8; 16];
        writer.copy_from_slice(&b[..16]);
        let mut seq = [0u8; 8];
        seq.copy_from_slice(&b[16..]);
        SampleIdentity {
            writer,
            sequence_number: i64::from_le_bytes(seq),
        }
    }
}

/// A message that can be written into a buffer of its [`Encode::encoded_len`] (a loan of
/// shared memory, or a vector).
pub trait Encode {
    /// Header and body.
    fn encoded_len(&self) -> usize;
    /// Writes the message into `out`, which is exactly [`Encode::encoded_len`] bytes long.
    fn encode_into(&self, out: &mut [u8]);
    /// The message as bytes.
    fn encode(&self) -> Vec<u8> {
        let mut v = vec![0u8; self.encoded_len()];
        self.encode_into(&mut v);
        v
    }
}

/// A request and its route: what travels on the request service.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestMessage<'a> {
    /// What it concerns.
    pub route: Route,
    /// The front-end needs no wake-up for this operation's progress (a best-effort write
    /// sent with most of the window free). The worker still reports progress for it, but
    /// only wakes the front-end for progress that covers an operation sent without it: the
    /// front-end reads it on its next wake-up, which its next datagram brings.
    pub progress_can_wait: bool,
    /// What is asked.
    pub request: Request<'a>,
}

/// A reply and its route: what travels on a front-end's reply service and on the announce
/// service.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReplyMessage<'a> {
    /// What it concerns.
    pub route: Route,
    /// What is said.
    pub reply: Reply<'a>,
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
            kind::WRITE => Request::Write {
                data: Cow::Borrowed(body),
                data_format: h.data_format,
                little_endian: has(flag::LITTLE_ENDIAN),
                dialect: if has(flag::DIALECT_SPEC) {
                    Dialect::Spec
                } else {
                    Dialect::Eprosima
                },
                status_requested: has(flag::STATUS_REQUESTED),
            },
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
                ..
            } => {
                set(&mut h, flag::LITTLE_ENDIAN, *little_endian);
                set(&mut h, flag::DIALECT_SPEC, *dialect == Dialect::Spec);
                set(&mut h, flag::STATUS_REQUESTED, *status_requested);
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

impl Encode for RequestMessage<'_> {
    fn encoded_len(&self) -> usize {
        HEADER_LEN + self.request.body().len()
    }

    fn encode_into(&self, out: &mut [u8]) {
        let body = self.request.body();
        self.header().write(out, body.len());
        out[HEADER_LEN..].copy_from_slice(body);
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
                Reply::Sample(Sample {
                    identity: SampleIdentity::read(id),
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
        };
        h
    }

    fn body_len(&self) -> usize {
        match &self.reply {
            Reply::Status { .. } => 2,
            Reply::Sample(s) => SAMPLE_IDENTITY_LEN + s.data.len(),
            Reply::Progress { .. } => 16,
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
                body[SAMPLE_IDENTITY_LEN..].copy_from_slice(&s.data);
            }
            Reply::Progress {
                executed,
                acknowledged,
            } => {
                body[..8].copy_from_slice(&executed.to_le_bytes());
                body[8..].copy_from_slice(&acknowledged.to_le_bytes());
            }
            _ => {}
        }
    }
}

fn is_request_kind(k: u8) -> bool {
    (kind::FRONTEND_HELLO..=kind::REPLAY_DONE).contains(&k)
}

fn is_reply_kind(k: u8) -> bool {
    (kind::WORKER_HELLO..=kind::WRITER_MATCHED).contains(&k)
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
