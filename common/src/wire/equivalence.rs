//! Whether two descriptions of an object mean the same object: what a CREATE flagged REUSE
//! is compared by (§7.8.3.1, Table 5: "the existing object matches the representation").
//!
//! Comparing bytes is not enough. Real clients serialize a binary description in a buffer they
//! do not clear, so the alignment padding between its members carries whatever the buffer
//! held before: micro-ROS's second CREATE of the same data writer after a reset differs from
//! its first in a padding octet (`wire-traces/microros-reset.txt`). A byte comparison then
//! calls the same writer different, and REUSE|REPLACE tears down and re-creates an entity
//! the client meant to keep. So binary descriptions are compared decoded, XML documents as
//! trees (markup, whitespace between elements, comments and attribute order do not count),
//! references by name. Descriptions in two different forms are different: the agent cannot
//! tell whether a reference and an XML document describe the same profile without resolving
//! both, and a REPLACE then re-creates the object, which is always correct.

use super::binary::{EndpointBinary, GroupBinary, ParticipantBinary, ServiceBinary, TopicBinary};
use super::{object_kind, ObjectVariant, Representation};

/// Whether `a` (sent in the byte order `a_little_endian`) and `b` describe the same object.
pub fn same_meaning(
    a: &ObjectVariant,
    a_little_endian: bool,
    b: &ObjectVariant,
    b_little_endian: bool,
) -> bool {
    if a.kind != b.kind || a.extra != b.extra {
        return false;
    }
    match (&a.representation, &b.representation) {
        (Representation::Reference(x), Representation::Reference(y)) => x == y,
        (Representation::Xml(x), Representation::Xml(y)) => x == y || same_xml(x, y),
        (Representation::Binary(x), Representation::Binary(y)) => {
            (x == y && a_little_endian == b_little_endian)
                || same_binary(a.kind, x, a_little_endian, y, b_little_endian)
        }
        _ => false,
    }
}

/// Two binary bodies of an object of `kind`, decoded; a body that does not decode matches
/// nothing but its own bytes.
fn same_binary(kind: u8, x: &[u8], x_le: bool, y: &[u8], y_le: bool) -> bool {
    fn both<T: PartialEq, E>(x: Result<T, E>, y: Result<T, E>) -> bool {
        matches!((x, y), (Ok(x), Ok(y)) if x == y)
    }
    match kind {
        object_kind::PARTICIPANT => both(
            ParticipantBinary::decode(x, x_le),
            ParticipantBinary::decode(y, y_le),
        ),
        object_kind::TOPIC => both(TopicBinary::decode(x, x_le), TopicBinary::decode(y, y_le)),
        object_kind::PUBLISHER | object_kind::SUBSCRIBER => {
            both(GroupBinary::decode(x, x_le), GroupBinary::decode(y, y_le))
        }
        object_kind::DATAWRITER | object_kind::DATAREADER => {
            let writer = kind == object_kind::DATAWRITER;
            both(
                EndpointBinary::decode(x, writer, x_le),
                EndpointBinary::decode(y, writer, y_le),
            )
        }
        object_kind::REQUESTER | object_kind::REPLIER => both(
            ServiceBinary::decode(x, x_le),
            ServiceBinary::decode(y, y_le),
        ),
        _ => false,
    }
}

/// Two XML documents as trees: the same elements with the same attributes (in any order) and
/// the same text (trimmed; whitespace-only text between elements, comments and processing
/// instructions ignored). A document that does not parse matches nothing but its own text.
fn same_xml(x: &str, y: &str) -> bool {
    let (Ok(x), Ok(y)) = (roxmltree::Document::parse(x), roxmltree::Document::parse(y)) else {
        return false;
    };
    // Walked with a stack, not recursion: the depth is the client's to choose.
    let mut pending = vec![(x.root_element(), y.root_element())];
    while let Some((a, b)) = pending.pop() {
        if a.tag_name() != b.tag_name() {
            return false;
        }
        if sorted_attributes(a) != sorted_attributes(b) {
            return false;
        }
        let mut ac = meaningful_children(a);
        let mut bc = meaningful_children(b);
        loop {
            match (ac.next(), bc.next()) {
                (None, None) => break,
                (Some(p), Some(q)) if p.is_element() && q.is_element() => pending.push((p, q)),
                (Some(p), Some(q)) if p.is_text() && q.is_text() => {
                    if p.text().map(str::trim) != q.text().map(str::trim) {
                        return false;
                    }
                }
                _ => return false,
            }
        }
    }
    true
}

/// An element's attributes, sorted: their order carries no meaning.
fn sorted_attributes<'a>(n: roxmltree::Node<'a, '_>) -> Vec<(Option<&'a str>, &'a str, &'a str)> {
    let mut v: Vec<_> = n
        .attributes()
        .map(|a| (a.namespace(), a.name(), a.value()))
        .collect();
    v.sort_unstable();
    v
}

