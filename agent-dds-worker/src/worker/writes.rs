//! Writes: the DDS writers of XRCE data writers (shared ones included), the samples a new
//! or replayed writer holds until its readers match, and what is reported about matches.

use super::release_gate::{Admission, RELEASE_GATE_MAX};
use super::*;

/// The DDS writer behind one XRCE data writer, or behind several with `share_writers`.
pub(super) struct DdsWriter {
    pub(super) raw: Box<dyn backend::DdsWriter>,
    /// Its place among the shared writers, if it is one.
    pub(super) shared: Option<SharedWriterKey>,
    /// When it was first seen matching a reader (kept here, so that every XRCE writer
    /// sharing it sees the match).
    pub(super) matched_at: Cell<Option<Instant>>,
    /// How many readers it matched when last looked at.
    pub(super) matched: Cell<usize>,
    /// Front-end operations written through it that its readers may not have acknowledged.
    pub(super) outstanding: Outstanding,
    /// Its domain and topic: which of the worker's own readers must take what it wrote
    /// before a write counts as acknowledged ([`crate::acks`]).
    pub(super) topic: TopicKey,
}

impl Acknowledging for DdsWriter {
    fn acknowledged_writes(&self) -> u64 {
        self.raw.acknowledged_writes()
    }
    fn outstanding(&self) -> &Outstanding {
        &self.outstanding
    }
}

impl DdsWriter {
    /// Looks at the writer's matched readers; returns when it first matched one.
    pub(super) fn poll_matched(&self, now: Instant) -> Option<Instant> {
        let n = self.raw.matched_readers();
        if n > 0 && self.matched_at.get().is_none() {
            self.matched_at.set(Some(now));
        }
        self.matched.set(n);
        self.matched_at.get()
    }
}

/// A shared DDS writer, with the QoS and key type it was made with.
pub(super) struct SharedWriterEntry {
    pub(super) qos: EndpointQos,
    pub(super) ty: Option<Arc<StructDef>>,
    pub(super) writer: std::rc::Weak<DdsWriter>,
}

/// Most XRCE writers on one shared DDS writer. The shared writer keeps this many times the
/// history depth the clients asked for ([`EndpointQos::deeper`]), so that every client keeps
/// the resend window of a writer of its own (a reliable writer overwrites samples beyond its
/// depth, acknowledged or not), and its memory stays within what that many writers of their
/// own would hold.
pub(super) const SHARE_GROUP: usize = 32;

/// What makes two XRCE data writers able to share one DDS writer, besides equal QoS and
/// type: the domain, topic name, type name and byte order.
pub(super) type SharedWriterKey = (u16, String, String, bool);

/// A sample a writer holds for its readers.
pub(super) struct HeldSample {
    /// The front-end operation that wrote it.
    pub(super) seq: u64,
    pub(super) sample: Sample,
    /// It disposes (or unregisters) its instance.
    pub(super) dispose: bool,
    /// When its front-end took it from the client ([`ipc::Request::Write`]'s
    /// `received_us`): the release keeps the spacing.
    pub(super) received_us: u64,
    /// The client write it came from, if its front-end keeps that write for a resend.
    pub(super) origin: Option<ipc::SampleOrigin>,
}

/// One sample of a client's write, on its way to a DDS writer.
pub(super) struct OutgoingSample<'a> {
    /// The front-end operation that wrote it.
    pub(super) seq: u64,
    /// When its front-end took it from the client.
    pub(super) received_us: u64,
    pub(super) little_endian: bool,
    /// The serialized sample (or key fields, for a dispose).
    pub(super) body: &'a [u8],
    /// It disposes (or unregisters) its instance.
    pub(super) dispose: bool,
    /// The client write it came from, if its front-end keeps that write for a resend.
    pub(super) origin: Option<ipc::SampleOrigin>,
}

