//! What the agent sends its clients: replies, samples and the queueing of reliable output
//! into its window.

use super::*;

/// Why a reply could not be queued.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SendError {
    /// The client has no session (any more).
    #[error("no such client")]
    NoClient,
    /// The output stream's queue is full; the reply was dropped.
    #[error("output queue full")]
    QueueFull,
    /// The reply does not fit one submessage.
    #[error("reply too large")]
    TooLarge,
    /// The read asked for an undefined DataFormat.
    #[error("undefined data format")]
    BadFormat,
}

/// A sample for [`Agent::send_data`].
#[derive(Debug, Clone, Copy)]
pub struct DataReply<'a> {
    /// The READ_DATA answered.
    pub request: BaseObjectRequest,
    /// The DataFormat the read asked for.
    pub format: u8,
    /// The serialized sample.
    pub sample: &'a [u8],
    /// Whether `sample` is little endian.
    pub little_endian: bool,
    /// [`crate::wire::sample::sample_state`] bits (0 = alive), for the formats with SampleInfo.
    pub state: u8,
    /// Sequence number of the sample within its read, for the formats with SampleInfo.
    pub sequence_number: u32,
}

/// An INFO payload (reply and ObjectInfo) encoded whole, so that the ObjectInfo is aligned
/// relative to the payload start as on the wire.
pub(super) fn info_bytes(reply: BaseObjectReply, info: &ObjectInfo, dialect: Dialect) -> Vec<u8> {
    let mut buf = Vec::new();
    let w = &mut CdrWriter::new(&mut buf, true);
    reply.encode(w);
    info.encode(w, dialect);
    buf
}

/// An INFO message about the agent: its representation and activity (available, with
/// `locators`), answering `request`, with `header`'s session and key.
pub(crate) fn agent_info_message(
    header: MessageHeader,
    request: BaseObjectRequest,
    in_session: bool,
    dialect: Dialect,
    vendor_id: [u8; 2],
    locators: Vec<TransportLocator>,
) -> Vec<u8> {
    let reply = BaseObjectReply {
        related: request,
        result: ResultStatus {
            status: status::OK,
            implementation_status: in_session as u8,
        },
    };
    let info = ObjectInfo {
        activity: Some(ActivityInfo::Agent {
            availability: 1,
            locators,
        }),
        config: Some(ObjectConfig::Agent(AgentRepresentation {
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id,
            properties: None,
        })),
    };
    let h = MessageHeader {
        stream_id: stream_id::NONE,
        sequence_nr: 0,
        ..header
    };
    let mut b = MessageBuilder::new(h);
    let bytes = info_bytes(reply, &info, dialect);
    let _ = b.push(
        &Payload::Info(InfoPayload {
            reply,
            object_info: bytes.get(BaseObjectReply::LEN..).unwrap_or_default(),
        }),
        true,
    );
    b.finish()
}

impl<A: Endpoint> Agent<A> {
    /// Moves queued reliable submessages into free window slots and sends them.
    pub(super) fn flush_client(&mut self, now: Instant, key: ClientKey) {
        self.touch(key);
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let mut out = Vec::new();
        for (sid, s) in c.reliable_out.iter_mut() {
            while s.reliable.has_room() {
                let Some(sub) = s.queue.pop_front() else {
                    break;
                };
                s.queued_bytes -= sub.len();
                let mut msg = Vec::with_capacity(8 + sub.len());
                MessageHeader::new(c.session_id, *sid, s.reliable.next_seq(), c.key)
                    .encode(&mut msg);
                msg.extend_from_slice(&sub);
                s.reliable.record(msg.clone());
                out.push(msg);
            }
        }
        if c.detached {
            // Kept for when it comes back; its streams restart if it creates its session anew.
            return;
        }
        let unacked = c.reliable_out.values().any(|s| s.reliable.unacked() > 0);
        let mut schedule = false;
        if unacked && c.heartbeat_due.is_none() {
            c.heartbeat_due = Some(now + c.heartbeat_interval);
            schedule = true;
        }
        let addr = c.addr;
        for m in out {
            self.push_transmit(addr, m);
        }
        if schedule {
            self.schedule(key);
        }
    }

