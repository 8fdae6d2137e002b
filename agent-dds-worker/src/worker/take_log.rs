//! Which of this worker's own writes a read has taken, for readers that take in write order.
//!
//! A write stays unacknowledged until the worker's own readers of its topic were drained
//! past it ([`crate::acks`]). Seen only when a read empties its reader, that point never
//! moves while the read's path stays congested (each pump takes a batch and more has come):
//! writes already delivered then stayed unacknowledged for seconds, and a crash had the
//! front-end resend them, repeated at their subscribers (thousands in a crash-loop soak).
//!
//! A volatile reader of a topic without a key keeps its samples in the order they came, and
//! this worker's writes reach it inside the write call, in the order written. So from a
//! point where it held none (its creation, or a read that emptied it), the n-th sample it
//! takes from one of the worker's writers of the topic is the n-th of their writes since.
//! (After a worker restart the replayed reader is new: from its creation it has a position,
//! where a lagging subscriber's reader would never be seen empty. A durable reader may get
//! older samples after that point: it has none.) The log keeps, per topic, the
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

/// Most topics with a log, and most writers one log names. Logs go only when full, so a
/// client that makes readers (or writers) under ever new names or ever new writers would
/// grow them without end: past these, the logs (or that log) end, counted
/// (`take_logs_ended`): reads are then seen drained only when emptied, until they are again.
pub(super) const TAKE_LOGS_MAX: usize = 4096;

/// A place in a topic's log: the log (logs of one topic that end and begin again are told
/// apart) and how many of its writes were taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct LogPosition {
    /// Which log of the topic.
    pub(super) epoch: u64,
    /// Its writes taken.
    pub(super) at: u64,
}

/// One topic's log.
#[derive(Debug, Default)]
struct TopicLog {
    /// Which log of the topic this is.
    epoch: u64,
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
    /// Logs begun so far.
    epochs: u64,
    /// Logs ended at a bound ([`TAKE_LOGS_MAX`]) since last told.
    ended: u64,
}

impl TakeLogs {
    /// A read of `topic` was seen empty: its position, from which it counts what it takes
    /// (the log begins if it had not).
    pub(super) fn sync(&mut self, topic: &TopicKey) -> LogPosition {
        if self.logs.len() >= TAKE_LOGS_MAX && !self.logs.contains_key(topic) {
            self.ended += self.logs.len() as u64;
            self.logs.clear();
        }
        let epochs = &mut self.epochs;
        let log = self.logs.entry(*topic).or_insert_with(|| {
            *epochs += 1;
            TopicLog {
                epoch: *epochs,
                first: 1,
                ..TopicLog::default()
            }
        });
        LogPosition {
            epoch: log.epoch,
            at: log.end(),
        }
    }

