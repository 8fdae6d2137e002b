//! Creation of entities from their XRCE descriptions: participants, topics, publishers and
//! subscribers, data writers and readers, types.

use super::*;

/// What a data reader's content filters need.
pub(super) struct ReaderInfo {
    /// The topic's domain.
    pub(super) domain: u16,
    /// The topic's name.
    pub(super) topic: String,
    /// The topic's type, if known.
    pub(super) ty: Option<Arc<StructDef>>,
    /// The reader's own filter (XML `<content_filter>` or the binary `contentbased_filter`).
    pub(super) filter: Option<Filter>,
    /// The fewest samples of an instance it keeps (its history's depth, as bounded).
    pub(super) depth: u32,
    /// It takes in write order: volatile, of a topic without a key (a keyed reader takes
    /// instance by instance; a durable one may get older samples late) ([`super::take_log`]).
    pub(super) in_write_order: bool,
}

/// Every endpoint's topic: as the backend makes it (with its key), its description, and
/// its type.
pub(super) type EndpointTopic = (TopicSpec, TopicDesc, Option<Arc<StructDef>>);

/// A described topic as the backend makes it.
fn topic_spec(desc: &TopicDesc, key: Option<Arc<KeyDescriptor>>) -> TopicSpec {
    TopicSpec {
        name: desc.name.clone(),
        type_name: desc.type_name.clone(),
        key,
    }
}

/// Compiles a content filter against a reader's type (which it needs).
pub(super) fn compile_filter(
    expression: &str,
    ty: Option<&Arc<StructDef>>,
    type_name: &str,
) -> Result<Filter, OpError> {
    let ty = ty.ok_or_else(|| {
        OpError::Incompatible(format!(
            "a content filter needs the type of {type_name}: define it in <types>, by a \
                 TYPE object or in the references file"
        ))
    })?;
    Filter::compile(expression, ty.clone()).map_err(|e| {
        // A bound on the work a client may cause is a refusal for resources; the rest is
        // an invalid expression.
        let why = format!("content filter {expression:?}: {e}");
        if e.is_limit() {
            OpError::Resources(why)
        } else {
            OpError::InvalidData(why)
        }
    })
}

