//! Where an agent keeps its files, and how it creates and reads them so that no other local
//! user can read, forge or redirect them.
//!
//! The files hold what a client must keep secret from other users of the gateway: client
//! keys, session state, unacknowledged samples, object descriptions. So every process of an
//! agent works in one **private runtime directory**, decided here and nowhere else:
//!
//! 1. `$XRCE_RUNTIME_DIR`, if set;
//! 2. systemd's `$RUNTIME_DIRECTORY` (its first entry: the unit's `RuntimeDirectory=`);
//! 3. `$XDG_RUNTIME_DIR/xrce-agent`, when `$XDG_RUNTIME_DIR` is a directory of this user
//!    (it is not after `su` or `sudo`, which keep the caller's);
//! 4. `/dev/shm/xrce-agent-<euid>` (the temporary directory when there is no `/dev/shm`).
//!
//! All of these are in memory (tmpfs) on a usual Linux system, which the front-end's session
//! store relies on: it maps its files and writes them through the mapping, and on a disk file
//! system a write to a mapped page can fail as a SIGBUS instead of an error.
//!
//! Under it, per instance (an instance name is `[A-Za-z0-9_-]{1,32}`, never a path):
//!
//! ```text
//! <runtime>/<instance>/              0700, the instance's directory
//! <runtime>/<instance>/agent.lock    0600, held (flock) by the instance's supervisor
//! <runtime>/<instance>/shm-token     0600, the random part of its shared-memory names
//! <runtime>/<instance>/sessions/frontend-<id>/   0700, a front-end's session store, its lock
//! <runtime>/<instance>/status/       0700, the processes' status reports (0600 files)
//! <runtime>/ipc/                     0700, iceoryx2's root (node and service files, sockets)
//! ```
//!
//! `XRCE_SESSION_DIR` (the parent of `xrce-sessions-<instance>/`) and `XRCE_STATUS_DIR` (the
//! status directory itself) still move those parts elsewhere, under the same checks.
//!
//! **Rules.** A directory the agent creates is made with mode 0700 (`mkdir` with that mode,
//! then checked and corrected, whatever the umask), exclusively: `mkdir` fails on anything
//! already there. A directory that already exists is used only if it is a real directory (not
//! a symbolic link), owned by this process's effective user, with no permission bit for
//! group or others; anything else was made by someone else or loosened since, and the agent
//! refuses to start, saying which path, what it found and what to do
//! ([`RuntimeDirError`]). A directory the user or systemd *gives* (`$XRCE_RUNTIME_DIR`,
//! `$RUNTIME_DIRECTORY`, `XRCE_SESSION_DIR`, `XRCE_STATUS_DIR`) may be readable by others
//! (systemd makes `RuntimeDirectory=` 0755 by default) but must be ours and writable by us
//! alone: nothing can then be planted or renamed in it, and what the agent creates in it is
//! 0700 again.
//!
//! Files are created 0600 with `O_NOFOLLOW` (a symbolic link where a file will be is never
//! followed) and `O_CLOEXEC`; temporary files with `O_EXCL` too, then renamed into place.
//! Files read back are opened with `O_NOFOLLOW` and used only if they are regular files
//! owned by us ([`open_owned`]). Locks ([`LockFile`]) are `flock`s on 0600 files, held for a
//! process's life and released by the kernel when it dies, never inherited by children.

use std::ffi::OsString;
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

/// Overrides the runtime directory (any directory of this user, writable by it alone).
pub const RUNTIME_DIR_ENV: &str = "XRCE_RUNTIME_DIR";
/// Set by systemd for a unit with `RuntimeDirectory=` (colon-separated; the first is used).
pub const SYSTEMD_RUNTIME_DIR_ENV: &str = "RUNTIME_DIRECTORY";
/// The user's runtime directory (freedesktop.org base directory specification).
pub const XDG_RUNTIME_DIR_ENV: &str = "XDG_RUNTIME_DIR";
/// Moves the session stores: the parent of `xrce-sessions-<instance>/`.
pub const SESSION_DIR_ENV: &str = "XRCE_SESSION_DIR";
/// Moves the status reports: the status directory itself (shared by every instance).
pub const STATUS_DIR_ENV: &str = "XRCE_STATUS_DIR";
/// The supervisor's lock in the instance's directory.
pub const AGENT_LOCK: &str = "agent.lock";
/// A front-end's lock in its session-store directory.
pub const FRONTEND_LOCK: &str = "lock";
/// iceoryx2's root under the runtime directory (shared by the user's instances; the file
/// name prefix of each instance keeps them apart, as in `/dev/shm`).
pub const IPC_DIR: &str = "ipc";
/// Name of the session-store parent under [`SESSION_DIR_ENV`].
pub const SESSIONS_PREFIX: &str = "xrce-sessions-";

