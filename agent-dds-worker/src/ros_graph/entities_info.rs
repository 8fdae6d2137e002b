//! `rmw_dds_common/msg/ParticipantEntitiesInfo`, the message ROS 2 participants publish on
//! `ros_discovery_info`, encoded by hand in plain little-endian CDR, in either layout of its
//! `Gid`.
//!
//! Why not ros2-client's types: ros2-client fixes the length of a `Gid` when it is compiled
//! (its distribution features; this workspace builds `jazzy`, 16 octets), but the length a
//! reader expects depends on the ROS 2 distribution it runs. rmw_dds_common's `msg/Gid.msg`
//! is `char[24] data` in Humble (and Foxy, Galactic) and `char[16] data` from Iron on
//! (rmw_dds_common#68, "Change Gid.msg to be 16 bytes"). A reader meeting the other layout
//! cannot parse the message, and some crash (micro-ROS-Agent#214, #266), so the worker
//! chooses the layout when it starts ([`GidLayout`], from `--ros-distro`).
//!
//! The types (rmw_dds_common `msg/*.msg` of humble, iron, jazzy and rolling, identical but
//! for the Gid; a ROS `char` is one octet):
//!
//! ```text
//! Gid:                     char[24] data        (Humble)   char[16] data   (Iron and later)
//! NodeEntitiesInfo:        string<=256 node_namespace
//!                          string<=256 node_name
//!                          Gid[] reader_gid_seq
//!                          Gid[] writer_gid_seq
//! ParticipantEntitiesInfo: Gid gid
//!                          NodeEntitiesInfo[] node_entities_info_seq
//! ```
//!
//! The CDR rules this needs (XCDR1, the `CDR_LE` encapsulation ROS 2 uses; the types are
//! final, so nothing but the members is written):
//!
//! * an octet array is its octets: no length, no alignment;
//! * a sequence is a `uint32` element count aligned to 4, then its elements;
//! * a string is a `uint32` length aligned to 4 that counts the terminating NUL, the
//!   octets, then the NUL;
//! * alignment is relative to the start of the body, just after the 4-octet encapsulation
//!   header (`00 01 00 00`), which the DDS backend writes, not this encoder.
//!
//! Since a Gid is 16 or 24 octets (multiples of 4), padding (0 to 3 zero octets) only ever
//! follows a string. The tests below spell out every offset for both layouts.

use crate::backend::Guid;

/// The DDS topic of the ROS 2 graph.
pub const TOPIC_NAME: &str = "ros_discovery_info";
/// The DDS type name ROS 2's rmw implementations register for it (what readers match on).
pub const TYPE_NAME: &str = "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_";
/// The bound of `node_namespace` and `node_name` (`string<=256`), in octets without the
/// NUL. Readers with bounded-string type support refuse a whole sample with a longer one.
pub const STRING_BOUND: usize = 256;

/// How many octets a `Gid` has on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum GidLayout {
    /// `char[24] data`: ROS 2 Humble (and the older Foxy and Galactic). The 16-octet DDS
    /// GUID followed by 8 zero octets, as rmw_fastrtps and rmw_cyclonedds fill
    /// `rmw_gid_t` there (zeroed, then the GUID copied in front).
    Octets24,
    /// `char[16] data`: ROS 2 Iron and later. The DDS GUID itself.
    Octets16,
}

impl GidLayout {
    /// Octets of one `Gid`.
    pub const fn octets(self) -> usize {
        match self {
            GidLayout::Octets24 => 24,
            GidLayout::Octets16 => 16,
        }
    }
}

/// One node of a participant, as the message lists it.
#[derive(Debug, Clone, Copy)]
pub struct NodeEntities<'a> {
    /// `node_namespace`, e.g. `/` or `/robot`.
    pub namespace: &'a str,
    /// `node_name`, e.g. `talker`.
    pub name: &'a str,
    /// GUIDs of the node's data readers (`reader_gid_seq`).
    pub readers: &'a [Guid],
    /// GUIDs of the node's data writers (`writer_gid_seq`).
    pub writers: &'a [Guid],
}

impl NodeEntities<'_> {
    /// Whether both names fit the IDL's bound and carry no NUL (a C reader would cut the
    /// name there): a node that does not is left out rather than spoiling the whole
    /// message for every reader.
    fn fits(&self) -> bool {
        [self.namespace, self.name]
            .iter()
            .all(|s| s.len() <= STRING_BOUND && !s.contains('\0'))
    }
}

/// An encoded message and the nodes that had to be left out of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Encoded {
    /// The CDR body (no encapsulation header).
    pub body: Vec<u8>,
    /// `namespace/name` of nodes left out because a name is longer than [`STRING_BOUND`]
    /// or contains a NUL.
    pub omitted: Vec<String>,
}

/// Why a message cannot be encoded at all.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// A sequence longer than a CDR `uint32` count can say.
    #[error("{what}: {count} elements do not fit a CDR sequence")]
    TooManyElements {
        /// Which sequence.
        what: &'static str,
        /// Its length.
        count: usize,
    },
}

