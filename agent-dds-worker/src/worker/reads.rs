//! Reads: the active reads of the front-ends' clients, their delivery limits and pacing,
//! and the samples taken from DDS readers for them.

use super::take_log::LogPosition;
use super::*;
use crate::filter::{EVAL_BUDGET, READER_PASS_BUDGET};

pub(super) struct ActiveRead {
    pub(super) request_id: xrce_common::wire::RequestId,
    /// Samples still to deliver (None = unlimited).
    pub(super) remaining: Option<u32>,
    /// When the read ends by time.
    pub(super) deadline: Option<Instant>,
    /// No delivery control: deliver what is there, or the first sample to come, then end.
    pub(super) one_shot: bool,
    /// The front-end asked to hold samples back (its client is not keeping up).
    pub(super) paused: bool,
    /// DataDeliveryControl pacing; samples wait in the DDS reader meanwhile.
    pub(super) pacing: Pacing,
    /// The read's content filter.
    pub(super) filter: Option<Filter>,
    /// The DataFormat the client asked for: without a SampleInfo (DATA, DATA_SEQ) a
    /// dispose cannot be told from a sample, so those reads get no instance ends.
    pub(super) data_format: u8,
    /// The data reader's topic (None for a requester or replier).
    pub(super) topic: Option<TopicKey>,
    /// The data reader's history depth ([`ReaderInfo::depth`]; 0 for the others).
    pub(super) depth: u32,
    /// The worker's write stamp up to which the reader was last seen drained: every sample
    /// written before taken and handed to the front-end ([`crate::acks`]); 0 until then.
    pub(super) drained_through: u64,
    /// The reader may hold samples this read has not handed over: it was named ready since
    /// a pump last emptied it with what it took in its front-end's queue (or the read is
    /// new). One that does not was drained through the last readiness scan too
    /// ([`Readers::drained_through`]).
    pub(super) holds: bool,
    /// The write stamp a pump drained the reader through (it emptied it then, or took up to
    /// there in write order) while what it took still waited in the worker for room in the
    /// front-end's queue: drained through it once that backlog is sent. A reader of a
    /// congested path is rarely seen empty with its front-end's queue empty at once;
    /// without this its writes would stay unacknowledged until
    /// [`crate::acks::ACK_GIVE_UP`], and be resent (repeated) if the worker died.
    pub(super) pending_drained: Option<u64>,
    /// Its reader takes in write order (a volatile data reader of a topic without a key,
    /// [`super::take_log`]).
    pub(super) in_write_order: bool,
    /// How many of this worker's writes to the topic, logged since the log began, its
    /// reader took ([`Readers::positions`]; None after it fell behind the log, until it is
    /// seen empty again).
    pub(super) position: Option<LogPosition>,
    /// Samples taken for it so far: the release gate sees a reader that takes without being
    /// emptied as taking ([`super::release_gate`]).
    pub(super) taken: u64,
}

/// DataDeliveryControl's `min_pace_period` and `max_bytes_per_second`.
#[derive(Debug, Default)]
pub(super) struct Pacing {
    /// At least this long between two samples (one DATA each).
    pub(super) min_pace: Option<Duration>,
    /// At most this many sample bytes per one-second window.
    pub(super) bytes_per_second: Option<u64>,
    /// No delivery before this.
    pub(super) next_at: Option<Instant>,
    pub(super) window_start: Option<Instant>,
    pub(super) window_bytes: u64,
}

impl Pacing {
    pub(super) fn new(d: &xrce_common::wire::DataDeliveryControl) -> Self {
        Pacing {
            min_pace: (d.min_pace_period > 0)
                .then(|| Duration::from_millis(u64::from(d.min_pace_period))),
            bytes_per_second: (d.max_bytes_per_second > 0)
                .then_some(u64::from(d.max_bytes_per_second)),
            ..Pacing::default()
        }
    }

    pub(super) fn limited(&self) -> bool {
        self.min_pace.is_some() || self.bytes_per_second.is_some()
    }

