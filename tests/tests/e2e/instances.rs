//! Two agents on the same UDP port, bound to different loopback addresses and started with
//! their default instance names, are isolated from each other: each answers on its own
//! address, their shared memory is separate, and each stops cleanly. The same command line
//! started again takes its instance over.

use std::time::Duration;

use xrce_tests::{free_udp_port, AgentProcess, TestClient};

#[test]
fn two_agents_on_one_port_do_not_share_their_ipc() {
    let port = free_udp_port();
    let a = AgentProcess::at(([127, 0, 0, 1], port).into()).start();
    let b = AgentProcess::at(([127, 0, 0, 2], port).into()).start();
    // The instance each agent's processes really use (not the name the harness expects):
    // the front-end's `--instance` argument (its settings travel as arguments), the
    // worker's XRCE_INSTANCE.
    let used = |agent: &AgentProcess| -> Vec<String> {
        let nul_separated = |path: String| -> Vec<String> {
            std::fs::read(path)
                .unwrap_or_default()
                .split(|b| *b == 0)
                .map(|p| String::from_utf8_lossy(p).into_owned())
                .collect()
        };
        agent
            .child_pids("dds-worker")
            .into_iter()
            .chain(agent.child_pids("frontend"))
            .filter_map(|pid| {
                let args = nul_separated(format!("/proc/{pid}/cmdline"));
                let by_argument = args
                    .iter()
                    .find_map(|a| a.strip_prefix("--instance=").map(String::from))
                    .or_else(|| {
                        args.iter()
                            .position(|a| a == "--instance")
                            .and_then(|i| args.get(i + 1).cloned())
                    });
                by_argument.or_else(|| {
                    nul_separated(format!("/proc/{pid}/environ"))
                        .iter()
                        .find_map(|kv| kv.strip_prefix("XRCE_INSTANCE=").map(String::from))
                })
            })
            .collect()
    };
    let (ia, ib) = (used(&a), used(&b));
    assert_eq!(
        ia,
        [a.instance.clone(), a.instance.clone()],
        "agent A's processes"
    );
    assert_eq!(
        ib,
        [b.instance.clone(), b.instance.clone()],
        "agent B's processes"
    );
    assert_ne!(ia[0], ib[0], "two agents on one port share an instance");
    assert!(
        !xrce_ipc::shm::instance_files(&a.instance).is_empty(),
        "agent A has no shared memory of its own"
    );
    assert!(
        !xrce_ipc::shm::instance_files(&b.instance).is_empty(),
        "agent B has no shared memory of its own"
    );
    // A session with each: every create is answered by that agent's own worker.
    for (i, agent) in [&a, &b].into_iter().enumerate() {
        let mut c = TestClient::new(agent.addr(), [0x1D, 0, 0, i as u8]);
        c.connect(Duration::from_secs(10));
        c.setup_publisher(16);
    }
    assert_eq!(a.child_pids("dds-worker").len(), 1);
    assert_eq!(b.child_pids("dds-worker").len(), 1);
    assert!(a.stop(), "agent A did not stop cleanly");
    assert!(b.stop(), "agent B did not stop cleanly");
}

#[test]
fn a_killed_agents_instance_is_taken_over_and_left_clean_by_the_next_one() {
    use nix::sys::signal::{kill, Signal};
    use nix::unistd::Pid;
    let port = free_udp_port();
    let dead = AgentProcess::at(([127, 0, 0, 1], port).into()).start();
    let instance = dead.instance.clone();
    // Freeze the supervisor so it restarts nothing, then kill everything without cleanup.
    let supervisor = Pid::from_raw(dead.pid() as i32);
    kill(supervisor, Signal::SIGSTOP).expect("SIGSTOP");
    let children: Vec<i32> = dead
        .child_pids("dds-worker")
        .into_iter()
        .chain(dead.child_pids("frontend"))
        .collect();
    assert_eq!(children.len(), 2, "the worker and the front-end");
    for child in &children {
        xrce_tests::sigkill(*child);
    }
    kill(supervisor, Signal::SIGKILL).expect("SIGKILL");
    drop(dead);
    // Until every process of the killed agent is gone.
    let end = std::time::Instant::now() + Duration::from_secs(10);
    while children
        .iter()
        .chain([supervisor.as_raw()].iter())
        .any(|p| is_alive(*p))
        && std::time::Instant::now() < end
    {
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(
        !xrce_ipc::shm::instance_files(&instance).is_empty(),
        "the killed agent left nothing to clean"
    );
    // The same command line derives the same instance: the next agent takes it over (its
    // predecessor's dead nodes are cleaned when its own are made), serves, and leaves
    // nothing in shared memory when it stops.
    let next = AgentProcess::at(([127, 0, 0, 1], port).into()).start();
    assert_eq!(
        next.instance(),
        instance,
        "the same command line, another instance"
    );
    let mut c = TestClient::new(next.addr(), [0x1E, 0, 0, 1]);
    c.connect(Duration::from_secs(10));
    c.setup_publisher(17);
    assert!(next.stop());
    let left = xrce_ipc::shm::instance_files(&instance);
    assert!(left.is_empty(), "leftovers of the killed agent: {left:?}");
}

/// Whether a process exists and is not a zombie.
fn is_alive(pid: i32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .map(|s| {
            !s.lines()
                .any(|l| l.starts_with("State:") && l.contains('Z'))
        })
        .unwrap_or(false)
}
