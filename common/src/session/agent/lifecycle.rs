//! Sessions begin and end: CREATE_CLIENT, the requests that need no session, endpoints that
//! close, deletions.

use super::*;

impl<A: Endpoint> Agent<A> {
    /// A datagram without a session (session id 0x00 or 0x80): CREATE_CLIENT and GET_INFO.
    /// One request per datagram is acted on, the first; what else it packs is dropped
    /// (counted as `overpacked_datagram`): one datagram in, at most one reply out, so a
    /// forged source cannot turn the agent into an amplifier.
    pub(super) fn handle_sessionless(
        &mut self,
        now: Instant,
        src: A,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        for (i, raw) in Submessages::new(bytes, hlen).enumerate() {
            if i > 0 {
                return self.drop_input("overpacked_datagram", bytes);
            }
            let raw = match raw {
                Ok(r) => r,
                Err(e) => return self.drop_input(e.reason(), bytes),
            };
            let payload = match raw.decode() {
                Ok(p) => p,
                // eProsima's client always declares 16 bytes for CREATE_CLIENT, also when it
                // appends properties (hard liveliness, shared memory) and then the MTU after
                // them: read the CREATE_CLIENT from the rest of the datagram instead.
                Err(DecodeError::Truncated) if raw.id == submessage_id::CREATE_CLIENT => {
                    let rest = bytes.get(raw.offset + 4..).unwrap_or_default();
                    match Payload::decode(raw.id, raw.flags, rest) {
                        Ok(Payload::CreateClient(c)) => {
                            tracing::trace!("CREATE_CLIENT longer than its declared length");
                            return self.create_client(now, src, &c, sink);
                        }
                        Ok(_) => return,
                        Err(e) => return self.drop_input(e.reason(), bytes),
                    }
                }
                Err(e) => return self.drop_input(e.reason(), bytes),
            };
            match payload {
                Payload::CreateClient(c) => self.create_client(now, src, &c, sink),
                Payload::GetInfo(g) if self.once(Reply::Info) => {
                    let dialect = self.config.dialect.unwrap_or_default();
                    self.reply_info(src, header, g.base, false, dialect)
                }
                Payload::GetInfo(_) => self.count_drop("repeated_request"),
                _ => return self.drop_input("no_session", bytes),
            }
        }
    }

