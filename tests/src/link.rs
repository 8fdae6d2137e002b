//! How a test client reaches the agent: a UDP socket, a TCP connection (length-prefixed
//! messages) or a serial line (the master side of a pty whose slave the agent opened, with
//! eProsima's stream framing). Each delivers whole XRCE messages both ways.

use std::fs::File;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, UdpSocket};
use std::os::fd::AsFd;
use std::time::{Duration, Instant};

use xrce_common::framing::length_prefix::{self, LengthPrefixDecoder};
use xrce_common::framing::serial::{self as serial_framing, SerialDecoder, AGENT_ADDRESS};

/// A client's connection to the agent.
#[derive(Debug)]
pub enum Link {
    /// One datagram per message.
    Udp(UdpSocket),
    /// A TCP connection.
    Tcp {
        /// The connection (non-blocking).
        stream: TcpStream,
        /// Splits the byte stream.
        decoder: LengthPrefixDecoder,
    },
    /// A serial line shared with other clients (at other addresses) of this test.
    SharedSerial {
        /// The line and what arrived on it for each address.
        line: SharedLine,
        /// This client's address on the line.
        address: u8,
    },
    /// A serial line.
    Serial {
        /// The line (non-blocking).
        file: File,
        /// Splits the byte stream.
        decoder: SerialDecoder,
        /// This client's address on the line.
        address: u8,
    },
}

impl Link {
    /// A UDP socket on loopback connected to `agent`.
    pub fn udp(agent: SocketAddr) -> Self {
        let local: SocketAddr = if agent.is_ipv4() {
            "127.0.0.1:0".parse().expect("addr")
        } else {
            "[::1]:0".parse().expect("addr")
        };
        let socket = UdpSocket::bind(local).expect("bind client");
        socket.connect(agent).expect("connect");
        socket.set_nonblocking(true).expect("non-blocking");
        Link::Udp(socket)
    }

    /// A UDP socket at `local` (an address of this host, e.g. 127.0.0.2: every address of
    /// 127.0.0.0/8 is local) connected to `agent`: a client from another host, as far as
    /// the agent can tell.
    pub fn udp_from(agent: SocketAddr, local: std::net::IpAddr) -> Self {
        let socket = UdpSocket::bind(SocketAddr::new(local, 0)).expect("bind client");
        socket.connect(agent).expect("connect");
        socket.set_nonblocking(true).expect("non-blocking");
        Link::Udp(socket)
    }

    /// A UDP socket bound to exactly `local` (a port a client used before: a board whose
    /// UDP stack always sends from the same port) connected to `agent`.
    pub fn udp_at(agent: SocketAddr, local: SocketAddr) -> std::io::Result<Self> {
        let socket = UdpSocket::bind(local)?;
        socket.connect(agent)?;
        socket.set_nonblocking(true)?;
        Ok(Link::Udp(socket))
    }

    /// The local address of a UDP link.
    pub fn local_udp_addr(&self) -> Option<SocketAddr> {
        match self {
            Link::Udp(s) => s.local_addr().ok(),
            _ => None,
        }
    }

    /// A TCP connection to `agent`.
    pub fn tcp(agent: SocketAddr) -> std::io::Result<Self> {
        let stream = TcpStream::connect_timeout(&agent, Duration::from_secs(5))?;
        stream.set_nodelay(true)?;
        stream.set_nonblocking(true)?;
        Ok(Link::Tcp {
            stream,
            decoder: LengthPrefixDecoder::new(length_prefix::MAX_MESSAGE),
        })
    }

