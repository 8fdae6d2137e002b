//! Readiness: each front-end reports that it serves (its transport is open and a DDS worker
//! answered it) by writing `READY` to a pipe the supervisor gave it at descriptor
//! [`READY_FD`] (`XRCE_READY_FD`). That works for every transport alike (a UDP ping cannot
//! test a serial line). Once every front-end has reported, the supervisor logs that the agent
//! is ready and tells systemd (`Type=notify`, through the `sd-notify` crate). A restarted
//! front-end reports again.

use std::io::BufRead;
use std::os::fd::{OwnedFd, RawFd};
use std::sync::mpsc;
use std::time::Duration;

/// The descriptor number at which a front-end finds its readiness pipe.
pub const READY_FD: RawFd = 4;

/// A readiness pipe: (read end for the supervisor, write end for the front-end), both
/// numbered above the descriptors children get ([`crate::high_fd`]) and close-on-exec.
pub fn pipe() -> std::io::Result<(OwnedFd, OwnedFd)> {
    let (r, w) = nix::unistd::pipe2(nix::fcntl::OFlag::O_CLOEXEC)?;
    Ok((crate::high_fd(&r)?, crate::high_fd(&w)?))
}

/// Watches the read ends of the front-ends' readiness pipes (named for logs) on threads of
/// its own; calls `on_ready` once all of them reported, and warns about those still silent
/// after `patience`.
pub fn watch(
    frontends: Vec<(String, OwnedFd)>,
    patience: Duration,
    on_ready: impl FnOnce() + Send + 'static,
) {
    let (tx, rx) = mpsc::channel::<String>();
    let names: Vec<String> = frontends.iter().map(|(n, _)| n.clone()).collect();
    for (name, fd) in frontends {
        let tx = tx.clone();
        std::thread::spawn(move || {
            let reader = std::io::BufReader::new(std::fs::File::from(fd));
            for line in reader.lines() {
                match line {
                    Ok(l) if l.trim() == "READY" => {
                        if tx.send(name.clone()).is_err() {
                            tracing::info!(frontend = %name, "front-end serving again");
                        }
                    }
                    Ok(_) => {}
                    Err(_) => return,
                }
            }
        });
    }
    drop(tx);
    std::thread::spawn(move || {
        let mut waiting = names;
        let mut warned = false;
        while !waiting.is_empty() {
            match rx.recv_timeout(patience) {
                Ok(name) => {
                    tracing::debug!(frontend = %name, "front-end serving");
                    waiting.retain(|n| *n != name);
                }
                Err(mpsc::RecvTimeoutError::Timeout) if !warned => {
                    tracing::warn!(?waiting, waited = ?patience, "front-ends not serving yet");
                    warned = true;
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => return,
            }
        }
        on_ready();
        // Later reports (restarted front-ends) are logged by the reader threads.
        drop(rx);
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_frontend_must_report_before_ready() {
        use std::io::Write;
        let (r1, w1) = pipe().expect("pipe");
        let (r2, w2) = pipe().expect("pipe");
        let (tx, rx) = mpsc::channel();
        watch(
            vec![("a".into(), r1), ("b".into(), r2)],
            Duration::from_secs(30),
            move || tx.send(()).expect("send"),
        );
        let mut w1 = std::fs::File::from(w1);
        w1.write_all(b"READY\n").expect("write");
        assert!(
            rx.recv_timeout(Duration::from_millis(300)).is_err(),
            "ready with one of two"
        );
        let mut w2 = std::fs::File::from(w2);
        w2.write_all(b"READY\n").expect("write");
        rx.recv_timeout(Duration::from_secs(5))
            .expect("ready once both reported");
    }
}
