//! Simulated clients: common's client state machine and a link each (UDP socket, TCP
//! connection or paced serial line), polled through one epoll set per group of clients.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashSet};
use std::net::{TcpStream, UdpSocket};
use std::time::{Duration, Instant};

use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::{
    status, ClientKey, ObjectId, ObjectVariant, Representation, RequestId, VariantExtra,
};

use crate::link::PeerLink;

/// One simulated client: its protocol state and its link to the agent.
pub struct Peer {
    /// The client's protocol state.
    pub client: Client,
    link: PeerLink,
    /// Creations whose STATUS has not come yet.
    pub pending: HashSet<RequestId>,
    /// The client's next timer, as of its last pump.
    next_timeout: Option<Instant>,
    /// The timer entered in its group's heap (at most one live entry per client).
    registered: Option<Instant>,
    /// The group's pump round in which it was last pumped.
    round: u64,
}

impl Peer {
    /// A client with its own socket on `source`, connected to the agent's port on
    /// 127.0.0.1.
    pub fn new(
        source: std::net::Ipv4Addr,
        port: u16,
        key: [u8; 4],
        mtu: u16,
    ) -> std::io::Result<Self> {
        let socket = UdpSocket::bind((source, 0))?;
        socket.connect(("127.0.0.1", port))?;
        socket.set_nonblocking(true)?;
        Ok(Self::on_link(PeerLink::Udp(socket), key, mtu))
    }

    /// A client on its own TCP connection to the agent's port on 127.0.0.1.
    pub fn tcp(port: u16, key: [u8; 4], mtu: u16) -> std::io::Result<Self> {
        let stream = TcpStream::connect(("127.0.0.1", port))?;
        stream.set_nodelay(true)?;
        stream.set_nonblocking(true)?;
        Ok(Self::on_link(PeerLink::tcp(stream), key, mtu))
    }

    /// A client on a serial line (a pty master) paced at `baud`.
    pub fn serial(line: std::fs::File, baud: u32, key: [u8; 4], mtu: u16) -> Self {
        Self::on_link(PeerLink::serial(line, baud), key, mtu)
    }

    /// A client announcing `mtu` (the largest message it takes: the agent sends nothing
    /// bigger, and drops a best-effort sample that does not fit).
    fn on_link(link: PeerLink, key: [u8; 4], mtu: u16) -> Self {
        let mut config = ClientConfig::new(ClientKey(key));
        config.mtu = mtu;
        Peer {
            client: Client::new(config),
            link,
            pending: HashSet::new(),
            next_timeout: None,
            registered: None,
            round: 0,
        }
    }

    /// Sends what is due, receives what arrived (if `readable`), and collects events, each
    /// with `index` (the peer's place in its group).
    fn pump(
        &mut self,
        index: usize,
        now: Instant,
        readable: bool,
        buf: &mut [u8],
        events: &mut Vec<(usize, ClientEvent)>,
    ) -> Result<(), String> {
        if readable {
            let client = &mut self.client;
            self.link.receive(buf, |m| client.handle_datagram(now, m));
        }
        if self.client.poll_timeout().is_some_and(|t| t <= now) {
            self.client.handle_timeout(now);
        }
        self.link.flush(now);
        while let Some(t) = self.client.poll_transmit() {
            self.link.send(&t, now);
        }
        self.next_timeout = match (self.client.poll_timeout(), self.link.next_flush(now)) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        for e in std::iter::from_fn(|| self.client.poll_event()) {
            match e {
                ClientEvent::Status(s) if self.pending.remove(&s.related.request_id) => {
                    if s.result.status != status::OK {
                        return Err(format!(
                            "creation refused with status {:#04x}",
                            s.result.status
                        ));
                    }
                }
                other => events.push((index, other)),
            }
        }
        Ok(())
    }

    /// Queues a CREATE; its STATUS is awaited through `pending`.
    pub fn create(
        &mut self,
        id: ObjectId,
        kind: u8,
        representation: Representation,
        extra: VariantExtra,
    ) -> Result<(), String> {
        let v = ObjectVariant {
            kind,
            representation,
            extra,
        };
        let req = self
            .client
            .create(Instant::now(), id, v, false, true)
            .map_err(|e| e.to_string())?;
        self.pending.insert(req);
        Ok(())
    }
}

/// A group of clients polled together, one thread's worth. An iteration costs one epoll
/// call plus the clients that have something to do (data arrived, a timer due, something
/// queued), so thousands of idle clients cost nothing.
pub struct Group {
    /// The group's clients.
    pub peers: Vec<Peer>,
    epoll: nix::sys::epoll::Epoll,
    events: Vec<nix::sys::epoll::EpollEvent>,
    /// Clients with something queued since their last pump.
    queued: Vec<usize>,
    /// Clients' timers: (when, client); stale entries are skipped.
    timers: BinaryHeap<Reverse<(Instant, usize)>>,
    round: u64,
    buf: Vec<u8>,
}

