//! The TCP transport on real loopback sockets, driven by a mio poll as the event loop drives
//! it: framing across segments, bad input, a client that stops reading, the connection cap,
//! and a thousand connections at once.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

use mio::{Events, Poll};
use xrce_frontend::transport::tcp::{TcpConfig, TcpEndpoint, TcpTransport};
use xrce_frontend::transport::Transport;

struct Harness {
    poll: Poll,
    events: Events,
    tcp: TcpTransport,
    closed: Vec<TcpEndpoint>,
}

impl Harness {
    fn new(config: TcpConfig) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let mut tcp = TcpTransport::new(listener, config).expect("transport");
        let poll = Poll::new().expect("poll");
        tcp.register(poll.registry(), 16).expect("register");
        Harness {
            poll,
            events: Events::with_capacity(1024),
            tcp,
            closed: Vec::new(),
        }
    }

    fn connect(&self) -> TcpStream {
        let s = TcpStream::connect(self.tcp.local_addr()).expect("connect");
        s.set_nodelay(true).expect("nodelay");
        s
    }

    /// A connection from another loopback address (the whole of 127.0.0.0/8 is local).
    fn connect_from(&self, ip: &str) -> TcpStream {
        let socket = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None)
            .expect("socket");
        let from: std::net::SocketAddr = format!("{ip}:0").parse().expect("address");
        socket.bind(&from.into()).expect("bind the source address");
        socket
            .connect(&self.tcp.local_addr().into())
            .expect("connect");
        let s: TcpStream = socket.into();
        s.set_nodelay(true).expect("nodelay");
        s
    }

    /// Runs the transport for `d` or until `done`, collecting messages.
    fn run(
        &mut self,
        d: Duration,
        mut done: impl FnMut(&[(TcpEndpoint, Vec<u8>)], &[TcpEndpoint]) -> bool,
    ) -> Vec<(TcpEndpoint, Vec<u8>)> {
        let mut got = Vec::new();
        let end = Instant::now() + d;
        let mut left = true;
        while Instant::now() < end {
            let timeout = if left {
                Duration::ZERO
            } else {
                Duration::from_millis(10)
            };
            self.poll
                .poll(&mut self.events, Some(timeout))
                .expect("poll");
            for e in self.events.iter() {
                self.tcp.on_event(e);
            }
            if self.tcp.poll_timeout().is_some_and(|t| t <= Instant::now()) {
                self.tcp.handle_timeout(Instant::now());
            }
            left = self.tcp.receive(Instant::now(), 256, &mut |from, m| {
                got.push((from, m.to_vec()))
            });
            while let Some(c) = self.tcp.poll_closed() {
                self.closed.push(c);
            }
            if done(&got, &self.closed) {
                break;
            }
        }
        got
    }
}

fn framed(m: &[u8]) -> Vec<u8> {
    let mut v = (m.len() as u16).to_le_bytes().to_vec();
    v.extend_from_slice(m);
    v
}

#[test]
fn messages_split_across_segments_or_merged_in_one_come_out_whole() {
    let mut h = Harness::new(TcpConfig::default());
    let mut c = h.connect();
    // The eProsima client: prefix and message as separate sends, read separately here (the
    // transport runs in between, so it has read the prefix alone before the message comes).
    c.write_all(&[5, 0]).expect("write");
    let early = h.run(Duration::from_millis(50), |_, _| false);
    assert!(early.is_empty(), "a message from a prefix alone");
    c.write_all(b"hello").expect("write");
    // Several in one send, a zero length among them, the last one cut in the middle.
    let mut many = framed(b"one");
    many.extend([0, 0]);
    many.extend(framed(b"two"));
    let third = framed(b"three");
    many.extend(&third[..3]);
    c.write_all(&many).expect("write");
    let mut got = h.run(Duration::from_secs(5), |g, _| g.len() >= 3);
    assert_eq!(got.len(), 3, "the cut message came out early");
    c.write_all(&third[3..]).expect("write");
    got.extend(h.run(Duration::from_secs(5), |g, _| !g.is_empty()));
    let msgs: Vec<&[u8]> = got.iter().map(|(_, m)| m.as_slice()).collect();
    assert_eq!(msgs, [&b"hello"[..], b"one", b"two", b"three"]);
    assert!(got.windows(2).all(|w| w[0].0 == w[1].0), "one endpoint");
    // Replies go out framed the same way.
    h.tcp.send(got[0].0, b"reply");
    let mut buf = [0u8; 7];
    c.set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    c.read_exact(&mut buf).expect("reply");
    assert_eq!(&buf, b"\x05\x00reply");
}

