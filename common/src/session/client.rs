//! The client side of an XRCE session, as a sans-IO state machine.
//!
//! It speaks the eProsima dialect (vendor 01 0F, trailing MTU in CREATE_CLIENT) and behaves like
//! the reference client: one submessage per message, an ACKNACK for every reliable message
//! received and for every HEARTBEAT, HEARTBEATs while its own output is unacknowledged, and
//! CREATE_CLIENT retried until STATUS_AGENT arrives. Tests and the load generator drive it.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use super::fragment::{fragments, Reassembly};
use super::stream::{Arrival, BestEffortInput, ReliableInput, ReliableOutput};
use crate::wire::{
    stream_id, BaseObjectReply, BaseObjectRequest, ClientKey, CreateClientPayload, CreatePayload,
    DataPayload, GetInfoPayload, InfoPayload, MessageBuilder, MessageHeader, ObjectId,
    ObjectVariant, Payload, ReadDataPayload, ReadSpecification, RequestId, ResultStatus,
    Submessages, TimestampReplyPayload, VENDOR_EPROSIMA, XRCE_COOKIE, XRCE_VERSION,
};

/// Tunables of the client.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// The client key.
    pub key: ClientKey,
    /// Session id (≥ 0x81: no key in headers; the agent knows the client by address).
    pub session_id: u8,
    /// MTU announced in CREATE_CLIENT.
    pub mtu: u16,
    /// Unacknowledged messages per reliable output stream.
    pub output_window: usize,
    /// HEARTBEAT period while output is unacknowledged.
    pub heartbeat_period: Duration,
    /// CREATE_CLIENT retry period.
    pub connect_retry: Duration,
    /// Ask the agent for hard liveliness with this timeout (eProsima property `uxr_hl`).
    pub hard_liveliness: Option<Duration>,
    /// Byte order of the submessages the client sends on its streams (a big-endian
    /// microcontroller sends big-endian CREATE and WRITE_DATA).
    pub little_endian: bool,
    /// Vendor id announced in CREATE_CLIENT (eProsima's by default).
    pub vendor_id: [u8; 2],
    /// Number of the first message of every stream, both ways: 0 (eProsima's client), or 1
    /// as RTI's nano-client numbers them, which drops an agent's messages numbered below.
    pub first_seq: u16,
}

impl ClientConfig {
    /// Defaults for a client with this key.
    pub fn new(key: ClientKey) -> Self {
        ClientConfig {
            key,
            session_id: 0x81,
            mtu: 512,
            output_window: 16,
            heartbeat_period: Duration::from_millis(50),
            connect_retry: Duration::from_millis(250),
            hard_liveliness: None,
            little_endian: true,
            vendor_id: VENDOR_EPROSIMA,
            first_seq: 0,
        }
    }

    /// A client that behaves as RTI's nano-client does where agents must tell: RTI's vendor
    /// id, streams numbered from 1.
    pub fn like_rti(key: ClientKey) -> Self {
        ClientConfig {
            vendor_id: crate::wire::VENDOR_RTI,
            first_seq: 1,
            ..ClientConfig::new(key)
        }
    }
}

/// What the client learned from the agent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ClientEvent {
    /// The answer to CREATE_CLIENT.
    SessionStatus(ResultStatus),
    /// A STATUS reply.
    Status(BaseObjectReply),
    /// A DATA reply (the bytes after the BaseObjectRequest, in `format`).
    Data {
        /// The READ_DATA it answers.
        request: BaseObjectRequest,
        /// The DataFormat (FORMAT_DATA: `data` is the sample itself).
        format: u8,
        /// The stream it came on.
        stream_id: u8,
        /// The bytes after the BaseObjectRequest.
        data: Vec<u8>,
    },
    /// An INFO reply.
    Info(BaseObjectReply),
    /// A TIMESTAMP_REPLY.
    TimestampReply(TimestampReplyPayload),
}

/// Why a request could not be sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ClientError {
    /// The session is not established.
    #[error("not connected")]
    NotConnected,
    /// The reliable stream's window is full; try again after acknowledgements.
    #[error("reliable window full")]
    WindowFull,
    /// The payload does not fit a submessage.
    #[error("payload too large")]
    TooLarge,
}

