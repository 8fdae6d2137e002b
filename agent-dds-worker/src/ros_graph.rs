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

use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};

use ros2_client::builtin_topics::ros_discovery;
use ros2_client::entities_info::{NodeEntitiesInfo, ParticipantEntitiesInfo};
use ros2_client::{Gid, NodeName};

use crate::backend::{DdsBackend, DdsGroup, DdsWriter, EndpointQos, Guid, Sample, TopicSpec};

/// Shortest time between two updates of one domain's graph message.
pub const REFRESH: Duration = Duration::from_millis(100);

/// The node name a participant name stands for: micro-ROS sends `name` for a node in the
/// root namespace and `/ns/name` otherwise; None if it is not a valid ROS node name.
pub fn node_name(participant_name: &str) -> Option<NodeName> {
    let n = participant_name.trim();
    let (ns, base) = match n.rsplit_once('/') {
        Some(("", base)) => ("/", base),
        Some((ns, base)) if ns.starts_with('/') => (ns, base),
        Some((ns, base)) => return NodeName::new(&format!("/{ns}"), base).ok(),
        None => ("/", n),
    };
    NodeName::new(ns, base).ok()
}

/// What one domain's message lists: nodes with their endpoints' GUIDs.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct DomainNodes {
    /// (node, writer GUIDs, reader GUIDs), in a stable order.
    pub nodes: Vec<(NodeName, Vec<Guid>, Vec<Guid>)>,
}

/// A domain's graph writer (with its publisher), its participant's GUID, and what it last
/// published.
struct GraphWriter {
    writer: Box<dyn DdsWriter>,
    _group: Box<dyn DdsGroup>,
    participant: Guid,
    last: DomainNodes,
}

/// The `ros_discovery_info` writers and what changed.
pub struct RosGraph {
    enabled: bool,
    writers: HashMap<u16, GraphWriter>,
    dirty: HashSet<u16>,
    next_at: Option<Instant>,
}

impl std::fmt::Debug for RosGraph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RosGraph")
            .field("enabled", &self.enabled)
            .field("domains", &self.writers.len())
            .finish()
    }
}

impl RosGraph {
    /// A graph publisher; `enabled` = false publishes nothing.
    pub fn new(enabled: bool) -> Self {
        RosGraph {
            enabled,
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

    fn make_writer(backend: &mut dyn DdsBackend, domain: u16) -> Result<GraphWriter, String> {
        let participant = backend.participant_guid(domain)?;
        let group = backend.create_group(domain, true, &[])?;
        let topic = TopicSpec {
            name: ros_discovery::TOPIC_NAME.to_string(),
            type_name: ros_discovery::TYPE_NAME.to_string(),
            key: None,
        };
        let writer = backend
            .create_writer(&*group, &topic, &EndpointQos::ros_discovery_writer(), true)
            .map_err(|e| format!("ros_discovery_info writer: {e}"))?;
        Ok(GraphWriter {
            writer,
            _group: group,
            participant,
            last: DomainNodes { nodes: vec![] },
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
    ) -> Result<(), String> {
        use std::collections::hash_map::Entry;
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
        let body = encode(w.participant, &nodes)?;
        w.writer
            .write(Sample::cdr(true, &body))
            .map_err(|e| format!("ros_discovery_info write: {e}"))?;
        tracing::info!(domain, nodes = nodes.nodes.len(), "ROS graph published");
        w.last = nodes;
        Ok(())
    }
}

/// The `ParticipantEntitiesInfo` of a participant and its nodes, in little-endian CDR.
pub fn encode(participant: Guid, nodes: &DomainNodes) -> Result<Vec<u8>, String> {
    let infos = nodes
        .nodes
        .iter()
        .map(|(name, writers, readers)| {
            let mut n = NodeEntitiesInfo::new(name.clone());
            for g in writers {
                n.add_writer(Gid::from(*g));
            }
            for g in readers {
                n.add_reader(Gid::from(*g));
            }
            n
        })
        .collect();
    let info = ParticipantEntitiesInfo::new(Gid::from(participant), infos);
    cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&info)
        .map_err(|e| format!("ros_discovery_info encoding: {e}"))
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
        // reader_gid_seq, writer_gid_seq); a Gid is GID_LENGTH octets.
        let n = ros2_client::gid::GID_LENGTH;
        let gid = |b: u8| {
            let mut g = vec![b; 16];
            g.resize(n, 0);
            g
        };
        let nodes = DomainNodes {
            nodes: vec![(
                node_name("talker").expect("name"),
                vec![[1; 16], [2; 16]],
                vec![[3; 16]],
            )],
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
        assert_eq!(encode([9; 16], &nodes).expect("encoded"), expected);
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
