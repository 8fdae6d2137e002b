//! `-m zenoh`: an XRCE client's node in a ROS 2 graph on rmw_zenoh, checked by an independent
//! Zenoh peer (eclipse-zenoh from PyPI) through a Zenoh router on loopback: the node's,
//! publisher's and subscription's liveliness tokens as rmw_zenoh writes them, samples both
//! ways on rmw_zenoh's key with its attachment and CDR payload, a service call answered by an
//! XRCE replier, a transient-local late joiner, and a worker killed and replayed.

use std::time::{Duration, Instant};

use xrce_common::wire::binary::{
    qos_flags, EndpointBinary, EndpointBinaryQos, EndpointQosBinary, GroupBinary,
    ParticipantBinary, TopicBinary,
};
use xrce_common::wire::{object_kind as k, status, ObjectId, Representation, VariantExtra};
use xrce_tests::{free_tcp_port, libtest_name, AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);
const DOMAIN: i16 = 7;
const STRING: &str = "std_msgs::msg::dds_::String_";
const STRING_HASH: &str = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18";
const ADD_TWO_INTS: &str = "example_interfaces::srv::dds_::AddTwoInts_";
const ADD_TWO_INTS_HASH: &str =
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a";

/// A router, and an agent on `-m zenoh` connected to it (both on loopback).
struct Graph {
    router: DdsPeer,
    endpoint: String,
    agent: AgentProcess,
}

fn start_graph(tag: &str) -> Graph {
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let router = DdsPeer::zenoh(&["router", "--listen", &endpoint]);
    assert!(
        router.wait_for("READY", 30 * SECOND, || {}).is_some(),
        "the Zenoh router did not start"
    );
    let overrides =
        format!("connect/endpoints=[\"{endpoint}\"];listen/endpoints=[\"tcp/127.0.0.1:0\"]");
    let agent = AgentProcess::builder(tag)
        .env(&[
            ("XRCE_DDS_BACKEND", "zenoh"),
            ("ZENOH_CONFIG_OVERRIDE", &overrides),
        ])
        .start();
    Graph {
        router,
        endpoint,
        agent,
    }
}

fn peer(g: &Graph, args: &[&str]) -> DdsPeer {
    let mut all = vec![args[0], "--connect", &g.endpoint];
    all.extend_from_slice(&args[1..]);
    let p = DdsPeer::zenoh(&all);
    // A transient-local subscription asks the router for the publishers' caches before it
    // says READY, and the suite runs other tests beside this one: a minute, not a budget.
    // The history may arrive before READY: those lines are kept for the test.
    assert!(
        p.wait_for_keeping("READY", 60 * SECOND, || {}).is_some(),
        "zenoh_peer {args:?} did not start within 60 s"
    );
    p
}

/// A std_msgs/String body (CDR, little endian, without the encapsulation header).
fn string_body(text: &str) -> Vec<u8> {
    let data = [text.as_bytes(), b"\0"].concat();
    [(data.len() as u32).to_le_bytes().to_vec(), data].concat()
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len() / 2)
        .filter_map(|i| u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok())
        .collect()
}

/// A `SAMPLE {...}` or `REPLY {...}` line: key, payload, attachment.
fn parse_sample(l: &str, prefix: &str) -> Option<(String, Vec<u8>, Option<Vec<u8>>)> {
    let v: serde_json::Value = serde_json::from_str(l.strip_prefix(prefix)?).ok()?;
    Some((
        v["key"].as_str()?.to_string(),
        unhex(v["payload"].as_str()?),
        v["attachment"].as_str().map(unhex),
    ))
}

