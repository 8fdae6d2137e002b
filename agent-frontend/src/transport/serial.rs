//! Serial devices (a UART, a USB CDC-ACM or FTDI adapter, a pty slave): opened raw 8N1 at any
//! baud rate (standard or not) with optional RTS/CTS flow control, exclusively (another
//! program opening the port then gets EBUSY instead of stealing bytes), non-blocking for the
//! event loop. Opening errors are classified so the transport can wait for a device that is
//! not there yet and tell the user what to do about one it may not open.

use std::fs::File;
use std::path::{Path, PathBuf};

/// How a serial device is opened.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TtyConfig {
    /// The device path (a symlink such as /dev/serial/by-id/... is fine).
    pub path: PathBuf,
    /// Bits per second.
    pub baudrate: u32,
    /// RTS/CTS hardware flow control.
    pub flow_control: bool,
}

/// Why a device could not be opened, as far as the user can act on it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum OpenError {
    /// No such device (yet): waited for.
    Absent,
    /// Another program holds it (exclusive lock, EBUSY).
    Busy,
    /// No permission (usually: not in the `dialout` group).
    Denied,
    /// Anything else, with the system's words.
    Other(String),
}

impl OpenError {
    /// What to tell the user about `path`.
    pub fn explain(&self, path: &Path) -> String {
        let p = path.display();
        match self {
            OpenError::Absent => format!("{p}: no such device; waiting for it to appear"),
            OpenError::Busy => format!(
                "{p}: device busy: another program holds it open (a second agent, ModemManager, \
                 a serial console or screen/minicom?); retrying"
            ),
            OpenError::Denied => format!(
                "{p}: permission denied: add the agent's user to the group owning the device \
                 (usually `dialout`: sudo usermod -aG dialout $USER, then log in again); retrying"
            ),
            OpenError::Other(e) => format!("{p}: cannot open: {e}; retrying"),
        }
    }
}

/// The standard rates of termios (B0 … B4000000); others are set as custom rates.
pub const STANDARD_RATES: &[u32] = &[
    0, 50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400, 57600,
    115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2000000, 2500000,
    3000000, 3500000, 4000000,
];

/// Opens and configures a device; the file is non-blocking.
pub fn open(config: &TtyConfig) -> Result<File, OpenError> {
    if !config.path.exists() {
        return Err(OpenError::Absent);
    }
    let flow = if config.flow_control {
        serialport::FlowControl::Hardware
    } else {
        serialport::FlowControl::None
    };
    let port = serialport::new(config.path.to_string_lossy(), config.baudrate)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(flow)
        .open_native()
        .map_err(|e| classify(&e))?;
    let file = crate::sys::owned_fd::from_serial_port(port);
    set_nonblocking(&file).map_err(|e| OpenError::Other(e.to_string()))?;
    Ok(file)
}

fn classify(e: &serialport::Error) -> OpenError {
    match e.kind() {
        serialport::ErrorKind::NoDevice => OpenError::Busy,
        serialport::ErrorKind::Io(std::io::ErrorKind::NotFound) => OpenError::Absent,
        serialport::ErrorKind::Io(std::io::ErrorKind::PermissionDenied) => OpenError::Denied,
        _ => {
            let d = e.to_string();
            // ENXIO, ENODEV: the node is there but its device is not (yet).
            if d.contains("No such device") || d.contains("No such file") {
                OpenError::Absent
            } else {
                OpenError::Other(d)
            }
        }
    }
}

/// Makes a descriptor non-blocking.
pub fn set_nonblocking(file: &File) -> std::io::Result<()> {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    let flags = fcntl(file, FcntlArg::F_GETFL)?;
    let flags = OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK;
    fcntl(file, FcntlArg::F_SETFL(flags))?;
    Ok(())
}

/// Whether a rate is one of termios' standard ones.
pub fn is_standard_rate(rate: u32) -> bool {
    STANDARD_RATES.contains(&rate)
}
