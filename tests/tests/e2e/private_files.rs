//! An agent's files are its user's alone (issue 29, "private files"): everything it creates
//! in its runtime directory is 0700/0600 and owned by it, another local user (`nobody`)
//! cannot read the session store, iceoryx2's files are private too, a runtime or instance
//! directory planted beforehand is refused with a clear message, a link planted where a file
//! will be created is not followed, and a second front-end or agent on the same instance is
//! refused while the first one keeps its sessions.
//!
//! Every agent here gets its own runtime directory (`XRCE_RUNTIME_DIR`, under `/dev/shm` so
//! that it is a tmpfs like the default one) so the test sees exactly what it created. The
//! parts run as another user need root (CI runs the tests as root; root itself reads every
//! file whatever its mode, so those parts run `setpriv` to become `nobody`).

use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind, ObjectId, VariantExtra};
use xrce_tests::{
    binaries, free_udp_port, output_within, unique_instance, AgentProcess, TestClient,
};

const SECOND: Duration = Duration::from_secs(1);
/// The client's key, and its name in the session store.
const KEY: [u8; 4] = [0xAA, 0xAA, 0xBB, 0xBB];
const KEY_NAME: &str = "AAAABBBB";
/// `nobody` and `nogroup` (65534 on Debian, Ubuntu and Fedora alike).
const NOBODY: u32 = 65534;

fn euid() -> u32 {
    xrce_ipc::runtime_dir::euid()
}

fn is_root() -> bool {
    euid() == 0
}

