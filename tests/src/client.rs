//! A Rust XRCE client for the tests, over any [`Link`], on `xrce_common`'s client state
//! machine.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind, stream_id, ClientKey, ObjectId, ObjectVariant, ReadSpecification, Representation,
    RequestId, VariantExtra,
};

use crate::*;

/// A Rust XRCE client over a [`Link`] (UDP, TCP or a serial line), driving `xrce_common`'s
/// client state machine.
#[derive(Debug)]
pub struct TestClient {
    /// The protocol state.
    pub client: Client,
    /// How it reaches the agent.
    pub link: Link,
    /// Events received and not yet consumed.
    pub events: Vec<ClientEvent>,
    /// Messages sent so far.
    pub sent: u64,
    buf: Vec<u8>,
}

impl TestClient {
    /// A client with `key`, talking to `agent`.
    pub fn new(agent: SocketAddr, key: [u8; 4]) -> Self {
        Self::with_config(agent, ClientConfig::new(ClientKey(key)))
    }

    /// A client with its own settings (byte order, liveliness, ...), talking to `agent`.
    pub fn with_config(agent: SocketAddr, config: ClientConfig) -> Self {
        Self::on_link(Link::udp(agent), config)
    }

    /// A client with `key` on a TCP connection to `agent`.
    pub fn tcp(agent: SocketAddr, key: [u8; 4]) -> Self {
        let link = Link::tcp(agent).expect("TCP connection to the agent");
        Self::on_link(link, ClientConfig::new(ClientKey(key)))
    }

    /// A client with `key` at `address` on a serial line.
    pub fn serial(line: std::fs::File, address: u8, key: [u8; 4]) -> Self {
        Self::on_link(
            Link::serial(line, address),
            ClientConfig::new(ClientKey(key)),
        )
    }

    /// A client on any link.
    pub fn on_link(link: Link, config: ClientConfig) -> Self {
        TestClient {
            client: Client::new(config),
            link,
            events: Vec::new(),
            sent: 0,
            buf: vec![0; 65_536],
        }
    }

    /// Runs the protocol for up to `d`, or until `done` says so.
    pub fn run_until(&mut self, d: Duration, mut done: impl FnMut(&mut Self) -> bool) -> bool {
        let end = Instant::now() + d;
        loop {
            self.step();
            if done(self) {
                return true;
            }
            if Instant::now() >= end {
                return false;
            }
        }
    }

    /// How many times the agent answered this client's CREATE_CLIENT (a client that had to
    /// create its session again shows more than one).
    pub fn session_statuses(&self) -> usize {
        self.events
            .iter()
            .filter(|e| matches!(e, ClientEvent::SessionStatus(_)))
            .count()
    }

    /// One round: flush, receive what arrived (up to 5 ms), fire timers.
    pub fn step(&mut self) {
        while let Some(t) = self.client.poll_transmit() {
            self.sent += u64::from(self.link.send(&t));
        }
        for m in self.link.receive(Duration::from_millis(5), &mut self.buf) {
            self.client.handle_datagram(Instant::now(), &m);
        }
        self.client.handle_timeout(Instant::now());
        while let Some(e) = self.client.poll_event() {
            self.events.push(e);
        }
        while let Some(t) = self.client.poll_transmit() {
            self.sent += u64::from(self.link.send(&t));
        }
    }

    /// Opens the session; panics if the agent does not accept it within `d`.
    pub fn connect(&mut self, d: Duration) {
        self.client.connect(Instant::now());
        let ok = self.run_until(d, |c| c.client.is_connected());
        assert!(ok, "session not established: {:?}", self.events);
    }

    /// Creates an object and waits for its STATUS; returns the status value.
    pub fn create(&mut self, id: ObjectId, kind: u8, xml: &str, extra: VariantExtra) -> u8 {
        self.create_as(id, kind, Representation::Xml(xml.into()), extra)
    }

    /// Creates an object from any representation and waits for its STATUS.
    pub fn create_as(
        &mut self,
        id: ObjectId,
        kind: u8,
        representation: Representation,
        extra: VariantExtra,
    ) -> u8 {
        if let VariantExtra::DomainId(domain) = extra {
            // A participant: its domain is the running test's module's ([`crate::domains`]).
            crate::domains::claim(u32::from(domain as u16));
        }
        let variant = ObjectVariant {
            kind,
            representation,
            extra,
        };
        let req = self
            .client
            .create(Instant::now(), id, variant, false, true)
            .expect("create");
        self.wait_status(req, Duration::from_secs(20))
    }

