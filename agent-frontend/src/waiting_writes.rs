//! Best-effort writes waiting for the worker's window, shared fairly among the clients.
//!
//! In hand-over mode a best-effort write that finds the window's best-effort share full
//! waits here, within a bound of entries and of bytes, instead of being dropped (a worker
//! pass that stalls a few milliseconds is absorbed). What the queue holds is shared:
//!
//! * **Turns.** The clients with waiting writes take turns, one write each, oldest first
//!   within a client. A quiet client's write is sent after at most one write of every other
//!   waiting client, not after a flood's backlog. (Order between clients means nothing to
//!   DDS; order within one client's writes is kept.)
//! * **The heaviest pays.** When the queue is full, a write of a client that holds less than
//!   another makes room by dropping that other's newest waiting write. A client that holds
//!   the most when the queue is full is overloading it: its write is dropped and its
//!   best-effort writes are *held*, not queued at all, for a while ([`WaitingWrites::hold`]),
//!   as is a client whose write was dropped to make room. Queueing a flood only feeds it, at
//!   the expense of every other client's service. A write that finds nothing waiting and the
//!   window's share free goes to the worker at once, held or not (the caller decides that).
//!   If dropping the newer writes of heavier clients cannot make room (a large write into a
//!   queue bound by its bytes), nothing of theirs is dropped.
//!
//! The structure is sans-IO: the caller passes the time and does the sending.

use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::time::{Duration, Instant};

use xrce_common::wire::ClientKey;

/// One client's waiting writes, oldest first, with their weights.
#[derive(Debug)]
struct ClientWrites<T> {
    items: VecDeque<(T, usize)>,
    bytes: usize,
}

impl<T> Default for ClientWrites<T> {
    fn default() -> Self {
        ClientWrites {
            items: VecDeque::new(),
            bytes: 0,
        }
    }
}

/// Whether a write may wait ([`WaitingWrites::make_room`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Room {
    /// It may: push it. `evicted` newer writes of heavier clients were dropped for it, and
    /// `holds_started` of those clients are now held.
    Yes {
        /// Writes of heavier clients dropped to make room.
        evicted: usize,
        /// Clients held because of those drops (they were not held already).
        holds_started: usize,
    },
    /// It may not: drop it. `hold_started`: this write overflowed the queue and its client
    /// is now held (false: the client was held already).
    No {
        /// Whether this write started its client's hold.
        hold_started: bool,
    },
}

/// Best-effort writes waiting for the window, per client in turns (see the module docs).
///
/// Queueing a write costs a few hash lookups and a push onto a heap of what clients hold
/// (entries go stale as clients' writes leave and are corrected when they reach the top;
/// the heap is rebuilt when it has grown to twice the clients); taking one costs a few hash
/// lookups. A full queue finds the client holding the most in O(log clients).
#[derive(Debug)]
pub struct WaitingWrites<T> {
    /// An entry per client in `turns` (it may have no writes left: dropped when its turn
    /// comes, so that no client is ever twice in `turns`).
    clients: HashMap<ClientKey, ClientWrites<T>>,
    /// The clients with an entry, the next to send first; each once.
    turns: VecDeque<ClientKey>,
    len: usize,
    bytes: usize,
    max_len: usize,
    max_bytes: usize,
    hold: Duration,
    /// What clients held when a write of theirs was queued: for every client with waiting
    /// writes at least one entry at or above what it holds now (see
    /// [`WaitingWrites::heaviest_other`]).
    heaviest: BinaryHeap<(u128, ClientKey)>,
    /// Clients whose writes are not queued until then.
    holds: HashMap<ClientKey, Instant>,
    /// Size of `holds` beyond which ended holds are removed (amortised).
    prune_holds_beyond: usize,
}

impl<T> WaitingWrites<T> {
    /// An empty queue of at most `max_len` writes and `max_bytes` bytes (one write of any
    /// weight fits an empty queue), whose overflowing clients are held for `hold`.
    pub fn new(max_len: usize, max_bytes: usize, hold: Duration) -> Self {
        WaitingWrites {
            clients: HashMap::new(),
            turns: VecDeque::new(),
            len: 0,
            bytes: 0,
            max_len: max_len.max(1),
            max_bytes,
            hold,
            heaviest: BinaryHeap::new(),
            holds: HashMap::new(),
            prune_holds_beyond: 64,
        }
    }

