//! The contract between front-ends and the DDS worker (version [`IPC_VERSION`]).
//!
//! Every message is a fixed little-endian [`IpcHeader`] followed by `body_len` bytes. Object
//! descriptions and read specifications travel in their XRCE encoding (little endian), so
//! there is one codec for them. Service names live under `xrce/<instance>/`.
//!
//! Flow: front-ends publish operations on [`request_service`] (many publishers, one worker);
//! the worker answers each front-end on its own [`reply_service`], and announces each new
//! worker generation on [`announce_service`]. Every data service has an event service of the
//! same name plus `.ev` so receivers block instead of polling.

#[cfg(feature = "shm")]
pub mod runtime_dir;
#[cfg(feature = "shm")]
pub mod shm;
#[cfg(feature = "shm")]
pub mod status;

use crate::wire::{ClientKey, ObjectId, RequestId};

/// Version of this contract; both sides drop (and log) messages of another version.
pub const IPC_VERSION: u16 = 6;
/// Magic at the start of every message.
pub const IPC_MAGIC: [u8; 4] = *b"XRIP";

/// Largest message body carried (a sample of up to 1 MiB, the largest message the session
/// core reassembles, plus slack); bigger samples are refused.
pub const MAX_BODY: usize = (1 << 20) + 512;
/// Body size the shared-memory segments are first laid out for; larger bodies grow them.
pub const INITIAL_BODY: usize = 65_536 + 512;
/// Buffer of each publisher→subscriber connection in messages.
pub const CHANNEL_DEPTH: usize = 256;
/// Operations a front-end may have sent and not seen processed; below [`CHANNEL_DEPTH`] so the
/// worker's queue never overflows (an overflow would silently lose operations).
pub const IN_FLIGHT_WINDOW: u64 = 192;

/// What a message is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum MessageKind {
    /// Front-end → worker: I (re)started; the entities you hold for me are mine to take back
    /// by replaying their CREATEs (see [`MessageKind::ReplayDone`]).
    FrontendHello = 1,
    /// Front-end → worker: create an object (body: XRCE ObjectVariant, LE).
    Create = 2,
    /// Front-end → worker: delete an object and its children.
    Delete = 3,
    /// Front-end → worker: write a sample (body: serialized sample; flag LE).
    Write = 4,
    /// Front-end → worker: start or replace a read (body: XRCE ReadSpecification, LE).
    Read = 5,
    /// Front-end → worker: a session ended; delete all its objects.
    DeleteClient = 6,
    /// Front-end → worker: the client is not keeping up with this read; leave its samples
    /// in the DDS reader (whose history QoS applies) until ResumeRead.
    PauseRead = 7,
    /// Front-end → worker: deliver the read's samples again.
    ResumeRead = 8,
    /// Front-end → worker: the replay that follows my hello is complete; entities of mine
    /// it did not take back can go.
    ReplayDone = 9,
    /// Worker → all: a new worker generation is serving.
    WorkerHello = 16,
    /// Worker → front-end: the result of a Create, Delete, Write or Read (body: status, detail).
    Status = 17,
    /// Worker → front-end: a sample for an active read (body: its [`SampleIdentity`], then
    /// the serialized sample; flag LE).
    Sample = 18,
    /// Worker → front-end: every operation up to `op_seq` has left the queue; the body (two
    /// u64 LE) says up to which one they have all been executed (writes held by a writer that
    /// waits for its readers are taken but not executed yet), then up to which one every
    /// write was acknowledged by all the matched reliable readers of its DDS writer (the
    /// front-end stops keeping those for a resend to a restarted worker).
    Progress = 19,
    /// Worker → front-end: a read finished (its delivery limits were reached).
    ReadEnded = 20,
    /// Worker → front-end: how many DDS readers the DDS writer of this data writer matched
    /// now (`readers`); sent when it changes.
    WriterMatched = 21,
}

