//! Micro-benchmark of the IPC hop front-end → worker → front-end over iceoryx2 shared
//! memory, as the agent does it: a WRITE_DATA operation (header + 40-byte sample) published
//! and notified on the request service, received by the "worker", answered with a Sample
//! on the reply service, and received back.
//!
//! `hop/in_thread`: both ends in one thread, so only the IPC work is timed (loan, copy,
//! publish, event notification, receive). `hop/ping_pong`: the "worker" in its own thread,
//! woken by the event descriptor as the real one is (poll(2)), so thread wake-ups count.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use std::os::fd::AsFd;
use xrce_common::wire::Dialect;
use xrce_ipc::shm::{IpcNode, Receiver, Sender, ServiceKind};
use xrce_ipc::{
    reply_service, request_service, Reply, ReplyMessage, Request, RequestMessage, Route, Sample,
};

const BODY: [u8; 40] = [0x5A; 40];

/// Waits until `rx` is notified or `timeout_ms` passes, as the worker's loop does.
fn wait_readable(rx: &Receiver, timeout_ms: u16) {
    let mut fds = [PollFd::new(rx.as_fd(), PollFlags::POLLIN)];
    let _ = poll(&mut fds, PollTimeout::from(timeout_ms));
}

struct Ends {
    req_tx: Sender,
    req_rx: Receiver,
    rep_tx: Sender,
    rep_rx: Receiver,
    _nodes: (IpcNode, IpcNode),
}

fn ends(instance: &str) -> Ends {
    let fe = IpcNode::new(instance, "bench-frontend").expect("front-end node");
    let wk = IpcNode::new(instance, "bench-worker").expect("worker node");
    let req = request_service(instance);
    let rep = reply_service(instance, 0);
    Ends {
        req_rx: wk
            .receiver(&req, ServiceKind::Data)
            .expect("request receiver"),
        req_tx: fe.sender(&req, ServiceKind::Data).expect("request sender"),
        rep_rx: fe
            .receiver(&rep, ServiceKind::Reply)
            .expect("reply receiver"),
        rep_tx: wk.sender(&rep, ServiceKind::Reply).expect("reply sender"),
        _nodes: (fe, wk),
    }
}

/// The worker's side of one hop: every request answered with a Sample of the same body.
fn answer(req_rx: &Receiver, rep_tx: &Sender) -> usize {
    req_rx.clear_events();
    let n = req_rx
        .drain(|m| {
            if let Ok(RequestMessage {
                route,
                request: Request::Write { data, .. },
                ..
            }) = RequestMessage::decode(m)
            {
                let sample = Sample {
                    identity: Default::default(),
                    origin: None,
                    data,
                    little_endian: true,
                    disposed: false,
                    unregistered: false,
                };
                let _ = rep_tx.send(&ReplyMessage::new(route, Reply::Sample(sample)));
            }
        })
        .unwrap_or(0);
    if n > 0 {
        let _ = rep_tx.notify();
    }
    n
}

/// A write of [`BODY`], as a front-end sends one.
fn write() -> RequestMessage<'static> {
    RequestMessage::new(
        Route::default(),
        Request::Write {
            data: BODY[..].into(),
            data_format: 0,
            little_endian: true,
            dialect: Dialect::Eprosima,
            status_requested: false,
            position: None,
            received_us: 0,
            resend_of: None,
        },
    )
}

fn request(e: &Ends) {
    let _ = e.req_tx.send(&write());
    let _ = e.req_tx.notify();
}

fn hop(c: &mut Criterion) {
    let mut g = c.benchmark_group("hop");
    let e = ends(&format!("bench-ipc-{}", std::process::id()));
    g.bench_function("in_thread", |b| {
        b.iter(|| {
            request(&e);
            answer(&e.req_rx, &e.rep_tx);
            e.rep_rx.clear_events();
            let n = e.rep_rx.drain(|m| {
                std::hint::black_box(m);
            });
            assert_eq!(n.ok(), Some(1));
        })
    });
    drop(e);

    let instance = format!("bench-ipc-pp-{}", std::process::id());
    let stop = Arc::new(AtomicBool::new(false));
    let stop2 = stop.clone();
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    // iceoryx2 ports stay in the thread that made them: the worker's are made there.
    let worker_instance = instance.clone();
    let worker = std::thread::spawn(move || {
        let wk = IpcNode::new(&worker_instance, "bench-worker").expect("worker node");
        let req_rx = wk
            .receiver(&request_service(&worker_instance), ServiceKind::Data)
            .expect("request receiver");
        let rep_tx = wk
            .sender(&reply_service(&worker_instance, 0), ServiceKind::Reply)
            .expect("reply sender");
        let _ = ready_tx.send(());
        while !stop2.load(Ordering::Relaxed) {
            wait_readable(&req_rx, 50);
            answer(&req_rx, &rep_tx);
        }
    });
    let _ = ready_rx.recv_timeout(Duration::from_secs(10));
    let fe = IpcNode::new(&instance, "bench-frontend").expect("front-end node");
    let req_tx = fe
        .sender(&request_service(&instance), ServiceKind::Data)
        .expect("request sender");
    let rep_rx = fe
        .receiver(&reply_service(&instance, 0), ServiceKind::Reply)
        .expect("reply receiver");
    // Let the worker's ports see the front-end's before the first message.
    std::thread::sleep(Duration::from_millis(200));
    g.bench_function("ping_pong", |b| {
        b.iter_custom(|iters| {
            let start = Instant::now();
            for _ in 0..iters {
                let _ = req_tx.send(&write());
                let _ = req_tx.notify();
                let end = Instant::now() + Duration::from_secs(1);
                loop {
                    wait_readable(&rep_rx, 100);
                    rep_rx.clear_events();
                    let got = rep_rx
                        .drain(|m| {
                            std::hint::black_box(m);
                        })
                        .unwrap_or(0);
                    if got > 0 || Instant::now() > end {
                        break;
                    }
                }
            }
            start.elapsed()
        })
    });
    stop.store(true, Ordering::Relaxed);
    let _ = worker.join();
    drop((req_tx, rep_rx, fe));
    g.finish();
}

criterion_group!(benches, hop);
criterion_main!(benches);
