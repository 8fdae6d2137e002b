//! The release gate: how many held samples draining writers may have written into a topic
//! that this worker's own readers of it (those with a read) have not taken yet.
//!
//! After a worker restart a hundred writers drain what they held at once. Such a reader,
//! whose client cannot keep up, has its read paused and keeps the last so many samples of
//! the topic: written faster than its client takes them, the writers' backlogs overwrote
//! each other there. So the samples released into a topic and not yet taken by its readers
//! are at most half the smallest history those readers keep (and at most a pump); the rest
//! stays held, safe with its front-end. Readers without a read, paced reads and the readers
//! of a front-end whose process is gone do not count (as for acknowledgements): a topic
//! with none is not gated. The gate is the topic's, not a writer's: writers that each waited
//! only for their own last batch still put a batch each into a paused reader, a hundred of
//! them more than its history.
//!
//! A reader that takes nothing for [`RELEASE_GATE_MAX`] while samples wait for it (its
//! client stopped reading) does not hold the topic's writers for ever: the gate opens until
//! that reader takes again (counted as `release_gate_expired`). A reader that takes, however
//! slowly, keeps the gate: the release follows its pace, each drain for at most
//! [`super::writes::RELEASE_GATE_DRAIN_MAX`] in all.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use super::reads::PUMP_BATCH;
use super::TopicKey;

/// Longest this worker's readers of a topic may take nothing while released samples wait
/// for them before the gate opens.
pub(super) const RELEASE_GATE_MAX: Duration = Duration::from_secs(1);

/// Most released samples waiting for this worker's readers of a topic, whatever their
/// history: what one pump takes ([`PUMP_BATCH`]). A reader is seen drained (and the writes
/// it holds acknowledged, [`crate::acks`]) only once emptied; released samples in the
/// thousands kept a deep reader (5,000) behind its congested client for seconds, so that
/// writes it had delivered were still unacknowledged at a crash and resent: 13,845
/// repeated in a crash-loop soak, against 8.
pub(super) const RELEASE_IN_FLIGHT_MAX: u32 = PUMP_BATCH as u32;

/// Most stamps of released samples a gate keeps (far above the allowance).
const RELEASED_KEPT_MAX: usize = 4096;

/// What this worker's readers of a topic (those with an unpaced read) stand at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Drained {
    /// The write stamp up to which every one of them was drained ([`crate::acks`]).
    pub(super) through: u64,
    /// The fewest samples of an instance one of them keeps (its history depth).
    pub(super) depth: u32,
    /// Samples they took so far, in all: a reader that takes without being emptied (more
    /// came meanwhile) is taking, though not yet drained further.
    pub(super) taken: u64,
}

/// What the gate lets a draining writer do now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Admission {
    /// Write at most this many held samples.
    Release(usize),
    /// Write none: the readers have not taken enough of what was released.
    Wait,
}

/// One topic's gate.
#[derive(Debug, Default)]
struct TopicGate {
    /// Write stamps of the samples released into the topic that its readers may not have
    /// taken yet, oldest first.
    released: VecDeque<u64>,
    /// Where the readers stood when last looked at.
    drained: u64,
    /// What they had taken then.
    taken: u64,
    /// When a writer last asked (a gate no writer asks for a while is forgotten).
    asked: Option<Instant>,
    /// Since when they have taken nothing while samples waited for them.
    stalled_since: Option<Instant>,
    /// They took nothing for [`RELEASE_GATE_MAX`]: open until they take again.
    open: bool,
}

/// The gates of the topics draining writers write to.
#[derive(Debug, Default)]
pub(super) struct ReleaseGates {
    gates: HashMap<TopicKey, TopicGate>,
    /// Times a gate opened for readers that took nothing, not yet reported.
    expired: u64,
}

impl ReleaseGates {
    /// How many of `want` held samples a draining writer of `topic` may write now, its
    /// readers standing at `drained` (None: the topic has no reader that counts).
    pub(super) fn admit(
        &mut self,
        topic: &TopicKey,
        drained: Option<Drained>,
        want: usize,
        now: Instant,
    ) -> Admission {
        let Some(d) = drained else {
            return Admission::Release(want);
        };
        let gate = match self.gates.get_mut(topic) {
            Some(g) => g,
            None => self.gates.entry(*topic).or_default(),
        };
        gate.asked = Some(now);
        while gate.released.front().is_some_and(|s| *s <= d.through) {
            gate.released.pop_front();
        }
        if d.through > gate.drained || d.taken != gate.taken {
            // They took some: the wait starts again, and an opened gate closes.
            gate.drained = gate.drained.max(d.through);
            gate.taken = d.taken;
            gate.stalled_since = None;
            gate.open = false;
        }
        if gate.open || want == 0 {
            return Admission::Release(want);
        }
        let allowance = (d.depth / 2).clamp(1, RELEASE_IN_FLIGHT_MAX) as usize;
        let room = allowance.saturating_sub(gate.released.len());
        if room > 0 {
            gate.stalled_since = None;
            return Admission::Release(want.min(room));
        }
        let since = *gate.stalled_since.get_or_insert(now);
        if now.saturating_duration_since(since) >= RELEASE_GATE_MAX {
            gate.open = true;
            gate.stalled_since = None;
            self.expired += 1;
            return Admission::Release(want);
        }
        Admission::Wait
    }

    /// A held sample of `topic` was written with write stamp `stamp`.
    pub(super) fn released(&mut self, topic: &TopicKey, stamp: u64) {
        if let Some(g) = self.gates.get_mut(topic) {
            // Only an open gate lets more than the allowance (at most 256) wait; it forgets
            // the oldest rather than grow with what its stalled readers never take.
            if g.released.len() >= RELEASED_KEPT_MAX {
                g.released.pop_front();
            }
            g.released.push_back(stamp);
        }
    }

