//! Identifiers and small value types shared by many payloads (Annex A).

use std::fmt;

/// The 4-octet secret that identifies a client (§7.8.1).
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct ClientKey(pub [u8; 4]);

impl ClientKey {
    /// CLIENTKEY_INVALID.
    pub const INVALID: ClientKey = ClientKey([0; 4]);
}

impl fmt::Debug for ClientKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [a, b, c, d] = self.0;
        write!(f, "{a:02X}{b:02X}{c:02X}{d:02X}")
    }
}

impl fmt::Display for ClientKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self, f)
    }
}

/// `ObjectKind` values (§7.7.5, Annex A, plus eProsima's requester/replier).
pub mod object_kind {
    /// No object (an invalid id).
    pub const INVALID: u8 = 0x00;
    /// A DDS domain participant.
    pub const PARTICIPANT: u8 = 0x01;
    /// A topic.
    pub const TOPIC: u8 = 0x02;
    /// A publisher.
    pub const PUBLISHER: u8 = 0x03;
    /// A subscriber.
    pub const SUBSCRIBER: u8 = 0x04;
    /// A data writer.
    pub const DATAWRITER: u8 = 0x05;
    /// A data reader.
    pub const DATAREADER: u8 = 0x06;
    /// A requester (eProsima): a writer of requests and a reader of replies.
    pub const REQUESTER: u8 = 0x07;
    /// A replier (eProsima): a reader of requests and a writer of replies.
    pub const REPLIER: u8 = 0x08;
    /// A type.
    pub const TYPE: u8 = 0x0A;
    /// A QoS profile.
    pub const QOSPROFILE: u8 = 0x0B;
    /// An application.
    pub const APPLICATION: u8 = 0x0C;
    /// The agent itself.
    pub const AGENT: u8 = 0x0D;
    /// The client (its session).
    pub const CLIENT: u8 = 0x0E;
    /// Anything else.
    pub const OTHER: u8 = 0x0F;
}

/// A 2-octet object id: 12-bit prefix and the object kind in the low nibble of byte 1.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct ObjectId(pub [u8; 2]);

impl ObjectId {
    /// OBJECTID_INVALID.
    pub const INVALID: ObjectId = ObjectId([0x00, 0x00]);
    /// OBJECTID_AGENT.
    pub const AGENT: ObjectId = ObjectId([0xFF, 0xFD]);
    /// OBJECTID_CLIENT: DELETE of this id deletes the session.
    pub const CLIENT: ObjectId = ObjectId([0xFF, 0xFE]);
    /// OBJECTID_SESSION.
    pub const SESSION: ObjectId = ObjectId([0xFF, 0xFF]);

    /// Builds an id from a 12-bit prefix number and a kind, the way the eProsima client does.
    pub const fn new(prefix: u16, kind: u8) -> Self {
        let raw = (prefix << 4) | (kind as u16 & 0x0F);
        ObjectId(raw.to_be_bytes())
    }

    /// The object kind (low nibble of byte 1).
    pub fn kind(self) -> u8 {
        self.0[1] & 0x0F
    }

    /// The 12-bit prefix.
    pub fn prefix(self) -> u16 {
        u16::from_be_bytes(self.0) >> 4
    }
}

impl fmt::Debug for ObjectId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:02X}{:02X}", self.0[0], self.0[1])
    }
}

/// The 2-octet request id that replies echo. Opaque to the agent.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct RequestId(pub [u8; 2]);

impl RequestId {
    /// The eProsima client writes the id big endian.
    pub fn from_u16(v: u16) -> Self {
        RequestId(v.to_be_bytes())
    }

    /// The id as the eProsima client numbers it.
    pub fn as_u16(self) -> u16 {
        u16::from_be_bytes(self.0)
    }
}

impl fmt::Debug for RequestId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:02X}{:02X}", self.0[0], self.0[1])
    }
}

/// `StatusValue` (§7.7.7, Table 2).
pub mod status {
    /// Done.
    pub const OK: u8 = 0x00;
    /// Done: the object existed already as asked (REUSE).
    pub const OK_MATCHED: u8 = 0x01;
    /// DDS failed.
    pub const ERR_DDS_ERROR: u8 = 0x80;
    /// An object with that id exists but differs, and REPLACE was not asked.
    pub const ERR_MISMATCH: u8 = 0x81;
    /// An object with that id exists, and neither REUSE nor REPLACE was asked.
    pub const ERR_ALREADY_EXISTS: u8 = 0x82;
    /// Not allowed.
    pub const ERR_DENIED: u8 = 0x83;
    /// A reference names nothing the agent knows.
    pub const ERR_UNKNOWN_REFERENCE: u8 = 0x84;
    /// The request cannot be read or makes no sense.
    pub const ERR_INVALID_DATA: u8 = 0x85;
    /// The client's version or vendor is not served.
    pub const ERR_INCOMPATIBLE: u8 = 0x86;
    /// Out of room: a bound of the agent bit.
    pub const ERR_RESOURCES: u8 = 0x87;

