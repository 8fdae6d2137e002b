//! Sessions saved for, and taken over by, a successor front-end process.

use super::*;

impl<A: Endpoint> Agent<A> {
    /// The sessions whose snapshot may have changed, and the sessions deleted, since the
    /// last call (empty unless `track_sessions`). A front-end stores the snapshots before
    /// it sends what the core produced, so what a client saw acknowledged or numbered is
    /// never behind what the stored state says.
    ///
    /// Sessions whose input positions changed are always returned; those where only the
    /// output side changed only with `with_output` (a successor copes with output state a
    /// little behind: its clients' ACKNACKs tell it where they are).
    pub fn take_session_changes(&mut self, with_output: bool) -> (Vec<ClientKey>, Vec<ClientKey>) {
        let mut changed: HashSet<ClientKey> = self.changed_input.drain().collect();
        if with_output {
            changed.extend(self.changed.drain());
        }
        (
            changed.into_iter().collect(),
            std::mem::take(&mut self.removed),
        )
    }

    /// The state a successor front-end needs to take a session over, with its endpoint
    /// encoded by `endpoint`.
    pub fn snapshot(
        &self,
        key: ClientKey,
        endpoint: impl Fn(A) -> Vec<u8>,
    ) -> Option<SessionSnapshot> {
        let c = self.clients.get(&key)?;
        let mut reliable_in: Vec<(u8, u16)> = c
            .reliable_in
            .iter()
            .map(|(s, i)| (*s, i.expected()))
            .collect();
        let mut best_effort_in: Vec<(u8, u16)> = c
            .best_effort_in
            .iter()
            .filter_map(|(s, i)| Some((*s, i.last()?)))
            .collect();
        let mut reliable_out: Vec<OutputSnapshot> = c
            .reliable_out
            .iter()
            .map(|(s, o)| OutputSnapshot {
                stream_id: *s,
                next: o.reliable.next_seq(),
                // A stream still asking the client where it is has nothing to resend.
                in_flight: (!o.reliable.is_resyncing()).then(|| {
                    o.reliable
                        .in_flight()
                        .map(|(seq, m)| (seq, m.to_vec()))
                        .collect()
                }),
                queued: o.queue.iter().cloned().collect(),
            })
            .collect();
        reliable_out.sort_by_key(|o| o.stream_id);
        let mut best_effort_out: Vec<(u8, u16)> =
            c.best_effort_out.iter().map(|(s, n)| (*s, *n)).collect();
        for list in [&mut reliable_in, &mut best_effort_in, &mut best_effort_out] {
            list.sort_unstable();
        }
        Some(SessionSnapshot {
            key,
            session_id: c.session_id,
            endpoint: endpoint(c.addr),
            mtu: c.mtu,
            dialect: c.dialect,
            dead_time: c.dead_time,
            reliable_in,
            best_effort_in,
            reliable_out,
            best_effort_out,
            epoch: c.epoch,
        })
    }

    /// Tells every client at once where its reliable streams stand: an ACKNACK of each input
    /// stream (what was taken, what is missing) and a HEARTBEAT of each output stream with
    /// something unacknowledged. For a front-end whose worker came back (a new generation
    /// took the replay): messages refused meanwhile wait for the client's own next
    /// HEARTBEAT otherwise, and a client whose library gives up on a confirmation window
    /// (eProsima's example publisher ends its session when a sample stays unconfirmed for a
    /// second) gives up instead.
    pub fn announce_streams(&mut self, now: Instant) {
        let keys: Vec<ClientKey> = self
            .clients
            .values()
            .filter(|c| !c.detached)
            .map(|c| c.key)
            .collect();
        for key in keys {
            self.announce_client(now, key);
        }
    }

    /// [`Self::announce_streams`] for one client.
    fn announce_client(&mut self, now: Instant, key: ClientKey) {
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        if c.reliable_out
            .values()
            .any(|s| s.reliable.heartbeat().is_some())
        {
            c.heartbeat_due = Some(now);
        }
        let inputs: Vec<u8> = c.reliable_in.keys().copied().collect();
        for stream in inputs {
            self.send_acknack(now, key, stream, AckCause::Heartbeat);
        }
        self.schedule(key);
    }

