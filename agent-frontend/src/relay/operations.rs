//! The session core's operations taken: the client object mirror (creation modes, quotas,
//! the object-description budget, GET_INFO answered here), writes routed by their stream's
//! reliability (best-effort writes wait for their share of the window, or are dropped), and
//! the rest handed to the worker.

use std::time::{Duration, Instant};

use xrce_common::session::agent::{Operation, OperationSink};
use xrce_common::session::graph::{ActiveRead, CreateDecision, GraphObject, ObjectGraph};
use xrce_common::wire::cdr::CdrWriter;
use xrce_common::wire::sample::is_defined_format;
use xrce_common::wire::{
    status, stream_id, BaseObjectRequest, ClientKey, Dialect, ObjectId, ResultStatus,
};
use xrce_ipc::{Encode, Request};

use super::queue::{Awaited, OwnedOp, Weighed};
use super::{
    message, BestEffortRoute, Link, Relay, BEST_EFFORT_OUTBOX_MAX, BEST_EFFORT_RESERVE,
    HAND_OVER_HEADROOM,
};
use crate::waiting_writes::Room;
use xrce_ipc::IN_FLIGHT_WINDOW;

/// GET_INFO mask bit asking for the object's configuration.
const INFO_CONFIGURATION: u32 = 0x01;

