//! Pseudoterminals (`pseudoterminal` transport): the agent opens a pty master, prints the path
//! of its slave (`/dev/pts/N`), and a client program opens that path as its serial port.
//! The master is set raw (the pair shares one line discipline, so the slave is raw too: the
//! eProsima client sets no terminal mode itself).
//!
//! Once a client has closed the slave the master reports a hang-up until another opens it;
//! that is the normal state between clients, not an error: [`super::multiserial::slave_is_open`] tells when one
//! arrived. (Before the first client nothing tells; the line counts as open then, and nothing
//! is sent on it before a client speaks.)

use std::fs::File;
use std::os::fd::{AsFd, OwnedFd};
use std::path::PathBuf;

use nix::fcntl::OFlag;
use nix::sys::termios;

/// An open pseudoterminal.
#[derive(Debug)]
pub struct Pty {
    /// The master side (non-blocking), what the agent reads and writes.
    pub master: File,
    /// Where clients open the slave side.
    pub slave_path: PathBuf,
}

/// Opens a new pseudoterminal, raw, at `baudrate` (which a pty ignores; set for tools that
/// read it back).
pub fn open(baudrate: u32) -> std::io::Result<Pty> {
    let master = nix::pty::posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC)?;
    nix::pty::grantpt(&master)?;
    nix::pty::unlockpt(&master)?;
    let slave_path = PathBuf::from(nix::pty::ptsname_r(&master)?);
    let master = File::from(OwnedFd::from(master));
    make_raw(&master, baudrate)?;
    super::serial::set_nonblocking(&master)?;
    Ok(Pty { master, slave_path })
}

/// Sets a terminal raw 8N1 (no echo, no line editing, no translation).
pub fn make_raw(fd: &impl AsFd, baudrate: u32) -> std::io::Result<()> {
    let mut t = termios::tcgetattr(fd)?;
    termios::cfmakeraw(&mut t);
    if let Some(rate) = standard_baud(baudrate) {
        // Informational only on a pty; a rate without a termios constant is left alone.
        let _ = termios::cfsetspeed(&mut t, rate);
    }
    termios::tcsetattr(fd, termios::SetArg::TCSANOW, &t)?;
    Ok(())
}

fn standard_baud(rate: u32) -> Option<termios::BaudRate> {
    use termios::BaudRate::*;
    Some(match rate {
        9600 => B9600,
        19200 => B19200,
        38400 => B38400,
        57600 => B57600,
        115200 => B115200,
        230400 => B230400,
        460800 => B460800,
        500000 => B500000,
        576000 => B576000,
        921600 => B921600,
        1000000 => B1000000,
        1152000 => B1152000,
        1500000 => B1500000,
        2000000 => B2000000,
        2500000 => B2500000,
        3000000 => B3000000,
        3500000 => B3500000,
        4000000 => B4000000,
        _ => return None,
    })
}

/// `pseudoterminal`: serves the pty master the supervisor left open (`inherited`: its
/// descriptor and the slave's path), or opens a new pseudoterminal at `baudrate` and prints
/// its path.
pub fn open_transport(
    inherited: Option<(std::os::fd::RawFd, PathBuf)>,
    baudrate: u32,
) -> anyhow::Result<super::multiserial::SerialTransport> {
    use super::multiserial::{LineDevice, SerialTransport};
    let (master, slave_path) = match inherited {
        Some((fd, path)) => {
            let master = crate::sys::owned_fd::inherited(fd)?;
            super::serial::set_nonblocking(&master)?;
            (master, path)
        }
        None => {
            let pty = open(baudrate)?;
            let path = pty.slave_path.display();
            println!("Pseudoterminal opened at {path} (dev: {path})");
            (pty.master, pty.slave_path)
        }
    };
    Ok(SerialTransport::new(
        "pseudoterminal",
        vec![LineDevice::Pty { master, slave_path }],
        xrce_common::framing::serial::MAX_PAYLOAD,
    ))
}