    /// This worker's writer `writer` wrote to `topic`, as the worker's `stamp`-th write.
    /// `positioned` tells, when the log is full, the oldest place a read of the topic still
    /// has in the log of the epoch it is given (None: no read has one), so that the log
    /// keeps what is still needed.
    pub(super) fn record(
        &mut self,
        topic: &TopicKey,
        writer: Guid,
        stamp: u64,
        positioned: impl FnOnce(u64) -> Option<u64>,
    ) {
        let Some(log) = self.logs.get_mut(topic) else {
            return;
        };
        if log.stamps.len() >= TAKE_LOG_MAX {
            let Some(oldest) = positioned(log.epoch) else {
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
        if log.writers.len() >= TAKE_LOGS_MAX && !log.writers.contains(&writer) {
            self.logs.remove(topic);
            self.ended += 1;
            return;
        }
        log.writers.insert(writer);
        log.stamps.push_back(stamp);
    }

    /// A write to `topic` failed: it may have reached some readers all the same (a backend
    /// delivers to them one by one), unlogged, and a reader that took it would be counted a
    /// place ahead. The log ends; positions in it mean nothing in the topic's next one.
    pub(super) fn write_failed(&mut self, topic: &TopicKey) {
        self.logs.remove(topic);
    }

    /// Logs ended at a bound since the last call.
    pub(super) fn take_ended(&mut self) -> u64 {
        std::mem::take(&mut self.ended)
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
        position: LogPosition,
        taken: u64,
    ) -> Option<(LogPosition, u64)> {
        let log = self.logs.get(topic).filter(|l| l.epoch == position.epoch)?;
        if position.at + 1 < log.first {
            return None;
        }
        // Never past the newest write (a sample the log could not tell came from before).
        let at = (position.at + taken).min(log.end());
        let to = LogPosition { at, ..position };
        if at < log.first {
            // Nothing taken since the log's start: the position stands.
            return Some((to, 0));
        }
        let stamp = log.stamps.get((at - log.first) as usize).copied()?;
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

    fn at(p: LogPosition) -> u64 {
        p.at
    }

    /// A read's position follows what it takes of the logged writes, in order.
    #[test]
    fn a_reads_position_gives_the_stamp_of_the_last_write_it_took() {
        let mut logs = TakeLogs::default();
        // Nothing is logged before a read syncs.
        logs.record(&topic(), W, 1, |_| None);
        assert!(!logs.is_logged_writer(&topic(), &W));
        let start = logs.sync(&topic());
        assert_eq!(at(start), 0);
        for stamp in [5, 7, 9] {
            logs.record(&topic(), W, stamp, |_| Some(at(start)));
        }
        assert!(logs.is_logged_writer(&topic(), &W));
        assert!(!logs.is_logged_writer(&topic(), &OTHER));
        let (two, stamp) = logs.advance(&topic(), start, 2).expect("in the log");
        assert_eq!((at(two), stamp), (2, 7));
        let (three, stamp) = logs.advance(&topic(), two, 5).expect("in the log");
        assert_eq!((at(three), stamp), (3, 9), "never past the end");
        // A read that syncs later starts at the end.
        assert_eq!(logs.sync(&topic()), three);
        // A failed write may have reached the reader unlogged: the log ends.
        logs.write_failed(&topic());
        assert_eq!(logs.advance(&topic(), three, 1), None);
        assert_ne!(logs.sync(&topic()), three, "another epoch");
    }

    /// Logs of ever new topics, or one log of ever new writers, end at their bounds
    /// (counted), not grow.
    #[test]
    fn logs_and_their_writers_are_bounded() {
        let mut logs = TakeLogs::default();
        for t in 0..TAKE_LOGS_MAX as u64 {
            logs.sync(&TopicKey(t));
        }
        assert_eq!(logs.take_ended(), 0);
        logs.sync(&TopicKey(u64::MAX));
        assert_eq!(logs.take_ended(), TAKE_LOGS_MAX as u64);
        assert_eq!(logs.logs.len(), 1);
        let start = logs.sync(&topic());
        for w in 0..TAKE_LOGS_MAX as u32 {
            let mut guid = [0; 16];
            guid[..4].copy_from_slice(&w.to_le_bytes());
            logs.record(&topic(), guid, u64::from(w) + 1, |_| Some(0));
        }
        assert_eq!(logs.take_ended(), 0);
        logs.record(&topic(), [0xff; 16], 1 << 20, |_| Some(0));
        assert_eq!(logs.take_ended(), 1);
        assert_eq!(logs.advance(&topic(), start, 1), None, "the log ended");
    }

    /// A full log keeps what the furthest-behind read needs; a read left behind its start
    /// loses its position; a log no read is positioned in goes, and a position in it means
    /// nothing in the topic's next log.
    #[test]
    fn a_full_log_keeps_what_reads_still_need() {
        let mut logs = TakeLogs::default();
        let start = logs.sync(&topic());
        let place = |at| LogPosition { at, ..start };
        for s in 1..=TAKE_LOG_MAX as u64 {
            logs.record(&topic(), W, s, |_| Some(0));
        }
        // The oldest read is at 10: the log drops a quarter, that read loses its place.
        logs.record(&topic(), W, 5000, |_| Some(10));
        assert_eq!(logs.advance(&topic(), place(10), 1), None);
        let quarter = (TAKE_LOG_MAX / 4) as u64;
        assert_eq!(
            logs.advance(&topic(), place(quarter), 1),
            Some((place(quarter + 1), quarter + 1))
        );
        // Full again, with no read positioned: the log goes.
        for s in 0..quarter - 1 {
            logs.record(&topic(), W, 6000 + s, |_| Some(quarter));
        }
        logs.record(&topic(), W, 9000, |_| None);
        assert!(!logs.is_logged_writer(&topic(), &W));
        assert_eq!(logs.advance(&topic(), place(quarter), 1), None);
        // The next log of the topic does not take the old position for one of its own.
        let next = logs.sync(&topic());
        logs.record(&topic(), W, 9001, |_| Some(at(next)));
        assert_eq!(logs.advance(&topic(), place(0), 1), None);
        assert_eq!(
            logs.advance(&topic(), next, 1).map(|(p, s)| (at(p), s)),
            Some((1, 9001))
        );
    }
}
