//! Every `unsafe` of the crate, each call with its safety argument: the system calls std
//! does not offer at the workspace's minimum Rust version, and the descriptor iceoryx2's
//! listener lends out.

use std::os::fd::{AsRawFd, BorrowedFd};

/// This process's effective user id.
pub fn euid() -> u32 {
    // SAFETY: geteuid takes no argument, touches no memory and cannot fail.
    unsafe { libc::geteuid() }
}

/// Takes an exclusive `flock` on `file` without waiting; `Ok(false)` if another open file
/// description holds it.
pub(crate) fn try_flock(file: &std::fs::File) -> std::io::Result<bool> {
    loop {
        // SAFETY: the descriptor is open (borrowed from `file` for the call); flock only
        // changes the lock state of its open file description.
        let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if rc == 0 {
            return Ok(true);
        }
        let e = std::io::Error::last_os_error();
        match e.raw_os_error() {
            Some(libc::EWOULDBLOCK) => return Ok(false),
            Some(libc::EINTR) => continue,
            _ => return Err(e),
        }
    }
}

/// The file-system type of the file system `file` lives on (`statfs`'s `f_type`).
pub(crate) fn fs_type(file: &std::fs::File) -> Option<u64> {
    let mut st = std::mem::MaybeUninit::<libc::statfs>::uninit();
    // SAFETY: the descriptor is open for the call and `st` is a writable statfs the
    // kernel fills in completely when the call succeeds (checked before it is read).
    let rc = unsafe { libc::fstatfs(file.as_raw_fd(), st.as_mut_ptr()) };
    if rc != 0 {
        return None;
    }
    // SAFETY: fstatfs succeeded, so `st` is initialised.
    let st = unsafe { st.assume_init() };
    #[allow(clippy::unnecessary_cast)]
    Some(st.f_type as u64 & 0xFFFF_FFFF)
}

/// The descriptor of an iceoryx2 event listener, borrowed for as long as the listener.
pub(crate) fn listener_fd(
    listener: &iceoryx2::port::listener::Listener<iceoryx2::service::ipc::Service>,
) -> BorrowedFd<'_> {
    use iceoryx2::prelude::*;
    // SAFETY: the descriptor is open and owned by the listener, and the borrow returned cannot
    // outlive the listener (iceoryx2 closes the descriptor only when the listener is dropped).
    unsafe { BorrowedFd::borrow_raw(listener.file_descriptor().native_handle()) }
}
