//! The agent's input path: datagrams to sessions, reliable streams in order, ACKNACKs
//! back, and accepted messages split into submessages.

use super::*;

impl<A: Endpoint> Agent<A> {
    /// Handles one datagram from `src`.
    pub fn handle_datagram(
        &mut self,
        now: Instant,
        src: A,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        self.stats.datagrams_in += 1;
        self.replied.clear();
        tracing::trace!(?src, len = bytes.len(), bytes = %hex(bytes), "datagram in");
        let (header, hlen) = match MessageHeader::decode(bytes) {
            Ok(h) => h,
            Err(e) => return self.drop_input(e.reason(), bytes),
        };
        if header.session_id == 0x00 || header.session_id == 0x80 {
            return self.handle_sessionless(now, src, header, hlen, bytes, sink);
        }
        let key = match header.client_key {
            Some(k) => k,
            None => match self.by_addr.get(&src) {
                Some(k) => *k,
                None => return self.answer_orphan(src, header, hlen, bytes, "no_client"),
            },
        };
        let Some(client) = self.clients.get_mut(&key) else {
            return self.answer_orphan(src, header, hlen, bytes, "no_client");
        };
        if client.session_id != header.session_id {
            return self.answer_orphan(src, header, hlen, bytes, "wrong_session");
        }
        if client.addr != src {
            // Only a key in the header names a session from another endpoint.
            if !self.config.admission.allow_roaming {
                // Whoever learnt the key does not take the session over: only the client's
                // CREATE_CLIENT moves it (or roaming, when the operator allows it).
                client.foreign_drops += 1;
                if client.foreign_drops == 1 {
                    tracing::warn!(client = %key, from = ?src, at = ?client.addr, "message for a session from another endpoint dropped (a client that moved must send CREATE_CLIENT again, or run the agent with --allow-roaming); further ones are counted");
                }
                return self.drop_input("foreign_endpoint", bytes);
            }
            // The client moved (e.g. a new source port after a NAT rebinding).
            if self.by_addr.get(&client.addr) == Some(&key) {
                self.by_addr.remove(&client.addr);
            }
            tracing::info!(client = %key, from = ?client.addr, to = ?src, "session roamed");
            client.addr = src;
            self.by_addr.insert(src, key);
        }
        client.last_heard = now;
        client.reattach();
        client.counters.messages_in += 1;
        let lost_before = self.stats.lost_total;
        self.handle_session_message(now, key, header, hlen, bytes, sink);
        if stream_id::is_reliable(header.stream_id) {
            // Its input position moved: stored before anything acknowledges it.
            self.touch_input(key);
        } else {
            self.touch(key);
        }
        let lost = self.stats.lost_total - lost_before;
        if let Some(c) = self.clients.get_mut(&key) {
            c.counters.dropped += lost;
        }
        self.account(key);
    }

    /// A message of an existing session, from its endpoint.
    fn handle_session_message(
        &mut self,
        now: Instant,
        key: ClientKey,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        if let Some(meter) = &mut client.meter {
            match meter.admit(now, bytes.len()) {
                Metered::Admitted => {}
                Metered::BackWithin { dropped } => {
                    tracing::info!(client = %key, dropped, "client back within its rate quota");
                }
                Metered::WentOver(hit) => {
                    let quota = self.config.admission.rate;
                    tracing::warn!(client = %key, bound = hit.name(), messages_per_second = ?quota.messages_per_second, bytes_per_second = ?quota.bytes_per_second, "client over its rate quota: its messages are dropped until it slows down (reliable ones are sent again by the client)");
                    return self.drop_input("rate_quota", bytes);
                }
                Metered::StillOver => return self.drop_input("rate_quota", bytes),
            }
        }
        let stream = header.stream_id;
        if client.restart_suspected && stream != stream_id::NONE {
            client.restart_suspected = false;
            let first = client.first_seq;
            let from_the_start = header.sequence_nr == first
                && if stream_id::is_reliable(stream) {
                    client
                        .reliable_in
                        .get(&stream)
                        .is_some_and(|i| i.is_behind(first))
                } else {
                    client
                        .best_effort_in
                        .get(&stream)
                        .is_some_and(|i| i.is_stale(first))
                };
            if from_the_start {
                client.reset_streams(issue_epoch(&mut self.epochs_issued, self.config.epoch_seed));
                client.established_at = now;
                tracing::info!(client = %key, stream, "the CREATE_CLIENT taken for a duplicate was the client's restart: its streams start again");
                // Stored with this message whatever its stream: a successor must not take
                // the new run's messages for copies of the old one's.
                self.touch_input(key);
            }
        }
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        if stream != stream_id::NONE {
            client.streams_used = true;
        }
        if stream == stream_id::NONE && is_bare_probe_reply(&bytes[hlen..]) {
            // A live client answered a liveliness probe (hearing it was the point).
        } else if stream == stream_id::NONE {
            self.process(now, key, bytes, hlen, sink);
        } else if !stream_id::is_reliable(stream) {
            let accepted = client
                .best_effort_in
                .entry(stream)
                .or_default()
                .accept(header.sequence_nr);
            if accepted {
                self.process(now, key, bytes, hlen, sink);
            } else {
                self.drop_input("stale_best_effort", bytes);
            }
        } else {
            self.handle_reliable(now, key, header, hlen, bytes, sink);
        }
        // HEARTBEATs that came inside reliable messages (delivering may bring more).
        while let Some(s) = self.heartbeat_deliveries.pop() {
            self.deliver_ready(now, key, s, sink);
            self.send_acknack(now, key, s, AckCause::Heartbeat);
        }
        self.flush_client(now, key);
        self.finish_client(now, key, sink);
    }

