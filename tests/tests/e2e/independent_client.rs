//! What an XRCE client other than eProsima's does differently, end to end: RTI's nano-client
//! numbers its streams from 1 (and drops an agent's message numbered 0, its stream state
//! starting at "0 received"), and ends its session with DELETE of object 0x000E (kind
//! CLIENT, id 0) rather than OBJECTID_CLIENT. The Rust test client plays those parts
//! (`ClientConfig::like_rti`: RTI's vendor id, streams from 1, anything numbered below
//! dropped), so a first reply numbered 0 would be lost for good and the test would wait
//! for a STATUS that never comes.

use std::time::{Duration, Instant};

use xrce_common::session::client::ClientConfig;
use xrce_common::wire::{status, ClientKey, ObjectId};
use xrce_tests::{hello_world, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn a_client_numbering_its_streams_from_one_loses_no_first_exchange() {
    let agent = AgentProcess::builder("fromone").start();
    let domain = 96;
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &domain.to_string(),
        "--count",
        "100000",
        "--reliable",
        "--timeout",
        "60",
    ]);
    // Its subscriber reads what a second client of the same kind publishes.
    let mut sub =
        TestClient::with_config(agent.addr(), ClientConfig::like_rti(ClientKey(*b"RTI2")));
    sub.connect(10 * SECOND);
    sub.setup_subscriber(domain);
    let mut publ =
        TestClient::with_config(agent.addr(), ClientConfig::like_rti(ClientKey(*b"RTI1")));
    publ.connect(10 * SECOND);
    // Every CREATE's STATUS must arrive (the first is the agent's first reliable reply).
    let w = publ.setup_publisher(domain);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || {
                publ.step();
                sub.step();
            })
            .is_some(),
        "Cyclone never matched the writer"
    );
    let t = Instant::now() + 2 * SECOND;
    while Instant::now() < t {
        publ.step();
        sub.step();
    }
    for i in 0..20 {
        publ.write_reliable(w, &hello_world(i, "from one"));
        sub.step();
    }
    let got = reader.collect_deliveries(20, "from one", 30 * SECOND, || {
        publ.step();
        sub.step();
    });
    got.assert_exactly_once(0..20, "Cyclone reading a client that numbers from 1");
    // The subscriber got them too, on a stream the agent numbered from 1 for it.
    let mut seen = std::collections::BTreeMap::new();
    let end = Instant::now() + 20 * SECOND;
    while Instant::now() < end && seen.len() < 20 {
        publ.step();
        sub.step();
        for (i, m) in sub.take_samples() {
            assert_eq!(m, "from one");
            *seen.entry(i).or_insert(0) += 1;
        }
    }
    let missing: Vec<u32> = (0..20).filter(|i| !seen.contains_key(i)).collect();
    assert!(missing.is_empty(), "the subscriber lacks {missing:?}");
    assert!(
        seen.values().all(|n| *n == 1),
        "the subscriber got repeats: {seen:?}"
    );
    // The session's line says who the client is and what the agent does for it.
    assert!(
        agent
            .output()
            .logged("RTI (01.01)", 2, xrce_tests::LOG_WAIT),
        "no session line names the vendor"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_session_ended_by_deleting_the_client_kind_is_answered_and_deleted() {
    let agent = AgentProcess::builder("delkind").start();
    let mut c = TestClient::with_config(agent.addr(), ClientConfig::like_rti(ClientKey(*b"RTI3")));
    c.connect(10 * SECOND);
    c.setup_publisher(97);
    let out = agent.output().clone();
    let mark = out.len();
    // Object 0x000E: kind CLIENT (0xE), id 0, as RTI's nano-client names it.
    let req = c
        .client
        .delete(Instant::now(), ObjectId([0x00, 0x0E]))
        .expect("delete");
    assert_eq!(c.wait_status(req, 10 * SECOND), status::OK);
    assert!(
        out.wait_for(mark, "session deleted", 10 * SECOND).is_some(),
        "the session was not deleted"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
