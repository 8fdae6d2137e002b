//! The checked file operations every file of the runtime directory goes through: a
//! directory or file is used only if it is what it claims to be (no symbolic link, ours, no
//! permission for others where it must be private), and what is created is private from
//! its first byte.

use std::fs::File;
use std::io::{Read, Write};
use std::os::unix::fs::{DirBuilderExt, MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use super::{euid, FoundKind, RuntimeDirError, DIR_MODE, FILE_MODE};

fn kind_of(m: &std::fs::Metadata) -> FoundKind {
    let t = m.file_type();
    if t.is_symlink() {
        FoundKind::Symlink
    } else if t.is_dir() {
        FoundKind::Directory
    } else if t.is_file() {
        FoundKind::File
    } else {
        FoundKind::Other
    }
}

/// Checks that `path` is a real directory of ours with none of the bits of `forbidden`
/// (0o077: private; 0o022: given); returns it opened (`O_NOFOLLOW`, so what was checked is
/// what is open).
pub(super) fn check_dir(path: &Path, forbidden: u32) -> Result<File, RuntimeDirError> {
    let lmeta = std::fs::symlink_metadata(path).map_err(RuntimeDirError::io("inspecting", path))?;
    if !lmeta.is_dir() {
        return Err(RuntimeDirError::WrongKind {
            path: path.to_path_buf(),
            found: kind_of(&lmeta),
            expected: "a directory",
        });
    }
    let dir = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_DIRECTORY | libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .map_err(RuntimeDirError::io("opening", path))?;
    let meta = dir
        .metadata()
        .map_err(RuntimeDirError::io("inspecting", path))?;
    check_owner_mode(path, &meta, forbidden)?;
    Ok(dir)
}

/// Refuses what another user owns.
fn check_owner(path: &Path, meta: &std::fs::Metadata) -> Result<(), RuntimeDirError> {
    let me = euid();
    if meta.uid() != me {
        return Err(RuntimeDirError::WrongOwner {
            path: path.to_path_buf(),
            owner: meta.uid(),
            euid: me,
        });
    }
    Ok(())
}

fn check_owner_mode(
    path: &Path,
    meta: &std::fs::Metadata,
    forbidden: u32,
) -> Result<(), RuntimeDirError> {
    check_owner(path, meta)?;
    let mode = meta.mode() & 0o7777;
    let loose = mode & forbidden;
    if loose != 0 {
        let who = match (loose & 0o070 != 0, loose & 0o007 != 0) {
            (true, true) => "group and others",
            (true, false) => "group",
            _ => "others",
        };
        let fix = if meta.is_dir() { DIR_MODE } else { FILE_MODE };
        return Err(RuntimeDirError::LooseMode {
            path: path.to_path_buf(),
            mode,
            fix: if forbidden == 0o022 {
                mode & !0o022
            } else {
                fix
            },
            who,
            what: if forbidden == 0o022 {
                "change"
            } else {
                "read or change"
            },
        });
    }
    Ok(())
}

/// Creates the directory `path` with mode 0700 (its parent must exist), or checks the one
/// there: a real directory, ours, private (no group or other bits). Returns it opened.
pub fn prepare_private_dir(path: &Path) -> Result<File, RuntimeDirError> {
    let created = match std::fs::DirBuilder::new().mode(DIR_MODE).create(path) {
        Ok(()) => true,
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => false,
        Err(e) => return Err(RuntimeDirError::io("creating", path)(e)),
    };
    if created {
        // The umask may have taken bits away (never added any): put them back, by path
        // (a directory with no read bit for its owner could not be opened to check it). It
        // was just made, exclusively, in a directory where nobody else can rename it.
        let meta =
            std::fs::symlink_metadata(path).map_err(RuntimeDirError::io("inspecting", path))?;
        if meta.is_dir() && meta.uid() == euid() && meta.mode() & 0o777 != DIR_MODE {
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(DIR_MODE))
                .map_err(RuntimeDirError::io("setting the mode of", path))?;
        }
    }
    check_dir(path, 0o077)
}

/// Creates the given directory `path` (and missing parents) with mode 0700, or checks the
/// one there: a real directory, ours, writable by us alone. Returns it opened.
pub fn prepare_given_dir(path: &Path) -> Result<File, RuntimeDirError> {
    if std::fs::symlink_metadata(path).is_err() {
        match std::fs::DirBuilder::new()
            .mode(DIR_MODE)
            .recursive(true)
            .create(path)
        {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(RuntimeDirError::io("creating", path)(e)),
        }
    }
    check_dir(path, 0o022)
}

/// Creates the directory `path` (0700) if missing, else checks it is a real directory of ours
/// that only we can change: for writers that find their directory prepared already (status
/// reports), at the cost of one `lstat`.
pub fn prepare_dir_for_writing(path: &Path) -> Result<(), RuntimeDirError> {
    match std::fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => prepare_private_dir(path).map(drop),
        _ => check_dir(path, 0o022).map(drop),
    }
}

fn open_flags() -> i32 {
    libc::O_NOFOLLOW | libc::O_CLOEXEC
}

/// Sets `file`'s mode to 0600 if it is anything else (the umask, or an earlier version's
/// 0644), so that a file we made is private whatever the umask was.
fn make_private(file: &File, path: &Path) -> Result<(), RuntimeDirError> {
    let meta = file
        .metadata()
        .map_err(RuntimeDirError::io("inspecting", path))?;
    if meta.mode() & 0o7777 != FILE_MODE {
        file.set_permissions(std::fs::Permissions::from_mode(FILE_MODE))
            .map_err(RuntimeDirError::io("setting the mode of", path))?;
    }
    Ok(())
}

