//! Submessage payloads (§8.3.5) and their encoding.
//!
//! Decoded payloads borrow sample bytes from the datagram, so a WRITE_DATA body can be copied
//! once, straight from the socket buffer to its destination.

use super::cdr::{CdrReader, CdrWriter};
use super::types::{
    object_kind, ClientKey, ObjectId, RequestId, ResultStatus, Time, VENDOR_EPROSIMA, XRCE_COOKIE,
    XRCE_VERSION,
};
use super::DecodeError;

/// Submessage ids (§8.3.5, Table 10).
pub mod submessage_id {
    /// CREATE_CLIENT: opens a session.
    pub const CREATE_CLIENT: u8 = 0;
    /// CREATE: creates an object.
    pub const CREATE: u8 = 1;
    /// GET_INFO: asks about the agent or an object.
    pub const GET_INFO: u8 = 2;
    /// DELETE: deletes an object or the session.
    pub const DELETE: u8 = 3;
    /// STATUS_AGENT: answers CREATE_CLIENT.
    pub const STATUS_AGENT: u8 = 4;
    /// STATUS: answers CREATE and DELETE.
    pub const STATUS: u8 = 5;
    /// INFO: answers GET_INFO.
    pub const INFO: u8 = 6;
    /// WRITE_DATA: a client's sample(s) for a data writer.
    pub const WRITE_DATA: u8 = 7;
    /// READ_DATA: asks a data reader for samples.
    pub const READ_DATA: u8 = 8;
    /// DATA: samples for a client's read.
    pub const DATA: u8 = 9;
    /// ACKNACK: what a reliable stream's receiver has and lacks.
    pub const ACKNACK: u8 = 10;
    /// HEARTBEAT: what a reliable stream's sender holds.
    pub const HEARTBEAT: u8 = 11;
    /// RESET: restarts the streams.
    pub const RESET: u8 = 12;
    /// FRAGMENT: a slice of a larger submessage.
    pub const FRAGMENT: u8 = 13;
    /// TIMESTAMP: asks for the agent's clock.
    pub const TIMESTAMP: u8 = 14;
    /// TIMESTAMP_REPLY: answers TIMESTAMP.
    pub const TIMESTAMP_REPLY: u8 = 15;
}

/// Flag bits beyond endianness.
pub mod flags {
    /// Endianness: set = little endian.
    pub const LITTLE_ENDIAN: u8 = 0x01;
    /// CREATE: reuse an existing object.
    pub const REUSE: u8 = 0x02;
    /// CREATE: replace an existing object.
    pub const REPLACE: u8 = 0x04;
    /// FRAGMENT: last fragment.
    pub const LAST_FRAGMENT: u8 = 0x02;
}

/// Longest reference string accepted (REFERENCE_MAX_LEN).
pub const MAX_REFERENCE_LEN: usize = 128;
/// Longest XML representation or binary body accepted; a submessage cannot be longer anyway.
pub const MAX_REPRESENTATION_LEN: usize = 65_535;
/// Longest property name/value or filter expression accepted.
pub const MAX_STRING_LEN: usize = 4096;
/// Most properties accepted in a CLIENT_Representation.
pub const MAX_PROPERTIES: usize = 32;

/// `BaseObjectRequest`: request id and object id.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct BaseObjectRequest {
    /// Echoed by the reply.
    pub request_id: RequestId,
    /// The object the request is about.
    pub object_id: ObjectId,
}

impl BaseObjectRequest {
    fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        Ok(BaseObjectRequest {
            request_id: RequestId(r.array()?),
            object_id: ObjectId(r.array()?),
        })
    }

    fn encode(&self, w: &mut CdrWriter<'_>) {
        w.bytes(&self.request_id.0);
        w.bytes(&self.object_id.0);
    }
}

/// `BaseObjectReply`: the request it answers and its result (the STATUS payload).
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct BaseObjectReply {
    /// The request answered.
    pub related: BaseObjectRequest,
    /// Its result.
    pub result: ResultStatus,
}

impl BaseObjectReply {
    /// Encoded length.
    pub const LEN: usize = 6;

    fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        let related = BaseObjectRequest::decode(r)?;
        let result = ResultStatus {
            status: r.u8()?,
            implementation_status: r.u8()?,
        };
        Ok(BaseObjectReply { related, result })
    }

    /// Appends the reply.
    pub fn encode(&self, w: &mut CdrWriter<'_>) {
        self.related.encode(w);
        w.u8(self.result.status);
        w.u8(self.result.implementation_status);
    }
}