#[test]
fn an_over_long_message_closes_only_its_connection() {
    let mut h = Harness::new(TcpConfig {
        max_message: 100,
        ..TcpConfig::default()
    });
    let mut bad = h.connect();
    let mut good = h.connect();
    bad.write_all(&[200, 0]).expect("write");
    bad.write_all(&[0; 200]).expect("write");
    good.write_all(&framed(b"fine")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, closed| {
        !g.is_empty() && !closed.is_empty()
    });
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].1, b"fine");
    assert_eq!(h.closed.len(), 1);
    assert_ne!(h.closed[0], got[0].0, "the good connection was closed");
    assert_eq!(h.tcp.stats().dropped("tcp_frame_too_long"), 1);
    // The bad client sees its connection end.
    bad.set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    let mut buf = [0u8; 8];
    assert!(matches!(bad.read(&mut buf), Ok(0) | Err(_)));
    assert_eq!(h.tcp.connections(), 1);
}

#[test]
fn a_client_that_stops_reading_is_closed_and_the_others_are_served() {
    let mut h = Harness::new(TcpConfig {
        send_buffer: 16 << 10,
        ..TcpConfig::default()
    });
    // A small receive buffer, so the kernel fills up quickly.
    let stuck =
        socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).expect("socket");
    stuck.set_recv_buffer_size(4096).expect("rcvbuf");
    stuck.connect(&h.tcp.local_addr().into()).expect("connect");
    let mut stuck: TcpStream = stuck.into();
    let mut other = h.connect();
    stuck.write_all(&framed(b"stuck")).expect("write");
    other.write_all(&framed(b"other")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| g.len() >= 2);
    let by_msg: BTreeMap<Vec<u8>, TcpEndpoint> = got.iter().map(|(e, m)| (m.clone(), *e)).collect();
    let (stuck_ep, other_ep) = (by_msg[&b"stuck".to_vec()], by_msg[&b"other".to_vec()]);
    let payload = vec![0xAB; 1000];
    let mut sent = 0;
    while h.closed.is_empty() && sent < 100_000 {
        h.tcp.send(stuck_ep, &payload);
        sent += 1;
        while let Some(c) = h.tcp.poll_closed() {
            h.closed.push(c);
        }
    }
    assert_eq!(h.closed, [stuck_ep], "closed after {sent} messages");
    assert!(sent < 10_000, "the kernel and our buffer held {sent} kB");
    assert_eq!(h.tcp.stats().dropped("tcp_send_buffer_overflow"), 1);
    // Sends to the closed endpoint are counted, not an error.
    h.tcp.send(stuck_ep, b"late");
    assert_eq!(h.tcp.stats().dropped("tcp_connection_gone"), 1);
    h.tcp.send(other_ep, b"still served");
    let mut buf = [0u8; 14];
    other
        .set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    other.read_exact(&mut buf).expect("reply");
    assert_eq!(&buf[2..], b"still served");
    drop(stuck);
}

#[test]
fn connections_beyond_the_cap_are_refused() {
    let mut h = Harness::new(TcpConfig {
        max_connections: 2,
        ..TcpConfig::default()
    });
    let mut a = h.connect();
    let mut b = h.connect();
    a.write_all(&framed(b"a")).expect("write");
    b.write_all(&framed(b"b")).expect("write");
    h.run(Duration::from_secs(5), |g, _| g.len() >= 2);
    let mut third = h.connect();
    let deadline = Instant::now() + Duration::from_secs(5);
    while h.tcp.stats().dropped("tcp_connection_refused") == 0 && Instant::now() < deadline {
        h.run(Duration::from_millis(10), |_, _| false);
    }
    assert_eq!(h.tcp.stats().dropped("tcp_connection_refused"), 1);
    third
        .set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    let mut buf = [0u8; 4];
    assert!(
        matches!(third.read(&mut buf), Ok(0) | Err(_)),
        "refused connection still open"
    );
    // Room again once one leaves.
    drop(a);
    h.run(Duration::from_secs(5), |_, closed| !closed.is_empty());
    let mut fourth = h.connect();
    fourth.write_all(&framed(b"d")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].1, b"d");
}

