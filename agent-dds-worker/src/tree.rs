//! The entity tree: every entity of every client by (front-end, client key, object id), with
//! its parent, and an index of each client's objects so that finding a client's entities or
//! an entity's children never scans every client's.
//!
//! Generic over what an entity holds, so it knows nothing of DDS: the worker keeps its DDS
//! endpoints in it, the tests plain values.

use std::collections::{HashMap, HashSet};

use xrce_common::wire::{ClientKey, ObjectId};

use crate::adoption::EntityKey;

/// How far a walk up from an entity goes (participant, publisher, writer: 3 levels; the
/// bound stops a walk up a chain that loops).
const MAX_DEPTH: usize = 8;

/// One entity and its parent (an object id of the same client).
#[derive(Debug)]
pub struct Node<T> {
    /// The parent's object id, for entities that have one.
    pub parent: Option<ObjectId>,
    /// What the entity holds.
    pub value: T,
}

impl<T> std::ops::Deref for Node<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.value
    }
}

impl<T> std::ops::DerefMut for Node<T> {
    fn deref_mut(&mut self) -> &mut T {
        &mut self.value
    }
}

/// Every entity, and each client's object ids.
#[derive(Debug)]
pub struct EntityTree<T> {
    nodes: HashMap<EntityKey, Node<T>>,
    by_client: HashMap<(u32, ClientKey), HashSet<ObjectId>>,
}

impl<T> Default for EntityTree<T> {
    fn default() -> Self {
        EntityTree {
            nodes: HashMap::new(),
            by_client: HashMap::new(),
        }
    }
}

impl<T> EntityTree<T> {
    /// Adds entity `key` under `parent`; an entity of that key is replaced (its value is
    /// returned; its children stay: remove its subtree first to replace them too).
    pub fn insert(&mut self, key: EntityKey, parent: Option<ObjectId>, value: T) -> Option<T> {
        self.by_client
            .entry((key.0, key.1))
            .or_default()
            .insert(key.2);
        self.nodes
            .insert(key, Node { parent, value })
            .map(|n| n.value)
    }

    /// The entity `key`.
    pub fn get(&self, key: &EntityKey) -> Option<&Node<T>> {
        self.nodes.get(key)
    }

    /// The entity `key`, to change what it holds.
    pub fn get_mut(&mut self, key: &EntityKey) -> Option<&mut Node<T>> {
        self.nodes.get_mut(key)
    }

    /// What entity `key` holds.
    pub fn value(&self, key: &EntityKey) -> Option<&T> {
        self.nodes.get(key).map(|n| &n.value)
    }

    /// What entity `key` holds, to change it.
    pub fn value_mut(&mut self, key: &EntityKey) -> Option<&mut T> {
        self.nodes.get_mut(key).map(|n| &mut n.value)
    }

    /// Whether entity `key` exists.
    pub fn contains_key(&self, key: &EntityKey) -> bool {
        self.nodes.contains_key(key)
    }

    /// How many entities one client has.
    pub fn count_of(&self, client: &(u32, ClientKey)) -> usize {
        self.by_client.get(client).map_or(0, HashSet::len)
    }

    /// How many entities there are.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Every entity, in no order.
    pub fn iter(&self) -> impl Iterator<Item = (&EntityKey, &Node<T>)> {
        self.nodes.iter()
    }

    /// Every entity, to change what they hold.
    pub fn iter_mut(&mut self) -> impl Iterator<Item = (&EntityKey, &mut Node<T>)> {
        self.nodes.iter_mut()
    }

    /// Every entity (its parent and what it holds).
    pub fn values(&self) -> impl Iterator<Item = &Node<T>> {
        self.nodes.values()
    }

    /// The clients (front-end, client key) with at least one entity.
    pub fn clients(&self) -> impl Iterator<Item = &(u32, ClientKey)> {
        self.by_client.keys()
    }

    /// The entities of the clients `pred` selects.
    pub fn keys_of(&self, pred: impl Fn(&(u32, ClientKey)) -> bool) -> Vec<EntityKey> {
        self.by_client
            .iter()
            .filter(|(c, _)| pred(c))
            .flat_map(|(c, ids)| ids.iter().map(move |id| (c.0, c.1, *id)))
            .collect()
    }