    /// A TCP connection to `agent` from the local address `local` (127.0.0.2, say).
    pub fn tcp_from(agent: SocketAddr, local: std::net::IpAddr) -> std::io::Result<Self> {
        let domain = if agent.is_ipv4() {
            socket2::Domain::IPV4
        } else {
            socket2::Domain::IPV6
        };
        let socket = socket2::Socket::new(domain, socket2::Type::STREAM, None)?;
        socket.bind(&SocketAddr::new(local, 0).into())?;
        socket.connect_timeout(&agent.into(), Duration::from_secs(5))?;
        let stream: TcpStream = socket.into();
        stream.set_nodelay(true)?;
        stream.set_nonblocking(true)?;
        Ok(Link::Tcp {
            stream,
            decoder: LengthPrefixDecoder::new(length_prefix::MAX_MESSAGE),
        })
    }

    /// A serial line (for example a pty master) on which this client has `address`.
    pub fn serial(file: File, address: u8) -> Self {
        set_nonblocking(&file);
        Link::Serial {
            file,
            decoder: SerialDecoder::new(address, serial_framing::MAX_PAYLOAD),
            address,
        }
    }

    /// Sends one message; returns whether it went out (a closed link fails).
    pub fn send(&mut self, message: &[u8]) -> bool {
        match self {
            Link::Udp(s) => s.send(message).is_ok(),
            Link::Tcp { stream, .. } => {
                // As the eProsima client sends it: the prefix, then the message, apart.
                let Ok(len) = u16::try_from(message.len()) else {
                    return false;
                };
                write_all(stream, &len.to_le_bytes()) && write_all(stream, message)
            }
            Link::Serial { file, address, .. } => {
                let mut framed = Vec::new();
                if serial_framing::encode(*address, AGENT_ADDRESS, message, &mut framed).is_err() {
                    return false;
                }
                write_all(file, &framed)
            }
            Link::SharedSerial { line, address } => {
                let mut framed = Vec::new();
                if serial_framing::encode(*address, AGENT_ADDRESS, message, &mut framed).is_err() {
                    return false;
                }
                let Ok(mut l) = line.0.lock() else {
                    return false;
                };
                write_all(&mut l.file, &framed)
            }
        }
    }

    /// Waits up to `wait` for input, then returns every whole message that arrived.
    pub fn receive(&mut self, wait: Duration, buf: &mut [u8]) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        if let Link::SharedSerial { line, address } = self {
            return line.receive(*address, wait, buf);
        }
        let readable = match self {
            Link::SharedSerial { .. } => false,
            Link::Udp(s) => wait_readable(s, wait),
            Link::Tcp { stream, .. } => wait_readable(stream, wait),
            Link::Serial { file, .. } => wait_readable(file, wait),
        };
        if !readable {
            return out;
        }
        match self {
            Link::SharedSerial { .. } => {}
            Link::Udp(s) => {
                while let Ok(n) = s.recv(buf) {
                    out.push(buf[..n].to_vec());
                }
            }
            Link::Tcp { stream, decoder } => {
                while let Ok(n) = stream.read(buf) {
                    if n == 0 {
                        break;
                    }
                    if decoder.push(&buf[..n], |m| out.push(m.to_vec())).is_err() {
                        break;
                    }
                }
            }
            Link::Serial { file, decoder, .. } => {
                while let Ok(n) = file.read(buf) {
                    if n == 0 {
                        break;
                    }
                    decoder.push(&buf[..n], |f| {
                        if let Ok(f) = f {
                            if f.source == AGENT_ADDRESS {
                                out.push(f.payload.to_vec());
                            }
                        }
                    });
                }
            }
        }
        out
    }
}

