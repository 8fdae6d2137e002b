//! The front-end's share of memory for its clients' object descriptions (the XML, reference
//! or binary bodies of CREATEs, kept to replay them to a new worker): a pool shared fairly
//! between source addresses and their sessions, as the session core's budget is
//! ([`xrce_common::session::budget`]). A CREATE whose description does not fit the client's
//! share while the pool is under pressure is refused with STATUS_ERR_RESOURCES. Nothing is
//! evicted (an object, once created, is the client's), so one source address never holds
//! more than half the pool: the other half stays for the others.

use std::collections::HashMap;

use xrce_common::session::budget::{Budget, Decision, OriginId};
use xrce_common::wire::{ClientKey, ObjectId};

#[derive(Debug, Default)]
struct ClientObjects {
    origin: OriginId,
    sizes: HashMap<ObjectId, usize>,
    held: usize,
}

/// Bytes of object descriptions held per client, within one pool.
#[derive(Debug)]
pub struct ObjectBudget {
    pool: Budget,
    clients: HashMap<ClientKey, ClientObjects>,
}

/// The origin of a client whose origin is not known (a session restored from the store
/// before its client was heard): a host of its own.
fn own_origin(client: ClientKey) -> OriginId {
    OriginId((1u128 << 127) | u128::from(u32::from_be_bytes(client.0)))
}

impl ObjectBudget {
    /// An empty pool of `bytes`.
    pub fn new(bytes: usize) -> Self {
        ObjectBudget {
            pool: Budget::new(bytes),
            clients: HashMap::new(),
        }
    }

    /// Bytes held in total, and the pool's size.
    pub fn held(&self) -> (usize, usize) {
        (self.pool.total(), self.pool.limit())
    }

    /// A client's session began at `origin`.
    pub fn client_created(&mut self, client: ClientKey, origin: OriginId) {
        self.client_deleted(client);
        self.pool.session_added(origin);
        self.clients.insert(
            client,
            ClientObjects {
                origin,
                ..ClientObjects::default()
            },
        );
    }

    /// A client's session ended: its descriptions are gone.
    pub fn client_deleted(&mut self, client: ClientKey) {
        if let Some(c) = self.clients.remove(&client) {
            self.pool.session_removed(c.origin, c.held);
        }
    }

    fn entry(&mut self, client: ClientKey) -> &mut ClientObjects {
        if !self.clients.contains_key(&client) {
            let origin = own_origin(client);
            self.pool.session_added(origin);
        }
        self.clients.entry(client).or_insert_with(|| ClientObjects {
            origin: own_origin(client),
            ..ClientObjects::default()
        })
    }

    /// Whether object `id` of `client` may be described by `size` bytes (replacing what
    /// the id held); if so, it is accounted.
    pub fn admit(&mut self, client: ClientKey, id: ObjectId, size: usize) -> bool {
        let c = self.entry(client);
        let (origin, held) = (c.origin, c.held);
        let old = c.sizes.get(&id).copied().unwrap_or(0);
        let extra = size.saturating_sub(old);
        if extra > 0
            && (self.pool.decide(origin, held, extra) != Decision::Grant
                || self.pool.held_by(origin).saturating_add(extra) > self.pool.limit() / 2)
        {
            return false;
        }
        self.set(client, id, size);
        true
    }

    /// Accounts a description without asking (objects restored from the store).
    pub fn set(&mut self, client: ClientKey, id: ObjectId, size: usize) {
        let c = self.entry(client);
        let old = c.sizes.insert(id, size).unwrap_or(0);
        let before = c.held;
        c.held = c.held.saturating_sub(old).saturating_add(size);
        let (origin, after) = (c.origin, c.held);
        self.pool.changed(origin, before, after);
    }

    /// Objects of a client were deleted.
    pub fn removed(&mut self, client: ClientKey, ids: &[ObjectId]) {
        let Some(c) = self.clients.get_mut(&client) else {
            return;
        };
        let before = c.held;
        for id in ids {
            if let Some(size) = c.sizes.remove(id) {
                c.held = c.held.saturating_sub(size);
            }
        }
        let (origin, after) = (c.origin, c.held);
        self.pool.changed(origin, before, after);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_host_cannot_take_the_pool_from_another() {
        let mut b = ObjectBudget::new(1 << 20);
        let attacker = OriginId(1);
        for i in 0..100u32 {
            let k = ClientKey(i.to_be_bytes());
            b.client_created(k, attacker);
            let mut n = 0;
            while b.admit(k, ObjectId([0, n]), 4096) {
                n += 1;
                if n == 255 {
                    break;
                }
            }
        }
        let (held, pool) = b.held();
        assert!(held <= pool);
        assert!(held <= pool / 2, "one address holds {held} of {pool}");
        let genuine = ClientKey([9, 9, 9, 9]);
        b.client_created(genuine, OriginId(2));
        for n in 0..64 {
            assert!(
                b.admit(genuine, ObjectId([1, n]), 4096),
                "object {n} refused"
            );
        }
        b.removed(
            genuine,
            &(2..64).map(|n| ObjectId([1, n])).collect::<Vec<_>>(),
        );
        // Deleting the attacker's sessions returns their room.
        for i in 0..100u32 {
            b.client_deleted(ClientKey(i.to_be_bytes()));
        }
        assert!(b.admit(genuine, ObjectId([0, 2]), 4096));
        b.removed(
            genuine,
            &[ObjectId([1, 0]), ObjectId([1, 1]), ObjectId([0, 2])],
        );
        assert_eq!(b.held().0, 0);
    }

    #[test]
    fn replacing_an_object_accounts_the_difference() {
        let mut b = ObjectBudget::new(1 << 20);
        let k = ClientKey([1, 2, 3, 4]);
        b.client_created(k, OriginId(1));
        assert!(b.admit(k, ObjectId([0, 1]), 1000));
        assert!(b.admit(k, ObjectId([0, 1]), 300));
        assert_eq!(b.held().0, 300);
        b.client_deleted(k);
        assert_eq!(b.held().0, 0);
    }
}
