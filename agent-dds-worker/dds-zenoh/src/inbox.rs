//! Where Zenoh's callback threads leave what arrives for the worker: one bounded queue per
//! reader, and the list of readers with something new behind one descriptor the worker's
//! loop polls.

use std::collections::VecDeque;
use std::io::{Read as _, Write as _};
use std::os::fd::{AsFd, BorrowedFd};
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use xrce_dds_seam::{BackendError, ReaderToken, Taken};

/// Locks a mutex whose holder may have panicked (the data stays usable: queues and lists).
pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The readers with something new, and the descriptor that says so.
#[derive(Debug)]
pub(super) struct Wakeup {
    ready: Mutex<Vec<ReaderToken>>,
    tx: UnixStream,
    rx: UnixStream,
}

impl Wakeup {
    pub(super) fn new() -> std::io::Result<Self> {
        let (tx, rx) = UnixStream::pair()?;
        tx.set_nonblocking(true)?;
        rx.set_nonblocking(true)?;
        Ok(Wakeup {
            ready: Mutex::new(Vec::new()),
            tx,
            rx,
        })
    }

    fn notify(&self, token: ReaderToken) {
        let mut ready = lock(&self.ready);
        if ready.is_empty() {
            // One byte per batch: a full socket buffer already says "ready".
            let _ = (&self.tx).write(&[1]);
        }
        ready.push(token);
    }

    pub(super) fn fd(&self) -> BorrowedFd<'_> {
        self.rx.as_fd()
    }

    /// Moves the ready readers' tokens to `out` and clears the descriptor.
    pub(super) fn drain(&self, out: &mut Vec<ReaderToken>) -> std::io::Result<()> {
        let mut buf = [0u8; 256];
        loop {
            match (&self.rx).read(&mut buf) {
                Ok(0) => break,
                Ok(_) => continue,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            }
        }
        out.append(&mut lock(&self.ready));
        Ok(())
    }
}

/// What a full queue gives up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum WhenFull {
    /// Keep last: the oldest sample goes.
    DropOldest,
    /// Keep all (bounded): the new sample goes.
    DropNewest,
}

/// Most bytes of sample bodies one reader's queue holds, whatever its depth: a remote
/// publisher's large samples cannot make the worker hold more.
pub(super) const MAX_QUEUED_BYTES: usize = 16 << 20;

/// The limit of every reader's queue together ([`QueuedBytes`]): however many readers clients
/// make, what arrives for them while they do not read stays within one and a half times it.
pub(super) const MAX_ALL_QUEUED_BYTES: usize = 64 << 20;

/// Bytes queued in every reader's queue together, shared as a front-end's memory budget is:
/// below half the limit a reader takes what comes; beyond, only up to its equal share (the
/// limit over the readers), so readers that never read cannot take the room of those that
/// do. A reader within its share always finds room: what was taken below half plus every
/// share is the most all hold together, one and a half times the limit.
#[derive(Debug)]
pub(super) struct QueuedBytes {
    held: AtomicUsize,
    readers: AtomicUsize,
    limit: usize,
}

impl QueuedBytes {
    pub(super) fn new(limit: usize) -> Self {
        QueuedBytes {
            held: AtomicUsize::new(0),
            readers: AtomicUsize::new(0),
            limit,
        }
    }

    fn share(&self) -> usize {
        self.limit / self.readers.load(Ordering::Relaxed).max(1)
    }

    /// Whether a reader holding `own` bytes must give up some before it takes `more`.
    fn over(&self, own: usize, more: usize) -> bool {
        let held = self.held.load(Ordering::Relaxed);
        held + more > self.limit / 2 && own + more > self.share()
    }

    /// Whether `more` bytes cannot be taken even by a reader that gave up all its `own`.
    fn hopeless(&self, own: usize, more: usize) -> bool {
        let others = self.held.load(Ordering::Relaxed).saturating_sub(own);
        others + more > self.limit / 2 && more > self.share()
    }

    fn add(&self, n: usize) {
        self.held.fetch_add(n, Ordering::Relaxed);
    }

    fn sub(&self, n: usize) {
        self.held.fetch_sub(n, Ordering::Relaxed);
    }
}

impl Default for QueuedBytes {
    fn default() -> Self {
        QueuedBytes::new(MAX_ALL_QUEUED_BYTES)
    }
}

fn size(item: &Result<Taken, BackendError>) -> usize {
    item.as_ref().map_or(0, |t| t.sample.body.len())
}

#[derive(Debug)]
struct Queue {
    items: VecDeque<Result<Taken, BackendError>>,
    bytes: usize,
    /// The reader's token is in the ready list (or it is being drained).
    listed: bool,
}

/// What [`Inbox::push`] did.
#[derive(Debug)]
pub(super) struct Pushed {
    /// The item is in the queue.
    pub(super) queued: bool,
    /// Older items given up for it.
    pub(super) evicted: Vec<Result<Taken, BackendError>>,
}

