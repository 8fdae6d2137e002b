//! The byte framers against real captures of the eProsima client and agent
//! (`tests/data/wire-traces`, copied from `shared/reference/wire-traces`): the TCP pcap and the serial hexdump. Every frame must
//! decode to an XRCE message, and re-encoding what was decoded must give the captured bytes
//! back; then the same streams cut at every possible point decode the same (property tests).

use std::path::PathBuf;

use proptest::prelude::*;
use xrce_common::framing::length_prefix::{self, LengthPrefixDecoder};
use xrce_common::framing::serial::{self, SerialDecoder, AGENT_ADDRESS};
use xrce_common::wire::Message;

fn trace(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/wire-traces")
        .join(name)
}

/// The serial hexdump as two byte streams (client to agent, agent to client), with the
/// chunk boundaries of the recording (each read the capture logged).
fn serial_streams() -> (Vec<Vec<u8>>, Vec<Vec<u8>>) {
    let text = std::fs::read_to_string(trace("serial-ping-and-ref-creation.hexdump.txt"))
        .expect("serial trace");
    let (mut to_agent, mut to_client) = (Vec::new(), Vec::new());
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        let dir = match line.chars().next() {
            Some('<') => &mut to_agent,
            Some('>') => &mut to_client,
            _ => continue,
        };
        let hex = lines.next().expect("hex line after a direction line");
        let bytes: Vec<u8> = hex
            .split_whitespace()
            .map(|h| u8::from_str_radix(h, 16).expect("hex byte"))
            .collect();
        dir.push(bytes);
    }
    (to_agent, to_client)
}

/// The TCP payloads of the pcap, per direction (to the agent's port, from it), in order.
fn tcp_streams() -> (u16, Vec<Vec<u8>>, Vec<Vec<u8>>) {
    let file = std::fs::File::open(trace("tcp-ping-and-ref-creation.pcap")).expect("tcp trace");
    let mut reader = pcap_file::pcap::PcapReader::new(file).expect("pcap");
    let mut segments = Vec::new();
    while let Some(packet) = reader.next_packet() {
        let packet = packet.expect("pcap packet");
        let sliced = etherparse::SlicedPacket::from_ethernet(&packet.data).expect("ethernet");
        let Some(etherparse::TransportSlice::Tcp(tcp)) = sliced.transport else {
            continue;
        };
        if tcp.payload().is_empty() {
            continue;
        }
        segments.push((
            tcp.source_port(),
            tcp.destination_port(),
            tcp.payload().to_vec(),
        ));
    }
    // The agent's port is the one the first SYN went to: the destination of the first
    // client segment, which is the lower-numbered listening port here.
    let agent_port = segments.first().map(|s| s.1).expect("segments");
    let to_agent = segments
        .iter()
        .filter(|s| s.1 == agent_port)
        .map(|s| s.2.clone())
        .collect();
    let to_client = segments
        .iter()
        .filter(|s| s.0 == agent_port)
        .map(|s| s.2.clone())
        .collect();
    (agent_port, to_agent, to_client)
}

fn decode_serial(chunks: &[Vec<u8>], local: u8) -> Vec<(u8, Vec<u8>)> {
    let mut d = SerialDecoder::new(local, serial::MAX_PAYLOAD);
    let mut out = Vec::new();
    for c in chunks {
        d.push(c, |f| {
            let f = f.expect("every captured frame is valid");
            out.push((f.source, f.payload.to_vec()));
        });
    }
    out
}

fn decode_tcp(chunks: &[Vec<u8>]) -> Vec<Vec<u8>> {
    let mut d = LengthPrefixDecoder::new(length_prefix::MAX_MESSAGE);
    let mut out = Vec::new();
    for c in chunks {
        d.push(c, |m| out.push(m.to_vec()))
            .expect("captured stream is well framed");
    }
    assert_eq!(d.buffered(), 0, "a partial message left over");
    out
}