    /// One message if the submessage fits the client's MTU, else FRAGMENTs filling it, as
    /// the reference agent sends them.
    pub(super) fn fit_or_fragment(c: &ProxyClient<A>, sub: Vec<u8>) -> Vec<Vec<u8>> {
        let header_len = MessageHeader::encoded_len(c.session_id);
        if header_len + sub.len() <= c.mtu as usize {
            vec![sub]
        } else {
            fragments(&sub, c.mtu as usize - header_len - 4)
        }
    }

    pub(super) fn encode_submessage(
        payload: &Payload<'_>,
        little_endian: bool,
    ) -> Result<Vec<u8>, SendError> {
        crate::wire::encode_submessage(payload, little_endian).map_err(|_| SendError::TooLarge)
    }

    /// Queues submessages (each one message) on a reliable output stream: all or none.
    pub(super) fn queue_reliable(
        &mut self,
        key: ClientKey,
        stream: u8,
        subs: Vec<Vec<u8>>,
    ) -> Result<(), SendError> {
        let (window, max_queue) = (self.config.output_window, self.config.max_output_queue);
        let max_bytes = self.config.max_output_queue_bytes;
        let c = self.clients.get_mut(&key).ok_or(SendError::NoClient)?;
        let first = c.first_seq;
        let s = c.reliable_out.entry(stream).or_insert_with(|| OutStream {
            queued_bytes: 0,
            reliable: ReliableOutput::starting_at(stream, window, first),
            queue: VecDeque::new(),
        });
        let bytes: usize = subs.iter().map(Vec::len).sum();
        if s.queue.len() + subs.len() > max_queue || s.queued_bytes + bytes > max_bytes {
            self.count_drop("output_queue_full");
            return Err(SendError::QueueFull);
        }
        s.queued_bytes += bytes;
        s.queue.extend(subs);
        Ok(())
    }

    pub(super) fn queue_status(
        &mut self,
        key: ClientKey,
        request: BaseObjectRequest,
        result: ResultStatus,
    ) {
        let payload = Payload::Status(BaseObjectReply {
            related: request,
            result,
        });
        if let Ok(sub) = Self::encode_submessage(&payload, true) {
            let _ = self.queue_reliable(key, stream_id::BUILTIN_RELIABLE, vec![sub]);
        }
    }

    /// Queues a STATUS reply (on the built-in reliable stream, as the reference agent does).
    pub fn send_status(
        &mut self,
        now: Instant,
        key: ClientKey,
        request: BaseObjectRequest,
        result: ResultStatus,
    ) -> Result<(), SendError> {
        let Some(c) = self.clients.get_mut(&key) else {
            return Err(SendError::NoClient);
        };
        // The answer to a CREATE: a session holds objects once one was created.
        if let Some(i) = c
            .pending_creates
            .iter()
            .position(|o| *o == request.object_id)
        {
            c.pending_creates.swap_remove(i);
            c.has_objects |= status::is_ok(result.status);
        }
        self.queue_status(key, request, result);
        self.flush_client(now, key);
        self.account(key);
        Ok(())
    }

    /// Queues an INFO reply about one of the client's objects on the built-in reliable
    /// stream: `config` is the object's description when the client asked for it.
    pub fn send_info(
        &mut self,
        now: Instant,
        key: ClientKey,
        request: BaseObjectRequest,
        result: ResultStatus,
        config: Option<&ObjectVariant>,
    ) -> Result<(), SendError> {
        let dialect = self.dialect(key).ok_or(SendError::NoClient)?;
        let reply = BaseObjectReply {
            related: request,
            result,
        };
        let info = ObjectInfo {
            activity: None,
            config: config.cloned().map(ObjectConfig::Object),
        };
        let buf = info_bytes(reply, &info, dialect);
        let payload = Payload::Info(InfoPayload {
            reply,
            object_info: buf.get(BaseObjectReply::LEN..).unwrap_or_default(),
        });
        let sub = Self::encode_submessage(&payload, true)?;
        let c = self.clients.get(&key).ok_or(SendError::NoClient)?;
        let parts = Self::fit_or_fragment(c, sub);
        self.queue_reliable(key, stream_id::BUILTIN_RELIABLE, parts)?;
        self.flush_client(now, key);
        self.account(key);
        Ok(())
    }