    /// Waits for the STATUS of `req`.
    pub fn wait_status(&mut self, req: RequestId, d: Duration) -> u8 {
        let mut found = None;
        self.run_until(d, |c| {
            if let Some(i) = c
                .events
                .iter()
                .position(|e| matches!(e, ClientEvent::Status(s) if s.related.request_id == req))
            {
                if let ClientEvent::Status(s) = c.events.remove(i) {
                    found = Some(s.result.status);
                }
                return true;
            }
            false
        });
        found.unwrap_or_else(|| panic!("no STATUS for request {req:?}"))
    }

    /// Creates the HelloWorld chain participant (in `domain`) → topic → `group` (publisher
    /// or subscriber) → `endpoint` (writer or reader), asserting every STATUS is OK; returns
    /// the endpoint id.
    pub fn setup_chain(
        &mut self,
        domain: i16,
        group: u8,
        endpoint: u8,
        endpoint_xml: &str,
    ) -> ObjectId {
        let p = ObjectId::new(1, object_kind::PARTICIPANT);
        let t = ObjectId::new(1, object_kind::TOPIC);
        let g = ObjectId::new(1, group);
        let e = ObjectId::new(1, endpoint);
        let steps = [
            (
                p,
                object_kind::PARTICIPANT,
                xml::PARTICIPANT,
                VariantExtra::DomainId(domain),
            ),
            (t, object_kind::TOPIC, xml::TOPIC, VariantExtra::Parent(p)),
            (g, group, "", VariantExtra::Parent(p)),
            (e, endpoint, endpoint_xml, VariantExtra::Parent(g)),
        ];
        for (id, kind, xml, extra) in steps {
            assert_eq!(self.create(id, kind, xml, extra), 0, "creating {id:?}");
        }
        e
    }

    /// Creates participant (in `domain`), topic, publisher and writer of the HelloWorld
    /// example; returns the writer id.
    pub fn setup_publisher(&mut self, domain: i16) -> ObjectId {
        self.setup_chain(
            domain,
            object_kind::PUBLISHER,
            object_kind::DATAWRITER,
            xml::WRITER,
        )
    }

    /// Creates participant, topic, subscriber and reader of the HelloWorld example and
    /// starts an unlimited READ_DATA on the reliable stream; returns the reader id.
    pub fn setup_subscriber(&mut self, domain: i16) -> ObjectId {
        self.setup_subscriber_with(domain, unlimited_reliable_read())
    }

    /// Participant, topic, subscriber and HelloWorld reader in `domain`, then READ_DATA with
    /// `spec`.
    pub fn setup_subscriber_with(&mut self, domain: i16, spec: ReadSpecification) -> ObjectId {
        let r = self.setup_chain(
            domain,
            object_kind::SUBSCRIBER,
            object_kind::DATAREADER,
            xml::READER,
        );
        self.client.read(Instant::now(), r, spec).expect("read");
        r
    }

    /// A participant in `domain` and an adder requester or replier (`kind`) under it, with an
    /// unlimited read started on it; returns the requester's or replier's id. (With either
    /// DDS backend: Cyclone DDS's C API cannot send a related sample identity, so with it the
    /// worker serves requesters and repliers through RustDDS beside it.)
    pub fn setup_adder(&mut self, domain: i16, kind: u8) -> ObjectId {
        let p = ObjectId::new(1, object_kind::PARTICIPANT);
        let e = ObjectId::new(1, kind);
        let status = self.create(
            p,
            object_kind::PARTICIPANT,
            xml::PARTICIPANT,
            VariantExtra::DomainId(domain),
        );
        assert_eq!(status, 0, "creating the participant");
        let element = if kind == object_kind::REQUESTER {
            "requester"
        } else {
            "replier"
        };
        let x = xml::ADDER_SERVICE.replace("{e}", element);
        let status = self.create(e, kind, &x, VariantExtra::Parent(p));
        assert_eq!(status, 0, "creating the {element}");
        self.read_unlimited(e);
        e
    }

    /// Takes the adder replies this requester (`req`) received so far into `answered` (the
    /// sums, by request id; a reply repeated shows as a second sum), checking that each
    /// names the requester.
    pub fn take_adder_replies(
        &mut self,
        req: ObjectId,
        answered: &mut std::collections::HashMap<RequestId, Vec<u32>>,
    ) {
        for (_, d) in self.take_data() {
            assert!(d.len() >= 8, "reply too short: {d:?}");
            assert_eq!(
                ObjectId([d[2], d[3]]),
                req,
                "the BaseObjectRequest names the requester"
            );
            let sum = u32::from_le_bytes([d[4], d[5], d[6], d[7]]);
            answered
                .entry(RequestId([d[0], d[1]]))
                .or_default()
                .push(sum);
        }
    }

