//! Faults injected on purpose, to prove that the end-to-end tests catch them.
//!
//! Built only with the feature `fault-injection`, which the test harness turns on when it
//! builds the agent's binaries and which no release build enables. Each process of such a
//! build reads `XRCE_FAULT` once at start ([`install_from_env`]) and then misbehaves in the
//! one named way; `tests/fault-check.sh` runs every fault against the tests that must catch
//! it. Without the feature, [`hit`] is a constant `false` and the code paths vanish.
//!
//! A fault is a global of the process, not state of the sans-IO core: it stands for a bug in
//! the code, which would be global too.

use std::fmt;

/// One way the agent can be made to misbehave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// The worker writes every 10th sample to DDS twice.
    DdsDuplicate,
    /// The worker drops every 10th sample instead of writing it to DDS.
    DdsDrop,
    /// The front-end sends every 10th DATA to its client twice, as two messages.
    ClientDuplicate,
    /// The front-end drops every 10th DATA instead of sending it to its client.
    ClientDrop,
    /// A requester gets every reply twice.
    ReplyDuplicate,
    /// HEARTBEATs to a silent client keep the base period (no back-off).
    HeartbeatFixed,
    /// A restarted worker is not given one client's read in the replay.
    ReplaySkip,
    /// A front-end that took over ignores what the worker executed for its predecessor.
    ExecutedIgnored,
    /// A front-end delivers a resent write's sample that its read had delivered (ignores
    /// the write's origin).
    OriginIgnored,
}

impl Fault {
    /// Every fault, in the order `tests/fault-check.sh` runs them.
    pub const ALL: [Fault; 9] = [
        Fault::DdsDuplicate,
        Fault::DdsDrop,
        Fault::ClientDuplicate,
        Fault::ClientDrop,
        Fault::ReplyDuplicate,
        Fault::HeartbeatFixed,
        Fault::ReplaySkip,
        Fault::ExecutedIgnored,
        Fault::OriginIgnored,
    ];

    /// The name `XRCE_FAULT` takes.
    pub fn name(self) -> &'static str {
        match self {
            Fault::DdsDuplicate => "dds-duplicate",
            Fault::DdsDrop => "dds-drop",
            Fault::ClientDuplicate => "client-duplicate",
            Fault::ClientDrop => "client-drop",
            Fault::ReplyDuplicate => "reply-duplicate",
            Fault::HeartbeatFixed => "heartbeat-fixed",
            Fault::ReplaySkip => "replay-skip",
            Fault::ExecutedIgnored => "executed-ignored",
            Fault::OriginIgnored => "origin-ignored",
        }
    }

    /// The fault named `name`, if there is one.
    pub fn from_name(name: &str) -> Option<Fault> {
        Fault::ALL.into_iter().find(|f| f.name() == name)
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Why `XRCE_FAULT` could not be honoured.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum FaultError {
    /// The name is not one of [`Fault::ALL`].
    #[error("XRCE_FAULT={0}: no such fault (known: dds-duplicate, dds-drop, client-duplicate, client-drop, reply-duplicate, heartbeat-fixed, replay-skip, executed-ignored, origin-ignored)")]
    Unknown(String),
    /// The binary was built without the feature `fault-injection`.
    #[error(
        "XRCE_FAULT={0}: this build has no fault injection (feature `fault-injection`); ignored"
    )]
    NotBuiltIn(String),
}

#[cfg(feature = "fault-injection")]
mod active {
    use super::Fault;
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::OnceLock;

    static ACTIVE: OnceLock<Fault> = OnceLock::new();
    static CALLS: AtomicU64 = AtomicU64::new(0);

    pub(super) fn install(f: Fault) {
        let _ = ACTIVE.set(f);
    }

    pub(super) fn hit(f: Fault, every: u64) -> bool {
        if ACTIVE.get() != Some(&f) {
            return false;
        }
        // One fault per process, so one counter.
        let n = CALLS.fetch_add(1, Ordering::Relaxed) + 1;
        n % every.max(1) == 0
    }

    pub(super) fn once(f: Fault) -> bool {
        ACTIVE.get() == Some(&f) && CALLS.fetch_add(1, Ordering::Relaxed) == 0
    }
}

/// Reads `XRCE_FAULT` and turns its fault on for the rest of the process. `Ok(None)` when the
/// variable is unset or empty.
pub fn install_from_env() -> Result<Option<Fault>, FaultError> {
    let name = match std::env::var("XRCE_FAULT") {
        Ok(n) if !n.trim().is_empty() => n.trim().to_string(),
        _ => return Ok(None),
    };
    let fault = Fault::from_name(&name).ok_or_else(|| FaultError::Unknown(name.clone()))?;
    #[cfg(feature = "fault-injection")]
    {
        active::install(fault);
        Ok(Some(fault))
    }
    #[cfg(not(feature = "fault-injection"))]
    {
        let _ = fault;
        Err(FaultError::NotBuiltIn(name))
    }
}

/// Whether `fault` strikes now: true on every `every`-th call while it is the process's fault
/// (`every` = 1: always).
#[inline]
pub fn hit(fault: Fault, every: u64) -> bool {
    #[cfg(feature = "fault-injection")]
    {
        active::hit(fault, every)
    }
    #[cfg(not(feature = "fault-injection"))]
    {
        let _ = (fault, every);
        false
    }
}

/// Whether `fault` strikes now: true on the first call only, while it is the process's fault.
#[inline]
pub fn once(fault: Fault) -> bool {
    #[cfg(feature = "fault-injection")]
    {
        active::once(fault)
    }
    #[cfg(not(feature = "fault-injection"))]
    {
        let _ = fault;
        false
    }
}

/// Installs the fault named by `XRCE_FAULT` and logs it: a warning for an active fault (so a
/// log shows the process misbehaves on purpose), an error for a name not known or a build
/// without the feature. An unknown name is an error the caller returns; a build without
/// the feature runs normally.
pub fn install_and_log(process: &str) -> Result<(), FaultError> {
    match install_from_env() {
        Ok(Some(f)) => {
            tracing::warn!(process, fault = %f, "FAULT INJECTION active: this process misbehaves on purpose (XRCE_FAULT)");
            Ok(())
        }
        Ok(None) => Ok(()),
        Err(e @ FaultError::NotBuiltIn(_)) => {
            tracing::error!(process, "{e}");
            Ok(())
        }
        Err(e) => Err(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for f in Fault::ALL {
            assert_eq!(Fault::from_name(f.name()), Some(f));
        }
        assert_eq!(Fault::from_name("nothing"), None);
    }

    #[test]
    fn nothing_strikes_when_not_installed() {
        for f in Fault::ALL {
            assert!(!(0..30).any(|_| hit(f, 10)));
            assert!(!once(f));
        }
    }
}