impl MessageKind {
    fn from_u8(v: u8) -> Option<Self> {
        use MessageKind::*;
        Some(match v {
            1 => FrontendHello,
            2 => Create,
            3 => Delete,
            4 => Write,
            5 => Read,
            6 => DeleteClient,
            7 => PauseRead,
            8 => ResumeRead,
            9 => ReplayDone,
            16 => WorkerHello,
            17 => Status,
            18 => Sample,
            19 => Progress,
            20 => ReadEnded,
            21 => WriterMatched,
            _ => return None,
        })
    }
}

/// Flag: the body's sample is little endian.
pub const FLAG_LITTLE_ENDIAN: u8 = 0x01;
/// Flag on Create/Delete/Read: part of a replay to a new worker; answer it but the client
/// is not waiting for the answer.
pub const FLAG_REPLAY: u8 = 0x02;
/// Flag on Write: the client expects a STATUS for it (spec dialect), success included.
pub const FLAG_STATUS_REQUESTED: u8 = 0x04;
/// Flag on Write: SampleInfos in the body are in the spec dialect (else eProsima's).
pub const FLAG_DIALECT_SPEC: u8 = 0x08;
/// Bytes in front of every Sample body: the DDS identity of the sample ([`SampleIdentity`]).
pub const SAMPLE_IDENTITY_LEN: usize = 24;

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

    /// The identity as it leads a Sample body.
    pub fn encode(&self) -> [u8; SAMPLE_IDENTITY_LEN] {
        let mut out = [0u8; SAMPLE_IDENTITY_LEN];
        out[..16].copy_from_slice(&self.writer);
        out[16..].copy_from_slice(&self.sequence_number.to_le_bytes());
        out
    }

    /// Splits a Sample body into the identity and the sample; `None` if it is too short.
    pub fn split(body: &[u8]) -> Option<(Self, &[u8])> {
        let (id, sample) = body.split_at_checked(SAMPLE_IDENTITY_LEN)?;
        let mut writer = [0u8; 16];
        writer.copy_from_slice(&id[..16]);
        let mut seq = [0u8; 8];
        seq.copy_from_slice(&id[16..]);
        Some((
            SampleIdentity {
                writer,
                sequence_number: i64::from_le_bytes(seq),
            },
            sample,
        ))
    }
}

/// Flag on Write and Sample: the sample disposes its instance.
pub const FLAG_DISPOSED: u8 = 0x10;
/// Flag on Write and Sample: the sample unregisters its instance.
pub const FLAG_UNREGISTERED: u8 = 0x20;
/// Flag on a request: the front-end needs no wake-up for this operation's progress (a
/// best-effort write sent with most of the window free). The worker still sends progress
/// for it, but only wakes the front-end for progress that covers an operation sent without
/// the flag: the front-end reads it on its next wake-up, which its next datagram brings.
/// Without the flag (and from a front-end that never sets it) every progress wakes.
pub const FLAG_PROGRESS_CAN_WAIT: u8 = 0x40;

/// The fixed header of every IPC message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IpcHeader {
    /// What the message is.
    pub kind: MessageKind,
    /// [`FLAG_LITTLE_ENDIAN`], [`FLAG_REPLAY`].
    pub flags: u8,
    /// The front-end the message comes from or goes to.
    pub frontend_id: u32,
    /// The worker generation (set by the worker; 0 from front-ends).
    pub generation: u32,
    /// Front-end operation sequence number (requests), or the one answered (replies).
    pub op_seq: u64,
    /// The client concerned.
    pub client_key: ClientKey,
    /// The XRCE request id to echo.
    pub request_id: RequestId,
    /// The XRCE object concerned.
    pub object_id: ObjectId,
    /// Write: the XRCE DataFormat of the body (the bytes after the WRITE_DATA's
    /// BaseObjectRequest); 0 = FORMAT_DATA, a bare sample.
    pub data_format: u8,
    /// Which process of the front-end (it changes with every restart): on requests, the
    /// sender's; on replies, the one they are for. A restarted front-end ignores replies
    /// meant for its predecessor, and the worker finishes the predecessor's queued
    /// operations before it serves the successor. 0 on announcements.
    pub incarnation: u16,
    /// A replayed Create of a data writer: how many DDS readers its writer had matched (the
    /// new one holds its samples until as many match again, or a bound passes);
    /// WriterMatched: the count now. Saturates at 255; 0 otherwise.
    pub readers: u8,
}