    fn handle_reliable(
        &mut self,
        now: Instant,
        key: ClientKey,
        header: MessageHeader,
        hlen: usize,
        bytes: &[u8],
        sink: &mut impl OperationSink,
    ) {
        let window = self.config.input_window;
        let max_streams = self.config.max_input_streams;
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        let stream = header.stream_id;
        if !client.reliable_in.contains_key(&stream) && client.reliable_in.len() >= max_streams {
            return self.drop_input("too_many_streams", bytes);
        }
        let first = client.first_seq;
        let input = client
            .reliable_in
            .entry(stream)
            .or_insert_with(|| ReliableInput::resuming(window, first));
        let mut cause = AckCause::Arrival;
        match input.classify(header.sequence_nr) {
            Arrival::Duplicate => self.count_drop("duplicate"),
            Arrival::OutOfWindow => self.drop_input("out_of_window", bytes),
            Arrival::Early => {
                let held: usize = client
                    .reliable_in
                    .values()
                    .map(ReliableInput::early_bytes)
                    .sum();
                if held + bytes.len() > self.config.max_early_bytes {
                    self.count_drop("early_buffer_full");
                } else if !self.make_room(now, key, bytes.len(), "memory_budget") {
                    // Not acknowledged: sent again once it is next.
                } else if let Some(input) = self
                    .clients
                    .get_mut(&key)
                    .and_then(|c| c.reliable_in.get_mut(&stream))
                {
                    input.store_early(header.sequence_nr, bytes.to_vec());
                    self.account(key);
                }
            }
            Arrival::InOrder => {
                // A FRAGMENT makes the core keep its bytes until the last one: room for
                // them first, or the message is not acknowledged and comes again.
                let kept = fragment_bytes(bytes, hlen);
                let growth = self.reassembly_growth(key, stream, kept);
                if growth > 0 && !self.make_room(now, key, growth, "memory_budget") {
                    cause = AckCause::Refused;
                } else if room_for(sink, bytes, hlen) {
                    if let Some(input) = self
                        .clients
                        .get_mut(&key)
                        .and_then(|c| c.reliable_in.get_mut(&stream))
                    {
                        input.advance();
                    }
                    self.process(now, key, bytes, hlen, sink);
                    if !self.deliver_ready(now, key, stream, sink) {
                        cause = AckCause::Refused;
                    }
                } else {
                    // Flow control: not acknowledged, so the client will send it again.
                    self.count_drop("backpressure");
                    cause = AckCause::Refused;
                }
            }
        }
        self.send_acknack(now, key, stream, cause);
    }

    /// Bytes of memory a stream's reassembly takes on if it collects `kept` more.
    fn reassembly_growth(&self, key: ClientKey, stream: u8, kept: usize) -> usize {
        self.clients
            .get(&key)
            .and_then(|c| c.reassembly.get(&stream))
            .map_or(kept, |r| r.growth_for(kept))
    }

    /// Delivers messages that arrived early and are now next, while the sink has room and,
    /// for a FRAGMENT, the memory budget has room for the reassembly's growth (the early
    /// message's own bytes are no longer held once taken). One that finds no room is dropped
    /// unacknowledged (false is returned): the ACKNACK that answers the client's next
    /// HEARTBEAT asks for it again.
    pub(super) fn deliver_ready(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        sink: &mut impl OperationSink,
    ) -> bool {
        loop {
            let Some(input) = self
                .clients
                .get_mut(&key)
                .and_then(|c| c.reliable_in.get_mut(&stream))
            else {
                return true;
            };
            let Some(next) = input.take_ready() else {
                return true;
            };
            let Ok((_, hlen)) = MessageHeader::decode(&next) else {
                input.advance();
                continue;
            };
            if !room_for(sink, &next, hlen) {
                self.count_drop("backpressure");
                self.account(key);
                return false;
            }
            let kept = fragment_bytes(&next, hlen);
            if kept > 0 {
                self.account(key);
                let growth = self.reassembly_growth(key, stream, kept);
                if growth > 0 && !self.make_room(now, key, growth, "memory_budget") {
                    return false;
                }
            }
            let Some(input) = self
                .clients
                .get_mut(&key)
                .and_then(|c| c.reliable_in.get_mut(&stream))
            else {
                return true;
            };
            input.advance();
            self.process(now, key, &next, hlen, sink);
        }
    }

