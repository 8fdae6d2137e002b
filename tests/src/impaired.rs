//! An impaired network between clients and an agent: a UDP relay that drops, duplicates,
//! delays and reorders datagrams (a radio link, a congested Wi-Fi), and a serial line that
//! flips bits (a noisy UART). The agent sees each client at a port of the relay's own, one
//! per client endpoint, so a client that resets (a new socket) is a new endpoint to the agent
//! too, as without the relay.
//!
//! Impairments are drawn from a seeded generator: a failing run can be repeated. Besides the
//! random ones, a rule can drop chosen datagrams (the agent's reply to a DELETE_CLIENT, say).

use std::collections::HashMap;
use std::fs::File;
use std::io::{Read, Write};
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Which way a datagram goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// From a client to the agent.
    ToAgent,
    /// From the agent to a client.
    ToClient,
}

/// What happens to the datagrams (each probability per datagram and direction).
#[derive(Debug, Clone, Copy)]
pub struct Impairment {
    /// Dropped.
    pub loss: f64,
    /// Sent twice.
    pub duplicate: f64,
    /// Held back and sent after the next datagram of its direction (or after
    /// [`Impairment::hold`], whichever comes first).
    pub reorder: f64,
    /// The longest a reordered datagram is held.
    pub hold: Duration,
    /// Seed of the generator.
    pub seed: u64,
}

impl Impairment {
    /// A link that only loses `loss` of the datagrams each way.
    pub fn lossy(loss: f64, seed: u64) -> Self {
        Impairment {
            loss,
            duplicate: 0.0,
            reorder: 0.0,
            hold: Duration::from_millis(30),
            seed,
        }
    }

    /// A clean link (rules still apply).
    pub fn clean() -> Self {
        Self::lossy(0.0, 1)
    }
}

/// xorshift64*: small, deterministic, good enough for a link.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    /// A generator from `seed` (0 is replaced: xorshift needs a nonzero state).
    pub fn new(seed: u64) -> Self {
        Rng(seed.max(1))
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64) < p
    }
}

/// A rule that drops the datagrams it returns true for (each rule sees every datagram
/// before the random impairments).
pub type DropRule = Box<dyn FnMut(Direction, &[u8]) -> bool + Send>;

/// What a relay did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RelayCounts {
    /// Datagrams received from clients and from the agent.
    pub received: u64,
    /// Of those, from the agent.
    pub from_agent: u64,
    /// Dropped by chance.
    pub lost: u64,
    /// Dropped by a rule.
    pub ruled_out: u64,
    /// Sent twice.
    pub duplicated: u64,
    /// Held and sent after a later one.
    pub reordered: u64,
}

struct Shared {
    rules: Vec<DropRule>,
    counts: RelayCounts,
    impairment: Impairment,
}