/// One reader's queue.
#[derive(Debug)]
pub(super) struct Inbox {
    queue: Mutex<Queue>,
    capacity: usize,
    when_full: WhenFull,
    token: ReaderToken,
    wakeup: Arc<Wakeup>,
    dropped: Arc<AtomicU64>,
    all: Arc<QueuedBytes>,
}

impl Inbox {
    pub(super) fn new(
        token: ReaderToken,
        capacity: usize,
        when_full: WhenFull,
        wakeup: Arc<Wakeup>,
        dropped: Arc<AtomicU64>,
        all: Arc<QueuedBytes>,
    ) -> Self {
        all.readers.fetch_add(1, Ordering::Relaxed);
        Inbox {
            queue: Mutex::new(Queue {
                items: VecDeque::new(),
                bytes: 0,
                listed: false,
            }),
            capacity: capacity.max(1),
            when_full,
            token,
            wakeup,
            dropped,
            all,
        }
    }

    /// Queues what arrived and wakes the worker if the reader was not listed yet. Returns
    /// whether it was queued, and what was given up for it (keep-last: the oldest), so that a
    /// replier can let go of the queries of requests that will never be delivered.
    pub(super) fn push(&self, item: Result<Taken, BackendError>) -> Pushed {
        let mut q = lock(&self.queue);
        let new = size(&item);
        let mut evicted = Vec::new();
        if new > MAX_QUEUED_BYTES {
            self.dropped.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                bytes = new,
                "a Zenoh sample larger than a reader's queue: dropped"
            );
            return Pushed {
                queued: false,
                evicted,
            };
        }
        // What the other readers hold leaves no room however much of its own it gave up:
        // the new sample goes, its queue stays.
        let hopeless = self.all.hopeless(q.bytes, new);
        while hopeless
            || q.items.len() >= self.capacity
            || q.bytes + new > MAX_QUEUED_BYTES
            || self.all.over(q.bytes, new)
        {
            if self.dropped.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!(
                    capacity = self.capacity,
                    max_bytes = MAX_QUEUED_BYTES,
                    max_bytes_all_readers = self.all.limit,
                    "a Zenoh reader's queue is full: samples are dropped (its history depth, \
                     or its resource limits for keep-all, or 16 MiB, or its share of the room \
                     of every reader's queue together; counted in the worker's status)"
                );
            }
            let oldest = match self.when_full {
                WhenFull::DropOldest if !hopeless => q.items.pop_front(),
                _ => None,
            };
            match oldest {
                Some(old) => {
                    q.bytes -= size(&old);
                    self.all.sub(size(&old));
                    evicted.push(old);
                }
                // Keep-all, or nothing of its own left to give up while the other readers'
                // queues hold the rest: the new one goes.
                None => {
                    return Pushed {
                        queued: false,
                        evicted,
                    }
                }
            }
        }
        q.bytes += new;
        self.all.add(new);
        q.items.push_back(item);
        if !q.listed {
            q.listed = true;
            self.wakeup.notify(self.token);
        }
        Pushed {
            queued: true,
            evicted,
        }
    }

    /// The next item; when there is none, the reader is listed again on the next push.
    pub(super) fn pop(&self) -> Option<Result<Taken, BackendError>> {
        let mut q = lock(&self.queue);
        let item = q.items.pop_front();
        match &item {
            Some(i) => {
                q.bytes -= size(i);
                self.all.sub(size(i));
            }
            None => q.listed = false,
        }
        item
    }
}

