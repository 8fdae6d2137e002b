//! The replay to a new worker generation: what makes sessions survive a worker restart.

use std::collections::HashMap;

use xrce_common::fault::{self, Fault};
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::{status, BaseObjectRequest, ClientKey, ObjectId, RequestId, ResultStatus};
use xrce_ipc::{Request, RequestMessage, Route};

use super::queue::{Awaited, OwnedOp, PendingKind};
use super::{message, Link, Relay};

impl<L: Link> Relay<L> {
    /// A new worker generation serves: the replay to it (this process's hello, sessions
    /// that ended meanwhile, every client's objects in creation order and reads, the end of
    /// the replay, the retained writes, then the writes that waited) goes before anything
    /// new; what clients waited for is answered by it or here.
    pub(super) fn new_generation(&mut self, generation: u32) {
        let first = self.generation.is_none();
        tracing::info!(
            generation,
            first,
            clients = self.graphs.len(),
            "worker generation seen; replaying sessions"
        );
        self.generation = Some(generation);
        self.generation_changed = true;
        self.processed = self.next_seq - 1;
        self.stats.replays += 1;
        // The new worker starts every read unpaused.
        self.paused.clear();
        let old_outbox = self.outbox.take();
        // Best-effort writes that waited for the share of a worker now gone are stale: they
        // are dropped, as they would have been without the wait, and the new worker starts
        // without a shedding hold.
        self.stats.ops_dropped += self.best_effort_waiting.clear() as u64;
        // Operations a client still waits for: answered by the replay, or (deletes) now.
        let mut awaited: HashMap<(ClientKey, ObjectId), RequestId> = HashMap::new();
        // Writes of spec-dialect clients waiting for their STATUS.
        let mut awaited_writes: HashMap<u64, (ClientKey, BaseObjectRequest)> = HashMap::new();
        for (seq, (client, req, kind)) in self.pending.drain() {
            match kind {
                PendingKind::Create => {
                    awaited.insert((client, req.object_id), req.request_id);
                }
                PendingKind::Delete => self.replies_out.push((client, req, ResultStatus::OK)),
                PendingKind::Write => {
                    awaited_writes.insert(seq, (client, req));
                }
                PendingKind::Other => {}
            }
        }
        let mut writes = Vec::new();
        // Sessions that ended before this worker was seen: a worker that kept their entities
        // for this front-end (it took over from a predecessor) must not hand them to a
        // session created again with the same key.
        let mut deletes = Vec::new();
        for op in old_outbox {
            let r = op.message.route;
            match (&op.message.request, op.awaited) {
                (Request::Write { .. }, _) => writes.push(op),
                (Request::DeleteClient, _) => deletes.push(op),
                (Request::Create { .. }, Awaited::Yes) => {
                    awaited.insert((r.client_key, r.object_id), r.request_id);
                }
                (Request::Delete, Awaited::Yes) => self.replies_out.push((
                    r.client_key,
                    BaseObjectRequest {
                        request_id: r.request_id,
                        object_id: r.object_id,
                    },
                    ResultStatus::OK,
                )),
                _ => {}
            }
        }
        let fe = self.frontend_id;
        let internal = move |request: Request<'static>| OwnedOp {
            message: RequestMessage::new(Route::frontend(fe), request),
            retain: false,
            awaited: Awaited::No,
        };
        self.outbox.push_back(internal(Request::FrontendHello));
        self.outbox.extend(deletes);
        for (client, graph) in &self.graphs {
            for o in graph.objects() {
                let mut body = Vec::new();
                o.variant.encode(&mut CdrWriter::new(&mut body, true));
                let req = BaseObjectRequest {
                    request_id: o.request_id,
                    object_id: o.object_id,
                };
                let waited = awaited.get(&(*client, o.object_id)) == Some(&o.request_id);
                let create = Request::Create {
                    description: body.into(),
                    client_little_endian: o.little_endian,
                    replay: !waited,
                    readers_matched: o.readers_matched,
                };
                self.outbox.push_back(OwnedOp {
                    message: message(self.frontend_id, *client, req, create),
                    retain: false,
                    awaited: if waited { Awaited::Yes } else { Awaited::No },
                });
            }
            for (reader, read) in graph.reads() {
                if !first && fault::once(Fault::ReplaySkip) {
                    continue;
                }
                let mut body = Vec::new();
                read.spec.encode(&mut CdrWriter::new(&mut body, true));
                let req = BaseObjectRequest {
                    request_id: read.request_id,
                    object_id: *reader,
                };
                let read = Request::Read {
                    spec: body.into(),
                    replay: true,
                };
                self.outbox.push_back(OwnedOp {
                    message: message(self.frontend_id, *client, req, read),
                    retain: false,
                    awaited: Awaited::No,
                });
            }
        }
        // A worker that kept this front-end's entities (this process took over from a
        // predecessor) removes those the replay did not take back.
        self.outbox.push_back(internal(Request::ReplayDone));
        for r in self.retention.take() {
            self.stats.writes_resent += 1;
            let waited = awaited_writes.remove(&r.seq).is_some();
            let mut message = r.message;
            if let Request::Write { resend_of, .. } = &mut message.request {
                // Its origin stays that of its first send (a write resent twice keeps it), so
                // that subscribers tell it from a write they did not deliver.
                resend_of.get_or_insert(r.seq);
            }
            self.outbox.push_back(OwnedOp {
                message,
                retain: true,
                awaited: if waited { Awaited::Yes } else { Awaited::No },
            });
        }
        // Best-effort writes the dead worker may not have published: say so.
        for (client, req) in awaited_writes.into_values() {
            self.replies_out
                .push((client, req, ResultStatus::new(status::ERR_DDS_ERROR)));
        }
        self.outbox.extend(writes);
    }
}
