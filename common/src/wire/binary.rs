//! Binary object representations (`OBJK_*_Binary`, §7.7.3.x) in the layout every real client
//! sends (eProsima Micro XRCE-DDS, hence micro-ROS and PX4): no DHEADERs, `@optional` members
//! as a presence octet, data writers and readers naming their topic by ObjectId, the QoS as a
//! 16-bit flag word plus optional members, and 64-bit integers aligned to 8 (spec-digest §14).
//!
//! A body is serialized on its own, so alignment is measured from the start of the body.

use super::cdr::{CdrReader, CdrWriter};
use super::types::ObjectId;
use super::DecodeError;

/// Longest name accepted.
pub const MAX_NAME: usize = 256;
/// Longest user data, group data or filter expression accepted.
pub const MAX_BLOB: usize = 4096;
/// Most partitions accepted.
pub const MAX_PARTITIONS: usize = 64;

/// `EndpointQosFlags` bits (eProsima: bit 1 is keep-last, where Annex A says keep-all).
pub mod qos_flags {
    /// Reliable (else best effort).
    pub const RELIABLE: u16 = 0x0001;
    /// Keep last (else keep all), as eProsima's clients set it.
    pub const HISTORY_KEEP_LAST: u16 = 0x0002;
    /// Exclusive ownership (else shared).
    pub const OWNERSHIP_EXCLUSIVE: u16 = 0x0004;
    /// Transient-local durability.
    pub const DURABILITY_TRANSIENT_LOCAL: u16 = 0x0008;
    /// Transient durability.
    pub const DURABILITY_TRANSIENT: u16 = 0x0010;
    /// Persistent durability.
    pub const DURABILITY_PERSISTENT: u16 = 0x0020;
}

fn optional<'a, T>(
    r: &mut CdrReader<'a>,
    f: impl FnOnce(&mut CdrReader<'a>) -> Result<T, DecodeError>,
) -> Result<Option<T>, DecodeError> {
    if r.bool()? {
        f(r).map(Some)
    } else {
        Ok(None)
    }
}

fn put_optional<T>(w: &mut CdrWriter<'_>, v: &Option<T>, f: impl FnOnce(&mut CdrWriter<'_>, &T)) {
    w.bool(v.is_some());
    if let Some(v) = v {
        f(w, v);
    }
}

/// `OBJK_DomainParticipant_Binary`.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct ParticipantBinary {
    /// Reference to a domain definition.
    pub domain_reference: Option<String>,
    /// Reference to a QoS profile.
    pub qos_profile_reference: Option<String>,
}

/// `OBJK_Topic_Binary` (eProsima: a type name instead of a TypeIdentifier).
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct TopicBinary {
    /// Topic name.
    pub topic_name: String,
    /// Reference to a registered type.
    pub type_reference: Option<String>,
    /// Type name.
    pub type_name: Option<String>,
}

/// `OBJK_Publisher_Binary` / `OBJK_Subscriber_Binary`.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct GroupBinary {
    /// Publisher or subscriber name.
    pub name: Option<String>,
    /// Partitions and group data.
    pub qos: Option<GroupQosBinary>,
}

/// `OBJK_Publisher_Binary_Qos` / `OBJK_Subscriber_Binary_Qos`.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct GroupQosBinary {
    /// Partition names.
    pub partitions: Option<Vec<String>>,
    /// Group data.
    pub group_data: Option<Vec<u8>>,
}

/// `OBJK_Endpoint_QosBinary`.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct EndpointQosBinary {
    /// [`qos_flags`] bits.
    pub flags: u16,
    /// History depth (keep-last).
    pub history_depth: Option<u16>,
    /// Deadline period in milliseconds.
    pub deadline_msec: Option<u32>,
    /// Lifespan in milliseconds.
    pub lifespan_msec: Option<u32>,
    /// User data.
    pub user_data: Option<Vec<u8>>,
}

/// The QoS of a data writer or data reader.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct EndpointBinaryQos {
    /// The members common to both.
    pub base: EndpointQosBinary,
    /// Writer: ownership strength.
    pub ownership_strength: Option<u64>,
    /// Reader: time-based filter (minimum separation) in milliseconds.
    pub timebasedfilter_msec: Option<u64>,
    /// Reader: content filter expression.
    pub contentbased_filter: Option<String>,
}

/// `OBJK_DataWriter_Binary` or `OBJK_DataReader_Binary`.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct EndpointBinary {
    /// The topic, by ObjectId.
    pub topic_id: ObjectId,
    /// QoS.
    pub qos: Option<EndpointBinaryQos>,
}

fn read_name(r: &mut CdrReader<'_>) -> Result<String, DecodeError> {
    r.string(MAX_NAME)
}

impl ParticipantBinary {
    /// Decodes a body in the client's byte order.
    pub fn decode(body: &[u8], little_endian: bool) -> Result<Self, DecodeError> {
        let r = &mut CdrReader::new(body, little_endian);
        Ok(ParticipantBinary {
            domain_reference: optional(r, read_name)?,
            qos_profile_reference: optional(r, read_name)?,
        })
    }

    /// Encodes a body.
    pub fn encode(&self, little_endian: bool) -> Vec<u8> {
        let mut out = Vec::new();
        let w = &mut CdrWriter::new(&mut out, little_endian);
        put_optional(w, &self.domain_reference, |w, s| w.string(s));
        put_optional(w, &self.qos_profile_reference, |w, s| w.string(s));
        out
    }
}

impl TopicBinary {
    /// Decodes a body in the client's byte order.
    pub fn decode(body: &[u8], little_endian: bool) -> Result<Self, DecodeError> {
        let r = &mut CdrReader::new(body, little_endian);
        Ok(TopicBinary {
            topic_name: read_name(r)?,
            type_reference: optional(r, read_name)?,
            type_name: optional(r, read_name)?,
        })
    }