/// Creates the new file `path` (0600, `O_EXCL | O_NOFOLLOW`) for reading and writing. A file
/// or link already there is removed first (unlinking never follows a link): for temporary
/// files, whose name is this process's alone, that something else left.
pub fn create_temp(path: &Path) -> Result<File, RuntimeDirError> {
    let open = || {
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .mode(FILE_MODE)
            .custom_flags(open_flags())
            .open(path)
    };
    let file = match open() {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            if let Ok(m) = std::fs::symlink_metadata(path) {
                if !m.is_file() {
                    tracing::warn!(path = %path.display(), found = %kind_of(&m), "removed something planted where a temporary file is made (not followed)");
                }
            }
            std::fs::remove_file(path).map_err(RuntimeDirError::io("removing", path))?;
            open().map_err(RuntimeDirError::io("creating", path))?
        }
        Err(e) => return Err(RuntimeDirError::io("creating", path)(e)),
    };
    make_private(&file, path)?;
    Ok(file)
}

/// Replaces `path` with `bytes` atomically: written to the new private file `tmp`
/// ([`create_temp`]) and renamed over `path` (a link at `path` is replaced, not followed).
pub fn write_atomically(path: &Path, tmp: &Path, bytes: &[u8]) -> Result<(), RuntimeDirError> {
    let mut f = create_temp(tmp)?;
    if let Err(e) = f.write_all(bytes) {
        drop(f);
        let _ = std::fs::remove_file(tmp);
        return Err(RuntimeDirError::io("writing", tmp)(e));
    }
    drop(f);
    std::fs::rename(tmp, path).map_err(RuntimeDirError::io("renaming into", path))
}

/// A file opened without following links, checked to be a regular file: a link where the
/// file should be (`ELOOP`) or anything but a regular file is refused.
fn regular_file(
    path: &Path,
    opened: std::io::Result<File>,
) -> Result<(File, std::fs::Metadata), RuntimeDirError> {
    let file = opened.map_err(|e| {
        // ELOOP: the last component is a symbolic link.
        if e.raw_os_error() == Some(libc::ELOOP) {
            RuntimeDirError::WrongKind {
                path: path.to_path_buf(),
                found: FoundKind::Symlink,
                expected: "a regular file",
            }
        } else {
            RuntimeDirError::io("opening", path)(e)
        }
    })?;
    let meta = file
        .metadata()
        .map_err(RuntimeDirError::io("inspecting", path))?;
    if !meta.is_file() {
        return Err(RuntimeDirError::WrongKind {
            path: path.to_path_buf(),
            found: kind_of(&meta),
            expected: "a regular file",
        });
    }
    Ok((file, meta))
}

/// Opens `path` (`O_NOFOLLOW`, and `O_NONBLOCK` so that a planted FIFO cannot block) and
/// checks that it is a regular file owned by us; for writing too if `write`. What fails
/// the check was not written by the agent and must not be used.
pub fn open_owned(path: &Path, write: bool) -> Result<File, RuntimeDirError> {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .write(write)
        .custom_flags(open_flags() | libc::O_NONBLOCK)
        .open(path);
    let (file, meta) = regular_file(path, file)?;
    check_owner(path, &meta)?;
    Ok(file)
}

/// The bytes of `path`, at most `max` of them, if it is a regular file of ours
/// ([`open_owned`]).
pub fn read_owned(path: &Path, max: u64) -> Result<Vec<u8>, RuntimeDirError> {
    let file = open_owned(path, false)?;
    let len = file
        .metadata()
        .map_err(RuntimeDirError::io("inspecting", path))?
        .len();
    if len > max {
        return Err(RuntimeDirError::TooLarge {
            path: path.to_path_buf(),
            len,
            max,
        });
    }
    let mut out = Vec::with_capacity(len as usize);
    file.take(max)
        .read_to_end(&mut out)
        .map_err(RuntimeDirError::io("reading", path))?;
    Ok(out)
}

/// An exclusive `flock` on a 0600 lock file, held until dropped (or the process ends: the
/// kernel releases it then, so a successor of a process killed hard takes it at once). The
/// descriptor is close-on-exec, so no child inherits the lock and outlives its holder with it.
#[derive(Debug)]
pub struct LockFile {
    /// Kept open: the lock lives as long as this open file description.
    _file: File,
    path: PathBuf,
}

impl LockFile {
    /// Takes the lock at `path` (created if missing) without waiting; `what` names the
    /// holder kind in the error (`another xrce-agent`, `front-end 0`). The holder's pid is
    /// written into the file, for the message a refused process prints.
    pub fn acquire(path: &Path, what: &str) -> Result<Self, RuntimeDirError> {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(FILE_MODE)
            .custom_flags(open_flags())
            .open(path);
        let (file, meta) = regular_file(path, file)?;
        check_owner_mode(path, &meta, 0)?;
        make_private(&file, path)?;
        if !crate::sys::try_flock(&file).map_err(RuntimeDirError::io("locking", path))? {
            let mut text = String::new();
            let _ = (&file).take(32).read_to_string(&mut text);
            return Err(RuntimeDirError::Locked {
                path: path.to_path_buf(),
                what: what.to_string(),
                holder: text.trim().parse().ok(),
            });
        }
        let pid = format!("{}\n", std::process::id());
        let _ = file.set_len(0);
        {
            use std::os::unix::fs::FileExt;
            let _ = file.write_all_at(pid.as_bytes(), 0);
        }
        Ok(LockFile {
            _file: file,
            path: path.to_path_buf(),
        })
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Whether the lock at `path` is free (nobody holds it), taking and releasing it to know;
/// `false` when it cannot be told.
pub fn lock_is_free(path: &Path) -> bool {
    match LockFile::acquire(path, "") {
        Ok(l) => {
            drop(l);
            true
        }
        Err(_) => false,
    }
}