/// Writes everything to a non-blocking descriptor, waiting (up to 5 s) while it is full.
fn write_all(w: &mut impl Write, mut bytes: &[u8]) -> bool {
    let end = Instant::now() + Duration::from_secs(5);
    while !bytes.is_empty() {
        match w.write(bytes) {
            Ok(0) => return false,
            Ok(n) => bytes = &bytes[n..],
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock && Instant::now() < end => {
                std::thread::sleep(Duration::from_millis(1))
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(_) => return false,
        }
    }
    true
}

fn wait_readable(fd: &impl AsFd, wait: Duration) -> bool {
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
    let ms = u16::try_from(wait.as_millis()).unwrap_or(u16::MAX);
    let mut fds = [PollFd::new(fd.as_fd(), PollFlags::POLLIN)];
    matches!(poll(&mut fds, PollTimeout::from(ms)), Ok(n) if n > 0)
}

pub(crate) fn set_nonblocking(file: &File) {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    if let Ok(flags) = fcntl(file, FcntlArg::F_GETFL) {
        let flags = OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK;
        let _ = fcntl(file, FcntlArg::F_SETFL(flags));
    }
}

/// A pseudoterminal pair for a serial test: the agent opens `slave_path` as its device,
/// the test client talks on `master`. Both sides raw.
#[derive(Debug)]
pub struct PtyPair {
    /// The client's side.
    pub master: File,
    /// What the agent opens.
    pub slave_path: std::path::PathBuf,
}

impl PtyPair {
    /// Opens a new pair.
    pub fn open() -> Self {
        use nix::fcntl::OFlag;
        let master = nix::pty::posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC)
            .expect("posix_openpt");
        nix::pty::grantpt(&master).expect("grantpt");
        nix::pty::unlockpt(&master).expect("unlockpt");
        let slave_path = std::path::PathBuf::from(nix::pty::ptsname_r(&master).expect("ptsname"));
        let master = File::from(std::os::fd::OwnedFd::from(master));
        let mut t = nix::sys::termios::tcgetattr(&master).expect("tcgetattr");
        nix::sys::termios::cfmakeraw(&mut t);
        nix::sys::termios::tcsetattr(&master, nix::sys::termios::SetArg::TCSANOW, &t)
            .expect("tcsetattr");
        PtyPair { master, slave_path }
    }
}

/// One serial line several test clients share: whatever is read from it is decoded for
/// every address and queued for the client at that address.
#[derive(Debug, Clone)]
pub struct SharedLine(std::sync::Arc<std::sync::Mutex<SharedLineState>>);

/// The state behind a [`SharedLine`].
#[derive(Debug)]
pub struct SharedLineState {
    file: File,
    decoders: std::collections::BTreeMap<u8, SerialDecoder>,
    queues: std::collections::BTreeMap<u8, std::collections::VecDeque<Vec<u8>>>,
}

impl SharedLine {
    /// Shares `file` (a pty master) between clients.
    pub fn new(file: File) -> Self {
        set_nonblocking(&file);
        SharedLine(std::sync::Arc::new(std::sync::Mutex::new(
            SharedLineState {
                file,
                decoders: Default::default(),
                queues: Default::default(),
            },
        )))
    }

    /// A link for the client at `address`.
    pub fn link(&self, address: u8) -> Link {
        if let Ok(mut l) = self.0.lock() {
            l.decoders.insert(
                address,
                SerialDecoder::new(address, serial_framing::MAX_PAYLOAD),
            );
            l.queues.entry(address).or_default();
        }
        Link::SharedSerial {
            line: self.clone(),
            address,
        }
    }

    fn receive(&self, address: u8, wait: Duration, buf: &mut [u8]) -> Vec<Vec<u8>> {
        let Ok(mut guard) = self.0.lock() else {
            return Vec::new();
        };
        let l = &mut *guard;
        if l.queues.get(&address).is_some_and(|q| q.is_empty()) && wait_readable(&l.file, wait) {
            while let Ok(n) = l.file.read(buf) {
                if n == 0 {
                    break;
                }
                for (a, d) in l.decoders.iter_mut() {
                    let q = l.queues.entry(*a).or_default();
                    d.push(&buf[..n], |f| {
                        if let Ok(f) = f {
                            if f.source == AGENT_ADDRESS {
                                q.push_back(f.payload.to_vec());
                            }
                        }
                    });
                }
            }
        }
        l.queues
            .get_mut(&address)
            .map(|q| q.drain(..).collect())
            .unwrap_or_default()
    }
}
