//! Which front-end operations DDS readers have acknowledged.
//!
//! A front-end keeps each reliable write it handed over until this worker says every matched
//! reliable DDS reader acknowledged it, so that after a worker crash it resends only the
//! writes that may not have reached the readers (a fixed retention repeated more). Each DDS
//! writer keeps the operations written through it and not known to be acknowledged
//! ([`Outstanding`]); the [`AckTracker`] watches the writers that have some and tells, per
//! front-end, the newest operation up to which everything was acknowledged.
//!
//! DDS acknowledgements cover other processes' readers only: a reader in this worker (an
//! XRCE client's) counts as acknowledged at once (Cyclone DDS delivers to it inside the
//! write), yet its samples die with the worker until they were taken and handed to the
//! client's front-end. So each write also carries a stamp, the worker's count of recorded
//! writes, and is done only once the worker's own readers of its topic were drained past
//! that stamp (what the caller of [`AckTracker::poll`] says of each writer). That holds for
//! backends that deliver to the worker's own readers inside the write call (Cyclone DDS, the
//! RustDDS backend's in-process delivery); with Zenoh, or RustDDS without that delivery, a
//! reader may be drained before a sample reaches it, and the write counts as taken.
//!
//! An outstanding write also knows the client write it came from (its origin) and the
//! sequence number its DDS writer gave it: a sample one of the worker's readers takes from
//! one of its writers is looked up by writer GUID and number ([`AckTracker::origin_of`]), so
//! that the subscriber's front-end can tell a write resent after a crash from a new one.

use std::cell::RefCell;
use std::collections::{HashMap, HashSet, VecDeque};
use std::rc::{Rc, Weak};
use std::time::{Duration, Instant};

use xrce_ipc::SampleOrigin;

/// How often watched writers are asked whether their readers acknowledged everything.
pub const ACK_POLL_PERIOD: Duration = Duration::from_millis(2);

/// Writes older than this stop being waited for (a reader that never acknowledges must not
/// keep memory or the loop busy): the frontier reported moves past them, which front-ends
/// count as acknowledged, though they had released them already after their own settle
/// time (1.5 s after execution).
pub const ACK_GIVE_UP: Duration = Duration::from_secs(2);

/// A DDS writer whose acknowledgements can be asked for.
pub trait Acknowledging {
    /// How many of its writes, counted from its creation, every matched reliable reader
    /// acknowledged (all with none): the writes recorded with an ordinal up to it are done.
    fn acknowledged_writes(&self) -> u64;
    /// The operations written through it not known to be acknowledged.
    fn outstanding(&self) -> &Outstanding;
}

/// One sample of a front-end operation written through a DDS writer.
#[derive(Debug, Clone, Copy)]
pub struct Written {
    /// The front-end that handed it over.
    pub frontend: u32,
    /// The front-end's operation number.
    pub seq: u64,
    /// When it was written.
    pub at: Instant,
    /// The writer's write count after it.
    pub ordinal: u64,
    /// The worker's count of recorded writes after it (over every writer).
    pub stamp: u64,
    /// The sequence number the DDS writer gave it (0: the backend cannot tell): the
    /// worker's readers that take it tell it by that number ([`AckTracker::origin_of`]).
    pub sequence_number: i64,
    /// The client write it came from.
    pub origin: Option<SampleOrigin>,
}

/// Operations written through one DDS writer and not known to be acknowledged, in the order
/// they were written (one front-end's in increasing order unless the writer is shared), each
/// with its ordinal among the writer's writes.
#[derive(Debug, Default)]
pub struct Outstanding {
    writes: RefCell<VecDeque<Written>>,
    /// The writes are not one front-end's in increasing order (a shared DDS writer: several
    /// front-ends, or several XRCE writers whose held samples are released in turns).
    mixed: std::cell::Cell<bool>,
}

impl Outstanding {
    /// Records a write (the writer's `ordinal`-th, the worker's `stamp`-th recorded one);
    /// true if nothing was outstanding before (the writer must be watched from now on).
    pub fn record(&self, written: Written) -> bool {
        let mut w = self.writes.borrow_mut();
        let first = w.is_empty();
        if w.back()
            .is_some_and(|b| b.frontend != written.frontend || b.seq > written.seq)
        {
            self.mixed.set(true);
        }
        w.push_back(written);
        first
    }

