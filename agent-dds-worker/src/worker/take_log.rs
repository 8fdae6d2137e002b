//! Which of this worker's own writes a read has taken, for readers that take in write order.
//!
//! A write stays unacknowledged until the worker's own readers of its topic were drained
//! past it ([`crate::acks`]). Seen only when a read empties its reader, that point never
//! moves while the read's path stays congested (each pump takes a batch and more has come):
//! writes already delivered then stayed unacknowledged for seconds, and a crash had the
//! front-end resend them, repeated at their subscribers (thousands in a crash-loop soak).
//!
//! A reader of a topic without a key keeps its samples in the order they came, and this
//! worker's writes reach it inside the write call, in the order written. So once such a
//! read was seen empty (its sync point), the n-th sample it takes from one of the worker's
//! writers of the topic is the n-th of their writes since. The log keeps, per topic, the
//! write stamps of those writes in order, and which writers made them; a read keeps its
//! position in it. Samples it does not get (another partition, overwritten in its history)
//! or cannot tell (no identity) make the position lag, never lead: a write is at worst
//! acknowledged later. A keyed topic's reader takes instance by instance, not in write
//! order: it has no position.

use std::collections::{HashMap, HashSet, VecDeque};

use super::TopicKey;
use crate::backend::Guid;

/// Most write stamps a topic's log keeps. A read whose position falls behind its start (its
/// client stopped taking) loses its position until its reader is seen empty again; the log
/// of a topic with no read positioned in it is dropped as it reaches this.
pub(super) const TAKE_LOG_MAX: usize = 4096;

/// One topic's log.
#[derive(Debug, Default)]
struct TopicLog {
    /// Stamps of the writes since the log began, oldest first, from `first`.
    stamps: VecDeque<u64>,
    /// The position of `stamps[0]` (1 for the first write logged).
    first: u64,
    /// The writers that wrote to the topic since the log began.
    writers: HashSet<Guid>,
}

impl TopicLog {
    /// Writes logged so far: a position just past the newest.
    fn end(&self) -> u64 {
        self.first - 1 + self.stamps.len() as u64
    }
}

/// The logs of the topics some read has a position in.
#[derive(Debug, Default)]
pub(super) struct TakeLogs {
    logs: HashMap<TopicKey, TopicLog>,
}

impl TakeLogs {
    /// A read of `topic` was seen empty: its position, from which it counts what it takes
    /// (the log begins if it had not).
    pub(super) fn sync(&mut self, topic: &TopicKey) -> u64 {
        match self.logs.get(topic) {
            Some(log) => log.end(),
            None => {
                self.logs.insert(
                    *topic,
                    TopicLog {
                        first: 1,
                        ..TopicLog::default()
                    },
                );
                0
            }
        }
    }

    /// This worker's writer `writer` wrote to `topic`, as the worker's `stamp`-th write.
    /// `positioned` tells, when the log is full, the oldest position a read of the topic
    /// still has (None: no read has one), so that the log keeps what is still needed.
    pub(super) fn record(
        &mut self,
        topic: &TopicKey,
        writer: Guid,
        stamp: u64,
        positioned: impl FnOnce() -> Option<u64>,
    ) {
        let Some(log) = self.logs.get_mut(topic) else {
            return;
        };
        if log.stamps.len() >= TAKE_LOG_MAX {
            let Some(oldest) = positioned() else {
                self.logs.remove(topic);
                return;
            };
            // Drop what no read needs any more, and at least a quarter (a read that far
            // behind loses its position).
            let needed = oldest.saturating_sub(log.first - 1) as usize;
            let drop = needed.max(TAKE_LOG_MAX / 4).min(log.stamps.len());
            log.stamps.drain(..drop);
            log.first += drop as u64;
        }
        log.writers.insert(writer);
        log.stamps.push_back(stamp);
    }

    /// Whether `writer` is one of this worker's writers that wrote to `topic` since its log
    /// began.
    pub(super) fn is_logged_writer(&self, topic: &TopicKey, writer: &Guid) -> bool {
        self.logs
            .get(topic)
            .is_some_and(|l| l.writers.contains(writer))
    }

    /// A read at `position` took `taken` more of the logged writes: its new position and
    /// the stamp of the write there (None: the position is no longer in the log, or the
    /// log is gone; the read has no position then).
    pub(super) fn advance(
        &self,
        topic: &TopicKey,
        position: u64,
        taken: u64,
    ) -> Option<(u64, u64)> {
        let log = self.logs.get(topic)?;
        if position + 1 < log.first {
            return None;
        }
        // Never past the newest write (a sample the log could not tell came from before).
        let to = (position + taken).min(log.end());
        if to < log.first {
            // Nothing taken since the log's start: the position stands.
            return Some((to, 0));
        }
        let stamp = log.stamps.get((to - log.first) as usize).copied()?;
        Some((to, stamp))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn topic() -> TopicKey {
        TopicKey(1)
    }

    const W: Guid = [1; 16];
    const OTHER: Guid = [2; 16];

    /// A read's position follows what it takes of the logged writes, in order.
    #[test]
    fn a_reads_position_gives_the_stamp_of_the_last_write_it_took() {
        let mut logs = TakeLogs::default();
        // Nothing is logged before a read syncs.
        logs.record(&topic(), W, 1, || None);
        assert!(!logs.is_logged_writer(&topic(), &W));
        assert_eq!(logs.sync(&topic()), 0);
        for stamp in [5, 7, 9] {
            logs.record(&topic(), W, stamp, || Some(0));
        }
        assert!(logs.is_logged_writer(&topic(), &W));
        assert!(!logs.is_logged_writer(&topic(), &OTHER));
        assert_eq!(logs.advance(&topic(), 0, 2), Some((2, 7)));
        assert_eq!(
            logs.advance(&topic(), 2, 5),
            Some((3, 9)),
            "never past the end"
        );
        // A read that syncs later starts at the end.
        assert_eq!(logs.sync(&topic()), 3);
        assert_eq!(logs.advance(&topic(), 3, 0), Some((3, 9)));
    }

    /// A full log keeps what the furthest-behind read needs; a read left behind its start
    /// loses its position; a log no read is positioned in goes.
    #[test]
    fn a_full_log_keeps_what_reads_still_need() {
        let mut logs = TakeLogs::default();
        logs.sync(&topic());
        for s in 1..=TAKE_LOG_MAX as u64 {
            logs.record(&topic(), W, s, || Some(0));
        }
        // The oldest read is at 10: the log drops a quarter, that read loses its place.
        logs.record(&topic(), W, 5000, || Some(10));
        assert_eq!(logs.advance(&topic(), 10, 1), None);
        let quarter = (TAKE_LOG_MAX / 4) as u64;
        assert_eq!(
            logs.advance(&topic(), quarter, 1),
            Some((quarter + 1, quarter + 1))
        );
        // Full again, with no read positioned: the log goes.
        for s in 0..quarter - 1 {
            logs.record(&topic(), W, 6000 + s, || Some(quarter));
        }
        logs.record(&topic(), W, 9000, || None);
        assert!(!logs.is_logged_writer(&topic(), &W));
        assert_eq!(logs.advance(&topic(), quarter, 1), None);
    }
}