    /// Acknowledges a reliable input stream (see [`AckCause`] for when an ACKNACK asks for
    /// messages again and when one is left out).
    pub(super) fn send_acknack(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        cause: AckCause,
    ) {
        let Some(client) = self.clients.get_mut(&key) else {
            return;
        };
        let Some(input) = client.reliable_in.get(&stream) else {
            return;
        };
        let mut ack = input.acknack(stream);
        if cause == AckCause::Refused {
            ack.nack_bitmap = 0;
        }
        let same = (ack.first_unacked_seq_num, ack.nack_bitmap);
        if cause != AckCause::Heartbeat {
            let repeated = client.last_acknack.get(&stream).is_some_and(|&(f, m, at)| {
                (f, m) == same && now.saturating_duration_since(at) < ACKNACK_REPEAT_INTERVAL
            });
            if repeated {
                return;
            }
        }
        client.last_acknack.insert(stream, (same.0, same.1, now));
        let mut b = MessageBuilder::new(client.header(stream_id::NONE, 0));
        let _ = b.push(&Payload::Acknack(ack), true);
        let addr = client.addr;
        self.push_transmit(addr, b.finish());
    }

    /// Processes the submessages of one accepted message.
    fn process(
        &mut self,
        now: Instant,
        key: ClientKey,
        bytes: &[u8],
        hlen: usize,
        sink: &mut impl OperationSink,
    ) {
        let stream = bytes.get(1).copied().unwrap_or(0);
        let sequence = u16::from_le_bytes([
            bytes.get(2).copied().unwrap_or(0),
            bytes.get(3).copied().unwrap_or(0),
        ]);
        let mut at = MessageAt {
            epoch: self.clients.get(&key).map_or(0, |c| c.epoch),
            stream,
            sequence,
            writes: 0,
        };
        for raw in Submessages::new(bytes, hlen) {
            let raw = match raw {
                Ok(r) => r,
                Err(e) => {
                    self.drop_input(e.reason(), bytes);
                    break;
                }
            };
            self.dispatch(now, key, &mut at, raw, false, sink);
        }
        if let Some(c) = self
            .clients
            .get_mut(&key)
            .filter(|_| stream_id::is_reliable(stream))
        {
            // The relay takes reliable messages only once the worker said what it executed.
            c.awaiting_executed = false;
            // A floor lasts up to the last message it covers.
            c.executed_floor
                .retain(|f| f.last.stream_id != stream || !f.ends_with(sequence));
        }
    }
}

/// The message a submessage came in: its stream and sequence number, and how many WRITE_DATA
/// of it were dispatched so far (reassembled fragments count in the message of the last one).
#[derive(Debug)]
pub(super) struct MessageAt {
    /// The run of the client's streams the message came in (a RESET inside it starts
    /// another).
    pub(super) epoch: u64,
    pub(super) stream: u8,
    pub(super) sequence: u16,
    pub(super) writes: u16,
}

/// Whether `sink` has room for the operations of the reliable message `bytes` (header
/// `hlen` bytes long): asked for its submessages' count when none is a FRAGMENT (whose
/// completion can bring a message of any size) and every header is whole, else for the
/// largest message. (A HEARTBEAT in it delivers buffered messages only after it.)
fn room_for(sink: &impl OperationSink, bytes: &[u8], hlen: usize) -> bool {
    let mut count = 0;
    for raw in Submessages::new(bytes, hlen) {
        match raw {
            Ok(r) if r.id != submessage_id::FRAGMENT => count += 1,
            _ => return sink.has_room(),
        }
    }
    sink.has_room_for(count)
}

/// Bytes of FRAGMENT payload in a message (what the core keeps of it until the last
/// fragment).
fn fragment_bytes(bytes: &[u8], hlen: usize) -> usize {
    Submessages::new(bytes, hlen)
        .filter_map(Result::ok)
        .filter(|r| r.id == submessage_id::FRAGMENT)
        .map(|r| r.payload.len())
        .sum()
}