/// A vendor property (name, value).
pub type Property = (String, String);

pub(crate) fn decode_properties(
    r: &mut CdrReader<'_>,
) -> Result<Option<Vec<Property>>, DecodeError> {
    if !r.bool()? {
        return Ok(None);
    }
    let n = r.u32()? as usize;
    if n > MAX_PROPERTIES {
        return Err(DecodeError::TooLong("properties"));
    }
    let mut v = Vec::with_capacity(n);
    for _ in 0..n {
        v.push((r.string(MAX_STRING_LEN)?, r.string(MAX_STRING_LEN)?));
    }
    Ok(Some(v))
}

pub(crate) fn encode_properties(w: &mut CdrWriter<'_>, p: &Option<Vec<Property>>) {
    w.bool(p.is_some());
    if let Some(p) = p {
        w.u32(p.len() as u32);
        for (k, v) in p {
            w.string(k);
            w.string(v);
        }
    }
}

/// CREATE_CLIENT payload: `CLIENT_Representation` plus eProsima's trailing MTU.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct CreateClientPayload {
    /// Must be "XRCE".
    pub cookie: [u8; 4],
    /// Major, minor.
    pub version: [u8; 2],
    /// Client vendor id (eProsima = 01 0F).
    pub vendor_id: [u8; 2],
    /// The client's key.
    pub client_key: ClientKey,
    /// The session id the client wants.
    pub session_id: u8,
    /// Vendor properties.
    pub properties: Option<Vec<Property>>,
    /// eProsima extension: the client's transport MTU.
    pub mtu: Option<u16>,
}

impl CreateClientPayload {
    /// What an eProsima client sends to open session `session_id` as `key`: this protocol
    /// version, eProsima's vendor id, no properties, an MTU of 512 (change a field with
    /// `..CreateClientPayload::eprosima(key, id)`).
    pub fn eprosima(key: ClientKey, session_id: u8) -> Self {
        CreateClientPayload {
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id: VENDOR_EPROSIMA,
            client_key: key,
            session_id,
            properties: None,
            mtu: Some(512),
        }
    }

    fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        let cookie = r.array()?;
        let version = r.array()?;
        let vendor_id = r.array()?;
        let client_key = ClientKey(r.array()?);
        let session_id = r.u8()?;
        let properties = decode_properties(r)?;
        // Lenient: the MTU is an eProsima extension; anything shorter is ignored.
        let mtu = if r.remaining() >= 2 + (r.position() % 2) {
            Some(r.u16()?)
        } else {
            None
        };
        Ok(CreateClientPayload {
            cookie,
            version,
            vendor_id,
            client_key,
            session_id,
            properties,
            mtu,
        })
    }

    fn encode(&self, w: &mut CdrWriter<'_>) {
        w.bytes(&self.cookie);
        w.bytes(&self.version);
        w.bytes(&self.vendor_id);
        w.bytes(&self.client_key.0);
        w.u8(self.session_id);
        encode_properties(w, &self.properties);
        if let Some(mtu) = self.mtu {
            w.u16(mtu);
        }
    }
}

/// STATUS_AGENT payload: optional `ResultStatus` (eProsima dialect) and `AGENT_Representation`.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct StatusAgentPayload {
    /// Present in the eProsima dialect, absent in the spec-literal one.
    pub result: Option<ResultStatus>,
    /// Must be "XRCE".
    pub cookie: [u8; 4],
    /// Version the agent uses with this client.
    pub version: [u8; 2],
    /// Agent vendor id.
    pub vendor_id: [u8; 2],
    /// Vendor properties.
    pub properties: Option<Vec<Property>>,
}

impl StatusAgentPayload {
    fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        // The spec-literal form starts with the cookie; the eProsima form with a ResultStatus.
        let peek = r.clone().take(4)?;
        let result = if peek == XRCE_COOKIE {
            None
        } else {
            Some(ResultStatus {
                status: r.u8()?,
                implementation_status: r.u8()?,
            })
        };
        Ok(StatusAgentPayload {
            result,
            cookie: r.array()?,
            version: r.array()?,
            vendor_id: r.array()?,
            properties: decode_properties(r)?,
        })
    }

    fn encode(&self, w: &mut CdrWriter<'_>) {
        if let Some(res) = self.result {
            w.u8(res.status);
            w.u8(res.implementation_status);
        }
        w.bytes(&self.cookie);
        w.bytes(&self.version);
        w.bytes(&self.vendor_id);
        encode_properties(w, &self.properties);
    }
}

