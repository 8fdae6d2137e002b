//! The transport seam: what the front-end's event loop needs of a way to reach clients.
//!
//! A transport owns its sockets or devices, registers them with the loop's [`mio::Registry`]
//! and turns readiness into whole XRCE messages from an endpoint of its own type (a UDP
//! address, a TCP connection, a serial line and address). The loop feeds those messages to
//! the sans-IO session core and hands the core's transmits back to [`Transport::send`]. Each
//! transport is one module:
//!
//! * [`udp`]: one datagram socket, one message per datagram (IPv4 or IPv6);
//! * [`tcp`]: a listener and its connections, messages with a 2-byte length prefix;
//! * [`multiserial`]: serial lines (`serial` is one, `multiserial` several, `pseudoterminal`
//!   one line on a pty), eProsima's stream framing, each line's clients by address; the
//!   devices themselves are opened by [`serial`] (a tty) and [`pty`] (a pseudoterminal);
//! * [`discovery`] is no transport of sessions but answers multicast agent discovery beside
//!   one.
//!
//! [`registry`] lists them, one line each, with the function of each module that opens it from
//! the front-end's settings.

pub mod discovery;
pub mod icmp;
pub mod multiserial;
pub mod pty;
pub mod registry;
pub mod serial;
pub mod tcp;
pub mod udp;

use std::collections::BTreeMap;
use std::fmt::Debug;
use std::hash::Hash;
use std::time::Instant;

use mio::event::Event;
use mio::Registry;
use xrce_common::session::budget::Origin;
use xrce_common::wire::info::TransportLocator;

/// A way to reach clients, driven by the front-end's event loop.
pub trait Transport {
    /// Identifies where a message came from and where a reply goes.
    type Endpoint: Copy + Eq + Hash + Debug + StoredEndpoint + Origin;

    /// Name for logs and counters (`udp4`, `tcp6`, `serial`, ...).
    fn name(&self) -> &'static str;

    /// Largest XRCE message it carries; the session core caps client MTUs to it.
    fn max_message_size(&self) -> u16;

    /// Registers its event sources; it owns every token from `first_token` on.
    fn register(&mut self, registry: &Registry, first_token: usize) -> std::io::Result<()>;

    /// Records the readiness of one of its tokens (no I/O beyond what writability allows).
    fn on_event(&mut self, event: &Event);

    /// Reads what is ready and hands each whole message to `deliver`, at most `budget`
    /// messages; returns whether input is left (call again without waiting for an event).
    fn receive(
        &mut self,
        now: Instant,
        budget: usize,
        deliver: &mut dyn FnMut(Self::Endpoint, &[u8]),
    ) -> bool;

    /// Sends one message to an endpoint, framed as the transport needs. Never blocks:
    /// output that cannot be written now waits in a bounded buffer of the endpoint; beyond
    /// it the message is dropped (counted) or, where one slow peer would otherwise hold
    /// memory for ever (TCP), its connection is closed.
    fn send(&mut self, to: Self::Endpoint, message: &[u8]);

    /// An endpoint that is gone for good since the last call (a closed connection).
    fn poll_closed(&mut self) -> Option<Self::Endpoint>;

    /// An endpoint whose host said nothing listens there any more (UDP: ICMP port
    /// unreachable) since the last call. The session there is kept (its client may come
    /// back); a claim on it from a new endpoint needs no longer wait for the probe.
    fn poll_unreachable(&mut self) -> Option<Self::Endpoint> {
        None
    }

    /// When [`Self::handle_timeout`] is due (devices waited for, reopened or probed).
    fn poll_timeout(&self) -> Option<Instant>;

    /// Runs due timers.
    fn handle_timeout(&mut self, now: Instant);

    /// Counters.
    fn stats(&self) -> &TransportStats;

    /// Where clients reach it, for discovery answers (empty for serial lines).
    fn locators(&self) -> Vec<TransportLocator>;

    /// What it serves, for status reports (an address and port, or devices).
    fn serving(&self) -> String;

    /// Where an endpoint is, for status reports and logs (a peer address, or a device and
    /// serial address).
    fn describe(&self, endpoint: Self::Endpoint) -> String;

    /// The endpoint [`StoredEndpoint::stored`] described, if this transport serves it.
    fn decode_endpoint(&self, bytes: &[u8]) -> Option<Self::Endpoint>;
}

/// An endpoint as bytes a successor front-end turns back into the same endpoint with
/// [`Transport::decode_endpoint`].
pub trait StoredEndpoint {
    /// Its bytes; empty when it would not outlive this process (a TCP connection closes
    /// with it).
    fn stored(&self) -> Vec<u8>;
}

impl StoredEndpoint for std::net::SocketAddr {
    fn stored(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(19);
        match self.ip() {
            std::net::IpAddr::V4(ip) => {
                out.push(4);
                out.extend_from_slice(&ip.octets());
            }
            std::net::IpAddr::V6(ip) => {
                out.push(6);
                out.extend_from_slice(&ip.octets());
            }
        }
        out.extend_from_slice(&self.port().to_le_bytes());
        if let std::net::SocketAddr::V6(v6) = self {
            // A link-local peer is only the same peer with its scope.
            out.extend_from_slice(&v6.flowinfo().to_le_bytes());
            out.extend_from_slice(&v6.scope_id().to_le_bytes());
        }
        out
    }
}

/// What a transport counted.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TransportStats {
    /// Whole messages received.
    pub messages_in: u64,
    /// Messages sent or buffered for sending.
    pub messages_out: u64,
    /// Endpoints opened (connections accepted, devices opened).
    pub opened: u64,
    /// Endpoints closed (connections, devices gone).
    pub closed: u64,
    /// Input and output dropped, by reason.
    pub dropped: BTreeMap<&'static str, u64>,
}

impl TransportStats {
    /// Counts one drop for `reason`; returns the new total for it (callers log on powers of
    /// two, so a flood is visible without a line per drop).
    pub fn drop(&mut self, reason: &'static str) -> u64 {
        let n = self.dropped.entry(reason).or_default();
        *n += 1;
        *n
    }

    /// Total drops for a reason.
    pub fn dropped(&self, reason: &str) -> u64 {
        self.dropped.get(reason).copied().unwrap_or(0)
    }

    /// Every drop.
    pub fn total_dropped(&self) -> u64 {
        self.dropped.values().sum()
    }
}

/// Whether an I/O error means the peer or device went away (an event, not a fault).
pub(crate) fn is_gone(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        ConnectionReset | ConnectionAborted | BrokenPipe | NotConnected | UnexpectedEof
    ) || matches!(
        e.raw_os_error(),
        Some(libc::EIO | libc::ENXIO | libc::ENODEV | libc::EPIPE | libc::ECONNRESET)
    )
}
