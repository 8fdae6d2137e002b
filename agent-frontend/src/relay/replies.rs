//! The worker's replies applied: results to the clients that wait for them, samples to the
//! reads they belong to (once each, across worker restarts), progress to the window and the
//! retention, and reads paused for clients that do not keep up.

use std::time::Instant;

use xrce_common::fault::{self, Fault};
use xrce_common::session::agent::{Agent, DataReply, Endpoint};
use xrce_common::wire::sample::sample_state;
use xrce_common::wire::{data_format, object_kind, status, stream_id, BaseObjectRequest, ObjectId};
use xrce_ipc::{Reply, ReplyMessage, Request};

use super::queue::{Awaited, PendingKind};
use super::{message, Link, Relay, PAUSE_READ_AT};

impl<L: Link> Relay<L> {
    /// Handles one message of the announce service: a new worker generation is replayed to.
    pub fn handle_announcement(&mut self, m: &[u8]) {
        match ReplyMessage::decode(m) {
            Ok(ReplyMessage {
                route,
                reply: Reply::WorkerHello,
            }) if Some(route.generation) != self.generation => {
                self.new_generation(route.generation);
            }
            Ok(_) => {}
            Err(e) => {
                self.stats.ipc_dropped += 1;
                tracing::warn!(error = %e, "bad announcement");
            }
        }
    }

    /// After a batch of replies: releases settled writes and hands the decided replies to
    /// the session core.
    pub fn after_replies<A: Endpoint>(&mut self, now: Instant, agent: &mut Agent<A>) {
        self.retention.settle(now, &mut self.stats);
        self.apply_replies(now, agent);
    }

