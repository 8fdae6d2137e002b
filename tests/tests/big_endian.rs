//! A big-endian client: its CREATE and WRITE_DATA are big endian, and its samples reach
//! Cyclone DDS with the CDR_BE encapsulation, decoded to the right values.

use std::collections::BTreeSet;
use std::time::Duration;

use xrce_common::session::client::ClientConfig;
use xrce_common::wire::ClientKey;
use xrce_tests::{hello_world_be, parse_sample_line, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

#[test]
fn a_big_endian_client_publishes_values_cyclone_reads_correctly() {
    let agent = AgentProcess::start("bigend");
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        "22",
        "--count",
        "10",
        "--reliable",
        "--timeout",
        "60",
    ]);
    let mut c = TestClient::with_config(
        agent.addr(),
        ClientConfig {
            little_endian: false,
            ..ClientConfig::new(ClientKey([0xBE, 0xBE, 0x00, 0x01]))
        },
    );
    c.connect(10 * SECOND);
    let w = c.setup_publisher(22);
    assert!(
        reader
            .wait_for("MATCHED 1", 30 * SECOND, || c.step())
            .is_some(),
        "Cyclone never matched the agent's writer"
    );
    // Indexes whose byte order matters (a swapped 0x01000000 would show).
    let indexes: Vec<u32> = (0..10).map(|i| 1 + i * 0x0101).collect();
    for i in &indexes {
        c.write_reliable(w, &hello_world_be(*i, "big end"));
    }
    let mut got = BTreeSet::new();
    let end = std::time::Instant::now() + 30 * SECOND;
    while got.len() < indexes.len() && std::time::Instant::now() < end {
        c.step();
        while let Some(l) = reader.line(Duration::from_millis(1)) {
            if let Some((i, m)) = parse_sample_line(&l) {
                assert_eq!(m, "big end");
                got.insert(i);
            }
        }
    }
    assert_eq!(got, indexes.into_iter().collect::<BTreeSet<u32>>());
    assert!(agent.stop(), "agent did not stop cleanly");
}
