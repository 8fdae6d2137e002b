//! Serial lines: the `serial` transport is one line, `multiserial` several, `pseudoterminal`
//! one line on a pty the agent opened. Each line carries eProsima's stream framing
//! ([`xrce_common::framing::serial`]); the agent is address 0 and every source address on a
//! line is a client endpoint of its own, so one line may carry several clients and every
//! line's clients are separate.
//!
//! Device life cycle: a device that is not there is waited for (logged once); one that goes
//! away (USB unplugged: hang-up, EIO, ENXIO) is closed and reopened when it reappears under
//! the same path, and the sessions of its clients are kept, so a client that comes back
//! continues where it was. A pseudoterminal without a client is waited on the same way.
//! Nothing here blocks: output waits in a bounded buffer per line, beyond which it is dropped
//! (counted) and the reliable streams repair it.

use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use mio::event::Event;
use mio::unix::SourceFd;
use mio::{Interest, Registry, Token};
use xrce_common::framing::serial::{self as framing, SerialDecoder, AGENT_ADDRESS};
use xrce_common::wire::info::TransportLocator;

use super::serial::{OpenError, TtyConfig};
use super::{is_gone, Transport, TransportStats};

/// How often a missing device is looked for, and a pty checked for a client.
pub const REOPEN_PERIOD: Duration = Duration::from_millis(100);
/// Output a line may queue, in line time: beyond it new messages are dropped (counted),
/// rather than queued behind seconds of old output the client would ask for again.
pub const LINE_SEND_TIME: Duration = Duration::from_millis(250);
/// Output queued for a line at least (and for a pseudoterminal, which has no rate).
pub const LINE_SEND_MIN: usize = 4096;
/// Output queued for a pseudoterminal.
pub const PTY_SEND_BUFFER: usize = 64 << 10;
/// Bytes read from a line at once.
const READ_CHUNK: usize = 4096;
/// Bytes read from one line per loop pass before the others get a turn.
const READ_BUDGET: usize = 64 << 10;

/// A client on a line: which line, and its address there.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct SerialEndpoint {
    /// Index of the line, in the order the devices were given.
    pub line: u16,
    /// The client's address on it.
    pub address: u8,
}

impl xrce_common::session::budget::Origin for SerialEndpoint {
    /// Everyone on a line shares its wire: one origin per line.
    fn origin(&self) -> xrce_common::session::budget::OriginId {
        xrce_common::session::budget::OriginId(u128::from(self.line))
    }
    fn ip(&self) -> Option<std::net::IpAddr> {
        None
    }
}

impl super::StoredEndpoint for SerialEndpoint {
    fn stored(&self) -> Vec<u8> {
        let mut out = self.line.to_le_bytes().to_vec();
        out.push(self.address);
        out
    }
}