/// Mode of every directory the agent creates.
pub const DIR_MODE: u32 = 0o700;
/// Mode of every file the agent creates.
pub const FILE_MODE: u32 = 0o600;

/// What a directory or file was found to be when it could not be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FoundKind {
    /// A symbolic link.
    Symlink,
    /// A directory.
    Directory,
    /// A regular file.
    File,
    /// A FIFO, socket or device.
    Other,
}

impl std::fmt::Display for FoundKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FoundKind::Symlink => "a symbolic link",
            FoundKind::Directory => "a directory",
            FoundKind::File => "a regular file",
            FoundKind::Other => "a FIFO, socket or device",
        })
    }
}

/// Why the agent will not use a directory or file (every message names the path, what was
/// found and what to do).
#[derive(Debug, thiserror::Error)]
pub enum RuntimeDirError {
    /// A system call failed.
    #[error("{action} {path}: {source}")]
    Io {
        /// What was being done (`creating`, `opening`, ...).
        action: &'static str,
        /// Where.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// Something else stands where a directory (or a regular file) must be.
    #[error(
        "{path} is {found}, not {expected}: the agent does not follow links or use what it did \
         not make; remove it (if another user made it, that user or root must), or point \
         {RUNTIME_DIR_ENV} elsewhere"
    )]
    WrongKind {
        /// Where.
        path: PathBuf,
        /// What is there.
        found: FoundKind,
        /// What must be there (`a directory`, `a regular file`).
        expected: &'static str,
    },
    /// Owned by another user: it may have been planted to read or forge the agent's files.
    #[error(
        "{path} belongs to uid {owner}, not to this user (uid {euid}): another user may have \
         planted it to read or forge the agent's files; remove it (as uid {owner} or root) and \
         start again, or point {RUNTIME_DIR_ENV} to a directory of your own"
    )]
    WrongOwner {
        /// Where.
        path: PathBuf,
        /// Its owner.
        owner: u32,
        /// This process's effective user.
        euid: u32,
    },
    /// Group or others may read, enter or change it.
    #[error(
        "{path} has mode {mode:04o}: {who} may {what} it; if you made it and trust what is in \
         it, `chmod {fix:o} {path}`, else remove it and start again"
    )]
    LooseMode {
        /// Where.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
        /// The mode it should have.
        fix: u32,
        /// `group and others`, `group` or `others`.
        who: &'static str,
        /// `read or change` (private) or `change` (a given directory).
        what: &'static str,
    },
    /// Another process holds the lock.
    #[error(
        "{what} already runs with this instance: {path} is locked{}; stop it first, or give \
         this one another --instance",
        holder.map(|p| format!(" by process {p}")).unwrap_or_default()
    )]
    Locked {
        /// The lock file.
        path: PathBuf,
        /// What holds it (`another xrce-agent`, `front-end 0`).
        what: String,
        /// The pid written in the lock file by its holder, if readable.
        holder: Option<u32>,
    },
    /// Bigger than anything the agent writes there.
    #[error("{path} is {len} bytes, more than the {max} the agent ever writes there; ignored")]
    TooLarge {
        /// Where.
        path: PathBuf,
        /// Its length.
        len: u64,
        /// The largest accepted.
        max: u64,
    },
    /// Not a valid instance name (it is used as a directory name).
    #[error("instance name {0:?} must be 1-32 characters of [A-Za-z0-9_-]")]
    InstanceName(String),
}