/// How an object is described in a CREATE (§7.7.3).
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Representation {
    /// REPRESENTATION_BY_REFERENCE: the name of a pre-configured profile.
    Reference(String),
    /// REPRESENTATION_AS_XML_STRING.
    Xml(String),
    /// REPRESENTATION_IN_BINARY: the serialized OBJK_*_Binary body.
    Binary(Vec<u8>),
}

/// Representation format octets.
pub mod representation_format {
    /// A reference to a profile the agent knows.
    pub const BY_REFERENCE: u8 = 0x01;
    /// An XML text.
    pub const AS_XML_STRING: u8 = 0x02;
    /// The binary (XCDR) representation.
    pub const IN_BINARY: u8 = 0x03;
}

/// The member that follows the representation in an `ObjectVariant`.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum VariantExtra {
    /// Types, QoS profiles, applications: nothing follows.
    None,
    /// Participants: the DDS domain id.
    DomainId(i16),
    /// Topics, publishers, subscribers, writers, readers, requesters, repliers: the parent.
    Parent(ObjectId),
}

/// `ObjectVariant` for the object kinds a client creates.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct ObjectVariant {
    /// The discriminator (an [`object_kind`]).
    pub kind: u8,
    /// How the object is described.
    pub representation: Representation,
    /// The kind's extra member.
    pub extra: VariantExtra,
}

impl ObjectVariant {
    /// Decodes an object variant from a little- or big-endian payload.
    pub fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        let kind = r.u8()?;
        let format = r.u8()?;
        let representation = match format {
            representation_format::BY_REFERENCE => {
                Representation::Reference(r.string(MAX_REFERENCE_LEN)?)
            }
            representation_format::AS_XML_STRING => {
                Representation::Xml(r.string(MAX_REPRESENTATION_LEN)?)
            }
            representation_format::IN_BINARY => {
                Representation::Binary(r.octet_seq(MAX_REPRESENTATION_LEN)?.to_vec())
            }
            _ => return Err(DecodeError::InvalidValue("representation format")),
        };
        let extra = match kind {
            object_kind::PARTICIPANT => VariantExtra::DomainId(r.i16()?),
            object_kind::TOPIC
            | object_kind::PUBLISHER
            | object_kind::SUBSCRIBER
            | object_kind::DATAWRITER
            | object_kind::DATAREADER
            | object_kind::REQUESTER
            | object_kind::REPLIER => VariantExtra::Parent(ObjectId(r.array()?)),
            object_kind::TYPE | object_kind::QOSPROFILE | object_kind::APPLICATION => {
                VariantExtra::None
            }
            _ => return Err(DecodeError::InvalidValue("object kind")),
        };
        Ok(ObjectVariant {
            kind,
            representation,
            extra,
        })
    }

    /// Appends the encoded variant.
    pub fn encode(&self, w: &mut CdrWriter<'_>) {
        w.u8(self.kind);
        match &self.representation {
            Representation::Reference(s) => {
                w.u8(representation_format::BY_REFERENCE);
                w.string(s);
            }
            Representation::Xml(s) => {
                w.u8(representation_format::AS_XML_STRING);
                w.string(s);
            }
            Representation::Binary(b) => {
                w.u8(representation_format::IN_BINARY);
                w.octet_seq(b);
            }
        }
        match self.extra {
            VariantExtra::None => {}
            VariantExtra::DomainId(d) => w.i16(d),
            VariantExtra::Parent(p) => w.bytes(&p.0),
        }
    }

    /// The parent object, if this kind has one.
    pub fn parent(&self) -> Option<ObjectId> {
        match self.extra {
            VariantExtra::Parent(p) => Some(p),
            _ => None,
        }
    }
}

/// CREATE payload with the creation mode from the flags.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct CreatePayload {
    /// Request and object ids.
    pub base: BaseObjectRequest,
    /// The object.
    pub variant: ObjectVariant,
    /// Flag 0x02.
    pub reuse: bool,
    /// Flag 0x04.
    pub replace: bool,
}

