//! The serial-lines transport on real pseudoterminals, driven by a mio poll as the event loop
//! drives it: addresses as endpoints, a device that appears late, one held by another
//! program, and the agent's own pseudoterminal between clients.

use std::fs::File;
use std::io::{Read, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use mio::{Events, Poll};
use xrce_common::framing::serial::{encode, SerialDecoder, AGENT_ADDRESS};
use xrce_frontend::transport::multiserial::{LineDevice, SerialEndpoint, SerialTransport};
use xrce_frontend::transport::serial::TtyConfig;
use xrce_frontend::transport::Transport;

struct Harness {
    poll: Poll,
    events: Events,
    serial: SerialTransport,
}

impl Harness {
    fn new(devices: Vec<LineDevice>) -> Self {
        let mut serial = SerialTransport::new("serial", devices, 4096);
        let poll = Poll::new().expect("poll");
        serial.register(poll.registry(), 16).expect("register");
        Harness {
            poll,
            events: Events::with_capacity(64),
            serial,
        }
    }

    fn run(
        &mut self,
        d: Duration,
        mut done: impl FnMut(&SerialTransport, &[(SerialEndpoint, Vec<u8>)]) -> bool,
    ) -> Vec<(SerialEndpoint, Vec<u8>)> {
        let mut got = Vec::new();
        let end = Instant::now() + d;
        while Instant::now() < end {
            self.poll
                .poll(&mut self.events, Some(Duration::from_millis(10)))
                .expect("poll");
            for e in self.events.iter() {
                self.serial.on_event(e);
            }
            let now = Instant::now();
            self.serial
                .receive(now, 256, &mut |from, m| got.push((from, m.to_vec())));
            if self.serial.poll_timeout().is_some_and(|t| t <= now) {
                self.serial.handle_timeout(now);
            }
            if done(&self.serial, &got) {
                break;
            }
        }
        got
    }
}

/// A raw pty pair: (master, slave path).
fn pty_pair() -> (File, PathBuf) {
    use nix::fcntl::OFlag;
    let m = nix::pty::posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY).expect("openpt");
    nix::pty::grantpt(&m).expect("grantpt");
    nix::pty::unlockpt(&m).expect("unlockpt");
    let path = PathBuf::from(nix::pty::ptsname_r(&m).expect("ptsname"));
    let m = File::from(std::os::fd::OwnedFd::from(m));
    let mut t = nix::sys::termios::tcgetattr(&m).expect("tcgetattr");
    nix::sys::termios::cfmakeraw(&mut t);
    nix::sys::termios::tcsetattr(&m, nix::sys::termios::SetArg::TCSANOW, &t).expect("raw");
    (m, path)
}

fn tty(path: PathBuf) -> LineDevice {
    LineDevice::Tty(TtyConfig {
        path,
        baudrate: 921_600,
        flow_control: false,
    })
}

fn frame(src: u8, dst: u8, payload: &[u8]) -> Vec<u8> {
    let mut v = Vec::new();
    encode(src, dst, payload, &mut v).expect("fits");
    v
}

