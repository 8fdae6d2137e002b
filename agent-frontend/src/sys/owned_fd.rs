//! Taking ownership of file descriptors that arrive as bare numbers.
//!
//! Invariant for both functions: the number names an open descriptor that nothing else in
//! this process owns or will close, so wrapping it in a [`File`] (which closes it on drop)
//! cannot close a descriptor twice or one that another owner still uses.

#![allow(unsafe_code)]

use std::fs::File;
use std::os::fd::{BorrowedFd, FromRawFd, IntoRawFd, RawFd};

/// The descriptor of an opened serial port, owned as a [`File`].
pub(crate) fn from_serial_port(port: serialport::TTYPort) -> File {
    // SAFETY: `into_raw_fd` releases the port's ownership of its open descriptor without
    // closing it (invariant above).
    unsafe { File::from_raw_fd(port.into_raw_fd()) }
}

/// Descriptors already taken by [`inherited`], so none is owned twice.
static TAKEN: std::sync::Mutex<Vec<RawFd>> = std::sync::Mutex::new(Vec::new());

/// A descriptor the parent process left open for us (`--pty-fd`, `XRCE_READY_FD`), owned as
/// a [`File`]. Fails if `fd` is not open, is one of the standard streams, or was taken
/// already.
pub(crate) fn inherited(fd: RawFd) -> std::io::Result<File> {
    if fd <= 2 {
        return Err(std::io::Error::other(format!(
            "descriptor {fd} is a standard stream, not an inherited one"
        )));
    }
    let mut taken = TAKEN
        .lock()
        .map_err(|_| std::io::Error::other("descriptor registry poisoned"))?;
    if taken.contains(&fd) {
        return Err(std::io::Error::other(format!(
            "descriptor {fd} is inherited for two uses"
        )));
    }
    // SAFETY: only borrowed for the duration of the check; F_GETFD fails with EBADF on a
    // descriptor that is not open, without side effects.
    let borrowed = unsafe { BorrowedFd::borrow_raw(fd) };
    nix::fcntl::fcntl(borrowed, nix::fcntl::FcntlArg::F_GETFD)
        .map_err(|e| std::io::Error::other(format!("descriptor {fd} is not open: {e}")))?;
    taken.push(fd);
    // SAFETY: open (checked above), handed to this process by its parent for this use only,
    // and taken once (the registry above refuses a second take).
    Ok(unsafe { File::from_raw_fd(fd) })
}