impl<L: WorkerLink> Worker<L> {
    pub(super) fn create(
        &mut self,
        key: EntityKey,
        body: &[u8],
        replay: bool,
        little_endian: bool,
        readers: u8,
    ) -> Result<(), OpError> {
        let variant = ObjectVariant::decode(&mut CdrReader::new(body, true))
            .map_err(|e| OpError::InvalidData(format!("object representation: {e}")))?;
        if variant.kind != key.2.kind() {
            return Err(OpError::InvalidData(
                "object id kind differs from the representation kind".into(),
            ));
        }
        if self.frontends.adoption.claim(&key) && self.adopt(key, body, little_endian) {
            return Ok(());
        }
        // The front-end decides creation modes; here an existing object is replaced. A data
        // writer's samples still held for its readers to match are carried to its successor
        // (written once, in order, when it matched); what it wrote and its readers have not
        // acknowledged is still delivered by its retiring DDS writer.
        let carried = if self.entities.contains_key(&key) {
            let carried = self.take_held(key);
            self.remove_subtree(key);
            carried
        } else {
            self.room_for_entity(key)?;
            Default::default()
        };
        let mut samples = 0;
        let repr = &variant.representation;
        let dds_err = OpError::from;
        let (parent, kind) = match (variant.kind, variant.extra) {
            (object_kind::PARTICIPANT, VariantExtra::DomainId(d)) => {
                check_plain(repr, variant.kind, &self.config.references, little_endian)?;
                let domain = effective_domain(d, self.config.default_domain)
                    .map_err(OpError::InvalidData)?;
                self.admit_domain(domain, key)?;
                let node = participant_name(repr, &self.config.references, little_endian)
                    .as_deref()
                    .and_then(crate::ros_graph::node_name);
                (None, EntityKind::Participant { domain, node })
            }
            (object_kind::TOPIC, VariantExtra::Parent(p)) => {
                self.parent_entity(key, p, object_kind::PARTICIPANT)?;
                let desc = describe_topic(repr, &self.config.references, little_endian)?;
                (Some(p), EntityKind::Topic(desc))
            }
            (
                kind @ (object_kind::PUBLISHER | object_kind::SUBSCRIBER),
                VariantExtra::Parent(p),
            ) => {
                self.parent_entity(key, p, object_kind::PARTICIPANT)?;
                let partitions = check_plain(repr, kind, &self.config.references, little_endian)?;
                if !partitions.is_empty() && !self.dds.supports_partitions() {
                    // Refused rather than let the entity's data reach readers outside the
                    // partitions the client asked for.
                    return Err(OpError::Incompatible(format!(
                        "the PARTITION QoS is not supported by the {} DDS backend \
                             (--dds-backend cyclone has partitions)",
                        self.dds.name()
                    )));
                }
                let (_, domain) = self
                    .participant_of(key, p)
                    .ok_or(OpError::UnknownReference("no participant".into()))?;
                let entity = if kind == object_kind::PUBLISHER {
                    let publisher = self
                        .dds
                        .create_publisher(domain, &partitions)
                        .map_err(dds_err)?;
                    EntityKind::Publisher(Rc::new(publisher))
                } else {
                    let subscriber = self
                        .dds
                        .create_subscriber(domain, &partitions)
                        .map_err(dds_err)?;
                    EntityKind::Subscriber(Rc::new(subscriber))
                };
                (Some(p), entity)
            }
            (object_kind::DATAWRITER, VariantExtra::Parent(p)) => {
                let publisher = match &self.parent_entity(key, p, object_kind::PUBLISHER)?.kind {
                    EntityKind::Publisher(g) => g.clone(),
                    _ => {
                        return Err(OpError::UnknownReference(
                            "parent is not a publisher".into(),
                        ))
                    }
                };
                let desc = describe_endpoint(repr, true, &self.config.references, little_endian)?;
                let (topic, tdesc, ty) = self.endpoint_topic(key, p, &desc)?;
                let mut qos = EndpointQos::resolve(EndpointSide::Writer, &tdesc.qos, &desc.qos);
                samples = self.bound_endpoint(key, &mut qos, &topic)?;
                let domain = publisher.domain();
                let shared_key: Option<SharedWriterKey> =
                    (self.config.share_writers && qos.shareable()).then(|| {
                        (
                            domain,
                            tdesc.name.clone(),
                            tdesc.type_name.clone(),
                            little_endian,
                        )
                    });
                let existing = shared_key
                    .as_ref()
                    .and_then(|k| self.shared_writer(k, &qos, ty.as_ref()));
                let w = match existing {
                    Some(w) => w,
                    None => {
                        let dds_qos = if shared_key.is_some() {
                            qos.deeper(SHARE_GROUP)
                        } else {
                            qos
                        };
                        // A client writes in its native byte order, the one of its CREATE.
                        let raw = self
                            .dds
                            .create_writer(&publisher, &topic, &dds_qos, little_endian)
                            .map_err(dds_err)?;
                        let w = Rc::new(DdsWriter {
                            raw,
                            shared: shared_key.clone(),
                            matched_at: Cell::new(None),
                            matched: Cell::new(0),
                            outstanding: Outstanding::default(),
                            topic: TopicKey::of(&self.topic_keys, domain, &tdesc.name),
                        });
                        if let Some(k) = shared_key {
                            self.writers
                                .shared
                                .entry(k)
                                .or_default()
                                .push(SharedWriterEntry {
                                    qos,
                                    ty: ty.clone(),
                                    writer: Rc::downgrade(&w),
                                });
                        }
                        w
                    }
                };
                let now = self.now;
                // A writer joining a shared DDS writer that matched its readers long enough
                // ago writes at once.
                let matched = w
                    .poll_matched(now)
                    .is_some_and(|t| now >= t + REMATCH_MARGIN)
                    && w.matched.get() >= usize::from(readers);
                let rematch = Rematch {
                    until: (!matched).then(|| {
                        now + if replay {
                            REMATCH_MAX
                        } else {
                            NEW_WRITER_HOLD_MAX
                        }
                    }),
                    expected: readers,
                    ..Default::default()
                };
                (
                    Some(p),
                    EntityKind::Writer {
                        writer: w,
                        rematch,
                        ty,
                    },
                )
            }
            (object_kind::DATAREADER, VariantExtra::Parent(p)) => {
                let subscriber = match &self.parent_entity(key, p, object_kind::SUBSCRIBER)?.kind {
                    EntityKind::Subscriber(g) => g.clone(),
                    _ => {
                        return Err(OpError::UnknownReference(
                            "parent is not a subscriber".into(),
                        ))
                    }
                };
                let desc = describe_endpoint(repr, false, &self.config.references, little_endian)?;
                let (topic, tdesc, ty) = self.endpoint_topic(key, p, &desc)?;
                let filter = desc
                    .content_filter
                    .as_deref()
                    .map(|f| compile_filter(f, ty.as_ref(), &tdesc.type_name))
                    .transpose()
                    .map_err(|e| self.filter_refused(e))?;
                let mut qos = EndpointQos::resolve(EndpointSide::Reader, &tdesc.qos, &desc.qos);
                samples = self.bound_endpoint(key, &mut qos, &topic)?;
                let token = self.readers.new_token();
                let r = self
                    .dds
                    .create_reader(&subscriber, &topic, &qos, token)
                    .map_err(dds_err)?;
                self.readers.by_token.insert(token, key);
                let in_write_order = topic.key.is_none()
                    && qos.durability == crate::backend::policies::Durability::Volatile
                    && self.dds.delivers_locally_in_write_order();
                if in_write_order {
                    // New, it holds nothing: its place in the topic's take log is the end.
                    let t = TopicKey::of(&self.topic_keys, subscriber.domain(), &tdesc.name);
                    let at = self.writers.take_logs.sync(&t);
                    self.readers.positions.insert(key, at);
                }
                (
                    Some(p),
                    EntityKind::Reader {
                        reader: r,
                        token,
                        info: ReaderInfo {
                            domain: subscriber.domain(),
                            topic: tdesc.name.clone(),
                            ty,
                            filter,
                            in_write_order,
                            depth: match qos.history {
                                crate::backend::policies::History::KeepLast(d) => {
                                    u32::try_from(d).unwrap_or(0).max(1)
                                }
                                crate::backend::policies::History::KeepAll => samples.max(1),
                            },
                        },
                    },
                )
            }
            (kind @ (object_kind::REQUESTER | object_kind::REPLIER), VariantExtra::Parent(p)) => {
                self.parent_entity(key, p, object_kind::PARTICIPANT)?;
                let requester = kind == object_kind::REQUESTER;
                let desc =
                    describe_service(repr, requester, &self.config.references, little_endian)?;
                let (_, domain) = self
                    .participant_of(key, p)
                    .ok_or(OpError::UnknownReference("no participant".into()))?;
                let endpoint = self.create_service(&desc, domain, requester, little_endian)?;
                self.readers.by_token.insert(endpoint.token, key);
                tracing::info!(
                    frontend = key.0,
                    client = %key.1,
                    service = %desc.service_name,
                    request_topic = %desc.request_topic,
                    reply_topic = %desc.reply_topic,
                    requester,
                    "service endpoint created"
                );
                (Some(p), EntityKind::Service(Box::new(endpoint)))
            }
            (object_kind::TYPE, _) => {
                let set = match repr {
                    xrce_common::wire::Representation::Xml(x) => {
                        TypeSet::parse(x).map_err(|e| OpError::InvalidData(e.to_string()))?
                    }
                    xrce_common::wire::Representation::Reference(r) => {
                        let t = self.config.references.types().get(r).ok_or_else(|| {
                            OpError::UnknownReference(format!(
                                "type {r:?} is not in the references file"
                            ))
                        })?;
                        TypeSet::single(t)
                    }
                    xrce_common::wire::Representation::Binary(_) => {
                        return Err(OpError::InvalidData(
                            "a TYPE object is described by XML or by reference".into(),
                        ))
                    }
                };
                if set.is_empty() {
                    return Err(OpError::InvalidData(
                        "the TYPE representation defines no structure".into(),
                    ));
                }
                tracing::info!(main = ?set.main(), "types registered");
                (None, EntityKind::Type(Arc::new(set)))
            }
            (k, _) => {
                return Err(OpError::InvalidData(format!(
                    "object kind {k:#04x} is not supported yet"
                )))
            }
        };
        let mut kind = kind;
        if let EntityKind::Writer { rematch, .. } = &mut kind {
            if !carried.is_empty() {
                rematch.held_bytes = carried.iter().map(|h| h.sample.body.len()).sum();
                rematch.held = carried;
                rematch
                    .until
                    .get_or_insert_with(|| self.now + NEW_WRITER_HOLD_MAX);
            }
            if rematch.until.is_some() {
                self.writers.holding.insert(key);
            }
        }
        let graph_change = matches!(
            &kind,
            EntityKind::Participant { node: Some(_), .. }
                | EntityKind::Writer { .. }
                | EntityKind::Reader { .. }
                | EntityKind::Service(..)
        );
        let joins = match &kind {
            EntityKind::Participant { domain: d, .. } => Some(*d),
            _ => None,
        };
        let origin = Origin::new(body, little_endian);
        self.holdings.reserve(key.0, key.1, samples);
        self.entities.insert(
            key,
            parent,
            Entity {
                kind,
                origin,
                samples,
            },
        );
        if let Some(d) = joins {
            if self.domains.join(d) {
                let in_use = self.domains.in_use().count();
                tracing::info!(domain = d, in_use, "DDS domain in use");
            }
        }
        if graph_change {
            if let Some(d) = self.domain_of(key) {
                self.graph.touch(d, self.now);
            }
        }
        Ok(())
    }

