//! The front-end's sessions kept where its successor finds them, so that a front-end
//! killed hard (or replaced by a new binary) is taken over without its clients noticing.
//!
//! One directory per front-end (`<runtime>/<instance>/sessions/frontend-<id>/`, in the
//! agent's private runtime directory: [`xrce_ipc::runtime_dir`]), and in it per
//! client:
//!
//! * `<KEY>.state`: the session core's snapshot
//!   ([`xrce_common::session::snapshot::SessionSnapshot`]: streams' positions, endpoint) and
//!   the client's active reads with their delivered marks. It changes with almost every
//!   message, so it is rewritten in place, through a memory mapping of the file (no system
//!   call: `sys::mapped_file`), alternating between two slots (the two halves of the
//!   file), each with a sequence number and a CRC over the whole record: a copy cut short by
//!   the kill leaves the other slot whole.
//! * `<KEY>.objects`: the client's objects (their XRCE descriptions), rewritten (temporary
//!   file, then rename) only when one is created or deleted; absent while it has none.
//!
//! **Size.** A state file grows with what it holds: one page (two 2 KiB slots) for a
//! session whose record is small, doubled (a new file written, then renamed over the old)
//! when a record does not fit a slot, up to two 256 KiB slots, and made small again when
//! its records have shrunk to an eighth of a slot. A session thus costs one page of the
//! store plus what its records and objects need; the page is bounded by the session cap,
//! the rest is counted in the session core's memory budget as the client's
//! ([`SessionStore::client_bytes`], [`xrce_common::session::agent::Agent::set_stored_bytes`]).
//!
//! Limits of the mapping: each stored client takes one of the process's memory mappings
//! (the kernel's `vm.max_map_count`, 65,530 by default, bounds them all: raise it for more
//! than about 60,000 clients on one front-end); the directory should be a tmpfs (the default
//! runtime directories are), since on a copy-on-write disk file system a write to a page allocated
//! already can still fail and that failure is a SIGBUS; and a front-end of a version before
//! the mapping (records `XRSS`) or before files grew with their records (`XRS2`) cannot read
//! these records (`XRS3`), so a downgrade loses the stored sessions and their clients create
//! them again (rather than being restored from a stale record).
//!
//! The event loop stores what changed before it sends what the core produced, so nothing a
//! client saw acknowledged or numbered is ahead of what a successor reads. An `alive` file
//! holds the time the front-end last ran; a successor takes the sessions over only if that
//! is recent ([`TAKE_OVER_WITHIN`]): after a long stop its clients are gone.
//!
//! **Privacy and ownership.** The directory is 0700 and every file 0600, created without
//! following links (temporary files exclusively, then renamed); files read back are opened
//! without following links and restored only if they are regular files of this user: a
//! file another user planted is ignored, counted and logged, never replayed to the worker.
//! The front-end holds an exclusive `flock` on the directory's `lock` file for its whole
//! life, taken before it reads or clears anything ([`next_incarnation`] or [`SessionStore::open`],
//! whichever comes first): a second front-end with the same instance and id cannot take
//! the store (and so cannot wipe the first one's sessions), while the successor of a
//! front-end killed hard takes it at once (the kernel releases a dead process's lock).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use xrce_common::wire::ClientKey;
use xrce_ipc::runtime_dir::{self, LockFile, RuntimeDirError};

use crate::sys::mapped_file::MappedFile;