    /// Handles one message of this front-end's reply service: a worker's hello, the result
    /// of an operation, a sample for a client's read, progress. Results for clients go to
    /// `agent` (samples at once; STATUS replies with [`Relay::apply_replies`]).
    pub fn handle_reply<A: Endpoint>(&mut self, now: Instant, m: &[u8], agent: &mut Agent<A>) {
        let ReplyMessage { route: h, reply } = match ReplyMessage::decode(m) {
            Ok(v) => v,
            Err(e) => {
                self.stats.ipc_dropped += 1;
                return tracing::warn!(error = %e, "bad reply from the worker");
            }
        };
        if h.incarnation != 0 && h.incarnation != self.incarnation {
            // Meant for the process this one took over from (its operation numbers mean
            // something else here).
            self.stats.predecessor_replies += 1;
            return;
        }
        if let Reply::Executed(position) = reply {
            // Before the hello it precedes, whatever generation this process knows yet.
            if !fault::hit(Fault::ExecutedIgnored, 1) {
                agent.skip_executed(h.client_key, position);
            }
            return;
        }
        if reply == Reply::WorkerHello {
            // Its Executed replies came before it: client messages can be taken again.
            self.awaiting_executed = false;
            if Some(h.generation) != self.generation {
                self.new_generation(h.generation);
            }
            return;
        }
        if Some(h.generation) != self.generation {
            // From a worker generation we no longer serve (or have not seen announced yet).
            self.stats.ipc_dropped += 1;
            return;
        }
        let req = BaseObjectRequest {
            request_id: h.request_id,
            object_id: h.object_id,
        };
        match reply {
            Reply::WorkerHello | Reply::Executed(_) => {}
            Reply::Progress {
                executed,
                acknowledged,
            } => {
                self.processed = self.processed.max(h.op_seq);
                let executed = executed.min(h.op_seq);
                self.retention.progress(now, executed, acknowledged);
            }
            Reply::Status { result, replay } => {
                let code = result.status;
                let waited = self.pending.remove(&h.op_seq);
                if replay && result.implementation_status == xrce_ipc::REPLAY_REFUSED {
                    self.sessions_to_end.insert(h.client_key);
                }
                if !status::is_ok(code) {
                    if let Some(g) = self.graphs.get_mut(&h.client_key) {
                        self.objects_changed.insert(h.client_key);
                        self.reads_changed.insert(h.client_key);
                        if waited.is_some_and(|w| w.2 == PendingKind::Create) {
                            let removed = g.remove(h.object_id);
                            self.object_budget.removed(h.client_key, &removed);
                            self.delivered_origins
                                .forget_objects(h.client_key, &removed);
                        } else if g
                            .read_mut(h.object_id)
                            .is_some_and(|r| r.request_id == h.request_id)
                        {
                            // The read itself failed (not, say, a write to the same
                            // requester or replier).
                            g.end_read(h.object_id);
                        }
                    }
                }
                if waited.is_some() || (!replay && !status::is_ok(code)) {
                    self.replies_out.push((h.client_key, req, result));
                } else if !status::is_ok(code) {
                    tracing::warn!(client = %h.client_key, object = ?h.object_id, status = code, "replayed operation failed on the new worker");
                }
            }
            Reply::Sample(sample) => {
                let identity = sample.identity;
                // A sample this read delivered before the worker restarted (offered again
                // by a writer that outlived the worker) is not delivered twice.
                let read = self
                    .graphs
                    .get_mut(&h.client_key)
                    .and_then(|g| g.read_mut(h.object_id));
                if let Some(a) = &read {
                    if identity.is_known()
                        && a.marks
                            .already_delivered(&identity.writer, identity.sequence_number)
                    {
                        self.stats.samples_already_delivered += 1;
                        return;
                    }
                    // A write resent to a new worker, whose predecessor had delivered it (it
                    // died before the write's publisher heard that it was taken).
                    if sample.origin.is_some_and(|o| {
                        o.resent
                            && !fault::hit(Fault::OriginIgnored, 1)
                            && self
                                .delivered_origins
                                .contains(h.client_key, h.object_id, &o.write)
                    }) {
                        self.stats.samples_already_delivered += 1;
                        self.stats.resent_samples_already_delivered += 1;
                        return;
                    }
                }
                // A read's deliveries are remembered by their writes' origins.
                let of_a_read = read.is_some();
                // The read's stream and format; a sample that overtook the end of its read
                // goes out plain on the built-in reliable stream.
                let (stream, format, sequence_number) =
                    read.map_or((stream_id::BUILTIN_RELIABLE, data_format::DATA, 0), |a| {
                        a.delivered = a.delivered.wrapping_add(1);
                        if identity.is_known() {
                            a.marks.record(identity.writer, identity.sequence_number);
                        }
                        (a.spec.preferred_stream_id, a.spec.data_format, a.delivered)
                    });
                let mut state = 0;
                if sample.disposed {
                    state |= sample_state::INSTANCE_DISPOSED;
                }
                if sample.unregistered {
                    state |= sample_state::INSTANCE_UNREGISTERED;
                }
                if state != 0 && matches!(format, data_format::DATA | data_format::DATA_SEQ) {
                    // Without a SampleInfo the client could not tell a disposed instance's
                    // key from a sample: instance ends reach only SAMPLE-format reads.
                    self.stats.instance_ends_skipped += 1;
                    return;
                }
                let reply = DataReply {
                    request: req,
                    format,
                    sample: &sample.data,
                    little_endian: sample.little_endian,
                    state,
                    sequence_number,
                };
                let mut sent = false;
                for _ in 0..fault_copies(h.object_id) {
                    match agent.send_data(now, h.client_key, stream, reply) {
                        Ok(_) => sent = true,
                        Err(e) => {
                            // A full output queue is counted by the core (output_queue_full).
                            if e != xrce_common::session::agent::SendError::QueueFull {
                                self.stats.samples_dropped += 1;
                            }
                            tracing::debug!(client = %h.client_key, error = %e, "sample not delivered");
                        }
                    }
                }
                // Remembered once the client's session holds it: a resend of a sample it
                // could not take is delivered.
                if let (true, true, Some(o)) = (sent, of_a_read, sample.origin) {
                    self.delivered_origins
                        .record(h.client_key, h.object_id, o.write);
                }
                let congested = agent
                    .output_backlog(h.client_key, stream)
                    .is_some_and(|(m, b)| m >= PAUSE_READ_AT.0 || b >= PAUSE_READ_AT.1);
                let key = (h.client_key, h.object_id);
                if congested && !self.paused.contains_key(&key) {
                    self.paused.insert(key, stream);
                    self.stats.reads_paused += 1;
                    tracing::debug!(client = %h.client_key, reader = ?h.object_id, "read paused: the client is not keeping up");
                    let pause = message(self.frontend_id, h.client_key, req, Request::PauseRead);
                    self.submit(pause, false, Awaited::No);
                }
            }
            Reply::WriterMatched { readers } => {
                if let Some(o) = self
                    .graphs
                    .get_mut(&h.client_key)
                    .and_then(|g| g.get_mut(h.object_id))
                {
                    o.readers_matched = readers;
                }
            }
            Reply::ReadEnded => {
                self.paused.remove(&(h.client_key, h.object_id));
                if let Some(g) = self.graphs.get_mut(&h.client_key) {
                    let same = g
                        .reads()
                        .any(|(r, a)| *r == h.object_id && a.request_id == h.request_id);
                    if same {
                        g.end_read(h.object_id);
                        self.reads_changed.insert(h.client_key);
                    }
                }
            }
        }
    }
}

/// How many times a sample from the worker goes to its client: once, unless a fault injected
/// on purpose (`xrce_common::fault`, test builds only) drops or repeats it.
fn fault_copies(reader: ObjectId) -> usize {
    if reader.kind() == object_kind::REQUESTER && fault::hit(Fault::ReplyDuplicate, 1) {
        return 2;
    }
    if fault::hit(Fault::ClientDuplicate, 10) {
        return 2;
    }
    if fault::hit(Fault::ClientDrop, 10) {
        return 0;
    }
    1
}
