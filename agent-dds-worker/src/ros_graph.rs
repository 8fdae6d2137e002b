//! The ROS 2 graph: XRCE participants created with a ROS node name and with an endpoint on a
//! ROS topic (`rt/`, `rq/`, `rr/`: what micro-ROS does) are announced on
//! `ros_discovery_info`, with the GIDs of their data writers and readers, so
//! `ros2 node list` and `ros2 node info` see them. Without this, their topics work but the
//! nodes are invisible, as with MicroXRCEAgent (the micro-ROS agent adds a graph manager).
//!
//! One `ParticipantEntitiesInfo` writer per domain, on the domain's publishing DDS
//! participant, carries every node of the domain (the topic has no key, so one writer per
//! DDS participant). The message is rebuilt from the worker's entities when something in the
//! domain changes, at most every [`REFRESH`].
//!
//! The message's layout depends on the ROS 2 distribution of the readers: Humble's GIDs have
//! 24 octets, Iron's and later ones' 16 ([`entities_info`]). The worker publishes the layout
//! of one distribution, [`RosDistro`], chosen when it starts (`--ros-distro`,
//! `XRCE_ROS_DISTRO`, else `ROS_DISTRO` as a sourced ROS 2 shell sets it, else jazzy).
//!
//! Why one explicit setting rather than following, per domain, the layout other participants
//! publish: the worker does not read `ros_discovery_info` at all (it only writes it; a
//! client's own reader on that topic gets the samples as opaque bytes, never parsed here), and
//! detection would have to add a reader per domain, guess from samples that can parse in both
//! layouts (every Humble message reads, in the 16-octet layout, as a GID and no node: the
//! count read there is the GID's zero padding), pick a side in domains where Humble and later
//! distributions meet (the case that crashes readers), and publish something before anyone
//! else spoke. A gateway serves one ROS 2 installation, whose `ROS_DISTRO` names the layout.

use std::collections::{HashMap, HashSet};
use std::ffi::OsStr;
use std::time::{Duration, Instant};

use crate::backend::{
    BackendError, DdsBackend, DdsWriter, EndpointQos, Guid, Publisher, Sample, TopicSpec,
};

pub mod entities_info;

pub use entities_info::{EncodeError, Encoded, GidLayout};

/// A ROS 2 distribution, for the layout of `ros_discovery_info` its readers parse.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, clap::ValueEnum)]
pub enum RosDistro {
    /// Humble Hawksbill (LTS until 2027): 24-octet GIDs.
    Humble,
    /// Iron Irwini: 16-octet GIDs from here on.
    Iron,
    /// Jazzy Jalisco (LTS), the default: 16-octet GIDs.
    #[default]
    Jazzy,
    /// Kilted Kaiju: 16-octet GIDs.
    Kilted,
    /// Rolling Ridley: 16-octet GIDs.
    Rolling,
}

/// Where the distribution in use was named.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DistroSource {
    /// `--ros-distro` or `XRCE_ROS_DISTRO`.
    Option,
    /// `ROS_DISTRO`, as a sourced ROS 2 environment sets it.
    RosDistroVariable,
    /// Neither: the default.
    Default,
}

/// A distribution name the agent does not know.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RosDistroError {
    /// Not one of [`RosDistro::ALL`].
    #[error(
        "unknown ROS 2 distribution {value:?}; accepted: humble, iron, jazzy, kilted, rolling"
    )]
    Unknown {
        /// The value as given (cut to 64 characters).
        value: String,
    },
    /// `ROS_DISTRO` names an unknown distribution (and no option overrides it).
    #[error(
        "ROS_DISTRO={value:?} is not a ROS 2 distribution this agent knows (accepted: humble, \
         iron, jazzy, kilted, rolling); pass --ros-distro (or set XRCE_ROS_DISTRO) to one of \
         them: humble for 24-octet GIDs, any other for 16"
    )]
    UnknownRosDistroVariable {
        /// The variable's value (cut to 64 characters).
        value: String,
    },
}

impl RosDistro {
    /// Every distribution the agent knows, oldest first.
    pub const ALL: [RosDistro; 5] = [
        RosDistro::Humble,
        RosDistro::Iron,
        RosDistro::Jazzy,
        RosDistro::Kilted,
        RosDistro::Rolling,
    ];