/// The node `talker` in DOMAIN with a writer and a reader on rt/chatter (`flags` their QoS).
fn create_talker(c: &mut TestClient, flags: u16) -> (ObjectId, ObjectId) {
    let p = ObjectId::new(1, k::PARTICIPANT);
    let t = ObjectId::new(1, k::TOPIC);
    let publisher = ObjectId::new(1, k::PUBLISHER);
    let subscriber = ObjectId::new(1, k::SUBSCRIBER);
    let w = ObjectId::new(1, k::DATAWRITER);
    let r = ObjectId::new(1, k::DATAREADER);
    let participant = ParticipantBinary {
        domain_reference: None,
        qos_profile_reference: Some("talker".into()),
    };
    let topic = TopicBinary {
        topic_name: "rt/chatter".into(),
        type_reference: None,
        type_name: Some(STRING.into()),
    };
    let endpoint = EndpointBinary {
        topic_id: t,
        qos: Some(EndpointBinaryQos {
            base: EndpointQosBinary {
                flags,
                history_depth: Some(5),
                ..EndpointQosBinary::default()
            },
            ..EndpointBinaryQos::default()
        }),
    };
    let steps = [
        (
            p,
            k::PARTICIPANT,
            participant.encode(true),
            VariantExtra::DomainId(DOMAIN),
        ),
        (t, k::TOPIC, topic.encode(true), VariantExtra::Parent(p)),
        (
            publisher,
            k::PUBLISHER,
            GroupBinary::default().encode(true),
            VariantExtra::Parent(p),
        ),
        (
            subscriber,
            k::SUBSCRIBER,
            GroupBinary::default().encode(true),
            VariantExtra::Parent(p),
        ),
        (
            w,
            k::DATAWRITER,
            endpoint.encode(true, true),
            VariantExtra::Parent(publisher),
        ),
        (
            r,
            k::DATAREADER,
            endpoint.encode(false, true),
            VariantExtra::Parent(subscriber),
        ),
    ];
    for (id, kind, body, extra) in steps {
        assert_eq!(
            c.create_as(id, kind, Representation::Binary(body), extra),
            status::OK,
            "creating {id:?}"
        );
    }
    (w, r)
}

/// The node `node` in DOMAIN with an AddTwoInts requester or replier (`kind`) on micro-ROS's
/// topic names, an unlimited read started on it.
fn create_adder(c: &mut TestClient, node: &str, kind: u8) -> ObjectId {
    let p = ObjectId::new(1, k::PARTICIPANT);
    let participant = ParticipantBinary {
        domain_reference: None,
        qos_profile_reference: Some(node.into()),
    };
    assert_eq!(
        c.create_as(
            p,
            k::PARTICIPANT,
            Representation::Binary(participant.encode(true)),
            VariantExtra::DomainId(DOMAIN)
        ),
        status::OK
    );
    let element = if kind == k::REQUESTER {
        "requester"
    } else {
        "replier"
    };
    let xml = format!(
        "<dds><{element} profile_name=\"add\" service_name=\"/add_two_ints\" \
         request_type=\"example_interfaces::srv::dds_::AddTwoInts_Request_\" \
         reply_type=\"example_interfaces::srv::dds_::AddTwoInts_Response_\">\
         <request_topic_name>rq/add_two_intsRequest</request_topic_name>\
         <reply_topic_name>rr/add_two_intsReply</reply_topic_name></{element}></dds>"
    );
    let e = ObjectId::new(1, kind);
    assert_eq!(c.create(e, kind, &xml, VariantExtra::Parent(p)), status::OK);
    c.read_unlimited(e);
    e
}

/// Waits until every one of `wanted` appears among the lines `peer` printed (kept in
/// `lines`), pumping the client.
fn wait_lines(
    c: &mut TestClient,
    peer: &DdsPeer,
    lines: &mut Vec<String>,
    d: Duration,
    mut wanted: impl FnMut(&[String]) -> bool,
) -> bool {
    c.run_until(d, |c| {
        while let Some(l) = peer.line(Duration::from_millis(1)) {
            lines.push(l);
        }
        c.step();
        wanted(lines)
    })
}

fn chatter_key() -> String {
    format!("{DOMAIN}/chatter/{STRING}/{STRING_HASH}")
}

