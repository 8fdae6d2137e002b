//! The front-end's sessions kept where its successor finds them, so that a front-end
//! killed hard (or replaced by a new binary) is taken over without its clients noticing.
//!
//! One directory per front-end (`/dev/shm/xrce-sessions-<instance>/frontend-<id>/`), and in
//! it per client:
//!
//! * `<KEY>.state`: the session core's snapshot
//!   ([`xrce_common::session::snapshot::SessionSnapshot`]: streams' positions, endpoint) and
//!   the client's active reads with their delivered marks. It changes with almost every
//!   message, so it is rewritten in place (one `pwrite`), alternating between two slots, each
//!   with a sequence number and a CRC: a write cut short by the kill leaves the other slot
//!   whole.
//! * `<KEY>.objects`: the client's objects (their XRCE descriptions), rewritten (temporary
//!   file, then rename) only when one is created or deleted.
//!
//! The event loop stores what changed before it sends what the core produced, so nothing a
//! client saw acknowledged or numbered is ahead of what a successor reads. An `alive` file
//! holds the time the front-end last ran; a successor takes the sessions over only if that
//! is recent ([`TAKE_OVER_WITHIN`]): after a long stop its clients are gone.

use std::collections::HashMap;
use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use xrce_common::wire::ClientKey;

/// Sessions of a front-end that stopped longer ago than this are not taken over.
pub const TAKE_OVER_WITHIN: Duration = Duration::from_secs(60);
/// How often the `alive` file is rewritten.
const ALIVE_PERIOD: Duration = Duration::from_secs(1);
/// Largest state record (reads with their marks are a few KiB at most).
const SLOT: u64 = 256 << 10;
/// Magic of a state record.
const MAGIC: [u8; 4] = *b"XRSS";
/// Header of a state record: magic, sequence, length, CRC.
const HEADER: usize = 4 + 8 + 4 + 4;

const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);

/// A client's stored state, as loaded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoredClient {
    /// Its key.
    pub key: ClientKey,
    /// The latest whole state record.
    pub state: Vec<u8>,
    /// Its objects.
    pub objects: Vec<u8>,
}

#[derive(Debug)]
struct StateFile {
    file: File,
    /// Sequence number of the last record written.
    seq: u64,
}

/// The store of one front-end.
#[derive(Debug)]
pub struct SessionStore {
    dir: PathBuf,
    files: HashMap<ClientKey, StateFile>,
    next_alive: Instant,
    /// Whether the last write failed (logged once per failure streak).
    failing: bool,
    /// Clients whose state was too large to store (warned once each).
    too_large: std::collections::HashSet<ClientKey>,
}

fn key_name(key: ClientKey) -> String {
    format!("{key}")
}

impl SessionStore {
    /// The store of front-end `id` of `instance` (its directory is created).
    pub fn open(instance: &str, id: u32) -> std::io::Result<Self> {
        let dir = xrce_common::ipc::status::sessions_dir(instance).join(format!("frontend-{id}"));
        Self::open_at(dir)
    }

    /// A store in `dir`.
    pub fn open_at(dir: PathBuf) -> std::io::Result<Self> {
        std::fs::create_dir_all(&dir)?;
        Ok(SessionStore {
            dir,
            files: HashMap::new(),
            next_alive: Instant::now(),
            failing: false,
            too_large: Default::default(),
        })
    }

