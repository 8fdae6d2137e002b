use super::*;

use std::os::unix::fs::{symlink, PermissionsExt};

fn scratch(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xrce-rtdir-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn mode(p: &Path) -> u32 {
    std::fs::symlink_metadata(p).expect("exists").mode() & 0o7777
}

#[test]
fn directories_are_made_private_whatever_exists() {
    let d = scratch("dirs");
    prepare_private_dir(&d).expect("created");
    assert_eq!(mode(&d), 0o700);
    prepare_private_dir(&d).expect("ours and private: accepted");
    // Loosened: refused, with the mode in the message.
    std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o777)).expect("chmod");
    let e = prepare_private_dir(&d).expect_err("loose");
    assert!(
        matches!(e, RuntimeDirError::LooseMode { mode: 0o777, .. }),
        "{e}"
    );
    assert!(
        e.to_string().contains("0777") && e.to_string().contains("chmod 700"),
        "{e}"
    );
    // Given directories may be readable, not writable, by others.
    std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    prepare_given_dir(&d).expect("0755 given: accepted");
    assert!(prepare_private_dir(&d).is_err());
    std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o700)).expect("chmod");
    // A link where a directory must be is not followed.
    let link = d.join("link");
    let target = d.join("target");
    prepare_private_dir(&target).expect("target");
    symlink(&target, &link).expect("symlink");
    let e = prepare_private_dir(&link).expect_err("link");
    assert!(
        matches!(
            e,
            RuntimeDirError::WrongKind {
                found: FoundKind::Symlink,
                ..
            }
        ),
        "{e}"
    );
    assert!(prepare_given_dir(&link).is_err());
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_directory_of_another_user_is_refused() {
    if euid() != 0 {
        return; // only root can make one
    }
    let d = scratch("owner");
    prepare_private_dir(&d).expect("created");
    std::os::unix::fs::chown(&d, Some(65534), None).expect("chown");
    let e = prepare_private_dir(&d).expect_err("not ours");
    assert!(
        matches!(e, RuntimeDirError::WrongOwner { owner: 65534, .. }),
        "{e}"
    );
    assert!(e.to_string().contains("uid 65534"), "{e}");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn files_are_private_and_links_are_never_followed() {
    let d = scratch("files");
    prepare_private_dir(&d).expect("dir");
    let victim = d.join("victim");
    std::fs::write(&victim, b"untouched").expect("victim");
    // A link planted at the temporary name: replaced, the victim untouched.
    symlink(&victim, d.join("x.tmp")).expect("symlink");
    write_atomically(&d.join("x"), &d.join("x.tmp"), b"new").expect("written");
    assert_eq!(std::fs::read(&victim).expect("victim"), b"untouched");
    assert_eq!(std::fs::read(d.join("x")).expect("x"), b"new");
    assert_eq!(mode(&d.join("x")), 0o600);
    // A link read back is refused; so is a FIFO (without blocking).
    symlink(&victim, d.join("y")).expect("symlink");
    let e = read_owned(&d.join("y"), 100).expect_err("link");
    assert!(e.is_untrusted(), "{e}");
    let fifo = d.join("fifo");
    assert!(std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success()));
    assert!(read_owned(&fifo, 100).expect_err("fifo").is_untrusted());
    assert_eq!(read_owned(&d.join("x"), 100).expect("ours"), b"new");
    assert!(matches!(
        read_owned(&d.join("x"), 2),
        Err(RuntimeDirError::TooLarge { .. })
    ));
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_lock_is_exclusive_until_dropped() {
    let d = scratch("lock");
    prepare_private_dir(&d).expect("dir");
    let path = d.join("agent.lock");
    let held = LockFile::acquire(&path, "another xrce-agent").expect("first");
    assert_eq!(mode(&path), 0o600);
    let e = LockFile::acquire(&path, "another xrce-agent").expect_err("second");
    match &e {
        RuntimeDirError::Locked { holder, .. } => {
            assert_eq!(*holder, Some(std::process::id()))
        }
        other => panic!("{other}"),
    }
    assert!(e.to_string().contains("already runs"), "{e}");
    assert!(!lock_is_free(&path));
    drop(held);
    // A process another test spawns at this moment holds a copy of every descriptor, the
    // lock's included, from its fork to its exec (close-on-exec): the lock is free once
    // that exec happened, within milliseconds.
    let free = (0..100).any(|_| {
        lock_is_free(&path) || {
            std::thread::sleep(std::time::Duration::from_millis(10));
            false
        }
    });
    assert!(free, "the lock is free once dropped");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn sockets_of_long_instance_names_move_to_a_shorter_root() {
    let long = "a".repeat(32);
    let deep = Path::new("/run/user/4294967294/some/deep/runtime/directory/xrce-agent/ipc");
    assert!(!ipc_root_fits(deep, &long));
    assert!(ipc_root_fits(Path::new("/dev/shm/xrce-ipc-65534"), &long));
}
