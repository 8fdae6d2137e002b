//! Reading binary representations (`OBJK_*_Binary`) in the layout the eProsima client sends
//! (what micro-ROS and PX4 use): no DHEADERs, `@optional` members as a presence octet, data
//! writers and readers naming their topic by ObjectId, QoS as a 16-bit flag word plus
//! optional depth, deadline, lifespan and user data.
//!
//! Alignment is measured from the start of the body, which the client serializes on its own.

use xrce_common::wire::cdr::CdrReader;
use xrce_common::wire::{DecodeError, ObjectId};

use crate::xml::{Durability, EndpointDesc, History, QosDesc, Reliability, TopicDesc};

/// Longest name accepted in a binary representation.
const MAX_NAME: usize = 256;
/// Longest user data, partition list or filter accepted.
const MAX_BLOB: usize = 4096;

/// `EndpointQosFlags` bits (eProsima: bit 1 is keep-last, not keep-all as in Annex A).
mod qos_flags {
    pub const RELIABLE: u16 = 0x0001;
    pub const HISTORY_KEEP_LAST: u16 = 0x0002;
    pub const DURABILITY_TRANSIENT_LOCAL: u16 = 0x0008;
    pub const DURABILITY_TRANSIENT: u16 = 0x0010;
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

/// Reads a participant body (optional domain and QoS profile references, not used yet).
pub fn parse_participant(body: &[u8]) -> Result<(), DecodeError> {
    let r = &mut CdrReader::new(body, true);
    optional(r, |r| r.string(MAX_NAME))?;
    optional(r, |r| r.string(MAX_NAME))?;
    Ok(())
}

/// Reads a topic body: name, optional type reference, optional type name.
pub fn parse_topic(body: &[u8]) -> Result<TopicDesc, DecodeError> {
    let r = &mut CdrReader::new(body, true);
    let name = r.string(MAX_NAME)?;
    let type_reference = optional(r, |r| r.string(MAX_NAME))?;
    let type_name = optional(r, |r| r.string(MAX_NAME))?;
    let type_name = type_name
        .or(type_reference)
        .ok_or(DecodeError::InvalidValue("topic without a type"))?;
    if name.is_empty() || type_name.is_empty() {
        return Err(DecodeError::InvalidValue("empty topic or type name"));
    }
    Ok(TopicDesc {
        name,
        type_name,
        keyed: false,
        qos: QosDesc::default(),
    })
}

/// Reads a publisher or subscriber body (optional name and partitions/group data).
pub fn parse_publisher_or_subscriber(body: &[u8]) -> Result<(), DecodeError> {
    if body.is_empty() {
        return Ok(());
    }
    let r = &mut CdrReader::new(body, true);
    optional(r, |r| r.string(MAX_NAME))?;
    optional(r, |r| {
        optional(r, |r| {
            let n = r.u32()? as usize;
            if n > 64 {
                return Err(DecodeError::TooLong("partitions"));
            }
            (0..n).try_for_each(|_| r.string(MAX_NAME).map(drop))
        })?;
        optional(r, |r| r.octet_seq(MAX_BLOB).map(drop))
    })?;
    Ok(())
}

/// Reads a data writer or data reader body.
pub fn parse_endpoint(body: &[u8], writer: bool) -> Result<EndpointDesc, DecodeError> {
    let r = &mut CdrReader::new(body, true);
    let topic_id = ObjectId(r.array()?);
    let qos = optional(r, |r| {
        let flags = r.u16()?;
        let depth = optional(r, |r| r.u16())?;
        let _deadline_ms = optional(r, |r| r.u32())?;
        let _lifespan_ms = optional(r, |r| r.u32())?;
        let _user_data = optional(r, |r| r.octet_seq(MAX_BLOB).map(drop))?;
        if writer {
            let _ownership_strength = optional(r, read_u64)?;
        } else {
            let _time_based_filter_ms = optional(r, read_u64)?;
            let _content_filter = optional(r, |r| r.string(MAX_BLOB))?;
        }
        Ok(qos_from_flags(flags, depth))
    })?;
    Ok(EndpointDesc {
        topic: None,
        topic_ref: None,
        topic_id: Some(topic_id),
        qos: qos.unwrap_or_default(),
    })
}

/// eProsima serializes these as 8-byte integers aligned to 8.
fn read_u64(r: &mut CdrReader<'_>) -> Result<u64, DecodeError> {
    r.align(8)?;
    let lo = r.u32()? as u64;
    let hi = r.u32()? as u64;
    Ok(lo | hi << 32)
}

fn qos_from_flags(flags: u16, depth: Option<u16>) -> QosDesc {
    use qos_flags as f;
    let durability = if flags & f::DURABILITY_PERSISTENT != 0 {
        Durability::Persistent
    } else if flags & f::DURABILITY_TRANSIENT != 0 {
        Durability::Transient
    } else if flags & f::DURABILITY_TRANSIENT_LOCAL != 0 {
        Durability::TransientLocal
    } else {
        Durability::Volatile
    };
    let history = if flags & f::HISTORY_KEEP_LAST != 0 {
        // A depth of 0 (or none) means the entity's default depth.
        depth
            .filter(|d| *d > 0)
            .map(|d| History::KeepLast(d as i32))
    } else {
        Some(History::KeepAll)
    };
    QosDesc {
        reliability: Some(if flags & f::RELIABLE != 0 {
            Reliability::Reliable
        } else {
            Reliability::BestEffort
        }),
        durability: Some(durability),
        history,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unhex(s: &str) -> Vec<u8> {
        let s: String = s.split_whitespace().collect();
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
            .collect()
    }

    /// Bodies from `binary-creation.txt` (the real eProsima client).
    #[test]
    fn captured_bodies() {
        parse_participant(&unhex("00 00")).expect("participant");
        let t = parse_topic(&unhex(
            "0d000000 4578616d706c65546f70696300 00 01 00 0c000000 4578616d706c655479706500",
        ))
        .expect("topic");
        assert_eq!(
            (t.name.as_str(), t.type_name.as_str()),
            ("ExampleTopic", "ExampleType")
        );
        parse_publisher_or_subscriber(&unhex("00 00")).expect("publisher");
        let w = parse_endpoint(&unhex("0012 01 00 0b00 00 00 00 00 00"), true).expect("writer");
        assert_eq!(w.topic_id, Some(ObjectId([0x00, 0x12])));
        assert_eq!(w.qos.reliability, Some(Reliability::Reliable));
        assert_eq!(w.qos.durability, Some(Durability::TransientLocal));
        assert_eq!(w.qos.history, None);
        let r = parse_endpoint(&unhex("0012 01 00 0b00 00 00 00 00 00 00"), false).expect("reader");
        assert_eq!(r.topic_id, Some(ObjectId([0x00, 0x12])));
    }

    #[test]
    fn spec_vector_topic_body() {
        // Spec digest §11, §7.7.3.1.3 OBJK_Topic_Binary (type_reference form).
        let t = parse_topic(&unhex(
            "07000000 5371756172650001 13000000 4d7954797065733a3a5368617065547970650000",
        ))
        .expect("topic");
        assert_eq!(
            (t.name.as_str(), t.type_name.as_str()),
            ("Square", "MyTypes::ShapeType")
        );
    }

    #[test]
    fn qos_flags_and_depth() {
        let q = qos_from_flags(0x0002, Some(10));
        assert_eq!(q.history, Some(History::KeepLast(10)));
        assert_eq!(q.reliability, Some(Reliability::BestEffort));
        assert_eq!(q.durability, Some(Durability::Volatile));
        assert_eq!(qos_from_flags(0x0000, None).history, Some(History::KeepAll));
    }

    #[test]
    fn truncated_bodies_are_errors() {
        assert!(parse_topic(&[0x05, 0, 0, 0, b'a']).is_err());
        assert!(parse_endpoint(&[0x00], true).is_err());
        assert!(parse_endpoint(&unhex("0012 01 00 0b00 01"), true).is_err());
    }
}