    /// Its directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The clients a predecessor left, if it ran within [`TAKE_OVER_WITHIN`]; otherwise
    /// (or when none ran) the directory is emptied and nothing is returned. Unreadable
    /// clients are skipped with a warning.
    pub fn take_over(&mut self) -> Vec<StoredClient> {
        let recent = std::fs::read(self.dir.join("alive"))
            .ok()
            .and_then(|b| b.try_into().ok().map(u64::from_le_bytes))
            .is_some_and(|ms| {
                xrce_common::ipc::status::unix_ms().saturating_sub(ms)
                    <= TAKE_OVER_WITHIN.as_millis() as u64
            });
        let mut out = Vec::new();
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return out;
        };
        let mut names: Vec<PathBuf> = entries.flatten().map(|e| e.path()).collect();
        names.sort();
        for path in names {
            if path.file_name().is_some_and(|n| n == "incarnation") {
                continue;
            }
            let is_state = path.extension().is_some_and(|x| x == "state");
            if !recent || !is_state {
                // Objects of a client whose state was never stored (a TCP one) go too.
                let orphan = path.extension().is_some_and(|x| x == "objects")
                    && !path.with_extension("state").exists();
                if !recent || orphan || path.extension().is_some_and(|x| x == "tmp") {
                    let _ = std::fs::remove_file(&path);
                }
                continue;
            }
            let Some(key) = path
                .file_stem()
                .and_then(|s| s.to_str())
                .and_then(parse_key)
            else {
                let _ = std::fs::remove_file(&path);
                continue;
            };
            let state = match std::fs::read(&path) {
                Ok(bytes) => latest_record(&bytes),
                Err(_) => None,
            };
            let objects = std::fs::read(path.with_extension("objects")).ok();
            match (state, objects) {
                (Some((seq, state)), Some(objects)) => {
                    if let Ok(file) = std::fs::OpenOptions::new().write(true).open(&path) {
                        self.files.insert(key, StateFile { file, seq });
                    }
                    out.push(StoredClient {
                        key,
                        state,
                        objects,
                    });
                }
                _ => {
                    tracing::warn!(client = %key, "stored session unreadable; the client will have to create it again");
                    self.remove(key);
                }
            }
        }
        out
    }

    /// Rewrites the `alive` file if it is due.
    pub fn keep_alive(&mut self, now: Instant) {
        if now < self.next_alive {
            return;
        }
        self.next_alive = now + ALIVE_PERIOD;
        let ms = xrce_common::ipc::status::unix_ms().to_le_bytes();
        let r = write_atomically(&self.dir.join("alive"), &ms);
        self.note(r, None);
    }

    /// Stores a client's state record.
    pub fn save_state(&mut self, key: ClientKey, record: &[u8]) {
        if record.len() + HEADER > SLOT as usize {
            if self.too_large.insert(key) {
                tracing::warn!(client = %key, bytes = record.len(), "session state too large to store; a front-end restart would lose this session");
            }
            return;
        }
        let r = self.write_state(key, record);
        self.note(r, Some(key));
    }

    fn write_state(&mut self, key: ClientKey, record: &[u8]) -> std::io::Result<()> {
        use std::collections::hash_map::Entry;
        let f = match self.files.entry(key) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(v) => {
                let path = self.dir.join(format!("{}.state", key_name(key)));
                let file = std::fs::OpenOptions::new()
                    .create(true)
                    .truncate(true)
                    .read(true)
                    .write(true)
                    .open(path)?;
                v.insert(StateFile { file, seq: 0 })
            }
        };
        f.seq += 1;
        let mut buf = Vec::with_capacity(HEADER + record.len());
        buf.extend_from_slice(&MAGIC);
        buf.extend_from_slice(&f.seq.to_le_bytes());
        buf.extend_from_slice(&(record.len() as u32).to_le_bytes());
        buf.extend_from_slice(&CRC.checksum(record).to_le_bytes());
        buf.extend_from_slice(record);
        f.file.write_all_at(&buf, (f.seq % 2) * SLOT)
    }

    /// Stores a client's objects.
    pub fn save_objects(&mut self, key: ClientKey, objects: &[u8]) {
        let path = self.dir.join(format!("{}.objects", key_name(key)));
        let r = write_atomically(&path, objects);
        self.note(r, Some(key));
    }

    /// Forgets a client (its session ended).
    pub fn remove(&mut self, key: ClientKey) {
        self.files.remove(&key);
        self.too_large.remove(&key);
        for ext in ["state", "objects"] {
            let _ = std::fs::remove_file(self.dir.join(format!("{}.{ext}", key_name(key))));
        }
    }

    fn note(&mut self, r: std::io::Result<()>, key: Option<ClientKey>) {
        match r {
            Ok(()) if self.failing => {
                self.failing = false;
                tracing::info!(dir = %self.dir.display(), "sessions are stored again");
            }
            Ok(()) => {}
            Err(e) if !self.failing => {
                self.failing = true;
                tracing::warn!(dir = %self.dir.display(), client = ?key, error = %e, "cannot store sessions: a front-end restart would lose them");
            }
            Err(_) => {}
        }
    }
}