    pub(super) fn create_client(
        &mut self,
        now: Instant,
        src: A,
        c: &CreateClientPayload,
        sink: &mut impl OperationSink,
    ) {
        let reply_header = MessageHeader::new(c.session_id, stream_id::NONE, 0, c.client_key);
        let result = if c.cookie != XRCE_COOKIE {
            status::ERR_INVALID_DATA
        } else if c.version[0] != XRCE_VERSION[0] {
            status::ERR_INCOMPATIBLE
        } else if c.session_id == 0x00 || c.session_id == 0x80 || c.client_key == ClientKey::INVALID
        {
            status::ERR_INVALID_DATA
        } else {
            match self.config.admission.admits(c.client_key, src.ip()) {
                KeyCheck::Admitted => status::OK,
                KeyCheck::NotListed => {
                    self.count_drop("key_not_allowed");
                    status::ERR_DENIED
                }
                KeyCheck::WrongNetwork => {
                    self.count_drop("key_wrong_network");
                    status::ERR_DENIED
                }
            }
        };
        let result = if result != status::OK {
            result
        } else if self.clients.contains_key(&c.client_key) {
            match self.takeover(now, c.client_key, src, c) {
                limits::Takeover::Allow => status::OK,
                limits::Takeover::Probing => {
                    // Unanswered for now: once the probe wait is over and the session's
                    // endpoint stayed silent, the core answers it itself (`grant_claims`);
                    // if the endpoint answered, the client's next attempt is refused.
                    self.count_drop("takeover_probing");
                    self.schedule(c.client_key);
                    tracing::info!(client = %c.client_key, from = ?src, "CREATE_CLIENT for a live session from another endpoint: probing the session's endpoint before moving it");
                    return;
                }
                limits::Takeover::Refuse => {
                    self.count_drop("takeover_refused");
                    if let Some(previous) = self.episodes.bite(now, "takeover_refused") {
                        tracing::warn!(client = %c.client_key, from = ?src, previous_episode = previous, "CREATE_CLIENT refused: the key's session is alive at another endpoint, which answered a probe (run with --allow-roaming to let sessions move freely; logged once per episode)");
                    }
                    status::ERR_DENIED
                }
            }
        } else if !self.creations.admit(now, src.origin()) {
            // Unanswered: the client tries again; an answer would make the agent a
            // reflector for forged sources, and each new session costs the worker work.
            self.count_drop("session_creation_rate");
            if let Some(previous) = self.episodes.bite(now, "session_creation_rate") {
                tracing::warn!(client = %c.client_key, from = ?src, per_second = self.config.limits.new_sessions_per_second, previous_episode = previous, "CREATE_CLIENT dropped: its address starts new sessions faster than --new-sessions-per-second (logged once per episode)");
            }
            return;
        } else if self.by_addr.get(&src).is_some_and(|k| *k != c.client_key)
            || self.admit_session(now, src, sink)
        {
            // (A new key at an endpoint that has a session replaces that session.)
            status::OK
        } else {
            status::ERR_RESOURCES
        };
        if result == status::OK {
            // Another client at the same source address is gone (it was restarted with a new key).
            if let Some(other) = self
                .by_addr
                .get(&src)
                .copied()
                .filter(|k| *k != c.client_key)
            {
                self.remove_client(now, other, sink);
            }
            // At least 64 (so fragments carry data), at most what the transport carries.
            let mtu = c
                .mtu
                .unwrap_or(self.config.default_mtu)
                .clamp(64, self.config.max_message_size.max(64));
            let dialect = self
                .config
                .dialect
                .unwrap_or(Dialect::for_vendor(c.vendor_id));
            let dead_time = hard_liveliness(c).or(self.config.client_dead_time);
            match self.clients.get_mut(&c.client_key) {
                Some(existing) if existing.session_id == c.session_id => {
                    // The same session again: a restarted client starts its streams at 0, so
                    // ours restart too; its objects stay (§7.8.2.1 "no action"). A copy of the
                    // CREATE_CLIENT that arrives just after the client began using its streams
                    // is a network duplicate or a stale retry, not a restart: keep the streams.
                    // From another endpoint (a new connection, a new source port) it is a
                    // restart whatever the timing.
                    let stale = existing.streams_used
                        && existing.addr == src
                        && !existing.detached
                        && now.saturating_duration_since(existing.established_at)
                            < self.config.duplicate_create_guard;
                    if stale {
                        self.stats.count("duplicate_create_client");
                        existing.restart_suspected = true;
                    } else {
                        existing.reset_streams(issue_epoch(
                            &mut self.epochs_issued,
                            self.config.epoch_seed,
                        ));
                        existing.established_at = now;
                    }
                    existing.first_seq = proxy::first_sequence_number(c.vendor_id);
                    existing.mtu = mtu;
                    existing.mtu_announced = c.mtu.is_some();
                    existing.last_heard = now;
                    existing.detached = false;
                    existing.closed_at = None;
                    existing.attached_dead_time = None;
                    existing.takeover = None;
                    existing.dialect = dialect;
                    existing.dead_time = dead_time;
                    let old = existing.addr;
                    existing.addr = src;
                    let (before_origin, held) = (existing.origin, existing.held);
                    existing.origin = src.origin();
                    if before_origin != existing.origin {
                        self.budget.session_removed(before_origin, held);
                        self.budget.session_added(src.origin());
                        self.budget.changed(src.origin(), 0, held);
                    }
                    if self.by_addr.get(&old) == Some(&c.client_key) {
                        self.by_addr.remove(&old);
                    }
                    self.by_addr.insert(src, c.client_key);
                    tracing::info!(client = %c.client_key, session = c.session_id, "session re-established");
                }
                existing => {
                    if existing.is_some() {
                        self.remove_client(now, c.client_key, sink);
                    }
                    let terms = proxy::SessionTerms {
                        key: c.client_key,
                        session_id: c.session_id,
                        mtu,
                        dialect,
                        dead_time,
                    };
                    let mut client = ProxyClient::new(terms, src, now, &self.config);
                    client.epoch = self.next_epoch();
                    client.mtu_announced = c.mtu.is_some();
                    client.first_seq = proxy::first_sequence_number(c.vendor_id);
                    self.budget.session_added(client.origin);
                    self.clients.insert(c.client_key, client);
                    self.by_addr.insert(src, c.client_key);
                    sink.operation(
                        now,
                        Operation::ClientCreated {
                            client: c.client_key,
                            origin: src.origin(),
                        },
                    );
                    tracing::info!(client = %c.client_key, session = c.session_id, vendor = %vendor_name(c.vendor_id), version = %format!("{}.{}", c.version[0], c.version[1]), mtu, ?dialect, ?dead_time, first_sequence_number = proxy::first_sequence_number(c.vendor_id), "session created");
                    self.warn_misfit(c, dialect);
                }
            }
            self.schedule(c.client_key);
            self.touch_input(c.client_key);
        } else if result == status::ERR_DENIED {
            if self.denied_logged.len() < 1024 && self.denied_logged.insert(c.client_key) {
                tracing::warn!(client = %c.client_key, "CREATE_CLIENT refused: the key is not in --allow-keys (further attempts of this key are counted)");
            } else {
                tracing::debug!(client = %c.client_key, "CREATE_CLIENT refused: key not allowed");
            }
        } else {
            tracing::info!(client = %c.client_key, status = result, "CREATE_CLIENT refused");
        }
        // Without a ResultStatus a refusal cannot be reported: only a forced spec dialect drops it.
        let forced_spec = self.config.dialect == Some(Dialect::Spec);
        let payload = Payload::StatusAgent(StatusAgentPayload {
            result: (!forced_spec).then(|| ResultStatus::new(result)),
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id: self.config.vendor_id,
            properties: None,
        });
        let mut b = MessageBuilder::new(reply_header);
        let _ = b.push(&payload, true);
        self.push_transmit(src, b.finish());
    }

