//! The front-end's sessions kept where its successor finds them, so that a front-end
//! killed hard (or replaced by a new binary) is taken over without its clients noticing.
//!
//! One directory per front-end (`/dev/shm/xrce-sessions-<instance>/frontend-<id>/`), and in
//! it per client:
//!
//! * `<KEY>.state`: the session core's snapshot
//!   ([`xrce_common::session::snapshot::SessionSnapshot`]: streams' positions, endpoint) and
//!   the client's active reads with their delivered marks. It changes with almost every
//!   message, so it is rewritten in place, through a memory mapping of the file (no system
//!   call: [`crate::sys::mapped_file`]), alternating between two slots, each with a
//!   sequence number and a CRC over the whole record: a copy cut short by the kill leaves
//!   the other slot whole.
//! * `<KEY>.objects`: the client's objects (their XRCE descriptions), rewritten (temporary
//!   file, then rename) only when one is created or deleted.
//!
//! Limits of the mapping: each stored client takes one of the process's memory mappings
//! (the kernel's `vm.max_map_count`, 65,530 by default, bounds them all: raise it for more
//! than about 60,000 clients on one front-end); the directory should be a tmpfs (the default,
//! `/dev/shm`), since on a copy-on-write disk file system a write to a page allocated
//! already can still fail and that failure is a SIGBUS; and a front-end of a version before
//! the mapping (records `XRSS`) cannot read these records (`XRS2`), so a downgrade loses the
//! stored sessions and their clients create them again.
//!
//! The event loop stores what changed before it sends what the core produced, so nothing a
//! client saw acknowledged or numbered is ahead of what a successor reads. An `alive` file
//! holds the time the front-end last ran; a successor takes the sessions over only if that
//! is recent ([`TAKE_OVER_WITHIN`]): after a long stop its clients are gone.

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use xrce_common::wire::ClientKey;

use crate::sys::mapped_file::MappedFile;

/// Sessions of a front-end that stopped longer ago than this are not taken over.
pub const TAKE_OVER_WITHIN: Duration = Duration::from_secs(60);
/// How often the `alive` file is rewritten.
const ALIVE_PERIOD: Duration = Duration::from_secs(1);
/// Largest state record (reads with their marks are a few KiB at most).
const SLOT: u64 = 256 << 10;
/// Magic of a state record whose CRC covers its sequence number, length and body.
const MAGIC: [u8; 4] = *b"XRS2";
/// Magic of a state record whose CRC covers only its body (written with `pwrite` by earlier
/// versions, which a front-end being upgraded hands its sessions over in; still read).
const MAGIC_BODY_CRC: [u8; 4] = *b"XRSS";
/// Header of a state record: magic, sequence, length, CRC.
const HEADER: usize = 4 + 8 + 4 + 4;
/// Length of a state file: two slots.
const STATE_FILE_LEN: u64 = 2 * SLOT;

/// Slice-by-16 tables: a subscriber's record (its reads' delivered marks) is rewritten on
/// every loop pass, and the byte-wise table made the checksum a twentieth of the front-end's
/// CPU with 100 clients.
const CRC: crc::Crc<u32, crc::Table<16>> = crc::Crc::<u32, crc::Table<16>>::new(&crc::CRC_32_ISCSI);

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
    map: MappedFile,
    /// Sequence number of the last record written.
    seq: u64,
    /// The record being written, reused.
    buf: Vec<u8>,
}