    /// The origin of the outstanding write the writer numbered `sequence_number`, if it had
    /// one. The writer numbers its writes in the order they are recorded (a backend that
    /// cannot tell numbers none), so the search halves the queue.
    pub fn origin_of(&self, sequence_number: i64) -> Option<SampleOrigin> {
        if sequence_number <= 0 {
            // Not a number a writer gives (0 stands for "cannot tell").
            return None;
        }
        let w = self.writes.borrow();
        let at = w.partition_point(|x| x.sequence_number < sequence_number);
        w.get(at)
            .filter(|x| x.sequence_number == sequence_number)
            .and_then(|x| x.origin)
    }

    /// Forgets the writes among the writer's first `acknowledged` that are stamped up to
    /// `drained` (ordinals and stamps grow in the order of the queue), noting whose they
    /// were; whether nothing is left.
    fn release_through(
        &self,
        acknowledged: u64,
        drained: u64,
        frontends: &mut HashSet<u32>,
    ) -> bool {
        self.release_while(
            |w| w.ordinal <= acknowledged && w.stamp <= drained,
            frontends,
        )
    }

    /// Forgets the oldest writes while `done` says so, noting whose they were; whether
    /// nothing is left.
    fn release_while(&self, done: impl Fn(&Written) -> bool, frontends: &mut HashSet<u32>) -> bool {
        let mut w = self.writes.borrow_mut();
        while let Some(front) = w.front().filter(|f| done(f)) {
            frontends.insert(front.frontend);
            w.pop_front();
        }
        if w.is_empty() {
            self.mixed.set(false);
        }
        w.is_empty()
    }

    /// The oldest outstanding operation of each front-end, merged into `min`.
    fn oldest(&self, min: &mut HashMap<u32, u64>) {
        let w = self.writes.borrow();
        let mut merge = |fe: u32, seq: u64| {
            let m = min.entry(fe).or_insert(seq);
            *m = (*m).min(seq);
        };
        if !self.mixed.get() {
            // One front-end's writes, in its order: the first is the oldest.
            if let Some(front) = w.front() {
                merge(front.frontend, front.seq);
            }
            return;
        }
        for x in w.iter() {
            merge(x.frontend, x.seq);
        }
    }

    /// Forgets writes older than `limit`; whether nothing is left.
    fn expire(&self, limit: Instant, frontends: &mut HashSet<u32>) -> bool {
        self.release_while(|w| w.at < limit, frontends)
    }

    /// Forgets front-end `frontend`'s writes.
    fn forget(&self, frontend: u32) {
        self.writes.borrow_mut().retain(|w| w.frontend != frontend);
    }

    /// How many writes are outstanding.
    pub fn len(&self) -> usize {
        self.writes.borrow().len()
    }

    /// Whether none is.
    pub fn is_empty(&self) -> bool {
        self.writes.borrow().is_empty()
    }
}

/// The writers with outstanding writes.
#[derive(Debug)]
pub struct AckTracker<W> {
    watched: Vec<Weak<W>>,
    /// The same writers by GUID, for the origins of what the worker's readers take.
    by_guid: HashMap<[u8; 16], Weak<W>>,
    next_poll: Instant,
}

impl<W: Acknowledging> AckTracker<W> {
    /// Nothing watched.
    pub fn new(now: Instant) -> Self {
        AckTracker {
            watched: Vec::new(),
            by_guid: HashMap::new(),
            next_poll: now,
        }
    }

    /// Watches `writer`, whose GUID is `guid` (call when [`Outstanding::record`] returned
    /// true).
    pub fn watch(&mut self, guid: [u8; 16], writer: &Rc<W>) {
        self.watched.push(Rc::downgrade(writer));
        self.by_guid.insert(guid, Rc::downgrade(writer));
    }

    /// The client write that sample `sequence_number` of the DDS writer `guid` came from,
    /// if that writer is one of the worker's, the write is outstanding and had an origin.
    pub fn origin_of(&self, guid: &[u8; 16], sequence_number: i64) -> Option<SampleOrigin> {
        self.by_guid
            .get(guid)?
            .upgrade()?
            .outstanding()
            .origin_of(sequence_number)
    }

    /// When the tracker wants to poll again (None: nothing watched).
    pub fn due(&self) -> Option<Instant> {
        (!self.watched.is_empty()).then_some(self.next_poll)
    }

