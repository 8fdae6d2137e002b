//! The supervisor's system calls that need `unsafe`, in one place.
//!
//! Invariants: between fork and exec only async-signal-safe functions run (sigprocmask,
//! prctl, dup2) and nothing allocates; every descriptor handed to a child is kept open by the
//! supervisor for as long as it may start that child ([`crate::ChildSpec::fds`]) and is
//! numbered above every number a child receives ([`high_fd`]), so no dup2 overwrites a
//! source still to be copied; a descriptor made here is owned by exactly one `OwnedFd`.

use std::os::fd::{FromRawFd, OwnedFd, RawFd};
use std::os::unix::process::CommandExt;
use std::process::Command;
use std::time::Duration;

use nix::sys::signal::{SigSet, Signal};

/// Lowest descriptor number [`high_fd`] returns: above every number a child is given.
const HIGH_FD_BASE: RawFd = 10;

/// A duplicate of `fd` numbered at least 10 (close-on-exec), so that handing descriptors to
/// a child at low fixed numbers never overwrites one still to be handed over.
pub fn high_fd(fd: &impl std::os::fd::AsFd) -> std::io::Result<OwnedFd> {
    let raw = nix::fcntl::fcntl(fd, nix::fcntl::FcntlArg::F_DUPFD_CLOEXEC(HIGH_FD_BASE))?;
    // SAFETY: F_DUPFD_CLOEXEC returned a new descriptor that nothing else owns.
    Ok(unsafe { OwnedFd::from_raw_fd(raw) })
}

/// Sets a child up between fork and exec: signals unblocked, killed with the supervisor,
/// each `(from, to)` descriptor copied to `to` (without close-on-exec).
pub(crate) fn prepare_child(cmd: &mut Command, fds: Vec<(RawFd, RawFd)>) {
    // SAFETY: the closure only makes async-signal-safe calls and does not allocate (`fds`
    // is moved in before the fork); the sources stay open in the supervisor (invariants
    // above).
    unsafe {
        cmd.pre_exec(move || {
            let set = SigSet::all();
            let _ = set.thread_unblock();
            // Children die with the supervisor, even if it is SIGKILLed.
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
            for &(from, to) in &fds {
                // dup2 clears close-on-exec on the copy.
                if libc::dup2(from, to) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
            }
            Ok(())
        });
    }
}

/// Waits for a signal of `set` for at most `timeout`.
pub(crate) fn wait_signal(set: &SigSet, timeout: Duration) -> Option<Signal> {
    let ts = libc::timespec {
        tv_sec: timeout.as_secs() as libc::time_t,
        tv_nsec: timeout.subsec_nanos() as libc::c_long,
    };
    // SAFETY: `set` is a valid sigset and `ts` a valid timespec for the duration of the call.
    let rc = unsafe { libc::sigtimedwait(set.as_ref(), std::ptr::null_mut(), &ts) };
    if rc > 0 {
        Signal::try_from(rc).ok()
    } else {
        None
    }
}

/// Makes a child the leader of a session of its own (`setsid` between fork and exec): no
/// terminal, not in the supervisor's process group, so that it outlives the supervisor.
pub(crate) fn detach(cmd: &mut Command) {
    // SAFETY: the closure makes one async-signal-safe call and does not allocate.
    unsafe {
        cmd.pre_exec(|| {
            nix::unistd::setsid()
                .map(drop)
                .map_err(std::io::Error::from)
        });
    }
}