impl StateFile {
    fn new(map: MappedFile, seq: u64) -> Self {
        StateFile {
            map,
            seq,
            buf: Vec::new(),
        }
    }
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
            let state = std::fs::File::open(&path)
                .ok()
                .and_then(|f| latest_record(&f));
            let objects = std::fs::read(path.with_extension("objects")).ok();
            match (state, objects) {
                (Some((seq, state)), Some(objects)) => {
                    // The predecessor is gone: its file is this front-end's to map (and to
                    // grow, if an earlier version wrote it shorter).
                    let mapped = std::fs::OpenOptions::new()
                        .read(true)
                        .write(true)
                        .open(&path)
                        .and_then(|file| MappedFile::open(file, STATE_FILE_LEN));
                    match mapped {
                        Ok(map) => {
                            self.files.insert(key, StateFile::new(map, seq));
                        }
                        Err(e) => {
                            tracing::warn!(client = %key, error = %e, "stored session taken over but cannot be stored again; a restart of this front-end would lose it");
                        }
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
                v.insert(StateFile::new(create_state_file(&path)?, 0))
            }
        };
        f.seq += 1;
        let buf = &mut f.buf;
        buf.clear();
        buf.extend_from_slice(&MAGIC);
        buf.extend_from_slice(&f.seq.to_le_bytes());
        buf.extend_from_slice(&(record.len() as u32).to_le_bytes());
        buf.extend_from_slice(&[0; 4]);
        buf.extend_from_slice(record);
        let crc = record_crc(&buf[4..16], &buf[HEADER..]);
        buf[16..HEADER].copy_from_slice(&crc.to_le_bytes());
        let at = ((f.seq % 2) * SLOT) as usize;
        let written = f.map.write_at(at, buf);
        if written.is_err() {
            // Not written: the next record goes to the same slot again, so the other one
            // keeps the last whole record.
            f.seq -= 1;
        }
        written
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
    let mut f = std::fs::File::create(&tmp)?;
    f.write_all(bytes)?;
    drop(f);
    std::fs::rename(&tmp, path)
}

/// A new state file at `path`, mapped. It is created under a temporary name, sized and then
/// renamed into place, so a file of the same name that another process may still map is
/// replaced rather than truncated under it.
fn create_state_file(path: &Path) -> std::io::Result<MappedFile> {
    let tmp = path.with_extension("state.tmp");
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(true)
        .read(true)
        .write(true)
        .open(&tmp)?;
    let map = MappedFile::open(file, STATE_FILE_LEN)?;
    std::fs::rename(&tmp, path)?;
    Ok(map)
}

/// The CRC of a record: its sequence number and length (`seq_len`, as stored) and its body.
fn record_crc(seq_len: &[u8], body: &[u8]) -> u32 {
    let mut digest = CRC.digest();
    digest.update(seq_len);
    digest.update(body);
    digest.finalize()
}

/// The whole record with the higher sequence number of a state file's two slots. Only the
/// two records are read, not the file (a sparse half MiB per client).
fn latest_record(file: &std::fs::File) -> Option<(u64, Vec<u8>)> {
    use std::os::unix::fs::FileExt;
    let slot = |at: u64| -> Option<(u64, Vec<u8>)> {
        let mut h = [0u8; HEADER];
        file.read_exact_at(&mut h, at).ok()?;
        let magic: [u8; 4] = h[..4].try_into().ok()?;
        if magic != MAGIC && magic != MAGIC_BODY_CRC {
            return None;
        }
        let seq = u64::from_le_bytes(h[4..12].try_into().ok()?);
        let len = u32::from_le_bytes(h[12..16].try_into().ok()?) as usize;
        let crc = u32::from_le_bytes(h[16..20].try_into().ok()?);
        if len > SLOT as usize - HEADER {
            return None;
        }
        let mut body = vec![0u8; len];
        file.read_exact_at(&mut body, at + HEADER as u64).ok()?;
        let whole = match magic {
            MAGIC => record_crc(&h[4..16], &body) == crc,
            _ => CRC.checksum(&body) == crc,
        };
        whole.then_some((seq, body))
    };
    match (slot(0), slot(SLOT)) {
        (Some(a), Some(b)) => Some(if a.0 > b.0 { a } else { b }),
        (a, b) => a.or(b),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::FileExt;

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

    /// Stores "first" then "second" for a client, damages the newer record (slot 0 holds
    /// sequence 2) with `bytes` at `offset` into it, and returns what a successor finds.
    fn taken_over_after_damage(tag: &str, offset: u64, bytes: &[u8]) -> Vec<u8> {
        let mut s = store(tag);
        let key = ClientKey([1, 2, 3, 4]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"o");
        s.save_state(key, b"first");
        s.save_state(key, b"second");
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(s.dir().join("01020304.state"))
            .expect("open");
        f.write_all_at(bytes, offset).expect("write");
        let dir = s.dir().to_path_buf();
        drop(s);
        let found = SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over();
        let _ = std::fs::remove_dir_all(dir);
        found[0].state.clone()
    }

    #[test]
    fn a_torn_record_falls_back_to_the_other_slot() {
        assert_eq!(
            taken_over_after_damage("torn", HEADER as u64 + 1, b"X"),
            b"first"
        );
    }

    #[test]
    fn a_record_whose_sequence_number_was_torn_is_not_taken_for_the_newest() {
        // A copy cut short in the sequence number (its high byte written, the body intact)
        // would make the record look far newer than the other slot's.
        assert_eq!(
            taken_over_after_damage("torn-seq", 4 + 7, &[0x7F]),
            b"first"
        );
    }

    #[test]
    fn a_state_file_an_earlier_version_wrote_is_taken_over_and_written_on() {
        let mut s = store("earlier");
        let key = ClientKey([9, 8, 7, 6]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"o");
        let dir = s.dir().to_path_buf();
        drop(s);
        // As earlier versions wrote it with pwrite: sequence 3 in slot 1, the CRC over the
        // body only, the file ending with the record.
        let body = b"from the predecessor";
        let mut record = Vec::new();
        record.extend_from_slice(b"XRSS");
        record.extend_from_slice(&3u64.to_le_bytes());
        record.extend_from_slice(&(body.len() as u32).to_le_bytes());
        record.extend_from_slice(&CRC.checksum(body).to_le_bytes());
        record.extend_from_slice(body);
        let path = dir.join("09080706.state");
        let f = std::fs::File::create(&path).expect("create");
        f.write_all_at(&record, SLOT).expect("write");
        drop(f);
        let mut next = SessionStore::open_at(dir.clone()).expect("store");
        assert_eq!(next.take_over()[0].state, body.to_vec());
        next.save_state(key, b"newer");
        assert_eq!(
            std::fs::metadata(&path).expect("file").len(),
            STATE_FILE_LEN,
            "grown to two whole slots"
        );
        drop(next);
        let found = SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over();
        assert_eq!(found[0].state, b"newer".to_vec());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_new_state_file_replaces_one_left_behind_without_truncating_it() {
        // A file of the same name (a process that may still map it) is renamed over, so
        // whoever holds the old one keeps all its bytes.
        let mut s = store("replace");
        let key = ClientKey([4, 4, 4, 4]);
        let path = s.dir().join("04040404.state");
        std::fs::write(&path, vec![1u8; 1000]).expect("write");
        let old = std::fs::File::open(&path).expect("open");
        s.save_state(key, b"mine");
        assert_eq!(old.metadata().expect("old").len(), 1000);
        assert_eq!(std::fs::metadata(&path).expect("new").len(), STATE_FILE_LEN);
        let _ = std::fs::remove_dir_all(s.dir());
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
