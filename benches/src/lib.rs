//! Benchmarks of the agent. `cargo bench -p xrce-benches` runs the micro-benchmarks of the
//! protocol core (`benches/protocol.rs`): decode and encode per submessage kind, and the agent
//! session core per datagram. The load generator (issue 4) will live here too.

/// Datagrams captured between the real eProsima client and agent, by direction.
pub fn captured(name: &str, to_agent: bool) -> Vec<Vec<u8>> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../common/tests/data/wire-traces")
        .join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_default();
    let dir = if to_agent { " C>A " } else { " A>C " };
    text.lines()
        .filter(|l| l.contains(dir))
        .filter_map(|l| l.split_whitespace().nth(3))
        .map(|h| {
            (0..h.len() / 2)
                .filter_map(|i| u8::from_str_radix(&h[2 * i..2 * i + 2], 16).ok())
                .collect()
        })
        .collect()
}