    /// Asks the watched writers (at most every [`ACK_POLL_PERIOD`]); returns the front-ends
    /// whose acknowledged frontier may have moved. `drained` tells, of a writer, the stamp
    /// up to which the worker's own readers of its topic took everything written (`u64::MAX`
    /// with none reading). A writer that was deleted has nothing outstanding any more: its
    /// front-ends are returned too (`all` true: unknown which).
    pub fn poll(
        &mut self,
        now: Instant,
        mut drained: impl FnMut(&W) -> u64,
    ) -> (HashSet<u32>, bool) {
        let mut moved = HashSet::new();
        let mut all = false;
        if self.watched.is_empty() || now < self.next_poll {
            return (moved, all);
        }
        self.next_poll = now + ACK_POLL_PERIOD;
        let limit = now.checked_sub(ACK_GIVE_UP).unwrap_or(now);
        self.watched.retain(|w| {
            let Some(w) = w.upgrade() else {
                all = true;
                return false;
            };
            let out = w.outstanding();
            if out.release_through(w.acknowledged_writes(), drained(&w), &mut moved) {
                return false;
            }
            !out.expire(limit, &mut moved)
        });
        // A writer no longer watched has nothing outstanding (or is gone); one watched twice
        // (its writes forgotten, then new ones) stays.
        if self.by_guid.len() > self.watched.len() {
            self.by_guid
                .retain(|_, w| w.upgrade().is_some_and(|w| !w.outstanding().is_empty()));
        }
        (moved, all)
    }

    /// Forgets the outstanding writes of front-end `frontend` on every watched writer: the
    /// process that kept them for a resend is gone, and its successor numbers its operations
    /// from 1 again (left, the old numbers would hold its acknowledged frontier back).
    pub fn forget_frontend(&mut self, frontend: u32) {
        for w in self.watched.iter().filter_map(Weak::upgrade) {
            w.outstanding().forget(frontend);
        }
    }

    /// For each front-end with outstanding writes, its oldest one.
    pub fn oldest_outstanding(&self) -> HashMap<u32, u64> {
        let mut min = HashMap::new();
        for w in self.watched.iter().filter_map(Weak::upgrade) {
            w.outstanding().oldest(&mut min);
        }
        min
    }

