//! Entities a restarted front-end takes back instead of having them re-created.
//!
//! When a front-end process is replaced (killed and restarted by the supervisor, or stopped
//! for an upgrade) while this worker keeps running, its successor takes the sessions over and
//! replays every client's objects, as it does to a new worker. Deleting the predecessor's DDS
//! entities and creating new ones would be visible in the DDS data space: a writer deleted
//! with samples its readers had not acknowledged yet loses them, a new reader misses what is
//! written before it matched, and every peer sees the endpoints leave and come back. So the
//! entities of a front-end that says hello again are offered for adoption: a replayed CREATE
//! of the same object with the same description takes the existing entity back as it is;
//! what the successor does not replay (a session it did not take over) is removed when it
//! says its replay is complete.

use std::collections::{HashMap, HashSet};

use xrce_common::wire::{ClientKey, ObjectId};

/// An entity: its front-end, client and object id.
pub type EntityKey = (u32, ClientKey, ObjectId);

/// What an entity was created from; a replayed CREATE with the same adopts it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Origin {
    /// The CREATE's object representation, as it came.
    pub body: Box<[u8]>,
    /// Its byte order.
    pub little_endian: bool,
}

impl Origin {
    /// The origin of an entity created from `body` in that byte order.
    pub fn new(body: &[u8], little_endian: bool) -> Self {
        Origin {
            body: body.into(),
            little_endian,
        }
    }
}

/// Entities offered to front-ends that came back.
#[derive(Debug, Default)]
pub struct Adoption {
    offered: HashSet<EntityKey>,
    /// Entities taken back per front-end since its offer.
    claimed: HashMap<u32, usize>,
}

impl Adoption {
    /// Offers `keys` (entities of front-end `frontend`) to that front-end's successor; an
    /// earlier offer to it that is still open is replaced.
    pub fn offer(&mut self, frontend: u32, keys: impl IntoIterator<Item = EntityKey>) {
        self.forget(frontend);
        self.offered.extend(keys);
    }

    /// Whether `key` was on offer (it is not any more).
    pub fn claim(&mut self, key: &EntityKey) -> bool {
        self.offered.remove(key)
    }

    /// Counts an entity of `frontend` taken back.
    pub fn adopted(&mut self, frontend: u32) {
        *self.claimed.entry(frontend).or_default() += 1;
    }

    /// Closes the offer to `frontend`: the entities it left unclaimed, and how many it took
    /// back.
    pub fn finish(&mut self, frontend: u32) -> (Vec<EntityKey>, usize) {
        let left: Vec<EntityKey> = self
            .offered
            .iter()
            .filter(|k| k.0 == frontend)
            .copied()
            .collect();
        for k in &left {
            self.offered.remove(k);
        }
        (left, self.claimed.remove(&frontend).unwrap_or(0))
    }

    /// Withdraws whatever is on offer to `frontend`.
    pub fn forget(&mut self, frontend: u32) {
        self.offered.retain(|k| k.0 != frontend);
        self.claimed.remove(&frontend);
    }

    /// How many entities are on offer.
    pub fn len(&self) -> usize {
        self.offered.len()
    }

    /// Whether none is.
    pub fn is_empty(&self) -> bool {
        self.offered.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(fe: u32, n: u16) -> EntityKey {
        (fe, ClientKey([1, 2, 3, 4]), ObjectId::new(n, 1))
    }

    #[test]
    fn an_offer_is_claimed_once_and_what_is_left_is_handed_back() {
        let mut a = Adoption::default();
        a.offer(1, [key(1, 1), key(1, 2), key(1, 3)]);
        a.offer(2, [key(2, 1)]);
        assert!(a.claim(&key(1, 2)));
        a.adopted(1);
        assert!(!a.claim(&key(1, 2)), "claimed twice");
        let (mut left, adopted) = a.finish(1);
        left.sort();
        assert_eq!(left, vec![key(1, 1), key(1, 3)]);
        assert_eq!(adopted, 1);
        assert_eq!(a.finish(1), (vec![], 0));
        assert_eq!(a.len(), 1, "another front-end's offer is untouched");
    }

    #[test]
    fn a_new_offer_replaces_the_open_one() {
        let mut a = Adoption::default();
        a.offer(1, [key(1, 1), key(1, 2)]);
        a.offer(1, [key(1, 3)]);
        assert!(!a.claim(&key(1, 1)));
        assert!(a.claim(&key(1, 3)));
        a.offer(1, [key(1, 4)]);
        a.forget(1);
        assert!(a.is_empty());
    }

    #[test]
    fn origins_differ_by_bytes_and_by_byte_order() {
        let a = Origin::new(&[1, 2, 3], true);
        assert_eq!(a, Origin::new(&[1, 2, 3], true));
        assert_ne!(a, Origin::new(&[1, 2, 3], false));
        assert_ne!(a, Origin::new(&[1, 2], true));
    }
}