impl RuntimeDirError {
    fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.to_path_buf();
        move |source| RuntimeDirError::Io {
            action,
            path,
            source,
        }
    }

    /// Whether the path was there but not of the right kind, owner or mode (a planted or
    /// loosened entry), rather than unreadable.
    pub fn is_untrusted(&self) -> bool {
        matches!(
            self,
            RuntimeDirError::WrongKind { .. }
                | RuntimeDirError::WrongOwner { .. }
                | RuntimeDirError::LooseMode { .. }
        )
    }
}

pub use crate::sys::euid;

/// The file-system types that keep files in memory (tmpfs, ramfs).
const MEMORY_FS: [u64; 2] = [0x0102_1994, 0x8584_58f6];

/// Where the runtime directory came from ([`runtime_root`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RootOrigin {
    /// `$XRCE_RUNTIME_DIR`.
    Env,
    /// systemd's `$RUNTIME_DIRECTORY`.
    Systemd,
    /// `$XDG_RUNTIME_DIR/xrce-agent`.
    Xdg,
    /// `/dev/shm/xrce-agent-<euid>` (or the temporary directory's).
    Shared,
}

impl RootOrigin {
    /// Whether the directory is given (checked, not created private by the agent).
    fn is_given(self) -> bool {
        matches!(self, RootOrigin::Env | RootOrigin::Systemd)
    }
}

/// The runtime directory of this process's agents, and where that choice came from. Pure:
/// nothing is created ([`ensure_runtime_root`] does).
pub fn runtime_root() -> (PathBuf, RootOrigin) {
    let nonempty = |name: &str| std::env::var_os(name).filter(|v| !v.is_empty());
    if let Some(dir) = nonempty(RUNTIME_DIR_ENV) {
        return (PathBuf::from(dir), RootOrigin::Env);
    }
    if let Some(dirs) = nonempty(SYSTEMD_RUNTIME_DIR_ENV) {
        let first: OsString = {
            use std::os::unix::ffi::{OsStrExt, OsStringExt};
            let bytes = dirs.as_bytes();
            let end = bytes.iter().position(|b| *b == b':').unwrap_or(bytes.len());
            OsString::from_vec(bytes[..end].to_vec())
        };
        if !first.is_empty() {
            return (PathBuf::from(first), RootOrigin::Systemd);
        }
    }
    if let Some(xdg) = nonempty(XDG_RUNTIME_DIR_ENV).map(PathBuf::from) {
        let ours = xdg.is_absolute()
            && std::fs::symlink_metadata(&xdg)
                .is_ok_and(|m| m.is_dir() && m.uid() == euid() && m.mode() & 0o022 == 0);
        if ours {
            return (xdg.join("xrce-agent"), RootOrigin::Xdg);
        }
    }
    let shm = Path::new("/dev/shm");
    let base = if shm.is_dir() {
        shm.to_path_buf()
    } else {
        std::env::temp_dir()
    };
    (
        base.join(format!("xrce-agent-{}", euid())),
        RootOrigin::Shared,
    )
}

/// Creates (0700) or checks the runtime directory; returns it. Warns once if it is not in
/// memory (the session store maps its files).
pub fn ensure_runtime_root() -> Result<PathBuf, RuntimeDirError> {
    let (root, origin) = runtime_root();
    let dir = if origin.is_given() {
        prepare_given_dir(&root)?
    } else {
        prepare_private_dir(&root)?
    };
    static WARNED: std::sync::Once = std::sync::Once::new();
    if crate::sys::fs_type(&dir).is_some_and(|t| !MEMORY_FS.contains(&t)) {
        WARNED.call_once(|| {
            tracing::warn!(dir = %root.display(), "the runtime directory is not in memory (tmpfs): session stores map their files there, and a full disk would kill a front-end with SIGBUS instead of an error");
        });
    }
    Ok(root)
}

/// Checks an instance name before it becomes a directory name.
fn check_instance(instance: &str) -> Result<(), RuntimeDirError> {
    if crate::names::valid_instance(instance) {
        Ok(())
    } else {
        Err(RuntimeDirError::InstanceName(instance.to_string()))
    }
}