    /// The nearest entity at or above object `id` of `client` (front-end, client key) whose
    /// value `is` says yes to (the participant an endpoint hangs under), with its object id.
    pub fn ancestor(
        &self,
        client: (u32, ClientKey),
        mut id: ObjectId,
        is: impl Fn(&T) -> bool,
    ) -> Option<(ObjectId, &T)> {
        for _ in 0..MAX_DEPTH {
            let n = self.nodes.get(&(client.0, client.1, id))?;
            if is(&n.value) {
                return Some((id, &n.value));
            }
            id = n.parent?;
        }
        None
    }

    /// Removes entity `key` and its descendants, however deep; returns them, each after its
    /// own descendants (endpoints before their parents). Nothing if `key` does not exist.
    pub fn remove_subtree(&mut self, key: EntityKey) -> Vec<(EntityKey, T)> {
        if !self.nodes.contains_key(&key) {
            return Vec::new();
        }
        // Depth first, each entity once (a parent chain that loops ends the descent).
        let mut order = Vec::new();
        let mut seen = HashSet::from([key]);
        let mut stack = vec![(key, false)];
        while let Some((k, expanded)) = stack.pop() {
            if expanded {
                order.push(k);
                continue;
            }
            stack.push((k, true));
            let ids = self.by_client.get(&(k.0, k.1)).into_iter().flatten();
            for id in ids {
                let c = (k.0, k.1, *id);
                let child = self.nodes.get(&c).is_some_and(|n| n.parent == Some(k.2));
                if child && seen.insert(c) {
                    stack.push((c, false));
                }
            }
        }
        let mut out = Vec::with_capacity(order.len());
        for k in order {
            if let Some(ids) = self.by_client.get_mut(&(k.0, k.1)) {
                ids.remove(&k.2);
                if ids.is_empty() {
                    self.by_client.remove(&(k.0, k.1));
                }
            }
            if let Some(n) = self.nodes.remove(&k) {
                out.push((k, n.value));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: ClientKey = ClientKey([0xAA, 0, 0, 1]);
    const B: ClientKey = ClientKey([0xBB, 0, 0, 2]);

    fn id(n: u16, kind: u8) -> ObjectId {
        ObjectId::new(n, kind)
    }

    /// A client's participant 1 with a publisher and a writer, and a subscriber and a
    /// reader; the values name the entities.
    fn client(t: &mut EntityTree<&'static str>, fe: u32, c: ClientKey) {
        t.insert((fe, c, id(1, 1)), None, "participant");
        t.insert((fe, c, id(1, 3)), Some(id(1, 1)), "publisher");
        t.insert((fe, c, id(1, 5)), Some(id(1, 3)), "writer");
        t.insert((fe, c, id(1, 4)), Some(id(1, 1)), "subscriber");
        t.insert((fe, c, id(1, 6)), Some(id(1, 4)), "reader");
    }

    #[test]
    fn a_subtree_goes_children_first_and_leaves_the_rest() {
        let mut t = EntityTree::default();
        client(&mut t, 0, A);
        client(&mut t, 0, B);
        let gone = t.remove_subtree((0, A, id(1, 3)));
        let names: Vec<&str> = gone.iter().map(|(_, v)| *v).collect();
        assert_eq!(names, ["writer", "publisher"]);
        assert_eq!(t.len(), 8);
        assert!(t.contains_key(&(0, A, id(1, 6))));
        assert!(
            t.remove_subtree((0, A, id(1, 3))).is_empty(),
            "gone already"
        );
        // The participant takes what is left of its client with it, parents last.
        let gone = t.remove_subtree((0, A, id(1, 1)));
        let names: Vec<&str> = gone.iter().map(|(_, v)| *v).collect();
        assert_eq!(names, ["reader", "subscriber", "participant"]);
        assert_eq!(t.clients().count(), 1, "client A has no entity left");
        assert_eq!(t.keys_of(|c| c.1 == A), vec![]);
    }

    fn remove_clients(
        t: &mut EntityTree<&'static str>,
        pred: impl Fn(&(u32, ClientKey)) -> bool,
    ) -> Vec<(EntityKey, &'static str)> {
        let mut gone = Vec::new();
        for k in t.keys_of(pred) {
            gone.extend(t.remove_subtree(k));
        }
        gone
    }

    #[test]
    fn clients_are_removed_by_front_end_or_key() {
        let mut t = EntityTree::default();
        client(&mut t, 0, A);
        client(&mut t, 1, A);
        client(&mut t, 1, B);
        let gone = remove_clients(&mut t, |c| c.0 == 1);
        assert_eq!(gone.len(), 10);
        // Every entity after its descendants: a client's participant last of its five.
        for c in [A, B] {
            let order: Vec<&str> = gone
                .iter()
                .filter(|(k, _)| k.1 == c)
                .map(|(_, v)| *v)
                .collect();
            assert_eq!(order.len(), 5);
            assert_eq!(order.last(), Some(&"participant"), "{order:?}");
            let pos = |n: &str| order.iter().position(|v| *v == n);
            assert!(pos("writer") < pos("publisher") && pos("reader") < pos("subscriber"));
        }
        assert_eq!(t.len(), 5);
        assert_eq!(t.clients().collect::<Vec<_>>(), vec![&(0, A)]);
        assert_eq!(remove_clients(&mut t, |c| *c == (0, A)).len(), 5);
        assert!(t.is_empty());
    }

    #[test]
    fn the_participant_above_an_endpoint_is_found() {
        let mut t = EntityTree::default();
        client(&mut t, 0, A);
        let found = t.ancestor((0, A), id(1, 5), |v| *v == "participant");
        assert_eq!(found, Some((id(1, 1), &"participant")));
        assert_eq!(t.ancestor((0, A), id(9, 5), |v| *v == "participant"), None);
        // A chain that loops is walked a bounded number of steps.
        t.insert((0, B, id(1, 3)), Some(id(2, 3)), "publisher");
        t.insert((0, B, id(2, 3)), Some(id(1, 3)), "publisher");
        assert_eq!(t.ancestor((0, B), id(1, 3), |v| *v == "participant"), None);
        assert_eq!(t.remove_subtree((0, B, id(1, 3))).len(), 2);
    }

    #[test]
    fn a_deep_chain_goes_whole() {
        let mut t = EntityTree::default();
        t.insert((0, A, id(0, 1)), None, "root");
        for n in 1..20 {
            t.insert(
                (0, A, id(n, 3)),
                Some(id(n - 1, if n == 1 { 1 } else { 3 })),
                "link",
            );
        }
        let gone = t.remove_subtree((0, A, id(0, 1)));
        assert_eq!(gone.len(), 20);
        assert_eq!(
            gone.first().map(|g| g.0 .2),
            Some(id(19, 3)),
            "the deepest first"
        );
        assert!(t.is_empty());
        assert_eq!(t.clients().count(), 0);
    }

    #[test]
    fn an_entity_replaced_keeps_the_index_whole() {
        let mut t = EntityTree::default();
        client(&mut t, 0, A);
        assert_eq!(
            t.insert((0, A, id(1, 5)), Some(id(1, 3)), "writer 2"),
            Some("writer")
        );
        assert_eq!(t.len(), 5);
        assert_eq!(t.get(&(0, A, id(1, 5))).map(|n| n.value), Some("writer 2"));
        // A parent replaced keeps its children; one moved under another parent is found
        // there.
        t.insert((0, A, id(1, 3)), Some(id(1, 1)), "publisher 2");
        assert!(t.contains_key(&(0, A, id(1, 5))));
        t.insert((0, A, id(2, 1)), None, "participant 2");
        t.insert((0, A, id(1, 4)), Some(id(2, 1)), "subscriber");
        assert_eq!(
            t.ancestor((0, A), id(1, 6), |v| v.starts_with("participant")),
            Some((id(2, 1), &"participant 2"))
        );
        let gone = t.remove_subtree((0, A, id(1, 1)));
        let names: Vec<&str> = gone.iter().map(|(_, v)| *v).collect();
        assert_eq!(names, ["writer 2", "publisher 2", "participant"]);
        assert_eq!(remove_clients(&mut t, |_| true).len(), 3);
        assert_eq!(t.clients().count(), 0);
    }
}
