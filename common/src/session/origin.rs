//! Which client write a sample came from, and the recent ones a read delivered.
//!
//! A worker that dies after it handed a sample to a subscriber's front-end, and before the
//! publisher's front-end heard that the write was taken, leaves that write unacknowledged:
//! the publisher's front-end resends it to the new worker, whose new DDS writer (another
//! GUID) publishes it again. The DDS identity cannot tell the two apart; the write's origin
//! can. The publisher's front-end numbers its writes, a resend keeps the number of the first
//! send, and the worker tags every sample its own writers wrote with that origin. A
//! subscriber's front-end remembers the origins its reads delivered lately
//! ([`DeliveredOrigins`]) and drops a resent sample a read already delivered.

use std::collections::{HashSet, VecDeque};

use crate::wire::{ClientKey, ObjectId};

/// One sample of one client write, as the front-end process that handed the write over
/// numbered it. Never issued twice: a process (its id and incarnation) numbers its
/// operations from 1 and a resend keeps its first number.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct WriteOrigin {
    /// The front-end that handed the write over.
    pub frontend: u32,
    /// Which process of it (its incarnation).
    pub incarnation: u16,
    /// The operation number the write had when that process first sent it.
    pub write: u64,
    /// Which sample of the write (a WRITE_DATA in a sequence format carries several).
    pub index: u32,
}

/// Deliveries a front-end remembers, over all its reads. A resent write reaches the new
/// worker within seconds of the crash, and what it repeats was delivered before the crash
/// while its acknowledgement lagged: a few milliseconds after its readers here took it
/// (acknowledgements are polled every 2 ms), or a whole backlog when a worker that keeps
/// dying had a backlog to drain (a crash loop: 4,096 left 1,480 repeats in one soak,
/// 16,384 none in two). At 10,000 reliable samples a second this is the last 1.6 s. A
/// resent sample delivered before that is delivered again: a repeat, never a loss.
pub const MAX_REMEMBERED_DELIVERIES: usize = 16_384;

/// One delivery: which client's read (by its reader) got a sample of which write, laid out
/// in 24 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct Delivery {
    write: u64,
    frontend: u32,
    index: u32,
    client: ClientKey,
    incarnation: u16,
    reader: ObjectId,
}

impl Delivery {
    fn new(client: ClientKey, reader: ObjectId, o: &WriteOrigin) -> Self {
        Delivery {
            write: o.write,
            frontend: o.frontend,
            index: o.index,
            client,
            incarnation: o.incarnation,
            reader,
        }
    }
}

/// The origins of the samples a front-end's reads delivered last, at most
/// [`MAX_REMEMBERED_DELIVERIES`] over all of them (about 1.2 MiB with the index), so that a
/// client that makes many reads makes the front-end hold no more. Kept in memory only: a
/// subscriber's front-end that dies with the worker may deliver a resent sample again.
#[derive(Debug, Clone, Default)]
pub struct DeliveredOrigins {
    /// Oldest first.
    order: VecDeque<Delivery>,
    known: HashSet<Delivery>,
}

impl DeliveredOrigins {
    /// Records that `client`'s read on `reader` delivered a sample of `origin`, forgetting
    /// the oldest delivery beyond the bound.
    pub fn record(&mut self, client: ClientKey, reader: ObjectId, origin: WriteOrigin) {
        let d = Delivery::new(client, reader, &origin);
        if !self.known.insert(d) {
            return;
        }
        if self.order.len() >= MAX_REMEMBERED_DELIVERIES {
            if let Some(old) = self.order.pop_front() {
                self.known.remove(&old);
            }
        }
        self.order.push_back(d);
    }

    /// Whether `client`'s read on `reader` delivered a sample of `origin` lately.
    pub fn contains(&self, client: ClientKey, reader: ObjectId, origin: &WriteOrigin) -> bool {
        self.known.contains(&Delivery::new(client, reader, origin))
    }

    /// Forgets `client`'s deliveries (its session ended, or began again).
    pub fn forget_client(&mut self, client: ClientKey) {
        self.forget(|d| d.client == client);
    }

