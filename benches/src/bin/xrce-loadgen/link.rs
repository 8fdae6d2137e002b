//! How a simulated client reaches the agent: a UDP socket, a TCP connection (2-byte length
//! prefix) or a serial line (a pty master, eProsima's stream framing) whose output is paced at
//! a baud rate, as a UART would send it (a pty itself moves bytes at memory speed).

use std::collections::VecDeque;
use std::fs::File;
use std::io::{Read, Write};
use std::net::{TcpStream, UdpSocket};
use std::os::fd::{AsFd, BorrowedFd};
use std::time::{Duration, Instant};

use xrce_common::framing::length_prefix::{self, LengthPrefixDecoder};
use xrce_common::framing::serial::{self as serial_framing, SerialDecoder, AGENT_ADDRESS};

/// Bits on the wire per byte at 8N1: start, 8 data, stop.
pub const BITS_PER_BYTE: f64 = 10.0;

/// A simulated client's connection.
pub enum PeerLink {
    /// One datagram per message.
    Udp(UdpSocket),
    /// A TCP connection.
    Tcp {
        /// The connection (non-blocking).
        stream: TcpStream,
        /// Splits what arrives.
        decoder: LengthPrefixDecoder,
        /// Framed bytes the socket did not take yet.
        out: VecDeque<u8>,
    },
    /// A serial line (this client at address 1), paced at `bytes_per_second`.
    Serial {
        /// The pty master.
        line: File,
        /// Splits what arrives.
        decoder: SerialDecoder,
        /// Framed bytes waiting for the line.
        out: VecDeque<u8>,
        /// The line's rate in bytes per second.
        bytes_per_second: f64,
        /// When the line is free for the next byte.
        free_at: Instant,
    },
}

/// The client's address on its serial line.
const CLIENT_ADDRESS: u8 = 1;

/// Bytes a receiving UART collects before it hands them over (a 16550's receive FIFO with
/// its trigger level at 14; USB serial adapters hand over 64 bytes or more at a time), so the
/// agent reads a serial line in chunks as it would on hardware, not byte by byte.
const UART_FIFO: usize = 14;

/// How long `n` bytes take on a line of `bytes_per_second`.
fn byte_time(n: usize, bytes_per_second: f64) -> Duration {
    Duration::from_secs_f64(n as f64 / bytes_per_second)
}