/// Why an IPC message was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum IpcError {
    /// Shorter than a header, or shorter than the header says.
    #[error("truncated IPC message")]
    Truncated,
    /// Not an IPC message.
    #[error("bad IPC magic")]
    BadMagic,
    /// Another contract version.
    #[error("IPC version {0} not supported (this build speaks {IPC_VERSION})")]
    Version(u16),
    /// Unknown kind.
    #[error("unknown IPC message kind {0}")]
    Kind(u8),
}

impl IpcHeader {
    /// Encoded length.
    pub const LEN: usize = 40;

    /// A header for `kind` with everything else zero.
    pub fn new(kind: MessageKind) -> Self {
        IpcHeader {
            kind,
            flags: 0,
            frontend_id: 0,
            generation: 0,
            op_seq: 0,
            client_key: ClientKey::INVALID,
            request_id: RequestId::default(),
            object_id: ObjectId::INVALID,
            data_format: 0,
            incarnation: 0,
            readers: 0,
        }
    }

    /// Writes the header for a body of `body_len` bytes into `out[..Self::LEN]`.
    ///
    /// `out` must be at least [`Self::LEN`] bytes long.
    pub fn write(&self, out: &mut [u8], body_len: usize) {
        let o = &mut out[..Self::LEN];
        o[0..4].copy_from_slice(&IPC_MAGIC);
        o[4..6].copy_from_slice(&IPC_VERSION.to_le_bytes());
        o[6] = self.kind as u8;
        o[7] = self.flags;
        o[8..12].copy_from_slice(&self.frontend_id.to_le_bytes());
        o[12..16].copy_from_slice(&self.generation.to_le_bytes());
        o[16..24].copy_from_slice(&self.op_seq.to_le_bytes());
        o[24..28].copy_from_slice(&self.client_key.0);
        o[28..30].copy_from_slice(&self.request_id.0);
        o[30..32].copy_from_slice(&self.object_id.0);
        o[32..36].copy_from_slice(&(body_len as u32).to_le_bytes());
        o[36] = self.data_format;
        o[37] = self.readers;
        o[38..40].copy_from_slice(&self.incarnation.to_le_bytes());
    }

    /// Encodes a whole message.
    pub fn encode(&self, body: &[u8]) -> Vec<u8> {
        let mut v = vec![0u8; Self::LEN + body.len()];
        self.write(&mut v, body.len());
        v[Self::LEN..].copy_from_slice(body);
        v
    }

    /// Decodes a message into its header and body.
    pub fn decode(buf: &[u8]) -> Result<(Self, &[u8]), IpcError> {
        if buf.len() < Self::LEN {
            return Err(IpcError::Truncated);
        }
        if buf[0..4] != IPC_MAGIC {
            return Err(IpcError::BadMagic);
        }
        let version = u16::from_le_bytes([buf[4], buf[5]]);
        if version != IPC_VERSION {
            return Err(IpcError::Version(version));
        }
        let kind = MessageKind::from_u8(buf[6]).ok_or(IpcError::Kind(buf[6]))?;
        let u32_at = |i: usize| u32::from_le_bytes([buf[i], buf[i + 1], buf[i + 2], buf[i + 3]]);
        let mut seq = [0u8; 8];
        seq.copy_from_slice(&buf[16..24]);
        let body_len = u32_at(32) as usize;
        let end = Self::LEN.checked_add(body_len).ok_or(IpcError::Truncated)?;
        let body = buf.get(Self::LEN..end).ok_or(IpcError::Truncated)?;
        let h = IpcHeader {
            kind,
            flags: buf[7],
            frontend_id: u32_at(8),
            generation: u32_at(12),
            op_seq: u64::from_le_bytes(seq),
            client_key: ClientKey([buf[24], buf[25], buf[26], buf[27]]),
            request_id: RequestId([buf[28], buf[29]]),
            object_id: ObjectId([buf[30], buf[31]]),
            data_format: buf[36],
            incarnation: u16::from_le_bytes([buf[38], buf[39]]),
            readers: buf[37],
        };
        Ok((h, body))
    }
}

