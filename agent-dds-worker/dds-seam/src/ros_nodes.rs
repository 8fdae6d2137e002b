//! The ROS 2 nodes a domain's graph lists, as plain data: built by the worker's graph
//! (the worker's `ros_graph`) and handed to a backend that announces nodes itself
//! ([`crate::DdsBackend::announce_graph`]). A leaf below both.

use ros2_client::NodeName;

/// A DDS GUID as the graph lists it (the same octets as [`crate::Guid`]).
pub type Guid = [u8; 16];

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
    /// Which XRCE participant each node is (same order; a number stable while it lives), so
    /// that a backend announcing nodes itself keeps a node's identity when another node of
    /// the same name comes or goes. Empty where nobody needs it.
    pub participants: Vec<u64>,
}
