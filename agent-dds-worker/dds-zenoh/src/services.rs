//! What joins the two halves of a service on Zenoh: a requester's querier to the reader its
//! replies go to, and a replier's queryable to the writer whose replies answer its queries;
//! with the bounds a remote peer or a client meets there.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use super::inbox::Inbox;

/// Requests a replier keeps waiting for their reply (the oldest are answered with nothing).
pub(super) const PENDING_QUERIES_MAX: usize = 4096;

/// Most bytes of request payloads a replier keeps waiting for their reply.
pub(super) const PENDING_QUERY_BYTES_MAX: usize = 64 << 20;

/// Most requests of one requester waiting for their replies in Zenoh (each lives until its
/// replies are in or it times out).
pub(super) const IN_FLIGHT_MAX: usize = 4096;

/// A service's writer waiting for its reader (the worker makes a requester's or replier's
/// writer, then at once its reader).
pub(super) struct PendingService {
    pub(super) domain: u16,
    pub(super) service: String,
    pub(super) requester: bool,
    pub(super) link: Arc<ServiceLink>,
}

/// The shared state of one requester or replier.
#[derive(Default)]
pub(super) struct ServiceLink {
    /// A requester's reader, where replies go.
    pub(super) replies: Mutex<Option<Arc<Inbox>>>,
    /// A replier's queries waiting for their reply.
    pub(super) queries: Mutex<PendingQueries>,
    /// A requester's requests in flight.
    in_flight: AtomicUsize,
}

/// Counts a request in flight while it lives (moved into its reply callback, which Zenoh
/// drops when the query ends).
pub(super) struct InFlight(Arc<ServiceLink>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::Relaxed);
    }
}

impl ServiceLink {
    /// A new request in flight, unless [`IN_FLIGHT_MAX`] are.
    pub(super) fn start_request(self: &Arc<Self>) -> Option<InFlight> {
        let n = self.in_flight.fetch_add(1, Ordering::Relaxed);
        let guard = InFlight(self.clone());
        (n < IN_FLIGHT_MAX).then_some(guard)
    }
}

/// A request's identity: the client's GID and its sequence number.
pub(super) type RequestKey = ([u8; 16], i64);

/// Queries waiting for their reply, oldest first, bounded in number and bytes.
pub(super) struct PendingQueries<Q = zenoh::query::Query> {
    by_id: HashMap<RequestKey, (u64, usize, Q)>,
    order: VecDeque<(RequestKey, u64)>,
    next: u64,
    bytes: usize,
}

impl<Q> Default for PendingQueries<Q> {
    fn default() -> Self {
        PendingQueries {
            by_id: HashMap::new(),
            order: VecDeque::new(),
            next: 0,
            bytes: 0,
        }
    }
}

impl<Q> PendingQueries<Q> {
    /// Keeps `query` (of `bytes` payload) for its reply; returns how many older ones were
    /// given up to stay within the bounds (dropping a query ends it for its client).
    pub(super) fn insert(&mut self, id: RequestKey, bytes: usize, query: Q) -> usize {
        self.next += 1;
        if let Some((_, old_bytes, _)) = self.by_id.insert(id, (self.next, bytes, query)) {
            // The same request again: the newer query replaces it.
            self.bytes -= old_bytes;
        }
        self.bytes += bytes;
        self.order.push_back((id, self.next));
        let mut evicted = 0;
        while self.by_id.len() > PENDING_QUERIES_MAX || self.bytes > PENDING_QUERY_BYTES_MAX {
            let Some((old, generation)) = self.order.pop_front() else {
                break;
            };
            if self
                .by_id
                .get(&old)
                .is_some_and(|(g, _, _)| *g == generation)
            {
                if let Some((_, b, _)) = self.by_id.remove(&old) {
                    self.bytes -= b;
                    evicted += 1;
                }
            }
        }
        // Answered or replaced ones leave stale entries in `order`: forget them now and then.
        if self.order.len() > 2 * self.by_id.len() + 64 {
            let by_id = &self.by_id;
            self.order
                .retain(|(k, g)| by_id.get(k).is_some_and(|(live, _, _)| live == g));
        }
        evicted
    }

    /// The query of a request, to answer it (it is no longer waiting then).
    pub(super) fn take(&mut self, id: &RequestKey) -> Option<Q> {
        let (_, bytes, query) = self.by_id.remove(id)?;
        self.bytes -= bytes;
        Some(query)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn waiting_queries_are_bounded_and_a_repeat_does_not_lose_the_newer_one() {
        let mut p: PendingQueries<u32> = PendingQueries::default();
        let id = |n: i64| ([1; 16], n);
        for n in 0..PENDING_QUERIES_MAX as i64 {
            assert_eq!(p.insert(id(n), 10, n as u32), 0);
        }
        assert_eq!(p.insert(id(-1), 10, 99), 1, "the oldest given up");
        assert_eq!(p.take(&id(0)), None);
        assert_eq!(p.take(&id(1)), Some(1));
        // Answered, then the same request again: the old order entry must not evict it.
        assert_eq!(p.insert(id(1), 10, 7), 0);
        for n in 0..2 {
            p.insert(([2; 16], n), 10, 0);
        }
        assert_eq!(p.take(&id(1)), Some(7));
        // Bytes: one large request makes room by giving up old ones.
        let mut b: PendingQueries<u32> = PendingQueries::default();
        b.insert(id(1), PENDING_QUERY_BYTES_MAX / 2, 1);
        b.insert(id(2), PENDING_QUERY_BYTES_MAX / 2, 2);
        assert_eq!(b.insert(id(3), 1, 3), 1);
        assert_eq!(b.take(&id(1)), None);
        assert_eq!(b.take(&id(3)), Some(3));
    }

    #[test]
    fn requests_in_flight_are_bounded_and_counted_down_when_they_end() {
        let link = Arc::new(ServiceLink::default());
        let guards: Vec<InFlight> = (0..IN_FLIGHT_MAX)
            .map(|_| link.start_request().expect("room"))
            .collect();
        assert!(link.start_request().is_none());
        drop(guards);
        assert!(link.start_request().is_some());
    }
}