/// A little-endian CDR body being written.
struct CdrWriter {
    buf: Vec<u8>,
    gid_len: usize,
}

impl CdrWriter {
    /// Zero octets up to the next multiple of 4 (from the start of the body).
    fn align4(&mut self) {
        let pad = (4 - self.buf.len() % 4) % 4;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    fn u32(&mut self, v: u32) {
        self.align4();
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    fn count(&mut self, what: &'static str, count: usize) -> Result<(), EncodeError> {
        let n = u32::try_from(count).map_err(|_| EncodeError::TooManyElements { what, count })?;
        self.u32(n);
        Ok(())
    }

    /// A string the caller checked ([`NodeEntities::fits`]): its length then fits a u32.
    fn string(&mut self, s: &str) -> Result<(), EncodeError> {
        self.count("string", s.len() + 1)?;
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
        Ok(())
    }

    /// A Gid: the GUID, then zeros up to the layout's length.
    fn gid(&mut self, guid: &Guid) {
        self.buf.extend_from_slice(guid);
        let pad = self.gid_len.saturating_sub(guid.len());
        self.buf.resize(self.buf.len() + pad, 0);
    }

    fn gids(&mut self, what: &'static str, guids: &[Guid]) -> Result<(), EncodeError> {
        self.count(what, guids.len())?;
        for g in guids {
            self.gid(g);
        }
        Ok(())
    }
}

/// The `ParticipantEntitiesInfo` of the DDS participant `participant` listing `nodes`, as a
/// little-endian CDR body in `layout`. Nodes whose names do not fit the IDL are left out
/// and named in [`Encoded::omitted`].
pub fn encode<'a>(
    participant: &Guid,
    nodes: impl IntoIterator<Item = NodeEntities<'a>>,
    layout: GidLayout,
) -> Result<Encoded, EncodeError> {
    let (kept, left_out): (Vec<NodeEntities<'a>>, Vec<NodeEntities<'a>>) =
        nodes.into_iter().partition(NodeEntities::fits);
    let mut w = CdrWriter {
        buf: Vec::new(),
        gid_len: layout.octets(),
    };
    w.gid(participant);
    w.count("node_entities_info_seq", kept.len())?;
    for n in &kept {
        w.string(n.namespace)?;
        w.string(n.name)?;
        w.gids("reader_gid_seq", n.readers)?;
        w.gids("writer_gid_seq", n.writers)?;
    }
    Ok(Encoded {
        body: w.buf,
        omitted: left_out
            .iter()
            .map(|n| {
                // Cut (a client chose these names): a log line names the node, no more.
                let ns: String = n.namespace.chars().take(64).collect();
                let name: String = n.name.chars().take(64).collect();
                let sep = if ns.ends_with('/') { "" } else { "/" };
                format!("{ns}{sep}{name}")
            })
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const PARTICIPANT: Guid = [
        0x10, 0x11, 0x12, 0x13, 0x14, 0x15, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x1b, 0, 0, 1, 0xc1,
    ];
    const READER: Guid = [
        0x10, 0x11, 0x12, 0x13, 0x14, 0x15, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x1b, 0, 0, 2, 0x04,
    ];
    const WRITER: Guid = [
        0x10, 0x11, 0x12, 0x13, 0x14, 0x15, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x1b, 0, 0, 3, 0x03,
    ];

    fn talker() -> NodeEntities<'static> {
        NodeEntities {
            namespace: "/robot",
            name: "talker",
            readers: &[READER],
            writers: &[WRITER],
        }
    }

    /// Humble: one node `/robot/talker` with one reader and one writer, every offset by hand.
    #[test]
    fn humble_layout_has_24_octet_gids_padded_with_zeros() {
        let e = encode(&PARTICIPANT, [talker()], GidLayout::Octets24).expect("encoded");
        assert!(e.omitted.is_empty());
        let b = &e.body;
        let zeros8 = [0u8; 8];
        // 0..24: gid, the GUID then 8 zero octets.
        assert_eq!(&b[0..16], &PARTICIPANT);
        assert_eq!(&b[16..24], &zeros8);
        // 24..28: node_entities_info_seq count = 1 (24 is 4-aligned: no padding).
        assert_eq!(&b[24..28], &[1, 0, 0, 0]);
        // 28..32: node_namespace length 7 ("/robot" + NUL); 32..39 the octets and NUL.
        assert_eq!(&b[28..32], &[7, 0, 0, 0]);
        assert_eq!(&b[32..39], b"/robot\0");
        // 39..40: one padding octet, so the next length is at 40.
        assert_eq!(b[39], 0);
        // 40..44: node_name length 7 ("talker" + NUL); 44..51 the octets; 51 padding.
        assert_eq!(&b[40..44], &[7, 0, 0, 0]);
        assert_eq!(&b[44..51], b"talker\0");
        assert_eq!(b[51], 0);
        // 52..56: reader_gid_seq count 1; 56..80 the reader's Gid (GUID + 8 zeros).
        assert_eq!(&b[52..56], &[1, 0, 0, 0]);
        assert_eq!(&b[56..72], &READER);
        assert_eq!(&b[72..80], &zeros8);
        // 80..84: writer_gid_seq count 1 (80 is 4-aligned); 84..108 the writer's Gid.
        assert_eq!(&b[80..84], &[1, 0, 0, 0]);
        assert_eq!(&b[84..100], &WRITER);
        assert_eq!(&b[100..108], &zeros8);
        assert_eq!(b.len(), 108, "nothing after the last Gid");

        // The same, as one literal.
        let mut expected = Vec::new();
        expected.extend(PARTICIPANT);
        expected.extend([0; 8]);
        expected.extend([1, 0, 0, 0]);
        expected.extend([7, 0, 0, 0]);
        expected.extend(b"/robot\0\0");
        expected.extend([7, 0, 0, 0]);
        expected.extend(b"talker\0\0");
        expected.extend([1, 0, 0, 0]);
        expected.extend(READER);
        expected.extend([0; 8]);
        expected.extend([1, 0, 0, 0]);
        expected.extend(WRITER);
        expected.extend([0; 8]);
        assert_eq!(e.body, expected);
    }

    /// Iron and later: the same node with 16-octet Gids.
    #[test]
    fn iron_and_later_layout_has_16_octet_gids() {
        let e = encode(&PARTICIPANT, [talker()], GidLayout::Octets16).expect("encoded");
        let b = &e.body;
        // 0..16 gid; 16..20 node count 1.
        assert_eq!(&b[0..16], &PARTICIPANT);
        assert_eq!(&b[16..20], &[1, 0, 0, 0]);
        // 20..24 namespace length 7; 24..31 "/robot\0"; 31 padding.
        assert_eq!(&b[20..24], &[7, 0, 0, 0]);
        assert_eq!(&b[24..31], b"/robot\0");
        assert_eq!(b[31], 0);
        // 32..36 name length 7; 36..43 "talker\0"; 43 padding.
        assert_eq!(&b[32..36], &[7, 0, 0, 0]);
        assert_eq!(&b[36..43], b"talker\0");
        assert_eq!(b[43], 0);
        // 44..48 reader count 1; 48..64 the reader's Gid.
        assert_eq!(&b[44..48], &[1, 0, 0, 0]);
        assert_eq!(&b[48..64], &READER);
        // 64..68 writer count 1; 68..84 the writer's Gid.
        assert_eq!(&b[64..68], &[1, 0, 0, 0]);
        assert_eq!(&b[68..84], &WRITER);
        assert_eq!(b.len(), 84);
    }

    /// Padding after strings of every length modulo 4, and empty sequences: the root
    /// namespace `/` (length 2: 2 padding octets), a name of 3 octets + NUL (none).
    #[test]
    fn strings_are_padded_to_the_next_length_field() {
        let node = NodeEntities {
            namespace: "/",
            name: "abc",
            readers: &[],
            writers: &[WRITER],
        };
        let e = encode(&PARTICIPANT, [node], GidLayout::Octets16).expect("encoded");
        let mut expected = Vec::new();
        expected.extend(PARTICIPANT); // 0..16
        expected.extend([1, 0, 0, 0]); // 16..20 one node
        expected.extend([2, 0, 0, 0]); // 20..24 "/" + NUL
        expected.extend([b'/', 0, 0, 0]); // 24..26, 2 padding octets
        expected.extend([4, 0, 0, 0]); // 28..32 "abc" + NUL
        expected.extend(*b"abc\0"); // 32..36, no padding
        expected.extend([0, 0, 0, 0]); // 36..40 no readers
        expected.extend([1, 0, 0, 0]); // 40..44 one writer
        expected.extend(WRITER); // 44..60
        assert_eq!(e.body, expected);
        // No node: the gid and a zero count.
        let e = encode(&PARTICIPANT, [], GidLayout::Octets24).expect("encoded");
        let mut expected = PARTICIPANT.to_vec();
        expected.extend([0; 8]);
        expected.extend([0; 4]);
        assert_eq!(e.body, expected);
    }

    /// A node whose names do not fit `string<=256` (or hold a NUL) is left out, named, and
    /// the others are still announced.
    #[test]
    fn nodes_that_do_not_fit_the_idl_are_left_out_and_named() {
        let long = "n".repeat(STRING_BOUND + 1);
        let fits = "n".repeat(STRING_BOUND);
        let nodes = [
            NodeEntities {
                name: &long,
                ..talker()
            },
            NodeEntities {
                name: "a\0b",
                ..talker()
            },
            NodeEntities {
                name: &fits,
                ..talker()
            },
        ];
        let e = encode(&PARTICIPANT, nodes, GidLayout::Octets16).expect("encoded");
        assert_eq!(e.omitted.len(), 2);
        assert!(e.omitted[0].starts_with("/robot/nnn"), "{:?}", e.omitted);
        assert_eq!(&e.body[16..20], &[1, 0, 0, 0], "one node kept");
        let alone = encode(
            &PARTICIPANT,
            [NodeEntities {
                name: &fits,
                ..talker()
            }],
            GidLayout::Octets16,
        )
        .expect("encoded");
        assert_eq!(e.body, alone.body);
    }
}