    /// Whether a sample may go now; if not, `next_at` says when to try again.
    pub(super) fn may_send(&mut self, now: Instant) -> bool {
        if self.next_at.is_some_and(|t| now < t) {
            return false;
        }
        self.next_at = None;
        if let Some(limit) = self.bytes_per_second {
            let start = *self.window_start.get_or_insert(now);
            if now >= start + Duration::from_secs(1) {
                self.window_start = Some(now);
                self.window_bytes = 0;
            } else if self.window_bytes >= limit {
                self.next_at = Some(start + Duration::from_secs(1));
                return false;
            }
        }
        true
    }

    /// Accounts a delivered sample of `len` bytes.
    pub(super) fn sent(&mut self, now: Instant, len: usize) {
        self.window_bytes += len as u64;
        if let Some(p) = self.min_pace {
            self.next_at = Some(now + p);
        }
    }
}

/// Samples taken from one reader per wake-up before others get a turn.
pub(super) const PUMP_BATCH: usize = 256;

impl<L: WorkerLink> Worker<L> {
    pub(super) fn start_read(
        &mut self,
        key: EntityKey,
        request_id: xrce_common::wire::RequestId,
        replay: bool,
        body: &[u8],
    ) -> Result<(), OpError> {
        let (reader_type, topic, depth, in_write_order) = match self.entities.value(&key) {
            Some(Entity {
                kind: EntityKind::Reader { info, .. },
                ..
            }) => (
                Some(info.ty.clone()),
                Some(TopicKey::of(&self.topic_keys, info.domain, &info.topic)),
                info.depth,
                info.in_write_order,
            ),
            Some(Entity {
                kind: EntityKind::Service(..),
                ..
            }) => (None, None, 0, false),
            _ => {
                return Err(OpError::UnknownReference(
                    "read from an unknown data reader, requester or replier".into(),
                ))
            }
        };
        let spec = ReadSpecification::decode(&mut CdrReader::new(body, true))
            .map_err(|e| OpError::InvalidData(format!("read specification: {e}")))?;
        // The front-end puts each sample in the requested format.
        if !xrce_common::wire::sample::is_defined_format(spec.data_format) {
            return Err(OpError::InvalidData(format!(
                "undefined data format {:#04x}",
                spec.data_format
            )));
        }
        let filter = match (spec.content_filter_expression.as_deref(), reader_type) {
            (None, _) => None,
            (Some(f), _) if f.trim().is_empty() => None,
            (Some(f), Some(ty)) => Some(
                compile_filter(f, ty.as_ref(), "the reader's topic")
                    .map_err(|e| self.filter_refused(e))?,
            ),
            (Some(_), None) => {
                return Err(OpError::Incompatible(
                    "content filters apply to data readers, not requesters or repliers".into(),
                ))
            }
        };
        // A new read starts unpaused (the front-end forgets its pause too).
        let paused = false;
        // Where its reader stands in the topic's take log (from its creation on).
        let position = self.readers.positions.get(&key).copied();
        let read = match spec.delivery_control {
            Some(d) if d.max_samples == 0 => {
                self.readers.reads.remove(&key);
                return Ok(());
            }
            Some(d) => ActiveRead {
                request_id,
                remaining: (d.max_samples != u16::MAX).then_some(d.max_samples as u32),
                deadline: (d.max_elapsed_time != 0)
                    .then(|| self.now + Duration::from_secs(d.max_elapsed_time as u64)),
                one_shot: false,
                paused,
                pacing: Pacing::new(&d),
                filter,
                data_format: spec.data_format,
                topic,
                depth,
                drained_through: 0,
                holds: true,
                pending_drained: None,
                taken: 0,
                in_write_order,
                position,
            },
            None => ActiveRead {
                request_id,
                remaining: None,
                deadline: None,
                one_shot: true,
                paused,
                pacing: Pacing::default(),
                filter,
                data_format: spec.data_format,
                topic,
                depth,
                drained_through: 0,
                holds: true,
                pending_drained: None,
                taken: 0,
                in_write_order,
                position,
            },
        };
        self.readers.reads.insert(key, read);
        if replay {
            self.offer_recent(key, request_id);
        } else if let Some(r) = self.frontends.recent.get_mut(&key.0) {
            // The client has no record of what an earlier read on this reader delivered.
            r.forget(&key);
        }
        Ok(())
    }