    /// Whether a status value means success.
    pub fn is_ok(v: u8) -> bool {
        v == OK || v == OK_MATCHED
    }
}

/// `ResultStatus`: a status value and a vendor-specific detail octet.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct ResultStatus {
    /// A value of [`status`].
    pub status: u8,
    /// Vendor-specific detail.
    pub implementation_status: u8,
}

impl ResultStatus {
    /// STATUS_OK with no detail.
    pub const OK: ResultStatus = ResultStatus {
        status: status::OK,
        implementation_status: 0,
    };

    /// A status with no detail.
    pub fn new(status: u8) -> Self {
        ResultStatus {
            status,
            implementation_status: 0,
        }
    }
}

/// Stream ids with a meaning of their own (§8.3.2.2).
pub mod stream_id {
    /// Submessages that belong to no stream (ACKNACK, HEARTBEAT, ...).
    pub const NONE: u8 = 0x00;
    /// Built-in best-effort stream.
    pub const BUILTIN_BEST_EFFORT: u8 = 0x01;
    /// Built-in reliable stream.
    pub const BUILTIN_RELIABLE: u8 = 0x80;

    /// Whether a (non-zero) stream id denotes a reliable stream.
    pub fn is_reliable(id: u8) -> bool {
        id & 0x80 != 0
    }
}

/// `DataFormat` values carried in WRITE_DATA / DATA flags and in READ_DATA (§4 of the digest).
pub mod data_format {
    /// One sample, its bytes only.
    pub const DATA: u8 = 0x00;
    /// One sample with its SampleInfo.
    pub const SAMPLE: u8 = 0x02;
    /// A sequence of samples, bytes only.
    pub const DATA_SEQ: u8 = 0x08;
    /// A sequence of samples with their SampleInfos.
    pub const SAMPLE_SEQ: u8 = 0x0A;
    /// Samples packed with delta SampleInfos.
    pub const PACKED_SAMPLES: u8 = 0x0E;
    /// Mask of the format bits in submessage flags.
    pub const MASK: u8 = 0x0E;
}

/// The "XRCE" cookie.
pub const XRCE_COOKIE: [u8; 4] = *b"XRCE";
/// The protocol version this agent speaks.
pub const XRCE_VERSION: [u8; 2] = [0x01, 0x00];
/// eProsima's vendor id.
pub const VENDOR_EPROSIMA: [u8; 2] = [0x01, 0x0F];

/// XRCE vendor id of RTI (its nano-client), whose reliable streams start at 1.
pub const VENDOR_RTI: [u8; 2] = [0x01, 0x01];

/// `Time_t`: seconds and nanoseconds.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct Time {
    /// Seconds.
    pub seconds: i32,
    /// Nanoseconds.
    pub nanoseconds: u32,
}

/// Which reading of the protocol a peer speaks where the spec and eProsima's implementation
/// differ (spec-digest §14). Chosen per session from the CREATE_CLIENT vendor id.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub enum Dialect {
    /// The OMG text as corrected: octet SampleInfoDetail discriminator, ObjectInfo with
    /// activity first, a STATUS for every WRITE_DATA.
    Spec,
    /// eProsima Micro XRCE-DDS: u32 SampleInfoDetail discriminator with shifted cases,
    /// ObjectInfo with config first, no STATUS after WRITE_DATA.
    #[default]
    Eprosima,
}

impl Dialect {
    /// The dialect a client with this vendor id speaks.
    pub fn for_vendor(vendor_id: [u8; 2]) -> Self {
        if vendor_id == VENDOR_EPROSIMA {
            Dialect::Eprosima
        } else {
            Dialect::Spec
        }
    }
}

impl std::str::FromStr for Dialect {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "spec" => Ok(Dialect::Spec),
            "eprosima" => Ok(Dialect::Eprosima),
            other => Err(format!(
                "unknown dialect {other:?} (expected spec or eprosima)"
            )),
        }
    }
}
