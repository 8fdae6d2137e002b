//! What the agent does with each submessage of an accepted message: CREATE_CLIENT and
//! the other operations, fragments, time and ACKNACKs.

use super::*;

impl<A: Endpoint> Agent<A> {
    /// Acts on one submessage of an accepted message (or of a reassembled one).
    pub(super) fn dispatch(
        &mut self,
        now: Instant,
        key: ClientKey,
        at: &mut MessageAt,
        raw: RawSubmessage<'_>,
        reassembled: bool,
        sink: &mut impl OperationSink,
    ) {
        let stream = at.stream;
        let payload = match raw.decode() {
            Ok(p) => p,
            Err(e) => return self.drop_submessage(e, raw.id, raw.payload),
        };
        let le = raw.little_endian();
        match payload {
            Payload::Create(c) => {
                if let Some(client) = self.clients.get_mut(&key) {
                    if client.pending_creates.len() < proxy::MAX_PENDING_CREATES {
                        client.pending_creates.push(c.base.object_id);
                    } else {
                        client.has_objects = true;
                    }
                }
                sink.operation(
                    now,
                    Operation::Create {
                        client: key,
                        create: &c,
                        little_endian: le,
                    },
                )
            }
            // The client object by its kind, whatever its number: eProsima's client names
            // it OBJECTID_CLIENT (0xFFFE), RTI's nano-client 0x000E (kind CLIENT, id 0);
            // MicroXRCEAgent also looks at the kind only.
            Payload::Delete(d) if d.object_id.kind() == crate::wire::object_kind::CLIENT => {
                if stream == stream_id::NONE {
                    // Answered the way it came, as the reference agent does: the
                    // session's streams end with it.
                    if let Some(c) = self.clients.get(&key) {
                        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
                        let reply = BaseObjectReply {
                            related: d,
                            result: ResultStatus::OK,
                        };
                        let _ = b.push(&Payload::Status(reply), true);
                        let addr = c.addr;
                        self.push_transmit(addr, b.finish());
                    }
                } else {
                    self.queue_status(key, d, ResultStatus::OK);
                }
                if let Some(c) = self.clients.get_mut(&key) {
                    c.delete_requested = true;
                }
            }
            Payload::Delete(d) => sink.operation(
                now,
                Operation::Delete {
                    client: key,
                    request: d,
                },
            ),
            Payload::WriteData(d) => {
                // After a RESET in the same message its writes belong to the new run, at no
                // position of it (the message is numbered in the old one): none.
                let same_run = self.clients.get(&key).is_some_and(|c| c.epoch == at.epoch);
                let position =
                    (stream_id::is_reliable(stream) && same_run).then_some(InputPosition {
                        epoch: at.epoch,
                        stream_id: stream,
                        sequence: at.sequence,
                        write_index: at.writes,
                    });
                at.writes = at.writes.wrapping_add(1);
                let dialect = self.client_dialect(key);
                if let Some(p) = position.filter(|p| self.executed_before(key, p)) {
                    // The front-end this one took over from handed it to the worker, which
                    // wrote it, and died before storing that it took the message: written
                    // once is enough. A client that asks a STATUS for each write gets its
                    // answer, which went to the process that died.
                    self.count_drop("executed_before_takeover");
                    tracing::debug!(client = %key, stream = p.stream_id, sequence = p.sequence, write = p.write_index, "write resent after a takeover not written again");
                    if dialect == Dialect::Spec {
                        self.queue_status(key, d.base, ResultStatus::OK);
                    }
                    return;
                }
                self.stats.samples_in += 1;
                if let Some(c) = self.clients.get_mut(&key) {
                    c.counters.samples_in += 1;
                }
                sink.operation(
                    now,
                    Operation::Write {
                        client: key,
                        stream_id: stream,
                        position,
                        data: d,
                        little_endian: le,
                        dialect,
                    },
                )
            }
            Payload::ReadData(r) => sink.operation(
                now,
                Operation::Read {
                    client: key,
                    request: r.base,
                    spec: &r.spec,
                },
            ),
            Payload::GetInfo(_) if !self.once(Reply::Info) => self.count_drop("repeated_request"),
            Payload::GetInfo(g)
                if g.base.object_id == ObjectId::AGENT || g.base.object_id == ObjectId::CLIENT =>
            {
                if let Some(c) = self.clients.get(&key) {
                    let (addr, h, d) = (c.addr, c.header(stream_id::NONE, 0), c.dialect);
                    self.reply_info(addr, h, g.base, true, d);
                }
            }
            Payload::GetInfo(g) => sink.operation(
                now,
                Operation::GetInfo {
                    client: key,
                    request: g.base,
                    info_mask: g.info_mask,
                },
            ),
            // A client's answer to a liveliness probe: hearing it was the point.
            Payload::Info(_) => {}
            Payload::Acknack(a) => {
                // One ACKNACK per stream per datagram: more would only multiply resends.
                if self.once(Reply::Retransmit(a.stream_id)) {
                    self.on_acknack(now, key, &a);
                }
            }
            Payload::Heartbeat(h) if stream_id::is_reliable(h.stream_id) => {
                // The stream may be new to us: if every message the client sent on it was
                // lost, this HEARTBEAT is the first we hear of it, and the ACKNACK must ask
                // for everything, or the client would wait for ever.
                let (window, max_streams) =
                    (self.config.input_window, self.config.max_input_streams);
                if let Some(c) = self.clients.get_mut(&key) {
                    if c.reliable_in.contains_key(&h.stream_id) || c.reliable_in.len() < max_streams
                    {
                        let first = c.first_seq;
                        c.reliable_in
                            .entry(h.stream_id)
                            .or_insert_with(|| ReliableInput::resuming(window, first))
                            .on_heartbeat(&h);
                    }
                }
                // Messages the sender gave up on may have unblocked buffered ones. Inside a
                // reliable message they wait for the end of it: its own operations were
                // given room and go first (delivered in its middle, buffered ones could take
                // that room and leave the rest of it behind, after it was acknowledged).
                if self.once(Reply::Acknack(h.stream_id)) {
                    if stream_id::is_reliable(stream) {
                        self.heartbeat_deliveries.push(h.stream_id);
                    } else {
                        self.deliver_ready(now, key, h.stream_id, sink);
                        self.send_acknack(now, key, h.stream_id, AckCause::Heartbeat);
                    }
                }
            }
            Payload::Heartbeat(_) => self.count_drop("heartbeat_for_best_effort_stream"),
            Payload::Reset => {
                let epoch = self.next_epoch();
                if let Some(c) = self.clients.get_mut(&key) {
                    c.reset_streams(epoch);
                }
                // Stored before the next datagram: a successor must not take the client's
                // new messages for copies of old ones.
                self.touch_input(key);
            }
            Payload::Timestamp(t) if self.once(Reply::Timestamp) => {
                self.reply_timestamp(now, key, t)
            }
            Payload::Timestamp(_) => self.count_drop("repeated_request"),
            Payload::Fragment { data, .. } if reassembled || !stream_id::is_reliable(stream) => {
                self.drop_submessage(
                    DecodeError::InvalidValue("fragment outside a reliable stream"),
                    submessage_id::FRAGMENT,
                    data,
                )
            }
            Payload::Fragment { last, data } => self.on_fragment(now, key, at, last, data, sink),
            _ => self.drop_submessage(
                DecodeError::InvalidValue("submessage for an agent"),
                raw.id,
                raw.payload,
            ),
        }
    }