/// A UDP relay on loopback between clients and an agent, impairing what crosses it.
#[allow(missing_debug_implementations)] // Holds rules (closures).
pub struct ImpairedUdp {
    addr: SocketAddr,
    shared: Arc<Mutex<Shared>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl ImpairedUdp {
    /// A relay to `agent`; clients send to [`ImpairedUdp::addr`].
    pub fn start(agent: SocketAddr, impairment: Impairment) -> Self {
        Self::start_on(agent, 0, impairment)
    }

    /// A relay to `agent` listening on loopback port `port` (0: any free one).
    pub fn start_on(agent: SocketAddr, port: u16, impairment: Impairment) -> Self {
        let local = if agent.is_ipv4() {
            "127.0.0.1:0"
        } else {
            "[::1]:0"
        };
        let ip: std::net::IpAddr = if agent.is_ipv4() {
            std::net::Ipv4Addr::LOCALHOST.into()
        } else {
            std::net::Ipv6Addr::LOCALHOST.into()
        };
        let front = UdpSocket::bind(SocketAddr::new(ip, port)).expect("bind the relay");
        front.set_nonblocking(true).expect("non-blocking");
        let addr = front.local_addr().expect("relay address");
        let shared = Arc::new(Mutex::new(Shared {
            rules: Vec::new(),
            counts: RelayCounts::default(),
            impairment,
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (shared, stop) = (shared.clone(), stop.clone());
            std::thread::spawn(move || relay(front, agent, local, &shared, &stop))
        };
        ImpairedUdp {
            addr,
            shared,
            stop,
            thread: Some(thread),
        }
    }

    /// Where clients send.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Adds a rule that drops what it returns true for.
    pub fn drop_when(&self, rule: impl FnMut(Direction, &[u8]) -> bool + Send + 'static) {
        if let Ok(mut s) = self.shared.lock() {
            s.rules.push(Box::new(rule));
        }
    }

    /// Changes the random impairments from now on.
    pub fn set_impairment(&self, impairment: Impairment) {
        if let Ok(mut s) = self.shared.lock() {
            s.impairment = impairment;
        }
    }

    /// What it did so far.
    pub fn counts(&self) -> RelayCounts {
        self.shared.lock().map(|s| s.counts).unwrap_or_default()
    }
}

impl Drop for ImpairedUdp {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// One direction's datagram held back for reordering.
struct Held {
    bytes: Vec<u8>,
    until: Instant,
}

/// A client endpoint's own socket towards the agent, and what is held each way.
struct Path {
    back: UdpSocket,
    held_to_agent: Option<Held>,
    held_to_client: Option<Held>,
}

fn relay(
    front: UdpSocket,
    agent: SocketAddr,
    local: &str,
    shared: &Mutex<Shared>,
    stop: &AtomicBool,
) {
    let mut rng = shared
        .lock()
        .map(|s| Rng::new(s.impairment.seed))
        .unwrap_or(Rng::new(1));
    let mut paths: HashMap<SocketAddr, Path> = HashMap::new();
    let mut buf = vec![0u8; 65_536];
    while !stop.load(Ordering::Relaxed) {
        let mut idle = true;
        while let Ok((n, from)) = front.recv_from(&mut buf) {
            idle = false;
            if let std::collections::hash_map::Entry::Vacant(v) = paths.entry(from) {
                let Some(back) = path_to(agent, local) else {
                    continue;
                };
                v.insert(Path {
                    back,
                    held_to_agent: None,
                    held_to_client: None,
                });
            }
            if let Some(p) = paths.get_mut(&from) {
                let Path {
                    back,
                    held_to_agent,
                    ..
                } = p;
                pass(
                    shared,
                    &mut rng,
                    Direction::ToAgent,
                    &buf[..n],
                    held_to_agent,
                    |b| {
                        let _ = back.send(b);
                    },
                );
            }
        }
        for (client, p) in paths.iter_mut() {
            while let Ok(n) = p.back.recv(&mut buf) {
                idle = false;
                pass(
                    shared,
                    &mut rng,
                    Direction::ToClient,
                    &buf[..n],
                    &mut p.held_to_client,
                    |b| {
                        let _ = front.send_to(b, client);
                    },
                );
            }
            // A held datagram goes out once its time is up, even without a successor.
            let now = Instant::now();
            if p.held_to_agent.as_ref().is_some_and(|h| h.until <= now) {
                if let Some(h) = p.held_to_agent.take() {
                    let _ = p.back.send(&h.bytes);
                }
            }
            if p.held_to_client.as_ref().is_some_and(|h| h.until <= now) {
                if let Some(h) = p.held_to_client.take() {
                    let _ = front.send_to(&h.bytes, client);
                }
            }
        }
        if idle {
            std::thread::sleep(Duration::from_micros(200));
        }
    }
}

/// A client endpoint's own socket towards the agent.
fn path_to(agent: SocketAddr, local: &str) -> Option<UdpSocket> {
    let back = UdpSocket::bind(local).ok()?;
    back.connect(agent).ok()?;
    back.set_nonblocking(true).ok()?;
    Some(back)
}

/// One datagram through the impairments: dropped, sent, sent twice, or held for reordering
/// (a datagram held before goes out after it).
fn pass(
    shared: &Mutex<Shared>,
    rng: &mut Rng,
    dir: Direction,
    bytes: &[u8],
    held: &mut Option<Held>,
    mut send: impl FnMut(&[u8]),
) {
    let Ok(mut s) = shared.lock() else {
        return;
    };
    s.counts.received += 1;
    if dir == Direction::ToClient {
        s.counts.from_agent += 1;
    }
    let ruled = s.rules.iter_mut().any(|r| r(dir, bytes));
    if ruled {
        s.counts.ruled_out += 1;
        return;
    }
    let imp = s.impairment;
    if rng.chance(imp.loss) {
        s.counts.lost += 1;
        return;
    }
    let copies = if rng.chance(imp.duplicate) {
        s.counts.duplicated += 1;
        2
    } else {
        1
    };
    if held.is_none() && rng.chance(imp.reorder) {
        s.counts.reordered += 1;
        *held = Some(Held {
            bytes: bytes.to_vec(),
            until: Instant::now() + imp.hold,
        });
        return;
    }
    drop(s);
    for _ in 0..copies {
        send(bytes);
    }
    if let Some(h) = held.take() {
        send(&h.bytes);
    }
}

/// A serial line between two ptys that flips bits: the agent opens one pty's slave, the
/// client the other's, and every byte crossing is flipped in one of its bits with
/// probability `flip` (a noisy UART at a marginal baud rate). The framing's CRC turns a
/// flipped frame into a lost one.
#[derive(Debug)]
pub struct NoisyLine {
    /// The slave path the agent opens (`--dev`).
    pub agent_path: String,
    /// The client's end (non-blocking), for [`crate::Link::serial`].
    pub client_end: Option<File>,
    counts: Arc<Mutex<(u64, u64)>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl NoisyLine {
    /// Two pty pairs joined by a thread that flips bits with probability `flip` per byte.
    pub fn open(flip: f64, seed: u64) -> Self {
        let agent_side = crate::PtyPair::open();
        let client_side = crate::PtyPair::open();
        let agent_path = agent_side.slave_path.display().to_string();
        let client_end = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&client_side.slave_path)
            .expect("open the client's pty");
        set_raw_nonblocking(&client_end);
        let counts = Arc::new(Mutex::new((0, 0)));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (counts, stop) = (counts.clone(), stop.clone());
            let (a, b) = (agent_side.master, client_side.master);
            crate::link::set_nonblocking(&a);
            crate::link::set_nonblocking(&b);
            std::thread::spawn(move || {
                let mut rng = Rng::new(seed);
                let mut buf = [0u8; 4096];
                while !stop.load(Ordering::Relaxed) {
                    let mut idle = true;
                    for (mut from, mut to) in [(&a, &b), (&b, &a)] {
                        let n = match from.read(&mut buf) {
                            Ok(n) if n > 0 => n,
                            _ => continue,
                        };
                        idle = false;
                        let mut flipped = 0;
                        for byte in &mut buf[..n] {
                            if rng.chance(flip) {
                                *byte ^= 1 << (rng.next_u64() % 8);
                                flipped += 1;
                            }
                        }
                        if let Ok(mut c) = counts.lock() {
                            c.0 += n as u64;
                            c.1 += flipped;
                        }
                        write_all(&mut to, &buf[..n]);
                    }
                    if idle {
                        std::thread::sleep(Duration::from_micros(300));
                    }
                }
            })
        };
        NoisyLine {
            agent_path,
            client_end: Some(client_end),
            counts,
            stop,
            thread: Some(thread),
        }
    }

    /// Bytes carried and bytes flipped so far.
    pub fn counts(&self) -> (u64, u64) {
        self.counts.lock().map(|c| *c).unwrap_or_default()
    }
}

impl Drop for NoisyLine {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Writes everything to a non-blocking pty, waiting while it is full (bounded: a reader
/// gone for a second loses the rest, as a line would).
fn write_all(to: &mut &File, mut bytes: &[u8]) {
    let end = Instant::now() + Duration::from_secs(1);
    while !bytes.is_empty() && Instant::now() < end {
        match to.write(bytes) {
            Ok(n) if n > 0 => bytes = &bytes[n..],
            _ => std::thread::sleep(Duration::from_micros(200)),
        }
    }
}

/// Raw mode (no echo, no line editing: the bytes as sent) and non-blocking.
fn set_raw_nonblocking(f: &File) {
    use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
    if let Ok(mut t) = tcgetattr(f) {
        cfmakeraw(&mut t);
        let _ = tcsetattr(f, SetArg::TCSANOW, &t);
    }
    crate::link::set_nonblocking(f);
}
