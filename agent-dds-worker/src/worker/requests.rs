//! Dispatch of the front-ends' requests: which process a request comes from, in what order
//! a restarted front-end's are served, and a successor taking its entities back.

use super::*;

impl Worker {
    /// Screens a request by the front-end process that sent it: a restarted front-end's
    /// requests wait until the queue holds nothing more of its predecessor's (whose
    /// operations run first, on the entities they were meant for); a predecessor's request
    /// that comes after its successor took over is dropped.
    pub(super) fn handle_request(&mut self, bytes: &[u8]) {
        let (h, body) = match IpcHeader::decode(bytes) {
            Ok(v) => v,
            Err(e) => {
                tracing::warn!(error = %e, "dropped IPC message");
                return self.count("bad_ipc_message");
            }
        };
        let fe = h.frontend_id;
        if self.successors.get(&fe) == Some(&h.incarnation) {
            return self.deferred.push(bytes.to_vec());
        }
        let current = self
            .ports
            .get(&fe)
            .map(|p| p.incarnation)
            .filter(|i| *i != 0);
        let greeted = self.greeted.contains(&(fe, h.incarnation));
        match current {
            Some(c) if c != h.incarnation && h.kind == MessageKind::FrontendHello => {
                self.successors.insert(fe, h.incarnation);
                self.deferred.push(bytes.to_vec());
            }
            Some(c) if c != h.incarnation => self.count("predecessor_operation"),
            _ if !greeted && h.kind != MessageKind::FrontendHello => {
                // Sent before the front-end knew this worker (to the one that died): the
                // front-end replays and resends what matters after its hello.
                self.count("operation_before_hello");
            }
            _ => self.process_request(h, body),
        }
    }

    /// Serves the requests of restarted front-ends held back by [`Self::handle_request`],
    /// once the queue was drained of their predecessors'.
    pub(super) fn serve_successors(&mut self) {
        if self.deferred.is_empty() {
            return;
        }
        self.successors.clear();
        for m in std::mem::take(&mut self.deferred) {
            if let Ok((h, body)) = IpcHeader::decode(&m) {
                self.process_request(h, body);
            }
        }
    }

    pub(super) fn process_request(&mut self, h: IpcHeader, body: &[u8]) {
        let key = (h.frontend_id, h.client_key, h.object_id);
        match h.kind {
            MessageKind::FrontendHello => {
                tracing::info!(
                    frontend = h.frontend_id,
                    incarnation = h.incarnation,
                    "front-end (re)connected"
                );
                self.greeted.retain(|(fe, _)| *fe != h.frontend_id);
                self.greeted.insert((h.frontend_id, h.incarnation));
                self.offer_entities(h.frontend_id);
                if let Ok(p) = self.port(h.frontend_id) {
                    // Its operations are numbered from its hello on.
                    p.incarnation = h.incarnation;
                    p.processed = h.op_seq;
                }
                // Replies held for a previous incarnation of this front-end mean nothing now.
                if let Some(p) = self.ports.get_mut(&h.frontend_id) {
                    p.backlog.clear();
                    p.backlog_bytes = 0;
                    p.deferred.clear();
                }
                let mut hello = IpcHeader::new(MessageKind::WorkerHello);
                hello.frontend_id = h.frontend_id;
                self.reply(hello, &[]);
            }
            MessageKind::ReplayDone => self.end_adoption(h.frontend_id),
            MessageKind::DeleteClient => {
                self.remove_where(|c| c.0 == h.frontend_id && c.1 == h.client_key)
            }
            MessageKind::Create => {
                let r = self.create(
                    key,
                    body,
                    h.flags & FLAG_REPLAY != 0,
                    h.flags & FLAG_LITTLE_ENDIAN != 0,
                    h.readers,
                );
                if r.is_ok() {
                    tracing::debug!(client = %h.client_key, object = ?h.object_id, replay = h.flags & FLAG_REPLAY != 0, "created");
                }
                self.status(&h, r);
            }
            MessageKind::Delete => {
                let r = if self.entities.contains_key(&key) {
                    self.remove_subtree(key);
                    Ok(())
                } else {
                    Err((
                        status::ERR_UNKNOWN_REFERENCE,
                        "delete of an unknown object".into(),
                    ))
                };
                self.status(&h, r);
            }
            MessageKind::Write => {
                let r = self.write(key, &h, body);
                if r.is_err() || h.flags & FLAG_STATUS_REQUESTED != 0 {
                    self.status(&h, r);
                }
            }
            MessageKind::PauseRead | MessageKind::ResumeRead => {
                let pause = h.kind == MessageKind::PauseRead;
                if let Some(r) = self.reads.get_mut(&key) {
                    r.paused = pause;
                    if !pause {
                        self.to_pump.push(key);
                    }
                }
            }
            MessageKind::Read => {
                let r = self.start_read(key, &h, body);
                if r.is_err() {
                    self.status(&h, r);
                } else {
                    self.to_pump.push(key);
                }
            }
            other => {
                tracing::warn!(kind = ?other, "unexpected IPC message kind on the request service");
                self.count("unexpected_ipc_kind");
            }
        }
        if let Ok(p) = self.port(h.frontend_id) {
            if p.incarnation == h.incarnation {
                p.processed = p.processed.max(h.op_seq);
            }
            p.dirty = true;
            if h.flags & ipc::FLAG_PROGRESS_CAN_WAIT == 0 {
                p.progress_wake_owed = true;
            }
        }
    }

    /// A front-end said hello (it started, or took over from a predecessor): the entities
    /// held for it wait for its replay to take them back, and their reads stop (the replay
    /// starts those the client still has; samples wait in the DDS readers meanwhile).
    pub(super) fn offer_entities(&mut self, fe: u32) {
        let keys = self.entities.keys_of(|c| c.0 == fe);
        if !keys.is_empty() {
            tracing::info!(
                frontend = fe,
                entities = keys.len(),
                "front-end came back; its entities are kept for its replay to take back"
            );
        }
        self.reads.retain(|k, _| k.0 != fe);
        self.to_pump.retain(|k| k.0 != fe);
        self.pump_again.retain(|k| k.0 != fe);
        self.over_budget.retain(|k| k.0 != fe);
        self.acks.forget_frontend(fe);
        self.adoption.offer(fe, keys);
    }

    /// The replay of front-end `fe` is complete: what it did not take back goes.
    pub(super) fn end_adoption(&mut self, fe: u32) {
        let (left, adopted) = self.adoption.finish(fe);
        let mut removed = 0;
        for k in left {
            if self.entities.contains_key(&k) {
                self.remove_subtree(k);
                removed += 1;
            }
        }
        if adopted + removed > 0 {
            tracing::info!(frontend = fe, adopted, removed, "front-end replay complete");
        }
    }

    /// Takes entity `key` back for a replay of its CREATE (`body`, `little_endian`), if it
    /// was created from the same; whether it was.
    pub(super) fn adopt(&mut self, key: EntityKey, body: &[u8], little_endian: bool) -> bool {
        let Some(e) = self.entities.get_mut(&key) else {
            return false;
        };
        if e.origin != Origin::new(body, little_endian) {
            return false;
        }
        if let EntityKind::Writer(_, rematch, _) = &mut e.kind {
            // Samples it still holds were numbered by the predecessor: as old as any.
            for h in rematch.held.iter_mut() {
                h.0 = 0;
            }
        }
        self.adoption.adopted(key.0);
        tracing::debug!(client = %key.1, object = ?key.2, "entity taken back");
        true
    }
}