    /// A message for a session the agent does not have (`reason` says how it missed): a
    /// DELETE of the client is answered STATUS_OK in the message's own header, as the
    /// reference agent does, so a client whose first STATUS was lost does not wait out its
    /// retries for a session that is already gone; a GET_INFO (PX4's and micro-ROS's ping in
    /// session) is answered "no session" at once. Everything else is dropped, counted under
    /// `reason`. At most one reply of each kind per datagram, none longer than what came
    /// in: nothing to amplify.
    pub(super) fn answer_orphan(
        &mut self,
        src: A,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        reason: &'static str,
    ) {
        let mut answered = false;
        for raw in Submessages::new(bytes, hlen) {
            let Ok(raw) = raw else { break };
            match raw.decode() {
                Ok(Payload::Delete(d))
                    if d.object_id.kind() == crate::wire::object_kind::CLIENT
                        && self.once(Reply::Status) =>
                {
                    let mut b = MessageBuilder::new(header);
                    let reply = BaseObjectReply {
                        related: d,
                        result: ResultStatus::OK,
                    };
                    let _ = b.push(&Payload::Status(reply), raw.little_endian());
                    self.stats.count("delete_without_session");
                    tracing::debug!(
                        ?src,
                        session = header.session_id,
                        "DELETE of a session the agent does not have: answered STATUS_OK"
                    );
                    self.push_transmit(src, b.finish());
                    answered = true;
                }
                Ok(Payload::GetInfo(g)) if self.once(Reply::Info) => {
                    let dialect = self.config.dialect.unwrap_or_default();
                    self.stats.count("info_without_session");
                    self.reply_info(src, header, g.base, false, dialect);
                    answered = true;
                }
                _ => {}
            }
        }
        if !answered {
            self.drop_input(reason, bytes);
        }
    }

    pub(super) fn reply_info(
        &mut self,
        dst: A,
        header: MessageHeader,
        request: BaseObjectRequest,
        in_session: bool,
        dialect: Dialect,
    ) {
        // Available, no locators advertised (discovery answers with them, see `discovery`).
        let m = agent_info_message(
            header,
            request,
            in_session,
            dialect,
            self.config.vendor_id,
            Vec::new(),
        );
        self.push_transmit(dst, m);
    }

    /// Tells the core that a transport endpoint is gone for good (a TCP connection closed)
    /// at `now` (the detached grace counts from then). The session there is kept, with its
    /// objects: a client that reconnects and creates its
    /// session again with the same key continues with them, as over UDP. Until it is heard
    /// again nothing is sent to it (replies meanwhile wait in its reliable streams, bounded as
    /// ever). Returns whether a session was at that endpoint.
    pub fn endpoint_closed(&mut self, now: Instant, endpoint: A) -> bool {
        let Some(key) = self.by_addr.remove(&endpoint) else {
            return false;
        };
        match self.clients.get_mut(&key) {
            Some(c) if c.addr == endpoint => {
                c.detached = true;
                c.closed_at = Some(now);
                c.heartbeat_due = None;
                if let Some(grace) = self.config.limits.detached_grace {
                    if c.attached_dead_time.is_none() {
                        c.attached_dead_time = Some(c.dead_time);
                    }
                    c.dead_time = Some(c.dead_time.map_or(grace, |d| d.min(grace)));
                }
                tracing::info!(client = %key, "client's endpoint closed; session kept");
                self.schedule(key);
                true
            }
            _ => false,
        }
    }