    /// Whether the agent still serves this client's session: the STATUS of a DELETE of an
    /// object it never created (ERR_UNKNOWN_REFERENCE from a live session), within `d`.
    pub fn session_answers(&mut self, d: Duration) -> bool {
        let req = self
            .client
            .delete(Instant::now(), ObjectId::new(9, object_kind::DATAWRITER))
            .expect("delete");
        self.wait_status(req, d) == xrce_common::wire::status::ERR_UNKNOWN_REFERENCE
    }

    /// WRITE_DATA (FORMAT_DATA) on the reliable stream; returns its request id.
    pub fn write_reliable_id(&mut self, writer: ObjectId, sample: &[u8]) -> RequestId {
        let ok = self.run_until(Duration::from_secs(60), |c| {
            c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        });
        assert!(ok, "reliable window never opened");
        let id = self
            .client
            .write(Instant::now(), stream_id::BUILTIN_RELIABLE, writer, sample)
            .expect("write");
        self.step();
        id
    }

    /// READ_DATA on the reliable stream with unlimited delivery (data readers, requesters,
    /// repliers).
    pub fn read_unlimited(&mut self, object: ObjectId) {
        self.client
            .read(Instant::now(), object, crate::unlimited_reliable_read())
            .expect("read");
    }

    /// WRITE_DATA in `format` on the reliable stream (`data` follows the BaseObjectRequest).
    pub fn write_reliable_format(&mut self, writer: ObjectId, format: u8, data: &[u8]) {
        let ok = self.run_until(Duration::from_secs(60), |c| {
            c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        });
        assert!(ok, "reliable window never opened");
        self.client
            .write_format(
                Instant::now(),
                stream_id::BUILTIN_RELIABLE,
                writer,
                format,
                data,
            )
            .expect("write");
        self.step();
    }

    /// Every DATA received so far as (format, bytes after the BaseObjectRequest).
    pub fn take_data(&mut self) -> Vec<(u8, Vec<u8>)> {
        let mut out = Vec::new();
        self.events.retain(|e| match e {
            ClientEvent::Data { format, data, .. } => {
                out.push((*format, data.clone()));
                false
            }
            _ => true,
        });
        out
    }

    /// Writes on the reliable stream, waiting for window room.
    pub fn write_reliable(&mut self, writer: ObjectId, sample: &[u8]) {
        let ok = self.run_until(Duration::from_secs(60), |c| {
            c.client.can_send_reliable(stream_id::BUILTIN_RELIABLE)
        });
        assert!(ok, "reliable window never opened");
        self.client
            .write(Instant::now(), stream_id::BUILTIN_RELIABLE, writer, sample)
            .expect("write");
        self.step();
    }

    /// Writes on the best-effort stream (nothing waits: what is lost is lost).
    pub fn write_best_effort(&mut self, writer: ObjectId, sample: &[u8]) {
        self.client
            .write(
                Instant::now(),
                stream_id::BUILTIN_BEST_EFFORT,
                writer,
                sample,
            )
            .expect("write");
        self.step();
    }

    /// HelloWorld samples received so far (consumed from `events`). A DATA that is not a
    /// HelloWorld sample fails the test: a corrupted sample must not pass as a lost one.
    pub fn take_samples(&mut self) -> Vec<(u32, String)> {
        let mut out = Vec::new();
        self.events.retain(|e| match e {
            ClientEvent::Data { data, .. } => {
                match parse_hello_world(data) {
                    Some(s) => out.push(s),
                    None => panic!("a DATA that is not a HelloWorld sample: {data:?}"),
                }
                false
            }
            _ => true,
        });
        out
    }
}

impl TestClient {
    /// Records the HelloWorld samples this client receives (checking each message is
    /// `message`) until `want` distinct ones arrived and [`DUPLICATE_GRACE`] passed, or `d`
    /// passed.
    pub fn collect_deliveries(&mut self, want: usize, message: &str, d: Duration) -> Deliveries {
        let mut got = Deliveries::default();
        let end = Instant::now() + d;
        let mut complete_at: Option<Instant> = None;
        while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
            self.step();
            for (i, m) in self.take_samples() {
                assert_eq!(m, message, "sample {i} carries another message");
                got.record(i);
            }
            if complete_at.is_none() && got.distinct() >= want {
                complete_at = Some(Instant::now());
            }
        }
        got
    }
}
