//! The reply ports: what goes back to each front-end (replies, samples, progress), the
//! backlog of a congested one, and front-ends whose process is gone.

use super::*;

pub(super) struct FrontendPort {
    /// The front-end process served (see [`Route::incarnation`]).
    pub(super) incarnation: u16,
    pub(super) processed: u64,
    pub(super) dirty: bool,
    /// Replies the front-end's full queue refused, oldest first (sent before anything new).
    pub(super) backlog: std::collections::VecDeque<Vec<u8>>,
    /// Bytes in `backlog`.
    pub(super) backlog_bytes: usize,
    /// Readers not drained while the front-end is congested; pumped once it has room.
    pub(super) deferred: Turns<EntityKey>,
    /// When the front-end last took a message (a dead one takes none: back off).
    pub(super) last_delivery: Instant,
    /// Messages were published since the front-end was last woken.
    pub(super) unnotified: bool,
    /// The front-end is woken for the next progress message: an operation it sent without
    /// [`RequestMessage::progress_can_wait`] was processed, or DDS readers acknowledged writes.
    /// Kept while execution stops short of what was processed (held writes), so the progress
    /// that finally covers them wakes it too.
    pub(super) progress_wake_owed: bool,
}

/// Most replies held for one congested front-end; beyond, the oldest are dropped (counted).
/// Samples stop being taken from DDS readers while a front-end is congested, so this only
/// fills if a front-end stops reading altogether.
pub(super) const BACKLOG_MAX: usize = 4096;

/// Bytes of refused replies kept per front-end (samples reach 1 MiB each).
pub(super) const BACKLOG_MAX_BYTES: usize = 64 << 20;

impl<L: WorkerLink> Worker<L> {
    /// Deletes the entities of front-ends whose process has been gone for the grace period
    /// (a gateway front-end stopped for good); a restarted one says hello within it and
    /// takes over, as before. Dead nodes' shared-memory resources are removed on the way.
    pub(super) fn watch_frontends(&mut self) {
        let now = self.now;
        if now < self.next_census {
            return;
        }
        self.next_census = now + CENSUS_PERIOD;
        let served: HashSet<u32> = self.entities.clients().map(|(fe, _)| *fe).collect();
        if served.is_empty() && self.frontends.orphaned.is_empty() {
            return;
        }
        let gone = self.link.gone(&served);
        self.frontends.orphaned.retain(|fe, _| served.contains(fe));
        for fe in served {
            if !gone.contains(&fe) {
                if self.frontends.orphaned.remove(&fe).is_some() {
                    tracing::info!(frontend = fe, "front-end is back");
                }
                continue;
            }
            let grace = self.config.frontend_grace;
            let since = *self.frontends.orphaned.entry(fe).or_insert_with(|| {
                tracing::warn!(
                    frontend = fe,
                    grace_s = grace.as_secs_f64(),
                    "front-end process gone; its clients' entities are kept for it to come back"
                );
                now
            });
            // A replay from a front-end that is gone did not crash this worker.
            if self.replay_guard.end(fe) {
                self.link.mark_replay(fe, None);
            }
            if now.saturating_duration_since(since) >= grace {
                let clients = self.entities.clients().filter(|(f, _)| *f == fe).count();
                tracing::warn!(
                    frontend = fe,
                    clients,
                    "front-end did not come back; deleting its clients' entities"
                );
                self.remove_where(|c| c.0 == fe);
                self.frontends.adoption.forget(fe);
                self.frontends.recent.remove(&fe);
                self.frontends.executed.forget_frontend(fe);
                self.frontends.ports.remove(&fe);
                self.link.forget(fe);
                self.frontends.greeted.retain(|(f, _)| *f != fe);
                self.frontends.orphaned.remove(&fe);
                self.count("frontend_gone");
            }
        }
    }

    /// What the worker keeps for a front-end, made on first use.
    pub(super) fn port(&mut self, frontend: u32) -> &mut FrontendPort {
        self.frontends.port(frontend, self.now)
    }