/// READ_DATA's optional `DataDeliveryControl`.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct DataDeliveryControl {
    /// 0 cancels, 0xFFFF is unlimited.
    pub max_samples: u16,
    /// Seconds; 0 is unlimited.
    pub max_elapsed_time: u16,
    /// Bytes per second; 0 is unlimited.
    pub max_bytes_per_second: u16,
    /// Milliseconds between DATA messages.
    pub min_pace_period: u16,
}

/// `ReadSpecification` (§7.7.14).
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct ReadSpecification {
    /// Stream the agent should answer on (0 = agent's choice).
    pub preferred_stream_id: u8,
    /// Format of the DATA replies.
    pub data_format: u8,
    /// Optional content filter expression.
    pub content_filter_expression: Option<String>,
    /// Optional delivery control.
    pub delivery_control: Option<DataDeliveryControl>,
    /// Whether the delivery control carried an XCDR2 DHEADER (spec-literal form).
    pub delivery_control_dheader: bool,
}

impl ReadSpecification {
    /// Decodes a read specification.
    pub fn decode(r: &mut CdrReader<'_>) -> Result<Self, DecodeError> {
        let preferred_stream_id = r.u8()?;
        let data_format = r.u8()?;
        let content_filter_expression = if r.bool()? {
            Some(r.string(MAX_STRING_LEN)?)
        } else {
            None
        };
        let mut dheader = false;
        let delivery_control = if r.bool()? {
            // eProsima writes the four shorts directly; the spec-literal form adds a DHEADER.
            let mut probe = r.clone();
            if probe.align(4).is_ok()
                && probe.remaining() >= 12
                && probe.u32().map(|v| v & 0x7FFF_FFFF == 8).unwrap_or(false)
            {
                r.u32()?;
                dheader = true;
            }
            Some(DataDeliveryControl {
                max_samples: r.u16()?,
                max_elapsed_time: r.u16()?,
                max_bytes_per_second: r.u16()?,
                min_pace_period: r.u16()?,
            })
        } else {
            None
        };
        Ok(ReadSpecification {
            preferred_stream_id,
            data_format,
            content_filter_expression,
            delivery_control,
            delivery_control_dheader: dheader,
        })
    }

    /// Appends the encoded specification.
    pub fn encode(&self, w: &mut CdrWriter<'_>) {
        w.u8(self.preferred_stream_id);
        w.u8(self.data_format);
        w.bool(self.content_filter_expression.is_some());
        if let Some(f) = &self.content_filter_expression {
            w.string(f);
        }
        w.bool(self.delivery_control.is_some());
        if let Some(d) = &self.delivery_control {
            if self.delivery_control_dheader {
                w.u32(8);
            }
            w.u16(d.max_samples);
            w.u16(d.max_elapsed_time);
            w.u16(d.max_bytes_per_second);
            w.u16(d.min_pace_period);
        }
    }
}

/// READ_DATA payload.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct ReadDataPayload {
    /// Request and reader ids.
    pub base: BaseObjectRequest,
    /// What to read and how to deliver it.
    pub spec: ReadSpecification,
}

/// WRITE_DATA or DATA payload: the format bits and the representation bytes, undecoded.
///
/// For FORMAT_DATA `data` is the serialized sample itself.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct DataPayload<'a> {
    /// Request and writer (WRITE_DATA) or reader (DATA) ids.
    pub base: BaseObjectRequest,
    /// A [`super::data_format`] value from flag bits 1–3.
    pub format: u8,
    /// The bytes after the base request.
    pub data: &'a [u8],
}

/// ACKNACK payload.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct AcknackPayload {
    /// All lower sequence numbers were received.
    pub first_unacked_seq_num: u16,
    /// Bit i set: `first_unacked_seq_num + i` is missing. Sent high byte first.
    pub nack_bitmap: u16,
    /// The stream acknowledged (the acknowledger's input stream).
    pub stream_id: u8,
}

/// HEARTBEAT payload.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct HeartbeatPayload {
    /// Oldest sequence number the sender still has.
    pub first_unacked_seq_num: u16,
    /// Newest sequence number sent.
    pub last_unacked_seq_num: u16,
    /// The sender's output stream.
    pub stream_id: u8,
}

/// GET_INFO payload.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct GetInfoPayload {
    /// Request and object ids.
    pub base: BaseObjectRequest,
    /// INFO_CONFIGURATION = 1, INFO_ACTIVITY = 2.
    pub info_mask: u32,
}