/// The children of an element that carry meaning: elements, and text that is not only
/// whitespace.
fn meaningful_children<'a, 'i>(
    n: roxmltree::Node<'a, 'i>,
) -> impl Iterator<Item = roxmltree::Node<'a, 'i>> {
    n.children().filter(|c| {
        c.is_element() || (c.is_text() && c.text().is_some_and(|t| !t.trim().is_empty()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::binary::{EndpointBinaryQos, EndpointQosBinary};
    use crate::wire::{ObjectId, VariantExtra};

    fn variant(kind: u8, representation: Representation) -> ObjectVariant {
        ObjectVariant {
            kind,
            representation,
            extra: VariantExtra::Parent(ObjectId::new(1, object_kind::PUBLISHER)),
        }
    }

    fn unhex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
            .collect()
    }

    /// The CREATE of a message of `microros-reset.txt`.
    fn create_in(message: &str) -> (ObjectVariant, bool) {
        let bytes = unhex(message);
        let m = crate::wire::Message::decode(&bytes).expect("message");
        let sub = m.submessages.into_iter().next().expect("a submessage");
        match sub.payload {
            crate::wire::Payload::Create(c) => (c.variant, sub.little_endian),
            other => panic!("not a CREATE: {other:?}"),
        }
    }

    /// micro-ROS's data writer and participant of `microros-reset.txt`, created before and
    /// after the reset: the bodies differ in alignment padding only.
    #[test]
    fn a_binary_body_differing_in_padding_means_the_same() {
        let pairs = [
            (
                "8180030001071c00000d0005050300000e00000000020100030001000a00000000000003",
                "8180030001071c00000d0005050300000e000000000201000300017b0a00000000000003",
            ),
            (
                "8180000001071e00000a0001010300000f000000000100000700000074616c6b6572000000000000",
                "8180000001071e00000a0001010300000f000000000100000700000074616c6b6572007400000000",
            ),
            (
                "8180000001071e00000a0001010300000f00000000012f2f0700000074616c6b6572000000000000",
                "8180000001071e00000a0001010300000f000000000100000700000074616c6b6572000000000000",
            ),
        ];
        for (first, second) in pairs {
            let (a, a_le) = create_in(first);
            let (b, b_le) = create_in(second);
            assert!(same_meaning(&a, a_le, &b, b_le), "{first} / {second}");
        }
        let (a, _) = create_in(pairs[0].0);
        let (b, _) = create_in(pairs[0].1);
        assert_ne!(a, b, "the bytes differ");
    }

    #[test]
    fn a_binary_body_with_another_qos_or_byte_order_differs_where_it_matters() {
        let qos = |depth| EndpointBinary {
            topic_id: ObjectId::new(0, object_kind::TOPIC),
            qos: Some(EndpointBinaryQos {
                base: EndpointQosBinary {
                    flags: 0x0003,
                    history_depth: Some(depth),
                    ..Default::default()
                },
                ..Default::default()
            }),
        };
        let w = |e: &EndpointBinary, le| {
            variant(
                object_kind::DATAWRITER,
                Representation::Binary(e.encode(true, le)),
            )
        };
        assert!(!same_meaning(
            &w(&qos(10), true),
            true,
            &w(&qos(5), true),
            true
        ));
        // The same writer sent big-endian by another build of the client.
        assert!(same_meaning(
            &w(&qos(10), true),
            true,
            &w(&qos(10), false),
            false
        ));
        // Bytes that do not decode match only themselves.
        let junk = variant(object_kind::DATAWRITER, Representation::Binary(vec![1, 2]));
        assert!(same_meaning(&junk, true, &junk.clone(), true));
        assert!(!same_meaning(&junk, true, &junk.clone(), false));
    }

    #[test]
    fn xml_compares_as_a_tree() {
        let a = "<dds><data_writer><topic><kind>NO_KEY</kind><name>T</name>\
                 <dataType>HelloWorld</dataType></topic></data_writer></dds>";
        let b = "<?xml version=\"1.0\"?>\n<dds>\n  <data_writer>\n    <!-- the topic -->\n\
                 <topic>\n <kind> NO_KEY </kind>\n<name>T</name>\n\
                 <dataType>HelloWorld</dataType>\n</topic>\n  </data_writer>\n</dds>\n";
        let x = |s: &str| variant(object_kind::DATAWRITER, Representation::Xml(s.into()));
        assert!(same_meaning(&x(a), true, &x(b), true));
        assert!(!same_meaning(
            &x(a),
            true,
            &x(&a.replace("NO_KEY", "WITH_KEY")),
            true
        ));
        // Order of elements counts, order of attributes does not.
        let p = "<dds><participant><rtps a=\"1\" b=\"2\"><name>n</name></rtps></participant></dds>";
        let q = "<dds><participant><rtps b='2' a='1'><name>n</name></rtps></participant></dds>";
        assert!(same_meaning(&x(p), true, &x(q), true));
        let r = "<dds><participant><rtps a=\"1\"><name>n</name></rtps></participant></dds>";
        assert!(!same_meaning(&x(p), true, &x(r), true));
        // Broken XML matches only itself.
        assert!(same_meaning(&x("<dds>"), true, &x("<dds>"), true));
        assert!(!same_meaning(&x("<dds>"), true, &x("<dds> "), true));
    }

    #[test]
    fn different_forms_kinds_or_parents_differ() {
        let xml = variant(object_kind::DATAWRITER, Representation::Xml("<a/>".into()));
        let by_ref = variant(
            object_kind::DATAWRITER,
            Representation::Reference("a".into()),
        );
        assert!(!same_meaning(&xml, true, &by_ref, true));
        let mut other_parent = xml.clone();
        other_parent.extra = VariantExtra::Parent(ObjectId::new(2, object_kind::PUBLISHER));
        assert!(!same_meaning(&xml, true, &other_parent, true));
        assert!(same_meaning(&by_ref, true, &by_ref.clone(), false));
    }
}
