//! Dispatch of the front-ends' requests: which process a request comes from, in what order
//! a restarted front-end's are served, and a successor taking its entities back.

use super::*;

impl<L: WorkerLink> Worker<L> {
    /// Screens a request by the front-end process that sent it: a restarted front-end's
    /// requests wait until the queue holds nothing more of its predecessor's (whose
    /// operations run first, on the entities they were meant for); a predecessor's request
    /// that comes after its successor took over is dropped.
    pub(super) fn screen_request(&mut self, bytes: &[u8]) {
        let m = match RequestMessage::decode(bytes) {
            Ok(m) => m,
            Err(e) => {
                tracing::warn!(error = %e, "dropped IPC message");
                return self.count("bad_ipc_message");
            }
        };
        let fe = m.route.frontend_id;
        let incarnation = m.route.incarnation;
        if self.frontends.successors.get(&fe) == Some(&incarnation) {
            return self.frontends.deferred.push(bytes.to_vec());
        }
        let current = self
            .frontends
            .ports
            .get(&fe)
            .map(|p| p.incarnation)
            .filter(|i| *i != 0);
        let greeted = self.frontends.greeted.contains(&(fe, incarnation));
        let hello = m.request == Request::FrontendHello;
        match current {
            Some(c) if c != incarnation && hello => {
                self.frontends.successors.insert(fe, incarnation);
                self.frontends.deferred.push(bytes.to_vec());
            }
            Some(c) if c != incarnation => self.count("predecessor_operation"),
            _ if !greeted && !hello => {
                // Sent before the front-end knew this worker (to the one that died): the
                // front-end replays and resends what matters after its hello.
                self.count("operation_before_hello");
            }
            _ => self.process_request(m),
        }
    }

    /// Serves the requests of restarted front-ends held back by [`Self::screen_request`],
    /// once the queue was drained of their predecessors'.
    pub(super) fn serve_successors(&mut self) {
        if self.frontends.deferred.is_empty() {
            return;
        }
        self.frontends.successors.clear();
        for m in std::mem::take(&mut self.frontends.deferred) {
            if let Ok(m) = RequestMessage::decode(&m) {
                self.process_request(m);
            }
        }
    }

