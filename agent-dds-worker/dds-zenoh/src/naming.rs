//! rmw_zenoh's names, sans IO: the key expression of a topic or service, the liveliness
//! token of a node or an endpoint, the QoS text inside a token, and the attachment every
//! sample, query and reply carries.
//!
//! The conventions are those of rmw_zenoh 0.2.10 (ROS 2 Jazzy) and 0.6.7 (Kilted), which do
//! not differ in any of them (`liveliness_utils.cpp`, `attachment_helpers.cpp`,
//! `rmw_zenoh.cpp` at those tags).

use xrce_dds_seam::policies::{Durability, History, Reliability};
use xrce_dds_seam::qos::EndpointQos;

/// What an XRCE topic name stands for in a ROS graph.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RosName {
    /// `rt/<name>`: the topic `/<name>`.
    Topic(String),
    /// `rq/<name>Request`: the requests of the service `/<name>`.
    Request(String),
    /// `rr/<name>Reply`: the replies of the service `/<name>`.
    Reply(String),
    /// Any other name: a plain XRCE application's topic, kept as it is.
    Plain(String),
}

impl RosName {
    /// Reads a DDS topic name as micro-ROS writes them.
    pub fn from_dds(topic: &str) -> Self {
        if let Some(t) = topic.strip_prefix("rt/") {
            return RosName::Topic(t.to_string());
        }
        if let Some(s) = topic
            .strip_prefix("rq/")
            .and_then(|s| s.strip_suffix("Request"))
        {
            return RosName::Request(s.to_string());
        }
        if let Some(s) = topic
            .strip_prefix("rr/")
            .and_then(|s| s.strip_suffix("Reply"))
        {
            return RosName::Reply(s.to_string());
        }
        RosName::Plain(topic.to_string())
    }

    /// The name without slashes at either end (what goes into a key expression).
    pub fn stripped(&self) -> &str {
        let n = match self {
            RosName::Topic(n) | RosName::Request(n) | RosName::Reply(n) | RosName::Plain(n) => n,
        };
        n.trim_matches('/')
    }

    /// Whether it names a service (requests or replies).
    pub fn is_service(&self) -> bool {
        matches!(self, RosName::Request(_) | RosName::Reply(_))
    }

    /// The fully qualified ROS name (`/chatter`), as graph tools show it.
    pub fn qualified(&self) -> String {
        format!("/{}", self.stripped())
    }
}

/// A name that cannot be part of a key expression.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    /// Empty after removing the slashes at its ends.
    #[error("an empty topic name")]
    Empty,
    /// A character Zenoh reserves (`*`, `$`, `?`, `#`), an empty chunk (`a//b`) or a
    /// control character.
    #[error("{0:?} cannot be part of a Zenoh key expression")]
    Reserved(String),
}

fn check_chunks(s: &str) -> Result<(), NameError> {
    if s.is_empty() {
        return Err(NameError::Empty);
    }
    let bad = s.split('/').any(str::is_empty)
        || s.chars()
            .any(|c| matches!(c, '*' | '$' | '?' | '#') || c.is_control());
    if bad {
        return Err(NameError::Reserved(s.chars().take(64).collect()));
    }
    Ok(())
}

/// The key expression of a topic or service: `<domain>/<name>/<type>/<hash>`, the name without
/// its outer slashes (inner ones kept), as rmw_zenoh's publishers, subscriptions, services and
/// clients all use it (no wildcard: another type or hash is another key).
pub fn data_key(
    domain: u16,
    name: &RosName,
    type_name: &str,
    hash: &str,
) -> Result<String, NameError> {
    let topic = name.stripped();
    check_chunks(topic)?;
    if type_name.contains('/') {
        return Err(NameError::Reserved(type_name.chars().take(64).collect()));
    }
    check_chunks(type_name)?;
    check_chunks(hash)?;
    Ok(format!("{domain}/{topic}/{type_name}/{hash}"))
}

/// A part of a liveliness token: `%` for an empty one, and `/` inside it as `%` too.
pub fn mangle(part: &str) -> String {
    if part.is_empty() {
        return "%".to_string();
    }
    part.replace('/', "%")
}