impl<L: Link> Relay<L> {
    /// Takes one operation of the session core: the client object mirror decides creations
    /// and answers GET_INFO itself; what the worker must do goes to it.
    pub(super) fn take_operation(&mut self, now: Instant, op: Operation<'_>) {
        let fe = self.frontend_id;
        match op {
            Operation::ClientCreated { client, origin } => {
                self.graphs.insert(client, ObjectGraph::default());
                self.delivered_origins.forget_client(client);
                self.object_budget.client_created(client, origin);
                self.objects_changed.insert(client);
            }
            Operation::ClientDeleted { client } => {
                self.graphs.remove(&client);
                self.delivered_origins.forget_client(client);
                self.object_budget.client_deleted(client);
                self.drop_waiting_writes(client, None);
                let delete = message(
                    fe,
                    client,
                    BaseObjectRequest::default(),
                    Request::DeleteClient,
                );
                self.submit(delete, false, Awaited::No);
            }
            Operation::Create {
                client,
                create,
                little_endian,
            } => {
                self.objects_changed.insert(client);
                let graph = self.graphs.entry(client).or_default();
                let id = create.base.object_id;
                let max = self.max_objects;
                match graph.decide_create(
                    id,
                    &create.variant,
                    little_endian,
                    create.reuse,
                    create.replace,
                    max,
                ) {
                    CreateDecision::Reply(code) => {
                        if code == status::ERR_RESOURCES && graph.len() >= max {
                            self.stats.objects_over_quota += 1;
                            if self.stats.objects_over_quota.is_power_of_two() {
                                tracing::warn!(%client, objects = graph.len(), quota = max, refused = self.stats.objects_over_quota, "CREATE refused: the client has its quota of objects (--max-objects-per-client)");
                            }
                        }
                        self.replies_out
                            .push((client, create.base, ResultStatus::new(code)))
                    }
                    decision => {
                        let mut body = Vec::new();
                        create.variant.encode(&mut CdrWriter::new(&mut body, true));
                        if !self.object_budget.admit(client, id, body.len()) {
                            self.stats.objects_over_budget += 1;
                            let (held, pool) = self.object_budget.held();
                            if self.object_budget_episodes.bite(now, "objects").is_some() {
                                tracing::warn!(%client, bytes = body.len(), held, pool, refused = self.stats.objects_over_budget, "CREATE refused with STATUS_ERR_RESOURCES: object descriptions over the client's share of the memory budget (--memory-budget; logged once per episode)");
                            }
                            self.replies_out.push((
                                client,
                                create.base,
                                ResultStatus::new(status::ERR_RESOURCES),
                            ));
                            return;
                        }
                        let Some(graph) = self.graphs.get_mut(&client) else {
                            return;
                        };
                        let mut replaced = if decision == CreateDecision::Replace {
                            graph.remove(id)
                        } else {
                            Vec::new()
                        };
                        let children: Vec<ObjectId> =
                            replaced.iter().copied().filter(|r| *r != id).collect();
                        self.object_budget.removed(client, &children);
                        // A reader created again is another read's.
                        self.delivered_origins.forget_objects(client, &replaced);
                        // Writes a client sent to the id before it existed must not go to
                        // the new object either.
                        replaced.push(id);
                        graph.insert(GraphObject {
                            object_id: id,
                            request_id: create.base.request_id,
                            variant: create.variant.clone(),
                            little_endian,
                            readers_matched: 0,
                        });
                        if !self.best_effort_waiting.is_empty() {
                            self.drop_waiting_writes(client, Some(&replaced));
                        }
                        let request = Request::Create {
                            description: body.into(),
                            client_little_endian: little_endian,
                            replay: false,
                            readers_matched: 0,
                        };
                        let m = message(fe, client, create.base, request);
                        self.submit(m, false, Awaited::Yes);
                    }
                }
            }
            Operation::Delete { client, request } => {
                let removed = self
                    .graphs
                    .get_mut(&client)
                    .map(|g| g.remove(request.object_id))
                    .unwrap_or_default();
                self.object_budget.removed(client, &removed);
                self.delivered_origins.forget_objects(client, &removed);
                self.objects_changed.insert(client);
                if !removed.is_empty() {
                    self.drop_waiting_writes(client, Some(&removed));
                    self.submit(
                        message(fe, client, request, Request::Delete),
                        false,
                        Awaited::Yes,
                    );
                } else {
                    self.replies_out.push((
                        client,
                        request,
                        ResultStatus::new(status::ERR_UNKNOWN_REFERENCE),
                    ));
                }
            }
            Operation::Write {
                client,
                stream_id: stream,
                position,
                data,
                little_endian,
                dialect,
            } => {
                if !is_defined_format(data.format) {
                    tracing::debug!(%client, format = data.format, "WRITE_DATA with an undefined DataFormat");
                    self.replies_out.push((
                        client,
                        data.base,
                        ResultStatus::new(status::ERR_INVALID_DATA),
                    ));
                    return;
                }
                // The worker splits the samples (it knows the types) and, for spec-dialect
                // clients, answers every write with a STATUS.
                let status_requested = dialect == Dialect::Spec;
                let awaited = if status_requested {
                    Awaited::Yes
                } else {
                    Awaited::No
                };
                let write = Request::Write {
                    data: data.data.into(),
                    data_format: data.format,
                    little_endian,
                    dialect,
                    status_requested,
                    position,
                    received_us: self.received_us(now),
                    resend_of: None,
                };
                let mut m = message(fe, client, data.base, write);
                let reliable = stream_id::is_reliable(stream);
                let route = if reliable {
                    Some(BestEffortRoute::Now)
                } else {
                    self.best_effort_route(now, client, m.encoded_len())
                };
                let Some(route) = route else {
                    // Best-effort data is not held back by flow control: drop it, counted.
                    self.stats.ops_dropped += 1;
                    if self.stats.ops_dropped.is_power_of_two() {
                        tracing::warn!(
                            client = %client,
                            dropped = self.stats.ops_dropped,
                            in_flight = self.in_flight(),
                            outbox = self.outbox.len(),
                            retained = self.retention.len(),
                            waiting = self.best_effort_waiting.len(),
                            "best-effort write dropped: the worker has not taken the \
                             operations sent before it (further drops are counted)"
                        );
                    }
                    return;
                };
                match route {
                    BestEffortRoute::Now => self.submit(m, reliable, awaited),
                    BestEffortRoute::Wait => {
                        m.route.incarnation = self.incarnation;
                        let op = OwnedOp {
                            message: m.into_owned(),
                            retain: false,
                            awaited,
                        };
                        let weight = op.weight();
                        self.best_effort_waiting.push(client, op, weight);
                    }
                }
            }
            Operation::GetInfo {
                client,
                request,
                info_mask,
            } => {
                let object = self
                    .graphs
                    .get(&client)
                    .and_then(|g| g.get(request.object_id));
                let result = if object.is_some() {
                    status::OK
                } else {
                    status::ERR_UNKNOWN_REFERENCE
                };
                let config = object
                    .filter(|_| info_mask & INFO_CONFIGURATION != 0)
                    .map(|o| o.variant.clone());
                self.infos_out
                    .push((client, request, ResultStatus::new(result), config));
            }
            Operation::Read {
                client,
                request,
                spec,
            } => {
                let known = self
                    .graphs
                    .get(&client)
                    .is_some_and(|g| g.get(request.object_id).is_some());
                if !known {
                    self.replies_out.push((
                        client,
                        request,
                        ResultStatus::new(status::ERR_UNKNOWN_REFERENCE),
                    ));
                    return;
                }
                // A new read starts unpaused on both sides.
                self.paused.remove(&(client, request.object_id));
                if let Some(g) = self.graphs.get_mut(&client) {
                    g.set_read(
                        request.object_id,
                        ActiveRead {
                            request_id: request.request_id,
                            spec: spec.clone(),
                            delivered: 0,
                            marks: Default::default(),
                        },
                    );
                }
                let mut body = Vec::new();
                spec.encode(&mut CdrWriter::new(&mut body, true));
                let read = Request::Read {
                    spec: body.into(),
                    replay: false,
                };
                self.submit(message(fe, client, request, read), false, Awaited::No);
            }
        }
    }