    /// Queues a DATA reply for a read request on `stream` (0 = built-in reliable), in the
    /// DataFormat the read asked for.
    pub fn send_data(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        reply: DataReply<'_>,
    ) -> Result<(), SendError> {
        let dropped_before = self.stats.dropped_total;
        let result = self.queue_data(now, key, stream, reply);
        self.touch(key);
        let dropped = self.stats.dropped_total - dropped_before;
        let queued = result.is_ok() && dropped == 0;
        if let Some(c) = self.clients.get_mut(&key) {
            if queued {
                c.counters.samples_out += 1;
            } else {
                // Not queued (an error is counted by the caller in its own drops).
                c.counters.dropped += dropped.max(1);
            }
        }
        if queued {
            self.stats.samples_out += 1;
        }
        result
    }

    pub(super) fn queue_data(
        &mut self,
        now: Instant,
        key: ClientKey,
        stream: u8,
        reply: DataReply<'_>,
    ) -> Result<(), SendError> {
        let c = self.clients.get_mut(&key).ok_or(SendError::NoClient)?;
        let little_endian = reply.little_endian;
        let mut wrapped = Vec::new();
        let data = if reply.format == data_format::DATA {
            reply.sample
        } else {
            let offset = now.saturating_duration_since(c.established_at).as_millis();
            let info = SampleInfo {
                state: reply.state,
                detail: SampleInfoDetail::Both {
                    sequence_number: reply.sequence_number,
                    session_time_offset: u32::try_from(offset).unwrap_or(u32::MAX),
                },
            };
            let one = [SampleRef {
                info: Some(info),
                data: reply.sample,
            }];
            encode_samples(reply.format, &one, little_endian, c.dialect, &mut wrapped)
                .map_err(|_| SendError::BadFormat)?;
            &wrapped
        };
        let payload = Payload::Data(DataPayload {
            base: reply.request,
            format: reply.format,
            data,
        });
        let stream = if stream == stream_id::NONE {
            stream_id::BUILTIN_RELIABLE
        } else {
            stream
        };
        if stream_id::is_reliable(stream) {
            let sub = crate::wire::encode_large_submessage(&payload, little_endian)
                .map_err(|_| SendError::TooLarge)?;
            let parts = Self::fit_or_fragment(c, sub);
            let bytes: usize = parts.iter().map(Vec::len).sum();
            if !self.make_room(now, key, bytes, "memory_budget_output") {
                return Err(SendError::QueueFull);
            }
            self.queue_reliable(key, stream, parts)?;
            self.flush_client(now, key);
            self.account(key);
        } else if c.detached {
            self.count_drop("endpoint_closed");
        } else {
            let seq = c.best_effort_out.entry(stream).or_insert(c.first_seq);
            let mut b = MessageBuilder::new(MessageHeader::new(c.session_id, stream, *seq, c.key));
            b.push(&payload, little_endian)
                .map_err(|_| SendError::TooLarge)?;
            let message = b.finish();
            // A client that announced its MTU cannot take a bigger message (the eProsima
            // client's UDP buffer truncates it, its serial or TCP framing rejects it); for one
            // that announced none the MTU is assumed (for fragments), so only what the
            // transport carries bounds its best-effort messages, as before.
            let limit = if c.mtu_announced {
                c.mtu
            } else {
                self.config.max_message_size
            };
            if message.len() > usize::from(limit) {
                // A best-effort stream cannot fragment: dropped, as the reference agent does,
                // without using a sequence number; counted here (the client's drops too),
                // so not an error for the caller to count again.
                let (key, len) = (c.key, message.len());
                self.count_drop("over_mtu");
                let n = self.stats.dropped("over_mtu");
                if n.is_power_of_two() {
                    tracing::warn!(client = %key, mtu = limit, message = len, dropped = n, "best-effort sample dropped: larger than the client's MTU (read it on a reliable stream, which fragments, or build the client with a larger MTU); further ones are counted");
                }
                return Ok(());
            }
            *seq = seq.wrapping_add(1);
            let addr = c.addr;
            self.push_transmit(addr, message);
        }
        Ok(())
    }
}