/// Operations from all front-ends to the worker.
pub fn request_service(instance: &str) -> String {
    format!("xrce/{instance}/requests")
}

/// Replies and samples from the worker to one front-end.
pub fn reply_service(instance: &str, frontend_id: u32) -> String {
    format!("xrce/{instance}/replies/{frontend_id}")
}

/// Worker generation announcements.
pub fn announce_service(instance: &str) -> String {
    format!("xrce/{instance}/announce")
}

/// The instance name an agent takes when none is given: `<label>-<8 hex digits>`, the digits
/// a CRC-32 of what the agent serves (`identity`: its transport's address and port, or its
/// devices) and of the network namespace it runs in (its inode, as `/proc/self/ns/net`
/// shows it). The same command line in the same namespace finds the same instance, and so
/// the sessions its predecessor stored, after a restart of the whole agent; two agents that
/// serve different things (one port on two addresses, one command line in two network
/// namespaces) never share one. Stays within the 32 characters an instance may have.
pub fn derived_instance(label: &str, identity: &str) -> String {
    let netns = std::fs::read_link("/proc/self/ns/net")
        .map(|p| p.display().to_string())
        .unwrap_or_default();
    derived_instance_in(label, identity, &netns)
}

/// [`derived_instance`] for a given network namespace.
pub fn derived_instance_in(label: &str, identity: &str, netns: &str) -> String {
    const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);
    let mut digest = CRC.digest();
    for part in [label, identity, netns] {
        digest.update(part.as_bytes());
        digest.update(&[0]);
    }
    let label: String = label
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .take(32 - 9)
        .collect();
    format!("{label}-{:08x}", digest.finalize())
}

/// The event service paired with a data service.
pub fn event_service(data_service: &str) -> String {
    format!("{data_service}.ev")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_instances_are_stable_and_tell_agents_apart() {
        let a = derived_instance_in("udp4-8888", "0.0.0.0:8888", "net:[4026531840]");
        assert_eq!(
            a,
            derived_instance_in("udp4-8888", "0.0.0.0:8888", "net:[4026531840]")
        );
        assert!(a.starts_with("udp4-8888-") && a.len() == 18, "{a}");
        assert_ne!(
            a,
            derived_instance_in("udp4-8888", "10.0.0.1:8888", "net:[4026531840]")
        );
        assert_ne!(
            a,
            derived_instance_in("udp4-8888", "0.0.0.0:8888", "net:[4026532000]")
        );
        let long = derived_instance_in(&"x".repeat(40), "", "");
        assert!(long.len() <= 32, "{long}");
        assert_eq!(derived_instance_in("a.b", "", "").chars().nth(1), Some('_'));
    }

    #[test]
    fn header_round_trips_and_rejects_other_versions() {
        let h = IpcHeader {
            kind: MessageKind::Write,
            flags: FLAG_LITTLE_ENDIAN,
            frontend_id: 7,
            generation: 3,
            op_seq: 1 << 40,
            client_key: ClientKey([1, 2, 3, 4]),
            request_id: RequestId([0, 9]),
            object_id: ObjectId::new(1, 5),
            data_format: 0x0A,
            incarnation: 0xBEEF,
            readers: 3,
        };
        let m = h.encode(b"body");
        assert_eq!(IpcHeader::decode(&m), Ok((h, &b"body"[..])));
        let mut other = m.clone();
        other[4] = 1;
        assert_eq!(IpcHeader::decode(&other), Err(IpcError::Version(1)));
        assert_eq!(
            IpcHeader::decode(&m[..m.len() - 1]),
            Err(IpcError::Truncated)
        );
        let mut bad_kind = m;
        bad_kind[6] = 99;
        assert_eq!(IpcHeader::decode(&bad_kind), Err(IpcError::Kind(99)));
    }
}
