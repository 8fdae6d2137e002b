//! A null agent, for measuring the generator's own ceiling (`--null-agent`): the XRCE
//! session core of `xrce_common` on a UDP socket, in a thread of the generator, with no DDS
//! and no IPC behind it. Every creation succeeds, and every sample written goes straight to
//! every active read. Whatever the generator reaches against it, it can drive a real agent
//! to; what it reaches against a real agent below that is the agent's limit.

use std::collections::HashMap;
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::AsFd;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use nix::poll::{poll, PollFd, PollFlags, PollTimeout};

use xrce_common::session::agent::{Agent, AgentConfig, DataReply, Operation, OperationSink};
use xrce_common::wire::{status, BaseObjectRequest, ClientKey, ResultStatus};

/// The running null agent; stopped when dropped.
pub struct NullAgent {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// What the core handed over during one datagram.
#[derive(Default)]
struct Collected {
    /// Requests to answer with STATUS_OK (creations, deletions).
    ok: Vec<(ClientKey, BaseObjectRequest)>,
    /// New reads: client, request, stream, format.
    reads: Vec<(ClientKey, BaseObjectRequest, u8, u8)>,
    /// Samples written, with their byte order.
    samples: Vec<(Vec<u8>, bool)>,
    /// Sessions that ended.
    gone: Vec<ClientKey>,
}

impl OperationSink for Collected {
    fn has_room(&self) -> bool {
        true
    }

    fn operation(&mut self, _now: Instant, op: Operation<'_>) {
        match op {
            Operation::Create { client, create, .. } => self.ok.push((client, create.base)),
            Operation::Delete { client, request } => self.ok.push((client, request)),
            Operation::Read {
                client,
                request,
                spec,
            } => self
                .reads
                .push((client, request, spec.preferred_stream_id, spec.data_format)),
            Operation::Write {
                data,
                little_endian,
                ..
            } => self.samples.push((data.data.to_vec(), little_endian)),
            Operation::ClientDeleted { client } => self.gone.push(client),
            Operation::ClientCreated { .. } | Operation::GetInfo { .. } => {}
        }
    }
}

/// An active read: its request, stream and data format.
type ActiveRead = (BaseObjectRequest, u8, u8);

impl NullAgent {
    /// Serves XRCE on 127.0.0.1:`port` until dropped.
    pub fn start(port: u16) -> Result<Self, String> {
        let socket = UdpSocket::bind(("127.0.0.1", port))
            .map_err(|e| format!("null agent: cannot bind UDP port {port}: {e}"))?;
        socket.set_nonblocking(true).map_err(|e| e.to_string())?;
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        let thread = std::thread::spawn(move || serve(&socket, &stop2));
        Ok(NullAgent {
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for NullAgent {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn serve(socket: &UdpSocket, stop: &AtomicBool) {
    let mut agent: Agent<SocketAddr> = Agent::new(AgentConfig {
        max_clients: 100_000,
        ..AgentConfig::default()
    });
    let mut reads: HashMap<ClientKey, Vec<ActiveRead>> = HashMap::new();
    let mut buf = vec![0u8; 65_536];
    let mut seq = 0u32;
    let ok = ResultStatus {
        status: status::OK,
        implementation_status: 0,
    };
    while !stop.load(Ordering::Relaxed) {
        let mut fds = [PollFd::new(socket.as_fd(), PollFlags::POLLIN)];
        let _ = poll(&mut fds, PollTimeout::from(1u8));
        let now = Instant::now();
        let mut c = Collected::default();
        for _ in 0..256 {
            match socket.recv_from(&mut buf) {
                Ok((n, from)) => agent.handle_datagram(now, from, &buf[..n], &mut c),
                Err(_) => break,
            }
        }
        for k in c.gone {
            reads.remove(&k);
        }
        for (client, request) in c.ok {
            let _ = agent.send_status(now, client, request, ok);
        }
        for (client, request, stream, format) in c.reads {
            reads
                .entry(client)
                .or_default()
                .push((request, stream, format));
        }
        for (sample, little_endian) in &c.samples {
            for (client, rs) in &reads {
                for (request, stream, format) in rs {
                    seq = seq.wrapping_add(1);
                    let reply = DataReply {
                        request: *request,
                        format: *format,
                        sample,
                        little_endian: *little_endian,
                        state: 0,
                        sequence_number: seq,
                    };
                    let _ = agent.send_data(now, *client, *stream, reply);
                }
            }
        }
        // Sessions the core deletes on its timers (dead clients) end their reads too.
        let mut timed = Collected::default();
        agent.handle_timeout(now, &mut timed);
        for k in timed.gone {
            reads.remove(&k);
        }
        while let Some(t) = agent.poll_transmit() {
            let _ = socket.send_to(&t.data, t.destination);
        }
    }
}