    /// Collects a FRAGMENT; the last one's reassembled submessages are processed as if they
    /// had arrived in the message of the last fragment.
    /// (A fragment nested in a reassembled message, or on a best-effort stream, is dropped
    /// before it comes here.)
    fn on_fragment(
        &mut self,
        now: Instant,
        key: ClientKey,
        at: &mut MessageAt,
        last: bool,
        data: &[u8],
        sink: &mut impl OperationSink,
    ) {
        let (max, stream) = (self.config.max_reassembly, at.stream);
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let pushed = c
            .reassembly
            .entry(stream)
            .or_default()
            .push(data, last, max);
        if matches!(pushed, Ok(None)) {
            c.reassembly_at.insert(stream, now);
        } else {
            c.reassembly_at.remove(&stream);
        }
        if c.reassembly_at.len() == 1 {
            // The first reassembly in progress: its timeout is a timer of the client.
            self.schedule(key);
        }
        match pushed {
            Ok(None) => {}
            Ok(Some(whole)) => {
                for raw in Submessages::reassembled(&whole) {
                    match raw {
                        Ok(raw) => self.dispatch(now, key, at, raw, true, sink),
                        Err(e) => return self.drop_input(e.reason(), &whole),
                    }
                }
            }
            Err(crate::session::fragment::ReassemblyError::TooLarge(_)) => {
                self.count_drop("reassembly_too_large")
            }
            Err(crate::session::fragment::ReassemblyError::Discarded) => {
                self.count_drop("reassembly_discarded")
            }
        }
    }

    fn drop_submessage(&mut self, e: DecodeError, id: u8, payload: &[u8]) {
        let reason = if id == submessage_id::FRAGMENT {
            "fragment_unsupported"
        } else {
            e.reason()
        };
        self.stats.count(reason);
        tracing::debug!(reason, id, error = %e, "dropped submessage");
        tracing::trace!(bytes = %hex(payload), "dropped submessage payload");
    }

    fn reply_timestamp(&mut self, now: Instant, key: ClientKey, originate: Time) {
        let Some((base, unix)) = self.wall_clock else {
            return self.count_drop("no_wall_clock");
        };
        let t = unix + now.saturating_duration_since(base);
        let t = Time {
            seconds: t.as_secs() as i32,
            nanoseconds: t.subsec_nanos(),
        };
        let Some(c) = self.clients.get(&key) else {
            return;
        };
        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
        let _ = b.push(
            &Payload::TimestampReply(TimestampReplyPayload {
                transmit: t,
                receive: t,
                originate,
            }),
            true,
        );
        let addr = c.addr;
        self.push_transmit(addr, b.finish());
    }

    fn on_acknack(&mut self, now: Instant, key: ClientKey, a: &AcknackPayload) {
        let base = self.config.heartbeat_period;
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        // It answers: HEARTBEATs at the base period again, the next one included.
        c.heartbeat_interval = base;
        let sooner = c.heartbeat_due.is_some_and(|d| d > now + base);
        if sooner {
            c.heartbeat_due = Some(now + base);
        }
        let addr = c.addr;
        let Some(out) = c.reliable_out.get_mut(&a.stream_id) else {
            return;
        };
        let resend: Vec<Vec<u8>> = out
            .reliable
            .on_acknack(a)
            .into_iter()
            .map(|m| m.to_vec())
            .collect();
        for m in resend {
            self.stats.retransmissions += 1;
            self.push_transmit(addr, m);
        }
        if sooner {
            self.schedule(key);
        }
    }
}