/// Sessions of a front-end that stopped longer ago than this are not taken over.
pub const TAKE_OVER_WITHIN: Duration = Duration::from_secs(60);
/// How often the `alive` file is rewritten.
const ALIVE_PERIOD: Duration = Duration::from_secs(1);
/// Largest slot, so largest state record (reads with their marks are a few KiB, output in
/// flight what the session core's budget lets the client hold).
const SLOT: u64 = 256 << 10;
/// Smallest slot: two fit one page.
const MIN_SLOT: u64 = 2 << 10;
/// Bytes of the store every session has, whatever it holds (its state file's first page);
/// bounded by the session cap, so not counted in the budget (see the module docs).
pub const SESSION_PAGE: u64 = 4 << 10;
/// Magic of a state record whose CRC covers its sequence number, length and body, in a file
/// whose slots are half its length (one that grows with its records).
const MAGIC: [u8; 4] = *b"XRS3";
/// Magic of such a record in a file of two fixed 256 KiB slots (earlier versions; still
/// read). A version that knows only this one finds no record in the newer files, so a
/// downgrade drops the sessions rather than restoring a stale record.
const MAGIC_FIXED_SLOTS: [u8; 4] = *b"XRS2";
/// Magic of a state record whose CRC covers only its body (written with `pwrite` by earlier
/// versions, which a front-end being upgraded hands its sessions over in; still read).
const MAGIC_BODY_CRC: [u8; 4] = *b"XRSS";
/// Header of a state record: magic, sequence, length, CRC.
const HEADER: usize = 4 + 8 + 4 + 4;
/// Largest objects file read back (object descriptions of one client).
const MAX_OBJECTS_FILE: u64 = 64 << 20;

/// What the session stores of one instance hold on disk (every front-end's), as a sweep
/// or `xrce-agent status` sees them.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StoredSessions {
    /// Clients with a stored session.
    pub clients: usize,
    /// Bytes the stores take (allocated blocks: the state files are sparse).
    pub bytes: u64,
    /// When a front-end of the instance last said it was alive (Unix ms), if one did.
    pub last_alive_ms: Option<u64>,
}

impl StoredSessions {
    /// Whether no restart can take these sessions over any more: the last front-end alive
    /// stopped longer than [`TAKE_OVER_WITHIN`] before `now_ms` (a running one says so every
    /// second).
    pub fn expired(&self, now_ms: u64) -> bool {
        self.last_alive_ms
            .is_none_or(|ms| now_ms.saturating_sub(ms) > TAKE_OVER_WITHIN.as_millis() as u64)
    }
}

/// The session stores of `instance` ([`runtime_dir::sessions_dir`]): looked at, not
/// changed; only this user's regular files are counted.
pub fn inspect(instance: &str) -> StoredSessions {
    use std::os::unix::fs::MetadataExt;
    let mut out = StoredSessions::default();
    let Ok(stores) = std::fs::read_dir(runtime_dir::sessions_dir(instance)) else {
        return out;
    };
    let me = runtime_dir::euid();
    for store in stores.flatten() {
        let dir = store.path();
        if !store.file_type().is_ok_and(|t| t.is_dir()) {
            continue;
        }
        let alive = runtime_dir::read_owned(&dir.join("alive"), 8)
            .ok()
            .and_then(|b| b.try_into().ok().map(u64::from_le_bytes));
        out.last_alive_ms = out.last_alive_ms.max(alive);
        let Ok(files) = std::fs::read_dir(&dir) else {
            continue;
        };
        for f in files.flatten() {
            let Ok(m) = std::fs::symlink_metadata(f.path()) else {
                continue;
            };
            if !m.is_file() || m.uid() != me {
                continue;
            }
            out.bytes += m.blocks() * 512;
            out.clients += usize::from(f.path().extension().is_some_and(|e| e == "state"));
        }
    }
    out
}

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
    /// Bytes of the client's objects file (0: none).
    objects: u64,
}

impl StateFile {
    fn new(map: MappedFile, seq: u64) -> Self {
        StateFile {
            map,
            seq,
            buf: Vec::new(),
            objects: 0,
        }
    }

    /// Bytes of one slot: half the file.
    fn slot(&self) -> u64 {
        self.map.mapped_len() as u64 / 2
    }
}

/// The slot size of a state file of `len` bytes: half of it, rounded up to a power of two
/// (an earlier version wrote files that end where their last record does) and kept
/// between [`MIN_SLOT`] and [`SLOT`].
fn slot_of_len(len: u64) -> u64 {
    (len.next_power_of_two() / 2).clamp(MIN_SLOT, SLOT)
}

/// The slot size for a record of `len` bytes (with its header): the smallest that holds it.
fn slot_for_record(len: u64) -> u64 {
    (len + HEADER as u64)
        .next_power_of_two()
        .clamp(MIN_SLOT, SLOT)
}