    /// Whether the client of `key` may have one more entity ([`WorkerBounds`]); a refusal
    /// is counted and logged once per episode.
    fn room_for_entity(&mut self, key: EntityKey) -> Result<(), OpError> {
        let b = self.config.bounds;
        let over = if self.entities.count_of(&(key.0, key.1)) >= b.entities_per_client {
            Some((OverBound::EntitiesPerClient, b.entities_per_client))
        } else if self.entities.len() >= b.entities_total {
            Some((OverBound::EntitiesTotal, b.entities_total))
        } else {
            None
        };
        match over {
            None => Ok(()),
            Some((o, n)) => {
                let why = format!(
                    "entity refused: {} ({n}) reached (client {})",
                    o.reason(),
                    key.1
                );
                self.refused(o.reason(), &why);
                Err(OpError::Resources(why))
            }
        }
    }

    /// Clamps a data writer's or reader's QoS to the bounds (logged once per episode when
    /// the client asked for more) and checks that the samples it may then keep fit its
    /// client's share and the worker's total; returns them, to be reserved.
    fn bound_endpoint(
        &mut self,
        key: EntityKey,
        qos: &mut EndpointQos,
        topic: &TopicSpec,
    ) -> Result<u32, OpError> {
        let bounds = self.config.bounds;
        let asked = (qos.history, qos.resource_limits);
        let clamped = crate::bounds::clamp(qos, topic.key.is_some(), &bounds);
        if clamped.changed {
            self.count("qos_clamped");
            if self.episodes.refused("qos_clamped", self.now) {
                tracing::warn!(client = %key.1, topic = %topic.name, ?asked, history = ?qos.history, resource_limits = ?qos.resource_limits, "endpoint QoS clamped to the worker's bounds: its cache keeps at most {} samples (further clamps are counted, not logged, until the episode ends)", clamped.samples);
            }
        }
        if let Err(o) = self.holdings.check(key.0, key.1, clamped.samples, &bounds) {
            let why = format!(
                "endpoint refused: its cache of {} samples exceeds {} (client {}, {} held in all)",
                clamped.samples,
                o.reason(),
                key.1,
                self.holdings.total()
            );
            self.refused(o.reason(), &why);
            return Err(OpError::Resources(why));
        }
        Ok(clamped.samples)
    }