    pub(super) fn process_request(&mut self, m: RequestMessage<'_>) {
        let r = m.route;
        let key = (r.frontend_id, r.client_key, r.object_id);
        let what = m.request.name();
        match m.request {
            Request::FrontendHello => {
                tracing::info!(
                    frontend = r.frontend_id,
                    incarnation = r.incarnation,
                    "front-end (re)connected"
                );
                self.frontends
                    .greeted
                    .retain(|(fe, _)| *fe != r.frontend_id);
                self.frontends
                    .greeted
                    .insert((r.frontend_id, r.incarnation));
                self.offer_entities(r.frontend_id);
                // Its operations are numbered from its hello on.
                let p = self.port(r.frontend_id);
                p.incarnation = r.incarnation;
                p.processed = r.op_seq;
                // Replies held for a previous incarnation of this front-end mean nothing now.
                if let Some(p) = self.frontends.ports.get_mut(&r.frontend_id) {
                    p.backlog.clear();
                    p.backlog_bytes = 0;
                    p.deferred.clear();
                }
                // What its predecessor handed over and this worker executed, before the
                // answer: the successor takes no client message until it has that answer.
                for (client, position) in self.frontends.executed.of_frontend(r.frontend_id) {
                    let route = Route {
                        client_key: client,
                        ..Route::frontend(r.frontend_id)
                    };
                    self.reply(route, Reply::Executed(position));
                }
                self.reply(Route::frontend(r.frontend_id), Reply::WorkerHello);
                self.replay_guard.begin(r.frontend_id);
            }
            Request::ReplayDone => {
                if self.replay_guard.end(r.frontend_id) {
                    self.link.mark_replay(r.frontend_id, None);
                }
                self.end_adoption(r.frontend_id)
            }
            Request::DeleteClient => {
                self.frontends
                    .executed
                    .forget_client(r.frontend_id, r.client_key);
                self.remove_where(|c| c.0 == r.frontend_id && c.1 == r.client_key)
            }
            Request::Create {
                description,
                client_little_endian,
                replay,
                readers_matched,
            } => {
                let screened = self.replay_guard.screen(r.frontend_id, r.client_key);
                if let Screened::Admitted { mark: Some(mark) } = screened {
                    self.link.mark_replay(r.frontend_id, Some(mark));
                }
                if screened == Screened::Refused {
                    let why = format!(
                        "replayed objects of client {} refused, its session ended: the last \
                         worker died while replaying them",
                        r.client_key
                    );
                    self.refused("replay_crash", &why);
                    let result = ResultStatus {
                        status: status::ERR_RESOURCES,
                        implementation_status: ipc::REPLAY_REFUSED,
                    };
                    self.reply(r, Reply::Status { result, replay });
                    return;
                }
                let result = self.create(
                    key,
                    &description,
                    replay,
                    client_little_endian,
                    readers_matched,
                );
                if result.is_ok() {
                    tracing::debug!(client = %r.client_key, object = ?r.object_id, replay, "created");
                }
                self.status(r, what, replay, result);
            }
            Request::Delete => {
                let result = if self.entities.contains_key(&key) {
                    self.remove_subtree(key);
                    Ok(())
                } else {
                    Err(OpError::UnknownReference(
                        "delete of an unknown object".into(),
                    ))
                };
                self.status(r, what, false, result);
            }
            Request::Write {
                data,
                data_format,
                little_endian,
                dialect,
                status_requested,
                position,
                received_us,
                resend_of,
            } => {
                // A write its front-end keeps for a resend (reliable) is tagged with its
                // origin, which a resend keeps ([`xrce_common::session::origin`]).
                let kept = resend_of.is_some()
                    || position.is_some_and(|p| stream_id::is_reliable(p.stream_id));
                let origin = kept.then(|| ipc::SampleOrigin {
                    write: ipc::WriteOrigin {
                        frontend: r.frontend_id,
                        incarnation: r.incarnation,
                        write: resend_of.unwrap_or(r.op_seq),
                        index: 0,
                    },
                    resent: resend_of.is_some(),
                });
                let data = WriteData {
                    data_format,
                    little_endian,
                    dialect,
                    body: &data,
                    received_us,
                    origin,
                };
                let result = self.write(key, &r, data);
                if let Some(p) = position.filter(|p| stream_id::is_reliable(p.stream_id)) {
                    let recorded = self
                        .frontends
                        .executed
                        .record(r.frontend_id, r.client_key, p);
                    if recorded == Recorded::Full {
                        let why = format!(
                            "the position of a write of client {} of front-end {} not kept ({} clients \
                             have theirs kept, or it uses too many streams): that write could repeat if \
                             its front-end crashes",
                            r.client_key,
                            r.frontend_id,
                            executed::MAX_CLIENTS
                        );
                        self.refused("executed_positions_full", &why);
                    }
                }
                if result.is_err() || status_requested {
                    self.status(r, what, false, result);
                }
            }
            Request::PauseRead | Request::ResumeRead => {
                let pause = m.request == Request::PauseRead;
                if let Some(read) = self.readers.reads.get_mut(&key) {
                    read.paused = pause;
                    if !pause {
                        self.readers.to_pump.push(key);
                    }
                }
            }
            Request::Read { spec, replay } => {
                let result = self.start_read(key, r.request_id, replay, &spec);
                if result.is_err() {
                    self.status(r, what, replay, result);
                } else {
                    self.readers.to_pump.push(key);
                }
            }
        }
        let p = self.port(r.frontend_id);
        if p.incarnation == r.incarnation {
            p.processed = p.processed.max(r.op_seq);
        }
        p.dirty = true;
        if !m.progress_can_wait {
            p.progress_wake_owed = true;
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
        self.readers.reads.retain(|k, _| k.0 != fe);
        self.readers.to_pump.retain(|k| k.0 != fe);
        self.readers.pump_again.retain(|k| k.0 != fe);
        self.readers.over_budget.retain(|k| k.0 != fe);
        self.writers.acks.forget_frontend(fe);
        self.frontends.adoption.offer(fe, keys);
    }

    /// The replay of front-end `fe` is complete: what it did not take back goes.
    pub(super) fn end_adoption(&mut self, fe: u32) {
        let (left, adopted) = self.frontends.adoption.finish(fe);
        let mut clients: Vec<ClientKey> = left.iter().map(|k| k.1).collect();
        clients.sort_unstable();
        clients.dedup();
        let mut removed = 0;
        for k in left {
            if self.entities.contains_key(&k) {
                self.remove_subtree(k);
                removed += 1;
            }
        }
        // A client the replay did not take back has no session here any more: what it
        // executed means nothing to a later one of the same key.
        for client in clients {
            if !self.entities.clients().any(|c| *c == (fe, client)) {
                self.frontends.executed.forget_client(fe, client);
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
        if let EntityKind::Writer { rematch, .. } = &mut e.kind {
            // Samples it still holds were numbered by the predecessor: as old as any.
            for h in rematch.held.iter_mut() {
                h.seq = 0;
            }
        }
        self.frontends.adoption.adopted(key.0);
        tracing::debug!(client = %key.1, object = ?key.2, "entity taken back");
        true
    }
}