/// Bytes a file of `len` takes in memory: whole pages.
fn in_pages(len: u64) -> u64 {
    len.div_ceil(SESSION_PAGE) * SESSION_PAGE
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
    /// Files found in the directory that were not this user's regular files (planted), so
    /// not restored.
    ignored: usize,
    /// Objects files of clients without a state file yet (bytes), kept until it comes.
    objects_only: HashMap<ClientKey, u64>,
    /// Clients whose objects could not be stored: their state is not stored either (a
    /// successor would take the missing file for "no objects") until their objects are.
    objects_unsaved: std::collections::HashSet<ClientKey>,
}

fn key_name(key: ClientKey) -> String {
    format!("{key}")
}

/// The session stores whose lock this process holds, with their locks: held for the
/// process's life (a front-end serves one store), taken once.
static HELD: std::sync::Mutex<Vec<(PathBuf, LockFile)>> = std::sync::Mutex::new(Vec::new());

/// Takes the lock of the store in `dir` for this process, unless it holds it already;
/// fails if another process holds it (`what` names that one in the message).
fn lock_store(dir: &Path, what: &str) -> Result<(), RuntimeDirError> {
    let mut held = HELD
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if held.iter().any(|(d, _)| d == dir) {
        return Ok(());
    }
    let lock = LockFile::acquire(&dir.join(runtime_dir::FRONTEND_LOCK), what)?;
    held.push((dir.to_path_buf(), lock));
    Ok(())
}

impl SessionStore {
    /// The store of front-end `id` of `instance`: its directory is created (0700) or
    /// checked, and its lock taken; another live front-end with this id is an error.
    pub fn open(instance: &str, id: u32) -> Result<Self, RuntimeDirError> {
        let dir = runtime_dir::ensure_frontend_store_dir(instance, id)?;
        lock_store(&dir, &format!("front-end {id}"))?;
        Ok(Self::prepared(dir))
    }

    /// A store in `dir` (created 0700 if missing, its parent must exist; checked if there),
    /// with its lock.
    pub fn open_at(dir: PathBuf) -> Result<Self, RuntimeDirError> {
        runtime_dir::prepare_private_dir(&dir)?;
        lock_store(&dir, "another front-end")?;
        Ok(Self::prepared(dir))
    }

    fn prepared(dir: PathBuf) -> Self {
        SessionStore {
            dir,
            files: HashMap::new(),
            next_alive: Instant::now(),
            failing: false,
            too_large: Default::default(),
            ignored: 0,
            objects_only: HashMap::new(),
            objects_unsaved: Default::default(),
        }
    }

    /// How many files [`Self::take_over`] ignored because they were not this user's
    /// regular files (planted by someone else, or links).
    pub fn ignored_files(&self) -> usize {
        self.ignored
    }

    /// Its directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Bytes of memory a client's stored session takes beyond its first page
    /// ([`SESSION_PAGE`]): what it holds makes its state file grow, and its objects file is
    /// as large as its objects' descriptions. What the session core's budget counts.
    pub fn client_bytes(&self, key: ClientKey) -> u64 {
        let objects = self.objects_only.get(&key).copied().unwrap_or(0);
        self.files.get(&key).map_or(in_pages(objects), |f| {
            (f.map.mapped_len() as u64 + in_pages(f.objects)).saturating_sub(SESSION_PAGE)
        })
    }

    /// Bytes of memory every stored session takes (state files at their whole length,
    /// objects files in whole pages), and how many clients are stored.
    pub fn bytes(&self) -> (u64, usize) {
        let files: u64 = self
            .files
            .values()
            .map(|f| f.map.mapped_len() as u64 + in_pages(f.objects))
            .sum();
        let objects: u64 = self.objects_only.values().copied().map(in_pages).sum();
        (files + objects, self.files.len())
    }