    /// Takes the samples a data writer holds for its readers to match (none for another
    /// kind of entity).
    fn take_held(&mut self, key: EntityKey) -> std::collections::VecDeque<HeldSample> {
        match self.entities.value_mut(&key) {
            Some(Entity {
                kind: EntityKind::Writer { rematch, .. },
                ..
            }) => {
                rematch.held_bytes = 0;
                std::mem::take(&mut rematch.held)
            }
            _ => Default::default(),
        }
    }

    /// Counts (and logs once per episode) a content filter refused for its size; passes
    /// any error on.
    pub(super) fn filter_refused(&mut self, e: OpError) -> OpError {
        if let OpError::Resources(why) = &e {
            let why = why.clone();
            self.refused("filters_refused", &why);
        }
        e
    }

    /// A type by name: from the client's TYPE objects, else the references file.
    pub(super) fn type_named(&self, key: EntityKey, name: &str) -> Option<Arc<StructDef>> {
        // The client's TYPE object with the lowest id wins when several define the name.
        self.entities
            .iter()
            .filter(|(k, _)| k.0 == key.0 && k.1 == key.1)
            .filter_map(|(k, e)| match &e.kind {
                EntityKind::Type(set) => Some((k.2 .0, set.get(name)?)),
                _ => None,
            })
            .min_by_key(|(id, _)| *id)
            .map(|(_, t)| t)
            .or_else(|| self.config.references.types().get(name))
    }