/// The directory of `instance` (pure).
pub fn instance_dir(instance: &str) -> PathBuf {
    runtime_root().0.join(instance)
}

/// The file a new supervisor of `instance` keeps while it waits for its predecessor's
/// processes to stop (pure): a front-end whose supervisor died holds its port until this
/// appears ([`successor_waiting`]), so that its clients' datagrams meanwhile are not answered
/// with ICMP errors (some client libraries count each as a wait, and give up the sooner).
pub fn successor_marker(instance: &str) -> PathBuf {
    instance_dir(instance).join("successor")
}

/// Whether a successor supervisor of `instance` waits ([`successor_marker`]; in the private
/// instance directory, where only this user creates files).
pub fn successor_waiting(instance: &str) -> bool {
    std::fs::symlink_metadata(successor_marker(instance)).is_ok_and(|m| m.is_file())
}

/// Says that a successor waits (a new 0600 file, never through a link), until
/// [`clear_successor`].
pub fn announce_successor(instance: &str) -> Result<(), RuntimeDirError> {
    let path = successor_marker(instance);
    let _ = std::fs::remove_file(&path);
    files::create_temp(&path).map(drop)
}

/// Takes the successor's marker away.
pub fn clear_successor(instance: &str) {
    let _ = std::fs::remove_file(successor_marker(instance));
}

/// A random secret of an instance, kept in its private directory: its name there, and its
/// length in hex digits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Secret {
    /// File name in the instance's directory.
    pub file: &'static str,
    /// Hex digits.
    pub len: usize,
}

/// The random part of an instance's names in `/dev/shm` and iceoryx2's root. `/dev/shm` is
/// shared by every local user and its names are visible to all: with a part nobody else can
/// read beforehand, no one can plant files under the names an instance is about to take. A
/// supervisor draws a new one at each start ([`renew_secret`]), so names seen during an
/// earlier run are no use. Short: iceoryx2's socket paths must fit 108 bytes.
pub const SHM_TOKEN: Secret = Secret {
    file: "shm-token",
    len: 8,
};

/// The file holding `secret` of `instance` (pure).
pub fn secret_file(instance: &str, secret: Secret) -> PathBuf {
    instance_dir(instance).join(secret.file)
}