    /// Sends a reply to its front-end (encoded in place in shared memory when the
    /// front-end's queue has room), or queues it behind earlier refused ones.
    pub(super) fn reply(&mut self, mut route: Route, reply: Reply<'_>) {
        route.generation = self.generation;
        let incarnation = self
            .frontends
            .ports
            .get(&route.frontend_id)
            .map_or(0, |p| p.incarnation);
        if route.incarnation == 0 {
            route.incarnation = incarnation;
        }
        let m = ReplyMessage::new(route, reply);
        let len = m.encoded_len() - ipc::HEADER_LEN;
        if len > ipc::MAX_BODY {
            tracing::warn!(frontend = route.frontend_id, client = %route.client_key, len, "sample too large for the front-end link; dropped");
            return self.count("sample_too_large");
        }
        let now = self.now;
        let port = self.frontends.port(route.frontend_id, now);
        port.dirty = true;
        if port.backlog.is_empty() {
            match self.link.send(route.frontend_id, &m) {
                Ok(true) => {
                    port.last_delivery = now;
                    port.unnotified = true;
                    return;
                }
                // Its queue is full: woken, it drains it and takes the backlog.
                Ok(false) => port.unnotified = true,
                Err(e @ LinkError::Unreachable { .. }) => {
                    // Nothing can reach it (tried again with the next reply): no progress
                    // owed, no pass asked for it.
                    port.dirty = false;
                    tracing::warn!(error = %e, "reply lost");
                    return self.count("reply_send_failed");
                }
                Err(e) => tracing::debug!(error = %e, "reply send failed; queued"),
            }
        }
        let m = m.encode();
        let mut overflow = false;
        while !port.backlog.is_empty()
            && (port.backlog.len() >= BACKLOG_MAX
                || port.backlog_bytes + m.len() > BACKLOG_MAX_BYTES)
        {
            if let Some(old) = port.backlog.pop_front() {
                port.backlog_bytes -= old.len();
            }
            overflow = true;
        }
        port.backlog_bytes += m.len();
        port.backlog.push_back(m);
        if overflow {
            self.count("reply_backlog_overflow");
        }
    }

    /// Answers request `what` on `route` (a replayed one if `replay`) with its result.
    pub(super) fn status(
        &mut self,
        route: Route,
        what: &'static str,
        replay: bool,
        result: Result<(), OpError>,
    ) {
        let code = match &result {
            Ok(()) => status::OK,
            // Refusals of the worker's bounds (resources, denied) were counted and logged
            // once per episode where they were decided: a client causes them at will.
            Err(e) if e.is_refusal() => {
                tracing::debug!(client = %route.client_key, object = ?route.object_id, kind = what, status = e.status(), "{e}");
                e.status()
            }
            Err(e) => {
                tracing::warn!(client = %route.client_key, object = ?route.object_id, kind = what, status = e.status(), "{e}");
                e.status()
            }
        };
        self.reply(
            route,
            Reply::Status {
                result: ResultStatus::new(code),
                replay,
            },
        );
    }