/// What an entity is in the graph (the token's kind letters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum EntityKind {
    /// A node (`NN`).
    Node,
    /// A publisher (`MP`).
    Publisher,
    /// A subscription (`MS`).
    Subscription,
    /// A service server (`SS`).
    Service,
    /// A service client (`SC`).
    Client,
}

impl EntityKind {
    /// The two letters of the token.
    pub fn letters(self) -> &'static str {
        match self {
            EntityKind::Node => "NN",
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
            EntityKind::Service => "SS",
            EntityKind::Client => "SC",
        }
    }
}

/// A node as its tokens name it.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeToken {
    /// The session's Zenoh id, as `ZenohId` displays it.
    pub zid: String,
    /// The node's id within the session.
    pub id: u64,
    /// The enclave (`/` unless security is configured).
    pub enclave: String,
    /// The namespace (`/`, `/ns`).
    pub namespace: String,
    /// The node's name.
    pub name: String,
}

/// An endpoint's part of its token.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct EndpointToken {
    /// Publisher, subscription, service or client.
    pub kind: EntityKind,
    /// Its id within the session.
    pub id: u64,
    /// The fully qualified topic or service name (`/chatter`).
    pub name: String,
    /// The DDS type name (`std_msgs::msg::dds_::String_`).
    pub type_name: String,
    /// The type hash (`RIHS01_...`).
    pub hash: String,
    /// The QoS text ([`qos_text`]).
    pub qos: String,
}

/// The liveliness token of a node (`endpoint` None) or of one of its endpoints:
/// `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>` and,
/// for an endpoint, `/<name>/<type>/<hash>/<qos>`. A node's entity id is its node id.
pub fn liveliness_token(domain: u16, node: &NodeToken, endpoint: Option<&EndpointToken>) -> String {
    let (id, kind) = match endpoint {
        Some(e) => (e.id, e.kind),
        None => (node.id, EntityKind::Node),
    };
    let mut t = format!(
        "@ros2_lv/{domain}/{}/{}/{id}/{}/{}/{}/{}",
        node.zid,
        node.id,
        kind.letters(),
        mangle(&node.enclave),
        mangle(&node.namespace),
        mangle(&node.name),
    );
    if let Some(e) = endpoint {
        t.push_str(&format!(
            "/{}/{}/{}/{}",
            mangle(&e.name),
            mangle(&e.type_name),
            mangle(&e.hash),
            e.qos
        ));
    }
    t
}

/// rmw_zenoh's default depth: a keep-last depth of 42 is left out of the QoS text.
pub const DEFAULT_DEPTH: i32 = 42;

/// The QoS text of a token: `<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:
/// <lifespan s>,<ns>:<liveliness>,<lease s>,<ns>`, each value rmw's enum number, and a value
/// equal to rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite durations,
/// automatic liveliness) left empty, as rmw_zenoh writes it. Reliability: 2 best effort;
/// durability: 1 transient local; history: 2 keep all.
pub fn qos_text(qos: &EndpointQos) -> String {
    let reliability = match qos.reliability {
        Reliability::Reliable => "",
        Reliability::BestEffort => "2",
    };
    let durability = match qos.durability {
        Durability::Volatile => "",
        // Transient and persistent need a service rmw does not have: rmw_zenoh's nearest is
        // transient local.
        _ => "1",
    };
    let (history, depth) = match qos.history {
        History::KeepLast(d) if d <= 0 || d == DEFAULT_DEPTH => ("", String::new()),
        History::KeepLast(d) => ("", d.to_string()),
        History::KeepAll => ("2", String::new()),
    };
    format!("{reliability}:{durability}:{history},{depth}:,:,:,,")
}

/// rmw_zenoh's attachment: the sample's sequence number (from 1 per publisher or client),
/// its source timestamp in nanoseconds since the epoch, and the source's 16-byte GID, as
/// zenoh-ext serializes `(i64, i64, [u8; 16])` (little endian, the array after its length
/// as a LEB128 byte, 16): 33 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    /// The sequence number.
    pub sequence_number: i64,
    /// The source timestamp (ns since the Unix epoch).
    pub source_timestamp: i64,
    /// The writer's GID.
    pub gid: [u8; 16],
}