/// `secret` of `instance`: read from the private instance directory, or made there if none
/// is (the first process of an instance makes it, exclusively; the others read it).
pub fn secret(instance: &str, secret: Secret) -> Result<String, RuntimeDirError> {
    use std::os::unix::fs::OpenOptionsExt;
    ensure_instance_dir(instance)?;
    let path = secret_file(instance, secret);
    for _ in 0..50 {
        match files::read_owned(&path, 256) {
            Ok(b) => match parse_secret(&b, secret.len) {
                Some(t) => return Ok(t),
                // Being written by the process that made it.
                None => std::thread::sleep(std::time::Duration::from_millis(2)),
            },
            Err(RuntimeDirError::Io { source, .. })
                if source.kind() == std::io::ErrorKind::NotFound =>
            {
                let token = new_secret(secret.len)?;
                let made = std::fs::OpenOptions::new()
                    .write(true)
                    .create_new(true)
                    .mode(FILE_MODE)
                    .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
                    .open(&path);
                match made {
                    Ok(mut f) => {
                        use std::io::Write;
                        f.write_all(token.as_bytes())
                            .map_err(RuntimeDirError::io("writing", &path))?;
                        return Ok(token);
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                    Err(e) => return Err(RuntimeDirError::io("creating", &path)(e)),
                }
            }
            Err(e) => return Err(e),
        }
    }
    // Still no valid secret: one written half by a process that died; replace it.
    renew_secret(instance, secret)
}

/// Draws a new `secret` for `instance`, for the processes started from now on (a
/// supervisor's first steps, while it holds the instance's lock).
pub fn renew_secret(instance: &str, secret: Secret) -> Result<String, RuntimeDirError> {
    ensure_instance_dir(instance)?;
    let path = secret_file(instance, secret);
    let token = new_secret(secret.len)?;
    let tmp = instance_dir(instance).join(format!(".{}.{}", secret.file, std::process::id()));
    files::write_atomically(&path, &tmp, token.as_bytes())?;
    Ok(token)
}

fn parse_secret(b: &[u8], len: usize) -> Option<String> {
    let t = std::str::from_utf8(b).ok()?.trim();
    (t.len() == len && t.bytes().all(|c| c.is_ascii_hexdigit())).then(|| t.to_ascii_lowercase())
}

fn new_secret(len: usize) -> Result<String, RuntimeDirError> {
    let mut bytes = vec![0u8; len.div_ceil(2)];
    getrandom::getrandom(&mut bytes).map_err(|e| RuntimeDirError::Io {
        action: "drawing random bytes for",
        path: PathBuf::from("a secret"),
        source: std::io::Error::other(e.to_string()),
    })?;
    let mut hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    hex.truncate(len);
    Ok(hex)
}

/// Creates or checks the runtime directory and the directory of `instance` in it.
pub fn ensure_instance_dir(instance: &str) -> Result<PathBuf, RuntimeDirError> {
    check_instance(instance)?;
    let root = ensure_runtime_root()?;
    let dir = root.join(instance);
    prepare_private_dir(&dir)?;
    Ok(dir)
}

/// Checks the runtime directory and the directory of `instance` in it, where they exist
/// (nothing is created): every process of an agent refuses to run on a planted or loosened
/// one, whichever process comes first.
pub fn check_instance_dir(instance: &str) -> Result<(), RuntimeDirError> {
    check_instance(instance)?;
    let (root, origin) = runtime_root();
    let exists = |p: &Path| std::fs::symlink_metadata(p).is_ok();
    if exists(&root) {
        check_dir(&root, if origin.is_given() { 0o022 } else { 0o077 })?;
        let dir = root.join(instance);
        if exists(&dir) {
            check_dir(&dir, 0o077)?;
        }
    }
    Ok(())
}

/// The parent of the front-ends' session stores of `instance` (pure): `XRCE_SESSION_DIR`'s
/// `xrce-sessions-<instance>/` when set, else `<runtime>/<instance>/sessions/`.
pub fn sessions_dir(instance: &str) -> PathBuf {
    match std::env::var_os(SESSION_DIR_ENV).filter(|v| !v.is_empty()) {
        Some(dir) => PathBuf::from(dir).join(format!("{SESSIONS_PREFIX}{instance}")),
        None => instance_dir(instance).join("sessions"),
    }
}

/// Creates or checks [`sessions_dir`] and every directory above it that the agent owns.
pub fn ensure_sessions_dir(instance: &str) -> Result<PathBuf, RuntimeDirError> {
    check_instance(instance)?;
    let dir = match std::env::var_os(SESSION_DIR_ENV).filter(|v| !v.is_empty()) {
        Some(parent) => {
            let parent = PathBuf::from(parent);
            prepare_given_dir(&parent)?;
            parent.join(format!("{SESSIONS_PREFIX}{instance}"))
        }
        None => ensure_instance_dir(instance)?.join("sessions"),
    };
    prepare_private_dir(&dir)?;
    Ok(dir)
}

/// The session store of front-end `id` of `instance` (pure).
pub fn frontend_store_dir(instance: &str, id: u32) -> PathBuf {
    sessions_dir(instance).join(format!("frontend-{id}"))
}

/// Creates or checks [`frontend_store_dir`] (and the directories above it).
pub fn ensure_frontend_store_dir(instance: &str, id: u32) -> Result<PathBuf, RuntimeDirError> {
    let dir = ensure_sessions_dir(instance)?.join(format!("frontend-{id}"));
    prepare_private_dir(&dir)?;
    Ok(dir)
}

/// The status directory of `instance` (pure): `XRCE_STATUS_DIR` when set, else
/// `<runtime>/<instance>/status/`.
pub fn status_dir(instance: &str) -> PathBuf {
    match std::env::var_os(STATUS_DIR_ENV).filter(|v| !v.is_empty()) {
        Some(dir) => PathBuf::from(dir),
        None => instance_dir(instance).join("status"),
    }
}

/// Creates or checks [`status_dir`] (and the directories above it).
pub fn ensure_status_dir(instance: &str) -> Result<PathBuf, RuntimeDirError> {
    match std::env::var_os(STATUS_DIR_ENV).filter(|v| !v.is_empty()) {
        Some(dir) => {
            let dir = PathBuf::from(dir);
            prepare_given_dir(&dir)?;
            Ok(dir)
        }
        None => {
            let dir = ensure_instance_dir(instance)?.join("status");
            prepare_private_dir(&dir)?;
            Ok(dir)
        }
    }
}

/// The instances with a directory in the runtime directory, with their status directories
/// (`XRCE_STATUS_DIR`, when set, is the one status directory, with an empty name). The
/// runtime directory is checked first: one planted by another user is an error, not a list.
pub fn list_instances() -> Result<Vec<(String, PathBuf)>, RuntimeDirError> {
    if let Some(dir) = std::env::var_os(STATUS_DIR_ENV).filter(|v| !v.is_empty()) {
        return Ok(vec![(String::new(), PathBuf::from(dir))]);
    }
    let (root, origin) = runtime_root();
    match std::fs::symlink_metadata(&root) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        _ => {
            if origin.is_given() {
                check_dir(&root, 0o022)?;
            } else {
                check_dir(&root, 0o077)?;
            }
        }
    }
    let entries = std::fs::read_dir(&root).map_err(RuntimeDirError::io("listing", &root))?;
    let mut out: Vec<(String, PathBuf)> = entries
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            (name != IPC_DIR && crate::names::valid_instance(&name))
                .then(|| (name, e.path().join("status")))
        })
        .collect();
    out.sort();
    Ok(out)
}