/// A fresh directory for one test under `/dev/shm` (0755: another user may enter it, so
/// only the agent's own modes keep that user out).
fn scratch(tag: &str) -> PathBuf {
    let base = if Path::new("/dev/shm").is_dir() {
        PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let d = base.join(format!("xrce-pf-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir(&d).expect("scratch directory");
    std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    d
}

fn env_of(rt: &Path) -> [(&'static str, String); 1] {
    [("XRCE_RUNTIME_DIR", rt.display().to_string())]
}

fn start_agent(tag: &str, rt: &Path) -> AgentProcess {
    let env = env_of(rt);
    let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (*k, v.as_str())).collect();
    AgentProcess::builder(tag).env(&env).start()
}

/// Every entry under `dir` (not following links), `dir` first.
fn walk(dir: &Path) -> Vec<(PathBuf, std::fs::Metadata)> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(p) = todo.pop() {
        let Ok(m) = std::fs::symlink_metadata(&p) else {
            continue;
        };
        if m.is_dir() {
            if let Ok(entries) = std::fs::read_dir(&p) {
                todo.extend(entries.flatten().map(|e| e.path()));
            }
        }
        out.push((p, m));
    }
    out
}

/// The session store of front-end 0.
fn store_of(rt: &Path, instance: &str) -> PathBuf {
    rt.join(instance).join("sessions").join("frontend-0")
}

/// Waits up to `d` for `cond`.
fn wait_until(d: Duration, mut cond: impl FnMut() -> bool) -> bool {
    let end = Instant::now() + d;
    while Instant::now() < end {
        if cond() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    cond()
}

/// A client with the test's key, a session and a writer's chain of objects (so its state
/// and objects are stored); waits until both files are in the store.
fn client_with_objects(agent: &AgentProcess, rt: &Path, domain: i16) -> TestClient {
    let mut c = TestClient::new(agent.addr(), KEY);
    c.connect(10 * SECOND);
    c.setup_publisher(domain);
    let store = store_of(rt, agent.instance());
    assert!(
        wait_until(10 * SECOND, || {
            store.join(format!("{KEY_NAME}.state")).is_file()
                && store.join(format!("{KEY_NAME}.objects")).is_file()
        }),
        "the session was not stored in {}",
        store.display()
    );
    c
}

/// Runs `args` as `nobody` (no groups); its output.
fn as_nobody(args: &[&str]) -> std::process::Output {
    let mut cmd = Command::new("setpriv");
    cmd.args([
        &format!("--reuid={NOBODY}"),
        &format!("--regid={NOBODY}"),
        "--clear-groups",
        "--",
    ])
    .args(args);
    output_within(&mut cmd, 10 * SECOND)
}

/// `xrce-agent <args>` with the runtime directory `rt`, run to its end.
fn agent_command(args: &[&str], rt: &Path) -> std::process::Output {
    let mut cmd = Command::new(binaries().join("xrce-agent"));
    cmd.args(args)
        .env("XRCE_RUNTIME_DIR", rt)
        .env("XRCE_LOG", "info");
    output_within(&mut cmd, 30 * SECOND)
}

/// The shared-memory files of `instance` in `/dev/shm`.
fn shm_files(instance: &str) -> Vec<PathBuf> {
    let prefix = format!("xrce_{instance}_");
    std::fs::read_dir("/dev/shm")
        .map(|d| {
            d.flatten()
                .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
                .map(|e| e.path())
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn an_agents_files_are_private_to_its_user() {
    // Short names: iceoryx2's event sockets must fit 108 bytes under `<rt>/ipc/` (with the
    // instance's name and the random part of its names), or its root moves to /dev/shm.
    let dir = scratch("pv");
    let rt = dir.join("rt");
    let agent = start_agent("p", &rt);
    let instance = agent.instance().to_string();
    let _client = client_with_objects(&agent, &rt, 121);
    // Wait for the status reports too (every second).
    assert!(wait_until(5 * SECOND, || {
        rt.join(&instance).join("status/frontend-0.json").is_file()
    }));

    // Everything in the runtime directory is ours; our directories 0700, our files 0600;
    // iceoryx2's files (under ipc/) have no bit for group or others, and its per-node
    // directories (0750, iceoryx2's choice) none for others, inside 0700 ones.
    let ipc = rt.join("ipc");
    let entries = walk(&rt);
    assert!(entries.len() > 10, "{entries:?}");
    for (path, m) in &entries {
        let mode = m.mode() & 0o7777;
        assert_eq!(m.uid(), euid(), "{} is not ours", path.display());
        assert!(!m.file_type().is_symlink(), "{} is a link", path.display());
        let in_node_dir = path.parent() == Some(&ipc.join("nodes")) && m.is_dir();
        if in_node_dir {
            assert_eq!(mode & 0o007, 0, "{} is {mode:04o}", path.display());
        } else if path.starts_with(&ipc) {
            assert_eq!(mode & 0o077, 0, "{} is {mode:04o}", path.display());
        } else if m.is_dir() {
            assert_eq!(mode, 0o700, "{} is {mode:04o}", path.display());
        } else {
            assert_eq!(mode, 0o600, "{} is {mode:04o}", path.display());
        }
    }
    for d in [&rt, &ipc, &ipc.join("nodes"), &ipc.join("services")] {
        let m = std::fs::symlink_metadata(d).expect("exists");
        assert_eq!(m.mode() & 0o7777, 0o700, "{}", d.display());
    }
    // The event sockets are in iceoryx2's private root, not in /tmp/iceoryx2.
    assert!(
        entries.iter().any(|(p, m)| {
            use std::os::unix::fs::FileTypeExt;
            p.starts_with(&ipc) && m.file_type().is_socket()
        }),
        "no event socket under {}",
        ipc.display()
    );
    // iceoryx2's shared memory in /dev/shm: ours, 0600 (its node counter included, which
    // iceoryx2 makes 0666).
    let shm = shm_files(&instance);
    assert!(
        shm.iter()
            .any(|p| p.to_string_lossy().ends_with(".global_mgmt")),
        "{shm:?}"
    );
    for p in &shm {
        let m = std::fs::symlink_metadata(p).expect("exists");
        assert!(m.is_file(), "{}", p.display());
        assert_eq!(m.uid(), euid(), "{}", p.display());
        assert_eq!(
            m.mode() & 0o077,
            0,
            "{} is {:04o}",
            p.display(),
            m.mode() & 0o7777
        );
    }

    // The supervisor holds the instance's lock; its children do not (close-on-exec).
    let lock = rt.join(&instance).join("agent.lock");
    let holds = |pid: i32| {
        std::fs::read_dir(format!("/proc/{pid}/fd"))
            .map(|d| {
                d.flatten()
                    .any(|e| std::fs::read_link(e.path()).is_ok_and(|t| t == lock))
            })
            .unwrap_or(false)
    };
    assert!(holds(agent.pid() as i32), "the supervisor holds its lock");
    let children: Vec<i32> = ["dds-worker", "frontend"]
        .iter()
        .flat_map(|s| agent.child_pids(s))
        .collect();
    assert_eq!(children.len(), 2, "{children:?}");
    for pid in children {
        assert!(!holds(pid), "child {pid} inherited the supervisor's lock");
    }

    // `xrce-agent status` finds the agent in the runtime directory; keys are redacted
    // unless asked for.
    let mut shown = String::new();
    assert!(
        wait_until(10 * SECOND, || {
            let out = agent_command(&["status", "--instance", &instance], &rt);
            shown = String::from_utf8_lossy(&out.stdout).into_owned();
            shown.contains("0x****BBBB")
        }),
        "{shown}"
    );
    assert!(!shown.contains("AAAABBBB"), "{shown}");
    let out = agent_command(&["status", "--instance", &instance, "--show-keys"], &rt);
    assert!(String::from_utf8_lossy(&out.stdout).contains("0xAAAABBBB"));
    let out = agent_command(&["status", "--json"], &rt);
    let listed = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        listed.contains(&instance) && !listed.contains("AAAABBBB"),
        "{listed}"
    );

    // Another local user reads nothing: not the session store, not the reports, not the
    // shared memory, not even the names in the runtime directory.
    if is_root() {
        let readable = dir.join("readable");
        std::fs::write(&readable, b"x").expect("write");
        std::fs::set_permissions(&readable, std::fs::Permissions::from_mode(0o644)).expect("chmod");
        let control = as_nobody(&["cat", &readable.display().to_string()]);
        assert!(
            control.status.success(),
            "setpriv does not work here: {control:?}"
        );
        let store = store_of(&rt, &instance);
        let mut secrets: Vec<PathBuf> = ["state", "objects"]
            .iter()
            .map(|x| store.join(format!("{KEY_NAME}.{x}")))
            .collect();
        secrets.push(rt.join(&instance).join("status/frontend-0.json"));
        secrets.extend(shm.iter().cloned());
        for p in &secrets {
            let out = as_nobody(&["cat", &p.display().to_string()]);
            assert!(
                !out.status.success() && out.stdout.is_empty(),
                "nobody read {}",
                p.display()
            );
            assert!(
                String::from_utf8_lossy(&out.stderr).contains("Permission denied"),
                "{}: {}",
                p.display(),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        for d in [&rt, &store, &ipc] {
            let out = as_nobody(&["ls", &d.display().to_string()]);
            assert!(!out.status.success(), "nobody listed {}", d.display());
        }
    } else {
        eprintln!("not root: the part run as another user is skipped");
    }

    // A clean stop leaves nothing of the instance but its stored sessions (for the next
    // agent of the instance: a restart goes on with them), still private: not its status
    // reports, not its lock, not its files in iceoryx2's root or in /dev/shm.
    assert!(agent.stop_process(), "the agent did not stop cleanly");
    let kept: Vec<String> = std::fs::read_dir(rt.join(&instance))
        .map(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    assert_eq!(kept, ["sessions"], "left in the instance directory");
    let sessions_mode = std::fs::symlink_metadata(rt.join(&instance).join("sessions"))
        .expect("sessions kept")
        .mode()
        & 0o7777;
    assert_eq!(sessions_mode, 0o700);
    let _ = std::fs::remove_dir_all(rt.join(&instance));
    let prefix = format!("xrce_{instance}_");
    let left: Vec<PathBuf> = walk(&ipc)
        .into_iter()
        .map(|(p, _)| p)
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(&prefix))
        })
        .collect();
    assert!(left.is_empty(), "{left:?}");
    assert!(
        shm_files(&instance).is_empty(),
        "{:?}",
        shm_files(&instance)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Starts an agent that must refuse to start; returns what it printed on stderr.
fn refused(rt: &Path, instance: &str, env: &[(&str, &str)], unset: &[&str]) -> String {
    let port = free_udp_port().to_string();
    let mut cmd = Command::new(binaries().join("xrce-agent"));
    cmd.args(["udp4", "-p", &port, "--bind", "127.0.0.1"])
        .args(["--dds-interface", "127.0.0.1", "--instance", instance])
        .env("XRCE_RUNTIME_DIR", rt)
        .env("XRCE_LOG", "info")
        .envs(env.iter().copied());
    for v in unset {
        cmd.env_remove(v);
    }
    let out = output_within(&mut cmd, 30 * SECOND);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "the agent started: {stderr}");
    assert!(
        !String::from_utf8_lossy(&out.stdout).contains("ready") && !stderr.contains("agent ready"),
        "{stderr}"
    );
    stderr
}

#[test]
fn a_planted_runtime_or_instance_directory_is_refused() {
    let dir = scratch("planted");
    let instance = unique_instance("pf-planted");
    let mode = |p: &Path| std::fs::symlink_metadata(p).expect("exists").mode() & 0o7777;

    // The runtime directory itself, writable by everyone.
    let rt = dir.join("loose-rt");
    std::fs::create_dir(&rt).expect("mkdir");
    std::fs::set_permissions(&rt, std::fs::Permissions::from_mode(0o777)).expect("chmod");
    let said = refused(&rt, &instance, &[], &[]);
    assert!(
        said.contains(&rt.display().to_string()) && said.contains("mode 0777"),
        "{said}"
    );
    assert_eq!(mode(&rt), 0o777, "left as found");
    assert_eq!(
        std::fs::read_dir(&rt).expect("dir").count(),
        0,
        "nothing made in it"
    );

    // The instance's directory, planted with loose modes in a good runtime directory.
    let rt = dir.join("rt");
    std::fs::create_dir(&rt).expect("mkdir");
    std::fs::set_permissions(&rt, std::fs::Permissions::from_mode(0o700)).expect("chmod");
    let planted = rt.join(&instance);
    std::fs::create_dir(&planted).expect("mkdir");
    std::fs::set_permissions(&planted, std::fs::Permissions::from_mode(0o777)).expect("chmod");
    let said = refused(&rt, &instance, &[], &[]);
    assert!(
        said.contains(&planted.display().to_string())
            && said.contains("mode 0777")
            && said.contains("chmod 700"),
        "{said}"
    );
    assert_eq!(std::fs::read_dir(&planted).expect("dir").count(), 0);

    // A link where the instance's directory goes (to a directory that would pass).
    std::fs::remove_dir(&planted).expect("rmdir");
    let target = dir.join("target");
    std::fs::create_dir(&target).expect("mkdir");
    std::fs::set_permissions(&target, std::fs::Permissions::from_mode(0o700)).expect("chmod");
    std::os::unix::fs::symlink(&target, &planted).expect("symlink");
    let said = refused(&rt, &instance, &[], &[]);
    assert!(said.contains("is a symbolic link"), "{said}");
    assert_eq!(std::fs::read_dir(&target).expect("dir").count(), 0);
    std::fs::remove_file(&planted).expect("unlink");

    // The default runtime directory, `$XDG_RUNTIME_DIR/xrce-agent`, planted loose.
    let xdg = dir.join("xdg");
    std::fs::create_dir(&xdg).expect("mkdir");
    std::fs::set_permissions(&xdg, std::fs::Permissions::from_mode(0o700)).expect("chmod");
    let default = xdg.join("xrce-agent");
    std::fs::create_dir(&default).expect("mkdir");
    std::fs::set_permissions(&default, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    let xdg_s = xdg.display().to_string();
    let said = refused(
        &rt,
        &instance,
        &[("XDG_RUNTIME_DIR", &xdg_s)],
        &["XRCE_RUNTIME_DIR", "RUNTIME_DIRECTORY"],
    );
    assert!(
        said.contains(&default.display().to_string()) && said.contains("mode 0755"),
        "{said}"
    );

    // Directories of another user (root only can make them).
    if is_root() {
        std::fs::create_dir(&planted).expect("mkdir");
        std::fs::set_permissions(&planted, std::fs::Permissions::from_mode(0o700)).expect("chmod");
        std::os::unix::fs::chown(&planted, Some(NOBODY), Some(NOBODY)).expect("chown");
        let said = refused(&rt, &instance, &[], &[]);
        assert!(
            said.contains(&planted.display().to_string())
                && said.contains(&format!("belongs to uid {NOBODY}")),
            "{said}"
        );
        let theirs = dir.join("theirs");
        std::fs::create_dir(&theirs).expect("mkdir");
        std::fs::set_permissions(&theirs, std::fs::Permissions::from_mode(0o700)).expect("chmod");
        std::os::unix::fs::chown(&theirs, Some(NOBODY), Some(NOBODY)).expect("chown");
        let said = refused(&theirs, &instance, &[], &[]);
        assert!(said.contains(&format!("belongs to uid {NOBODY}")), "{said}");
        assert_eq!(std::fs::read_dir(&theirs).expect("dir").count(), 0);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_link_planted_where_a_file_will_be_created_is_not_followed() {
    let dir = scratch("links");
    let rt = dir.join("rt");
    let agent = start_agent("pf-links", &rt);
    let instance = agent.instance().to_string();
    let store = store_of(&rt, &instance);
    let status = rt.join(&instance).join("status");
    let victim = dir.join("victim");
    std::fs::write(&victim, b"untouched").expect("victim");
    let frontend = agent
        .child_pid_with("frontend", "udp4")
        .expect("the front-end runs");
    // Links at the temporary names the agent writes next: the client's objects and state,
    // the front-end's `alive` (rewritten every second) and its status report.
    let links = [
        store.join(format!("{KEY_NAME}.tmp")),
        store.join(format!("{KEY_NAME}.state.tmp")),
        store.join("alive.tmp"),
        status.join(format!(".frontend-0.{frontend}.tmp")),
    ];
    for l in &links {
        // The agent may be writing that very name at this instant (O_EXCL then fails
        // ours): try again.
        assert!(
            wait_until(5 * SECOND, || std::os::unix::fs::symlink(&victim, l)
                .is_ok()),
            "could not plant {}",
            l.display()
        );
    }
    let _client = client_with_objects(&agent, &rt, 122);
    // Two more rounds of `alive` and status reports.
    std::thread::sleep(5 * SECOND / 2);
    assert_eq!(std::fs::read(&victim).expect("victim"), b"untouched");
    for f in [
        store.join(format!("{KEY_NAME}.state")),
        store.join(format!("{KEY_NAME}.objects")),
        store.join("alive"),
        status.join("frontend-0.json"),
    ] {
        let m = std::fs::symlink_metadata(&f).expect("written");
        assert!(m.is_file(), "{} is not a regular file", f.display());
        assert_eq!(m.mode() & 0o7777, 0o600, "{}", f.display());
    }
    for l in &links {
        let still_link = std::fs::symlink_metadata(l).is_ok_and(|m| m.file_type().is_symlink());
        assert!(!still_link, "{} was left in place", l.display());
    }
    assert!(agent.stop_process());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_second_front_end_or_agent_on_the_instance_is_refused_and_the_first_keeps_its_sessions() {
    let dir = scratch("second");
    let rt = dir.join("rt");
    let agent = start_agent("pf-second", &rt);
    let instance = agent.instance().to_string();
    let mut client = client_with_objects(&agent, &rt, 123);
    let store = store_of(&rt, &instance);
    let snapshot = |name: &str| std::fs::read(store.join(name)).ok();
    let objects = snapshot(&format!("{KEY_NAME}.objects"));
    let incarnation = snapshot("incarnation");
    assert!(objects.is_some() && incarnation.is_some());

    // A second front-end with the same instance and id, on another port.
    let other = format!("127.0.0.1:{}", free_udp_port());
    let out = agent_command(
        &[
            "frontend",
            "--instance",
            &instance,
            "--frontend-id",
            "0",
            "--transport",
            "udp4",
            "--listen",
            &other,
        ],
        &rt,
    );
    let said = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{said}");
    assert!(said.contains("already runs"), "{said}");
    assert!(
        said.contains(&store.join("lock").display().to_string()),
        "{said}"
    );

    // A second agent with the same instance.
    let port = free_udp_port().to_string();
    let out = agent_command(
        &[
            "udp4",
            "-p",
            &port,
            "--bind",
            "127.0.0.1",
            "--dds-interface",
            "127.0.0.1",
            "--instance",
            &instance,
        ],
        &rt,
    );
    let said = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{said}");
    assert!(said.contains("another xrce-agent already runs"), "{said}");
    assert!(
        said.contains(&format!("agent.lock is locked by process {}", agent.pid())),
        "{said}"
    );

    // Nothing of the first one's store was touched, and it still serves the session.
    assert_eq!(snapshot(&format!("{KEY_NAME}.objects")), objects);
    assert_eq!(snapshot("incarnation"), incarnation);
    assert!(store.join(format!("{KEY_NAME}.state")).is_file());
    let p = ObjectId::new(1, object_kind::PARTICIPANT);
    let publisher = ObjectId::new(2, object_kind::PUBLISHER);
    assert_eq!(
        client.create(
            publisher,
            object_kind::PUBLISHER,
            "",
            VariantExtra::Parent(p)
        ),
        0,
        "the first agent no longer serves the session"
    );
    assert!(
        wait_until(5 * SECOND, || snapshot(&format!("{KEY_NAME}.objects"))
            != objects),
        "the new object was not stored"
    );
    assert!(agent.stop_process());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn files_planted_in_dev_shm_under_an_instance_s_names_do_not_stop_its_next_start() {
    if !is_root() {
        eprintln!("needs root to plant files as another user: checked by CI, which runs as root");
        return;
    }
    let instance = unique_instance("pf-shm");
    let addr: std::net::SocketAddr = ([127, 0, 0, 1], xrce_tests::free_udp_port()).into();
    // A first run shows its names in /dev/shm to every local user.
    let first = AgentProcess::at(addr).instance(instance.clone()).start();
    let seen = shm_files(&instance);
    assert!(!seen.is_empty(), "the agent has no shared memory");
    assert!(
        first.stop_keeping_sessions(),
        "first agent did not stop cleanly"
    );
    // Another user plants files under every name it saw, and under the instance's prefix
    // alone (what the names were before they had a random part).
    let mut planted: Vec<PathBuf> = seen.clone();
    planted.push(PathBuf::from(format!(
        "/dev/shm/xrce_{instance}_node.planted.global_mgmt"
    )));
    for p in &planted {
        std::fs::write(p, b"planted").expect("plant");
        std::os::unix::fs::chown(p, Some(NOBODY), Some(NOBODY)).expect("chown");
    }
    // The next start serves all the same.
    let second = AgentProcess::at(addr).instance(instance.clone()).start();
    let mut c = TestClient::new(second.addr(), *b"PLNT");
    c.connect(10 * SECOND);
    c.setup_publisher(99);
    for p in &planted {
        let m = std::fs::symlink_metadata(p).expect("the planted file is left alone");
        assert_eq!(m.uid(), NOBODY);
        std::fs::remove_file(p).expect("remove planted");
    }
    assert!(second.stop(), "second agent did not stop cleanly");
}

#[test]
fn full_client_keys_in_status_are_shown_only_to_the_agents_own_user() {
    if !is_root() {
        eprintln!("needs root to run a process as another user: checked by CI, which runs as root");
        return;
    }
    let port = free_udp_port().to_string();
    let listen = format!("127.0.0.1:{}", xrce_tests::free_tcp_port());
    let agent = AgentProcess::builder("pf-keys")
        .command_line(&[
            "udp4",
            "-p",
            &port,
            "--bind",
            "127.0.0.1",
            "--metrics",
            &listen,
        ])
        .launch()
        .expect("agent");
    let mut c = TestClient::new(agent.addr(), KEY);
    c.connect(10 * SECOND);
    c.setup_publisher(124);
    let status = |out: std::process::Output| String::from_utf8_lossy(&out.stdout).into_owned();
    let wanted = ["status", "--metrics", &listen, "--json", "--show-keys"];
    // The agent's own user sees the key whole (once the front-end reported the session).
    assert!(
        wait_until(10 * SECOND, || {
            let mut cmd = Command::new(binaries().join("xrce-agent"));
            cmd.args(wanted);
            status(output_within(&mut cmd, 10 * SECOND)).contains("0xAAAABBBB")
        }),
        "the agent's own user did not get the key whole"
    );
    // Another local user asking the same gets it redacted.
    let exe = binaries().join("xrce-agent").display().to_string();
    let mut as_other = vec![exe.as_str()];
    as_other.extend(wanted);
    let other = status(as_nobody(&as_other));
    assert!(other.contains("0x****BBBB"), "{other}");
    assert!(
        !other.contains("0xAAAABBBB"),
        "another user got the key: {other}"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