    /// Sends a replayed read the samples last handed to its front-end for it: a successor
    /// of a front-end that died gets those its predecessor may not have delivered (it drops
    /// the others by their identity).
    ///
    /// The read's limits count them: a one-shot read gets the newest and ends (the front-end
    /// drops it if its predecessor delivered it, and the read is over either way), a read of
    /// at most so many samples counts them all as delivered (it may end short by those the
    /// front-end drops, never beyond its limit).
    pub(super) fn offer_recent(
        &mut self,
        key: EntityKey,
        request_id: xrce_common::wire::RequestId,
    ) {
        let mut samples = self
            .frontends
            .recent
            .get(&key.0)
            .map(|r| r.of(&key, request_id))
            .unwrap_or_default();
        if samples.is_empty() {
            return;
        }
        let ended = match self.readers.reads.get_mut(&key) {
            Some(r) if r.one_shot => {
                samples.drain(..samples.len() - 1);
                true
            }
            Some(r) => match r.remaining.as_mut() {
                Some(rem) => {
                    let n = (*rem as usize).min(samples.len());
                    samples.drain(..samples.len() - n);
                    *rem -= n as u32;
                    *rem == 0
                }
                None => false,
            },
            None => false,
        };
        tracing::info!(client = %key.1, reader = ?key.2, samples = samples.len(), "recent samples offered again to a replayed read");
        for sample in samples {
            self.reply(
                Route::object(key.0, key.1, request_id, key.2),
                Reply::Sample(sample),
            );
        }
        if ended {
            self.end_read(key);
        }
    }

