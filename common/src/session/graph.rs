//! A client's object graph: the objects it created, in creation order, and its active reads.
//!
//! The front-end keeps one per client so that it can replay them to a new DDS worker, and it
//! decides the creation-mode outcome (§7.8.3.1, Table 5) for objects that already exist.

use std::collections::HashMap;

use crate::wire::cdr::{CdrReader, CdrWriter};
use crate::wire::equivalence::same_meaning;
use crate::wire::{status, DecodeError, ObjectId, ObjectVariant, ReadSpecification, RequestId};

/// What to do with a CREATE, given what exists.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CreateDecision {
    /// Nothing with this id exists: create it.
    Create,
    /// Delete the existing object (and what hangs off it), then create.
    Replace,
    /// Do nothing and answer with this status.
    Reply(u8),
}

/// An object the client created.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GraphObject {
    /// Its id.
    pub object_id: ObjectId,
    /// The request that created it (echoed again on replay).
    pub request_id: RequestId,
    /// How it was described.
    pub variant: ObjectVariant,
    /// The byte order of the CREATE (a client's native one).
    pub little_endian: bool,
    /// A data writer: how many DDS readers it matched, as the worker last reported
    /// (saturating at 255; not stored for a successor front-end): its replay on a new worker
    /// holds its samples until as many match again.
    pub readers_matched: u8,
}

/// An active READ_DATA.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ActiveRead {
    /// The READ_DATA request id, echoed by every DATA.
    pub request_id: RequestId,
    /// The read specification.
    pub spec: ReadSpecification,
    /// Samples delivered so far (numbers the SampleInfos of the formats that carry one).
    pub delivered: u32,
    /// The last sample delivered from each DDS writer.
    pub marks: DeliveredMarks,
}

/// Writers whose last delivered sample a read remembers; the oldest is forgotten beyond
/// (a topic with more writers than this can see repeats after a restart; measured with 100).
pub const MAX_MARKED_WRITERS: usize = 256;

/// The last sample delivered to a read from each DDS writer (its GUID and sequence number),
/// so that the read replayed on a new worker does not hand the client a sample it had
/// (a writer that outlived the worker offers its history again to the new DDS reader).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DeliveredMarks {
    marks: std::collections::VecDeque<([u8; 16], i64)>,
}

impl DeliveredMarks {
    /// Whether `writer`'s sample `sequence_number` is at or below the last one delivered.
    pub fn already_delivered(&self, writer: &[u8; 16], sequence_number: i64) -> bool {
        self.marks
            .iter()
            .any(|(w, s)| w == writer && sequence_number <= *s)
    }

    /// Records a delivery.
    pub fn record(&mut self, writer: [u8; 16], sequence_number: i64) {
        if let Some(i) = self.marks.iter().position(|(w, _)| *w == writer) {
            // The most recently heard writer goes last: the one evicted is the least recent.
            if let Some((w, s)) = self.marks.remove(i) {
                self.marks.push_back((w, s.max(sequence_number)));
            }
            return;
        }
        if self.marks.len() >= MAX_MARKED_WRITERS {
            self.marks.pop_front();
        }
        self.marks.push_back((writer, sequence_number));
    }

    /// Writers remembered.
    pub fn len(&self) -> usize {
        self.marks.len()
    }

    /// Whether no writer is remembered.
    pub fn is_empty(&self) -> bool {
        self.marks.is_empty()
    }
}

/// Most objects one client may create by default; more get STATUS_ERR_RESOURCES (every
/// object is a DDS entity in the worker). The operator sets another bound with
/// `--max-objects-per-client`.
pub const MAX_OBJECTS: usize = 1024;

/// Objects and reads of one client.
#[derive(Debug, Clone, Default)]
pub struct ObjectGraph {
    objects: Vec<GraphObject>,
    reads: HashMap<ObjectId, ActiveRead>,
}

impl ObjectGraph {
    /// Number of objects.
    pub fn len(&self) -> usize {
        self.objects.len()
    }

    /// Whether there are no objects.
    pub fn is_empty(&self) -> bool {
        self.objects.is_empty()
    }

    /// The object with this id.
    pub fn get(&self, id: ObjectId) -> Option<&GraphObject> {
        self.objects.iter().find(|o| o.object_id == id)
    }

    /// The object with this id, to change.
    pub fn get_mut(&mut self, id: ObjectId) -> Option<&mut GraphObject> {
        self.objects.iter_mut().find(|o| o.object_id == id)
    }

    /// Objects in creation order.
    pub fn objects(&self) -> impl Iterator<Item = &GraphObject> {
        self.objects.iter()
    }

