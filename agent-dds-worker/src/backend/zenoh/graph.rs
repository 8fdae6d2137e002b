//! The ROS graph as rmw_zenoh announces it: a liveliness token per node and per endpoint,
//! declared while it exists and undeclared when it goes (Zenoh tells every other session,
//! so `ros2 node list` on rmw_zenoh sees the XRCE client's nodes come and go).

use std::collections::{BTreeMap, BTreeSet, HashMap};

use zenoh::Wait as _;

use super::naming::{liveliness_token, EndpointToken, EntityKind, NodeToken};
use crate::backend::{BackendError, Guid};
use crate::ros_graph::DomainNodes;

/// What an endpoint's token says besides its node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Endpoint {
    pub(super) kind: EntityKind,
    pub(super) id: u64,
    pub(super) name: String,
    pub(super) type_name: String,
    pub(super) hash: String,
    pub(super) qos: String,
}

/// A node as the worker lists it: namespace, name, and which of the domain's nodes of that
/// name it is (two XRCE participants may carry one name).
type NodeKey = (u16, String, String, usize);

/// The tokens declared, by domain, and the ids given to nodes.
#[derive(Default)]
pub(super) struct Tokens {
    declared: HashMap<u16, BTreeMap<String, zenoh::liveliness::LivelinessToken>>,
    node_ids: HashMap<NodeKey, u64>,
}

impl Tokens {
    /// The token keys `nodes` of `domain` should have now; nodes without an id get one from
    /// `next_id` (the counter endpoints take theirs from, as rmw_zenoh's context does).
    pub(super) fn wanted(
        &mut self,
        domain: u16,
        zid: &str,
        nodes: &DomainNodes,
        endpoints: &HashMap<Guid, Endpoint>,
        next_id: &mut u64,
    ) -> BTreeSet<String> {
        let mut wanted = BTreeSet::new();
        let mut seen: HashMap<(String, String), usize> = HashMap::new();
        let mut live = BTreeSet::new();
        for (node, writers, readers) in &nodes.nodes {
            let (ns, name) = (node.namespace().to_string(), node.base_name().to_string());
            let nth = seen.entry((ns.clone(), name.clone())).or_default();
            let key = (domain, ns.clone(), name.clone(), *nth);
            *nth += 1;
            let id = *self.node_ids.entry(key.clone()).or_insert_with(|| {
                let id = *next_id;
                *next_id += 1;
                id
            });
            live.insert(key);
            let token = NodeToken {
                zid: zid.to_string(),
                id,
                enclave: "/".to_string(),
                namespace: ns,
                name,
            };
            wanted.insert(liveliness_token(domain, &token, None));
            for guid in writers.iter().chain(readers) {
                if let Some(e) = endpoints.get(guid) {
                    let endpoint = EndpointToken {
                        kind: e.kind,
                        id: e.id,
                        name: e.name.clone(),
                        type_name: e.type_name.clone(),
                        hash: e.hash.clone(),
                        qos: e.qos.clone(),
                    };
                    wanted.insert(liveliness_token(domain, &token, Some(&endpoint)));
                }
            }
        }
        self.node_ids
            .retain(|k, _| k.0 != domain || live.contains(k));
        wanted
    }

    /// Declares the tokens of `wanted` not declared yet and undeclares the others of
    /// `domain`. A token Zenoh refuses is reported (the rest are still declared).
    pub(super) fn apply(
        &mut self,
        domain: u16,
        wanted: BTreeSet<String>,
        session: &zenoh::Session,
    ) -> Result<(), BackendError> {
        let declared = self.declared.entry(domain).or_default();
        let before = declared.len();
        declared.retain(|k, _| wanted.contains(k));
        let undeclared = before - declared.len();
        let mut failed = Vec::new();
        let mut added = 0;
        for key in wanted {
            if declared.contains_key(&key) {
                continue;
            }
            match session.liveliness().declare_token(key.clone()).wait() {
                Ok(token) => {
                    declared.insert(key, token);
                    added += 1;
                }
                Err(e) => failed.push(format!("{key}: {e}")),
            }
        }
        if added > 0 || undeclared > 0 {
            tracing::info!(
                domain,
                declared = added,
                undeclared,
                tokens = declared.len(),
                "ROS graph announced (rmw_zenoh liveliness tokens)"
            );
        }
        if failed.is_empty() {
            Ok(())
        } else {
            Err(BackendError::InvalidInput(format!(
                "liveliness tokens refused: {}",
                failed.join("; ")
            )))
        }
    }

    /// Undeclares every token of `domain` (its last participant went).
    pub(super) fn forget(&mut self, domain: u16) {
        self.declared.remove(&domain);
        self.node_ids.retain(|k, _| k.0 != domain);
    }
}
