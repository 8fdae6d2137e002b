//! The ROS 2 graph: the nodes of each domain, published on `ros_discovery_info`.

use super::*;

/// A number for an XRCE participant, stable while it lives (its key hashed).
fn participant_number(key: &EntityKey) -> u64 {
    use std::hash::{Hash as _, Hasher as _};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    key.hash(&mut h);
    h.finish()
}

impl<L: WorkerLink> Worker<L> {
    /// Publishes the ROS graph in the `ros_discovery_info` layout of `distro` (24-octet GIDs
    /// for Humble, 16 for Iron and later). Called once before the worker serves
    /// ([`crate::process::WorkerProcess::run`]); the worker's configuration does not carry it
    /// so that the graph's settings stay in this module.
    pub fn set_ros_distro(&mut self, distro: crate::ros_graph::RosDistro) {
        self.graph.set_layout(distro.gid_layout(), self.now);
    }

    /// Publishes the ROS graph of every domain that changed, when its update is due.
    pub(super) fn publish_graph(&mut self) {
        let now = self.now;
        for domain in self.graph.due(now) {
            let nodes = self.domain_nodes(domain);
            if self.dds.announces_graph() {
                // The backend's own graph (rmw_zenoh's tokens), kept up to date even when
                // the last node of a domain went.
                if let Err(e) = self.dds.announce_graph(domain, &nodes) {
                    tracing::warn!(domain, error = %e, "ROS graph not fully announced");
                }
                continue;
            }
            if nodes.nodes.is_empty() && !self.graph.has_writer(domain) {
                // No node ever: no graph writer (nor DDS participant) for this domain.
                continue;
            }
            let published = self.graph.publish(domain, &mut *self.dds, nodes);
            if let Err(e) = published {
                tracing::warn!(domain, error = %e, "ROS graph not published; retrying");
                self.graph.touch(domain, now);
            }
        }
    }

    /// The ROS nodes of `domain`: participants with a node name, with the GUIDs of the
    /// writers and readers below them (requesters and repliers included).
    pub(super) fn domain_nodes(&self, domain: u16) -> DomainNodes {
        let mut nodes: std::collections::BTreeMap<
            EntityKey,
            (
                ros2_client::NodeName,
                Vec<backend::Guid>,
                Vec<backend::Guid>,
            ),
        > = Default::default();
        for (k, e) in self.entities.iter() {
            if let EntityKind::Participant {
                domain: d,
                node: Some(name),
            } = &e.kind
            {
                if *d == domain {
                    nodes.insert(*k, (name.clone(), Vec::new(), Vec::new()));
                }
            }
        }
        // A participant is announced as a ROS node once it has an endpoint on a ROS topic
        // (`rt/`, `rq/`, `rr/`, as micro-ROS names them): plain XRCE applications, whose
        // participants are named too, stay out of the ROS graph.
        let mut ros = std::collections::BTreeSet::new();
        let is_ros = |t: &str| ["rt/", "rq/", "rr/"].iter().any(|p| t.starts_with(p));
        for (k, e) in self.entities.iter() {
            let (writer, reader, ros_topic) = match &e.kind {
                EntityKind::Writer { writer: w, .. } => {
                    (Some(w.raw.guid()), None, is_ros(w.raw.topic_name()))
                }
                EntityKind::Reader {
                    reader: r, info, ..
                } => (None, Some(r.guid()), is_ros(&info.topic)),
                EntityKind::Service(s) => (
                    Some(s.writer.guid()),
                    Some(s.reader.guid()),
                    is_ros(s.writer.topic_name()),
                ),
                _ => continue,
            };
            let Some((pid, _)) = e.parent.and_then(|p| self.participant_of(*k, p)) else {
                continue;
            };
            if let Some(n) = nodes.get_mut(&(k.0, k.1, pid)) {
                n.1.extend(writer);
                n.2.extend(reader);
                if ros_topic {
                    ros.insert((k.0, k.1, pid));
                }
            }
        }
        let mut out = DomainNodes::default();
        for (k, (n, mut w, mut r)) in nodes.into_iter().filter(|(k, _)| ros.contains(k)) {
            w.sort();
            r.sort();
            out.nodes.push((n, w, r));
            out.participants.push(participant_number(&k));
        }
        out
    }
}