    /// Writes outstanding over every watched writer.
    pub fn outstanding_writes(&self) -> usize {
        self.watched
            .iter()
            .filter_map(Weak::upgrade)
            .map(|w| w.outstanding().len())
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    #[derive(Default)]
    struct FakeWriter {
        written: Cell<u64>,
        acked: Cell<u64>,
        out: Outstanding,
    }

    impl FakeWriter {
        /// Its readers acknowledged everything written so far.
        fn ack_all(&self) {
            self.acked.set(self.written.get());
        }
    }

    impl Acknowledging for FakeWriter {
        fn acknowledged_writes(&self) -> u64 {
            self.acked.get()
        }
        fn outstanding(&self) -> &Outstanding {
            &self.out
        }
    }

    thread_local! {
        /// The tests' count of recorded writes.
        static STAMP: Cell<u64> = const { Cell::new(0) };
    }

    fn write(t: &mut AckTracker<FakeWriter>, w: &Rc<FakeWriter>, fe: u32, seq: u64, now: Instant) {
        write_from(t, w, fe, seq, now, None);
    }

    /// The writer's GUID in these tests: its address.
    fn guid(w: &Rc<FakeWriter>) -> [u8; 16] {
        (Rc::as_ptr(w) as usize as u128).to_le_bytes()
    }

    fn write_from(
        t: &mut AckTracker<FakeWriter>,
        w: &Rc<FakeWriter>,
        fe: u32,
        seq: u64,
        now: Instant,
        origin: Option<SampleOrigin>,
    ) {
        w.written.set(w.written.get() + 1);
        STAMP.with(|s| s.set(s.get() + 1));
        let written = Written {
            frontend: fe,
            seq,
            at: now,
            ordinal: w.written.get(),
            stamp: STAMP.with(Cell::get),
            sequence_number: w.written.get() as i64,
            origin,
        };
        if w.out.record(written) {
            t.watch(guid(w), w);
        }
    }

    #[test]
    fn the_oldest_unacknowledged_write_of_each_frontend_bounds_its_frontier() {
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let (a, b) = (
            Rc::new(FakeWriter::default()),
            Rc::new(FakeWriter::default()),
        );
        write(&mut t, &a, 1, 10, t0);
        write(&mut t, &a, 1, 12, t0);
        write(&mut t, &b, 1, 11, t0);
        write(&mut t, &b, 2, 5, t0);
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 10), (2, 5)]));
        // Nothing acknowledged: nothing moves.
        assert_eq!(t.poll(t0, |_| u64::MAX).0, HashSet::new());
        // Writer a's readers acknowledged: front-end 1 now waits only for b's 11.
        a.ack_all();
        let (moved, all) = t.poll(t0 + ACK_POLL_PERIOD, |_| u64::MAX);
        assert_eq!((moved, all), (HashSet::from([1]), false));
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 11), (2, 5)]));
        assert_eq!(t.outstanding_writes(), 2);
        // Polls are rate-limited.
        b.ack_all();
        assert!(t.poll(t0 + ACK_POLL_PERIOD, |_| u64::MAX).0.is_empty());
        let (moved, _) = t.poll(t0 + 2 * ACK_POLL_PERIOD, |_| u64::MAX);
        assert_eq!(moved, HashSet::from([1, 2]));
        assert!(t.oldest_outstanding().is_empty());
        assert_eq!(t.due(), None);
    }

    #[test]
    fn a_departed_frontends_writes_are_forgotten() {
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let w = Rc::new(FakeWriter::default());
        write(&mut t, &w, 1, 3, t0);
        write(&mut t, &w, 2, 40, t0);
        t.forget_frontend(1);
        assert_eq!(t.oldest_outstanding(), HashMap::from([(2, 40)]));
        // The successor numbers from 1 again: its writes are not held back by 3.
        write(&mut t, &w, 1, 1, t0);
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 1), (2, 40)]));
        t.forget_frontend(1);
        t.forget_frontend(2);
        assert_eq!(t.outstanding_writes(), 0);
        // An empty writer is let go on the next poll.
        let _ = t.poll(t0 + ACK_GIVE_UP + ACK_POLL_PERIOD, |_| u64::MAX);
        assert_eq!(t.due(), None);
    }

    #[test]
    fn writes_recorded_out_of_order_bound_the_frontier_by_their_oldest() {
        // Two XRCE writers on one shared DDS writer release their held samples in turns:
        // one front-end's operations are not recorded in their order.
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let shared = Rc::new(FakeWriter::default());
        for seq in [10, 11, 12, 5, 6, 13, 7] {
            write(&mut t, &shared, 1, seq, t0);
        }
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 5)]));
        // And interleaved front-ends each get their own oldest.
        let other = Rc::new(FakeWriter::default());
        for (fe, seq) in [(2, 40), (3, 8), (2, 41), (3, 9)] {
            write(&mut t, &other, fe, seq, t0);
        }
        assert_eq!(
            t.oldest_outstanding(),
            HashMap::from([(1, 5), (2, 40), (3, 8)])
        );
    }

    #[test]
    fn writes_never_acknowledged_are_given_up_and_deleted_writers_release_theirs() {
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let stuck = Rc::new(FakeWriter::default());
        write(&mut t, &stuck, 3, 1, t0);
        write(&mut t, &stuck, 3, 2, t0 + Duration::from_secs(1));
        let (moved, _) = t.poll(t0 + ACK_GIVE_UP + Duration::from_millis(1), |_| u64::MAX);
        assert_eq!(moved, HashSet::from([3]));
        assert_eq!(t.oldest_outstanding(), HashMap::from([(3, 2)]));
        let gone = Rc::new(FakeWriter::default());
        write(&mut t, &gone, 4, 7, t0 + ACK_GIVE_UP);
        drop(gone);
        let (_, all) = t.poll(t0 + ACK_GIVE_UP + Duration::from_millis(10), |_| u64::MAX);
        assert!(all, "a deleted writer's front-ends are not known any more");
        assert_eq!(t.oldest_outstanding(), HashMap::from([(3, 2)]));
    }

    #[test]
    fn readers_acknowledging_part_of_a_stream_release_that_part() {
        // Readers that acknowledge only every so often (Cyclone DDS): while writes go on,
        // "everything acknowledged" is never true, but the acknowledged ones are let go.
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let w = Rc::new(FakeWriter::default());
        for seq in 1..=5 {
            write(&mut t, &w, 1, seq, t0);
        }
        w.acked.set(3);
        let (moved, _) = t.poll(t0, |_| u64::MAX);
        assert_eq!(moved, HashSet::from([1]));
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 4)]));
        write(&mut t, &w, 1, 6, t0);
        w.acked.set(5);
        let _ = t.poll(t0 + ACK_POLL_PERIOD, |_| u64::MAX);
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 6)]));
        w.ack_all();
        let _ = t.poll(t0 + 2 * ACK_POLL_PERIOD, |_| u64::MAX);
        assert!(t.oldest_outstanding().is_empty());
        assert_eq!(t.due(), None);
    }

    #[test]
    fn writes_wait_for_the_workers_own_readers_to_be_drained_past_them() {
        // Acknowledged by every reader DDS counts, but this worker's own reader of the topic
        // still holds some: those stay outstanding until it was drained past them.
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let w = Rc::new(FakeWriter::default());
        let first = STAMP.with(Cell::get) + 1;
        for seq in 1..=4 {
            write(&mut t, &w, 1, seq, t0);
        }
        w.ack_all();
        let (moved, _) = t.poll(t0, |_| first - 1);
        assert!(moved.is_empty(), "nothing drained past any write");
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 1)]));
        let (moved, _) = t.poll(t0 + ACK_POLL_PERIOD, |_| first + 1);
        assert_eq!(moved, HashSet::from([1]));
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 3)]));
        // Drained past everything, but DDS readers acknowledged only the first three.
        w.acked.set(3);
        write(&mut t, &w, 1, 5, t0);
        let _ = t.poll(t0 + 2 * ACK_POLL_PERIOD, |_| u64::MAX);
        assert_eq!(t.oldest_outstanding(), HashMap::from([(1, 4)]));
        // A reader that never drains holds nothing past the give-up time.
        w.ack_all();
        let _ = t.poll(t0 + ACK_GIVE_UP + ACK_POLL_PERIOD, |_| 0);
        assert!(t.oldest_outstanding().is_empty());
    }

    #[test]
    fn a_sample_taken_here_is_told_its_origin_while_its_write_is_outstanding() {
        let t0 = Instant::now();
        let mut t = AckTracker::new(t0);
        let w = Rc::new(FakeWriter::default());
        // A failed write numbered by the backend and not recorded (Cyclone numbers
        // attempts): sequence number 3 is missing.
        let skip = || w.written.set(w.written.get() + 1);
        let origin = |write: u64| SampleOrigin {
            write: xrce_ipc::WriteOrigin {
                frontend: 1,
                incarnation: 1,
                write,
                index: 0,
            },
            resent: write == 3,
        };
        // Sequence numbers 1, 2, 4, 5; the second write (a best-effort one) has no origin.
        write_from(&mut t, &w, 1, 1, t0, Some(origin(1)));
        write_from(&mut t, &w, 1, 2, t0, None);
        skip();
        write_from(&mut t, &w, 1, 3, t0, Some(origin(3)));
        write_from(&mut t, &w, 1, 4, t0, Some(origin(4)));
        let g = guid(&w);
        assert_eq!(t.origin_of(&g, 1), Some(origin(1)));
        assert_eq!(t.origin_of(&g, 2), None);
        assert_eq!(t.origin_of(&g, 3), None, "the failed write");
        assert_eq!(t.origin_of(&g, 4), Some(origin(3)));
        assert_eq!(t.origin_of(&g, 5), Some(origin(4)));
        assert_eq!(t.origin_of(&g, 6), None, "not written");
        assert_eq!(t.origin_of(&g, 0), None, "no number");
        assert_eq!(t.origin_of(&g, -1), None);
        assert_eq!(
            t.origin_of(&[7; 16], 1),
            None,
            "not one of the worker's writers"
        );
        // Acknowledged and drained past the first two: they are no longer told.
        w.acked.set(2);
        let first = STAMP.with(Cell::get) - 3;
        let _ = t.poll(t0, |_| first + 1);
        assert_eq!(t.origin_of(&g, 1), None);
        assert_eq!(t.origin_of(&g, 4), Some(origin(3)));
        // Everything acknowledged: the writer is forgotten.
        w.ack_all();
        let _ = t.poll(t0 + ACK_POLL_PERIOD, |_| u64::MAX);
        assert_eq!(t.origin_of(&g, 5), None);
        assert!(t.by_guid.is_empty());
    }
}