/// A new writer holds its writes until it has matched readers: volatile readers only get
/// samples written after they matched a writer, and DDS discovery takes 0.1–0.4 s here.
/// Without this, a client's first samples (the reference agent delivers them inside one Fast
/// DDS process) and the samples resent after a worker restart would reach nobody.
#[derive(Default)]
pub(super) struct Rematch {
    /// Until when writes are held at most (None = not holding).
    pub(super) until: Option<Instant>,
    /// When the writer first matched a reader again.
    pub(super) matched_at: Option<Instant>,
    /// Held writes, oldest first.
    pub(super) held: std::collections::VecDeque<HeldSample>,
    /// Bytes of the held samples.
    pub(super) held_bytes: usize,
    /// Matched: the held samples are being written in batches (new writes still queue behind
    /// them, so order is kept).
    pub(super) draining: bool,
    /// Whether the first held sample went out, alone (see [`RELEASE_FIRST_ACK_WAIT`]).
    pub(super) probed: bool,
    /// When the last batch of held samples was written.
    pub(super) last_batch: Option<Instant>,
    /// Readers the writer had matched before the worker restarted (from the front-end): a
    /// replayed writer holds until as many match again (0 or 1: the first match).
    pub(super) expected: u8,
    /// The matched count last reported to the front-end.
    pub(super) reported: Option<u8>,
    /// Where the release's schedule starts: when the writer began to drain, and the
    /// reception time of the sample it held first then ([`RELEASE_CATCH_UP`]).
    pub(super) schedule: Option<(Instant, u64)>,
    /// The worker stops: what is held goes out as fast as the readers acknowledge.
    pub(super) rush: bool,
    /// Its last batch waits for this worker's own readers of its topic to take what was
    /// released before ([`super::release_gate`]).
    pub(super) gated: bool,
    /// Since when it waits so.
    pub(super) gated_since: Option<Instant>,
    /// How long this drain waited so before (the current wait aside).
    pub(super) gate_waited: Duration,
    /// It waited [`RELEASE_GATE_DRAIN_MAX`] in all: it follows its schedule for the rest of
    /// this drain.
    pub(super) outwaited: bool,
}

impl Rematch {
    /// The writer stops holding: what it held went out, and a drain's state is forgotten.
    pub(super) fn end_drain(&mut self) {
        self.until = None;
        self.draining = false;
        self.schedule = None;
        self.gated = false;
        self.gated_since = None;
        self.gate_waited = Duration::ZERO;
        self.outwaited = false;
    }
}

/// Longest one drain waits at its topic's release gate in all, however its readers take:
/// a local reader whose client takes slowly must not hold the writer's other readers (and
/// its clients, whose new writes queue behind the held ones) to its pace for ever, nor let
/// the held samples grow to [`REMATCH_HELD_MAX`]. Beyond it, the writer goes on at its
/// schedule (counted, `release_gate_outwaited`); what it releases still counts against
/// the gate for the other writers.
pub(super) const RELEASE_GATE_DRAIN_MAX: Duration = Duration::from_secs(3);

/// Held samples written per batch while a writer drains: a whole backlog at once would
/// overrun the writer's keep-last history before its reader acknowledged (RustDDS then drops
/// the oldest), which lost samples after a worker restart.
pub(super) const RELEASE_BATCH: usize = 16;

/// How much faster than they came held samples are written: a sample received `d` after
/// the first one held is written `d / RELEASE_CATCH_UP` after the writer began to drain
/// (within the batches and the pass budget below). A burst of a second's samples overran
/// readers that keep the last 1,000; with 4 the readers see at most about four times the
/// rate the clients wrote at, and a writer that held for `h` has caught up with its
/// clients `h / 3` after it began to drain. (2 was too slow in a crash loop: the backlog
/// outlived each worker, measured in BENCHMARKS.)
pub(super) const RELEASE_CATCH_UP: u64 = 4;

/// Longest delay the schedule gives one held sample (reception times from another process
/// of the front-end, after a takeover, do not space like the rest).
pub(super) const RELEASE_SCHEDULE_MAX: Duration = Duration::from_secs(2);

/// Held samples written per millisecond since the last release, over every writer
/// (the writers take turns). After a worker restart a hundred writers may each hold a
/// second's samples; released together, as one burst, they overran the history of the
/// readers that keep the last 1,000 (this worker's own readers are taken only at the next
/// pass): a quarter of what was held was lost while every writer had its readers back.
/// Below [`PUMP_BATCH`](super::reads::PUMP_BATCH), what this worker's readers receive in a
/// pass is taken in the next. A stopping worker's writers are not held to it.
pub(super) const RELEASE_PASS_MAX: usize = 64;