    /// How long a client that overflows the queue is held.
    pub fn hold(&self) -> Duration {
        self.hold
    }

    /// Sets how long a client that overflows the queue is held (holds already started
    /// keep their end).
    pub fn set_hold(&mut self, hold: Duration) {
        self.hold = hold;
    }

    /// Writes waiting.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether nothing waits.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes waiting (the weights given to [`WaitingWrites::push`]).
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Writes of `client` waiting.
    pub fn len_of(&self, client: ClientKey) -> usize {
        self.clients.get(&client).map_or(0, |c| c.items.len())
    }

    /// Whether `client`'s writes are held at `now`.
    pub fn is_held(&self, client: ClientKey, now: Instant) -> bool {
        self.holds.get(&client).is_some_and(|&until| now < until)
    }

    /// Decides whether a write of `client` weighing `weight` may wait, making room for it at
    /// the expense of heavier clients if the queue is full. On [`Room::Yes`] the caller
    /// pushes it ([`WaitingWrites::push`]) before anything else changes the queue.
    pub fn make_room(&mut self, client: ClientKey, weight: usize, now: Instant) -> Room {
        if let Some(&until) = self.holds.get(&client) {
            if now < until {
                return Room::No {
                    hold_started: false,
                };
            }
            self.holds.remove(&client);
        }
        if self.fits(weight) {
            return Room::Yes {
                evicted: 0,
                holds_started: 0,
            };
        }
        let (own_len, own_bytes) = self
            .clients
            .get(&client)
            .map_or((0, 0), |c| (c.items.len(), c.bytes));
        let own = self.heaviness(own_len + 1, own_bytes.saturating_add(weight));
        // Take the newest write of whoever holds the most while that is more than this
        // client would; if that cannot make room, put everything back.
        let mut taken: Vec<(ClientKey, T, usize, bool)> = Vec::new();
        while !self.fits(weight) {
            match self.heaviest_other(client) {
                Some((theirs, other)) if theirs > own => {
                    let Some((item, w)) = self.take_newest(other) else {
                        break;
                    };
                    let held = self.start_hold(other, now);
                    taken.push((other, item, w, held));
                }
                _ => break,
            }
        }
        if self.fits(weight) {
            return Room::Yes {
                evicted: taken.len(),
                holds_started: taken.iter().filter(|t| t.3).count(),
            };
        }
        while let Some((other, item, w, held)) = taken.pop() {
            if held {
                self.holds.remove(&other);
            }
            self.push(other, item, w);
        }
        Room::No {
            hold_started: self.start_hold(client, now),
        }
    }

    /// Queues a write of `client` weighing `weight` (after [`Room::Yes`]).
    pub fn push(&mut self, client: ClientKey, item: T, weight: usize) {
        let writes = self.clients.entry(client).or_insert_with(|| {
            self.turns.push_back(client);
            ClientWrites::default()
        });
        writes.items.push_back((item, weight));
        writes.bytes += weight;
        let held = (writes.items.len(), writes.bytes);
        self.len += 1;
        self.bytes += weight;
        self.heaviest.push((self.heaviness(held.0, held.1), client));
        if self.heaviest.len() > 2 * self.clients.len() + 64 {
            self.rebuild_heaviest();
        }
    }

    /// The write whose turn it is, if any.
    pub fn front(&mut self) -> Option<&T> {
        self.skip_empty_turns();
        let client = self.turns.front()?;
        self.clients
            .get(client)
            .and_then(|c| c.items.front())
            .map(|(t, _)| t)
    }

    /// Takes the write whose turn it is; its client's next write waits for the next turn.
    pub fn pop(&mut self) -> Option<T> {
        self.skip_empty_turns();
        let client = self.turns.pop_front()?;
        let writes = self.clients.get_mut(&client)?;
        let (item, weight) = writes.items.pop_front()?;
        writes.bytes -= weight;
        if writes.items.is_empty() {
            self.clients.remove(&client);
        } else {
            self.turns.push_back(client);
        }
        self.len -= 1;
        self.bytes -= weight;
        Some(item)
    }