#[test]
fn a_thousand_connections_at_once_with_bounded_memory() {
    // Two descriptors a connection here (both ends live in this process).
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    let (_, hard) = getrlimit(Resource::RLIMIT_NOFILE).expect("getrlimit");
    setrlimit(Resource::RLIMIT_NOFILE, hard, hard).expect("setrlimit");
    let n = 1000.min((hard as usize).saturating_sub(100) / 2);
    assert!(
        n >= 1000,
        "this machine allows only {n} connections a process"
    );
    let mut h = Harness::new(TcpConfig {
        max_per_address: n,
        ..TcpConfig::default()
    });
    let mut clients: Vec<TcpStream> = Vec::with_capacity(n);
    let mut got = Vec::new();
    for i in 0..n {
        let mut c = h.connect();
        c.write_all(&framed(format!("client {i}").as_bytes()))
            .expect("write");
        clients.push(c);
        if i % 100 == 99 {
            got.extend(h.run(Duration::from_millis(1), |_, _| false));
        }
    }
    let end = Instant::now() + Duration::from_secs(30);
    while got.len() < n && Instant::now() < end {
        got.extend(h.run(Duration::from_millis(50), |_, _| false));
    }
    assert_eq!(got.len(), n, "messages from every connection");
    assert_eq!(h.tcp.connections(), n);
    let held = h.tcp.buffered_capacity();
    assert!(
        held <= n * 4096,
        "{held} bytes buffered for {n} idle connections"
    );
    let endpoints: BTreeSet<String> = got.iter().map(|(e, _)| format!("{e:?}")).collect();
    assert_eq!(endpoints.len(), n, "one endpoint each");
    // Every client gets its own reply.
    for (e, m) in &got {
        h.tcp.send(*e, m);
    }
    for (i, c) in clients.iter_mut().enumerate() {
        let want = format!("client {i}");
        let mut buf = vec![0u8; 2 + want.len()];
        c.set_read_timeout(Some(Duration::from_secs(5)))
            .expect("timeout");
        c.read_exact(&mut buf).expect("reply");
        assert_eq!(&buf[2..], want.as_bytes());
    }
}

/// Whether the peer closed a connection (read returns 0 or an error) within `d`.
fn closed_by_peer(s: &mut TcpStream, d: Duration) -> bool {
    s.set_read_timeout(Some(d)).expect("timeout");
    let mut buf = [0u8; 16];
    matches!(s.read(&mut buf), Ok(0) | Err(_))
}