    /// The worker executed `executed` (the last write it got from this front-end's
    /// predecessor on that client stream). If that write is in the run of the streams the
    /// stored session is in ([`InputPosition::epoch`]) and in a message from the one it
    /// expects next up to a window ahead, the predecessor handed those messages over (all
    /// the writes of the ones before, part or all of the last's) and died before storing
    /// that it took them: the client will send them again, and those writes are then not
    /// handed over a second time (a floor of the stream). Any other position is ignored (behind:
    /// stored as taken; another epoch: the streams started again since). A message is never
    /// taken as received on the worker's word: its other operations are processed again.
    /// Applied after a takeover, before any reliable client message is processed (the relay
    /// refuses them until the worker answered its hello).
    pub fn skip_executed(&mut self, key: ClientKey, executed: InputPosition) {
        let window = self.config.input_window;
        let Some(c) = self.clients.get_mut(&key).filter(|c| c.awaiting_executed) else {
            return;
        };
        let expected = c
            .reliable_in
            .get(&executed.stream_id)
            .map_or(c.first_seq, ReliableInput::expected);
        // Behind what was stored: taken already. Of another run of the streams: it says
        // nothing about this one. Further ahead than the window: not this stream's either
        // (what one datagram can hand over spans the window at most).
        let ahead = executed.sequence.wrapping_sub(expected);
        if !stream_id::is_reliable(executed.stream_id)
            || executed.epoch != c.epoch
            || ahead >= window
        {
            tracing::debug!(client = %key, stream = executed.stream_id, sequence = executed.sequence, epoch = executed.epoch, expected, session_epoch = c.epoch, "the worker's last executed write is not in the messages expected next; ignored");
            return;
        }
        c.executed_floor
            .retain(|f| f.last.stream_id != executed.stream_id);
        c.executed_floor.push(ExecutedFloor {
            from: expected,
            last: executed,
        });
        tracing::debug!(client = %key, stream = executed.stream_id, from = expected, sequence = executed.sequence, write = executed.write_index, "the worker executed writes of messages the last front-end had not stored as taken");
    }

    /// Whether the worker executed the write at `position` for the front-end this one took
    /// over from ([`Self::skip_executed`]).
    pub(super) fn executed_before(&self, key: ClientKey, position: &InputPosition) -> bool {
        self.clients
            .get(&key)
            .is_some_and(|c| c.executed_floor.iter().any(|f| f.covers(position)))
    }

    /// Takes over a session a front-end that died stored (its object graph is the bridge's
    /// business): the client goes on where it was. Its reliable output streams first ask
    /// the client where it is (a HEARTBEAT now), and its input streams tell it what was taken
    /// (an ACKNACK now, so it resumes at once instead of at its next HEARTBEAT); a session of
    /// this key that exists already is kept instead.
    pub fn restore(&mut self, now: Instant, snapshot: &SessionSnapshot, endpoint: A) -> bool {
        if self.clients.contains_key(&snapshot.key) || self.clients.len() >= self.config.max_clients
        {
            return false;
        }
        let (in_window, out_window) = (self.config.input_window, self.config.output_window);
        let reliable_out = snapshot
            .reliable_out
            .iter()
            .map(|o| {
                let reliable = match &o.in_flight {
                    Some(m) => ReliableOutput::restored(o.stream_id, out_window, o.next, m.clone()),
                    None => ReliableOutput::resuming(o.stream_id, out_window, o.next),
                };
                (
                    o.stream_id,
                    OutStream {
                        queued_bytes: o.queued.iter().map(Vec::len).sum(),
                        reliable,
                        queue: o.queued.iter().cloned().collect(),
                    },
                )
            })
            .collect();
        // A HEARTBEAT now: the client says what it lacks (or, resyncing, where it is).
        let resyncing = snapshot
            .reliable_out
            .iter()
            .any(|o| o.in_flight.as_ref().is_none_or(|m| !m.is_empty()) || !o.queued.is_empty());
        let terms = proxy::SessionTerms {
            key: snapshot.key,
            session_id: snapshot.session_id,
            mtu: snapshot.mtu.clamp(64, self.config.max_message_size.max(64)),
            dialect: snapshot.dialect,
            dead_time: snapshot.dead_time,
        };
        let mut client = ProxyClient::new(terms, endpoint, now, &self.config);
        client.epoch = snapshot.epoch;
        // Not stored: eProsima clients announce their MTU, spec clients do not.
        client.mtu_announced = snapshot.dialect == Dialect::Eprosima;
        client.reliable_in = snapshot
            .reliable_in
            .iter()
            .map(|(s, e)| (*s, ReliableInput::resuming(in_window, *e)))
            .collect();
        client.best_effort_in = snapshot
            .best_effort_in
            .iter()
            .map(|(s, l)| (*s, BestEffortInput::resuming(*l)))
            .collect();
        client.reliable_out = reliable_out;
        client.best_effort_out = snapshot.best_effort_out.iter().copied().collect();
        client.heartbeat_due = resyncing.then_some(now);
        // Not a fresh session: a CREATE_CLIENT now is the client's own restart.
        client.established_at = now
            .checked_sub(self.config.duplicate_create_guard)
            .unwrap_or(now);
        client.streams_used = true;
        client.awaiting_executed = true;
        // Its objects are the front-end's to restore: not a session to evict first.
        client.has_objects = true;
        if let Some(old) = self.clients.remove(&snapshot.key) {
            self.budget.session_removed(old.origin, old.held);
        }
        self.budget.session_added(client.origin);
        self.clients.insert(snapshot.key, client);
        self.by_addr.insert(endpoint, snapshot.key);
        self.account(snapshot.key);
        // Output that waited for window room goes out as room allows.
        self.flush_client(now, snapshot.key);
        self.announce_client(now, snapshot.key);
        tracing::info!(client = %snapshot.key, session = snapshot.session_id, ?endpoint, "session taken over from the previous front-end");
        true
    }
}
