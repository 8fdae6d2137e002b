//! A replay that crashed the worker is not replayed again.
//!
//! A new worker gets every front-end's objects again (the replay between the front-end's
//! hello and its `ReplayDone`). If one client's objects make the worker crash (a backend
//! that aborts on some description), replaying them to every new worker would keep the
//! worker crashing long after that client is gone. So while a front-end replays, the client
//! whose objects are being created is written down in the private instance directory
//! (by the link: a file `replaying-<front-end>`, rewritten when the client changes, removed at
//! `ReplayDone`);
//! a worker that finds such a file at its start refuses that client's replayed objects
//! (STATUS_ERR_RESOURCES with [`xrce_ipc::REPLAY_REFUSED`], counted as `replay_crash`,
//! logged), and the front-end ends the client's session: the client finds it gone and
//! creates it again. Everyone else is replayed as usual.

use std::collections::{HashMap, HashSet};

use xrce_common::wire::ClientKey;

/// What the worker knows about replays that crashed it, and the replays under way. It
/// decides; the link ([`super::WorkerLink::mark_replay`]) keeps the marks.
#[derive(Debug, Default)]
pub(crate) struct ReplayGuard {
    /// Clients whose replay was under way when the last worker died: (front-end, client).
    suspects: HashSet<(u32, ClientKey)>,
    /// Front-ends replaying now, and the client last written down for each.
    replaying: HashMap<u32, Option<ClientKey>>,
}

/// What a replay's next object means for the marks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Screened {
    /// Its client's replay crashed the last worker: refused.
    Refused,
    /// Created as usual; `mark`: the replay moved on to this client, to be written down
    /// first.
    Admitted {
        /// The client to write down.
        mark: Option<ClientKey>,
    },
}

impl ReplayGuard {
    /// A guard refusing the replays of `suspects` (those under way when the last worker
    /// died).
    pub(crate) fn new(suspects: HashSet<(u32, ClientKey)>) -> Self {
        for (fe, client) in &suspects {
            tracing::warn!(frontend = fe, client = %client, "the last worker died while replaying this client's objects: they are not replayed to this one");
        }
        ReplayGuard {
            suspects,
            replaying: HashMap::new(),
        }
    }

    /// Front-end `fe` begins a replay (its hello).
    pub(crate) fn begin(&mut self, fe: u32) {
        self.replaying.insert(fe, None);
    }

    /// Front-end `fe`'s replay is over (or the front-end is gone): its suspects were refused
    /// once, which ended their sessions; what they create from now on is theirs again.
    /// Whether a mark of `fe`'s stands (to be removed).
    pub(crate) fn end(&mut self, fe: u32) -> bool {
        self.suspects.retain(|(f, _)| *f != fe);
        matches!(self.replaying.remove(&fe), Some(Some(_)))
    }

    /// The worker stops of its own accord: the replays under way did not crash it. The
    /// front-ends whose marks are to be removed.
    pub(crate) fn stopping(&mut self) -> Vec<u32> {
        let under_way: Vec<u32> = self.replaying.keys().copied().collect();
        under_way.into_iter().filter(|fe| self.end(*fe)).collect()
    }

    /// An object of `client` is about to be created by `fe`: refused if its replay crashed
    /// the last worker; otherwise, during a replay, a change of client is to be written down
    /// first.
    pub(crate) fn screen(&mut self, fe: u32, client: ClientKey) -> Screened {
        let Some(current) = self.replaying.get_mut(&fe) else {
            return Screened::Admitted { mark: None };
        };
        if self.suspects.contains(&(fe, client)) {
            return Screened::Refused;
        }
        if *current == Some(client) {
            return Screened::Admitted { mark: None };
        }
        *current = Some(client);
        Screened::Admitted { mark: Some(client) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_client_whose_replay_was_under_way_is_refused_by_the_next_worker_only_in_replays() {
        let (a, b) = (ClientKey(*b"AAAA"), ClientKey(*b"BBBB"));
        let mut first = ReplayGuard::default();
        assert_eq!(
            first.screen(3, a),
            Screened::Admitted { mark: None },
            "not in a replay"
        );
        first.begin(3);
        assert_eq!(first.screen(3, a), Screened::Admitted { mark: Some(a) });
        assert_eq!(
            first.screen(3, a),
            Screened::Admitted { mark: None },
            "written once"
        );
        assert_eq!(first.screen(3, b), Screened::Admitted { mark: Some(b) });
        // The worker dies here, while b's objects are being replayed: the next one finds b.
        let mut second = ReplayGuard::new(HashSet::from([(3, b)]));
        second.begin(3);
        assert_eq!(
            second.screen(3, a),
            Screened::Admitted { mark: Some(a) },
            "a is replayed"
        );
        assert_eq!(
            second.screen(3, b),
            Screened::Refused,
            "b's replay crashed the last worker"
        );
        assert!(
            matches!(second.screen(4, b), Screened::Admitted { .. }),
            "another front-end's b is another client"
        );
        assert!(second.end(3), "a's mark is removed");
        assert_eq!(
            second.screen(3, b),
            Screened::Admitted { mark: None },
            "outside a replay, b creates as usual"
        );
        // A replay that ended leaves nothing to remove at the stop.
        assert!(second.stopping().is_empty());
    }
}