    /// Forgets the deliveries to `client`'s `objects` (deleted, or replaced: a reader made
    /// again under the same id is another reader, which may get those samples from DDS).
    pub fn forget_objects(&mut self, client: ClientKey, objects: &[ObjectId]) {
        self.forget(|d| d.client == client && objects.contains(&d.reader));
    }

    fn forget(&mut self, doomed: impl Fn(&Delivery) -> bool) {
        if self.order.iter().any(&doomed) {
            self.order.retain(|d| !doomed(d));
            self.known.retain(|d| !doomed(d));
        }
    }

    /// Deliveries remembered.
    pub fn len(&self) -> usize {
        self.order.len()
    }

    /// Whether none is.
    pub fn is_empty(&self) -> bool {
        self.order.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CLIENT: ClientKey = ClientKey([1, 2, 3, 4]);
    const READER: ObjectId = ObjectId::new(1, crate::wire::object_kind::DATAREADER);

    fn origin(write: u64, index: u32) -> WriteOrigin {
        WriteOrigin {
            frontend: 3,
            incarnation: 1,
            write,
            index,
        }
    }

    #[test]
    fn a_delivery_takes_24_bytes() {
        assert_eq!(std::mem::size_of::<Delivery>(), 24);
    }

    #[test]
    fn reads_know_the_origins_they_delivered_last_and_the_oldest_are_forgotten() {
        let mut d = DeliveredOrigins::default();
        assert!(d.is_empty());
        d.record(CLIENT, READER, origin(7, 0));
        d.record(CLIENT, READER, origin(7, 1));
        d.record(CLIENT, READER, origin(7, 1));
        assert_eq!(d.len(), 2, "a delivery is remembered once");
        assert!(d.contains(CLIENT, READER, &origin(7, 0)));
        assert!(d.contains(CLIENT, READER, &origin(7, 1)));
        // Another sample of the write, another write, another process, another read.
        assert!(!d.contains(CLIENT, READER, &origin(7, 2)));
        assert!(!d.contains(CLIENT, READER, &origin(8, 0)));
        let other_process = WriteOrigin {
            incarnation: 2,
            ..origin(7, 0)
        };
        assert!(!d.contains(CLIENT, READER, &other_process));
        let other_reader = ObjectId::new(2, crate::wire::object_kind::DATAREADER);
        assert!(!d.contains(CLIENT, other_reader, &origin(7, 0)));
        d.record(CLIENT, other_reader, origin(7, 0));
        // Full, nothing forgotten yet; one more and the oldest goes.
        for w in 100..100 + MAX_REMEMBERED_DELIVERIES as u64 - 3 {
            d.record(ClientKey([9; 4]), READER, origin(w, 0));
        }
        assert_eq!(d.len(), MAX_REMEMBERED_DELIVERIES);
        assert!(d.contains(CLIENT, READER, &origin(7, 0)));
        d.record(ClientKey([9; 4]), READER, origin(99, 0));
        assert_eq!(d.len(), MAX_REMEMBERED_DELIVERIES);
        assert!(
            !d.contains(CLIENT, READER, &origin(7, 0)),
            "the oldest forgotten"
        );
        assert!(d.contains(CLIENT, READER, &origin(7, 1)));
        // The reader deleted: its deliveries go, the other reader's stay.
        d.forget_objects(CLIENT, &[READER]);
        assert_eq!(d.len(), MAX_REMEMBERED_DELIVERIES - 1);
        assert!(!d.contains(CLIENT, READER, &origin(7, 1)));
        assert!(d.contains(CLIENT, other_reader, &origin(7, 0)));
        // The session ended: the rest of the client's go.
        d.forget_client(CLIENT);
        assert_eq!(d.len(), MAX_REMEMBERED_DELIVERIES - 2);
        assert!(!d.contains(CLIENT, other_reader, &origin(7, 0)));
        assert!(d.contains(ClientKey([9; 4]), READER, &origin(99, 0)));
    }
}