/// One simulated XRCE client.
#[derive(Debug)]
pub struct Client {
    config: ClientConfig,
    connected: bool,
    connect_due: Option<Instant>,
    next_request: u16,
    reliable_out: HashMap<u8, ReliableOutput>,
    best_effort_out: HashMap<u8, u16>,
    reliable_in: HashMap<u8, ReliableInput>,
    /// Submessages waiting for room in a reliable output window.
    pending: HashMap<u8, VecDeque<Vec<u8>>>,
    reassembly: HashMap<u8, Reassembly>,
    best_effort_in: HashMap<u8, BestEffortInput>,
    heartbeat_due: Option<Instant>,
    transmits: VecDeque<Vec<u8>>,
    events: VecDeque<ClientEvent>,
}

impl Client {
    /// A client that has not connected yet.
    pub fn new(config: ClientConfig) -> Self {
        Client {
            config,
            connected: false,
            connect_due: None,
            next_request: 0x10,
            reliable_out: HashMap::new(),
            best_effort_out: HashMap::new(),
            reliable_in: HashMap::new(),
            pending: HashMap::new(),
            reassembly: HashMap::new(),
            best_effort_in: HashMap::new(),
            heartbeat_due: None,
            transmits: VecDeque::new(),
            events: VecDeque::new(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &ClientConfig {
        &self.config
    }

    /// Whether STATUS_AGENT OK arrived.
    pub fn is_connected(&self) -> bool {
        self.connected
    }

    fn header(&self, stream: u8, seq: u16) -> MessageHeader {
        MessageHeader::new(self.config.session_id, stream, seq, self.config.key)
    }

    fn create_client_message(&self) -> Vec<u8> {
        let p = Payload::CreateClient(CreateClientPayload {
            cookie: XRCE_COOKIE,
            version: XRCE_VERSION,
            vendor_id: self.config.vendor_id,
            client_key: self.config.key,
            session_id: self.config.session_id,
            properties: self.config.hard_liveliness.map(|t| {
                let ms = t.as_millis().min(999_999);
                vec![("uxr_hl".to_string(), format!("{ms:06}"))]
            }),
            mtu: Some(self.config.mtu),
        });
        let mut b = MessageBuilder::new(MessageHeader::new(
            self.config.session_id & 0x80,
            0,
            0,
            self.config.key,
        ));
        let _ = b.push(&p, true);
        b.finish()
    }

    /// Starts (or restarts) the session: CREATE_CLIENT, retried until answered.
    pub fn connect(&mut self, now: Instant) {
        self.connected = false;
        self.reliable_out.clear();
        self.best_effort_out.clear();
        self.reliable_in.clear();
        self.pending.clear();
        self.reassembly.clear();
        self.best_effort_in.clear();
        self.heartbeat_due = None;
        self.transmits.push_back(self.create_client_message());
        self.connect_due = Some(now + self.config.connect_retry);
    }

    /// Sends a GET_INFO to the agent (a ping); works without a session.
    pub fn ping(&mut self) -> RequestId {
        let request_id = self.next_request_id();
        let p = Payload::GetInfo(GetInfoPayload {
            base: BaseObjectRequest {
                request_id,
                object_id: ObjectId::AGENT,
            },
            info_mask: 3,
        });
        let session = if self.connected {
            self.config.session_id
        } else {
            self.config.session_id & 0x80
        };
        let mut b = MessageBuilder::new(MessageHeader::new(session, 0, 0, self.config.key));
        let _ = b.push(&p, true);
        self.transmits.push_back(b.finish());
        request_id
    }

    fn next_request_id(&mut self) -> RequestId {
        let id = RequestId::from_u16(self.next_request);
        self.next_request = self.next_request.wrapping_add(1).max(0x10);
        id
    }

    /// Whether a reliable stream can take another message now.
    pub fn can_send_reliable(&self, stream: u8) -> bool {
        self.reliable_out.get(&stream).is_none_or(|s| s.has_room())
            && self.pending.get(&stream).is_none_or(VecDeque::is_empty)
    }

    /// Messages not yet acknowledged on a reliable output stream.
    pub fn unacked(&self, stream: u8) -> usize {
        self.reliable_out.get(&stream).map_or(0, |s| s.unacked())
    }

    /// Sends a payload on a stream (reliable or best-effort).
    pub fn send(
        &mut self,
        now: Instant,
        stream: u8,
        payload: &Payload<'_>,
    ) -> Result<(), ClientError> {
        if !self.connected {
            return Err(ClientError::NotConnected);
        }
        if stream_id::is_reliable(stream) {
            if !self.can_send_reliable(stream) {
                return Err(ClientError::WindowFull);
            }
            let sub = crate::wire::encode_large_submessage(payload, self.config.little_endian)
                .map_err(|_| ClientError::TooLarge)?;
            let header_len = MessageHeader::encoded_len(self.config.session_id);
            let mtu = self.config.mtu as usize;
            let parts = if header_len + sub.len() <= mtu {
                vec![sub]
            } else {
                fragments(&sub, mtu.saturating_sub(header_len + 4))
            };
            self.pending.entry(stream).or_default().extend(parts);
            self.flush_reliable(now, stream);
        } else {
            let first = self.config.first_seq;
            let seq = self.best_effort_out.entry(stream).or_insert(first);
            let mut b = MessageBuilder::new(MessageHeader::new(
                self.config.session_id,
                stream,
                *seq,
                self.config.key,
            ));
            *seq = seq.wrapping_add(1);
            b.push(payload, self.config.little_endian)
                .map_err(|_| ClientError::TooLarge)?;
            self.transmits.push_back(b.finish());
        }
        Ok(())
    }

    /// Sends queued submessages of a reliable stream while its window has room.
    fn flush_reliable(&mut self, now: Instant, stream: u8) {
        let (window, first) = (self.config.output_window, self.config.first_seq);
        let out = self
            .reliable_out
            .entry(stream)
            .or_insert_with(|| ReliableOutput::starting_at(stream, window, first));
        let Some(queue) = self.pending.get_mut(&stream) else {
            return;
        };
        let mut sent = false;
        while out.has_room() {
            let Some(sub) = queue.pop_front() else { break };
            let mut msg = Vec::with_capacity(8 + sub.len());
            MessageHeader::new(
                self.config.session_id,
                stream,
                out.next_seq(),
                self.config.key,
            )
            .encode(&mut msg);
            msg.extend_from_slice(&sub);
            out.record(msg.clone());
            self.transmits.push_back(msg);
            sent = true;
        }
        if sent && self.heartbeat_due.is_none() {
            self.heartbeat_due = Some(now + self.config.heartbeat_period);
        }
    }

    /// CREATE on the built-in reliable stream.
    pub fn create(
        &mut self,
        now: Instant,
        object_id: ObjectId,
        variant: ObjectVariant,
        reuse: bool,
        replace: bool,
    ) -> Result<RequestId, ClientError> {
        let request_id = self.next_request_id();
        let p = Payload::Create(CreatePayload {
            base: BaseObjectRequest {
                request_id,
                object_id,
            },
            variant,
            reuse,
            replace,
        });
        self.send(now, stream_id::BUILTIN_RELIABLE, &p)?;
        Ok(request_id)
    }

    /// DELETE on the built-in reliable stream (`ObjectId::CLIENT` ends the session).
    pub fn delete(&mut self, now: Instant, object_id: ObjectId) -> Result<RequestId, ClientError> {
        let request_id = self.next_request_id();
        self.send(
            now,
            stream_id::BUILTIN_RELIABLE,
            &Payload::Delete(BaseObjectRequest {
                request_id,
                object_id,
            }),
        )?;
        Ok(request_id)
    }

    /// Ends the session as eProsima's `uxr_delete_session` does: a DELETE of the client
    /// object on stream 0 (outside the reliable streams, so it can be sent again as it is),
    /// request id LOGOUT (0x0002); the STATUS comes back on stream 0. Sent again by the
    /// caller until answered; the session counts as ended from the first.
    pub fn delete_session(&mut self, _now: Instant) -> Result<RequestId, ClientError> {
        let request_id = RequestId::from_u16(0x0002);
        let p = Payload::Delete(BaseObjectRequest {
            request_id,
            object_id: ObjectId::CLIENT,
        });
        let header =
            MessageHeader::new(self.config.session_id, stream_id::NONE, 0, self.config.key);
        let mut b = MessageBuilder::new(header);
        b.push(&p, self.config.little_endian)
            .map_err(|_| ClientError::TooLarge)?;
        self.transmits.push_back(b.finish());
        Ok(request_id)
    }

    /// WRITE_DATA in FORMAT_DATA on `stream`.
    pub fn write(
        &mut self,
        now: Instant,
        stream: u8,
        writer: ObjectId,
        sample: &[u8],
    ) -> Result<RequestId, ClientError> {
        self.write_format(now, stream, writer, crate::wire::data_format::DATA, sample)
    }

    /// WRITE_DATA in any DataFormat: `data` is what follows the BaseObjectRequest.
    pub fn write_format(
        &mut self,
        now: Instant,
        stream: u8,
        writer: ObjectId,
        format: u8,
        data: &[u8],
    ) -> Result<RequestId, ClientError> {
        let request_id = self.next_request_id();
        let p = Payload::WriteData(DataPayload {
            base: BaseObjectRequest {
                request_id,
                object_id: writer,
            },
            format,
            data,
        });
        self.send(now, stream, &p)?;
        Ok(request_id)
    }

    /// READ_DATA on the built-in reliable stream.
    pub fn read(
        &mut self,
        now: Instant,
        reader: ObjectId,
        spec: ReadSpecification,
    ) -> Result<RequestId, ClientError> {
        let request_id = self.next_request_id();
        let p = Payload::ReadData(ReadDataPayload {
            base: BaseObjectRequest {
                request_id,
                object_id: reader,
            },
            spec,
        });
        self.send(now, stream_id::BUILTIN_RELIABLE, &p)?;
        Ok(request_id)
    }

    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.transmits.pop_front()
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<ClientEvent> {
        self.events.pop_front()
    }

    /// When [`Self::handle_timeout`] should run next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match (self.connect_due, self.heartbeat_due) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Retries CREATE_CLIENT and sends HEARTBEATs when due.
    pub fn handle_timeout(&mut self, now: Instant) {
        if let Some(due) = self.connect_due {
            if due <= now {
                self.transmits.push_back(self.create_client_message());
                self.connect_due = Some(now + self.config.connect_retry);
            }
        }
        if let Some(due) = self.heartbeat_due {
            if due <= now {
                let mut any = false;
                let header = self.header(stream_id::NONE, 0);
                for s in self.reliable_out.values() {
                    if let Some(hb) = s.heartbeat() {
                        let mut b = MessageBuilder::new(header);
                        let _ = b.push(&Payload::Heartbeat(hb), true);
                        self.transmits.push_back(b.finish());
                        any = true;
                    }
                }
                self.heartbeat_due = any.then_some(now + self.config.heartbeat_period);
            }
        }
    }

    /// Processes messages that arrived early and are now next.
    fn deliver_ready(&mut self, now: Instant, stream: u8) {
        while let Some(next) = self
            .reliable_in
            .get_mut(&stream)
            .and_then(ReliableInput::take_ready)
        {
            if let Some(i) = self.reliable_in.get_mut(&stream) {
                i.advance();
            }
            if let Ok((_, h)) = MessageHeader::decode(&next) {
                self.process(now, stream, &next, h);
            }
        }
    }

    fn send_acknack(&mut self, stream: u8) {
        if let Some(input) = self.reliable_in.get(&stream) {
            let mut b = MessageBuilder::new(self.header(stream_id::NONE, 0));
            let _ = b.push(&Payload::Acknack(input.acknack(stream)), true);
            self.transmits.push_back(b.finish());
        }
    }

    /// Handles a datagram from the agent. Malformed input is ignored.
    pub fn handle_datagram(&mut self, now: Instant, bytes: &[u8]) {
        let Ok((header, hlen)) = MessageHeader::decode(bytes) else {
            return;
        };
        let stream = header.stream_id;
        if stream == stream_id::NONE {
            self.process(now, stream, bytes, hlen);
        } else if !stream_id::is_reliable(stream) {
            let first = self.config.first_seq;
            if self
                .best_effort_in
                .entry(stream)
                .or_insert_with(|| {
                    if first == 0 {
                        BestEffortInput::default()
                    } else {
                        // Numbered from `first`: anything below is taken for old.
                        BestEffortInput::resuming(first.wrapping_sub(1))
                    }
                })
                .accept(header.sequence_nr)
            {
                self.process(now, stream, bytes, hlen);
            }
        } else {
            let first = self.config.first_seq;
            let input = self
                .reliable_in
                .entry(stream)
                .or_insert_with(|| ReliableInput::resuming(16, first));
            match input.classify(header.sequence_nr) {
                Arrival::InOrder => {
                    input.advance();
                    self.process(now, stream, bytes, hlen);
                    self.deliver_ready(now, stream);
                }
                Arrival::Early => input.store_early(header.sequence_nr, bytes.to_vec()),
                Arrival::Duplicate | Arrival::OutOfWindow => {}
            }
            self.send_acknack(stream);
        }
    }

    fn process(&mut self, now: Instant, stream: u8, bytes: &[u8], hlen: usize) {
        for raw in Submessages::new(bytes, hlen) {
            let Ok(payload) = raw.and_then(|r| r.decode()) else {
                return;
            };
            if let Payload::Fragment { last, data } = payload {
                let whole = self
                    .reassembly
                    .entry(stream)
                    .or_default()
                    .push(data, last, 1 << 20);
                if let Ok(Some(whole)) = whole {
                    for raw in Submessages::reassembled(&whole) {
                        match raw.and_then(|r| r.decode()) {
                            Ok(Payload::Fragment { .. }) | Err(_) => break,
                            Ok(p) => self.on_payload(now, stream, p),
                        }
                    }
                }
                continue;
            }
            self.on_payload(now, stream, payload);
        }
    }

    fn on_payload(&mut self, now: Instant, stream: u8, payload: Payload<'_>) {
        match payload {
            Payload::StatusAgent(s) => {
                let result = s.result.unwrap_or(ResultStatus::OK);
                if self.connect_due.is_some() {
                    self.connect_due = None;
                    self.connected = crate::wire::status::is_ok(result.status);
                    self.events.push_back(ClientEvent::SessionStatus(result));
                }
            }
            Payload::Status(s) => self.events.push_back(ClientEvent::Status(s)),
            Payload::Info(i) => self.events.push_back(ClientEvent::Info(i.reply)),
            Payload::GetInfo(g) => {
                // The agent checks that we are alive: answer at once, as eProsima's client does.
                let reply = BaseObjectReply {
                    related: g.base,
                    result: ResultStatus::OK,
                };
                let mut b = MessageBuilder::new(self.header(stream_id::NONE, 0));
                let _ = b.push(
                    &Payload::Info(InfoPayload {
                        reply,
                        object_info: &[0, 0],
                    }),
                    true,
                );
                self.transmits.push_back(b.finish());
            }
            Payload::Data(d) => self.events.push_back(ClientEvent::Data {
                request: d.base,
                format: d.format,
                stream_id: stream,
                data: d.data.to_vec(),
            }),
            Payload::Acknack(a) => {
                if let Some(out) = self.reliable_out.get_mut(&a.stream_id) {
                    let resend: Vec<Vec<u8>> =
                        out.on_acknack(&a).into_iter().map(<[u8]>::to_vec).collect();
                    self.transmits.extend(resend);
                }
                self.flush_reliable(now, a.stream_id);
                if self.reliable_out.values().all(|s| s.unacked() == 0) {
                    self.heartbeat_due = None;
                } else if self.heartbeat_due.is_none() {
                    self.heartbeat_due = Some(now + self.config.heartbeat_period);
                }
            }
            Payload::Heartbeat(h) => {
                let first = self.config.first_seq;
                let input = self
                    .reliable_in
                    .entry(h.stream_id)
                    .or_insert_with(|| ReliableInput::resuming(16, first));
                input.on_heartbeat(&h);
                self.deliver_ready(now, h.stream_id);
                self.send_acknack(h.stream_id);
            }
            Payload::TimestampReply(t) => self.events.push_back(ClientEvent::TimestampReply(t)),
            _ => {}
        }
    }
}
