//! What stopped agents of this user left behind: their session stores, kept for a restart
//! to take the sessions over, are removed once no restart can (past the adoption window),
//! with the rest of their instance's files. Done by every supervisor as it starts and then
//! every minute, and by a short-lived sweeper a stopping supervisor leaves behind
//! (`xrce-agent sweep`), so that a gateway whose agent is stopped for good does not keep
//! the stores in memory (they live in tmpfs).

use std::time::Duration;

use xrce_frontend::session_store::{self, StoredSessions, TAKE_OVER_WITHIN};
use xrce_ipc::{runtime_dir, status};

/// How often a running supervisor sweeps.
pub const SWEEP_PERIOD: Duration = Duration::from_secs(60);

/// A stopped instance's stores, and whether they were removed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Left {
    /// The instance.
    pub instance: String,
    /// What its stores hold.
    pub stored: StoredSessions,
}

/// The instances of this user that no process runs and that left session stores, with
/// what those hold (`except`: the caller's own instance, never listed).
pub fn stopped_instances(except: Option<&str>) -> Vec<Left> {
    status::instance_dirs()
        .into_iter()
        .filter(|(name, _)| !name.is_empty() && Some(name.as_str()) != except)
        .filter(|(_, dir)| !status::read_reports(dir).iter().any(status::report_is_live))
        // (Its lock is not probed here: taking it, even briefly, could make an agent of that
        // instance starting just then fail; the removal takes it, and only past the window.)
        .map(|(instance, _)| {
            let stored = session_store::inspect(&instance);
            Left { instance, stored }
        })
        .filter(|l| l.stored.clients > 0 || l.stored.bytes > 0)
        .collect()
}

/// Removes what stopped instances left once their sessions can no longer be taken over;
/// returns what was removed. Stores a front-end still holds are kept
/// ([`runtime_dir::remove_instance_if_unlocked`] takes every lock first).
pub fn sweep(except: Option<&str>) -> Vec<Left> {
    let now = status::unix_ms();
    let mut removed = Vec::new();
    for left in stopped_instances(except) {
        if !left.stored.expired(now) {
            continue;
        }
        // (Its shared memory went with its last process: a clean-up by prefix here could
        // touch another instance whose name begins with this one's.)
        if runtime_dir::remove_instance_if_unlocked(&left.instance) {
            tracing::info!(instance = %left.instance, clients = left.stored.clients, bytes = left.stored.bytes, "removed the session store of a stopped agent: past the adoption window, no restart can take its sessions over");
            removed.push(left);
        }
    }
    removed
}

/// Arguments of `xrce-agent sweep` (internal: what a stopping supervisor leaves behind).
#[derive(Debug, Clone, clap::Args)]
pub struct SweepArgs {
    /// The instance whose store to remove once the adoption window is over (unless an agent
    /// of the instance runs again by then).
    #[arg(long)]
    pub instance: String,
}

/// `xrce-agent sweep`: waits out the adoption window of `instance`'s store, then removes
/// it unless an agent of the instance took it back meanwhile.
pub fn run(args: &SweepArgs) -> anyhow::Result<()> {
    if !xrce_ipc::shm::valid_instance(&args.instance) {
        anyhow::bail!(
            "instance name {:?} is not [A-Za-z0-9_-]{{1,32}}",
            args.instance
        );
    }
    std::thread::sleep(TAKE_OVER_WITHIN + Duration::from_secs(2));
    let removed = sweep(None);
    tracing::debug!(removed = removed.len(), "sweep done");
    Ok(())
}

/// Leaves a sweeper behind for `instance` (detached: its own session, no terminal, no
/// inherited output), so that its store goes once the adoption window is over even when
/// no agent runs then. Under systemd it is stopped with the unit; the next agent sweeps.
pub fn leave_sweeper(instance: &str) {
    use std::process::{Command, Stdio};
    let Ok(exe) = std::env::current_exe() else {
        return;
    };
    let mut cmd = Command::new(exe);
    cmd.args(["sweep", "--instance", instance])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    crate::sys::detach(&mut cmd);
    match cmd.spawn() {
        Ok(child) => {
            tracing::debug!(pid = child.id(), "sweeper left for the session store");
        }
        Err(e) => tracing::debug!(error = %e, "no sweeper left: the next agent sweeps"),
    }
}