    /// The clients a predecessor left, if it ran within [`TAKE_OVER_WITHIN`]; otherwise
    /// (or when none ran) the directory is emptied and nothing is returned. Unreadable
    /// clients are skipped with a warning.
    ///
    /// Only regular files of this user are read, without following links; anything else
    /// (a file another user planted, a link) is left alone, counted
    /// ([`Self::ignored_files`]) and logged, and its client is not restored.
    pub fn take_over(&mut self) -> Vec<StoredClient> {
        let recent = runtime_dir::read_owned(&self.dir.join("alive"), 8)
            .ok()
            .and_then(|b| b.try_into().ok().map(u64::from_le_bytes))
            .is_some_and(|ms| {
                xrce_ipc::status::unix_ms().saturating_sub(ms)
                    <= TAKE_OVER_WITHIN.as_millis() as u64
            });
        let mut out = Vec::new();
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return out;
        };
        let mut names: Vec<PathBuf> = entries.flatten().map(|e| e.path()).collect();
        names.sort();
        for path in names {
            if path
                .file_name()
                .is_some_and(|n| n == "incarnation" || n == runtime_dir::FRONTEND_LOCK)
            {
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
            // Opened once, without following links, for reading its records and mapping it.
            let state_file = match runtime_dir::open_owned(&path, true) {
                Ok(f) => Some(f),
                Err(e) if e.is_untrusted() => {
                    self.ignore(&e);
                    continue;
                }
                Err(_) => None,
            };
            let objects_path = path.with_extension("objects");
            let objects = match runtime_dir::read_owned(&objects_path, MAX_OBJECTS_FILE) {
                Ok(b) => Some(b),
                Err(e) if e.is_untrusted() => {
                    self.ignore(&e);
                    continue;
                }
                // None stored: the client had no objects.
                Err(_) if !objects_path.exists() => Some(Vec::new()),
                Err(_) => None,
            };
            let state = state_file.and_then(|f| latest_record(&f).map(|r| (f, r)));
            match (state, objects) {
                (Some((file, (seq, state))), Some(objects)) => {
                    // The predecessor is gone: its file is this front-end's to map (and to
                    // grow to two whole slots, if an earlier version wrote it shorter; and to
                    // make private, if an earlier version made it 0644).
                    let mapped = private(&file).and_then(|()| {
                        let len = file.metadata()?.len();
                        MappedFile::open(file, 2 * slot_of_len(len))
                    });
                    match mapped {
                        Ok(map) => {
                            let mut f = StateFile::new(map, seq);
                            f.objects = objects.len() as u64;
                            self.files.insert(key, f);
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
        if self.ignored > 0 {
            tracing::warn!(dir = %self.dir.display(), ignored = self.ignored, "files in the session store that are not this user's regular files were ignored: their sessions are not restored");
        }
        out
    }

    /// Counts and logs a file of the store that is not ours to use.
    fn ignore(&mut self, why: &RuntimeDirError) {
        self.ignored += 1;
        tracing::warn!(error = %why, "not restored");
    }

    /// Rewrites the `alive` file if it is due.
    pub fn keep_alive(&mut self, now: Instant) {
        if now < self.next_alive {
            return;
        }
        self.next_alive = now + ALIVE_PERIOD;
        let ms = xrce_ipc::status::unix_ms().to_le_bytes();
        let r = write_atomically(&self.dir.join("alive"), &ms);
        self.note(r, None);
    }

    /// Stores a client's state record.
    pub fn save_state(&mut self, key: ClientKey, record: &[u8]) {
        if self.objects_unsaved.contains(&key) {
            return;
        }
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
        let wanted = slot_for_record(record.len() as u64);
        let path = self.dir.join(format!("{}.state", key_name(key)));
        let objects_only = self.objects_only.get(&key).copied();
        let f = match self.files.get_mut(&key) {
            Some(f) if wanted <= f.slot() && wanted * 8 > f.slot() => f,
            resized => {
                // New, grown past its slots or shrunk well below them: a file of the right
                // size, the record written before it replaces the old one (whose records
                // stay whole until then).
                let (seq, objects) =
                    resized.map_or((0, objects_only.unwrap_or(0)), |f| (f.seq, f.objects));
                let resized = create_state_file(&path, 2 * wanted).and_then(|map| {
                    let mut f = StateFile::new(map, seq);
                    f.objects = objects;
                    encode_record(&mut f, record);
                    let at = ((f.seq % 2) * f.slot()) as usize;
                    f.map.write_at(at, &f.buf)?;
                    rename_state_file(&path)?;
                    Ok(f)
                });
                let f = resized.inspect_err(|_| {
                    // Its pages back (the old file, if any, keeps the last whole record).
                    let _ = std::fs::remove_file(path.with_extension("state.tmp"));
                })?;
                self.files.insert(key, f);
                self.objects_only.remove(&key);
                return Ok(());
            }
        };
        encode_record(f, record);
        let at = ((f.seq % 2) * f.slot()) as usize;
        let written = f.map.write_at(at, &f.buf);
        if written.is_err() {
            // Not written: the next record goes to the same slot again, so the other one
            // keeps the last whole record.
            f.seq -= 1;
        }
        written
    }

    /// Stores a client's objects; empty when it has none (no file is kept then).
    pub fn save_objects(&mut self, key: ClientKey, objects: &[u8]) {
        let path = self.dir.join(format!("{}.objects", key_name(key)));
        let r = if objects.is_empty() {
            match std::fs::remove_file(&path) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
                _ => Ok(()),
            }
        } else {
            write_atomically(&path, objects)
        };
        if r.is_err() {
            // Without its objects, its state must not be found either.
            self.objects_unsaved.insert(key);
            self.files.remove(&key);
            let _ = std::fs::remove_file(self.dir.join(format!("{}.state", key_name(key))));
        } else {
            self.objects_unsaved.remove(&key);
            let len = objects.len() as u64;
            match self.files.get_mut(&key) {
                Some(f) => f.objects = len,
                None if len > 0 => {
                    self.objects_only.insert(key, len);
                }
                None => {
                    self.objects_only.remove(&key);
                }
            }
        }
        self.note(r, Some(key));
    }

    /// Forgets a client (its session ended).
    pub fn remove(&mut self, key: ClientKey) {
        self.files.remove(&key);
        self.objects_only.remove(&key);
        self.objects_unsaved.remove(&key);
        self.too_large.remove(&key);
        for ext in ["state", "objects", "state.tmp"] {
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
///
/// The first thing a front-end does in its session store, so it takes the store's lock
/// (kept for the process's life, see [`SessionStore::open`]): if another live front-end
/// holds it, nothing is read or written, the refusal is logged, and a fresh number returned
/// (the caller then fails on the duplicate id, or runs without a store).
pub fn next_incarnation(instance: &str, id: u32) -> u16 {
    let fresh = || {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        ((nanos ^ std::process::id().rotate_left(7)) as u16).max(1)
    };
    let dir = match runtime_dir::ensure_frontend_store_dir(instance, id) {
        Ok(dir) => dir,
        Err(e) => {
            tracing::error!(error = %e, "the session store cannot be used");
            return fresh();
        }
    };
    if let Err(e) = lock_store(&dir, &format!("front-end {id}")) {
        tracing::error!(error = %e, "the session store is another front-end's; it is left alone");
        return fresh();
    }
    let path = dir.join("incarnation");
    let next = match runtime_dir::read_owned(&path, 2)
        .ok()
        .and_then(|b| b.try_into().ok())
    {
        Some(b) => u16::from_le_bytes(b).wrapping_add(1).max(1),
        None => fresh(),
    };
    if let Err(e) = write_atomically(&path, &next.to_le_bytes()) {
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

/// Replaces `path` with `bytes` through a new private temporary file (never through a link).
fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    runtime_dir::write_atomically(path, &path.with_extension("tmp"), bytes)
        .map_err(std::io::Error::other)
}

/// Makes a file taken over private (0600) if an earlier version made it 0644.
fn private(file: &std::fs::File) -> std::io::Result<()> {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    if file.metadata()?.mode() & 0o077 != 0 {
        file.set_permissions(std::fs::Permissions::from_mode(runtime_dir::FILE_MODE))?;
    }
    Ok(())
}

/// A new state file of `len` bytes for `path`, mapped, under a temporary name (created 0600,
/// exclusively, never through a link) until [`rename_state_file`] puts it in place, so a file
/// of the same name that another process may still map is replaced rather than truncated
/// under it, and a file being replaced by a larger one keeps its records until the new one
/// holds the latest.
fn create_state_file(path: &Path, len: u64) -> std::io::Result<MappedFile> {
    let tmp = path.with_extension("state.tmp");
    let file = runtime_dir::create_temp(&tmp).map_err(std::io::Error::other)?;
    MappedFile::open(file, len)
}

/// Puts the state file [`create_state_file`] made for `path` in place.
fn rename_state_file(path: &Path) -> std::io::Result<()> {
    std::fs::rename(path.with_extension("state.tmp"), path)
}

/// The next record of `f` (sequence number one higher) encoded into its buffer.
fn encode_record(f: &mut StateFile, record: &[u8]) {
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
}

/// The CRC of a record: its sequence number and length (`seq_len`, as stored) and its body.
fn record_crc(seq_len: &[u8], body: &[u8]) -> u32 {
    let mut digest = CRC.digest();
    digest.update(seq_len);
    digest.update(body);
    digest.finalize()
}

/// The whole record with the higher sequence number of a state file's two slots. Only the
/// two records are read, not the file.
fn latest_record(file: &std::fs::File) -> Option<(u64, Vec<u8>)> {
    use std::os::unix::fs::FileExt;
    let size = slot_of_len(file.metadata().ok()?.len());
    let slot = |at: u64| -> Option<(u64, Vec<u8>)> {
        let mut h = [0u8; HEADER];
        file.read_exact_at(&mut h, at).ok()?;
        let magic: [u8; 4] = h[..4].try_into().ok()?;
        if magic != MAGIC && magic != MAGIC_FIXED_SLOTS && magic != MAGIC_BODY_CRC {
            return None;
        }
        let seq = u64::from_le_bytes(h[4..12].try_into().ok()?);
        let len = u32::from_le_bytes(h[12..16].try_into().ok()?) as usize;
        let crc = u32::from_le_bytes(h[16..20].try_into().ok()?);
        if len > size as usize - HEADER {
            return None;
        }
        let mut body = vec![0u8; len];
        file.read_exact_at(&mut body, at + HEADER as u64).ok()?;
        let whole = match magic {
            MAGIC | MAGIC_FIXED_SLOTS => record_crc(&h[4..16], &body) == crc,
            _ => CRC.checksum(&body) == crc,
        };
        whole.then_some((seq, body))
    };
    match (slot(0), slot(size)) {
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

    fn state_len(s: &SessionStore, key: ClientKey) -> u64 {
        std::fs::metadata(s.dir().join(format!("{}.state", key_name(key))))
            .expect("state file")
            .len()
    }

    #[test]
    fn a_state_file_grows_with_its_records_and_shrinks_back() {
        let mut s = store("grows");
        let key = ClientKey([0x12, 0x34, 0x56, 0x78]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"");
        s.save_state(key, b"small");
        assert_eq!(state_len(&s, key), SESSION_PAGE, "one page");
        assert_eq!(s.client_bytes(key), 0, "the page every session has");
        assert!(
            !s.dir().join("12345678.objects").exists(),
            "no objects, no file"
        );
        // 10 KiB records: two 16 KiB slots.
        s.save_state(key, &[1; 10 << 10]);
        assert_eq!(state_len(&s, key), 32 << 10);
        s.save_state(key, &[2; 10 << 10]);
        s.save_objects(key, &[3; 5000]);
        assert_eq!(s.client_bytes(key), (32 << 10) + (8 << 10) - SESSION_PAGE);
        assert_eq!(s.bytes(), ((32 << 10) + (8 << 10), 1));
        let dir = s.dir().to_path_buf();
        drop(s);
        let mut next = SessionStore::open_at(dir.clone()).expect("store");
        let found = next.take_over();
        assert_eq!(found[0].state, vec![2; 10 << 10]);
        assert_eq!(found[0].objects, vec![3; 5000]);
        assert_eq!(
            next.client_bytes(key),
            (32 << 10) + (8 << 10) - SESSION_PAGE
        );
        // Small again: back to one page, the latest record found.
        next.save_state(key, b"small again");
        assert_eq!(state_len(&next, key), SESSION_PAGE);
        next.save_objects(key, b"");
        assert_eq!(next.client_bytes(key), 0);
        let found = SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over();
        assert_eq!(found[0].state, b"small again");
        assert!(found[0].objects.is_empty());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_client_whose_objects_cannot_be_stored_has_no_state_until_they_are() {
        // A successor that found the state without the objects would take the session for
        // one without objects and never re-create them.
        let mut s = store("unsaved");
        let key = ClientKey([0x0B, 0x1E, 0xC7, 0x50]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"first objects");
        s.save_state(key, b"first state");
        let objects = s.dir().join("0B1EC750.objects");
        let state = s.dir().join("0B1EC750.state");
        assert!(state.exists() && objects.exists());

        // A directory where the objects file goes: the rename over it fails.
        std::fs::remove_file(&objects).expect("remove objects");
        std::fs::create_dir(&objects).expect("block objects");
        std::fs::write(objects.join("keep"), b"x").expect("fill block");
        s.save_objects(key, b"second objects");
        assert!(!state.exists(), "the state went with the objects");
        s.save_state(key, b"second state");
        assert!(!state.exists(), "no state while the objects are unsaved");
        let dir = s.dir().to_path_buf();
        assert!(
            SessionStore::open_at(dir.clone())
                .expect("store")
                .take_over()
                .iter()
                .all(|c| c.key != key),
            "a successor finds no session to restore without its objects"
        );

        // Storable again: both are stored from the next save on.
        std::fs::remove_dir_all(&objects).expect("unblock objects");
        s.save_objects(key, b"third objects");
        s.save_state(key, b"third state");
        drop(s);
        let found = SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over();
        assert_eq!(
            found,
            vec![StoredClient {
                key,
                state: b"third state".to_vec(),
                objects: b"third objects".to_vec()
            }]
        );
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_record_growing_a_little_keeps_its_file() {
        // Between an eighth of a slot and a whole one the file stays (no new file per
        // record for a client whose output comes and goes).
        let mut s = store("hysteresis");
        let key = ClientKey([8, 8, 8, 8]);
        s.save_state(key, &[1; 30 << 10]);
        assert_eq!(state_len(&s, key), 64 << 10);
        for len in [5 << 10, 20 << 10, 31 << 10] {
            s.save_state(key, &vec![2; len]);
            assert_eq!(state_len(&s, key), 64 << 10, "record of {len}");
        }
        s.save_state(key, &[3; 3 << 10]);
        assert_eq!(state_len(&s, key), 8 << 10);
        let _ = std::fs::remove_dir_all(s.dir());
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
            2 * MIN_SLOT,
            "made as small as its records"
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
        assert_eq!(std::fs::metadata(&path).expect("new").len(), 2 * MIN_SLOT);
        let _ = std::fs::remove_dir_all(s.dir());
    }

    fn mode(p: &Path) -> u32 {
        use std::os::unix::fs::MetadataExt;
        std::fs::symlink_metadata(p).expect("exists").mode() & 0o7777
    }

    #[test]
    fn the_store_and_its_files_are_private() {
        let mut s = store("private");
        let key = ClientKey([7, 7, 7, 7]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"o");
        s.save_state(key, b"s");
        assert_eq!(mode(s.dir()), 0o700);
        let mut names = Vec::new();
        for e in std::fs::read_dir(s.dir()).expect("dir").flatten() {
            assert_eq!(mode(&e.path()), 0o600, "{}", e.path().display());
            names.push(e.file_name().to_string_lossy().into_owned());
        }
        names.sort();
        assert_eq!(
            names,
            ["07070707.objects", "07070707.state", "alive", "lock"]
        );
        let _ = std::fs::remove_dir_all(s.dir());
    }

    #[test]
    fn links_planted_in_the_store_are_neither_followed_nor_restored() {
        use std::os::unix::fs::symlink;
        let mut s = store("planted");
        let dir = s.dir().to_path_buf();
        let victim = std::env::temp_dir().join(format!("xrce-victim-{}", std::process::id()));
        std::fs::write(&victim, b"untouched").expect("victim");
        // Links where temporary files will be made.
        symlink(&victim, dir.join("alive.tmp")).expect("link");
        symlink(&victim, dir.join("01010101.state.tmp")).expect("link");
        symlink(&victim, dir.join("01010101.tmp")).expect("link");
        let key = ClientKey([1, 1, 1, 1]);
        s.keep_alive(Instant::now());
        s.save_state(key, b"mine");
        s.save_objects(key, b"objects");
        assert_eq!(std::fs::read(&victim).expect("victim"), b"untouched");
        for f in ["alive", "01010101.state", "01010101.objects"] {
            let m = std::fs::symlink_metadata(dir.join(f)).expect("written");
            assert!(m.is_file(), "{f} is a regular file");
        }
        // A client whose stored files are links (to files that would pass for a session):
        // not restored, counted.
        let elsewhere = std::env::temp_dir().join(format!("xrce-elsewhere-{}", std::process::id()));
        std::fs::copy(dir.join("01010101.state"), &elsewhere).expect("copy");
        symlink(&elsewhere, dir.join("02020202.state")).expect("link");
        std::fs::write(dir.join("02020202.objects"), b"objects").expect("objects");
        drop(s);
        let mut next = SessionStore::open_at(dir.clone()).expect("store");
        let found = next.take_over();
        assert_eq!(found.len(), 1, "only the real client");
        assert_eq!(found[0].key, key);
        assert_eq!(next.ignored_files(), 1);
        let _ = std::fs::remove_file(victim);
        let _ = std::fs::remove_file(elsewhere);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_state_file_of_another_user_is_not_restored() {
        if xrce_ipc::runtime_dir::euid() != 0 {
            return; // only root can give a file away
        }
        let mut s = store("foreign");
        let key = ClientKey([3, 3, 3, 3]);
        s.keep_alive(Instant::now());
        s.save_objects(key, b"o");
        s.save_state(key, b"s");
        let dir = s.dir().to_path_buf();
        drop(s);
        std::os::unix::fs::chown(dir.join("03030303.state"), Some(65534), None).expect("chown");
        let mut next = SessionStore::open_at(dir.clone()).expect("store");
        assert!(next.take_over().is_empty());
        assert_eq!(next.ignored_files(), 1);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn a_store_locked_by_another_front_end_is_refused() {
        let dir = std::env::temp_dir().join(format!("xrce-store-locked-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        xrce_ipc::runtime_dir::prepare_private_dir(&dir).expect("dir");
        // Another open file description: another front-end, as far as flock is concerned.
        let other = LockFile::acquire(&dir.join("lock"), "front-end 0").expect("lock");
        let e = SessionStore::open_at(dir.clone()).expect_err("locked");
        assert!(matches!(e, RuntimeDirError::Locked { .. }), "{e}");
        assert!(e.to_string().contains("already runs"), "{e}");
        // Once it is gone (its process died), the store is taken.
        drop(other);
        SessionStore::open_at(dir.clone()).expect("free");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn sessions_of_a_front_end_long_gone_are_not_taken_over() {
        let mut s = store("old");
        let key = ClientKey([5, 6, 7, 8]);
        s.save_objects(key, b"o");
        s.save_state(key, b"s");
        let old = xrce_ipc::status::unix_ms() - 2 * TAKE_OVER_WITHIN.as_millis() as u64;
        std::fs::write(s.dir().join("alive"), old.to_le_bytes()).expect("alive");
        let dir = s.dir().to_path_buf();
        assert!(SessionStore::open_at(dir.clone())
            .expect("store")
            .take_over()
            .is_empty());
        let left: Vec<_> = std::fs::read_dir(&dir)
            .expect("dir")
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(left, ["lock"], "emptied but for the lock");
        let _ = std::fs::remove_dir_all(dir);
    }
}