    /// Its name as `ROS_DISTRO` spells it.
    pub const fn as_str(self) -> &'static str {
        match self {
            RosDistro::Humble => "humble",
            RosDistro::Iron => "iron",
            RosDistro::Jazzy => "jazzy",
            RosDistro::Kilted => "kilted",
            RosDistro::Rolling => "rolling",
        }
    }

    /// The `Gid` layout its rmw_dds_common defines (24 octets up to Humble, 16 from Iron).
    pub const fn gid_layout(self) -> GidLayout {
        match self {
            RosDistro::Humble => GidLayout::Octets24,
            RosDistro::Iron | RosDistro::Jazzy | RosDistro::Kilted | RosDistro::Rolling => {
                GidLayout::Octets16
            }
        }
    }

    /// The distribution in use: `explicit` (`--ros-distro`, or `XRCE_ROS_DISTRO`, parsed by
    /// clap) wins; else `ros_distro_var`, the value of `ROS_DISTRO` (empty counts as unset);
    /// else jazzy. An unknown `ROS_DISTRO` is an error rather than a silent default: the
    /// user's ROS 2 would then not see the nodes, with no hint why.
    pub fn resolve(
        explicit: Option<RosDistro>,
        ros_distro_var: Option<&OsStr>,
    ) -> Result<(RosDistro, DistroSource), RosDistroError> {
        if let Some(d) = explicit {
            return Ok((d, DistroSource::Option));
        }
        let Some(var) = ros_distro_var.filter(|v| !v.to_string_lossy().trim().is_empty()) else {
            return Ok((RosDistro::default(), DistroSource::Default));
        };
        let value = var.to_string_lossy();
        match value.parse::<RosDistro>() {
            Ok(d) => Ok((d, DistroSource::RosDistroVariable)),
            Err(_) => Err(RosDistroError::UnknownRosDistroVariable {
                value: value.chars().take(64).collect(),
            }),
        }
    }
}

impl std::fmt::Display for RosDistro {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for RosDistro {
    type Err = RosDistroError;

    /// A distribution name as `ROS_DISTRO` spells it (surrounding blanks and case ignored).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let t = s.trim();
        RosDistro::ALL
            .into_iter()
            .find(|d| d.as_str().eq_ignore_ascii_case(t))
            .ok_or_else(|| RosDistroError::Unknown {
                value: t.chars().take(64).collect(),
            })
    }
}

/// Shortest time between two updates of one domain's graph message.
pub const REFRESH: Duration = Duration::from_millis(100);

pub use crate::ros_nodes::{node_name, DomainNodes};

/// A domain's graph writer (with its publisher), its participant's GUID, and what it last
/// published.
struct GraphWriter {
    writer: Box<dyn DdsWriter>,
    _group: Publisher,
    participant: Guid,
    last: DomainNodes,
}

/// The `ros_discovery_info` writers and what changed.
pub struct RosGraph {
    enabled: bool,
    /// The layout every domain's message is encoded in.
    layout: GidLayout,
    writers: HashMap<u16, GraphWriter>,
    dirty: HashSet<u16>,
    next_at: Option<Instant>,
}

impl std::fmt::Debug for RosGraph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RosGraph")
            .field("enabled", &self.enabled)
            .field("layout", &self.layout)
            .field("domains", &self.writers.len())
            .finish()
    }
}

impl RosGraph {
    /// A graph publisher in the layout of the default distribution (jazzy); `enabled` =
    /// false publishes nothing.
    pub fn new(enabled: bool) -> Self {
        RosGraph {
            enabled,
            layout: RosDistro::default().gid_layout(),
            writers: HashMap::new(),
            dirty: HashSet::new(),
            next_at: None,
        }
    }

    /// Something in `domain` changed (a node or one of its endpoints came or went).
    pub fn touch(&mut self, domain: u16, now: Instant) {
        if !self.enabled {
            return;
        }
        self.dirty.insert(domain);
        if self.next_at.is_none() {
            self.next_at = Some(now + REFRESH);
        }
    }

    /// The layout messages are encoded in.
    pub fn layout(&self) -> GidLayout {
        self.layout
    }

    /// Encodes messages in `layout` from now on. Meant for start-up; should the layout
    /// change later, every domain that has a writer publishes again in the new one.
    pub fn set_layout(&mut self, layout: GidLayout, now: Instant) {
        if layout == self.layout {
            return;
        }
        self.layout = layout;
        let domains: Vec<u16> = self.writers.keys().copied().collect();
        for d in domains {
            if let Some(w) = self.writers.get_mut(&d) {
                // What was published is stale in the new layout: not "unchanged".
                w.last = DomainNodes::default();
            }
            self.touch(d, now);
        }
    }

    /// Whether `domain` has a graph writer (it had a node once).
    pub fn has_writer(&self, domain: u16) -> bool {
        self.writers.contains_key(&domain)
    }