    /// Encodes a body.
    pub fn encode(&self, little_endian: bool) -> Vec<u8> {
        let mut out = Vec::new();
        let w = &mut CdrWriter::new(&mut out, little_endian);
        w.string(&self.topic_name);
        put_optional(w, &self.type_reference, |w, s| w.string(s));
        put_optional(w, &self.type_name, |w, s| w.string(s));
        out
    }
}

impl GroupBinary {
    /// Decodes a body in the client's byte order (an empty body is a group with nothing
    /// set, as some clients send).
    pub fn decode(body: &[u8], little_endian: bool) -> Result<Self, DecodeError> {
        if body.is_empty() {
            return Ok(GroupBinary::default());
        }
        let r = &mut CdrReader::new(body, little_endian);
        let name = optional(r, read_name)?;
        let qos = optional(r, |r| {
            let partitions = optional(r, |r| {
                let n = r.u32()? as usize;
                if n > MAX_PARTITIONS {
                    return Err(DecodeError::TooLong("partitions"));
                }
                (0..n).map(|_| read_name(r)).collect()
            })?;
            let group_data = optional(r, |r| r.octet_seq(MAX_BLOB).map(<[u8]>::to_vec))?;
            Ok(GroupQosBinary {
                partitions,
                group_data,
            })
        })?;
        Ok(GroupBinary { name, qos })
    }

    /// Encodes a body.
    pub fn encode(&self, little_endian: bool) -> Vec<u8> {
        let mut out = Vec::new();
        let w = &mut CdrWriter::new(&mut out, little_endian);
        put_optional(w, &self.name, |w, s| w.string(s));
        put_optional(w, &self.qos, |w, q| {
            put_optional(w, &q.partitions, |w, p| {
                w.u32(p.len() as u32);
                for s in p {
                    w.string(s);
                }
            });
            put_optional(w, &q.group_data, |w, d| w.octet_seq(d));
        });
        out
    }
}

impl EndpointBinary {
    /// Decodes a data writer (`writer`) or data reader body in the client's byte order.
    pub fn decode(body: &[u8], writer: bool, little_endian: bool) -> Result<Self, DecodeError> {
        let r = &mut CdrReader::new(body, little_endian);
        let topic_id = ObjectId(r.array()?);
        let qos = optional(r, |r| {
            let base = EndpointQosBinary {
                flags: r.u16()?,
                history_depth: optional(r, |r| r.u16())?,
                deadline_msec: optional(r, |r| r.u32())?,
                lifespan_msec: optional(r, |r| r.u32())?,
                user_data: optional(r, |r| r.octet_seq(MAX_BLOB).map(<[u8]>::to_vec))?,
            };
            let mut q = EndpointBinaryQos {
                base,
                ..EndpointBinaryQos::default()
            };
            if writer {
                q.ownership_strength = optional(r, |r| r.u64_aligned(8))?;
            } else {
                q.timebasedfilter_msec = optional(r, |r| r.u64_aligned(8))?;
                q.contentbased_filter = optional(r, |r| r.string(MAX_BLOB))?;
            }
            Ok(q)
        })?;
        Ok(EndpointBinary { topic_id, qos })
    }

    /// Encodes a data writer (`writer`) or data reader body.
    pub fn encode(&self, writer: bool, little_endian: bool) -> Vec<u8> {
        let mut out = Vec::new();
        let w = &mut CdrWriter::new(&mut out, little_endian);
        w.bytes(&self.topic_id.0);
        put_optional(w, &self.qos, |w, q| {
            w.u16(q.base.flags);
            put_optional(w, &q.base.history_depth, |w, v| w.u16(*v));
            put_optional(w, &q.base.deadline_msec, |w, v| w.u32(*v));
            put_optional(w, &q.base.lifespan_msec, |w, v| w.u32(*v));
            put_optional(w, &q.base.user_data, |w, d| w.octet_seq(d));
            if writer {
                put_optional(w, &q.ownership_strength, |w, v| w.u64_aligned(*v, 8));
            } else {
                put_optional(w, &q.timebasedfilter_msec, |w, v| w.u64_aligned(*v, 8));
                put_optional(w, &q.contentbased_filter, |w, s| w.string(s));
            }
        });
        out
    }
}

/// `OBJK_Requester_Binary` / `OBJK_Replier_Binary` (eProsima, ObjectKind 0x07 / 0x08).
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct ServiceBinary {
    /// The service.
    pub service_name: String,
    /// Request type name.
    pub request_type: String,
    /// Reply type name.
    pub reply_type: String,
    /// Request topic name (default: derived from the service name).
    pub request_topic_name: Option<String>,
    /// Reply topic name (default: derived from the service name).
    pub reply_topic_name: Option<String>,
}

impl ServiceBinary {
    /// Decodes a body in the client's byte order.
    pub fn decode(body: &[u8], little_endian: bool) -> Result<Self, DecodeError> {
        let r = &mut CdrReader::new(body, little_endian);
        Ok(ServiceBinary {
            service_name: read_name(r)?,
            request_type: read_name(r)?,
            reply_type: read_name(r)?,
            request_topic_name: optional(r, read_name)?,
            reply_topic_name: optional(r, read_name)?,
        })
    }

    /// Encodes a body.
    pub fn encode(&self, little_endian: bool) -> Vec<u8> {
        let mut out = Vec::new();
        let w = &mut CdrWriter::new(&mut out, little_endian);
        w.string(&self.service_name);
        w.string(&self.request_type);
        w.string(&self.reply_type);
        put_optional(w, &self.request_topic_name, |w, s| w.string(s));
        put_optional(w, &self.reply_topic_name, |w, s| w.string(s));
        out
    }
}