    /// Drops the waiting best-effort writes of `client` (to `objects` only, if given): an
    /// operation sent now (a delete, a create, the end of the session) would otherwise reach
    /// the worker before them, and they would then go to no writer or to another one. They
    /// get no STATUS, as no dropped best-effort write does.
    pub(super) fn drop_waiting_writes(&mut self, client: ClientKey, objects: Option<&[ObjectId]>) {
        let dropped = match objects {
            None => self.best_effort_waiting.remove_client(client),
            Some(ids) => self
                .best_effort_waiting
                .retain_of(client, |op| !ids.contains(&op.message.route.object_id)),
        };
        self.stats.ops_dropped += dropped as u64;
    }

    /// How long a client's best-effort writes are shed, not queued, after it overflowed
    /// their waiting queue (default `BEST_EFFORT_SHED_HOLD`).
    pub fn set_best_effort_shed_hold(&mut self, hold: Duration) {
        self.best_effort_waiting.set_hold(hold);
    }

    /// Whether the window has room for a best-effort write beyond the share kept for
    /// reliable and control operations ([`BEST_EFFORT_RESERVE`]).
    pub(super) fn best_effort_share_free(&self) -> bool {
        self.can_send_now()
            && self.in_flight() + HAND_OVER_HEADROOM + BEST_EFFORT_RESERVE < IN_FLIGHT_WINDOW
    }

    /// Where a best-effort write of `client` weighing `weight` goes now, if anywhere: as
    /// [`OperationSink::has_room`], less the share kept for reliable and control operations
    /// ([`BEST_EFFORT_RESERVE`], [`BEST_EFFORT_OUTBOX_MAX`]), plus, in hand-over mode, a
    /// short wait unless the client is shed for overflowing it (`BEST_EFFORT_WAITING_MAX`,
    /// `BEST_EFFORT_SHED_HOLD`).
    pub(super) fn best_effort_route(
        &mut self,
        now: Instant,
        client: ClientKey,
        weight: usize,
    ) -> Option<BestEffortRoute> {
        if !self.retention.has_room() {
            return None;
        }
        if self.hand_over_at_once && self.generation.is_some() {
            if self.outbox.is_empty()
                && self.best_effort_waiting.is_empty()
                && self.best_effort_share_free()
            {
                return Some(BestEffortRoute::Now);
            }
            match self.best_effort_waiting.make_room(client, weight, now) {
                Room::Yes {
                    evicted,
                    holds_started,
                } => {
                    self.stats.ops_dropped += evicted as u64;
                    self.stats.best_effort_sheds += holds_started as u64;
                    Some(BestEffortRoute::Wait)
                }
                Room::No { hold_started } => {
                    if hold_started {
                        self.stats.best_effort_sheds += 1;
                        tracing::debug!(
                            %client,
                            waiting = self.best_effort_waiting.len(),
                            of_client = self.best_effort_waiting.len_of(client),
                            "a client's best-effort writes overflow their waiting queue: shedding, not queueing, its writes for a while"
                        );
                    }
                    None
                }
            }
        } else {
            (self.has_room() && self.outbox.len() < BEST_EFFORT_OUTBOX_MAX)
                .then_some(BestEffortRoute::Now)
        }
    }
}