#[test]
fn a_flood_of_unfinished_frames_from_one_address_does_not_lock_out_another() {
    // Every slot taken by connections from 127.0.0.1 that each hold one byte of a length
    // prefix (and would be allowed many more per address).
    let mut h = Harness::new(TcpConfig {
        max_connections: 64,
        max_per_address: 10_000,
        ..TcpConfig::default()
    });
    let mut flood = Vec::new();
    for _ in 0..100 {
        let mut c = h.connect();
        c.write_all(&[0x05]).expect("write");
        flood.push(c);
        h.run(Duration::from_millis(2), |_, _| false);
    }
    assert_eq!(h.tcp.connections(), 64);
    assert!(h.tcp.stats().dropped("tcp_connection_refused") >= 36);
    // A client from another address is served all the same: it displaces one of them.
    let mut other = h.connect_from("127.0.0.2");
    other.write_all(&framed(b"hello")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].1, b"hello");
    assert_eq!(h.tcp.stats().dropped("tcp_connection_displaced"), 1);
    assert_eq!(h.tcp.connections(), 64);
    // The newcomer, having sent a message, is not the next one displaced.
    let mut third = h.connect_from("127.0.0.3");
    third.write_all(&framed(b"again")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(got.len(), 1);
    h.tcp.send(got[0].0, b"reply");
    other.write_all(&framed(b"still here")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(
        got.first().map(|g| g.1.as_slice()),
        Some(&b"still here"[..])
    );
}

#[test]
fn connections_from_one_address_are_capped() {
    let mut h = Harness::new(TcpConfig {
        max_per_address: 3,
        ..TcpConfig::default()
    });
    let mut mine: Vec<TcpStream> = (0..3).map(|_| h.connect()).collect();
    h.run(Duration::from_millis(200), |_, _| false);
    let mut fourth = h.connect();
    h.run(Duration::from_millis(200), |_, _| false);
    assert!(closed_by_peer(&mut fourth, Duration::from_secs(5)));
    assert_eq!(
        h.tcp.stats().dropped("tcp_connection_refused_per_address"),
        1
    );
    let mut other = h.connect_from("127.0.0.2");
    other.write_all(&framed(b"x")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(got.len(), 1, "another address is served");
    mine[0].write_all(&framed(b"y")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(got.len(), 1, "the first three are served");
}

#[test]
fn a_message_trickled_slower_than_the_frame_limit_closes_its_connection() {
    let mut h = Harness::new(TcpConfig {
        frame_limit: Duration::from_millis(500),
        first_message_limit: Duration::from_secs(60),
        ..TcpConfig::default()
    });
    let mut slow = h.connect();
    let mut fine = h.connect();
    fine.write_all(&framed(b"ok")).expect("write");
    // One byte of a 100-byte message every 200 ms: input keeps coming, the message never ends.
    let start = Instant::now();
    let mut closed = false;
    for _ in 0..20 {
        let _ = slow.write_all(&[100]);
        h.run(Duration::from_millis(200), |_, c| !c.is_empty());
        if h.tcp.stats().dropped("tcp_stalled_message") == 1 {
            closed = true;
            break;
        }
    }
    assert!(closed, "still open after {:?}", start.elapsed());
    assert!(closed_by_peer(&mut slow, Duration::from_secs(5)));
    assert_eq!(h.tcp.connections(), 1, "the other connection stays");
}

#[test]
fn an_idle_connection_is_closed() {
    let mut h = Harness::new(TcpConfig {
        idle_timeout: Some(Duration::from_millis(500)),
        ..TcpConfig::default()
    });
    let mut c = h.connect();
    c.write_all(&framed(b"once")).expect("write");
    let got = h.run(Duration::from_secs(5), |g, _| !g.is_empty());
    assert_eq!(got.len(), 1);
    h.run(Duration::from_secs(5), |_, closed| !closed.is_empty());
    assert_eq!(h.tcp.stats().dropped("tcp_idle_connection"), 1);
    assert!(closed_by_peer(&mut c, Duration::from_secs(5)));
}

#[test]
fn a_client_streaming_messages_back_to_back_is_not_taken_for_a_stalled_one() {
    let mut h = Harness::new(TcpConfig {
        frame_limit: Duration::from_millis(500),
        ..TcpConfig::default()
    });
    let mut c = h.connect();
    // For two seconds, every write ends in the middle of the next message: there is always
    // a message begun, but each is finished in time.
    let start = Instant::now();
    let next = framed(b"next");
    let mut sent = 0;
    let mut got = 0;
    let mut bytes = Vec::new();
    while start.elapsed() < Duration::from_secs(2) {
        // The rest of the message begun last time, a whole one, the start of another.
        bytes.extend_from_slice(&framed(b"whole one"));
        bytes.extend_from_slice(&next[..3]);
        c.write_all(&bytes).expect("write");
        sent += 1;
        got += h.run(Duration::from_millis(50), |_, _| false).len();
        bytes = next[3..].to_vec();
        sent += 1;
    }
    c.write_all(&bytes).expect("write");
    got += h.run(Duration::from_millis(500), |_, _| false).len();
    assert_eq!(h.tcp.stats().dropped("tcp_stalled_message"), 0);
    assert_eq!(got, sent);
    assert_eq!(h.tcp.connections(), 1);
}
