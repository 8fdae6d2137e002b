//! Domain id 255 means "the agent's default": with `XRCE_DOMAIN_ID_OVERRIDE` set, a client's
//! participant in domain 255 publishes in that domain, where Cyclone DDS reads it; without
//! it, in `ROS_DOMAIN_ID`'s.

use std::time::Duration;

use xrce_tests::{hello_world, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn domain_255_follows_xrce_domain_id_override() {
    domain_255_follows(&[("XRCE_DOMAIN_ID_OVERRIDE", "45")], 45, "domover", 1);
}

/// What micro-ROS users set: ROS 2's own variable.
#[test]
fn domain_255_follows_ros_domain_id() {
    domain_255_follows(&[("ROS_DOMAIN_ID", "65")], 65, "rosdomain", 2);
}

/// Both set: the agent's own variable wins.
#[test]
fn xrce_domain_id_override_wins_over_ros_domain_id() {
    domain_255_follows(
        &[("XRCE_DOMAIN_ID_OVERRIDE", "66"), ("ROS_DOMAIN_ID", "67")],
        66,
        "bothdomain",
        3,
    );
}

/// A client's participant in domain 255, with the agent started with `env`, publishes in
/// `domain`, where Cyclone DDS reads each sample once.
fn domain_255_follows(env: &[(&str, &str)], domain: u16, tag: &str, key: u8) {
    let agent = AgentProcess::builder(tag).env(env).start();
    let domain_arg = domain.to_string();
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &domain_arg,
        "--count",
        "5",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x50, 0x00, key]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(255);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone in domain {domain} never matched the writer of a domain-255 participant ({env:?})"
    );
    for i in 0..5u32 {
        c.write_reliable(w, &hello_world(i, "overridden"));
    }
    let got = reader.collect_deliveries(5, "overridden", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..5, "a domain-255 participant, overridden");
    got.assert_in_order("a domain-255 participant, overridden");
    assert!(agent.stop(), "agent did not stop cleanly");
}
