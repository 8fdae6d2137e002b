//! Reliable writes kept for a resend: a worker that dies after taking a write may not have
//! published it, so the relay keeps every write that came on a reliable stream until the
//! worker executed it and every matched reliable DDS reader of its writer acknowledged it,
//! or [`SETTLE_TIME`] passed since its execution (a reader that never acknowledges does not
//! keep it for ever) and the worker was heard from after that (a worker that died within the
//! settle time, before its readers took the write, must not take it with it: the front-end
//! learns of the death only when the next worker announces itself, seconds later under a
//! supervisor's back-off). Only writes still kept at a worker crash are sent to the new
//! worker.

use std::collections::VecDeque;
use std::time::Instant;

use xrce_ipc::{Encode, RequestMessage};

use super::queue::{ByteQueue, Weighed};
use super::{RelayStats, RETAIN_MAX, SETTLE_TIME};

/// One write kept.
#[derive(Debug)]
pub(super) struct Retained {
    /// Its operation number.
    pub(super) seq: u64,
    /// When the worker reported it executed.
    executed_at: Option<Instant>,
    pub(super) message: RequestMessage<'static>,
}

impl Weighed for Retained {
    fn weight(&self) -> usize {
        self.message.encoded_len()
    }
}

/// The writes kept, in operation order.
#[derive(Debug)]
pub(super) struct Retention {
    queue: ByteQueue<Retained>,
    /// Bytes kept before new writes are refused.
    max_bytes: usize,
    /// Every write up to this operation was acknowledged by the readers of its DDS writer
    /// (reported by the worker; only rises).
    acknowledged: u64,
    /// When the worker last reported progress: it was alive then.
    heard_at: Option<Instant>,
}

impl Retention {
    pub(super) fn new(max_bytes: usize) -> Self {
        Retention {
            queue: ByteQueue::default(),
            max_bytes,
            acknowledged: 0,
            heard_at: None,
        }
    }

    pub(super) fn set_max_bytes(&mut self, max_bytes: usize) {
        self.max_bytes = max_bytes;
    }

    /// Whether there is room for more (flow control).
    pub(super) fn has_room(&self) -> bool {
        self.queue.len() < RETAIN_MAX && self.queue.bytes < self.max_bytes
    }

    pub(super) fn len(&self) -> usize {
        self.queue.len()
    }

    /// Keeps write `seq`, just sent.
    pub(super) fn keep(&mut self, seq: u64, message: RequestMessage<'static>) {
        self.queue.push_back(Retained {
            seq,
            executed_at: None,
            message,
        });
    }

    /// The worker executed every operation up to `executed`, and the DDS readers
    /// acknowledged every write up to `acknowledged`.
    pub(super) fn progress(&mut self, now: Instant, executed: u64, acknowledged: u64) {
        self.heard_at = Some(now);
        self.acknowledged = self.acknowledged.max(acknowledged.min(executed));
        for r in self.queue.iter_mut() {
            if r.seq > executed {
                break;
            }
            r.executed_at.get_or_insert(now);
        }
    }

    /// Releases the writes that were acknowledged, or executed [`SETTLE_TIME`] ago by a
    /// worker heard from since.
    pub(super) fn settle(&mut self, now: Instant, stats: &mut RelayStats) {
        while let Some(r) = self.queue.front() {
            let acknowledged = r.seq <= self.acknowledged && r.executed_at.is_some();
            match r.executed_at {
                _ if acknowledged => {
                    self.queue.pop_front();
                    stats.writes_acknowledged += 1;
                }
                Some(t)
                    if now.saturating_duration_since(t) >= SETTLE_TIME
                        && self.heard_at.is_some_and(|h| h >= t + SETTLE_TIME) =>
                {
                    self.queue.pop_front();
                    stats.writes_settled_unacknowledged += 1;
                }
                _ => break,
            }
        }
    }

    /// When the oldest executed write is released at the latest, if the worker is heard
    /// from by then (otherwise the next progress releases it: no timer waits for that).
    pub(super) fn deadline(&self) -> Option<Instant> {
        let settled = self
            .queue
            .front()
            .and_then(|r| r.executed_at)
            .map(|t| t + SETTLE_TIME)?;
        self.heard_at
            .is_some_and(|h| h >= settled)
            .then_some(settled)
    }

    /// Every write kept, oldest first, for a new worker (which executed none of them).
    pub(super) fn take(&mut self) -> VecDeque<Retained> {
        self.heard_at = None;
        self.queue.take()
    }
}