    /// When a gate that waits opens at the latest (None: none waits).
    pub(super) fn next_expiry(&self, topic: &TopicKey) -> Option<Instant> {
        self.gates
            .get(topic)
            .and_then(|g| g.stalled_since)
            .map(|t| t + RELEASE_GATE_MAX)
    }

    /// Forgets the gates of topics no writer drains into any more, once no writer asked
    /// for [`RELEASE_GATE_MAX`] (what was released into them may still wait for their
    /// readers when a drain of that topic starts again).
    pub(super) fn keep_only(
        &mut self,
        draining: &std::collections::HashSet<TopicKey>,
        now: Instant,
    ) {
        self.gates.retain(|t, g| {
            draining.contains(t)
                || g.asked
                    .is_some_and(|a| now.saturating_duration_since(a) < RELEASE_GATE_MAX)
        });
    }

    /// Times a gate opened for readers that took nothing since the last call.
    pub(super) fn take_expired(&mut self) -> u64 {
        std::mem::take(&mut self.expired)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn topic() -> TopicKey {
        TopicKey(1)
    }

    fn at(through: u64, depth: u32) -> Option<Drained> {
        Some(Drained {
            through,
            depth,
            taken: through,
        })
    }

    /// Released samples the readers have not taken are at most half their history, over
    /// every writer of the topic, and at most what a pump takes.
    #[test]
    fn the_topics_readers_have_at_most_half_their_history_waiting() {
        let mut g = ReleaseGates::default();
        let now = Instant::now();
        assert_eq!(
            g.admit(&topic(), at(0, 40), 16, now),
            Admission::Release(16)
        );
        (1..=16).for_each(|s| g.released(&topic(), s));
        // Another writer of the topic: four more fit.
        assert_eq!(g.admit(&topic(), at(0, 40), 16, now), Admission::Release(4));
        (17..=20).for_each(|s| g.released(&topic(), s));
        assert_eq!(g.admit(&topic(), at(0, 40), 16, now), Admission::Wait);
        // The readers took the first ten.
        assert_eq!(
            g.admit(&topic(), at(10, 40), 16, now),
            Admission::Release(10)
        );
        // A topic without readers that count is not gated.
        assert_eq!(g.admit(&topic(), None, 16, now), Admission::Release(16));
        let deep = TopicKey(2);
        assert_eq!(
            g.admit(&deep, at(0, 5000), 1000, now),
            Admission::Release(256)
        );
    }

    /// Readers that take nothing hold the topic only so long; once they take again, the
    /// gate closes again.
    #[test]
    fn readers_that_take_nothing_hold_the_release_only_so_long() {
        let mut g = ReleaseGates::default();
        let now = Instant::now();
        assert_eq!(g.admit(&topic(), at(0, 2), 16, now), Admission::Release(1));
        g.released(&topic(), 1);
        assert_eq!(g.admit(&topic(), at(0, 2), 16, now), Admission::Wait);
        let almost = now + RELEASE_GATE_MAX - Duration::from_millis(1);
        assert_eq!(g.next_expiry(&topic()), Some(now + RELEASE_GATE_MAX));
        assert_eq!(g.admit(&topic(), at(0, 2), 16, almost), Admission::Wait);
        let later = now + RELEASE_GATE_MAX;
        assert_eq!(
            g.admit(&topic(), at(0, 2), 16, later),
            Admission::Release(16)
        );
        assert_eq!(g.take_expired(), 1);
        (2..=17).for_each(|s| g.released(&topic(), s));
        assert_eq!(
            g.admit(&topic(), at(0, 2), 16, later),
            Admission::Release(16)
        );
        (18..=33).for_each(|s| g.released(&topic(), s));
        // They took one: closed again, and what was released while open waits for them.
        assert_eq!(g.admit(&topic(), at(1, 2), 16, later), Admission::Wait);
        assert_eq!(
            g.admit(&topic(), at(33, 2), 16, later),
            Admission::Release(1)
        );
        assert_eq!(g.take_expired(), 0);
    }

    /// Readers that take without being emptied (more came meanwhile) are taking: the gate
    /// does not open for them.
    #[test]
    fn readers_that_take_without_emptying_keep_the_gate() {
        let mut g = ReleaseGates::default();
        let mut now = Instant::now();
        let busy = |taken| {
            Some(Drained {
                through: 0,
                depth: 2,
                taken,
            })
        };
        assert_eq!(g.admit(&topic(), busy(0), 16, now), Admission::Release(1));
        g.released(&topic(), 1);
        for taken in 1..5 {
            now += RELEASE_GATE_MAX;
            assert_eq!(g.admit(&topic(), busy(taken), 16, now), Admission::Wait);
        }
        assert_eq!(g.take_expired(), 0);
    }

    /// A reader that takes slowly keeps the gate: each take restarts the wait.
    #[test]
    fn a_slow_reader_keeps_the_gate() {
        let mut g = ReleaseGates::default();
        let mut now = Instant::now();
        assert_eq!(g.admit(&topic(), at(0, 2), 16, now), Admission::Release(1));
        g.released(&topic(), 1);
        for s in 1..=5u64 {
            // Waiting from the first refusal, for almost the whole bound.
            assert_eq!(g.admit(&topic(), at(s - 1, 2), 16, now), Admission::Wait);
            now += RELEASE_GATE_MAX - Duration::from_millis(1);
            assert_eq!(g.admit(&topic(), at(s - 1, 2), 16, now), Admission::Wait);
            // It takes the one released: the next goes.
            assert_eq!(g.admit(&topic(), at(s, 2), 16, now), Admission::Release(1));
            g.released(&topic(), s + 1);
        }
        assert_eq!(g.take_expired(), 0);
    }
}