#[test]
fn an_xrce_node_joins_an_rmw_zenoh_graph_and_survives_a_worker_kill() {
    let g = start_graph("zenoh");
    let tokens = peer(&g, &["tokens", "--key", "@ros2_lv/**", "--timeout", "180"]);
    let sub = peer(
        &g,
        &[
            "sub",
            "--key",
            &chatter_key(),
            "--count",
            "100",
            "--timeout",
            "180",
        ],
    );
    let mut c = TestClient::new(g.agent.addr(), [0x2E, 0x40, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let (w, r) = create_talker(&mut c, qos_flags::RELIABLE | qos_flags::HISTORY_KEEP_LAST);
    c.read_unlimited(r);

    // The graph: the node and its two endpoints, as rmw_zenoh's tokens.
    let node = "/NN/%/%/talker".to_string();
    let publisher = format!("/MP/%/%/talker/%chatter/{STRING}/{STRING_HASH}/::,5:,:,:,,");
    let subscription = format!("/MS/%/%/talker/%chatter/{STRING}/{STRING_HASH}/::,5:,:,:,,");
    let seen = |lines: &[String], part: &str| {
        lines
            .iter()
            .any(|l| l.starts_with(&format!("TOKEN PUT @ros2_lv/{DOMAIN}/")) && l.ends_with(part))
    };
    let mut token_lines = Vec::new();
    let ok = wait_lines(&mut c, &tokens, &mut token_lines, 30 * SECOND, |l| {
        seen(l, &node) && seen(l, &publisher) && seen(l, &subscription)
    });
    assert!(ok, "the graph's tokens: {token_lines:#?}");

    // XRCE -> Zenoh: rmw_zenoh's payload (encapsulation header, body) and attachment.
    let mut sample_lines = Vec::new();
    let mut sent = 0u32;
    for i in 1..=3 {
        c.write_reliable(w, &string_body(&format!("hello {i}")));
        sent += 1;
    }
    let ok = wait_lines(&mut c, &sub, &mut sample_lines, 30 * SECOND, |l| {
        l.len() >= 3
    });
    assert!(ok, "samples at the Zenoh subscriber: {sample_lines:#?}");
    let mut gid = None;
    for (i, l) in sample_lines.iter().enumerate() {
        let (key, payload, attachment) = parse_sample(l, "SAMPLE ").expect("a sample line");
        assert_eq!(key, chatter_key());
        let body = string_body(&format!("hello {}", i + 1));
        assert_eq!(
            hex(&payload),
            format!("00010000{}", hex(&body)),
            "payload {l}"
        );
        let a = attachment.expect("rmw_zenoh's attachment");
        assert_eq!(a.len(), 33, "attachment {l}");
        assert_eq!(
            i64::from_le_bytes(a[..8].try_into().expect("8")),
            i as i64 + 1
        );
        let ts = i64::from_le_bytes(a[8..16].try_into().expect("8"));
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .expect("clock")
            .as_nanos() as i64;
        assert!(
            (now - ts).abs() < 60_000_000_000,
            "source timestamp {ts} vs now {now}"
        );
        assert_eq!(a[16], 16, "the GID's length");
        assert!(
            gid.is_none_or(|g: [u8; 16]| g == a[17..]),
            "one GID per publisher"
        );
        gid = Some(a[17..].try_into().expect("16"));
    }

    // Zenoh -> XRCE: a publisher as rmw_zenoh's, heard by the client's reader.
    let _publisher = peer(
        &g,
        &[
            "pub",
            "--key",
            &chatter_key(),
            "--count",
            "3",
            "--message",
            "from zenoh",
            "--delay-ms",
            "300",
        ],
    );
    // The client's reader hears its own writer too (as a reader of an rmw_zenoh node does,
    // without `ignore_local_publications`): only the peer's samples are counted here.
    let mut got = Vec::new();
    let ok = c.run_until(30 * SECOND, |c| {
        c.step();
        got.extend(
            c.take_data()
                .into_iter()
                .map(|(_, d)| d)
                .filter(|d| d.get(4..8) == Some(&b"from"[..])),
        );
        got.len() >= 3
    });
    assert!(ok, "samples from the Zenoh publisher: {got:?}");
    for (i, d) in got.iter().take(3).enumerate() {
        assert_eq!(d, &string_body(&format!("from zenoh {}", i + 1)));
    }

    // A worker killed: restarted, the node replayed onto Zenoh, samples flow again.
    let workers = g.agent.child_pids("dds-worker");
    assert_eq!(workers.len(), 1, "one worker");
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(workers[0]),
        nix::sys::signal::SIGKILL,
    )
    .expect("kill the worker");
    // Counted by text: the subscriber hears the peer's publisher on the key as well.
    let text = |l: &String| {
        parse_sample(l, "SAMPLE ")
            .map(|(_, p, _)| String::from_utf8_lossy(p.get(8..).unwrap_or_default()).to_string())
    };
    let after = |lines: &[String]| {
        lines
            .iter()
            .filter_map(text)
            .filter(|t| t.starts_with("after "))
            .count()
    };
    let end = Instant::now() + 60 * SECOND;
    let mut next = Instant::now();
    while after(&sample_lines) < 2 && Instant::now() < end {
        if Instant::now() >= next {
            sent += 1;
            c.write_reliable(w, &string_body(&format!("after {sent}")));
            next = Instant::now() + Duration::from_millis(300);
        }
        wait_lines(
            &mut c,
            &sub,
            &mut sample_lines,
            Duration::from_millis(100),
            |_| false,
        );
    }
    assert!(
        after(&sample_lines) >= 2,
        "samples after the worker restart: {sample_lines:#?}"
    );
    // The tokens again, from the new worker's session (another Zenoh id).
    let zid_of = |l: &str| l.split('/').nth(2).map(str::to_string);
    let first_zid = token_lines
        .iter()
        .find(|x| x.starts_with("TOKEN PUT") && x.ends_with(&publisher))
        .and_then(|l| zid_of(l))
        .expect("the first publisher token's zid");
    let mut new_zid = None;
    let ok = wait_lines(&mut c, &tokens, &mut token_lines, 30 * SECOND, |l| {
        new_zid = l
            .iter()
            .filter(|x| x.starts_with("TOKEN PUT") && x.ends_with(&publisher))
            .filter_map(|x| zid_of(x))
            .find(|z| *z != first_zid);
        new_zid.is_some()
    });
    assert!(
        ok,
        "the publisher's token from the restarted worker: {token_lines:#?}"
    );
    let new_zid = new_zid.expect("a new zid");

    // The participant deleted: the new session's tokens go.
    let mark = token_lines.len();
    let del = c
        .client
        .delete(Instant::now(), ObjectId::new(1, k::PARTICIPANT))
        .expect("delete");
    assert_eq!(c.wait_status(del, 10 * SECOND), status::OK);
    let withdrawn = |l: &[String], part: &str| {
        l[mark..].iter().any(|x| {
            x.starts_with(&format!("TOKEN DELETE @ros2_lv/{DOMAIN}/{new_zid}/"))
                && x.ends_with(part)
        })
    };
    let ok = wait_lines(&mut c, &tokens, &mut token_lines, 30 * SECOND, |l| {
        withdrawn(l, &node) && withdrawn(l, &publisher) && withdrawn(l, &subscription)
    });
    assert!(ok, "the tokens withdrawn: {token_lines:#?}");
    drop(g.router);
    assert!(g.agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_zenoh_client_calls_an_xrce_replier() {
    let g = start_graph("zenohsrv");
    let mut c = TestClient::new(g.agent.addr(), [0x2E, 0x40, 0x00, 0x02]);
    c.connect(10 * SECOND);
    let replier = create_adder(&mut c, "adder", k::REPLIER);
    let tokens = peer(&g, &["tokens", "--key", "@ros2_lv/**", "--timeout", "60"]);
    let server = format!("/SS/%/%/adder/%add_two_ints/{ADD_TWO_INTS}/{ADD_TWO_INTS_HASH}/");
    let mut token_lines = Vec::new();
    let ok = wait_lines(&mut c, &tokens, &mut token_lines, 30 * SECOND, |l| {
        l.iter()
            .any(|x| x.starts_with("TOKEN PUT") && x.contains(&server))
    });
    assert!(ok, "the service's token: {token_lines:#?}");

    // Two requests {a, b} (int64), CDR with its header, as rmw_zenoh's client sends them.
    let request = |a: i64, b: i64| {
        hex(&[
            vec![0, 1, 0, 0],
            a.to_le_bytes().to_vec(),
            b.to_le_bytes().to_vec(),
        ]
        .concat())
    };
    let key = format!("{DOMAIN}/add_two_ints/{ADD_TWO_INTS}/{ADD_TWO_INTS_HASH}");
    let client = peer(
        &g,
        &[
            "call",
            "--key",
            &key,
            "--count",
            "2",
            "--payload",
            &request(40, 2),
            "--delay-ms",
            "300",
            "--timeout",
            "30",
        ],
    );
    let mut replies = Vec::new();
    let mut answered = 0;
    let ok = c.run_until(40 * SECOND, |c| {
        c.step();
        for (_, d) in c.take_data() {
            // The request's SampleIdentity (24 bytes), then {a, b}.
            assert_eq!(d.len(), 24 + 16, "{d:?}");
            let a = i64::from_le_bytes(d[24..32].try_into().expect("8"));
            let b = i64::from_le_bytes(d[32..40].try_into().expect("8"));
            let reply = [d[..24].to_vec(), (a + b).to_le_bytes().to_vec()].concat();
            c.write_reliable(replier, &reply);
            answered += 1;
        }
        while let Some(l) = client.line(Duration::from_millis(1)) {
            replies.push(l);
        }
        replies.iter().filter(|l| l.starts_with("REPLY ")).count() >= 2
    });
    assert!(
        ok,
        "replies at the Zenoh client ({answered} answered): {replies:#?}"
    );
    for (i, l) in replies
        .iter()
        .filter(|l| l.starts_with("REPLY "))
        .enumerate()
    {
        let (rkey, payload, attachment) = parse_sample(l, "REPLY ").expect("a reply line");
        assert_eq!(rkey, key);
        assert_eq!(
            hex(&payload),
            format!("00010000{}", hex(&42i64.to_le_bytes()))
        );
        let a = attachment.expect("the reply's attachment");
        assert_eq!(a.len(), 33);
        assert_eq!(
            i64::from_le_bytes(a[..8].try_into().expect("8")),
            i as i64 + 1,
            "the request's sequence number"
        );
        assert_eq!(
            &a[17..],
            &(0xC0..0xD0).collect::<Vec<u8>>()[..],
            "the client's GID"
        );
    }
    drop(g.router);
    assert!(g.agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_late_zenoh_subscription_gets_a_transient_local_history() {
    let g = start_graph("zenohtl");
    let mut c = TestClient::new(g.agent.addr(), [0x2E, 0x40, 0x00, 0x03]);
    c.connect(10 * SECOND);
    let flags =
        qos_flags::RELIABLE | qos_flags::HISTORY_KEEP_LAST | qos_flags::DURABILITY_TRANSIENT_LOCAL;
    let (w, _) = create_talker(&mut c, flags);
    for i in 1..=3 {
        c.write_reliable(w, &string_body(&format!("kept {i}")));
    }
    // Written before anyone listened: the late subscription asks the publisher's cache.
    c.run_until(SECOND, |_| false);
    let late = peer(
        &g,
        &[
            "sub",
            "--key",
            &chatter_key(),
            "--count",
            "3",
            "--timeout",
            "30",
            "--transient-local",
        ],
    );
    let mut lines = Vec::new();
    let ok = wait_lines(&mut c, &late, &mut lines, 30 * SECOND, |l| l.len() >= 3);
    assert!(ok, "the history at the late subscription: {lines:#?}");
    let texts: Vec<String> = lines
        .iter()
        .filter_map(|l| parse_sample(l, "SAMPLE "))
        .map(|(_, p, _)| String::from_utf8_lossy(&p[8..p.len() - 1]).to_string())
        .collect();
    assert_eq!(texts, ["kept 1", "kept 2", "kept 3"]);
    drop(g.router);
    assert!(g.agent.stop(), "agent did not stop cleanly");
}

#[test]
fn an_xrce_requester_calls_a_zenoh_service() {
    let g = start_graph("zenohcli");
    let key = format!("{DOMAIN}/add_two_ints/{ADD_TWO_INTS}/{ADD_TWO_INTS_HASH}");
    let server = peer(
        &g,
        &["serve", "--key", &key, "--count", "3", "--timeout", "60"],
    );
    let mut c = TestClient::new(g.agent.addr(), [0x2E, 0x40, 0x00, 0x04]);
    c.connect(10 * SECOND);
    let requester = create_adder(&mut c, "caller", k::REQUESTER);
    // The server's queryable known to the agent's session (through the router) before the
    // requests go: a query that finds no queryable ends without a reply.
    c.run_until(2 * SECOND, |_| false);
    // Three requests at once: the replies may come in any order, each to its request.
    let mut ids = std::collections::HashMap::new();
    for (a, b) in [(1i64, 2i64), (30, 12), (-5, 5)] {
        let body = [a.to_le_bytes(), b.to_le_bytes()].concat();
        let id = c.write_reliable_id(requester, &body);
        ids.insert(id, a + b);
    }
    let mut sums = std::collections::HashMap::new();
    let mut served = Vec::new();
    let ok = c.run_until(40 * SECOND, |c| {
        c.step();
        for (_, d) in c.take_data() {
            // The BaseObjectRequest of the request, then {sum}.
            assert_eq!(d.len(), 4 + 8, "{d:?}");
            assert_eq!(ObjectId([d[2], d[3]]), requester);
            let id = xrce_common::wire::RequestId([d[0], d[1]]);
            let sum = i64::from_le_bytes(d[4..12].try_into().expect("8"));
            assert!(sums.insert(id, sum).is_none(), "a reply twice for {id:?}");
        }
        while let Some(l) = server.line(Duration::from_millis(1)) {
            served.push(l);
        }
        sums.len() >= 3
    });
    assert!(
        ok,
        "replies at the XRCE requester: {sums:?}, served {served:?}"
    );
    assert_eq!(sums, ids, "each reply answers its own request");
    // The server saw rmw_zenoh's request attachment: sequence numbers 1..3, one client GID.
    let requests: Vec<Vec<&str>> = served
        .iter()
        .filter(|l| l.starts_with("REQUEST "))
        .map(|l| l.split(' ').collect())
        .collect();
    let mut seqs: Vec<&str> = requests.iter().map(|r| r[1]).collect();
    seqs.sort();
    assert_eq!(seqs, ["1", "2", "3"], "{served:?}");
    assert!(requests
        .iter()
        .all(|r| r[4] == requests[0][4] && r[4].len() == 32));
    drop(g.router);
    assert!(g.agent.stop(), "agent did not stop cleanly");
}

/// Set, to `writer` or `reader`, in the environment of this test binary started again inside
/// a network namespace by [`devices_on_two_lans_meet_through_one_router`].
const LAN_ROLE: &str = "XRCE_TEST_ZENOH_LAN_ROLE";
/// The router's endpoint as seen from that namespace.
const LAN_ROUTER: &str = "XRCE_TEST_ZENOH_LAN_ROUTER";

/// Network namespaces made for one test, deleted with it.
struct Namespaces(Vec<String>);

impl Drop for Namespaces {
    fn drop(&mut self) {
        for n in &self.0 {
            let _ = std::process::Command::new("ip")
                .args(["netns", "del", n])
                .status();
        }
    }
}

fn ip(args: &[&str]) {
    let st = std::process::Command::new("ip")
        .args(args)
        .status()
        .expect("run ip");
    assert!(st.success(), "ip {args:?} failed");
}

/// Two agents on `-m zenoh` in two network namespaces ("LANs") that reach each other only
/// through a Zenoh router in a third (no IP route between them): a client's samples on one
/// LAN reach a client's reader on the other, as rmw_zenoh nodes across a router do.
/// Needs root (`ip netns`), as the suite's other namespace tests.
#[test]
fn devices_on_two_lans_meet_through_one_router() {
    if let Ok(role) = std::env::var(LAN_ROLE) {
        let router = std::env::var(LAN_ROUTER).expect("the router's endpoint");
        ip(&["link", "set", "lo", "up"]);
        return lan_role(&role, &router);
    }
    // Built (and Zenoh's Python installed) out here, where the network is.
    xrce_tests::binaries();
    xrce_tests::zenoh_python();
    let tag = std::process::id() % 100_000;
    let names: Vec<String> = ["a", "b", "r"]
        .iter()
        .map(|n| format!("xrce-z{n}-{tag}"))
        .collect();
    for n in &names {
        let st = std::process::Command::new("ip")
            .args(["netns", "add", n])
            .status();
        assert!(
            st.is_ok_and(|s| s.success()),
            "`ip netns add` failed: this test needs root (CAP_SYS_ADMIN) and iproute2"
        );
    }
    let ns = Namespaces(names);
    let (a, b, r) = (&ns.0[0], &ns.0[1], &ns.0[2]);
    for (lan, host, subnet) in [(a, "a", 1), (b, "b", 2)] {
        let (outer, inner) = (format!("xz{host}{tag}"), format!("xr{host}{tag}"));
        ip(&[
            "link", "add", &outer, "type", "veth", "peer", "name", &inner,
        ]);
        ip(&["link", "set", &outer, "netns", lan]);
        ip(&["link", "set", &inner, "netns", r]);
        ip(&[
            "-n",
            lan,
            "addr",
            "add",
            &format!("10.231.{subnet}.2/24"),
            "dev",
            &outer,
        ]);
        ip(&[
            "-n",
            r,
            "addr",
            "add",
            &format!("10.231.{subnet}.1/24"),
            "dev",
            &inner,
        ]);
        ip(&["-n", lan, "link", "set", &outer, "up"]);
        ip(&["-n", r, "link", "set", &inner, "up"]);
    }
    ip(&["-n", r, "link", "set", "lo", "up"]);
    let router = DdsPeer::zenoh_in(
        r,
        &[
            "router",
            "--private-namespace",
            "--listen",
            "tcp/10.231.1.1:7447",
            "--listen",
            "tcp/10.231.2.1:7447",
        ],
    );
    assert!(
        router.wait_for("READY", 30 * SECOND, || {}).is_some(),
        "the router did not start in its namespace"
    );
    let exe = std::env::current_exe().expect("the test binary");
    let start = |lan: &str, role: &str, subnet: u8| {
        std::process::Command::new("ip")
            .args(["netns", "exec", lan])
            .arg(&exe)
            .arg(libtest_name(
                module_path!(),
                "devices_on_two_lans_meet_through_one_router",
            ))
            .args(["--exact", "--nocapture", "--test-threads", "1"])
            .env(LAN_ROLE, role)
            .env(LAN_ROUTER, format!("tcp/10.231.{subnet}.1:7447"))
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("start the test in its namespace")
    };
    let mut writer = start(a, "writer", 1);
    let reader = start(b, "reader", 2);
    let out = {
        let mut reader = reader;
        let stdout = reader.stdout.take();
        let collected = std::thread::spawn(move || {
            let mut text = String::new();
            if let Some(mut out) = stdout {
                let _ = std::io::Read::read_to_string(&mut out, &mut text);
            }
            text
        });
        let end = Instant::now() + 150 * SECOND;
        let status = loop {
            if let Ok(Some(st)) = reader.try_wait() {
                break Some(st);
            }
            if Instant::now() >= end {
                let _ = reader.kill();
                let _ = reader.wait();
                break None;
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        (status, collected.join().unwrap_or_default())
    };
    // Its stdin closed, the writer stops its agent and ends (killed, it would leave the agent
    // running).
    drop(writer.stdin.take());
    let end = Instant::now() + 30 * SECOND;
    while writer.try_wait().ok().flatten().is_none() && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = writer.kill();
    let _ = writer.wait();
    let (status, stdout) = out;
    eprintln!("{stdout}");
    assert!(
        status.is_some_and(|s| s.success()),
        "the reader on LAN b failed or did not end in 150 s"
    );
    assert!(stdout.contains("1 passed"), "the reader did not run");
    assert!(stdout.contains("RECEIVED 3"), "{stdout}");
    drop(router);
}

/// One side of [`devices_on_two_lans_meet_through_one_router`], inside its namespace.
fn lan_role(role: &str, router: &str) {
    let overrides =
        format!("connect/endpoints=[\"{router}\"];listen/endpoints=[\"tcp/127.0.0.1:0\"]");
    let agent = AgentProcess::builder(&format!("lan{role}"))
        .env(&[
            ("XRCE_DDS_BACKEND", "zenoh"),
            ("ZENOH_CONFIG_OVERRIDE", &overrides),
        ])
        .start();
    let mut c = TestClient::new(agent.addr(), [0x2E, 0x40, 0x00, 0x10]);
    c.connect(10 * SECOND);
    let (w, r) = create_talker(&mut c, qos_flags::RELIABLE | qos_flags::HISTORY_KEEP_LAST);
    if role == "writer" {
        // Until the outer test has seen the reader through and closes this one's stdin.
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let eof = stop.clone();
        std::thread::spawn(move || {
            let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut Vec::new());
            eof.store(true, std::sync::atomic::Ordering::Relaxed);
        });
        let end = Instant::now() + 120 * SECOND;
        let mut i = 0;
        while Instant::now() < end && !stop.load(std::sync::atomic::Ordering::Relaxed) {
            i += 1;
            c.write_reliable(w, &string_body(&format!("from lan a {i}")));
            c.run_until(Duration::from_millis(200), |_| false);
        }
        assert!(agent.stop(), "agent did not stop cleanly");
        return;
    }
    c.read_unlimited(r);
    let mut got = Vec::new();
    let ok = c.run_until(90 * SECOND, |c| {
        c.step();
        got.extend(
            c.take_data()
                .into_iter()
                .filter(|(_, d)| d.get(4..14) == Some(&b"from lan a"[..])),
        );
        got.len() >= 3
    });
    assert!(ok, "samples from the other LAN: {got:?}");
    println!("RECEIVED {}", got.len().min(3));
    assert!(agent.stop(), "agent did not stop cleanly");
}
