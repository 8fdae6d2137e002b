//! Which event loop for the front-end: `poll(2)` (the loop before the transport seam), mio
//! (epoll, what the front-end uses now) or tokio (a current-thread runtime, what the project
//! card names). Each variant is a UDP echo server shaped like the front-end's loop: one
//! thread waiting on its socket and two more descriptors (the IPC event listeners, idle
//! here), answering each datagram. A client paced at 1,000 and 10,000 datagrams/s measures
//! the round trip; the difference between the variants is what their wake-up path costs.
//!
//! `cargo bench -p xrce-benches --bench event_loop` (add `-- --quick` for a short run).
//! Loopback only. The client busy-waits between sends (for accurate pacing), so it keeps
//! one core; on 2 cores the server has the other.

use std::net::UdpSocket;
use std::os::fd::{AsFd, AsRawFd, OwnedFd};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;

/// An echo server: serves `socket` until the flag is set.
type Server = fn(UdpSocket, Arc<AtomicBool>);

/// Two idle descriptors standing for the IPC event listeners.
fn idle_fds() -> [OwnedFd; 2] {
    let a = nix::sys::eventfd::EventFd::new().expect("eventfd");
    let b = nix::sys::eventfd::EventFd::new().expect("eventfd");
    [a.into(), b.into()]
}

fn echo_all(socket: &UdpSocket, buf: &mut [u8]) {
    while let Ok((n, from)) = socket.recv_from(buf) {
        let _ = socket.send_to(&buf[..n], from);
    }
}

fn poll_server(socket: UdpSocket, stop: Arc<AtomicBool>) {
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
    socket.set_nonblocking(true).expect("non-blocking");
    let idle = idle_fds();
    let mut buf = [0u8; 2048];
    while !stop.load(Ordering::Relaxed) {
        let mut fds = [
            PollFd::new(socket.as_fd(), PollFlags::POLLIN),
            PollFd::new(idle[0].as_fd(), PollFlags::POLLIN),
            PollFd::new(idle[1].as_fd(), PollFlags::POLLIN),
        ];
        let _ = poll(&mut fds, PollTimeout::from(100u16));
        echo_all(&socket, &mut buf);
    }
}

fn mio_server(socket: UdpSocket, stop: Arc<AtomicBool>) {
    use mio::unix::SourceFd;
    use mio::{Events, Interest, Poll, Token};
    socket.set_nonblocking(true).expect("non-blocking");
    let mut socket = mio::net::UdpSocket::from_std(socket);
    let idle = idle_fds();
    let mut poll = Poll::new().expect("poll");
    poll.registry()
        .register(&mut socket, Token(16), Interest::READABLE)
        .expect("register");
    for (i, fd) in idle.iter().enumerate() {
        poll.registry()
            .register(&mut SourceFd(&fd.as_raw_fd()), Token(i), Interest::READABLE)
            .expect("register");
    }
    let mut events = Events::with_capacity(64);
    let mut buf = [0u8; 2048];
    while !stop.load(Ordering::Relaxed) {
        let _ = poll.poll(&mut events, Some(Duration::from_millis(100)));
        while let Ok((n, from)) = socket.recv_from(&mut buf) {
            let _ = socket.send_to(&buf[..n], from);
        }
    }
}

fn tokio_server(socket: UdpSocket, stop: Arc<AtomicBool>) {
    socket.set_nonblocking(true).expect("non-blocking");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async move {
        let socket = tokio::net::UdpSocket::from_std(socket).expect("tokio socket");
        let [x, y] = idle_fds();
        // SAFETY: the descriptors are owned by the AsyncFds and closed only when they drop
        // (tokio 1.54 makes registering a foreign descriptor unsafe, as the front-end would
        // have to for iceoryx2's listeners).
        #[allow(unsafe_code)]
        let (a, b) = unsafe {
            (
                tokio::io::unix::AsyncFd::register(x).expect("async fd"),
                tokio::io::unix::AsyncFd::register(y).expect("async fd"),
            )
        };
        let mut buf = [0u8; 2048];
        while !stop.load(Ordering::Relaxed) {
            tokio::select! {
                r = socket.readable() => {
                    if r.is_ok() {
                        while let Ok((n, from)) = socket.try_recv_from(&mut buf) {
                            let _ = socket.try_send_to(&buf[..n], from);
                        }
                    }
                }
                _ = a.readable() => {}
                _ = b.readable() => {}
                _ = tokio::time::sleep(Duration::from_millis(100)) => {}
            }
        }
    });
}

/// Sends `count` datagrams at `rate`/s to `server` and returns the round-trip histogram (ns).
fn measure(server: std::net::SocketAddr, rate: f64, count: usize) -> Histogram<u64> {
    let client = UdpSocket::bind("127.0.0.1:0").expect("bind");
    client.connect(server).expect("connect");
    client.set_nonblocking(true).expect("non-blocking");
    let mut h = Histogram::<u64>::new_with_bounds(1, 10_000_000_000, 3).expect("histogram");
    let base = Instant::now();
    let period = Duration::from_secs_f64(1.0 / rate);
    let mut next = base;
    let (mut sent, mut got) = (0usize, 0usize);
    let mut buf = [0u8; 64];
    let deadline = base + Duration::from_secs_f64(count as f64 / rate + 2.0);
    while got < count && Instant::now() < deadline {
        let now = Instant::now();
        if sent < count && now >= next {
            let t = (now - base).as_nanos() as u64;
            let mut m = [0u8; 40];
            m[..8].copy_from_slice(&t.to_le_bytes());
            let _ = client.send(&m);
            sent += 1;
            next += period;
        }
        while let Ok(n) = client.recv(&mut buf) {
            if n >= 8 {
                let t = u64::from_le_bytes(buf[..8].try_into().expect("8 bytes"));
                let rtt = (Instant::now() - base).as_nanos() as u64 - t;
                let _ = h.record(rtt.max(1));
                got += 1;
            }
        }
    }
    h
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let variants: [(&str, Server); 3] = [
        ("poll(2)", poll_server),
        ("mio", mio_server),
        ("tokio current_thread", tokio_server),
    ];
    println!("round trip through a UDP echo loop, 40-byte datagrams, microseconds");
    println!(
        "{:<22} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "loop", "rate/s", "p50", "p90", "p99", "p99.9"
    );
    let rounds = if quick { 1 } else { 3 };
    for rate in [1_000.0, 10_000.0] {
        let count = if quick { 2_000 } else { 20_000 };
        for round in 0..rounds {
            for (name, server) in variants {
                let socket = UdpSocket::bind("127.0.0.1:0").expect("bind");
                let addr = socket.local_addr().expect("addr");
                let stop = Arc::new(AtomicBool::new(false));
                let s = stop.clone();
                let t = std::thread::spawn(move || server(socket, s));
                std::thread::sleep(Duration::from_millis(50));
                let h = measure(addr, rate, count);
                stop.store(true, Ordering::Relaxed);
                let _ = t.join();
                let us = |q: f64| h.value_at_quantile(q) as f64 / 1000.0;
                println!(
                    "{:<22} {:>8} {:>8.1} {:>8.1} {:>8.1} {:>8.1}   (round {}, {} of {count} back)",
                    name,
                    rate,
                    us(0.5),
                    us(0.9),
                    us(0.99),
                    us(0.999),
                    round + 1,
                    h.len()
                );
            }
        }
    }
}