/// The encoded length of an [`Attachment`].
pub const ATTACHMENT_LEN: usize = 33;

impl Attachment {
    /// Its bytes.
    pub fn encode(&self) -> [u8; ATTACHMENT_LEN] {
        let mut b = [0u8; ATTACHMENT_LEN];
        b[..8].copy_from_slice(&self.sequence_number.to_le_bytes());
        b[8..16].copy_from_slice(&self.source_timestamp.to_le_bytes());
        b[16] = 16;
        b[17..].copy_from_slice(&self.gid);
        b
    }

    /// Reads one; None if the bytes are not one (another length, another GID length).
    pub fn decode(b: &[u8]) -> Option<Self> {
        if b.len() != ATTACHMENT_LEN || b[16] != 16 {
            return None;
        }
        Some(Attachment {
            sequence_number: i64::from_le_bytes(b[..8].try_into().ok()?),
            source_timestamp: i64::from_le_bytes(b[8..16].try_into().ok()?),
            gid: b[17..].try_into().ok()?,
        })
    }
}

/// The ROS name of a DDS type name (`std_msgs::msg::dds_::String_` ->
/// `std_msgs/msg/String`), for looking up its hash; None for a name that is not one.
pub fn ros_type_name(dds_type: &str) -> Option<String> {
    let parts: Vec<&str> = dds_type.split("::").collect();
    match parts.as_slice() {
        [pkg, kind @ ("msg" | "srv" | "action"), "dds_", name] => {
            let name = name.strip_suffix('_')?;
            // ROS package and type names: letters, digits, underscores (the name becomes a
            // path in a ROS installation: nothing else may reach the file system).
            let identifier = |s: &str| {
                !s.is_empty() && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
            };
            if !identifier(pkg) || !identifier(name) {
                return None;
            }
            Some(format!("{pkg}/{kind}/{name}"))
        }
        _ => None,
    }
}

