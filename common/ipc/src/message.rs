//! The messages of the contract as types.
//!
//! Front-ends send [`Request`]s, the worker answers with [`Reply`]s; each travels with its
//! [`Route`] (which front-end process, operation, client and XRCE object it concerns). Both
//! ends and the tests' fake worker encode and decode through [`RequestMessage`] and
//! [`ReplyMessage`] only (their one codec is the private `codec` module: the byte layout,
//! kinds and flags, the version check, strict decoding into [`crate::IpcError`]), so a change
//! of a message is a change of a type that the compiler follows to every user.

use std::borrow::Cow;

pub use xrce_common::session::origin::WriteOrigin;
use xrce_common::session::stream::InputPosition;
use xrce_common::wire::{ClientKey, Dialect, ObjectId, RequestId, ResultStatus};

/// Bytes in front of every Sample's data: the DDS identity of the sample ([`SampleIdentity`]).
pub(crate) const SAMPLE_IDENTITY_LEN: usize = 24;

/// Bytes of a Sample's [`WriteOrigin`], after its identity when it has one.
pub(crate) const SAMPLE_ORIGIN_LEN: usize = 18;

/// Bytes of the header in front of every body.
pub const HEADER_LEN: usize = 40;

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
        /// Where it stood in the client's reliable input stream (`None` for a best-effort
        /// stream): the worker answers a successor's hello with the last one it executed
        /// ([`Reply::Executed`]).
        position: Option<InputPosition>,
        /// When the front-end took it from its client, in microseconds of that front-end
        /// process's clock: a writer that held samples for its readers (after a worker
        /// restart) writes them with the spacing they came with, not as one burst.
        received_us: u64,
        /// A resend to a new worker: the operation number this front-end process gave the
        /// write when it first sent it (the number of its [`WriteOrigin`]). `None` on the
        /// first send, where the route's `op_seq` is that number.
        resend_of: Option<u64>,
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
                position,
                received_us,
                resend_of,
            } => Request::Write {
                data: own(data),
                data_format,
                little_endian,
                dialect,
                status_requested,
                position,
                received_us,
                resend_of,
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
                position,
                received_us,
                resend_of,
            } => Request::Write {
                data: view(data),
                data_format: *data_format,
                little_endian: *little_endian,
                dialect: *dialect,
                status_requested: *status_requested,
                position: *position,
                received_us: *received_us,
                resend_of: *resend_of,
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

    pub(crate) fn body(&self) -> &[u8] {
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
    /// The client write it came from, for a sample one of this worker's writers wrote.
    pub origin: Option<SampleOrigin>,
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
        self.body_len() <= crate::MAX_BODY
    }

    /// Bytes of its message's body.
    pub(crate) fn body_len(&self) -> usize {
        SAMPLE_IDENTITY_LEN + self.origin.map_or(0, |_| SAMPLE_ORIGIN_LEN) + self.data.len()
    }

    /// A copy that borrows nothing.
    pub fn into_owned(self) -> Sample<'static> {
        Sample {
            data: Cow::Owned(self.data.into_owned()),
            ..self
        }
    }
}

/// The client write a sample came from ([`xrce_common::session::origin`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct SampleOrigin {
    /// The write, and which of its samples this is.
    pub write: WriteOrigin,
    /// The write was resent to this worker after its predecessor died: the reads of the
    /// subscribers may have delivered it already.
    pub resent: bool,
}

impl SampleOrigin {
    pub(crate) fn write_to(&self, out: &mut [u8]) {
        let w = &self.write;
        out[..4].copy_from_slice(&w.frontend.to_le_bytes());
        out[4..6].copy_from_slice(&w.incarnation.to_le_bytes());
        out[6..14].copy_from_slice(&w.write.to_le_bytes());
        out[14..SAMPLE_ORIGIN_LEN].copy_from_slice(&w.index.to_le_bytes());
    }

    pub(crate) fn read(b: &[u8; SAMPLE_ORIGIN_LEN], resent: bool) -> Self {
        let mut write = [0u8; 8];
        write.copy_from_slice(&b[6..14]);
        SampleOrigin {
            write: WriteOrigin {
                frontend: u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                incarnation: u16::from_le_bytes([b[4], b[5]]),
                write: u64::from_le_bytes(write),
                index: u32::from_le_bytes([b[14], b[15], b[16], b[17]]),
            },
            resent,
        }
    }
}

/// Implementation status of a STATUS refusing a replayed object: its client's replay was
/// under way when the last worker died ([`Reply::Status`]).
pub const REPLAY_REFUSED: u8 = 0xC1;

/// What the worker tells a front-end.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reply<'a> {
    /// A new worker generation is serving (on the announce service, and in answer to every
    /// [`Request::FrontendHello`]).
    WorkerHello,
    /// The result of a Create, Delete, Read, or of a Write that failed or asked for one. A
    /// replayed object refused because its client's replay crashed the last worker carries
    /// [`REPLAY_REFUSED`] as its implementation status: the front-end ends that session.
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
    /// The last write of the route's client on one of its reliable streams that this worker
    /// executed for the front-end (any of its processes): sent to a process that takes over,
    /// before the [`Reply::WorkerHello`] answering its hello, so that it does not hand over a
    /// second time what its predecessor handed over before storing that it took it.
    Executed(InputPosition),
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
            Reply::Executed(p) => Reply::Executed(p),
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

    pub(crate) fn write(&self, out: &mut [u8]) {
        out[..16].copy_from_slice(&self.writer);
        out[16..SAMPLE_IDENTITY_LEN].copy_from_slice(&self.sequence_number.to_le_bytes());
    }

    pub(crate) fn read(b: &[u8; SAMPLE_IDENTITY_LEN]) -> Self {
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
