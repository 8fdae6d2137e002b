//! Request/reply through the agent: an XRCE requester and an XRCE replier (two sessions) on a
//! service whose requests and replies cross DDS on `rq/…Request` / `rr/…Reply`, the reply
//! finding its request by the DDS sample identity, as with eProsima's agent: the replier gets
//! the request's SampleIdentity in front of it and sends it back in front of the reply; the
//! requester gets the BaseObjectRequest of its own WRITE_DATA in front of the reply.

use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind as k, ObjectId, RequestId};
use xrce_tests::{adder_request, AgentProcess, TestClient, DUPLICATE_GRACE};

const SECOND: Duration = Duration::from_secs(1);

fn endpoint(c: &mut TestClient, kind: u8) -> ObjectId {
    c.setup_adder(28, kind)
}

fn request(a: u32, b: u32) -> Vec<u8> {
    adder_request(a, b)
}

/// The replier's side: answers every request received so far with the sum, and checks that
/// no request arrives twice (`seen` holds the SampleIdentity of every request answered).
fn serve(replier: &mut TestClient, id: ObjectId, seen: &mut HashSet<Vec<u8>>) -> usize {
    replier.step();
    let mut n = 0;
    for (_, d) in replier.take_data() {
        assert!(d.len() >= 24 + 8, "request without SampleIdentity: {d:?}");
        let (identity, body) = d.split_at(24);
        assert!(
            seen.insert(identity.to_vec()),
            "the replier got the request {identity:?} twice"
        );
        let a = u32::from_le_bytes(body[0..4].try_into().expect("a"));
        let b = u32::from_le_bytes(body[4..8].try_into().expect("b"));
        let mut reply = identity.to_vec();
        reply.extend_from_slice(&(a + b).to_le_bytes());
        replier.write_reliable(id, &reply);
        n += 1;
    }
    n
}

#[test]
fn replies_reach_the_requester_matched_to_their_requests() {
    let agent = AgentProcess::builder("rpc").start();
    let mut replier = TestClient::new(agent.addr(), [0x2E, 0x91, 0x00, 0x01]);
    replier.connect(10 * SECOND);
    let rep = endpoint(&mut replier, k::REPLIER);
    let mut requester = TestClient::new(agent.addr(), [0x2E, 0x90, 0x00, 0x02]);
    requester.connect(10 * SECOND);
    let req = endpoint(&mut requester, k::REQUESTER);
    let mut seen = HashSet::new();

    // Requests are volatile: probe until the first reply shows both sides matched.
    let mut sent: HashMap<RequestId, u32> = HashMap::new();
    let mut answered: HashMap<RequestId, Vec<u32>> = HashMap::new();
    let end = Instant::now() + 30 * SECOND;
    while answered.is_empty() && Instant::now() < end {
        let id = requester.write_reliable_id(req, &request(100, 1));
        sent.insert(id, 101);
        let until = Instant::now() + Duration::from_millis(200);
        while Instant::now() < until {
            serve(&mut replier, rep, &mut seen);
            requester.step();
            requester.take_adder_replies(req, &mut answered);
        }
    }
    assert!(!answered.is_empty(), "no reply within 30 s");
    // Now ten requests with distinct operands; each reply must carry its request's id.
    let mut expected = HashMap::new();
    for i in 0..10u32 {
        let id = requester.write_reliable_id(req, &request(i, i * 10));
        expected.insert(id, i * 11);
    }
    let end = Instant::now() + 30 * SECOND;
    while expected.keys().any(|id| !answered.contains_key(id)) && Instant::now() < end {
        serve(&mut replier, rep, &mut seen);
        requester.step();
        requester.take_adder_replies(req, &mut answered);
    }
    // Then a while longer, so that a late repeated reply is seen.
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        serve(&mut replier, rep, &mut seen);
        requester.step();
        requester.take_adder_replies(req, &mut answered);
    }
    for (id, sum) in &expected {
        assert_eq!(
            answered.get(id).map(Vec::as_slice),
            Some(&[*sum][..]),
            "replies to request {id:?} (exactly one expected)"
        );
    }
    for (id, v) in &answered {
        let asked = expected.get(id).or(sent.get(id));
        assert!(
            asked.is_some() && v.iter().all(|s| Some(s) == asked),
            "replies {v:?} for request {id:?} that asked {asked:?}"
        );
        assert_eq!(v.len(), 1, "request {id:?} answered {} times", v.len());
    }
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_content_filter_on_a_requester_is_refused() {
    let agent = AgentProcess::builder("rpcfilter").start();
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x51, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let requester = endpoint(&mut c, k::REQUESTER);
    let spec = xrce_common::wire::ReadSpecification {
        preferred_stream_id: xrce_common::wire::stream_id::BUILTIN_RELIABLE,
        content_filter_expression: Some("a > 1".into()),
        ..Default::default()
    };
    let req = c
        .client
        .read(Instant::now(), requester, spec)
        .expect("read");
    assert_eq!(
        c.wait_status(req, 10 * SECOND),
        xrce_common::wire::status::ERR_INCOMPATIBLE,
        "requests and replies carry no type the worker could filter on"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}
