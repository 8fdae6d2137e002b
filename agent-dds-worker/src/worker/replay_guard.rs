//! A replay that crashed two workers in a row is not replayed again.
//!
//! A new worker gets every front-end's objects again (the replay between the front-end's
//! hello and its `ReplayDone`). If one client's objects make the worker crash (a backend
//! that aborts on some description), replaying them to every new worker would keep the
//! worker crashing long after that client is gone. So while a front-end replays, the client
//! whose objects are being created is written down in the private instance directory
//! (by the link: a file `replaying-<front-end>`, rewritten when the client changes, removed at
//! `ReplayDone`), with how many workers in a row died replaying it, this one included.
//! A worker that finds such a mark at its start replays that client once more if one worker
//! died on it: a worker killed from outside (an operator, the memory limit, a crash loop)
//! dies wherever its replay stands, and ending that client's session lost the writes its
//! client had sent meanwhile (50 in a crash-loop soak). Objects that crash the worker crash
//! the next one too: then it refuses that client's replayed objects (STATUS_ERR_RESOURCES
//! with [`xrce_ipc::REPLAY_REFUSED`], counted as `replay_crash`, logged), and the front-end
//! ends the client's session: the client finds it gone and creates it again. Everyone else
//! is replayed as usual.

use std::collections::HashMap;

use xrce_common::wire::ClientKey;

/// Workers in a row that died replaying a client before its objects are refused.
pub(crate) const REPLAY_DEATHS_REFUSED: u8 = 2;

/// A replay mark: the client whose objects a front-end is replaying, and how many workers
/// in a row will have died replaying them if this one dies now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReplayMark {
    /// The client.
    pub client: ClientKey,
    /// Workers in a row dead while replaying it, this one included.
    pub deaths: u8,
}

/// The marks a worker finds at its start: for each (front-end, client) whose replay was
/// under way when the last worker died, how many workers in a row died replaying it.
pub type CrashedReplays = HashMap<(u32, ClientKey), u8>;

/// What the worker knows about replays that crashed it, and the replays under way. It
/// decides; the link ([`super::WorkerLink::mark_replay`]) keeps the marks.
#[derive(Debug, Default)]
pub(crate) struct ReplayGuard {
    /// Clients whose replay was under way when the last worker died: (front-end, client),
    /// with the workers in a row that died replaying them.
    suspects: CrashedReplays,
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
        mark: Option<ReplayMark>,
    },
}

impl ReplayGuard {
    /// A guard refusing the replays of `suspects` (those under way when the last worker
    /// died) that [`REPLAY_DEATHS_REFUSED`] workers in a row died on.
    pub(crate) fn new(suspects: CrashedReplays) -> Self {
        for ((fe, client), deaths) in &suspects {
            if *deaths >= REPLAY_DEATHS_REFUSED {
                tracing::warn!(frontend = fe, client = %client, deaths, "workers in a row died while replaying this client's objects: they are not replayed to this one");
            } else {
                tracing::info!(frontend = fe, client = %client, "the last worker died while replaying this client's objects: they are replayed once more");
            }
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
        self.suspects.retain(|(f, _), _| *f != fe);
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
        let died = self.suspects.get(&(fe, client)).copied().unwrap_or(0);
        if died >= REPLAY_DEATHS_REFUSED {
            return Screened::Refused;
        }
        if *current == Some(client) {
            return Screened::Admitted { mark: None };
        }
        *current = Some(client);
        Screened::Admitted {
            mark: Some(ReplayMark {
                client,
                deaths: died + 1,
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mark(client: ClientKey, deaths: u8) -> Screened {
        Screened::Admitted {
            mark: Some(ReplayMark { client, deaths }),
        }
    }

    #[test]
    fn a_client_two_workers_died_replaying_is_refused_by_the_next_only_in_replays() {
        let (a, b) = (ClientKey(*b"AAAA"), ClientKey(*b"BBBB"));
        let mut first = ReplayGuard::default();
        assert_eq!(
            first.screen(3, a),
            Screened::Admitted { mark: None },
            "not in a replay"
        );
        first.begin(3);
        assert_eq!(first.screen(3, a), mark(a, 1));
        assert_eq!(
            first.screen(3, a),
            Screened::Admitted { mark: None },
            "written once"
        );
        assert_eq!(first.screen(3, b), mark(b, 1));
        // The worker dies here, while b's objects are being replayed: the next one replays
        // b once more, marked as the second death if it dies too.
        let mut second = ReplayGuard::new(HashMap::from([((3, b), 1)]));
        second.begin(3);
        assert_eq!(second.screen(3, a), mark(a, 1), "a is replayed");
        assert_eq!(second.screen(3, b), mark(b, 2), "b is replayed once more");
        // It dies on b too: b's objects are refused.
        let mut third = ReplayGuard::new(HashMap::from([((3, b), 2)]));
        third.begin(3);
        assert_eq!(third.screen(3, a), mark(a, 1));
        assert_eq!(
            third.screen(3, b),
            Screened::Refused,
            "b's replay crashed two workers"
        );
        assert!(
            matches!(third.screen(4, b), Screened::Admitted { .. }),
            "another front-end's b is another client"
        );
        assert!(third.end(3), "a's mark is removed");
        assert_eq!(
            third.screen(3, b),
            Screened::Admitted { mark: None },
            "outside a replay, b creates as usual"
        );
        // A replay that ended leaves nothing to remove at the stop.
        assert!(third.stopping().is_empty());
    }
}
