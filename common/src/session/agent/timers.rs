//! The agent's timers: HEARTBEATs, liveliness probes and dead sessions.

use super::*;

impl<A: Endpoint> Agent<A> {
    /// Sends due HEARTBEATs and liveliness probes, and deletes the sessions of clients that
    /// stayed silent past their dead time (their objects go with them through `sink`). Only
    /// the clients whose timer fell due are looked at.
    pub fn handle_timeout(&mut self, now: Instant, sink: &mut impl OperationSink) {
        let max_period = self.config.max_heartbeat_period;
        let base_period = self.config.heartbeat_period;
        let mut out = Vec::new();
        let mut dead = Vec::new();
        let mut due_clients = Vec::new();
        while let Some(Reverse((t, key))) = self.timers.peek().copied() {
            if t > now {
                break;
            }
            self.timers.pop();
            // Only the client's live entry counts (older ones were superseded).
            if let Some(c) = self.clients.get_mut(&key).filter(|c| c.timer == Some(t)) {
                c.timer = None;
                due_clients.push(key);
            }
        }
        let probe_wait = self.config.limits.takeover_probe_wait;
        let mut grants = Vec::new();
        for key in &due_clients {
            self.drop_stale_reassemblies(now, *key);
            let Some(c) = self.clients.get_mut(key) else {
                continue;
            };
            if let Some(claim) = c.takeover.as_mut() {
                if claim.answer_due(probe_wait).is_some_and(|d| d <= now) {
                    // Answered once: by the grant, or (the endpoint spoke meanwhile) by the
                    // claimant's next attempt, which is refused.
                    if let Some(request) = claim.request.take() {
                        if c.last_heard <= claim.probed {
                            grants.push((claim.claimant, request));
                        }
                    }
                }
            }
            if let Some(dead_time) = c.dead_time {
                // Detached, the time runs from the close (it may have been silent long
                // before without being dead).
                let since = match (c.detached, c.closed_at) {
                    (true, Some(at)) => at,
                    _ => c.last_heard,
                };
                let silence = now.saturating_duration_since(since);
                if silence >= dead_time {
                    dead.push((c.key, silence, c.detached));
                    continue;
                }
                if !c.detached && c.liveliness_due().is_some_and(|d| d <= now) {
                    // GET_INFO about the agent, as a ping: a live client answers with INFO.
                    let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
                    let probe = crate::wire::GetInfoPayload {
                        base: BaseObjectRequest {
                            request_id: LIVELINESS_PROBE_ID,
                            object_id: ObjectId::AGENT,
                        },
                        info_mask: 0x02,
                    };
                    let _ = b.push(&Payload::GetInfo(probe), true);
                    out.push((c.addr, b.finish()));
                    c.last_probe = Some(now);
                }
            }
            if c.detached {
                c.heartbeat_due = None;
            } else if c.heartbeat_due.is_some_and(|d| d <= now) {
                let mut any = false;
                for s in c.reliable_out.values() {
                    if let Some(hb) = s.reliable.heartbeat() {
                        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
                        let _ = b.push(&Payload::Heartbeat(hb), true);
                        out.push((c.addr, b.finish()));
                        any = true;
                    }
                }
                if any {
                    // Unanswered so far: the next one waits twice as long, unless the
                    // client was heard since the last one. A client that keeps talking is
                    // alive and its ACKNACKs were likely lost on the way (a flooded socket
                    // drops datagrams whatever their kind): every back-off step stalls its
                    // reliable output that much longer. Measured on a flooded socket, a
                    // back-off up to 400 ms for such clients left a reliable reader's
                    // median latency at 1.1 s with 6 % of its samples lost to its DDS
                    // history; keeping the base period, 0.09-0.28 s and none lost. The cost:
                    // a client that talks but never acknowledges gets ten small HEARTBEATs a
                    // second. Only a silent client is probed less and less, its period
                    // growing up to `max_heartbeat_period`.
                    let heard = now.saturating_duration_since(c.last_heard) < c.heartbeat_interval;
                    let fixed = crate::fault::hit(crate::fault::Fault::HeartbeatFixed, 1);
                    c.heartbeat_interval = if heard || fixed {
                        base_period
                    } else {
                        (c.heartbeat_interval * 2).min(max_period)
                    };
                }
                c.heartbeat_due = any.then_some(now + c.heartbeat_interval);
            }
        }
        for key in due_clients {
            self.schedule(key);
        }
        for (a, m) in out {
            self.push_transmit(a, m);
        }
        for (claimant, request) in grants {
            tracing::debug!(client = %request.client_key, to = ?claimant, "the session's endpoint stayed silent through the probe: the session moves");
            self.create_client(now, claimant, &request, sink);
        }
        for (key, silence, detached) in dead {
            if detached {
                tracing::warn!(client = %key, gone_ms = silence.as_millis() as u64, "client's connection closed and it did not come back within the grace period; deleting its session");
                self.count_drop("detached_expired");
            } else {
                tracing::warn!(client = %key, silent_ms = silence.as_millis() as u64, "client silent past its dead time; deleting its session");
                self.count_drop("client_dead");
            }
            self.remove_client(now, key, sink);
        }
    }
}