/// What a line is.
#[derive(Debug)]
pub enum LineDevice {
    /// A serial device, opened (and reopened) by path.
    Tty(TtyConfig),
    /// The master side of a pseudoterminal, open for the transport's whole life.
    Pty {
        /// The master.
        master: File,
        /// Its slave's path (for logs).
        slave_path: PathBuf,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LineState {
    /// Open and registered.
    Up,
    /// Not open (tty) or without a client (pty): look again then.
    Waiting(Instant),
}

#[derive(Debug)]
struct Line {
    device: LineDevice,
    /// The open tty (for a pty, the master lives in `device`).
    tty: Option<File>,
    state: LineState,
    decoder: SerialDecoder,
    out: Vec<u8>,
    out_start: usize,
    writable: bool,
    readable: bool,
    /// The last open error reported, so each distinct one is logged once.
    last_error: Option<OpenError>,
    /// When it last went down, for the outage length in the log.
    down_since: Option<Instant>,
    /// Bytes of output it may queue.
    send_limit: usize,
}

impl Line {
    fn path(&self) -> &Path {
        match &self.device {
            LineDevice::Tty(c) => &c.path,
            LineDevice::Pty { slave_path, .. } => slave_path,
        }
    }

    fn file(&self) -> Option<&File> {
        match &self.device {
            LineDevice::Tty(_) => self.tty.as_ref(),
            LineDevice::Pty { master, .. } => Some(master),
        }
    }

    fn pending_out(&self) -> usize {
        self.out.len() - self.out_start
    }

    /// Writes buffered output; `Err` when the device is gone.
    fn flush(&mut self) -> std::io::Result<()> {
        while self.out_start < self.out.len() {
            let Some(mut f) = self.file() else {
                return Ok(());
            };
            match f.write(&self.out[self.out_start..]) {
                Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
                Ok(n) => self.out_start += n,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        if self.out_start == self.out.len() {
            self.out.clear();
            self.out_start = 0;
        } else if self.out_start > self.out.len() / 2 {
            self.out.drain(..self.out_start);
            self.out_start = 0;
        }
        Ok(())
    }
}

/// The serial-lines transport.
#[derive(Debug)]
pub struct SerialTransport {
    name: &'static str,
    lines: Vec<Line>,
    registry: Option<Registry>,
    first_token: usize,
    read_buf: Vec<u8>,
    frame_buf: Vec<u8>,
    /// The line read first in the next pass (turns rotate, so none starves).
    next_first: usize,
    stats: TransportStats,
}

impl SerialTransport {
    /// A transport over `devices` (at most 65,536), named `name` in logs (`serial`,
    /// `multiserial`, `pseudoterminal`).
    pub fn new(name: &'static str, devices: Vec<LineDevice>, max_payload: usize) -> Self {
        let now = Instant::now();
        let lines = devices
            .into_iter()
            .take(u16::MAX as usize + 1)
            .map(|device| Line {
                send_limit: match &device {
                    LineDevice::Tty(c) => {
                        let per_second = f64::from(c.baudrate) / 10.0;
                        ((per_second * LINE_SEND_TIME.as_secs_f64()) as usize).max(LINE_SEND_MIN)
                    }
                    LineDevice::Pty { .. } => PTY_SEND_BUFFER,
                },
                device,
                tty: None,
                state: LineState::Waiting(now),
                decoder: SerialDecoder::new(AGENT_ADDRESS, max_payload),
                out: Vec::new(),
                out_start: 0,
                writable: false,
                readable: false,
                last_error: None,
                down_since: None,
            })
            .collect();
        SerialTransport {
            name,
            lines,
            registry: None,
            first_token: 0,
            read_buf: vec![0; READ_CHUNK],
            frame_buf: Vec::new(),
            next_first: 0,
            stats: TransportStats::default(),
        }
    }

    /// How many lines are open (with a client, for a pty).
    pub fn lines_up(&self) -> usize {
        self.lines
            .iter()
            .filter(|l| l.state == LineState::Up)
            .count()
    }

    fn token(&self, line: usize) -> Token {
        Token(self.first_token + line)
    }

    /// Tries to bring a waiting line up.
    fn try_open(&mut self, i: usize, now: Instant) {
        let token = self.token(i);
        let Some(registry) = self.registry.as_ref() else {
            return;
        };
        let line = &mut self.lines[i];
        match &line.device {
            LineDevice::Tty(config) => match super::serial::open(config) {
                Ok(f) => line.tty = Some(f),
                Err(e) => {
                    if line.last_error.as_ref() != Some(&e) {
                        let msg = e.explain(&config.path);
                        match e {
                            OpenError::Absent => tracing::info!(line = i, "{msg}"),
                            _ => tracing::error!(line = i, "{msg}"),
                        }
                        line.last_error = Some(e);
                    }
                    line.state = LineState::Waiting(now + REOPEN_PERIOD);
                    return;
                }
            },
            LineDevice::Pty { master, .. } => {
                if !slave_is_open(master) {
                    line.state = LineState::Waiting(now + REOPEN_PERIOD);
                    return;
                }
            }
        }
        let Some(fd) = line.file().map(AsRawFd::as_raw_fd) else {
            return;
        };
        if let Err(e) = registry.register(&mut SourceFd(&fd), token, Interest::READABLE) {
            tracing::error!(line = i, path = %line.path().display(), error = %e, "cannot watch the serial line");
            line.tty = None;
            line.state = LineState::Waiting(now + REOPEN_PERIOD);
            return;
        }
        line.state = LineState::Up;
        line.readable = true;
        line.writable = false;
        line.last_error = None;
        self.stats.opened += 1;
        let outage_ms = line.down_since.take().map(|t| (now - t).as_millis() as u64);
        match (&line.device, outage_ms) {
            (LineDevice::Tty(c), None) => {
                tracing::info!(line = i, path = %c.path.display(), baudrate = c.baudrate, flow_control = c.flow_control, "serial device opened")
            }
            (LineDevice::Tty(c), Some(ms)) => {
                tracing::info!(line = i, path = %c.path.display(), outage_ms = ms, "serial device back; its clients' sessions continue")
            }
            (LineDevice::Pty { slave_path, .. }, None) => {
                tracing::info!(line = i, path = %slave_path.display(), "pseudoterminal ready for a client")
            }
            (LineDevice::Pty { slave_path, .. }, Some(_)) => {
                tracing::info!(line = i, path = %slave_path.display(), "a client opened the pseudoterminal")
            }
        }
    }

    /// Takes a line down: its device went away (or its pty client left).
    fn take_down(&mut self, i: usize, now: Instant, why: &str) {
        let line = &mut self.lines[i];
        if line.state != LineState::Up {
            return;
        }
        if let (Some(r), Some(fd)) = (&self.registry, line.file().map(AsRawFd::as_raw_fd)) {
            let _ = r.deregister(&mut SourceFd(&fd));
        }
        line.tty = None;
        line.decoder.reset();
        let lost = line.pending_out();
        line.out = Vec::new();
        line.out_start = 0;
        line.readable = false;
        line.writable = false;
        line.state = LineState::Waiting(now + REOPEN_PERIOD);
        line.down_since = Some(now);
        self.stats.closed += 1;
        match &line.device {
            LineDevice::Tty(c) => {
                tracing::warn!(line = i, path = %c.path.display(), why, unsent_bytes = lost, "serial device gone (unplugged?); its clients' sessions are kept while it is waited for")
            }
            LineDevice::Pty { slave_path, .. } => {
                tracing::info!(line = i, path = %slave_path.display(), why, "the pseudoterminal's client closed it; waiting for another")
            }
        }
    }

    fn read_line(
        &mut self,
        i: usize,
        now: Instant,
        budget: usize,
        deliver: &mut dyn FnMut(SerialEndpoint, &[u8]),
    ) -> usize {
        let mut delivered = 0;
        let mut read = 0;
        let mut gone: Option<String> = None;
        {
            let line = &mut self.lines[i];
            let stats = &mut self.stats;
            let buf = &mut self.read_buf;
            while line.readable && delivered < budget && read < READ_BUDGET {
                let Some(mut f) = line.file() else {
                    break;
                };
                match f.read(buf) {
                    Ok(0) => {
                        gone = Some("end of file".into());
                        break;
                    }
                    Ok(n) => {
                        read += n;
                        line.decoder.push(&buf[..n], |frame| match frame {
                            Ok(f) if f.payload.is_empty() => {
                                stats.drop("serial_empty_frame");
                            }
                            Ok(f) => {
                                stats.messages_in += 1;
                                delivered += 1;
                                deliver(
                                    SerialEndpoint {
                                        line: i as u16,
                                        address: f.source,
                                    },
                                    f.payload,
                                );
                            }
                            Err(e) => {
                                let n = stats.drop(e.reason());
                                tracing::debug!(
                                    line = i,
                                    reason = e.reason(),
                                    dropped = n,
                                    "serial frame dropped"
                                );
                            }
                        });
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => line.readable = false,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        gone = Some(e.to_string());
                        break;
                    }
                }
            }
        }
        if let Some(why) = gone {
            self.take_down(i, now, &why);
        }
        delivered
    }
}

impl Transport for SerialTransport {
    type Endpoint = SerialEndpoint;

    fn name(&self) -> &'static str {
        self.name
    }

    fn max_message_size(&self) -> u16 {
        framing::MAX_PAYLOAD as u16
    }

    fn register(&mut self, registry: &Registry, first_token: usize) -> std::io::Result<()> {
        self.first_token = first_token;
        self.registry = Some(registry.try_clone()?);
        let now = Instant::now();
        for i in 0..self.lines.len() {
            if let LineDevice::Pty { slave_path, .. } = &self.lines[i].device {
                tracing::info!(path = %slave_path.display(), "pseudoterminal serving; clients open its slave");
            }
            self.try_open(i, now);
        }
        Ok(())
    }

    fn on_event(&mut self, event: &Event) {
        let Some(i) = event.token().0.checked_sub(self.first_token) else {
            return;
        };
        let now = Instant::now();
        let Some(line) = self.lines.get_mut(i) else {
            return;
        };
        if line.state != LineState::Up {
            return;
        }
        if event.is_readable() || event.is_read_closed() || event.is_error() {
            // A hang-up shows as a read of 0 bytes or EIO.
            line.readable = true;
        }
        if event.is_writable() {
            if let Err(e) = line.flush() {
                return self.take_down(i, now, &e.to_string());
            }
            if line.pending_out() == 0 && line.writable {
                let token = self.token(i);
                let line = &mut self.lines[i];
                if let (Some(r), Some(fd)) = (&self.registry, line.file().map(AsRawFd::as_raw_fd)) {
                    if r.reregister(&mut SourceFd(&fd), token, Interest::READABLE)
                        .is_ok()
                    {
                        line.writable = false;
                    }
                }
            }
        }
    }

    fn receive(
        &mut self,
        now: Instant,
        budget: usize,
        deliver: &mut dyn FnMut(SerialEndpoint, &[u8]),
    ) -> bool {
        let mut budget = budget;
        let n = self.lines.len();
        let first = self.next_first % n.max(1);
        self.next_first = first + 1;
        for k in 0..n {
            if budget == 0 {
                break;
            }
            let i = (first + k) % n;
            if self.lines[i].state == LineState::Up && self.lines[i].readable {
                budget -= self.read_line(i, now, budget, deliver).min(budget);
            }
        }
        self.lines
            .iter()
            .any(|l| l.state == LineState::Up && l.readable)
    }

    fn send(&mut self, to: SerialEndpoint, message: &[u8]) {
        let now = Instant::now();
        let i = to.line as usize;
        let Some(line) = self.lines.get_mut(i) else {
            self.stats.drop("serial_no_such_line");
            return;
        };
        if line.state != LineState::Up {
            self.stats.drop("serial_line_down");
            return;
        }
        self.frame_buf.clear();
        if framing::encode(AGENT_ADDRESS, to.address, message, &mut self.frame_buf).is_err() {
            self.stats.drop("message_too_long");
            return;
        }
        if line.pending_out() + self.frame_buf.len() > line.send_limit {
            let n = self.stats.drop("serial_send_buffer_full");
            if n.is_power_of_two() {
                tracing::warn!(line = i, path = %line.path().display(), dropped = n, "serial line too slow for its output; messages dropped (raise the baud rate?)");
            }
            return;
        }
        line.out.extend_from_slice(&self.frame_buf);
        self.stats.messages_out += 1;
        if let Err(e) = line.flush() {
            if is_gone(&e) || e.kind() == std::io::ErrorKind::WriteZero {
                return self.take_down(i, now, &e.to_string());
            }
            self.stats.drop("serial_write_failed");
            tracing::debug!(line = i, error = %e, "serial write");
            return;
        }
        if line.pending_out() > 0 && !line.writable {
            let token = self.token(i);
            let line = &mut self.lines[i];
            if let (Some(r), Some(fd)) = (&self.registry, line.file().map(AsRawFd::as_raw_fd)) {
                if r.reregister(
                    &mut SourceFd(&fd),
                    token,
                    Interest::READABLE | Interest::WRITABLE,
                )
                .is_ok()
                {
                    line.writable = true;
                }
            }
        }
    }

    fn poll_closed(&mut self) -> Option<SerialEndpoint> {
        // Lines come back: their endpoints are never gone for good.
        None
    }

    fn poll_timeout(&self) -> Option<Instant> {
        self.lines
            .iter()
            .filter_map(|l| match l.state {
                LineState::Waiting(t) => Some(t),
                LineState::Up => None,
            })
            .min()
    }

    fn handle_timeout(&mut self, now: Instant) {
        for i in 0..self.lines.len() {
            if matches!(self.lines[i].state, LineState::Waiting(t) if t <= now) {
                self.try_open(i, now);
            }
        }
    }

    fn stats(&self) -> &TransportStats {
        &self.stats
    }

    fn locators(&self) -> Vec<TransportLocator> {
        Vec::new()
    }

    fn serving(&self) -> String {
        let paths: Vec<String> = self
            .lines
            .iter()
            .map(|l| l.path().display().to_string())
            .collect();
        paths.join(", ")
    }

    fn describe(&self, endpoint: SerialEndpoint) -> String {
        match self.lines.get(endpoint.line as usize) {
            Some(l) => format!("{} address {}", l.path().display(), endpoint.address),
            None => format!("line {} address {}", endpoint.line, endpoint.address),
        }
    }

    fn decode_endpoint(&self, bytes: &[u8]) -> Option<SerialEndpoint> {
        let [a, b, address] = bytes.try_into().ok()?;
        let line = u16::from_le_bytes([a, b]);
        ((line as usize) < self.lines.len()).then_some(SerialEndpoint { line, address })
    }
}

/// `serial` and `multiserial` (named `name`): the `lines` at `baudrate`.
pub fn open(name: &'static str, lines: Vec<LineDevice>, baudrate: u32) -> SerialTransport {
    if !super::serial::is_standard_rate(baudrate) {
        tracing::warn!(baudrate, "not a standard baud rate: set as a custom rate");
    }
    SerialTransport::new(name, lines, framing::MAX_PAYLOAD)
}

/// Whether a program has the slave side of `master` open (the master reports no hang-up).
pub fn slave_is_open(master: &File) -> bool {
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
    use std::os::fd::AsFd;
    let mut fds = [PollFd::new(master.as_fd(), PollFlags::POLLIN)];
    match poll(&mut fds, PollTimeout::ZERO) {
        Ok(_) => !fds[0]
            .revents()
            .is_some_and(|r| r.contains(PollFlags::POLLHUP)),
        Err(_) => false,
    }
}