/// The next batch waits until the readers acknowledged the previous one, at most this long
/// (the loop's pace while draining, so readers that acknowledge only on heartbeats do not
/// slow the drain below 8,000 samples/s per writer).
pub(super) const RELEASE_ACK_WAIT: Duration = Duration::from_millis(2);

/// The first held sample goes alone, and the rest waits until the readers acknowledged it,
/// at most this long. A volatile Cyclone DDS reader takes the first HEARTBEAT it sees from
/// a writer as where its stream starts: whatever that heartbeat announces and the reader did
/// not have yet is given up, not requested. RustDDS coalesces a burst into datagrams of
/// several DATA with one trailing HEARTBEAT that announces the writer's newest sample, which
/// the worker may have written after the datagram was packed; a remote reader whose first
/// heartbeat came that way lost the tail of the first released batch for good (samples
/// 12-15 of 16, in about one run in three of the front-end takeover tests). Once every
/// reader acknowledged one sample, each has seen a heartbeat, and later gaps are repaired.
pub(super) const RELEASE_FIRST_ACK_WAIT: Duration = Duration::from_millis(100);

/// Longest hold of a replayed writer's samples when no reader matches.
pub(super) const REMATCH_MAX: Duration = Duration::from_secs(3);

/// Longest hold of a new writer's first samples when no reader matches (there may be none).
pub(super) const NEW_WRITER_HOLD_MAX: Duration = Duration::from_secs(1);

/// Margin after the writer's match so the reader has matched the writer too (with 200 ms,
/// a burst released at a replayed writer's match occasionally lost its last samples to
/// Cyclone DDS under load: the first-heartbeat rule of [`RELEASE_FIRST_ACK_WAIT`]).
pub(super) const REMATCH_MARGIN: Duration = Duration::from_millis(500);

/// Most samples one holding writer keeps; beyond, it stops waiting for its readers and
/// writes what it holds (logged). (4,096 was too few: 10,000 samples/s fill it in 0.4 s, and the writer then wrote all of
/// them before its readers matched: 3,000 lost per worker kill.)
pub(super) const REMATCH_HELD_MAX: usize = 65_536;

/// Most bytes one holding writer keeps (the same rule).
pub(super) const REMATCH_HELD_MAX_BYTES: usize = 32 << 20;

/// The data of one WRITE_DATA, as a front-end handed it over.
pub(super) struct WriteData<'a> {
    /// Its XRCE DataFormat.
    pub(super) data_format: u8,
    pub(super) little_endian: bool,
    pub(super) dialect: Dialect,
    /// The bytes after the WRITE_DATA's BaseObjectRequest.
    pub(super) body: &'a [u8],
    /// When its front-end received it (`ipc::Request::Write`'s `received_us`).
    pub(super) received_us: u64,
    /// Its origin (index 0), for a write its front-end keeps for a resend.
    pub(super) origin: Option<ipc::SampleOrigin>,
}

