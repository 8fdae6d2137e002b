//! A replay that crashed the worker is not replayed again.
//!
//! A new worker gets every front-end's objects again (the replay between the front-end's
//! hello and its `ReplayDone`). If one client's objects make the worker crash (a backend
//! that aborts on some description), replaying them to every new worker would keep the
//! worker crashing long after that client is gone. So while a front-end replays, the client
//! whose objects are being created is written down in the private instance directory
//! (`replaying-<front-end>`, rewritten when the client changes, removed at `ReplayDone`);
//! a worker that finds such a file at its start refuses that client's replayed objects
//! (STATUS_ERR_RESOURCES with [`xrce_ipc::REPLAY_REFUSED`], counted as `replay_crash`,
//! logged), and the front-end ends the client's session: the client finds it gone and
//! creates it again. Everyone else is replayed as usual.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;

use xrce_common::wire::ClientKey;
use xrce_ipc::runtime_dir;

/// Prefix of the marker files in the instance directory.
const MARKER: &str = "replaying-";

/// What the worker knows about replays that crashed it, and the replays under way.
#[derive(Debug, Default)]
pub(crate) struct ReplayGuard {
    dir: Option<PathBuf>,
    /// Clients whose replay was under way when the last worker died: (front-end, client).
    suspects: HashSet<(u32, ClientKey)>,
    /// Front-ends replaying now, and the client last written down for each.
    replaying: HashMap<u32, Option<ClientKey>>,
}

impl ReplayGuard {
    /// Reads (and removes) what a worker of `instance` that died left written down.
    pub(crate) fn open(instance: &str) -> Self {
        Self::open_in(runtime_dir::instance_dir(instance))
    }

    /// [`Self::open`] with the instance directory `dir`.
    fn open_in(dir: PathBuf) -> Self {
        let mut suspects = HashSet::new();
        if let Ok(entries) = std::fs::read_dir(&dir) {
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                let Some(fe) = name
                    .strip_prefix(MARKER)
                    .and_then(|f| f.parse::<u32>().ok())
                else {
                    continue;
                };
                if let Ok(bytes) = runtime_dir::read_owned(&e.path(), 4) {
                    if let Ok(key) = <[u8; 4]>::try_from(bytes.as_slice()) {
                        tracing::warn!(frontend = fe, client = %ClientKey(key), "the last worker died while replaying this client's objects: they are not replayed to this one");
                        suspects.insert((fe, ClientKey(key)));
                    }
                }
                let _ = std::fs::remove_file(e.path());
            }
        }
        ReplayGuard {
            dir: Some(dir),
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
    pub(crate) fn end(&mut self, fe: u32) {
        self.suspects.retain(|(f, _)| *f != fe);
        if let Some(Some(_)) = self.replaying.remove(&fe) {
            if let Some(dir) = &self.dir {
                let _ = std::fs::remove_file(dir.join(format!("{MARKER}{fe}")));
            }
        }
    }

    /// The worker stops of its own accord: the replays under way did not crash it.
    pub(crate) fn stopping(&mut self) {
        let under_way: Vec<u32> = self.replaying.keys().copied().collect();
        for fe in under_way {
            self.end(fe);
        }
    }

    /// An object of `client` is about to be created by `fe`: whether it must be refused
    /// (its replay crashed the last worker). Otherwise, during a replay, the client is
    /// written down first.
    pub(crate) fn refuses(&mut self, fe: u32, client: ClientKey) -> bool {
        let Some(current) = self.replaying.get_mut(&fe) else {
            return false;
        };
        if self.suspects.contains(&(fe, client)) {
            return true;
        }
        if *current != Some(client) {
            *current = Some(client);
            if let Some(dir) = &self.dir {
                let path = dir.join(format!("{MARKER}{fe}"));
                let tmp = dir.join(format!(".{MARKER}{fe}.{}", std::process::id()));
                if let Err(e) = runtime_dir::write_atomically(&path, &tmp, &client.0) {
                    tracing::debug!(error = %e, "replay marker not written");
                }
            }
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_client_whose_replay_was_under_way_is_refused_by_the_next_worker_only_in_replays() {
        let dir = std::env::temp_dir().join(format!("xrce-replay-guard-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let (a, b) = (ClientKey(*b"AAAA"), ClientKey(*b"BBBB"));
        let mut first = ReplayGuard::open_in(dir.clone());
        assert!(!first.refuses(3, a), "not in a replay");
        first.begin(3);
        assert!(!first.refuses(3, a));
        assert!(!first.refuses(3, b));
        // The worker dies here, while b's objects are being replayed.
        drop(first);
        let mut second = ReplayGuard::open_in(dir.clone());
        second.begin(3);
        assert!(!second.refuses(3, a), "a is replayed");
        assert!(second.refuses(3, b), "b's replay crashed the last worker");
        assert!(
            !second.refuses(4, b),
            "another front-end's b is another client"
        );
        second.end(3);
        assert!(
            !second.refuses(3, b),
            "outside a replay, b creates as usual"
        );
        // A replay that ended leaves nothing for the next worker.
        assert!(ReplayGuard::open_in(dir.clone()).suspects.is_empty());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
