//! What the worker holds for an entity (its DDS endpoints), how the tree of them is walked
//! up to a participant, and what goes with an entity when its subtree or its client is
//! removed (the tree itself is [`crate::tree`]).

use super::*;

pub(super) enum EntityKind {
    /// A logical XRCE participant in a DDS domain, and the ROS node its name stands for.
    Participant {
        domain: u16,
        node: Option<ros2_client::NodeName>,
    },
    /// A topic description; DDS topics are made by the backend when endpoints are.
    Topic(TopicDesc),
    /// A DDS publisher.
    Publisher(Rc<backend::Publisher>),
    /// A DDS subscriber.
    Subscriber(Rc<backend::Subscriber>),
    /// A type definition (`<types>`) the client's topics can use.
    Type(Arc<TypeSet>),
    /// A data writer.
    Writer {
        /// Its DDS writer, possibly shared with other data writers of the domain.
        writer: Rc<DdsWriter>,
        /// Whether it holds samples until its readers match again (after a replay).
        rematch: Rematch,
        /// Its topic's type, if known (where samples end, for sequence formats).
        ty: Option<Arc<StructDef>>,
    },
    /// A data reader.
    Reader {
        /// Its DDS reader.
        reader: Box<dyn DdsReader>,
        /// The token its wake-ups name.
        token: ReaderToken,
        /// What its content filters need.
        info: ReaderInfo,
    },
    /// A requester (publishes requests, reads the replies to them) or a replier (reads
    /// requests, publishes replies).
    Service(Box<ServiceEndpoint>),
}

/// What the worker holds for an entity (its parent is kept by the tree).
pub(super) struct Entity {
    pub(super) kind: EntityKind,
    /// What it was created from (a restarted front-end's replay of the same adopts it).
    pub(super) origin: Origin,
    /// Samples reserved for its cache ([`crate::bounds`]; 0 for entities without one).
    pub(super) samples: u32,
}

impl<L: WorkerLink> Worker<L> {
    /// The domain an entity lives in, if it is part of a participant.
    pub(super) fn domain_of(&self, key: EntityKey) -> Option<u16> {
        match &self.entities.get(&key)?.kind {
            EntityKind::Participant { domain: d, .. } => Some(*d),
            _ => self
                .participant_of(key, self.entities.get(&key)?.parent?)
                .map(|(_, d)| d),
        }
    }

    pub(super) fn parent_entity(
        &self,
        key: EntityKey,
        parent: ObjectId,
        kind: u8,
    ) -> Result<&Entity, OpError> {
        let e = self
            .entities
            .get(&(key.0, key.1, parent))
            .ok_or(OpError::UnknownReference(format!(
                "parent {parent:?} does not exist"
            )))?;
        if parent.kind() != kind {
            return Err(OpError::UnknownReference(format!(
                "parent {parent:?} is not of kind {kind}"
            )));
        }
        Ok(e)
    }

    /// The participant entity an object hangs under, and its domain.
    pub(super) fn participant_of(&self, key: EntityKey, id: ObjectId) -> Option<(ObjectId, u16)> {
        let (id, e) = self.entities.ancestor((key.0, key.1), id, |e| {
            matches!(e.kind, EntityKind::Participant { .. })
        })?;
        match e.kind {
            EntityKind::Participant { domain, .. } => Some((id, domain)),
            _ => None,
        }
    }

    /// Removes the entities of the clients `pred` selects (by front-end and client key).
    pub(super) fn remove_where(&mut self, pred: impl Fn(&(u32, ClientKey)) -> bool) {
        for k in self.entities.keys_of(pred) {
            // Already gone with its parent's subtree, or still there.
            if self.entities.contains_key(&k) {
                self.remove_subtree(k);
            }
        }
    }

    /// Removes an entity and its descendants, endpoints before their parents.
    pub(super) fn remove_subtree(&mut self, key: EntityKey) {
        // Every entity of a subtree lives in the domain of its root.
        if let Some(d) = self.domain_of(key) {
            self.graph.touch(d, self.now);
        }
        for (key, e) in self.entities.remove_subtree(key) {
            self.forget_entity(key, e);
        }
    }

    /// What the worker keeps about an entity besides the tree, dropped with it.
    fn forget_entity(&mut self, key: EntityKey, e: Entity) {
        self.holdings.release(key.0, key.1, e.samples);
        if let Some(r) = self.frontends.recent.get_mut(&key.0) {
            r.forget(&key);
        }
        let token = match &e.kind {
            EntityKind::Reader { token, .. } => Some(*token),
            EntityKind::Service(s) => Some(s.token),
            _ => None,
        };
        self.readers.forget(key, token);
        self.writers.holding.remove(&key);
        match e.kind {
            // Its subtree went before it (endpoints before their parents): the last
            // participant of a domain leaves nothing of the worker's in it.
            EntityKind::Participant { domain, .. } if self.domains.leave(domain) => {
                self.release_domain(domain);
            }
            EntityKind::Writer {
                writer,
                mut rematch,
                ..
            } => {
                // Samples it still held for its readers to match go out now (a replaced
                // writer's were carried to its successor before): the client was told they
                // were written.
                let now = self.now;
                let held = std::mem::take(&mut rematch.held);
                if !held.is_empty() {
                    self.publish_held(key, &writer, held, now);
                }
                self.writers.retire(writer, now)
            }
            // Dropped here, the backend's endpoints are deleted and wake nobody any more.
            _ => {}
        }
    }
}