impl<L: WorkerLink> Worker<L> {
    /// Publishes the samples of one WRITE_DATA (one, or several in the sequence formats).
    pub(super) fn write(
        &mut self,
        key: EntityKey,
        route: &Route,
        data: WriteData<'_>,
    ) -> Result<(), OpError> {
        let WriteData {
            data_format,
            little_endian,
            dialect,
            body,
            received_us,
            origin,
        } = data;
        // Without a type description the end of a sample is the end of the submessage, so
        // a sequence can be split only when it holds one sample; with it, the type says
        // where each sample ends.
        let ty = match self.entities.value(&key) {
            Some(Entity {
                kind: EntityKind::Writer { ty, .. },
                ..
            }) => ty.clone().map(Ty::Struct),
            _ => None,
        };
        let sizer_ty = ty.clone();
        let sizer =
            ty.map(|t| move |b: &[u8], origin: usize| sample_len(&t, b, origin, little_endian));
        let sizer_ref = sizer
            .as_ref()
            .map(|f| f as &dyn Fn(&[u8], usize) -> Option<usize>);
        let samples = decode_samples(data_format, body, little_endian, dialect, sizer_ref)
            .map_err(|e| OpError::InvalidData(format!("WRITE_DATA: {e}")))?;
        let ends_instance = |s: &xrce_common::wire::sample::SampleRef<'_>| {
            s.info.is_some_and(|i| {
                i.state & (sample_state::INSTANCE_DISPOSED | sample_state::INSTANCE_UNREGISTERED)
                    != 0
            })
        };
        if let Some(Entity {
            kind: EntityKind::Service(svc),
            ..
        }) = self.entities.value_mut(&key)
        {
            if samples.iter().any(ends_instance) {
                return Err(OpError::Incompatible(
                    "a requester or replier cannot dispose or unregister".into(),
                ));
            }
            for s in samples {
                service_write(svc, route.request_id, little_endian, s.data)?;
            }
            return Ok(());
        }
        let several = samples.len() > 1;
        for (index, s) in samples.into_iter().enumerate() {
            let dispose = ends_instance(&s);
            // A sample split out of a sequence aligns from the WRITE_DATA's payload; DDS
            // wants it aligned from its own start.
            let offset = (s.data.as_ptr() as usize).saturating_sub(body.as_ptr() as usize);
            let rebased = match (&sizer_ty, several && offset % 8 != 0) {
                (Some(t), true) => Some(
                    crate::types::rebase(t, s.data, offset, little_endian)
                        .map_err(|e| OpError::InvalidData(format!("WRITE_DATA sample: {e}")))?,
                ),
                _ => None,
            };
            let data = rebased.as_deref().unwrap_or(s.data);
            let origin = origin.map(|mut o| {
                // A body of at most MAX_BODY bytes holds fewer samples than u32 counts.
                o.write.index = u32::try_from(index).unwrap_or(u32::MAX);
                o
            });
            let sample = OutgoingSample {
                seq: route.op_seq,
                received_us,
                little_endian,
                body: data,
                dispose,
                origin,
            };
            self.write_sample(key, sample)?;
            self.samples_written += 1;
        }
        Ok(())
    }

    /// Writes one sample of no client write kept for a resend (the tests' way in).
    #[cfg(test)]
    pub(super) fn write_one(
        &mut self,
        key: EntityKey,
        seq: u64,
        received_us: u64,
        little_endian: bool,
        body: &[u8],
        dispose: bool,
    ) -> Result<(), OpError> {
        let sample = OutgoingSample {
            seq,
            received_us,
            little_endian,
            body,
            dispose,
            origin: None,
        };
        self.write_sample(key, sample)
    }

    /// Writes one sample of a client's write, or holds it while its writer waits for its
    /// readers.
    pub(super) fn write_sample(
        &mut self,
        key: EntityKey,
        sample: OutgoingSample<'_>,
    ) -> Result<(), OpError> {
        let OutgoingSample {
            seq,
            received_us,
            little_endian,
            body,
            dispose,
            origin,
        } = sample;
        let Some(Entity {
            kind: EntityKind::Writer {
                writer: w, rematch, ..
            },
            ..
        }) = self.entities.value_mut(&key)
        else {
            return Err(OpError::UnknownReference(
                "write to an unknown data writer".into(),
            ));
        };
        if little_endian != w.raw.little_endian() {
            // Without the type the bytes cannot be swapped.
            return Err(OpError::InvalidData(format!(
                "a {}-endian sample for a data writer created {}-endian",
                if little_endian { "little" } else { "big" },
                if w.raw.little_endian() {
                    "little"
                } else {
                    "big"
                },
            )));
        }
        let sample = Sample::cdr(little_endian, body);
        if dispose && w.raw.key().is_none() {
            // DDS has no instances on a topic without a key.
            return Err(OpError::Incompatible(
                "dispose or unregister on a topic without a key (or whose type is unknown)".into(),
            ));
        }
        if let Some(k) = w.raw.key() {
            // Checked now, so a held sample cannot fail later, unreported.
            let whole = k.of_sample(body, little_endian, false);
            if whole.is_err() && !(dispose && k.of_key_payload(body, little_endian, false).is_ok())
            {
                return Err(OpError::InvalidData(format!(
                    "a sample that is not a {}",
                    k.ty().name
                )));
            }
        }
        if rematch.until.is_some() {
            if rematch.held.len() < REMATCH_HELD_MAX
                && rematch.held_bytes + sample.body.len() <= REMATCH_HELD_MAX_BYTES
            {
                rematch.held_bytes += sample.body.len();
                rematch.held.push_back(HeldSample {
                    seq,
                    sample,
                    dispose,
                    received_us,
                    origin,
                });
                return Ok(());
            }
            // Bounded: a writer that would hold more stops waiting for its readers.
            tracing::warn!(
                frontend = key.0,
                client = %key.1,
                held = rematch.held.len(),
                "writer stops waiting for readers: too many samples held"
            );
            rematch.end_drain();
            rematch.held_bytes = 0;
            let held = std::mem::take(&mut rematch.held);
            let w = w.clone();
            self.publish_held(key, &w, held, self.now);
            return self.publish_one(key, &w, seq, sample, dispose, origin);
        }
        let w = w.clone();
        self.publish_one(key, &w, seq, sample, dispose, origin)
    }

    /// Writes one sample (or dispose) through `w` and records it for acknowledgement.
    fn publish_one(
        &mut self,
        key: EntityKey,
        w: &Rc<DdsWriter>,
        seq: u64,
        sample: Sample,
        dispose: bool,
        origin: Option<ipc::SampleOrigin>,
    ) -> Result<(), OpError> {
        let done = if dispose {
            w.raw
                .dispose(&sample)
                .map_err(|e| OpError::from(e.context("DDS dispose")))
        } else {
            publish(&*w.raw, sample).map_err(|e| OpError::from(e.context("DDS write")))
        };
        if done.is_ok() {
            self.writers
                .record(w, key.0, seq, origin, self.now, |epoch| {
                    self.readers.oldest_position(&w.topic, epoch)
                });
        } else {
            self.writers.take_logs.write_failed(&w.topic);
        }
        done
    }

    /// Writes `held` samples through `w` at once, in order (a holding writer that stops
    /// waiting for its readers, or one deleted while holding).
    pub(super) fn publish_held(
        &mut self,
        key: EntityKey,
        w: &Rc<DdsWriter>,
        held: std::collections::VecDeque<HeldSample>,
        now: Instant,
    ) {
        let mut failures = 0;
        for HeldSample {
            seq,
            sample: s,
            dispose,
            origin,
            ..
        } in held
        {
            let done = if dispose {
                w.raw.dispose(&s)
            } else {
                publish(&*w.raw, s)
            };
            match done {
                Ok(()) => self.writers.record(w, key.0, seq, origin, now, |epoch| {
                    self.readers.oldest_position(&w.topic, epoch)
                }),
                Err(_) => {
                    failures += 1;
                    self.writers.take_logs.write_failed(&w.topic);
                }
            }
        }
        for _ in 0..failures {
            self.count("dds_write_failed");
        }
    }

    /// A live shared DDS writer made with this QoS and type, if any (dead entries pruned).
    pub(super) fn shared_writer(
        &mut self,
        key: &SharedWriterKey,
        qos: &EndpointQos,
        ty: Option<&Arc<StructDef>>,
    ) -> Option<Rc<DdsWriter>> {
        let entries = self.writers.shared.get_mut(key)?;
        entries.retain(|e| e.writer.strong_count() > 0);
        let found = entries
            .iter()
            .filter(|e| e.writer.strong_count() < SHARE_GROUP)
            .find(|e| &e.qos == qos && e.ty.as_deref() == ty.map(|t| &**t))
            .and_then(|e| e.writer.upgrade());
        if entries.is_empty() {
            self.writers.shared.remove(key);
        }
        found
    }

    /// The worker stops: every holding writer stops waiting for its readers and releases
    /// what it holds over the next passes (in its paced batches), so that readers matched
    /// by then get the samples, which nobody would once the worker is gone.
    pub(super) fn stop_holding(&mut self) {
        let now = self.now;
        for key in &self.writers.holding {
            if let Some(Entity {
                kind: EntityKind::Writer { rematch, .. },
                ..
            }) = self.entities.value_mut(key)
            {
                if rematch.until.is_some_and(|until| until > now) {
                    rematch.until = Some(now);
                }
                rematch.rush = true;
            }
        }
    }

    /// When the next held sample of a draining writer is due (None: none drains).
    pub(super) fn next_release(&self) -> Option<Instant> {
        self.writers
            .holding
            .iter()
            .filter_map(|k| match self.entities.value(k) {
                Some(Entity {
                    kind:
                        EntityKind::Writer {
                            rematch: r,
                            writer: w,
                            ..
                        },
                    ..
                }) if r.draining => Some(match (r.schedule, r.held.front()) {
                    // Its readers' next pass opens the gate, at the latest its time.
                    _ if r.gated && !r.rush => self
                        .writers
                        .gates
                        .next_expiry(&w.topic)
                        .unwrap_or(self.now + RELEASE_GATE_MAX),
                    (Some((start, first)), Some(h)) if !r.rush => {
                        start + release_delay(first, h.received_us)
                    }
                    _ => self.now,
                }),
                _ => None,
            })
            .min()
    }

    /// Samples holding writers keep.
    pub(super) fn held_samples(&self) -> usize {
        self.writers
            .holding
            .iter()
            .filter_map(|k| match self.entities.value(k) {
                Some(Entity {
                    kind: EntityKind::Writer { rematch, .. },
                    ..
                }) => Some(rematch.held.len()),
                _ => None,
            })
            .sum()
    }

    /// Releases the samples of replayed writers that matched again (or waited long enough).
    pub(super) fn release_rematched(&mut self) {
        let now = self.now;
        let mut failures = 0u64;
        let mut done = Vec::new();
        // Front-ends whose held writes advanced: their progress is sent.
        let mut released = Vec::new();
        // Held samples written in this pass, over every writer: RELEASE_PASS_MAX per
        // millisecond since the last release pass (passes are not evenly spaced).
        // At most PUMP_BATCH in all, so that this worker's readers take in their next pass
        // what they receive in this one.
        let most_ms = (super::reads::PUMP_BATCH / RELEASE_PASS_MAX).max(1) as u128;
        let elapsed_ms = self.writers.last_release.map_or(1, |t| {
            now.saturating_duration_since(t)
                .as_millis()
                .clamp(1, most_ms) as usize
        });
        let mut budget = RELEASE_PASS_MAX * elapsed_ms;
        let mut spent = false;
        // This worker's readers drained up to, per topic (counted once, when needed).
        let mut drained = None;
        // The topics writers still drain into: their gates are kept.
        let mut draining_topics = HashSet::new();
        // Writers that waited for their readers as long as a drain may.
        let mut outwaited = 0u64;
        // In turns: the first writer of this pass is the second of the last one.
        let mut order: Vec<EntityKey> = self.writers.holding.iter().copied().collect();
        if !order.is_empty() {
            let turn = self.writers.release_turn % order.len();
            order.rotate_left(turn);
            self.writers.release_turn = turn + 1;
        }
        for key in &order {
            let Some(Entity {
                kind:
                    EntityKind::Writer {
                        writer: w, rematch, ..
                    },
                ..
            }) = self.entities.value_mut(key)
            else {
                done.push(*key);
                continue;
            };
            let Some(until) = rematch.until else {
                done.push(*key);
                continue;
            };
            if rematch.matched_at.is_none() {
                // As many readers as before the restart (at least one): a writer that
                // released when the first of several matched lost samples to the others.
                let first = w.poll_matched(now);
                if w.matched.get() >= usize::from(rematch.expected) {
                    rematch.matched_at = if rematch.expected <= 1 {
                        first
                    } else {
                        Some(now)
                    };
                }
            }
            let ready = rematch
                .matched_at
                .is_some_and(|t| now >= t + REMATCH_MARGIN)
                || now >= until;
            if ready && !rematch.draining {
                // Debug: with many clients every new writer passes here once.
                tracing::debug!(
                    client = %key.1,
                    held = rematch.held.len(),
                    matched = rematch.matched_at.is_some(),
                    readers = w.matched.get(),
                    expected = rematch.expected,
                    first = rematch.held.front().map(|h| h.seq),
                    "holding writer resumes"
                );
                rematch.draining = true;
            }
            // The first batch is one sample; the second waits longer for its acknowledgement.
            let wait = if rematch.probed {
                RELEASE_ACK_WAIT
            } else {
                RELEASE_FIRST_ACK_WAIT
            };
            let paced = rematch.last_batch.is_some_and(|t| {
                now.saturating_duration_since(t) < wait && !w.raw.all_acknowledged()
            });
            // Samples the schedule lets out by now.
            let due = if !rematch.draining {
                0
            } else if rematch.rush {
                rematch.held.len()
            } else if let Some(front) = rematch.held.front() {
                let (start, first) = *rematch.schedule.get_or_insert((now, front.received_us));
                rematch
                    .held
                    .iter()
                    .take(RELEASE_BATCH)
                    .take_while(|h| now >= start + release_delay(first, h.received_us))
                    .count()
            } else {
                0
            };
            // (A writer that holds nothing any more is done at once; a stopping worker's
            // writers are not held to the pass budget.)
            let room = budget > 0 || rematch.rush;
            let may_release =
                rematch.draining && !paced && room && (due > 0 || rematch.held.is_empty());
            if rematch.draining && !rematch.held.is_empty() && !draining_topics.contains(&w.topic) {
                draining_topics.insert(w.topic);
            }
            let batch = if !may_release {
                0
            } else if rematch.last_batch.is_none() {
                1
            } else if rematch.rush {
                RELEASE_BATCH.min(due)
            } else {
                RELEASE_BATCH.min(budget).min(due)
            };
            // This worker's readers of the topic take what was released into it before
            // (asked last: the answer costs a look at every read). A stopping worker's
            // writers do not wait for them.
            let wanted = batch;
            let batch = if batch == 0 || rematch.rush || rematch.outwaited {
                batch
            } else {
                let d = drained
                    .get_or_insert_with(|| self.readers.drained_through(&self.frontends.orphaned))
                    .get(&w.topic)
                    .copied();
                match self.writers.gates.admit(&w.topic, d, batch, now) {
                    Admission::Release(n) => n,
                    Admission::Wait => 0,
                }
            };
            rematch.gated = may_release && batch == 0 && !rematch.held.is_empty();
            let batch = if rematch.gated {
                let since = *rematch.gated_since.get_or_insert(now);
                if rematch.gate_waited + now.saturating_duration_since(since)
                    >= RELEASE_GATE_DRAIN_MAX
                {
                    rematch.outwaited = true;
                    rematch.gated = false;
                    outwaited += 1;
                    wanted
                } else {
                    0
                }
            } else {
                if let Some(since) = rematch.gated_since.take() {
                    rematch.gate_waited += now.saturating_duration_since(since);
                }
                batch
            };
            if may_release && !rematch.gated {
                if rematch.last_batch.is_some() {
                    rematch.probed = true;
                }
                budget = budget.saturating_sub(batch.min(rematch.held.len()));
                spent = true;
                rematch.last_batch = Some(now);
                released.push(key.0);
                for _ in 0..batch {
                    let Some(HeldSample {
                        seq,
                        sample,
                        dispose,
                        origin,
                        ..
                    }) = rematch.held.pop_front()
                    else {
                        break;
                    };
                    rematch.held_bytes = rematch.held_bytes.saturating_sub(sample.body.len());
                    let done = if dispose {
                        w.raw.dispose(&sample)
                    } else {
                        publish(&*w.raw, sample)
                    };
                    if let Err(e) = &done {
                        tracing::warn!(frontend = key.0, client = %key.1, error = %e, dispose, "held sample not published");
                    }
                    if done.is_err() {
                        failures += 1;
                        self.writers.take_logs.write_failed(&w.topic);
                    } else {
                        self.writers.record(w, key.0, seq, origin, now, |epoch| {
                            self.readers.oldest_position(&w.topic, epoch)
                        });
                        self.writers.gates.released(&w.topic, self.writers.stamp);
                    }
                }
                if rematch.held.is_empty() {
                    rematch.end_drain();
                    tracing::debug!("holding writer drained");
                    done.push(*key);
                }
            }
        }
        if spent {
            self.writers.last_release = Some(now);
        }
        for k in done {
            self.writers.holding.remove(&k);
            released.push(k.0);
        }
        for fe in released {
            if let Some(p) = self.frontends.ports.get_mut(&fe) {
                p.dirty = true;
            }
        }
        for _ in 0..failures {
            self.count("dds_write_failed");
        }
        self.writers.gates.keep_only(&draining_topics, now);
        if outwaited > 0 {
            let why = format!(
                "a draining writer waited {} s in all for this worker's readers of its topic \
                 to take what was released (their client takes slowly): it follows its \
                 schedule for the rest of the drain, and may overwrite their history",
                RELEASE_GATE_DRAIN_MAX.as_secs()
            );
            for _ in 0..outwaited {
                self.refused("release_gate_outwaited", &why);
            }
        }
        let gate_expired = self.writers.gates.take_expired();
        if gate_expired > 0 {
            let why = format!(
                "held samples released although this worker's reader of their topic has not \
                 taken the previous ones for {} ms (its client does not keep up): they may \
                 overwrite each other in its history",
                RELEASE_GATE_MAX.as_millis()
            );
            for _ in 0..gate_expired {
                self.refused("release_gate_expired", &why);
            }
        }
    }

    /// Tells front-ends how many readers each of their data writers matches, when that
    /// changed (every [`MATCH_REPORT_PERIOD`]).
    pub(super) fn report_matches(&mut self) {
        let now = self.now;
        if now < self.next_match_report {
            return;
        }
        self.next_match_report = now + MATCH_REPORT_PERIOD;
        let mut changed = Vec::new();
        for (key, e) in self.entities.iter_mut() {
            if let EntityKind::Writer {
                writer: w, rematch, ..
            } = &mut e.kind
            {
                w.poll_matched(now);
                let n = u8::try_from(w.matched.get()).unwrap_or(u8::MAX);
                if rematch.reported != Some(n) {
                    rematch.reported = Some(n);
                    changed.push((*key, n));
                }
            }
        }
        for ((fe, client, object), n) in changed {
            self.reply(
                Route::object(fe, client, Default::default(), object),
                Reply::WriterMatched { readers: n },
            );
        }
    }

    /// The oldest operation held by a replayed writer, per front-end.
    pub(super) fn oldest_held(&self) -> HashMap<u32, u64> {
        let mut m: HashMap<u32, u64> = HashMap::new();
        for (k, e) in self
            .writers
            .holding
            .iter()
            .filter_map(|k| Some((k, self.entities.get(k)?)))
        {
            if let EntityKind::Writer { rematch: r, .. } = &e.kind {
                if let Some(h) = r.held.front() {
                    let v = m.entry(k.0).or_insert(h.seq);
                    *v = (*v).min(h.seq);
                }
            }
        }
        m
    }
}

/// How long after a writer began to drain a held sample received at `received_us` is
/// written, when the first sample it held then was received at `first_us`.
pub(super) fn release_delay(first_us: u64, received_us: u64) -> Duration {
    Duration::from_micros(received_us.saturating_sub(first_us) / RELEASE_CATCH_UP)
        .min(RELEASE_SCHEDULE_MAX)
}

/// Writes one sample to DDS: once, unless a fault injected on purpose (`xrce_common::fault`,
/// test builds only) drops it or writes it twice.
fn publish(writer: &dyn backend::DdsWriter, sample: Sample) -> Result<(), BackendError> {
    if fault::hit(Fault::DdsDrop, 10) {
        return Ok(());
    }
    if fault::hit(Fault::DdsDuplicate, 10) {
        writer.write(sample.clone())?;
    }
    writer.write(sample)
}
