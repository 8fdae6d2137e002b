//! The ROS graph as rmw_zenoh announces it: a liveliness token per node and per endpoint,
//! declared while it exists and undeclared when it goes (Zenoh tells every other session,
//! so `ros2 node list` on rmw_zenoh sees the XRCE client's nodes come and go).

use std::collections::{BTreeMap, BTreeSet, HashMap};

use zenoh::Wait as _;

use super::naming::{liveliness_token, EndpointToken, EntityKind, NodeToken};
use xrce_dds_seam::ros_nodes::DomainNodes;
use xrce_dds_seam::{BackendError, Guid};

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

/// A node as the worker lists it: its domain and its XRCE participant's number (two
/// participants may carry one name; each keeps its id while it lives).
type NodeKey = (u16, u64);

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
        let mut live = BTreeSet::new();
        for (i, (node, writers, readers)) in nodes.nodes.iter().enumerate() {
            let (ns, name) = (node.namespace().to_string(), node.base_name().to_string());
            // Without participants' numbers (not from the worker), the node's place.
            let participant = nodes.participants.get(i).copied().unwrap_or(i as u64);
            let key = (domain, participant);
            let id = *self.node_ids.entry(key).or_insert_with(|| {
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

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_dds_seam::ros_nodes::node_name;

    fn nodes(list: &[(&str, u64, Vec<Guid>)]) -> DomainNodes {
        DomainNodes {
            nodes: list
                .iter()
                .map(|(n, _, w)| (node_name(n).expect("name"), w.clone(), vec![]))
                .collect(),
            participants: list.iter().map(|(_, p, _)| *p).collect(),
        }
    }

    #[test]
    fn a_node_keeps_its_id_and_tokens_while_others_of_its_name_come_and_go() {
        let mut t = Tokens::default();
        let mut next = 100;
        let publisher = Endpoint {
            kind: EntityKind::Publisher,
            id: 7,
            name: "/chatter".into(),
            type_name: "std_msgs::msg::dds_::String_".into(),
            hash: "H".into(),
            qos: "::,:,:,:,,".into(),
        };
        let endpoints: HashMap<Guid, Endpoint> = [([1; 16], publisher)].into_iter().collect();
        let both = t.wanted(
            3,
            "z",
            &nodes(&[
                ("/robot/talker", 11, vec![]),
                ("/robot/talker", 22, vec![[1; 16]]),
            ]),
            &endpoints,
            &mut next,
        );
        assert_eq!(both.len(), 3, "{both:#?}");
        assert!(both.contains("@ros2_lv/3/z/101/7/MP/%/%robot/talker/%chatter/std_msgs::msg::dds_::String_/H/::,:,:,:,,"));
        // The first participant goes: the second keeps node id 101 and its tokens.
        let one = t.wanted(
            3,
            "z",
            &nodes(&[("/robot/talker", 22, vec![[1; 16]])]),
            &endpoints,
            &mut next,
        );
        assert!(one.is_subset(&both), "{one:#?}");
        assert_eq!(one.len(), 2);
        // It comes back as a new participant: a new id, never 100 again.
        let again = t.wanted(
            3,
            "z",
            &nodes(&[
                ("/robot/talker", 33, vec![]),
                ("/robot/talker", 22, vec![[1; 16]]),
            ]),
            &endpoints,
            &mut next,
        );
        assert!(
            again.contains("@ros2_lv/3/z/102/102/NN/%/%robot/talker"),
            "{again:#?}"
        );
        assert!(!again.iter().any(|k| k.contains("/100/")));
        // An endpoint the backend does not know (another backend's, or gone) has no token.
        let unknown = t.wanted(
            3,
            "z",
            &nodes(&[("/robot/talker", 22, vec![[9; 16]])]),
            &endpoints,
            &mut next,
        );
        assert_eq!(unknown.len(), 1);
    }
}
