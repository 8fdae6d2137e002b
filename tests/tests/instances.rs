//! Two agents on the same UDP port, bound to different loopback addresses and started with
//! their default instance names, are isolated from each other: each answers on its own
//! address, their shared memory is separate, and each stops cleanly.

use std::time::Duration;

use xrce_tests::{free_udp_port, AgentProcess, TestClient};

#[test]
fn two_agents_on_one_port_do_not_share_their_ipc() {
    let port = free_udp_port();
    let a = AgentProcess::start_on(([127, 0, 0, 1], port).into(), None);
    let b = AgentProcess::start_on(([127, 0, 0, 2], port).into(), None);
    assert_ne!(a.instance, b.instance);
    assert!(
        !xrce_common::ipc::shm::instance_files(&a.instance).is_empty(),
        "agent A has no shared memory of its own"
    );
    assert!(
        !xrce_common::ipc::shm::instance_files(&b.instance).is_empty(),
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
fn shared_memory_of_a_killed_agent_is_removed_by_the_next_one() {
    use nix::sys::signal::{kill, Signal};
    use nix::unistd::Pid;
    let port = free_udp_port();
    let dead = AgentProcess::start_on(([127, 0, 0, 1], port).into(), None);
    let instance = dead.instance.clone();
    // Freeze the supervisor so it restarts nothing, then kill everything without cleanup.
    let supervisor = Pid::from_raw(dead.pid() as i32);
    kill(supervisor, Signal::SIGSTOP).expect("SIGSTOP");
    for child in dead
        .child_pids("dds-worker")
        .into_iter()
        .chain(dead.child_pids("frontend"))
    {
        xrce_tests::sigkill(child);
    }
    kill(supervisor, Signal::SIGKILL).expect("SIGKILL");
    drop(dead);
    std::thread::sleep(Duration::from_millis(200));
    assert!(
        !xrce_common::ipc::shm::instance_files(&instance).is_empty(),
        "the killed agent left nothing to clean"
    );
    let next = AgentProcess::start_on(([127, 0, 0, 1], port).into(), None);
    let left = xrce_common::ipc::shm::instance_files(&instance);
    assert!(left.is_empty(), "leftovers of the killed agent: {left:?}");
    assert!(next.stop());
}
