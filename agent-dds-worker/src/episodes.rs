//! Refusals logged once per episode.
//!
//! What a client can cause at will (a CREATE in a domain beyond the cap, a filter over its
//! budget) must not become a flood of log lines: each refusal is counted, but only the first
//! of an episode is logged. An episode of a reason ends when the worker says so (the
//! situation changed: a domain was released) or after [`QUIET`] without a refusal of that
//! reason; the next refusal then opens a new episode, logged again.

use std::collections::HashMap;
use std::time::{Duration, Instant};

/// An episode of refusals ends after this long without one.
pub const QUIET: Duration = Duration::from_secs(60);

#[derive(Debug, Clone, Copy)]
struct Episode {
    last: Instant,
    count: u64,
}

/// Open episodes by reason.
#[derive(Debug, Default)]
pub struct Episodes {
    open: HashMap<&'static str, Episode>,
}

impl Episodes {
    /// Counts a refusal for `reason` at `now`; true if it opens an episode (log it then).
    pub fn refused(&mut self, reason: &'static str, now: Instant) -> bool {
        match self.open.get_mut(reason) {
            Some(e) if now.saturating_duration_since(e.last) < QUIET => {
                e.last = now;
                e.count += 1;
                false
            }
            _ => {
                self.open.insert(
                    reason,
                    Episode {
                        last: now,
                        count: 1,
                    },
                );
                true
            }
        }
    }

    /// Ends the open episode of `reason`, if any; how many refusals it had.
    pub fn end(&mut self, reason: &'static str) -> Option<u64> {
        self.open.remove(reason).map(|e| e.count)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_log_per_episode_and_a_new_one_after_it_ended_or_went_quiet() {
        let mut e = Episodes::default();
        let t0 = Instant::now();
        assert!(e.refused("a", t0));
        assert!(!e.refused("a", t0 + Duration::from_secs(1)));
        assert!(e.refused("b", t0), "reasons have episodes of their own");
        assert_eq!(e.end("a"), Some(2));
        assert_eq!(e.end("a"), None);
        assert!(e.refused("a", t0 + Duration::from_secs(2)));
        assert!(!e.refused("b", t0 + QUIET - Duration::from_millis(1)));
        assert!(
            e.refused("b", t0 + QUIET * 2),
            "quiet for a while: a new episode"
        );
    }
}