    /// Drops `domain`'s graph writer and publisher (its last XRCE participant went, and the
    /// domain's DDS participant is released with them: ROS tools forget the nodes of a
    /// participant that left). A node in the domain later makes a new writer.
    pub fn forget(&mut self, domain: u16) {
        self.writers.remove(&domain);
        self.dirty.remove(&domain);
    }

    /// When the next update is due, if one is pending.
    pub fn deadline(&self) -> Option<Instant> {
        self.next_at
    }

    /// The domains whose message is due now (and clears them).
    pub fn due(&mut self, now: Instant) -> Vec<u16> {
        match self.next_at {
            Some(t) if t <= now => {
                self.next_at = None;
                self.dirty.drain().collect()
            }
            _ => Vec::new(),
        }
    }

    fn make_writer(backend: &mut dyn DdsBackend, domain: u16) -> Result<GraphWriter, BackendError> {
        let participant = backend.participant_guid(domain)?;
        let group = backend.create_publisher(domain, &[])?;
        let topic = TopicSpec {
            name: entities_info::TOPIC_NAME.to_string(),
            type_name: entities_info::TYPE_NAME.to_string(),
            key: None,
        };
        let writer = backend
            .create_writer(&group, &topic, &EndpointQos::ros_discovery_writer(), true)
            .map_err(|e| e.context("ros_discovery_info writer"))?;
        Ok(GraphWriter {
            writer,
            _group: group,
            participant,
            last: DomainNodes::default(),
        })
    }

    /// Publishes `nodes` for `domain` through `backend` (on the domain's publishing
    /// participant), unless the message would not change. The writer is made on first use;
    /// a domain that never had a node gets none.
    pub fn publish(
        &mut self,
        domain: u16,
        backend: &mut dyn DdsBackend,
        nodes: DomainNodes,
    ) -> Result<(), BackendError> {
        use std::collections::hash_map::Entry;
        let layout = self.layout;
        let w = match self.writers.entry(domain) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(v) => {
                if nodes.nodes.is_empty() {
                    return Ok(());
                }
                v.insert(Self::make_writer(backend, domain)?)
            }
        };
        if w.last == nodes {
            return Ok(());
        }
        let encoded = encode(w.participant, &nodes, layout)
            .map_err(|e| BackendError::Dds(format!("ros_discovery_info encoding: {e}")))?;
        if !encoded.omitted.is_empty() {
            tracing::warn!(
                domain,
                omitted = ?encoded.omitted,
                "ROS nodes left out of the graph: a namespace or name is longer than 256 \
                 octets or holds a NUL (rmw_dds_common's string<=256)"
            );
        }
        w.writer
            .write(Sample::cdr(true, &encoded.body))
            .map_err(|e| e.context("ros_discovery_info write"))?;
        tracing::info!(
            domain,
            nodes = nodes.nodes.len().saturating_sub(encoded.omitted.len()),
            gid_octets = layout.octets(),
            "ROS graph published"
        );
        w.last = nodes;
        Ok(())
    }
}