    /// A topic's type and key, when its type is known.
    pub(super) fn topic_type(
        &self,
        key: EntityKey,
        tdesc: &TopicDesc,
    ) -> (Option<Arc<StructDef>>, Option<Arc<KeyDescriptor>>) {
        let ty = self.type_named(key, &tdesc.type_name);
        let kd = ty.clone().and_then(KeyDescriptor::new).map(Arc::new);
        if tdesc.keyed && kd.is_none() {
            tracing::warn!(
                frontend = key.0,
                client = %key.1,
                topic = %tdesc.name,
                r#type = %tdesc.type_name,
                known = ty.is_some(),
                "WITH_KEY topic carried without a key: its type is unknown or has no key member \
                 (define it in <types>, by a TYPE object or in the references file)"
            );
        }
        (ty, kd)
    }

    /// The topic an endpoint names (inline, or a topic object of the same participant).
    pub(super) fn endpoint_topic(
        &self,
        key: EntityKey,
        parent: ObjectId,
        desc: &xml::EndpointDesc,
    ) -> Result<EndpointTopic, OpError> {
        let (pid, _) = self
            .participant_of(key, parent)
            .ok_or(OpError::UnknownReference("no participant".into()))?;
        // A topic object created by the client with the same name carries its QoS.
        if let Some(id) = desc.topic_id {
            let d = match self.entities.value(&(key.0, key.1, id)) {
                Some(Entity {
                    kind: EntityKind::Topic(d),
                    ..
                }) => d.clone(),
                _ => {
                    return Err(OpError::UnknownReference(format!(
                        "topic {id:?} does not exist"
                    )))
                }
            };
            let (ty, kd) = self.topic_type(key, &d);
            return Ok((topic_spec(&d, kd), d, ty));
        }
        let wanted = desc
            .topic
            .as_ref()
            .map(|t| t.name.as_str())
            .or(desc.topic_ref.as_deref())
            .unwrap_or_default();
        let existing = self.entities.iter().find_map(|(k, e)| match &e.kind {
            EntityKind::Topic(d)
                if k.0 == key.0 && k.1 == key.1 && e.parent == Some(pid) && d.name == wanted =>
            {
                Some(d.clone())
            }
            _ => None,
        });
        let tdesc = match (&desc.topic, existing) {
            (Some(inline), Some(d)) if inline.type_name != d.type_name => {
                return Err(OpError::Mismatch(format!(
                    "topic {wanted} exists with type {}",
                    d.type_name
                )))
            }
            (Some(inline), Some(found)) => found.refined_by(inline),
            (None, Some(found)) => found,
            (Some(inline), None) => inline.clone(),
            (None, None) => {
                return Err(OpError::UnknownReference(format!(
                    "topic {wanted} is unknown"
                )))
            }
        };
        let (ty, kd) = self.topic_type(key, &tdesc);
        Ok((topic_spec(&tdesc, kd), tdesc, ty))
    }
}