/// iceoryx2's root directory for `instance` (pure): `<runtime>/ipc/`, unless the event
/// sockets iceoryx2 makes there would not fit a Unix socket path (108 bytes) with this
/// instance's file name prefix; then `/dev/shm/xrce-ipc-<euid>/` (or the temporary
/// directory's), which is as private. Ends with `/`, as iceoryx2 expects.
pub fn ipc_root(instance: &str) -> PathBuf {
    let preferred = runtime_root().0.join(IPC_DIR);
    if ipc_root_fits(&preferred, instance) {
        return with_slash(preferred);
    }
    let shm = Path::new("/dev/shm");
    let base = if shm.is_dir() {
        shm.to_path_buf()
    } else {
        std::env::temp_dir()
    };
    with_slash(base.join(format!("xrce-ipc-{}", euid())))
}

fn with_slash(p: PathBuf) -> PathBuf {
    let mut s = p.into_os_string();
    s.push("/");
    PathBuf::from(s)
}

/// Longest event-socket file name iceoryx2 makes in its root for an instance (past its
/// prefix): a listener id (a `u128` in decimal, up to 39 digits) and the suffix.
pub const IPC_SOCKET_NAME_MAX: usize = 39 + crate::names::EVENT_SUFFIX.len();
/// Longest Unix socket path (`sun_path`, with its terminating NUL).
const SUN_PATH_MAX: usize = 108;

/// Whether every event socket of `instance` fits under `root`.
pub fn ipc_root_fits(root: &Path, instance: &str) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let root_len = root.as_os_str().as_bytes().len() + 1;
    // The instance's prefix, its random part and the `_` after it.
    let prefix_len = crate::names::file_prefix(instance).len() + SHM_TOKEN.len + 1;
    root_len + prefix_len + IPC_SOCKET_NAME_MAX < SUN_PATH_MAX
}

/// Creates or checks iceoryx2's root for `instance` ([`ipc_root`]) and its `services/` and
/// `nodes/` directories (0700: iceoryx2 would make them 0750 and 0755).
pub fn ensure_ipc_root(instance: &str) -> Result<PathBuf, RuntimeDirError> {
    check_instance(instance)?;
    let root = ipc_root(instance);
    let preferred = with_slash(runtime_root().0.join(IPC_DIR));
    if root == preferred {
        ensure_runtime_root()?;
    }
    prepare_private_dir(&root)?;
    for sub in ["services", "nodes"] {
        prepare_private_dir(&root.join(sub))?;
    }
    Ok(root)
}