    /// Drops the entries of clients whose writes were all removed, from the front of the
    /// turns.
    fn skip_empty_turns(&mut self) {
        while let Some(client) = self.turns.front() {
            if self
                .clients
                .get(client)
                .is_some_and(|c| !c.items.is_empty())
            {
                return;
            }
            self.clients.remove(client);
            self.turns.pop_front();
        }
    }

    /// Keeps the waiting writes of `client` that `keep` says yes to, in order; returns how
    /// many it removed.
    pub fn retain_of(&mut self, client: ClientKey, mut keep: impl FnMut(&T) -> bool) -> usize {
        let Some(writes) = self.clients.get_mut(&client) else {
            return 0;
        };
        let before = writes.items.len();
        let mut removed_bytes = 0;
        writes.items.retain(|(t, w)| {
            let kept = keep(t);
            if !kept {
                removed_bytes += *w;
            }
            kept
        });
        writes.bytes -= removed_bytes;
        let removed = before - writes.items.len();
        self.len -= removed;
        self.bytes -= removed_bytes;
        removed
    }

    /// Drops every waiting write of `client` and ends its hold (its session ended); returns
    /// how many were dropped.
    pub fn remove_client(&mut self, client: ClientKey) -> usize {
        self.holds.remove(&client);
        self.retain_of(client, |_| false)
    }

    /// Drops every waiting write and ends every hold; returns how many were dropped.
    pub fn clear(&mut self) -> usize {
        let dropped = self.len;
        self.clients.clear();
        self.turns.clear();
        self.heaviest.clear();
        self.holds.clear();
        self.len = 0;
        self.bytes = 0;
        dropped
    }

    fn fits(&self, weight: usize) -> bool {
        self.len < self.max_len
            && (self.len == 0 || self.bytes.saturating_add(weight) <= self.max_bytes)
    }

    /// How much of the queue `len` writes of `bytes` take: the larger of the two shares,
    /// scaled to compare without division.
    fn heaviness(&self, len: usize, bytes: usize) -> u128 {
        let by_len = len as u128 * self.max_bytes.max(1) as u128;
        let by_bytes = bytes as u128 * self.max_len as u128;
        by_len.max(by_bytes)
    }

    /// Takes the newest waiting write of `client` (its heap entry goes stale).
    fn take_newest(&mut self, client: ClientKey) -> Option<(T, usize)> {
        let writes = self.clients.get_mut(&client)?;
        let (item, weight) = writes.items.pop_back()?;
        writes.bytes -= weight;
        self.len -= 1;
        self.bytes -= weight;
        Some((item, weight))
    }

    /// What the client holding the most, other than `client`, holds, and who it is.
    ///
    /// Stale entries (the client holds less now, or nothing) at the top are replaced by
    /// what their client holds; since every client with writes has an entry at or above
    /// what it holds, a current entry at the top is the largest.
    fn heaviest_other(&mut self, client: ClientKey) -> Option<(u128, ClientKey)> {
        let mut own_entries = Vec::new();
        let found = loop {
            let Some((h, k)) = self.heaviest.pop() else {
                break None;
            };
            let now_holds = self
                .clients
                .get(&k)
                .map_or(0, |c| self.heaviness(c.items.len(), c.bytes));
            if now_holds == 0 {
                continue;
            }
            if now_holds != h {
                // One current entry of `client` set aside is enough.
                if k != client || own_entries.is_empty() {
                    self.heaviest.push((now_holds, k));
                }
                continue;
            }
            if k == client {
                own_entries.push((h, k));
                continue;
            }
            break Some((h, k));
        };
        // The entries looked at stay (a client's write may still be taken, or put back).
        self.heaviest.extend(own_entries);
        if let Some(entry) = found {
            self.heaviest.push(entry);
        }
        found
    }