/// The service type of a request or reply type (`example_interfaces::srv::dds_::AddTwoInts_Request_`
/// -> `example_interfaces::srv::dds_::AddTwoInts_`), which rmw_zenoh's service keys and
/// tokens carry; the name itself if it is neither.
pub fn service_type_name(dds_type: &str) -> String {
    for suffix in ["_Request_", "_Response_"] {
        if let Some(base) = dds_type.strip_suffix(suffix) {
            return format!("{base}_");
        }
    }
    dds_type.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_dds_seam::policies::QosDesc;
    use xrce_dds_seam::qos::EndpointSide;

    #[test]
    fn micro_ros_names_map_to_ros_names() {
        assert_eq!(
            RosName::from_dds("rt/chatter"),
            RosName::Topic("chatter".into())
        );
        assert_eq!(
            RosName::from_dds("rq/add_two_intsRequest"),
            RosName::Request("add_two_ints".into())
        );
        assert_eq!(
            RosName::from_dds("rr/ns/add_two_intsReply"),
            RosName::Reply("ns/add_two_ints".into())
        );
        assert_eq!(
            RosName::from_dds("HelloWorldTopic"),
            RosName::Plain("HelloWorldTopic".into())
        );
        assert_eq!(
            RosName::from_dds("rq/oddname"),
            RosName::Plain("rq/oddname".into())
        );
        assert_eq!(
            RosName::from_dds("rt/ns/chatter").qualified(),
            "/ns/chatter"
        );
    }

    #[test]
    fn data_keys_are_rmw_zenohs() {
        let hash = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18";
        assert_eq!(
            data_key(
                0,
                &RosName::from_dds("rt/chatter"),
                "std_msgs::msg::dds_::String_",
                hash
            ),
            Ok(format!("0/chatter/std_msgs::msg::dds_::String_/{hash}"))
        );
        assert_eq!(
            data_key(7, &RosName::from_dds("rt/robot1/cmd_vel/"), "T", "H"),
            Ok("7/robot1/cmd_vel/T/H".to_string())
        );
        for bad in ["rt/a//b", "rt/*", "rt/a/$x", "rt/", "rt/a?b", "rt/a#"] {
            assert!(
                data_key(0, &RosName::from_dds(bad), "T", "H").is_err(),
                "{bad}"
            );
        }
        assert!(data_key(0, &RosName::from_dds("rt/a"), "x/y", "H").is_err());
    }

    #[test]
    fn tokens_follow_rmw_zenohs_layout() {
        let node = NodeToken {
            zid: "aac3178e146ba6f1fc6e6a4085e77f21".into(),
            id: 0,
            enclave: "/".into(),
            namespace: "/".into(),
            name: "talker".into(),
        };
        assert_eq!(
            liveliness_token(0, &node, None),
            "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/talker"
        );
        let transient = EndpointQos::resolve(
            EndpointSide::Writer,
            &QosDesc {
                reliability: Some(Reliability::BestEffort),
                durability: Some(Durability::TransientLocal),
                history: Some(History::KeepLast(1)),
                ..QosDesc::default()
            },
            &QosDesc::default(),
        );
        assert_eq!(qos_text(&transient), "2:1:,1:,:,:,,");
        let keep_all = EndpointQos::resolve(
            EndpointSide::Reader,
            &QosDesc {
                reliability: Some(Reliability::Reliable),
                durability: Some(Durability::Volatile),
                history: Some(History::KeepAll),
                ..QosDesc::default()
            },
            &QosDesc::default(),
        );
        assert_eq!(qos_text(&keep_all), "::2,:,:,:,,");
        let qos = EndpointQos::resolve(
            EndpointSide::Writer,
            &QosDesc {
                reliability: Some(Reliability::Reliable),
                durability: Some(Durability::Volatile),
                history: Some(History::KeepLast(7)),
                ..QosDesc::default()
            },
            &QosDesc::default(),
        );
        let publisher = EndpointToken {
            kind: EntityKind::Publisher,
            id: 11,
            name: "/chatter".into(),
            type_name: "std_msgs::msg::dds_::String_".into(),
            hash: "RIHS01_df66".into(),
            qos: qos_text(&qos),
        };
        let ns_node = NodeToken {
            namespace: "/robot/arm".into(),
            ..node
        };
        assert_eq!(
            liveliness_token(3, &ns_node, Some(&publisher)),
            "@ros2_lv/3/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%robot%arm/talker/%chatter/\
             std_msgs::msg::dds_::String_/RIHS01_df66/::,7:,:,:,,"
        );
    }

    #[test]
    fn attachments_are_33_bytes_in_zenoh_exts_layout() {
        let a = Attachment {
            sequence_number: 1,
            source_timestamp: 0x0102_0304_0506_0708,
            gid: [0xab; 16],
        };
        let b = a.encode();
        assert_eq!(&b[..8], &[1, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(&b[8..16], &[8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(b[16], 16);
        assert_eq!(Attachment::decode(&b), Some(a));
        assert_eq!(Attachment::decode(&b[..32]), None);
        let mut wrong = b;
        wrong[16] = 15;
        assert_eq!(Attachment::decode(&wrong), None);
    }

    #[test]
    fn type_names() {
        assert_eq!(
            ros_type_name("std_msgs::msg::dds_::String_").as_deref(),
            Some("std_msgs/msg/String")
        );
        assert_eq!(
            ros_type_name("example_interfaces::srv::dds_::AddTwoInts_").as_deref(),
            Some("example_interfaces/srv/AddTwoInts")
        );
        assert_eq!(ros_type_name("HelloWorld"), None);
        assert_eq!(ros_type_name("a::msg::dds_::_"), None);
        assert_eq!(ros_type_name("..::msg::dds_::x_"), None);
        assert_eq!(ros_type_name("a/../../etc::msg::dds_::passwd_"), None);
        assert_eq!(ros_type_name("a::msg::dds_::b/c_"), None);
        assert_eq!(
            service_type_name("example_interfaces::srv::dds_::AddTwoInts_Request_"),
            "example_interfaces::srv::dds_::AddTwoInts_"
        );
        assert_eq!(
            service_type_name("example_interfaces::srv::dds_::AddTwoInts_Response_"),
            "example_interfaces::srv::dds_::AddTwoInts_"
        );
    }
}