    /// Active reads.
    pub fn reads(&self) -> impl Iterator<Item = (&ObjectId, &ActiveRead)> {
        self.reads.iter()
    }

    /// Decides a CREATE (sent in the byte order `little_endian`) per the creation-mode table;
    /// a new object beyond `max_objects` is refused with STATUS_ERR_RESOURCES (replacing one
    /// is not). REUSE compares descriptions by meaning ([`same_meaning`]), not bytes.
    pub fn decide_create(
        &self,
        id: ObjectId,
        variant: &ObjectVariant,
        little_endian: bool,
        reuse: bool,
        replace: bool,
        max_objects: usize,
    ) -> CreateDecision {
        let Some(existing) = self.get(id) else {
            if self.objects.len() >= max_objects {
                return CreateDecision::Reply(status::ERR_RESOURCES);
            }
            return CreateDecision::Create;
        };
        let matches = same_meaning(
            &existing.variant,
            existing.little_endian,
            variant,
            little_endian,
        );
        match (reuse, replace) {
            (false, false) => CreateDecision::Reply(status::ERR_ALREADY_EXISTS),
            (false, true) => CreateDecision::Replace,
            (true, _) if matches => CreateDecision::Reply(status::OK_MATCHED),
            (true, false) => CreateDecision::Reply(status::ERR_MISMATCH),
            (true, true) => CreateDecision::Replace,
        }
    }

    /// Records a created object (after any replaced one was removed).
    pub fn insert(&mut self, object: GraphObject) {
        self.objects.retain(|o| o.object_id != object.object_id);
        self.objects.push(object);
    }

    /// Removes an object and everything created under it; returns the removed ids,
    /// children first.
    pub fn remove(&mut self, id: ObjectId) -> Vec<ObjectId> {
        let mut doomed = vec![id];
        let mut i = 0;
        while i < doomed.len() {
            let parent = doomed[i];
            for o in &self.objects {
                if o.variant.parent() == Some(parent) && !doomed.contains(&o.object_id) {
                    doomed.push(o.object_id);
                }
            }
            i += 1;
        }
        // Creation order puts parents before children; reversed, children come first.
        let mut removed: Vec<ObjectId> = self
            .objects
            .iter()
            .map(|o| o.object_id)
            .filter(|o| doomed.contains(o))
            .collect();
        removed.reverse();
        self.objects.retain(|o| !doomed.contains(&o.object_id));
        for d in &doomed {
            self.reads.remove(d);
        }
        removed
    }

    /// Records (or replaces) the active read of a reader; `max_samples == 0` cancels it.
    pub fn set_read(&mut self, reader: ObjectId, read: ActiveRead) {
        if read
            .spec
            .delivery_control
            .is_some_and(|d| d.max_samples == 0)
        {
            self.reads.remove(&reader);
        } else {
            self.reads.insert(reader, read);
        }
    }

    /// The active read of a reader.
    pub fn read_mut(&mut self, reader: ObjectId) -> Option<&mut ActiveRead> {
        self.reads.get_mut(&reader)
    }

    /// Forgets a finished read.
    pub fn end_read(&mut self, reader: ObjectId) {
        self.reads.remove(&reader);
    }
}

/// Reads little-endian fields off a byte slice (the graph's stored form).
struct Fields<'a>(&'a [u8]);

impl<'a> Fields<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        if self.0.len() < n {
            return Err(DecodeError::Truncated);
        }
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Ok(head)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        self.take(N)?.try_into().map_err(|_| DecodeError::Truncated)
    }

    fn u32(&mut self) -> Result<u32, DecodeError> {
        Ok(u32::from_le_bytes(self.array()?))
    }
}

/// Most objects or reads a stored graph may hold (far above any quota).
const MAX_STORED: u32 = 1 << 16;

impl ObjectGraph {
    /// The objects in their stored form (for a successor front-end): creation order, each
    /// with its ids, byte order and XRCE-encoded variant.
    pub fn encode_objects(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(&(self.objects.len() as u32).to_le_bytes());
        for o in &self.objects {
            let mut variant = Vec::new();
            o.variant.encode(&mut CdrWriter::new(&mut variant, true));
            out.extend_from_slice(&o.object_id.0);
            out.extend_from_slice(&o.request_id.0);
            out.push(u8::from(o.little_endian));
            out.extend_from_slice(&(variant.len() as u32).to_le_bytes());
            out.extend_from_slice(&variant);
        }
        out
    }