    /// Rebuilds the heap from what every client holds.
    fn rebuild_heaviest(&mut self) {
        let entries: Vec<(u128, ClientKey)> = self
            .clients
            .iter()
            .filter(|(_, c)| !c.items.is_empty())
            .map(|(k, c)| (self.heaviness(c.items.len(), c.bytes), *k))
            .collect();
        self.heaviest = BinaryHeap::from(entries);
    }

    /// Holds `client` from `now`; false if it was held already.
    fn start_hold(&mut self, client: ClientKey, now: Instant) -> bool {
        if self.holds.len() >= self.prune_holds_beyond {
            self.holds.retain(|_, until| now < *until);
            self.prune_holds_beyond = (2 * self.holds.len()).max(64);
        }
        let until = now + self.hold;
        match self.holds.insert(client, until) {
            Some(previous) if now < previous => {
                self.holds.insert(client, previous);
                false
            }
            _ => true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: ClientKey = ClientKey([0xA0, 0, 0, 1]);
    const B: ClientKey = ClientKey([0xB0, 0, 0, 2]);
    const C: ClientKey = ClientKey([0xC0, 0, 0, 3]);
    const HOUR: Duration = Duration::from_secs(3600);

    fn queue(max_len: usize, max_bytes: usize) -> WaitingWrites<(ClientKey, u32)> {
        WaitingWrites::new(max_len, max_bytes, HOUR)
    }

    /// Offers `n` writes of `client` (numbered from `first`) weighing `weight` each;
    /// returns how many were queued.
    fn offer(
        q: &mut WaitingWrites<(ClientKey, u32)>,
        client: ClientKey,
        first: u32,
        n: u32,
        weight: usize,
        now: Instant,
    ) -> u32 {
        let mut queued = 0;
        for i in first..first + n {
            if let Room::Yes { .. } = q.make_room(client, weight, now) {
                q.push(client, (client, i), weight);
                queued += 1;
            }
        }
        queued
    }

    fn drain(q: &mut WaitingWrites<(ClientKey, u32)>) -> Vec<(ClientKey, u32)> {
        std::iter::from_fn(|| q.pop()).collect()
    }

    #[test]
    fn clients_take_turns_and_each_keeps_its_order() {
        let now = Instant::now();
        let mut q = queue(100, 1 << 20);
        offer(&mut q, A, 0, 5, 10, now);
        offer(&mut q, B, 0, 2, 10, now);
        assert_eq!(q.len(), 7);
        assert_eq!(q.bytes(), 70);
        assert_eq!(q.front(), Some(&(A, 0)));
        assert_eq!(
            drain(&mut q),
            vec![(A, 0), (B, 0), (A, 1), (B, 1), (A, 2), (A, 3), (A, 4)]
        );
        assert!(q.is_empty());
        assert_eq!(q.bytes(), 0);
    }

    #[test]
    fn a_quiet_client_gets_room_at_the_flooding_clients_expense() {
        let now = Instant::now();
        let mut q = queue(8, 1 << 20);
        // A fills the queue, then overflows it: it is held and its writes are dropped.
        assert_eq!(offer(&mut q, A, 0, 8, 10, now), 8);
        assert_eq!(q.make_room(A, 10, now), Room::No { hold_started: true });
        assert_eq!(
            q.make_room(A, 10, now),
            Room::No {
                hold_started: false
            }
        );
        assert!(q.is_held(A, now));
        // B's writes still wait, each in place of A's newest (A is already held).
        assert_eq!(
            q.make_room(B, 10, now),
            Room::Yes {
                evicted: 1,
                holds_started: 0
            }
        );
        q.push(B, (B, 0), 10);
        assert_eq!(offer(&mut q, B, 1, 2, 10, now), 2);
        assert_eq!((q.len_of(A), q.len_of(B)), (5, 3));
        // B's writes are among the first sent, A's oldest are kept.
        let sent = drain(&mut q);
        assert_eq!(
            &sent[..6],
            &[(A, 0), (B, 0), (A, 1), (B, 1), (A, 2), (B, 2)]
        );
        assert_eq!(&sent[6..], &[(A, 3), (A, 4)]);
        assert!(!q.is_held(B, now));
    }

    #[test]
    fn a_flooder_that_is_not_held_yet_is_held_when_it_is_made_to_pay() {
        let now = Instant::now();
        let mut q = queue(4, 1 << 20);
        assert_eq!(offer(&mut q, A, 0, 4, 10, now), 4);
        assert_eq!(
            q.make_room(B, 10, now),
            Room::Yes {
                evicted: 1,
                holds_started: 1
            }
        );
        q.push(B, (B, 0), 10);
        assert!(q.is_held(A, now));
        assert_eq!(
            q.make_room(A, 10, now),
            Room::No {
                hold_started: false
            }
        );
    }

    #[test]
    fn clients_holding_equal_shares_do_not_take_from_each_other() {
        let now = Instant::now();
        let mut q = queue(4, 1 << 20);
        offer(&mut q, A, 0, 2, 10, now);
        offer(&mut q, B, 0, 2, 10, now);
        assert_eq!(q.make_room(B, 10, now), Room::No { hold_started: true });
        assert_eq!((q.len_of(A), q.len_of(B)), (2, 2));
        // A third client with nothing waiting still gets in, from one of them.
        assert_eq!(offer(&mut q, C, 0, 1, 10, now), 1);
        assert_eq!(q.len(), 4);
        assert_eq!(q.len_of(C), 1);
    }

    #[test]
    fn bytes_count_as_much_as_entries() {
        let now = Instant::now();
        let mut q = queue(100, 1000);
        // A holds few writes but most of the bytes, B more writes of few bytes.
        assert_eq!(offer(&mut q, A, 0, 2, 400, now), 2);
        assert_eq!(offer(&mut q, B, 0, 5, 10, now), 5);
        // C's write does not fit the bytes: it takes the place of A's newest, not of B's.
        assert_eq!(offer(&mut q, C, 0, 1, 200, now), 1);
        assert_eq!((q.len_of(A), q.len_of(B), q.len_of(C)), (1, 5, 1));
        assert_eq!(q.bytes(), 650);
        // A single write larger than the bound waits in an empty queue only.
        let mut empty = queue(100, 1000);
        assert_eq!(offer(&mut empty, C, 0, 2, 5000, now), 1);
    }

    #[test]
    fn nothing_is_dropped_for_a_write_that_still_would_not_fit() {
        let now = Instant::now();
        let mut q = queue(100, 1000);
        offer(&mut q, A, 0, 4, 200, now);
        offer(&mut q, B, 0, 1, 190, now);
        // C's 500 bytes: dropping A's newest two would leave A no heavier than C, and the
        // write would still not fit; so nothing of A's goes, A is not held, C is.
        assert_eq!(q.make_room(C, 500, now), Room::No { hold_started: true });
        assert_eq!((q.len_of(A), q.len_of(B), q.bytes()), (4, 1, 990));
        assert!(!q.is_held(A, now));
        assert!(q.is_held(C, now));
        // A's writes are still in their order.
        assert_eq!(drain(&mut q), vec![(A, 0), (B, 0), (A, 1), (A, 2), (A, 3)]);
    }

    #[test]
    fn a_hold_ends() {
        let start = Instant::now();
        let mut q = WaitingWrites::new(2, 1 << 20, Duration::from_millis(200));
        assert_eq!(offer(&mut q, A, 0, 3, 10, start), 2);
        assert!(q.is_held(A, start));
        let later = start + Duration::from_millis(200);
        assert!(!q.is_held(A, later));
        q.pop();
        assert_eq!(offer(&mut q, A, 3, 1, 10, later), 1);
        // A zero hold never holds.
        q.set_hold(Duration::ZERO);
        assert_eq!(q.make_room(A, 10, later), Room::No { hold_started: true });
        assert!(!q.is_held(A, later));
    }

    #[test]
    fn removing_writes_keeps_the_counts_and_turns_right() {
        let now = Instant::now();
        let mut q = queue(100, 1 << 20);
        offer(&mut q, A, 0, 4, 10, now);
        offer(&mut q, B, 0, 2, 20, now);
        offer(&mut q, C, 0, 1, 30, now);
        assert_eq!(q.retain_of(A, |(_, i)| i % 2 == 0), 2);
        assert_eq!(q.remove_client(B), 2);
        assert_eq!(q.retain_of(B, |_| false), 0);
        assert_eq!((q.len(), q.bytes()), (3, 50));
        assert_eq!(drain(&mut q), vec![(A, 0), (C, 0), (A, 2)]);
        offer(&mut q, A, 0, 3, 10, now);
        assert_eq!(q.clear(), 3);
        assert_eq!((q.len(), q.bytes(), q.front()), (0, 0, None));
    }

    #[test]
    fn a_client_whose_writes_were_all_removed_has_one_turn_when_it_returns() {
        let now = Instant::now();
        let mut q = WaitingWrites::new(2, 1 << 20, Duration::ZERO);
        offer(&mut q, A, 0, 1, 10, now);
        offer(&mut q, B, 0, 1, 10, now);
        // C's write is refused (with it, C would hold as much as each of them); then the
        // writes of A and B are removed, and A comes back.
        assert_eq!(offer(&mut q, C, 0, 1, 100, now), 0);
        assert_eq!(q.retain_of(A, |_| false) + q.retain_of(B, |_| false), 2);
        assert!(q.is_empty());
        offer(&mut q, A, 1, 2, 10, now);
        assert_eq!(drain(&mut q), vec![(A, 1), (A, 2)]);
        offer(&mut q, B, 1, 1, 10, now);
        offer(&mut q, A, 3, 1, 10, now);
        assert_eq!(drain(&mut q), vec![(B, 1), (A, 3)]);
    }

    #[test]
    fn an_emptied_client_keeps_one_turn() {
        let now = Instant::now();
        let mut q = queue(100, 1 << 20);
        offer(&mut q, A, 0, 3, 10, now);
        offer(&mut q, B, 0, 1, 10, now);
        // B's only write goes (its entry stays in the turns, empty); B returns with three.
        assert_eq!(q.retain_of(B, |_| false), 1);
        offer(&mut q, B, 1, 3, 10, now);
        // One turn each, alternating: a second turn of B would put two of its writes in a
        // row.
        assert_eq!(
            drain(&mut q),
            vec![(A, 0), (B, 1), (A, 1), (B, 2), (A, 2), (B, 3)]
        );
        // The same after an eviction emptied it (only bytes can: a client holding one large
        // write for a small one).
        let mut q = queue(100, 1000);
        offer(&mut q, A, 0, 1, 900, now);
        offer(&mut q, B, 0, 3, 10, now);
        assert_eq!(offer(&mut q, C, 0, 1, 100, now), 1);
        assert_eq!(q.len_of(A), 0);
        q.push(A, (A, 1), 10);
        q.push(A, (A, 2), 10);
        q.push(A, (A, 3), 10);
        assert_eq!(
            drain(&mut q),
            vec![(A, 1), (B, 0), (C, 0), (A, 2), (B, 1), (A, 3), (B, 2)]
        );
    }

    #[test]
    fn ended_holds_are_forgotten() {
        let start = Instant::now();
        let mut q = WaitingWrites::new(1, 1 << 20, Duration::from_millis(1));
        q.push(C, (C, 0), 10);
        // A thousand clients overflow the full queue one after the other, each held 1 ms.
        for i in 1..=1000u32 {
            let client = ClientKey(i.to_be_bytes());
            let now = start + Duration::from_millis(u64::from(i) * 2);
            assert_eq!(
                q.make_room(client, 10, now),
                Room::No { hold_started: true }
            );
        }
        assert!(q.holds.len() <= 128, "{} holds kept", q.holds.len());
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        #[derive(Debug, Clone)]
        enum Step {
            Offer { client: u8, weight: usize },
            Pop,
            DropOdd { client: u8 },
            Remove { client: u8 },
            Clear,
            Later,
        }

        fn step() -> impl Strategy<Value = Step> {
            prop_oneof![
                6 => (0u8..6, 1usize..400).prop_map(|(client, weight)| Step::Offer { client, weight }),
                3 => Just(Step::Pop),
                1 => (0u8..6).prop_map(|client| Step::DropOdd { client }),
                1 => (0u8..6).prop_map(|client| Step::Remove { client }),
                1 => Just(Step::Clear),
                1 => Just(Step::Later),
            ]
        }

        proptest! {
            /// Whatever happens: the counts and bytes are the sum of what waits, the bounds
            /// hold (but for one write alone), every write offered is sent, dropped, evicted
            /// or refused exactly once, each client's writes are sent in their order, a
            /// refusal changes nothing but its client's hold, and a client is evicted from
            /// only for a write of a client that then holds less than it did.
            #[test]
            fn the_queue_keeps_its_promises(steps in proptest::collection::vec(step(), 1..300)) {
                let start = Instant::now();
                let mut now = start;
                let mut q: WaitingWrites<(ClientKey, u32, usize)> =
                    WaitingWrites::new(8, 1000, Duration::from_millis(5));
                let mut next = [0u32; 6];
                let mut last_sent: HashMap<ClientKey, u32> = HashMap::new();
                let (mut offered, mut accounted) = (0usize, 0usize);
                for s in steps {
                    match s {
                        Step::Offer { client, weight } => {
                            let key = ClientKey([client, 0, 0, 1]);
                            let before: Vec<(ClientKey, usize)> = (0..6u8)
                                .map(|c| ClientKey([c, 0, 0, 1]))
                                .map(|k| (k, q.len_of(k)))
                                .collect();
                            let (len, bytes) = (q.len(), q.bytes());
                            let own_after = q.heaviness(q.len_of(key) + 1, {
                                let b = q.clients.get(&key).map_or(0, |c| c.bytes);
                                b + weight
                            });
                            let heaviness_before: HashMap<ClientKey, u128> = q
                                .clients
                                .iter()
                                .map(|(k, c)| (*k, q.heaviness(c.items.len(), c.bytes)))
                                .collect();
                            offered += 1;
                            let i = next[client as usize];
                            next[client as usize] += 1;
                            match q.make_room(key, weight, now) {
                                Room::Yes { evicted, .. } => {
                                    q.push(key, (key, i, weight), weight);
                                    accounted += evicted;
                                    for (k, n) in &before {
                                        let lost = n.saturating_sub(q.len_of(*k));
                                        if *k != key && lost > 0 {
                                            prop_assert!(
                                                heaviness_before[k] > own_after,
                                                "{k:?} paid for a heavier or equal client"
                                            );
                                        }
                                    }
                                }
                                Room::No { .. } => {
                                    accounted += 1;
                                    prop_assert_eq!((q.len(), q.bytes()), (len, bytes));
                                    for (k, n) in &before {
                                        prop_assert_eq!(q.len_of(*k), *n);
                                    }
                                }
                            }
                        }
                        Step::Pop => {
                            if let Some((k, i, _)) = q.pop() {
                                accounted += 1;
                                if let Some(prev) = last_sent.insert(k, i) {
                                    prop_assert!(prev < i, "{k:?} sent {i} after {prev}");
                                }
                            }
                        }
                        Step::DropOdd { client } => {
                            accounted +=
                                q.retain_of(ClientKey([client, 0, 0, 1]), |(_, i, _)| i % 2 == 0);
                        }
                        Step::Remove { client } => {
                            accounted += q.remove_client(ClientKey([client, 0, 0, 1]));
                        }
                        Step::Clear => accounted += q.clear(),
                        Step::Later => now += Duration::from_millis(3),
                    }
                    let mut len = 0;
                    let mut bytes = 0;
                    for c in q.clients.values() {
                        len += c.items.len();
                        bytes += c.items.iter().map(|(_, w)| w).sum::<usize>();
                        prop_assert_eq!(c.bytes, c.items.iter().map(|(_, w)| w).sum::<usize>());
                    }
                    prop_assert_eq!((len, bytes), (q.len(), q.bytes()));
                    prop_assert!(q.len() <= 8);
                    prop_assert!(q.len() <= 1 || q.bytes() <= 1000);
                    let mut seen = std::collections::HashSet::new();
                    prop_assert!(q.turns.iter().all(|k| seen.insert(*k)), "a client twice in the turns");
                    prop_assert_eq!(q.turns.len(), q.clients.len());
                    prop_assert_eq!(offered, accounted + q.len());
                }
            }
        }
    }
}