#[test]
fn serial_capture_decodes_and_reencodes_byte_for_byte() {
    let (to_agent, to_client) = serial_streams();
    assert!(to_agent.len() >= 10 && to_client.len() >= 10);
    for (chunks, local, remote) in [(&to_agent, AGENT_ADDRESS, 1u8), (&to_client, 1, 0)] {
        let frames = decode_serial(chunks, local);
        assert!(frames.len() >= chunks.len(), "fewer frames than chunks");
        let mut again = Vec::new();
        for (source, payload) in &frames {
            assert_eq!(*source, remote);
            Message::decode(payload).expect("each frame carries an XRCE message");
            serial::encode(*source, local, payload, &mut again).expect("fits");
        }
        assert_eq!(again, chunks.concat(), "re-encoding changed the bytes");
    }
    // The agent merged frames into one write, and stuffed a CRC byte (0x7E): both covered.
    assert!(to_client
        .iter()
        .any(|c| c.iter().filter(|&&b| b == 0x7E).count() > 1));
    assert!(to_client.concat().windows(2).any(|w| w == [0x7D, 0x5E]));
}

#[test]
fn tcp_capture_decodes_and_reencodes_byte_for_byte() {
    let (port, to_agent, to_client) = tcp_streams();
    assert_eq!(port, 2020);
    // The client sends each length prefix as its own segment.
    assert!(to_agent.iter().any(|s| s.len() == 2));
    for chunks in [&to_agent, &to_client] {
        let messages = decode_tcp(chunks);
        assert!(messages.len() >= 5);
        let mut again = Vec::new();
        for m in &messages {
            Message::decode(m).expect("each frame carries an XRCE message");
            length_prefix::encode(m, &mut again).expect("fits");
        }
        assert_eq!(again, chunks.concat(), "re-encoding changed the bytes");
    }
}

/// Cuts `stream` at the given points (taken modulo its length).
fn cut(stream: &[u8], mut points: Vec<usize>) -> Vec<Vec<u8>> {
    if stream.is_empty() {
        return Vec::new();
    }
    points.iter_mut().for_each(|p| *p %= stream.len());
    points.sort_unstable();
    points.dedup();
    let mut out = Vec::new();
    let mut start = 0;
    for p in points.into_iter().chain([stream.len()]) {
        out.push(stream[start..p].to_vec());
        start = p;
    }
    out
}

proptest! {
    #[test]
    fn serial_any_split_gives_the_same_frames(points in proptest::collection::vec(any::<usize>(), 0..40)) {
        let (to_agent, _) = serial_streams();
        let whole = decode_serial(&to_agent, AGENT_ADDRESS);
        let split = decode_serial(&cut(&to_agent.concat(), points), AGENT_ADDRESS);
        prop_assert_eq!(whole, split);
    }

    #[test]
    fn tcp_any_split_gives_the_same_messages(points in proptest::collection::vec(any::<usize>(), 0..40)) {
        let (_, to_agent, _) = tcp_streams();
        let whole = decode_tcp(&to_agent);
        let split = decode_tcp(&cut(&to_agent.concat(), points));
        prop_assert_eq!(whole, split);
    }

    #[test]
    fn serial_encode_decode_is_the_identity(
        frames in proptest::collection::vec((any::<u8>(), proptest::collection::vec(any::<u8>(), 0..300)), 0..8),
        points in proptest::collection::vec(any::<usize>(), 0..20),
    ) {
        let mut wire = Vec::new();
        for (src, payload) in &frames {
            serial::encode(*src, AGENT_ADDRESS, payload, &mut wire).expect("fits");
        }
        let got = decode_serial(&cut(&wire, points), AGENT_ADDRESS);
        prop_assert_eq!(got, frames);
    }

    #[test]
    fn tcp_encode_decode_is_the_identity(
        messages in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 1..3000), 0..8),
        points in proptest::collection::vec(any::<usize>(), 0..20),
    ) {
        let mut wire = Vec::new();
        for m in &messages {
            length_prefix::encode(m, &mut wire).expect("fits");
        }
        let got = decode_tcp(&cut(&wire, points));
        prop_assert_eq!(got, messages);
    }

    #[test]
    fn serial_decoder_survives_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..2000)) {
        let mut d = SerialDecoder::new(AGENT_ADDRESS, 512);
        d.push(&bytes, |f| {
            if let Ok(f) = f {
                assert!(f.payload.len() <= 512);
            }
        });
    }

    #[test]
    fn tcp_decoder_survives_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..5000)) {
        let mut d = LengthPrefixDecoder::new(1024);
        let _ = d.push(&bytes, |m| assert!(m.len() <= 1024 && !m.is_empty()));
        prop_assert!(d.capacity() <= 1024 + 2 + 2048);
    }
}