#[test]
fn each_address_on_a_line_is_an_endpoint_and_replies_go_to_it() {
    let (mut master, slave) = pty_pair();
    let mut h = Harness::new(vec![tty(slave)]);
    h.run(Duration::from_secs(5), |s, _| s.lines_up() == 1);
    let mut bytes = frame(1, AGENT_ADDRESS, b"from one");
    bytes.extend(frame(2, AGENT_ADDRESS, b"from two"));
    bytes.extend(frame(3, 7, b"not for the agent"));
    master.write_all(&bytes).expect("write");
    let got = h.run(Duration::from_secs(5), |s, g| {
        g.len() >= 2 && s.stats().dropped("foreign_destination") == 1
    });
    assert_eq!(
        got,
        [
            (
                SerialEndpoint {
                    line: 0,
                    address: 1
                },
                b"from one".to_vec()
            ),
            (
                SerialEndpoint {
                    line: 0,
                    address: 2
                },
                b"from two".to_vec()
            ),
        ]
    );
    assert_eq!(h.serial.stats().dropped("foreign_destination"), 1);
    h.serial.send(got[1].0, b"to two");
    let mut d = SerialDecoder::new(2, 4096);
    let mut replies = Vec::new();
    let end = Instant::now() + Duration::from_secs(5);
    let mut buf = [0u8; 256];
    crate_nonblocking(&master);
    while replies.is_empty() && Instant::now() < end {
        if let Ok(n) = master.read(&mut buf) {
            d.push(&buf[..n], |f| {
                let f = f.expect("valid frame");
                replies.push((f.source, f.payload.to_vec()));
            });
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(replies, [(AGENT_ADDRESS, b"to two".to_vec())]);
}

fn crate_nonblocking(f: &File) {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    let flags = fcntl(f, FcntlArg::F_GETFL).expect("getfl");
    fcntl(
        f,
        FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
    )
    .expect("setfl");
}

#[test]
fn a_device_that_appears_late_is_opened_and_output_meanwhile_is_counted() {
    let dir = std::env::temp_dir().join(format!("xrce-late-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let link = dir.join("ttyUSB0");
    let _ = std::fs::remove_file(&link);
    let mut h = Harness::new(vec![tty(link.clone())]);
    h.run(Duration::from_millis(300), |_, _| false);
    assert_eq!(h.serial.lines_up(), 0);
    let ep = SerialEndpoint {
        line: 0,
        address: 1,
    };
    h.serial.send(ep, b"nobody there");
    assert_eq!(h.serial.stats().dropped("serial_line_down"), 1);
    let (mut master, slave) = pty_pair();
    std::os::unix::fs::symlink(&slave, &link).expect("symlink");
    h.run(Duration::from_secs(5), |s, _| s.lines_up() == 1);
    assert_eq!(h.serial.lines_up(), 1, "not opened after it appeared");
    master
        .write_all(&frame(1, AGENT_ADDRESS, b"hello"))
        .expect("write");
    let got = h.run(Duration::from_secs(5), |_, g| !g.is_empty());
    assert_eq!(got, [(ep, b"hello".to_vec())]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_device_another_program_holds_is_waited_for() {
    let (_master, slave) = pty_pair();
    let mut first = Harness::new(vec![tty(slave.clone())]);
    first.run(Duration::from_secs(5), |s, _| s.lines_up() == 1);
    assert_eq!(first.serial.lines_up(), 1);
    // Opened exclusively: a second agent on the same device gets EBUSY and keeps waiting.
    let mut second = Harness::new(vec![tty(slave)]);
    second.run(Duration::from_millis(300), |_, _| false);
    assert_eq!(second.serial.lines_up(), 0);
    drop(first);
    second.run(Duration::from_secs(5), |s, _| s.lines_up() == 1);
    assert_eq!(second.serial.lines_up(), 1, "not opened once released");
}

#[test]
fn the_agents_pseudoterminal_waits_for_each_client() {
    let pty = xrce_frontend::transport::pty::open(115_200).expect("pty");
    let path = pty.slave_path.clone();
    let mut h = Harness::new(vec![LineDevice::Pty {
        master: pty.master,
        slave_path: path.clone(),
    }]);
    // A pty master cannot tell "no client yet" from "a client" until one has come and gone
    // (a hang-up): the line starts up, and nothing is sent on it before a client speaks.
    h.run(Duration::from_millis(100), |_, _| false);
    for round in 0..2u8 {
        let mut client = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&path)
            .expect("open the slave");
        h.run(Duration::from_secs(5), |s, _| s.lines_up() == 1);
        client
            .write_all(&frame(1, AGENT_ADDRESS, &[round]))
            .expect("write");
        let got = h.run(Duration::from_secs(5), |_, g| !g.is_empty());
        assert_eq!(got.len(), 1, "round {round}");
        assert_eq!(got[0].1, [round]);
        drop(client);
        h.run(Duration::from_secs(5), |s, _| s.lines_up() == 0);
        assert_eq!(h.serial.lines_up(), 0, "still up after the client left");
        // Output for a client that left is dropped (counted), not buffered for the next.
        let before = h.serial.stats().dropped("serial_line_down");
        h.serial.send(got[0].0, b"too late");
        assert_eq!(h.serial.stats().dropped("serial_line_down"), before + 1);
    }
    assert!(h.serial.stats().opened >= 2);
}

#[test]
fn standard_and_custom_baud_rates_are_accepted() {
    for baudrate in [9_600, 115_200, 921_600, 4_000_000, 250_000, 1_234_567] {
        let (mut master, slave) = pty_pair();
        let mut h = Harness::new(vec![LineDevice::Tty(TtyConfig {
            path: slave,
            baudrate,
            flow_control: baudrate == 250_000,
        })]);
        h.run(Duration::from_secs(5), |s, _| s.lines_up() == 1);
        assert_eq!(h.serial.lines_up(), 1, "{baudrate} baud not opened");
        master
            .write_all(&frame(1, AGENT_ADDRESS, b"rate"))
            .expect("write");
        let got = h.run(Duration::from_secs(5), |_, g| !g.is_empty());
        assert_eq!(got.len(), 1, "{baudrate} baud");
    }
}