    /// The active reads in their stored form: ids, delivered count, XRCE-encoded read
    /// specification and the delivered marks.
    pub fn encode_reads(&self) -> Vec<u8> {
        let mut reads: Vec<(&ObjectId, &ActiveRead)> = self.reads.iter().collect();
        reads.sort_by_key(|(id, _)| id.0);
        let mut out = Vec::new();
        out.extend_from_slice(&(reads.len() as u32).to_le_bytes());
        for (id, r) in reads {
            let mut spec = Vec::new();
            r.spec.encode(&mut CdrWriter::new(&mut spec, true));
            out.extend_from_slice(&id.0);
            out.extend_from_slice(&r.request_id.0);
            out.extend_from_slice(&r.delivered.to_le_bytes());
            out.extend_from_slice(&(spec.len() as u32).to_le_bytes());
            out.extend_from_slice(&spec);
            out.extend_from_slice(&(r.marks.marks.len() as u32).to_le_bytes());
            for (writer, seq) in &r.marks.marks {
                out.extend_from_slice(writer);
                out.extend_from_slice(&seq.to_le_bytes());
            }
        }
        out
    }

    /// A graph from what [`Self::encode_objects`] and [`Self::encode_reads`] made.
    pub fn decode(objects: &[u8], reads: &[u8]) -> Result<Self, DecodeError> {
        let mut g = ObjectGraph::default();
        let mut f = Fields(objects);
        let n = f.u32()?;
        if n > MAX_STORED {
            return Err(DecodeError::TooLong("stored objects"));
        }
        for _ in 0..n {
            let object_id = ObjectId(f.array()?);
            let request_id = RequestId(f.array()?);
            let little_endian = f.array::<1>()?[0] != 0;
            let len = f.u32()? as usize;
            let variant = ObjectVariant::decode(&mut CdrReader::new(f.take(len)?, true))?;
            g.objects.push(GraphObject {
                object_id,
                request_id,
                variant,
                little_endian,
                readers_matched: 0,
            });
        }
        if !f.0.is_empty() {
            return Err(DecodeError::InvalidValue("bytes after the stored objects"));
        }
        let mut f = Fields(reads);
        let n = f.u32()?;
        if n > MAX_STORED {
            return Err(DecodeError::TooLong("stored reads"));
        }
        for _ in 0..n {
            let reader = ObjectId(f.array()?);
            let request_id = RequestId(f.array()?);
            let delivered = f.u32()?;
            let len = f.u32()? as usize;
            let spec = ReadSpecification::decode(&mut CdrReader::new(f.take(len)?, true))?;
            let marks = f.u32()?;
            if marks as usize > MAX_MARKED_WRITERS {
                return Err(DecodeError::TooLong("stored delivered marks"));
            }
            let mut m = DeliveredMarks::default();
            for _ in 0..marks {
                let writer = f.array::<16>()?;
                let seq = i64::from_le_bytes(f.array()?);
                m.marks.push_back((writer, seq));
            }
            g.reads.insert(
                reader,
                ActiveRead {
                    request_id,
                    spec,
                    delivered,
                    marks: m,
                },
            );
        }
        if !f.0.is_empty() {
            return Err(DecodeError::InvalidValue("bytes after the stored reads"));
        }
        Ok(g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::{object_kind as k, Representation, VariantExtra};

    fn obj(prefix: u16, kind: u8, parent: Option<ObjectId>) -> GraphObject {
        GraphObject {
            object_id: ObjectId::new(prefix, kind),
            request_id: RequestId::from_u16(prefix),
            variant: ObjectVariant {
                kind,
                representation: Representation::Xml(format!("<x{prefix}/>")),
                extra: parent
                    .map(VariantExtra::Parent)
                    .unwrap_or(VariantExtra::DomainId(0)),
            },
            little_endian: true,
            readers_matched: 0,
        }
    }

    #[test]
    fn a_graph_round_trips_through_its_stored_form() {
        let mut g = ObjectGraph::default();
        let p = obj(1, k::PARTICIPANT, None);
        let s = obj(2, k::SUBSCRIBER, Some(p.object_id));
        let r = obj(3, k::DATAREADER, Some(s.object_id));
        for o in [&p, &s, &r] {
            g.insert(o.clone());
        }
        let mut marks = DeliveredMarks::default();
        marks.record([7; 16], 41);
        marks.record([9; 16], -2);
        g.set_read(
            r.object_id,
            ActiveRead {
                request_id: RequestId::from_u16(77),
                spec: ReadSpecification {
                    preferred_stream_id: 0x80,
                    data_format: 0x08,
                    content_filter_expression: Some("x > 3".into()),
                    delivery_control: None,
                    delivery_control_dheader: false,
                },
                delivered: 12,
                marks,
            },
        );
        let back = ObjectGraph::decode(&g.encode_objects(), &g.encode_reads()).expect("decode");
        assert_eq!(back.objects, g.objects);
        assert_eq!(back.reads, g.reads);
        // Damaged bytes are refused, never misread.
        let objects = g.encode_objects();
        for cut in 0..objects.len() {
            assert!(ObjectGraph::decode(&objects[..cut], &g.encode_reads()).is_err());
        }
    }

    #[test]
    fn creation_modes_follow_table_5() {
        let mut g = ObjectGraph::default();
        let p = obj(1, k::PARTICIPANT, None);
        assert_eq!(
            g.decide_create(p.object_id, &p.variant, true, false, false, MAX_OBJECTS),
            CreateDecision::Create
        );
        g.insert(p.clone());
        let mut other = p.variant.clone();
        other.representation = Representation::Xml("<y/>".into());
        let id = p.object_id;
        assert_eq!(
            g.decide_create(id, &p.variant, true, false, false, MAX_OBJECTS),
            CreateDecision::Reply(status::ERR_ALREADY_EXISTS)
        );
        assert_eq!(
            g.decide_create(id, &other, true, false, true, MAX_OBJECTS),
            CreateDecision::Replace
        );
        assert_eq!(
            g.decide_create(id, &p.variant, true, true, false, MAX_OBJECTS),
            CreateDecision::Reply(status::OK_MATCHED)
        );
        assert_eq!(
            g.decide_create(id, &other, true, true, false, MAX_OBJECTS),
            CreateDecision::Reply(status::ERR_MISMATCH)
        );
        assert_eq!(
            g.decide_create(id, &p.variant, true, true, true, MAX_OBJECTS),
            CreateDecision::Reply(status::OK_MATCHED)
        );
        assert_eq!(
            g.decide_create(id, &other, true, true, true, MAX_OBJECTS),
            CreateDecision::Replace
        );
    }

    #[test]
    fn objects_per_client_are_bounded() {
        let mut g = ObjectGraph::default();
        for i in 0..MAX_OBJECTS as u16 {
            g.insert(obj(i, k::PARTICIPANT, None));
        }
        let one_more = obj(MAX_OBJECTS as u16, k::PARTICIPANT, None);
        assert_eq!(
            g.decide_create(
                one_more.object_id,
                &one_more.variant,
                true,
                false,
                false,
                MAX_OBJECTS
            ),
            CreateDecision::Reply(status::ERR_RESOURCES)
        );
        // Replacing an existing object is still allowed.
        let first = obj(0, k::PARTICIPANT, None);
        assert_eq!(
            g.decide_create(
                first.object_id,
                &first.variant,
                true,
                false,
                true,
                MAX_OBJECTS
            ),
            CreateDecision::Replace
        );
    }

    #[test]
    fn removing_a_parent_removes_its_subtree_children_first() {
        let mut g = ObjectGraph::default();
        let p = obj(1, k::PARTICIPANT, None);
        let s = obj(1, k::SUBSCRIBER, Some(p.object_id));
        let r = obj(1, k::DATAREADER, Some(s.object_id));
        let other = obj(2, k::PARTICIPANT, None);
        for o in [&p, &s, &r, &other] {
            g.insert(o.clone());
        }
        g.set_read(
            r.object_id,
            ActiveRead {
                request_id: RequestId::from_u16(9),
                spec: ReadSpecification::default(),
                delivered: 0,
                marks: DeliveredMarks::default(),
            },
        );
        let removed = g.remove(p.object_id);
        assert_eq!(removed, vec![r.object_id, s.object_id, p.object_id]);
        assert_eq!(g.len(), 1);
        assert_eq!(g.reads().count(), 0);
    }

    #[test]
    fn delivered_marks_remember_the_last_sample_of_each_writer_and_forget_the_oldest() {
        let mut m = DeliveredMarks::default();
        let (a, b) = ([1u8; 16], [2u8; 16]);
        m.record(a, 5);
        m.record(a, 3);
        m.record(b, 1);
        assert!(m.already_delivered(&a, 5) && m.already_delivered(&a, 4));
        assert!(!m.already_delivered(&a, 6));
        assert!(m.already_delivered(&b, 1) && !m.already_delivered(&b, 2));
        assert!(!m.already_delivered(&[3u8; 16], 0));
        for w in 0..MAX_MARKED_WRITERS as u32 {
            let mut writer = [0xEE; 16];
            writer[..4].copy_from_slice(&w.to_le_bytes());
            m.record(writer, 1);
        }
        assert_eq!(m.len(), MAX_MARKED_WRITERS);
        assert!(
            !m.already_delivered(&a, 1),
            "the oldest writer is forgotten"
        );
    }
}