impl PeerLink {
    /// The descriptor to wait on.
    pub fn fd(&self) -> BorrowedFd<'_> {
        match self {
            PeerLink::Udp(s) => s.as_fd(),
            PeerLink::Tcp { stream, .. } => stream.as_fd(),
            PeerLink::Serial { line, .. } => line.as_fd(),
        }
    }

    /// A serial line at `baud` bits per second.
    pub fn serial(line: File, baud: u32) -> Self {
        PeerLink::Serial {
            line,
            decoder: SerialDecoder::new(CLIENT_ADDRESS, serial_framing::MAX_PAYLOAD),
            out: VecDeque::new(),
            bytes_per_second: f64::from(baud.max(1)) / BITS_PER_BYTE,
            free_at: Instant::now(),
        }
    }

    /// A TCP connection.
    pub fn tcp(stream: TcpStream) -> Self {
        PeerLink::Tcp {
            stream,
            decoder: LengthPrefixDecoder::new(length_prefix::MAX_MESSAGE),
            out: VecDeque::new(),
        }
    }

    /// Queues one message and writes what the link takes now.
    pub fn send(&mut self, message: &[u8], now: Instant) {
        match self {
            PeerLink::Udp(s) => {
                let _ = s.send(message);
            }
            PeerLink::Tcp { out, .. } => {
                let mut framed = Vec::with_capacity(message.len() + 2);
                if length_prefix::encode(message, &mut framed).is_ok() {
                    out.extend(framed);
                }
                self.flush(now);
            }
            PeerLink::Serial { out, free_at, .. } => {
                let mut framed = Vec::with_capacity(message.len() + 16);
                if serial_framing::encode(CLIENT_ADDRESS, AGENT_ADDRESS, message, &mut framed)
                    .is_ok()
                {
                    if out.is_empty() {
                        // An idle line starts sending now.
                        *free_at = (*free_at).max(now);
                    }
                    out.extend(framed);
                }
                self.flush(now);
            }
        }
    }

    /// Writes queued bytes: all the socket takes (TCP), or what the line's rate allows by
    /// `now` (serial).
    pub fn flush(&mut self, now: Instant) {
        match self {
            PeerLink::Udp(_) => {}
            PeerLink::Tcp { stream, out, .. } => {
                while !out.is_empty() {
                    let (a, _) = out.as_slices();
                    match stream.write(a) {
                        Ok(n) if n > 0 => {
                            out.drain(..n);
                        }
                        _ => break,
                    }
                }
            }
            PeerLink::Serial {
                line,
                out,
                bytes_per_second,
                free_at,
                ..
            } => {
                // The receiving UART hands bytes over a FIFO's worth at a time (or what is
                // left in the queue), once the last of them has crossed the line; later
                // than that, all that has arrived by now.
                let first = out.len().min(UART_FIFO);
                if out.is_empty() || now < *free_at + byte_time(first, *bytes_per_second) {
                    return;
                }
                let arrived = now.saturating_duration_since(*free_at).as_secs_f64();
                let n = ((arrived * *bytes_per_second) as usize).clamp(first, out.len());
                let chunk: Vec<u8> = out.iter().take(n).copied().collect();
                match line.write(&chunk) {
                    Ok(w) => {
                        out.drain(..w);
                        *free_at = if w == n {
                            *free_at + byte_time(w, *bytes_per_second)
                        } else {
                            // The pty is full (the agent is not reading): the rest waits a
                            // FIFO's time from now rather than being retried at once.
                            now
                        };
                    }
                    Err(_) => *free_at = now,
                }
            }
        }
    }

    /// When queued output can go next (serial pacing; TCP waiting for room), if any.
    pub fn next_flush(&self, now: Instant) -> Option<Instant> {
        match self {
            PeerLink::Udp(_) => None,
            PeerLink::Tcp { out, .. } => (!out.is_empty()).then(|| now + Duration::from_millis(1)),
            PeerLink::Serial {
                out,
                free_at,
                bytes_per_second,
                ..
            } => (!out.is_empty()).then(|| {
                (*free_at + byte_time(out.len().min(UART_FIFO), *bytes_per_second)).max(now)
            }),
        }
    }

    /// Reads what arrived and hands each whole message to `on_message`.
    pub fn receive(&mut self, buf: &mut [u8], mut on_message: impl FnMut(&[u8])) {
        match self {
            PeerLink::Udp(s) => {
                while let Ok(n) = s.recv(buf) {
                    on_message(&buf[..n]);
                }
            }
            PeerLink::Tcp {
                stream, decoder, ..
            } => {
                while let Ok(n) = stream.read(buf) {
                    if n == 0 || decoder.push(&buf[..n], &mut on_message).is_err() {
                        break;
                    }
                }
            }
            PeerLink::Serial { line, decoder, .. } => {
                while let Ok(n) = line.read(buf) {
                    if n == 0 {
                        break;
                    }
                    decoder.push(&buf[..n], |f| {
                        if let Ok(f) = f {
                            on_message(f.payload);
                        }
                    });
                }
            }
        }
    }
}

/// A raw pty pair: the master (for the client) and the slave's path (for the agent).
pub fn pty_pair() -> Result<(File, std::path::PathBuf), String> {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    let m = nix::pty::posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC)
        .map_err(|e| format!("posix_openpt: {e}"))?;
    nix::pty::grantpt(&m).map_err(|e| format!("grantpt: {e}"))?;
    nix::pty::unlockpt(&m).map_err(|e| format!("unlockpt: {e}"))?;
    let path = std::path::PathBuf::from(nix::pty::ptsname_r(&m).map_err(|e| e.to_string())?);
    let m = File::from(std::os::fd::OwnedFd::from(m));
    let mut t = nix::sys::termios::tcgetattr(&m).map_err(|e| e.to_string())?;
    nix::sys::termios::cfmakeraw(&mut t);
    nix::sys::termios::tcsetattr(&m, nix::sys::termios::SetArg::TCSANOW, &t)
        .map_err(|e| e.to_string())?;
    let flags = fcntl(&m, FcntlArg::F_GETFL).map_err(|e| e.to_string())?;
    fcntl(
        &m,
        FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
    )
    .map_err(|e| e.to_string())?;
    Ok((m, path))
}