impl Drop for Inbox {
    /// What a deleted reader still had queued is given back to every reader's limit.
    fn drop(&mut self) {
        let q = lock(&self.queue);
        self.all.sub(q.bytes);
        self.all.readers.fetch_sub(1, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_dds_seam::{Sample, SampleIdentity};

    fn taken(n: u8) -> Result<Taken, BackendError> {
        Ok(Taken {
            sample: Sample::cdr(true, &[n]),
            identity: SampleIdentity::default(),
            related: None,
            disposed: false,
            unregistered: false,
        })
    }

    fn body(t: Option<Result<Taken, BackendError>>) -> Option<u8> {
        t.and_then(Result::ok).map(|t| t.sample.body[0])
    }

    #[test]
    fn a_reader_is_listed_once_until_drained_and_its_queue_is_bounded() {
        let wakeup = Arc::new(Wakeup::new().expect("socket pair"));
        let dropped = Arc::new(AtomicU64::new(0));
        let pool = Arc::new(QueuedBytes::default());
        let last = Inbox::new(
            7,
            2,
            WhenFull::DropOldest,
            wakeup.clone(),
            dropped.clone(),
            pool.clone(),
        );
        let all = Inbox::new(
            8,
            2,
            WhenFull::DropNewest,
            wakeup.clone(),
            dropped.clone(),
            pool,
        );
        for n in 1..=3 {
            last.push(taken(n));
            all.push(taken(n));
        }
        let mut ready = Vec::new();
        wakeup.drain(&mut ready).expect("drain");
        assert_eq!(ready, vec![7, 8]);
        assert_eq!(dropped.load(Ordering::Relaxed), 2);
        assert_eq!(body(last.pop()), Some(2));
        assert_eq!(body(last.pop()), Some(3));
        assert_eq!(body(all.pop()), Some(1));
        assert_eq!(body(all.pop()), Some(2));
        assert!(last.pop().is_none() && all.pop().is_none());
        ready.clear();
        wakeup.drain(&mut ready).expect("drain");
        assert!(ready.is_empty(), "nothing new, no wake-up");
        last.push(taken(4));
        wakeup.drain(&mut ready).expect("drain");
        assert_eq!(ready, vec![7], "drained readers are listed again");
    }

    #[test]
    fn a_queue_holds_at_most_its_byte_budget() {
        let wakeup = Arc::new(Wakeup::new().expect("socket pair"));
        let dropped = Arc::new(AtomicU64::new(0));
        let q = Inbox::new(
            1,
            1000,
            WhenFull::DropOldest,
            wakeup,
            dropped.clone(),
            Arc::default(),
        );
        let big = |n: u8| {
            Ok(Taken {
                sample: Sample::cdr(true, &vec![n; MAX_QUEUED_BYTES / 3]),
                identity: SampleIdentity::default(),
                related: None,
                disposed: false,
                unregistered: false,
            })
        };
        for n in 1..=4 {
            q.push(big(n));
        }
        assert_eq!(dropped.load(Ordering::Relaxed), 1, "the oldest made room");
        assert_eq!(body(q.pop()), Some(2));
        q.push(Ok(Taken {
            sample: Sample::cdr(true, &vec![9; MAX_QUEUED_BYTES + 1]),
            identity: SampleIdentity::default(),
            related: None,
            disposed: false,
            unregistered: false,
        }));
        assert_eq!(
            body(q.pop()),
            Some(3),
            "a sample over the whole budget is dropped"
        );
        assert_eq!(body(q.pop()), Some(4));
        assert!(q.pop().is_none());
    }

    /// `n` readers of `capacity` samples sharing 1 MiB, and the pool and drop counter.
    fn readers_sharing_1_mib(
        n: ReaderToken,
        capacity: usize,
        when_full: impl Fn(ReaderToken) -> WhenFull,
    ) -> (Vec<Inbox>, Arc<QueuedBytes>, Arc<AtomicU64>) {
        let wakeup = Arc::new(Wakeup::new().expect("socket pair"));
        let dropped = Arc::new(AtomicU64::new(0));
        let pool = Arc::new(QueuedBytes::new(1 << 20));
        let readers = (0..n)
            .map(|t| {
                Inbox::new(
                    t,
                    capacity,
                    when_full(t),
                    wakeup.clone(),
                    dropped.clone(),
                    pool.clone(),
                )
            })
            .collect();
        (readers, pool, dropped)
    }

    fn sample_10k() -> Result<Taken, BackendError> {
        Ok(Taken {
            sample: Sample::cdr(true, &[7; 10 << 10]),
            identity: SampleIdentity::default(),
            related: None,
            disposed: false,
            unregistered: false,
        })
    }

    #[test]
    fn every_reader_together_holds_at_most_the_shared_limit() {
        // 100 readers that never read, 1,000 samples of 10 KiB each offered to every one:
        // 1 GB offered, the limit (1 MiB here) held.
        let (readers, pool, dropped) = readers_sharing_1_mib(100, 1000, |t| {
            if t % 2 == 0 {
                WhenFull::DropOldest
            } else {
                WhenFull::DropNewest
            }
        });
        for _ in 0..1000 {
            for r in &readers {
                r.push(sample_10k());
            }
        }
        assert!(pool.held.load(Ordering::Relaxed) <= 3 << 19);
        assert!(dropped.load(Ordering::Relaxed) > 0);
        // What the readers take gives the room back.
        let mut taken = 0;
        for r in &readers {
            while r.pop().is_some() {
                taken += 1;
            }
        }
        assert!(taken > 0 && taken <= (3 << 19) / (10 << 10));
        assert_eq!(pool.held.load(Ordering::Relaxed), 0);
        assert!(readers[1].push(sample_10k()).queued, "room again");
        // A reader deleted with samples queued gives their room back.
        assert!(pool.held.load(Ordering::Relaxed) > 0);
        drop(readers);
        assert_eq!(pool.held.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn readers_that_never_read_leave_room_for_one_that_does() {
        // Four keep-last readers that never read, then a fifth: past half the limit each
        // holds its share (the limit over five), so the fifth finds room.
        let (readers, pool, _) = readers_sharing_1_mib(5, 10_000, |_| WhenFull::DropOldest);
        for r in &readers[..4] {
            for _ in 0..1000 {
                r.push(sample_10k());
            }
        }
        assert!(pool.held.load(Ordering::Relaxed) <= 3 << 19);
        for n in 0..10 {
            assert!(
                readers[4].push(sample_10k()).queued,
                "sample {n} of the reader that reads"
            );
        }
        // The greedy readers kept their newest samples (keep-last), none went unaccounted.
        let queued: usize = readers.iter().map(|r| lock(&r.queue).bytes).sum();
        assert_eq!(queued, pool.held.load(Ordering::Relaxed));
    }
}