impl Group {
    /// Registers every peer's socket; every peer is pumped once on the first pump.
    pub fn new(mut peers: Vec<Peer>) -> Result<Self, String> {
        use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags};
        // A new heap: every client registers its timer again on its first pump.
        for p in &mut peers {
            p.registered = None;
            p.round = 0;
        }
        let epoll = Epoll::new(EpollCreateFlags::empty()).map_err(|e| e.to_string())?;
        for (i, p) in peers.iter().enumerate() {
            epoll
                .add(p.link.fd(), EpollEvent::new(EpollFlags::EPOLLIN, i as u64))
                .map_err(|e| e.to_string())?;
        }
        let n = peers.len();
        Ok(Group {
            peers,
            epoll,
            events: vec![EpollEvent::empty(); 1024],
            queued: (0..n).collect(),
            timers: BinaryHeap::new(),
            round: 0,
            buf: vec![0u8; 65_536],
        })
    }

    /// Splits the peers into groups of the given sizes (in order), each with its own epoll.
    pub fn split(self, sizes: &[usize]) -> Result<Vec<Group>, String> {
        let Group { mut peers, .. } = self;
        let mut parts = Vec::with_capacity(sizes.len());
        for &n in sizes.iter().rev() {
            let at = peers.len().saturating_sub(n);
            parts.push(peers.split_off(at));
        }
        parts.into_iter().rev().map(Group::new).collect()
    }

    /// Marks client `i` as having something to send (after a write, a create or a read).
    pub fn touch(&mut self, i: usize) {
        self.queued.push(i);
    }

    /// Queues a sample on client `i`'s stream and marks it.
    pub fn write(&mut self, i: usize, stream: u8, writer: ObjectId, data: &[u8]) {
        if let Some(p) = self.peers.get_mut(i) {
            let _ = p.client.write(Instant::now(), stream, writer, data);
            self.queued.push(i);
        }
    }

    /// The earliest client timer.
    pub fn next_timer(&self) -> Option<Instant> {
        self.timers.peek().map(|Reverse((t, _))| *t)
    }

    /// Waits up to `wait` for data (not at all if something is queued or a timer is due),
    /// then lets every client with something to do handle it: received data, due timers,
    /// queued sends.
    pub fn pump(
        &mut self,
        events: &mut Vec<(usize, ClientEvent)>,
        wait: Duration,
    ) -> Result<(), String> {
        let now = Instant::now();
        let wait = if !self.queued.is_empty() || self.next_timer().is_some_and(|t| t <= now) {
            Duration::ZERO
        } else {
            self.next_timer()
                .map_or(wait, |t| wait.min(t.saturating_duration_since(now)))
        };
        let ms = u16::try_from(wait.as_millis()).unwrap_or(u16::MAX);
        let n = match self
            .epoll
            .wait(&mut self.events, nix::sys::epoll::EpollTimeout::from(ms))
        {
            Ok(n) => n,
            Err(nix::errno::Errno::EINTR) => 0,
            Err(e) => return Err(format!("epoll_wait: {e}")),
        };
        self.round += 1;
        let round = self.round;
        let now = Instant::now();
        let mut due = std::mem::take(&mut self.queued);
        while let Some(Reverse((t, i))) = self.timers.peek().copied() {
            if t > now {
                break;
            }
            self.timers.pop();
            // Only the client's live entry counts (older ones were superseded).
            if let Some(p) = self.peers.get_mut(i).filter(|p| p.registered == Some(t)) {
                p.registered = None;
                due.push(i);
            }
        }
        let ready = self.events[..n].iter().map(|e| (e.data() as usize, true));
        let all: Vec<(usize, bool)> = ready.chain(due.drain(..).map(|i| (i, false))).collect();
        for (i, readable) in all {
            let Some(p) = self.peers.get_mut(i) else {
                continue;
            };
            // Once per round: a client both readable and queued is pumped when readable.
            if p.round == round {
                continue;
            }
            p.round = round;
            p.pump(i, now, readable, &mut self.buf, events)?;
            // A new entry only when the timer is earlier than the live one (a later timer
            // is looked at when the live entry falls due).
            if let Some(t) = p
                .next_timeout
                .filter(|t| p.registered.is_none_or(|r| *t < r))
            {
                p.registered = Some(t);
                self.timers.push(Reverse((t, i)));
            }
        }
        self.queued = due;
        Ok(())
    }

    /// Pumps until `done` holds (true) or `limit` passes (false), reporting progress.
    pub fn pump_until(
        &mut self,
        limit: Duration,
        mut done: impl FnMut(&[Peer]) -> bool,
    ) -> Result<bool, String> {
        let end = Instant::now() + limit;
        let mut ignored = Vec::new();
        let mut last_report = Instant::now();
        while Instant::now() < end {
            self.pump(&mut ignored, Duration::from_millis(1))?;
            ignored.clear();
            if done(&self.peers) {
                return Ok(true);
            }
            if last_report.elapsed() > Duration::from_secs(1) {
                last_report = Instant::now();
                let connected = self
                    .peers
                    .iter()
                    .filter(|p| p.client.is_connected())
                    .count();
                let pending: usize = self.peers.iter().map(|p| p.pending.len()).sum();
                eprintln!(
                    "set-up: {connected} of {} sessions, {pending} creations pending",
                    self.peers.len()
                );
            }
        }
        Ok(false)
    }
}

/// Lets the open-file limit grow to its hard limit (one socket per simulated client).
pub fn raise_fd_limit() {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    if let Ok((_, hard)) = getrlimit(Resource::RLIMIT_NOFILE) {
        let _ = setrlimit(Resource::RLIMIT_NOFILE, hard, hard);
    }
}