/// The incarnation number of a new process of front-end `id` of `instance`: its
/// predecessor's plus one (kept beside its sessions), never 0; without a predecessor (or a
/// place to keep it), one from the clock and the process id.
pub fn next_incarnation(instance: &str, id: u32) -> u16 {
    let dir = xrce_common::ipc::status::sessions_dir(instance).join(format!("frontend-{id}"));
    let path = dir.join("incarnation");
    let fresh = || {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        ((nanos ^ std::process::id().rotate_left(7)) as u16).max(1)
    };
    let next = match std::fs::read(&path).ok().and_then(|b| b.try_into().ok()) {
        Some(b) => u16::from_le_bytes(b).wrapping_add(1).max(1),
        None => fresh(),
    };
    let kept =
        std::fs::create_dir_all(&dir).and_then(|()| write_atomically(&path, &next.to_le_bytes()));
    if let Err(e) = kept {
        tracing::debug!(error = %e, "front-end incarnation not kept");
    }
    next
}

fn parse_key(s: &str) -> Option<ClientKey> {
    if s.len() != 8 {
        return None;
    }
    let v = u32::from_str_radix(s, 16).ok()?;
    Some(ClientKey(v.to_be_bytes()))
}

fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension("tmp");
    let mut f = File::create(&tmp)?;
    f.write_all(bytes)?;
    drop(f);
    std::fs::rename(&tmp, path)
}

/// The whole record with the highest sequence number of the two slots.
fn latest_record(bytes: &[u8]) -> Option<(u64, Vec<u8>)> {
    let slot = |at: usize| -> Option<(u64, Vec<u8>)> {
        let h = bytes.get(at..at + HEADER)?;
        if h[..4] != MAGIC {
            return None;
        }
        let seq = u64::from_le_bytes(h[4..12].try_into().ok()?);
        let len = u32::from_le_bytes(h[12..16].try_into().ok()?) as usize;
        let crc = u32::from_le_bytes(h[16..20].try_into().ok()?);
        let start = at.checked_add(HEADER)?;
        let body = bytes.get(start..start.checked_add(len)?)?;
        (CRC.checksum(body) == crc).then(|| (seq, body.to_vec()))
    };
    match (slot(0), slot(SLOT as usize)) {
        (Some(a), Some(b)) => Some(if a.0 > b.0 { a } else { b }),
        (a, b) => a.or(b),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn store(tag: &str) -> SessionStore {
        let dir = std::env::temp_dir().join(format!("xrce-store-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        SessionStore::open_at(dir).expect("store")
    }

    #[test]
    fn a_successor_finds_the_latest_state_and_the_objects() {
        let mut s = store("latest");
        let key = ClientKey([0xAA, 0xAA, 0xBB, 0xBB]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"objects");
        for i in 0..5u8 {
            s.save_state(key, &[i; 10]);
        }
        let dir = s.dir().to_path_buf();
        drop(s);
        let mut next = SessionStore::open_at(dir.clone()).expect("store");
        let found = next.take_over();
        assert_eq!(
            found,
            vec![StoredClient {
                key,
                state: vec![4; 10],
                objects: b"objects".to_vec()
            }]
        );
        // It goes on writing where the predecessor stopped (the newer slot wins).
        next.save_state(key, &[9; 3]);
        let mut third = SessionStore::open_at(dir.clone()).expect("store");
        assert_eq!(third.take_over()[0].state, vec![9; 3]);
        third.remove(key);
        assert!(SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over()
            .is_empty());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_torn_record_falls_back_to_the_other_slot() {
        let mut s = store("torn");
        let key = ClientKey([1, 2, 3, 4]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"o");
        s.save_state(key, b"first");
        s.save_state(key, b"second");
        let path = s.dir().join("01020304.state");
        // Damage the newer record (slot 0 holds sequence 2).
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .expect("open");
        f.write_all_at(b"X", HEADER as u64 + 1).expect("write");
        let dir = s.dir().to_path_buf();
        let found = SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over();
        assert_eq!(found[0].state, b"first".to_vec());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn sessions_of_a_front_end_long_gone_are_not_taken_over() {
        let mut s = store("old");
        let key = ClientKey([5, 6, 7, 8]);
        s.save_objects(key, b"o");
        s.save_state(key, b"s");
        let old = xrce_common::ipc::status::unix_ms() - 2 * TAKE_OVER_WITHIN.as_millis() as u64;
        std::fs::write(s.dir().join("alive"), old.to_le_bytes()).expect("alive");
        let dir = s.dir().to_path_buf();
        assert!(SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over()
            .is_empty());
        assert_eq!(std::fs::read_dir(&dir).expect("dir").count(), 0, "emptied");
        let _ = std::fs::remove_dir_all(dir);
    }
}