    /// Ends a client's session from outside the protocol (its objects could not be given
    /// back to a new worker, say): deleted as a dead one is, counted under `reason`. Whether
    /// it had one.
    pub fn end_session(
        &mut self,
        now: Instant,
        key: ClientKey,
        reason: &'static str,
        sink: &mut impl OperationSink,
    ) -> bool {
        if !self.clients.contains_key(&key) {
            return false;
        }
        self.count_drop(reason);
        tracing::warn!(client = %key, reason, "session ended by the agent");
        self.remove_client(now, key, sink);
        true
    }

    pub(super) fn remove_client(
        &mut self,
        now: Instant,
        key: ClientKey,
        sink: &mut impl OperationSink,
    ) {
        if let Some(c) = self.clients.remove(&key) {
            self.budget.session_removed(c.origin, c.held);
            if self.config.track_sessions {
                self.changed.remove(&key);
                self.changed_input.remove(&key);
                self.removed.push(key);
            }
            if self.by_addr.get(&c.addr) == Some(&key) {
                self.by_addr.remove(&c.addr);
            }
            sink.operation(now, Operation::ClientDeleted { client: key });
            tracing::info!(client = %key, "session deleted");
        }
    }

    /// Tells the core that `endpoint`'s host says nothing listens there any more (UDP: an
    /// ICMP port unreachable, typically in answer to a takeover probe). A claim on the
    /// session there from a new endpoint (a client that reset and came back from a new
    /// port) is granted at once instead of after the probe wait. The session itself is kept
    /// as it is: a UDP session outlives its client's silence, as with the reference agent.
    pub fn endpoint_unreachable(
        &mut self,
        now: Instant,
        endpoint: A,
        sink: &mut impl OperationSink,
    ) {
        let Some(key) = self.by_addr.get(&endpoint).copied() else {
            return;
        };
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let Some(claim) = c.takeover.as_mut() else {
            return;
        };
        if c.addr != endpoint || c.last_heard > claim.probed {
            return;
        }
        claim.endpoint_gone = true;
        if let Some(request) = claim.request.take() {
            let claimant = claim.claimant;
            tracing::debug!(client = %key, to = ?claimant, "the session's endpoint is closed (ICMP port unreachable): the session moves");
            self.create_client(now, claimant, &request, sink);
        }
    }

    /// Removes a client that asked for its own deletion, after its STATUS went out.
    pub(super) fn finish_client(
        &mut self,
        now: Instant,
        key: ClientKey,
        sink: &mut impl OperationSink,
    ) {
        if self.clients.get(&key).is_some_and(|c| c.delete_requested) {
            self.flush_client(now, key);
            self.remove_client(now, key, sink);
        }
    }
}

/// A vendor id as a log line shows it: the name of a known implementation, else its hex.
pub(super) fn vendor_name(v: [u8; 2]) -> String {
    match v {
        crate::wire::VENDOR_EPROSIMA => "eProsima (01.0F)".into(),
        crate::wire::VENDOR_RTI => "RTI (01.01)".into(),
        [a, b] => format!("{a:02X}.{b:02X}"),
    }
}

impl<A: Endpoint> Agent<A> {
    /// Warns once per session about combinations known to misbehave: a dialect forced
    /// against the one the client's vendor speaks (eProsima's client cannot read a
    /// spec-dialect STATUS_AGENT without its ResultStatus, nor a spec client eProsima's).
    pub(super) fn warn_misfit(&self, c: &CreateClientPayload, dialect: Dialect) {
        let natural = Dialect::for_vendor(c.vendor_id);
        if self.config.dialect.is_some() && dialect != natural {
            tracing::warn!(client = %c.client_key, vendor = %vendor_name(c.vendor_id), forced = ?dialect, natural = ?natural, "--dialect forces a dialect this client's vendor does not speak: expect its replies to be misread");
        }
        if c.version[1] != XRCE_VERSION[1] {
            tracing::info!(client = %c.client_key, version = %format!("{}.{}", c.version[0], c.version[1]), "client of another minor protocol version: served as 1.0");
        }
    }
}

/// The hard-liveliness timeout a client asks for in CREATE_CLIENT (property `uxr_hl`, six
/// decimal digits of milliseconds).
pub(super) fn hard_liveliness(c: &CreateClientPayload) -> Option<Duration> {
    let props = c.properties.as_ref()?;
    let (_, v) = props.iter().find(|(k, _)| k == "uxr_hl")?;
    let ms: u64 = v.trim().parse().ok()?;
    (ms > 0).then(|| Duration::from_millis(ms.max(100)))
}
