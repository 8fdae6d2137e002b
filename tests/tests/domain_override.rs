//! Domain id 255 means "the agent's default": with `XRCE_DOMAIN_ID_OVERRIDE` set, a client's
//! participant in domain 255 publishes in that domain, where Cyclone DDS reads it.

use std::time::Duration;

use xrce_tests::{hello_world, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn domain_255_follows_xrce_domain_id_override() {
    let agent = AgentProcess::start_with_env("domover", &[("XRCE_DOMAIN_ID_OVERRIDE", "45")]);
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "45",
        "--count",
        "5",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x50, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(255);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone in domain 45 never matched the writer of a domain-255 participant"
    );
    for i in 0..5u32 {
        c.write_reliable(w, &hello_world(i, "overridden"));
    }
    let got = reader.collect_deliveries(5, "overridden", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..5, "a domain-255 participant, overridden");
    got.assert_in_order("a domain-255 participant, overridden");
    assert!(agent.stop(), "agent did not stop cleanly");
}
