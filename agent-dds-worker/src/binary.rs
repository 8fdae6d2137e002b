//! Entity descriptions from binary representations (`OBJK_*_Binary`, decoded by
//! `xrce_common::wire::binary`) in the layout the eProsima client sends
//! (what micro-ROS and PX4 use): no DHEADERs, `@optional` members as a presence octet, data
//! writers and readers naming their topic by ObjectId, QoS as a 16-bit flag word plus
//! optional depth, deadline, lifespan and user data.
//!
//! Alignment is measured from the start of the body, which the client serializes on its own.

use xrce_common::wire::binary::{
    qos_flags, EndpointBinary, EndpointBinaryQos, GroupBinary, ParticipantBinary, TopicBinary,
};
use xrce_common::wire::DecodeError;

use crate::backend::policies::{Durability, History, OwnershipKind, Period, QosDesc, Reliability};
use crate::xml::{EndpointDesc, TopicDesc};

/// Reads a participant body (optional domain and QoS profile references, not used yet).
pub fn parse_participant(body: &[u8], le: bool) -> Result<(), DecodeError> {
    ParticipantBinary::decode(body, le).map(drop)
}

/// Reads a topic body: name, optional type reference, optional type name.
pub fn parse_topic(body: &[u8], le: bool) -> Result<TopicDesc, DecodeError> {
    let t = TopicBinary::decode(body, le)?;
    let type_name = t
        .type_name
        .or(t.type_reference)
        .ok_or(DecodeError::InvalidValue("topic without a type"))?;
    if t.topic_name.is_empty() || type_name.is_empty() {
        return Err(DecodeError::InvalidValue("empty topic or type name"));
    }
    Ok(TopicDesc {
        name: t.topic_name,
        type_name,
        keyed: false,
        qos: QosDesc::default(),
    })
}

/// Reads a publisher or subscriber body; returns the partitions it names (none if every
/// name is empty: the default partition alone).
pub fn parse_publisher_or_subscriber(body: &[u8], le: bool) -> Result<Vec<String>, DecodeError> {
    let g = GroupBinary::decode(body, le)?;
    let names = g.qos.and_then(|q| q.partitions).unwrap_or_default();
    Ok(if names.iter().all(String::is_empty) {
        Vec::new()
    } else {
        names
    })
}

/// Reads a data writer or data reader body.
pub fn parse_endpoint(body: &[u8], writer: bool, le: bool) -> Result<EndpointDesc, DecodeError> {
    let e = EndpointBinary::decode(body, writer, le)?;
    Ok(EndpointDesc {
        topic: None,
        topic_ref: None,
        topic_id: Some(e.topic_id),
        content_filter: e
            .qos
            .as_ref()
            .and_then(|q| q.contentbased_filter.clone())
            .filter(|f| !f.trim().is_empty()),
        qos: e.qos.map(|q| endpoint_qos(&q)).unwrap_or_default(),
    })
}

/// Every policy a binary endpoint QoS carries.
fn endpoint_qos(q: &EndpointBinaryQos) -> QosDesc {
    let ms = |v: u64| Period::Finite(std::time::Duration::from_millis(v));
    let mut d = qos_from_flags(q.base.flags, q.base.history_depth);
    d.deadline = q.base.deadline_msec.map(|v| ms(v.into()));
    d.lifespan = q.base.lifespan_msec.map(|v| ms(v.into()));
    d.ownership = Some(if q.base.flags & qos_flags::OWNERSHIP_EXCLUSIVE != 0 {
        OwnershipKind::Exclusive
    } else {
        OwnershipKind::Shared
    });
    d.ownership_strength = q
        .ownership_strength
        .map(|v| i32::try_from(v).unwrap_or(i32::MAX));
    d.time_based_filter = q.timebasedfilter_msec.map(ms);
    d
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
        ..QosDesc::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_common::wire::ObjectId;

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
        parse_participant(&unhex("00 00"), true).expect("participant");
        let t = parse_topic(
            &unhex(
                "0d000000 4578616d706c65546f70696300 00 01 00 0c000000 4578616d706c655479706500",
            ),
            true,
        )
        .expect("topic");
        assert_eq!(
            (t.name.as_str(), t.type_name.as_str()),
            ("ExampleTopic", "ExampleType")
        );
        parse_publisher_or_subscriber(&unhex("00 00"), true).expect("publisher");
        let w =
            parse_endpoint(&unhex("0012 01 00 0b00 00 00 00 00 00"), true, true).expect("writer");
        assert_eq!(w.topic_id, Some(ObjectId([0x00, 0x12])));
        assert_eq!(w.qos.reliability, Some(Reliability::Reliable));
        assert_eq!(w.qos.durability, Some(Durability::TransientLocal));
        assert_eq!(w.qos.history, None);
        let r = parse_endpoint(&unhex("0012 01 00 0b00 00 00 00 00 00 00"), false, true)
            .expect("reader");
        assert_eq!(r.topic_id, Some(ObjectId([0x00, 0x12])));
    }

    #[test]
    fn spec_vector_topic_body() {
        // Spec digest §11, §7.7.3.1.3 OBJK_Topic_Binary (type_reference form).
        let t = parse_topic(
            &unhex("07000000 5371756172650001 13000000 4d7954797065733a3a5368617065547970650000"),
            true,
        )
        .expect("topic");
        assert_eq!(
            (t.name.as_str(), t.type_name.as_str()),
            ("Square", "MyTypes::ShapeType")
        );
    }

    #[test]
    fn binary_qos_members_map_to_policies() {
        use xrce_common::wire::binary::{EndpointBinary, EndpointQosBinary};
        let body = EndpointBinary {
            topic_id: ObjectId([0, 0x12]),
            qos: Some(EndpointBinaryQos {
                base: EndpointQosBinary {
                    flags: qos_flags::RELIABLE | qos_flags::OWNERSHIP_EXCLUSIVE,
                    history_depth: None,
                    deadline_msec: Some(250),
                    lifespan_msec: Some(10_000),
                    user_data: None,
                },
                ownership_strength: Some(3),
                ..EndpointBinaryQos::default()
            }),
        }
        .encode(true, true);
        let q = parse_endpoint(&body, true, true).expect("writer").qos;
        let ms = |v| Some(Period::Finite(std::time::Duration::from_millis(v)));
        assert_eq!(q.deadline, ms(250));
        assert_eq!(q.lifespan, ms(10_000));
        assert_eq!(q.ownership, Some(OwnershipKind::Exclusive));
        assert_eq!(q.ownership_strength, Some(3));
        let reader = EndpointBinary {
            topic_id: ObjectId([0, 0x12]),
            qos: Some(EndpointBinaryQos {
                timebasedfilter_msec: Some(40),
                ..EndpointBinaryQos::default()
            }),
        }
        .encode(false, true);
        assert_eq!(
            parse_endpoint(&reader, false, true)
                .expect("reader")
                .qos
                .time_based_filter,
            ms(40)
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
        assert!(parse_topic(&[0x05, 0, 0, 0, b'a'], true).is_err());
        assert!(parse_endpoint(&[0x00], true, true).is_err());
        assert!(parse_endpoint(&unhex("0012 01 00 0b00 01"), true, true).is_err());
    }
}