/// INFO payload: the reply and the undecoded `ObjectInfo`.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct InfoPayload<'a> {
    /// The request answered and its result.
    pub reply: BaseObjectReply,
    /// `ObjectInfo`, in the dialect of the sender.
    pub object_info: &'a [u8],
}

/// TIMESTAMP_REPLY payload.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct TimestampReplyPayload {
    /// When the reply was sent.
    pub transmit: Time,
    /// When the TIMESTAMP arrived.
    pub receive: Time,
    /// The TIMESTAMP's transmit time.
    pub originate: Time,
}

/// A decoded submessage payload.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Payload<'a> {
    /// CREATE_CLIENT.
    CreateClient(CreateClientPayload),
    /// CREATE.
    Create(CreatePayload),
    /// GET_INFO.
    GetInfo(GetInfoPayload),
    /// DELETE.
    Delete(BaseObjectRequest),
    /// STATUS_AGENT.
    StatusAgent(StatusAgentPayload),
    /// STATUS.
    Status(BaseObjectReply),
    /// INFO.
    Info(InfoPayload<'a>),
    /// WRITE_DATA.
    WriteData(DataPayload<'a>),
    /// READ_DATA.
    ReadData(ReadDataPayload),
    /// DATA.
    Data(DataPayload<'a>),
    /// ACKNACK.
    Acknack(AcknackPayload),
    /// HEARTBEAT.
    Heartbeat(HeartbeatPayload),
    /// RESET (no payload).
    Reset,
    /// A slice of a larger serialized submessage.
    Fragment {
        /// The Last Fragment flag: this slice ends the submessage.
        last: bool,
        /// The slice.
        data: &'a [u8],
    },
    /// TIMESTAMP: the client's transmit time.
    Timestamp(Time),
    /// TIMESTAMP_REPLY.
    TimestampReply(TimestampReplyPayload),
    /// A submessage id this codec does not know; skipped by its length.
    Unknown {
        /// Its submessage id.
        id: u8,
        /// Its flags.
        flags: u8,
        /// Its payload, undecoded.
        data: &'a [u8],
    },
}

fn decode_time(r: &mut CdrReader<'_>) -> Result<Time, DecodeError> {
    Ok(Time {
        seconds: r.i32()?,
        nanoseconds: r.u32()?,
    })
}

fn encode_time(w: &mut CdrWriter<'_>, t: Time) {
    w.i32(t.seconds);
    w.u32(t.nanoseconds);
}

impl<'a> Payload<'a> {
    /// Decodes the payload of a submessage with the given id and flags.
    pub fn decode(id: u8, flags_byte: u8, buf: &'a [u8]) -> Result<Self, DecodeError> {
        use submessage_id as s;
        let le = flags_byte & flags::LITTLE_ENDIAN != 0;
        let r = &mut CdrReader::new(buf, le);
        let p = match id {
            s::CREATE_CLIENT => Payload::CreateClient(CreateClientPayload::decode(r)?),
            s::CREATE => Payload::Create(CreatePayload {
                base: BaseObjectRequest::decode(r)?,
                variant: ObjectVariant::decode(r)?,
                reuse: flags_byte & flags::REUSE != 0,
                replace: flags_byte & flags::REPLACE != 0,
            }),
            s::GET_INFO => Payload::GetInfo(GetInfoPayload {
                base: BaseObjectRequest::decode(r)?,
                info_mask: r.u32()?,
            }),
            s::DELETE => Payload::Delete(BaseObjectRequest::decode(r)?),
            s::STATUS_AGENT => Payload::StatusAgent(StatusAgentPayload::decode(r)?),
            s::STATUS => Payload::Status(BaseObjectReply::decode(r)?),
            s::INFO => Payload::Info(InfoPayload {
                reply: BaseObjectReply::decode(r)?,
                object_info: r.rest(),
            }),
            s::WRITE_DATA | s::DATA => {
                let base = BaseObjectRequest::decode(r)?;
                let d = DataPayload {
                    base,
                    format: flags_byte & super::data_format::MASK,
                    data: r.rest(),
                };
                if id == s::WRITE_DATA {
                    Payload::WriteData(d)
                } else {
                    Payload::Data(d)
                }
            }
            s::READ_DATA => Payload::ReadData(ReadDataPayload {
                base: BaseObjectRequest::decode(r)?,
                spec: ReadSpecification::decode(r)?,
            }),
            s::ACKNACK => Payload::Acknack(AcknackPayload {
                first_unacked_seq_num: r.u16()?,
                nack_bitmap: u16::from_be_bytes(r.array()?),
                stream_id: r.u8()?,
            }),
            s::HEARTBEAT => Payload::Heartbeat(HeartbeatPayload {
                first_unacked_seq_num: r.u16()?,
                last_unacked_seq_num: r.u16()?,
                stream_id: r.u8()?,
            }),
            s::RESET => Payload::Reset,
            s::FRAGMENT => Payload::Fragment {
                last: flags_byte & flags::LAST_FRAGMENT != 0,
                data: r.rest(),
            },
            s::TIMESTAMP => Payload::Timestamp(decode_time(r)?),
            s::TIMESTAMP_REPLY => Payload::TimestampReply(TimestampReplyPayload {
                transmit: decode_time(r)?,
                receive: decode_time(r)?,
                originate: decode_time(r)?,
            }),
            _ => Payload::Unknown {
                id,
                flags: flags_byte & !flags::LITTLE_ENDIAN,
                data: r.rest(),
            },
        };
        Ok(p)
    }

    /// The submessage id of this payload.
    pub fn id(&self) -> u8 {
        use submessage_id as s;
        match self {
            Payload::CreateClient(_) => s::CREATE_CLIENT,
            Payload::Create(_) => s::CREATE,
            Payload::GetInfo(_) => s::GET_INFO,
            Payload::Delete(_) => s::DELETE,
            Payload::StatusAgent(_) => s::STATUS_AGENT,
            Payload::Status(_) => s::STATUS,
            Payload::Info(_) => s::INFO,
            Payload::WriteData(_) => s::WRITE_DATA,
            Payload::ReadData(_) => s::READ_DATA,
            Payload::Data(_) => s::DATA,
            Payload::Acknack(_) => s::ACKNACK,
            Payload::Heartbeat(_) => s::HEARTBEAT,
            Payload::Reset => s::RESET,
            Payload::Fragment { .. } => s::FRAGMENT,
            Payload::Timestamp(_) => s::TIMESTAMP,
            Payload::TimestampReply(_) => s::TIMESTAMP_REPLY,
            Payload::Unknown { id, .. } => *id,
        }
    }

    /// The flag bits other than endianness.
    pub fn extra_flags(&self) -> u8 {
        match self {
            Payload::Create(c) => {
                (if c.reuse { flags::REUSE } else { 0 })
                    | (if c.replace { flags::REPLACE } else { 0 })
            }
            Payload::WriteData(d) | Payload::Data(d) => d.format & super::data_format::MASK,
            Payload::Fragment { last: true, .. } => flags::LAST_FRAGMENT,
            Payload::Unknown { flags, .. } => flags & !flags::LITTLE_ENDIAN,
            _ => 0,
        }
    }

    /// Appends the encoded payload (without submessage header).
    pub fn encode(&self, out: &mut Vec<u8>, little_endian: bool) {
        let w = &mut CdrWriter::new(out, little_endian);
        match self {
            Payload::CreateClient(p) => p.encode(w),
            Payload::Create(p) => {
                p.base.encode(w);
                p.variant.encode(w);
            }
            Payload::GetInfo(p) => {
                p.base.encode(w);
                w.u32(p.info_mask);
            }
            Payload::Delete(p) => p.encode(w),
            Payload::StatusAgent(p) => p.encode(w),
            Payload::Status(p) => p.encode(w),
            Payload::Info(p) => {
                p.reply.encode(w);
                w.bytes(p.object_info);
            }
            Payload::WriteData(d) | Payload::Data(d) => {
                d.base.encode(w);
                w.bytes(d.data);
            }
            Payload::ReadData(p) => {
                p.base.encode(w);
                p.spec.encode(w);
            }
            Payload::Acknack(p) => {
                w.u16(p.first_unacked_seq_num);
                w.bytes(&p.nack_bitmap.to_be_bytes());
                w.u8(p.stream_id);
            }
            Payload::Heartbeat(p) => {
                w.u16(p.first_unacked_seq_num);
                w.u16(p.last_unacked_seq_num);
                w.u8(p.stream_id);
            }
            Payload::Reset => {}
            Payload::Fragment { data, .. } | Payload::Unknown { data, .. } => w.bytes(data),
            Payload::Timestamp(t) => encode_time(w, *t),
            Payload::TimestampReply(p) => {
                encode_time(w, p.transmit);
                encode_time(w, p.receive);
                encode_time(w, p.originate);
            }
        }
    }
}