/// The `ParticipantEntitiesInfo` of the DDS participant `participant` and its nodes, as a
/// little-endian CDR body in `layout` ([`entities_info`] has the byte layout).
pub fn encode(
    participant: Guid,
    nodes: &DomainNodes,
    layout: GidLayout,
) -> Result<Encoded, EncodeError> {
    let infos = nodes
        .nodes
        .iter()
        .map(|(name, writers, readers)| entities_info::NodeEntities {
            namespace: name.namespace(),
            name: name.base_name(),
            readers,
            writers,
        });
    entities_info::encode(&participant, infos, layout)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn participant_names_map_to_node_names_as_micro_ros_sends_them() {
        let n = node_name("talker").expect("root namespace");
        assert_eq!((n.namespace(), n.base_name()), ("/", "talker"));
        let n = node_name("/robot/arm/driver").expect("namespaced");
        assert_eq!((n.namespace(), n.base_name()), ("/robot/arm", "driver"));
        let n = node_name("robot/driver").expect("relative namespace");
        assert_eq!((n.namespace(), n.base_name()), ("/robot", "driver"));
        for bad in ["", "9lives", "has space", "a//b", "node-name"] {
            assert!(node_name(bad).is_none(), "{bad:?}");
        }
    }

    #[test]
    fn the_graph_message_is_laid_out_as_rmw_dds_common_defines_it() {
        // ParticipantEntitiesInfo: Gid gid, NodeEntitiesInfo[] (node_namespace, node_name,
        // reader_gid_seq, writer_gid_seq); a Gid is 24 octets in Humble, 16 after it.
        let nodes = DomainNodes {
            nodes: vec![(
                node_name("talker").expect("name"),
                vec![[1; 16], [2; 16]],
                vec![[3; 16]],
            )],
            participants: vec![],
        };
        for (layout, n) in [(GidLayout::Octets24, 24), (GidLayout::Octets16, 16)] {
            let gid = |b: u8| {
                let mut g = vec![b; 16];
                g.resize(n, 0);
                g
            };
            let mut expected = gid(9);
            expected.extend(1u32.to_le_bytes());
            expected.extend(2u32.to_le_bytes());
            expected.extend(b"/\0\0\0");
            expected.extend(7u32.to_le_bytes());
            expected.extend(b"talker\0\0");
            expected.extend(1u32.to_le_bytes());
            expected.extend(gid(3));
            expected.extend(2u32.to_le_bytes());
            expected.extend(gid(1));
            expected.extend(gid(2));
            let e = encode([9; 16], &nodes, layout).expect("encoded");
            assert_eq!(e.body, expected, "{layout:?}");
            assert!(e.omitted.is_empty());
        }
    }

    #[test]
    fn the_distribution_comes_from_the_option_then_ros_distro_then_the_default() {
        use std::ffi::OsString;
        let humble = OsString::from("humble");
        assert_eq!(
            RosDistro::resolve(Some(RosDistro::Jazzy), Some(&humble)),
            Ok((RosDistro::Jazzy, DistroSource::Option)),
            "the option wins"
        );
        assert_eq!(
            RosDistro::resolve(None, Some(&humble)),
            Ok((RosDistro::Humble, DistroSource::RosDistroVariable))
        );
        for unset in [None, Some(OsString::from("")), Some(OsString::from("  "))] {
            assert_eq!(
                RosDistro::resolve(None, unset.as_deref()),
                Ok((RosDistro::Jazzy, DistroSource::Default))
            );
        }
        // An unknown ROS_DISTRO is refused, naming every accepted value, unless the option
        // overrides it.
        let foxy = OsString::from("foxy");
        let err = RosDistro::resolve(None, Some(&foxy)).expect_err("unknown");
        let text = err.to_string();
        for d in RosDistro::ALL {
            assert!(text.contains(d.as_str()), "{text}");
        }
        assert!(
            text.contains("\"foxy\"") && text.contains("--ros-distro"),
            "{text}"
        );
        assert_eq!(
            RosDistro::resolve(Some(RosDistro::Humble), Some(&foxy)),
            Ok((RosDistro::Humble, DistroSource::Option))
        );
        // Names as ROS_DISTRO spells them, and their layouts.
        for d in RosDistro::ALL {
            assert_eq!(d.as_str().parse::<RosDistro>(), Ok(d));
            assert_eq!(
                d.gid_layout().octets(),
                if d == RosDistro::Humble { 24 } else { 16 }
            );
        }
        assert_eq!(" Humble\n".parse::<RosDistro>(), Ok(RosDistro::Humble));
        let err = "galactic".parse::<RosDistro>().expect_err("unknown");
        assert!(err
            .to_string()
            .contains("humble, iron, jazzy, kilted, rolling"));
        // The names clap accepts are the same.
        for d in RosDistro::ALL {
            assert_eq!(
                <RosDistro as clap::ValueEnum>::from_str(d.as_str(), false),
                Ok(d)
            );
        }
    }

    #[test]
    fn the_layout_is_jazzy_s_unless_set() {
        let mut g = RosGraph::new(true);
        assert_eq!(g.layout(), GidLayout::Octets16);
        let t0 = Instant::now();
        g.set_layout(GidLayout::Octets24, t0);
        assert_eq!(g.layout(), GidLayout::Octets24);
        // No domain has a writer yet: nothing to publish again.
        assert_eq!(g.deadline(), None);
    }

    #[test]
    fn updates_are_batched_per_refresh_period() {
        let mut g = RosGraph::new(true);
        let t0 = Instant::now();
        g.touch(3, t0);
        g.touch(4, t0 + Duration::from_millis(10));
        assert_eq!(g.deadline(), Some(t0 + REFRESH));
        assert!(g.due(t0 + Duration::from_millis(50)).is_empty());
        let mut due = g.due(t0 + REFRESH);
        due.sort();
        assert_eq!(due, vec![3, 4]);
        assert_eq!(g.deadline(), None);
        let mut off = RosGraph::new(false);
        off.touch(1, t0);
        assert_eq!(off.deadline(), None);
    }
}
