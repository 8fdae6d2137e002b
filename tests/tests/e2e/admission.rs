//! Who may hold a session and how much a client may do, end to end: the allow-list of client
//! keys, no takeover of a session from another socket (and roaming when allowed), the quota
//! of objects per client, the input quotas in messages and in bytes per second (a client
//! over one is slowed and loses nothing).

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use xrce_common::session::client::{ClientConfig, ClientEvent};
use xrce_common::wire::*;
use xrce_tests::{
    free_udp_port, hello_world, parse_sample_line, xml, AgentProcess, DdsPeer, Deliveries, Link,
    TestClient, DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

fn agent(tag: &str, extra: &[&str]) -> AgentProcess {
    let port = free_udp_port().to_string();
    let mut args = vec!["udp4", "-p", &port, "--bind", "127.0.0.1"];
    args.extend_from_slice(extra);
    AgentProcess::builder(tag)
        .command_line(&args)
        .launch()
        .expect("agent")
}

/// A Cyclone reader of `count` reliable HelloWorld samples in `domain`.
fn cyclone_reader(domain: &str, count: &str) -> DdsPeer {
    DdsPeer::start(&[
        "read",
        "--domain",
        domain,
        "--count",
        count,
        "--reliable",
        "--timeout",
        "60",
    ])
}

/// A client that puts its key in every header (session id below 0x80), as a session that
/// another socket could name.
fn keyed_client(agent: &AgentProcess, key: [u8; 4]) -> TestClient {
    let mut config = ClientConfig::new(ClientKey(key));
    config.session_id = 0x01;
    TestClient::with_config(agent.addr(), config)
}

#[test]
fn only_listed_keys_get_a_session_and_the_others_are_told_denied() {
    let agent = agent("allowkeys", &["--allow-keys", "0xAAAABBBB,0x0000CAFE"]);
    let mut listed = TestClient::new(agent.addr(), [0xAA, 0xAA, 0xBB, 0xBB]);
    listed.connect(10 * SECOND);
    // An unlisted key is refused with STATUS_ERR_DENIED, however often it tries.
    for _ in 0..3 {
        let mut other = TestClient::new(agent.addr(), [0x11, 0x11, 0x22, 0x22]);
        other.client.connect(Instant::now());
        let answered = other.run_until(10 * SECOND, |c| !c.events.is_empty());
        assert!(answered, "no answer to an unlisted key's CREATE_CLIENT");
        assert!(!other.client.is_connected());
        assert!(
            matches!(
                other.events[..],
                [ClientEvent::SessionStatus(s)] if s.status == status::ERR_DENIED
            ),
            "{:?}",
            other.events
        );
    }
    // The listed client is served meanwhile.
    let p = ObjectId::new(1, object_kind::PARTICIPANT);
    assert_eq!(
        listed.create(
            p,
            object_kind::PARTICIPANT,
            xml::PARTICIPANT,
            VariantExtra::DomainId(70)
        ),
        status::OK
    );
    // One warning names the refused key; repeats are only counted. (The log line may come
    // after the refusal it is about.)
    let out = agent.output();
    assert!(
        out.wait_for(0, "not in --allow-keys", 10 * SECOND)
            .is_some(),
        "no warning names the refused key"
    );
    assert_eq!(out.count("not in --allow-keys"), 1);
    assert!(out.count("11112222") >= 1);
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn another_socket_naming_a_session_does_not_take_it_over() {
    let agent = agent("takeover", &[]);
    let reader = cyclone_reader("71", "10");
    let key = [0xAB, 0xCD, 0x00, 0x71];
    let mut c = keyed_client(&agent, key);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(71);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    // Someone who learnt the key writes into the session from their own socket, at every
    // sequence number the client will use.
    let intruder = UdpSocket::bind("127.0.0.1:0").expect("bind");
    intruder
        .set_read_timeout(Some(Duration::from_millis(300)))
        .expect("timeout");
    for seq in 0..20u16 {
        let mut b = MessageBuilder::new(MessageHeader::new(
            0x01,
            stream_id::BUILTIN_RELIABLE,
            seq,
            ClientKey(key),
        ));
        b.push(
            &Payload::WriteData(DataPayload {
                base: BaseObjectRequest {
                    request_id: RequestId::from_u16(0x100 + seq),
                    object_id: w,
                },
                format: data_format::DATA,
                data: &hello_world(u32::from(seq), "intruder"),
            }),
            true,
        )
        .expect("encode");
        intruder.send_to(&b.finish(), agent.addr()).expect("send");
    }
    let mut buf = [0u8; 1024];
    assert!(
        intruder.recv_from(&mut buf).is_err(),
        "the agent answered a foreign socket"
    );
    // The client goes on undisturbed: every one of its samples, none of the intruder's
    // (collect_deliveries checks each message).
    for i in 0..10 {
        c.write_reliable(w, &hello_world(i, "genuine"));
    }
    let got = reader.collect_deliveries(10, "genuine", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..10, "the session's own client");
    got.assert_in_order("the session's own client");
    assert_eq!(
        agent
            .output()
            .count("message for a session from another endpoint dropped"),
        1
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn with_roaming_allowed_a_client_that_changes_socket_keeps_its_session() {
    let agent = agent("roaming", &["--allow-roaming"]);
    let reader = cyclone_reader("72", "20");
    let mut c = keyed_client(&agent, [0xAB, 0xCD, 0x00, 0x72]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(72);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    for i in 0..10 {
        c.write_reliable(w, &hello_world(i, "roaming"));
    }
    // A new source port (as after a NAT rebinding), no new CREATE_CLIENT.
    c.link = Link::udp(agent.addr());
    for i in 10..20 {
        c.write_reliable(w, &hello_world(i, "roaming"));
    }
    let got = reader.collect_deliveries(20, "roaming", 30 * SECOND, || c.step());
    got.assert_exactly_once(0..20, "a client that moved");
    assert_eq!(agent.output().count("session roamed"), 1);
    assert_eq!(agent.output().count("session created"), 1);
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn objects_beyond_the_quota_are_refused_with_err_resources() {
    let agent = agent("objquota", &["--max-objects-per-client", "3"]);
    let mut c = TestClient::new(agent.addr(), [0xAB, 0xCD, 0x00, 0x73]);
    c.connect(10 * SECOND);
    let p = ObjectId::new(1, object_kind::PARTICIPANT);
    let t = ObjectId::new(1, object_kind::TOPIC);
    let g = ObjectId::new(1, object_kind::PUBLISHER);
    let e = ObjectId::new(1, object_kind::DATAWRITER);
    let steps = [
        (
            p,
            object_kind::PARTICIPANT,
            xml::PARTICIPANT,
            VariantExtra::DomainId(73),
            status::OK,
        ),
        (
            t,
            object_kind::TOPIC,
            xml::TOPIC,
            VariantExtra::Parent(p),
            status::OK,
        ),
        (
            g,
            object_kind::PUBLISHER,
            "",
            VariantExtra::Parent(p),
            status::OK,
        ),
        (
            e,
            object_kind::DATAWRITER,
            xml::WRITER,
            VariantExtra::Parent(g),
            status::ERR_RESOURCES,
        ),
    ];
    for (id, kind, text, extra, expected) in steps {
        assert_eq!(c.create(id, kind, text, extra), expected, "creating {id:?}");
    }
    // The warning comes from the front-end's stderr, which may trail the STATUS reply.
    assert!(
        agent
            .output()
            .wait_for(0, "quota of objects", 10 * SECOND)
            .is_some(),
        "no warning about the quota"
    );
    // Deleting one makes room again.
    let req = c
        .client
        .delete(Instant::now(), g)
        .expect("delete the publisher");
    assert_eq!(c.wait_status(req, 10 * SECOND), status::OK);
    assert_eq!(
        c.create(g, object_kind::PUBLISHER, "", VariantExtra::Parent(p)),
        status::OK
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_client_over_its_message_quota_is_slowed_and_loses_nothing() {
    // 120 writes at 40 messages per second with a second's burst: the last cannot be taken
    // before (120 - 40) / 40 = 2 s after the first (unmetered, they all arrive within tens of
    // milliseconds). Half a second is left for the burst's edges.
    let span = metered_writes(
        "ratequota",
        ["--max-client-messages-per-second", "40"],
        74,
        120,
        "metered",
    );
    assert!(
        span >= Duration::from_millis(1500),
        "120 messages at 40 per second went through in {span:?}"
    );
}

#[test]
fn a_client_over_its_byte_quota_is_slowed_and_loses_nothing() {
    // 40 writes of about 220 bytes each (8.8 KB) at 3,000 bytes per second with a second's
    // burst: the last cannot be taken before about 1.9 s after the first.
    let message = "b".repeat(200);
    let span = metered_writes(
        "bytequota",
        ["--max-client-bytes-per-second", "3000"],
        75,
        40,
        &message,
    );
    assert!(
        span >= Duration::from_millis(1500),
        "8.8 KB at 3,000 bytes per second went through in {span:?}"
    );
}

/// Writes `count` reliable samples of `message` as fast as the client's window allows, to an
/// agent started with `quota` (a `--max-client-…-per-second` flag and its value); every
/// sample must reach Cyclone once, in order, and the quota must have bitten (logged).
/// Returns how long after the first write the last sample arrived.
fn metered_writes(tag: &str, quota: [&str; 2], domain: i16, count: u32, message: &str) -> Duration {
    let agent = agent(tag, &quota);
    let reader = cyclone_reader(&domain.to_string(), &count.to_string());
    let mut c = TestClient::new(agent.addr(), [0xAB, 0xCD, 0x00, domain as u8]);
    c.connect(10 * SECOND);
    let w = c.setup_publisher(domain);
    assert!(reader
        .wait_for("MATCHED 1", 30 * SECOND, || c.step())
        .is_some());
    // A second without messages: the burst allowance (a second's worth) is full again.
    c.run_until(SECOND, |_| false);
    let start = Instant::now();
    let mut got = Deliveries::default();
    let mut last_new = start;
    let take = |got: &mut Deliveries, last_new: &mut Instant| {
        while let Some(l) = reader.line(Duration::ZERO) {
            if let Some((i, m)) = parse_sample_line(&l) {
                assert_eq!(m, message, "sample {i}");
                if got.count(i) == 0 {
                    *last_new = Instant::now();
                }
                got.record(i);
            }
        }
    };
    for i in 0..count {
        c.write_reliable(w, &hello_world(i, message));
        take(&mut got, &mut last_new);
    }
    let end = Instant::now() + 60 * SECOND;
    let mut complete_at: Option<Instant> = None;
    while Instant::now() < end && complete_at.is_none_or(|t| t.elapsed() < DUPLICATE_GRACE) {
        c.step();
        take(&mut got, &mut last_new);
        if complete_at.is_none() && got.distinct() >= count as usize {
            complete_at = Some(Instant::now());
        }
    }
    got.assert_exactly_once(0..count, "a client over its quota");
    got.assert_in_order("a client over its quota");
    assert!(
        agent
            .output()
            .logged("over its rate quota", 1, xrce_tests::LOG_WAIT),
        "the quota never bit"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
    last_new.duration_since(start)
}