mod files;
use files::check_dir;
pub use files::{
    create_temp, lock_is_free, open_owned, prepare_dir_for_writing, prepare_given_dir,
    prepare_private_dir, read_owned, write_atomically, LockFile,
};

/// Takes the supervisor's lock of `instance` (creating the instance's directory): a second
/// supervisor of the same instance is refused before it removes or reads anything.
pub fn lock_instance(instance: &str) -> Result<LockFile, RuntimeDirError> {
    // Another agent's sweep may hold a stopped instance's lock for a moment while it
    // removes what no restart can take over: tried for half a second before refusing.
    let mut tries = 0;
    loop {
        let dir = ensure_instance_dir(instance)?;
        match LockFile::acquire(&dir.join(AGENT_LOCK), "another xrce-agent") {
            Err(RuntimeDirError::Locked { .. }) if tries < 25 => {
                tries += 1;
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            other => return other,
        }
    }
}

/// Removes the session stores of `instance` whose front-end is gone (its lock is free), for
/// a supervisor that starts or stops; a store whose front-end still runs (a child of a
/// supervisor killed hard, still stopping) is kept. Returns how many stores were kept.
pub fn clear_sessions(instance: &str) -> usize {
    let dir = sessions_dir(instance);
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return 0;
    };
    let mut kept = 0;
    for e in entries.flatten() {
        let path = e.path();
        let is_dir = e.file_type().is_ok_and(|t| t.is_dir());
        if is_dir {
            match LockFile::acquire(&path.join(FRONTEND_LOCK), "") {
                Ok(lock) => {
                    let _ = std::fs::remove_dir_all(&path);
                    drop(lock);
                }
                Err(RuntimeDirError::Locked { holder, .. }) => {
                    tracing::warn!(store = %path.display(), ?holder, "a front-end still runs with this session store; kept");
                    kept += 1;
                }
                Err(_) => {
                    let _ = std::fs::remove_dir_all(&path);
                }
            }
        } else {
            let _ = std::fs::remove_file(&path);
        }
    }
    if kept == 0 {
        let _ = std::fs::remove_dir(&dir);
    }
    kept
}

/// Removes what a stopping instance leaves in the runtime directory: its session stores
/// (see [`clear_sessions`]), its status directory, then its lock file and its directory
/// (if empty); `lock`, the supervisor's own, is released last.
pub fn remove_instance(instance: &str, lock: LockFile) {
    clear_sessions(instance);
    let _ = std::fs::remove_dir_all(status_dir(instance));
    remove_instance_dir(instance, lock);
}

/// Removes the instance's own status directory (not `XRCE_STATUS_DIR`), its lock and its
/// directory (if empty then): what a supervisor that fails to start leaves.
pub fn remove_instance_dir(instance: &str, lock: LockFile) {
    let dir = instance_dir(instance);
    let _ = std::fs::remove_dir_all(dir.join("status"));
    let _ = std::fs::remove_file(dir.join(SHM_TOKEN.file));
    let _ = std::fs::remove_file(lock.path());
    let _ = std::fs::remove_dir(&dir);
    drop(lock);
}

/// Removes the directory of an instance whose supervisor is gone (its lock is free; taken
/// while the directory is removed), for a supervisor that tidies up after dead agents;
/// returns whether it did. One whose lock is held (a running agent) is left alone.
pub fn remove_instance_if_unlocked(instance: &str) -> bool {
    if check_instance(instance).is_err() {
        return false;
    }
    let dir = instance_dir(instance);
    if check_dir(&dir, 0o077).is_err() {
        return false;
    }
    match LockFile::acquire(&dir.join(AGENT_LOCK), "") {
        Ok(lock) => {
            // Not `XRCE_STATUS_DIR`, shared by every instance.
            clear_sessions(instance);
            remove_instance_dir(instance, lock);
            true
        }
        Err(_) => false,
    }
}

#[cfg(test)]
mod tests;