    /// Takes samples of a reader with an active read and sends them to its front-end.
    ///
    /// A reader with a content filter (its own or its read's) spends from its filter budget
    /// for this pass ([`crate::filter::READER_PASS_BUDGET`], within what is left of the
    /// pass's [`crate::filter::PASS_BUDGET`]) and takes a sample only while a whole
    /// evaluation ([`crate::filter::EVAL_BUDGET`]) fits in what is left: the rest waits in
    /// the DDS reader for the next pass. A sample whose own evaluation runs out of budget is
    /// treated as not matching, and counted (`content_filter_over_budget`).
    pub(super) fn pump(&mut self, key: EntityKey) {
        let Some(read) = self.readers.reads.get_mut(&key).filter(|r| !r.paused) else {
            return;
        };
        if let Some(p) = self
            .frontends
            .ports
            .get_mut(&key.0)
            .filter(|p| !p.backlog.is_empty())
        {
            // The front-end is congested: leave the samples in the DDS reader for now.
            p.deferred.push(key);
            return;
        }
        // What an earlier pump took, when it emptied the reader, is in the queue now.
        if let Some(stamp) = read.pending_drained.take() {
            read.drained_through = read.drained_through.max(stamp);
        }
        let filtering = read.filter.is_some()
            || matches!(
                self.entities.value(&key),
                Some(Entity {
                    kind: EntityKind::Reader {
                        info: ReaderInfo {
                            filter: Some(_),
                            ..
                        },
                        ..
                    },
                    ..
                })
            );
        if filtering && self.readers.filter_pass_left < EVAL_BUDGET {
            // The pass's filter budget is spent: first in line next pass.
            self.readers.over_budget.push(key);
            return;
        }
        let Some(read) = self.readers.reads.get_mut(&key) else {
            return;
        };
        let mut budget = Steps::new(READER_PASS_BUDGET.min(self.readers.filter_pass_left));
        let mut over_budget = 0u64;
        let mut deferred = false;
        let request_id = read.request_id;
        let (reader, mut service, reader_filter) = match self.entities.value_mut(&key) {
            Some(Entity {
                kind: EntityKind::Reader { reader, info, .. },
                ..
            }) => (&mut **reader, None, info.filter.as_ref()),
            Some(Entity {
                kind: EntityKind::Service(s),
                ..
            }) => {
                let s = &mut **s;
                (
                    &mut *s.reader,
                    Some((s.requester, &*s.writer, &mut s.pending)),
                    None,
                )
            }
            _ => return,
        };
        let mut out = Vec::new();
        // This worker's writes taken, in write order ([`super::take_log`]).
        let mut logged_taken = 0u64;
        let logs = &self.writers.take_logs;
        let log_topic = read
            .topic
            .as_ref()
            .filter(|_| read.in_write_order && read.position.is_some());
        let mut more = false;
        // The reader gave everything it had.
        let mut emptied = false;
        let mut limit = read.remaining.unwrap_or(u32::MAX).min(PUMP_BATCH as u32);
        let one_shot = read.one_shot;
        let mut errors = 0u64;
        let mut filtered = 0u64;
        let now = self.now;
        while limit > 0 {
            if read.pacing.limited() && !read.pacing.may_send(now) {
                // Paced: the rest waits in the DDS reader until `next_at`.
                break;
            }
            if filtering && budget.left() < EVAL_BUDGET {
                // Not a whole evaluation left for this reader this pass: the rest waits in
                // the DDS reader (no sample is judged on a budget cut short).
                more = true;
                deferred = true;
                break;
            }
            match reader.take_next() {
                Ok(Some(taken)) => {
                    if let Some(topic) = log_topic {
                        if !taken.disposed
                            && !taken.unregistered
                            && logs.is_logged_writer(topic, &taken.identity.writer)
                        {
                            logged_taken += 1;
                        }
                    }
                    let mut s = taken.sample.clone();
                    if let Some((requester, writer, pending)) = service.as_mut() {
                        match service_sample(*requester, *writer, pending, &taken, key.2, s) {
                            Some(wrapped) => s = wrapped,
                            // A reply to another requester.
                            None => continue,
                        }
                    }
                    let ends = taken.disposed || taken.unregistered;
                    if ends
                        && matches!(
                            read.data_format,
                            xrce_common::wire::data_format::DATA
                                | xrce_common::wire::data_format::DATA_SEQ
                        )
                    {
                        // Taken, not delivered, not counted against max_samples.
                        continue;
                    }
                    // A filter sees samples; instance ends (key fields only) pass. Both
                    // filters of a sample share one evaluation's budget.
                    let selected = ends || {
                        let mut steps = Steps::new(EVAL_BUDGET);
                        let (le, xcdr2) = (s.little_endian(), s.encoding.is_xcdr2());
                        let mut verdict = Verdict::Match;
                        for f in [reader_filter, read.filter.as_ref()].into_iter().flatten() {
                            verdict = f.evaluate(&s.body, le, xcdr2, &mut steps);
                            if verdict != Verdict::Match {
                                break;
                            }
                        }
                        // What the evaluation spent leaves the reader's pass budget.
                        budget.charge(steps.spent());
                        if verdict == Verdict::OverBudget {
                            over_budget += 1;
                        }
                        verdict == Verdict::Match
                    };
                    if !selected {
                        // Taken and dropped; it does not count against max_samples, but it
                        // counts against the batch so a flood cannot starve the loop.
                        filtered += 1;
                        if filtered > 4 * PUMP_BATCH as u64 {
                            more = true;
                            break;
                        }
                        continue;
                    }
                    read.pacing.sent(now, s.body.len());
                    out.push((s, taken.disposed, taken.unregistered, taken.identity));
                    limit -= 1;
                    if one_shot {
                        break;
                    }
                }
                Ok(None) => {
                    emptied = true;
                    break;
                }
                Err(e) => {
                    // Counted against the batch, so a flood of them cannot starve the loop.
                    errors += 1;
                    limit -= 1;
                    tracing::debug!(error = ?e, "undecodable DDS sample skipped");
                }
            }
            if limit == 0 {
                // The batch is used up (by samples or by undecodable ones): come back.
                more = true;
            }
        }
        for _ in 0..errors {
            self.count("dds_sample_undecodable");
        }
        self.readers.filter_pass_left =
            self.readers.filter_pass_left.saturating_sub(budget.spent());
        if deferred {
            // Not a fault: the reader's samples wait for the next pass.
            self.count("filter_budget_deferrals");
        }
        if over_budget > 0 {
            *self
                .dropped
                .entry("content_filter_over_budget")
                .or_default() += over_budget - 1;
            self.refused(
                "content_filter_over_budget",
                "a content filter's evaluation of a sample ran out of its step budget: the \
                 sample was treated as not matching and dropped from the read",
            );
        }
        // Over-budget samples are counted on their own.
        let filtered = filtered - over_budget;
        if filtered > 0 {
            // Not a fault: counted so a filter's effect can be seen.
            *self.dropped.entry("content_filtered").or_default() += filtered;
        }
        let sent = out.len() as u32;
        self.samples_taken += u64::from(sent);
        for (s, disposed, unregistered, identity) in out {
            // A sample one of this worker's writers wrote for a client tells its write, so
            // that a read does not deliver it twice if the write is resent.
            let origin = identity
                .is_known()
                .then(|| {
                    self.writers
                        .acks
                        .origin_of(&identity.writer, identity.sequence_number)
                })
                .flatten();
            let sample = ipc::Sample {
                identity,
                origin,
                data: std::borrow::Cow::Borrowed(&s.body),
                little_endian: s.little_endian(),
                disposed,
                unregistered,
            };
            // Kept for a successor only if it went (or waits) to the front-end, and can be
            // told from what the front-end delivered already.
            if sample.fits() && identity.is_known() {
                self.frontends
                    .recent
                    .entry(key.0)
                    .or_default()
                    .record(key, request_id, &sample);
            }
            self.reply(
                Route::object(key.0, key.1, request_id, key.2),
                Reply::Sample(sample),
            );
        }
        // Drained, once what was taken reached the front-end's queue: then every write
        // recorded so far that this reader got is the front-end's to keep.
        let handed_over = self
            .frontends
            .ports
            .get(&key.0)
            .is_none_or(|p| p.backlog.is_empty());
        let stamp = self.writers.stamp;
        let logs = &mut self.writers.take_logs;
        let mut drained_some = false;
        let ended = match self.readers.reads.get_mut(&key) {
            Some(r) => {
                if let Some(rem) = r.remaining.as_mut() {
                    *rem = rem.saturating_sub(sent);
                }
                r.taken += u64::from(sent);
                // Taken from DDS through: everything so far (emptied), or, in write order,
                // this worker's writes up to its new position.
                let through = if emptied {
                    if let (true, Some(topic)) = (r.in_write_order, &r.topic) {
                        r.position = Some(logs.sync(topic));
                    }
                    Some(stamp)
                } else {
                    match (&r.topic, r.position) {
                        (Some(topic), Some(p)) if logged_taken > 0 => {
                            let advanced = logs.advance(topic, p, logged_taken);
                            r.position = advanced.map(|(to, _)| to);
                            advanced.map(|(_, s)| s).filter(|s| *s > 0)
                        }
                        _ => None,
                    }
                };
                if let Some(through) = through {
                    drained_some = true;
                    if handed_over {
                        r.drained_through = r.drained_through.max(through);
                        if emptied {
                            r.holds = false;
                        }
                    } else {
                        r.pending_drained = r.pending_drained.max(Some(through));
                    }
                }
                // Kept with the reader, for its next read.
                match (r.in_write_order, r.position) {
                    (true, Some(p)) => {
                        self.readers.positions.insert(key, p);
                    }
                    (true, None) => {
                        self.readers.positions.remove(&key);
                    }
                    _ => {}
                }
                r.remaining == Some(0) || (r.one_shot && sent > 0)
            }
            None => false,
        };
        if drained_some && !handed_over && !ended {
            // Pumped again once the backlog is sent, to be seen drained then.
            if let Some(p) = self.frontends.ports.get_mut(&key.0) {
                p.deferred.push(key);
            }
        }
        if ended {
            self.end_read(key);
        } else if more {
            self.readers.pump_again.push(key);
        }
    }

    pub(super) fn end_read(&mut self, key: EntityKey) {
        if let Some(r) = self.readers.reads.remove(&key) {
            self.reply(
                Route::object(key.0, key.1, r.request_id, key.2),
                Reply::ReadEnded,
            );
        }
    }

    pub(super) fn expire_reads(&mut self) {
        let now = self.now;
        // Paced reads whose wait is over take their next samples.
        for (k, r) in self.readers.reads.iter_mut() {
            if r.pacing.next_at.is_some_and(|t| t <= now) {
                r.pacing.next_at = None;
                self.readers.to_pump.push(*k);
            }
        }
        let expired: Vec<EntityKey> = self
            .readers
            .reads
            .iter()
            .filter(|(_, r)| r.deadline.is_some_and(|d| d <= now))
            .map(|(k, _)| *k)
            .collect();
        for k in expired {
            self.end_read(k);
        }
    }
}