    /// Sends refused replies again, then progress; wakes every front-end that got something.
    /// Failures are logged and retried on the next pass; they never stop the worker.
    pub(super) fn flush(&mut self) {
        let generation = self.generation;
        let held = self.oldest_held();
        let now = self.now;
        // The worker's own readers of each topic drained up to (counted once per poll).
        let mut drained = None;
        let (readers, orphaned) = (&self.readers, &self.frontends.orphaned);
        let (moved, all) = self.writers.acks.poll(now, |w| {
            drained
                .get_or_insert_with(|| readers.drained_through(orphaned))
                .get(&w.topic)
                .map_or(u64::MAX, |d| d.through)
        });
        if !self.writers.retiring.is_empty() {
            self.writers.prune_retiring(now);
        }
        for (fe, p) in self.frontends.ports.iter_mut() {
            if all || moved.contains(fe) {
                p.dirty = true;
                p.progress_wake_owed = true;
            }
        }
        // Computed once, and only when a progress message goes out (the loop runs per sample).
        let acks = &self.writers.acks;
        let link = &mut self.link;
        let mut outstanding: Option<HashMap<u32, u64>> = None;
        for (fe, p) in self.frontends.ports.iter_mut() {
            // Something the front-end must be woken for went out.
            let mut wake = false;
            let mut sent = false;
            while let Some(m) = p.backlog.front() {
                match link.send_encoded(*fe, m) {
                    Ok(true) => {}
                    Ok(false) => break,
                    Err(e) => {
                        // Not deliverable at all (it cannot happen for messages within
                        // MAX_BODY): drop it rather than block the front-end for ever.
                        tracing::warn!(frontend = fe, error = %e, "reply dropped");
                    }
                }
                if let Some(m) = p.backlog.pop_front() {
                    p.backlog_bytes -= m.len();
                }
                sent = true;
                wake = true;
            }
            if p.backlog.is_empty() {
                // What the reads waiting for it took when they emptied their readers is in
                // the front-end's queue now: drained that far, paused meanwhile or not.
                for key in p.deferred.iter() {
                    if let Some(r) = self.readers.reads.get_mut(key) {
                        if let Some(stamp) = r.pending_drained.take() {
                            r.drained_through = r.drained_through.max(stamp);
                        }
                    }
                }
                self.readers.to_pump.append(&mut p.deferred);
            }
            // Held writes left the queue but are not executed yet: execution stops just
            // before the oldest.
            let executed = held.get(fe).map_or(p.processed, |oldest| {
                p.processed.min(oldest.saturating_sub(1))
            });
            if p.dirty && p.backlog.is_empty() {
                let route = Route {
                    generation,
                    incarnation: p.incarnation,
                    op_seq: p.processed,
                    ..Route::frontend(*fe)
                };
                // Acknowledged by every matched reliable reader: up to just before the
                // oldest write still outstanding.
                let acknowledged = outstanding
                    .get_or_insert_with(|| acks.oldest_outstanding())
                    .get(fe)
                    .map_or(executed, |oldest| executed.min(oldest.saturating_sub(1)));
                let progress = ReplyMessage::new(
                    route,
                    Reply::Progress {
                        executed,
                        acknowledged,
                    },
                );
                match link.send(*fe, &progress) {
                    Ok(true) => {
                        p.dirty = false;
                        sent = true;
                        if p.progress_wake_owed {
                            wake = true;
                            p.progress_wake_owed = executed < p.processed;
                        }
                    }
                    // Full: tried again next pass.
                    Ok(false) => {}
                    // Its channel cannot be opened: the next reply tries again; until then
                    // no pass is asked for it.
                    Err(LinkError::Unreachable { .. }) => p.dirty = false,
                    Err(e) => tracing::debug!(frontend = fe, error = %e, "progress not sent"),
                }
            }
            if sent {
                p.last_delivery = now;
            }
            // Also when only replies sent directly went out (a full queue may have refused
            // the progress message): a front-end that is not woken does not read them.
            // Progress alone wakes only when owed: the front-end reads the rest on its next
            // wake-up (measured: a front-end of 100 publishing clients at 20,000 samples/s
            // slept about 0.15 times less per sample).
            if wake || p.unnotified {
                p.unnotified = false;
                if let Err(e) = link.wake(*fe) {
                    // Tried again on the next pass.
                    p.unnotified = true;
                    tracing::debug!(frontend = fe, error = %e, "front-end wake-up failed");
                }
            }
        }
    }
}

impl Frontends {
    /// What the worker keeps for `frontend`, made on first use (at `now`).
    fn port(&mut self, frontend: u32, now: Instant) -> &mut FrontendPort {
        self.ports.entry(frontend).or_insert_with(|| FrontendPort {
            incarnation: 0,
            processed: 0,
            dirty: false,
            backlog: Default::default(),
            backlog_bytes: 0,
            unnotified: false,
            progress_wake_owed: false,
            deferred: Turns::new(),
            last_delivery: now,
        })
    }
}
