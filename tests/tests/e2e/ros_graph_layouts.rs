//! The ROS 2 graph in the layout of the distribution in use: `ros_discovery_info`
//! (rmw_dds_common's ParticipantEntitiesInfo) carries 24-octet GIDs for Humble and 16-octet
//! GIDs for Iron and later. An independent decoder (tests/python/ros_graph_layouts.py,
//! Cyclone DDS's Python binding with the IDL of one layout) reads what the agent announces
//! for a node created the way micro-ROS creates one: the decoder of the layout chosen
//! (`XRCE_ROS_DISTRO`, `ROS_DISTRO`, or the default, jazzy) finds the node, the decoder of
//! the other layout does not. An unknown `ROS_DISTRO` stops the worker at start, naming the
//! accepted values.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use xrce_common::wire::binary::{
    qos_flags, EndpointBinary, EndpointBinaryQos, EndpointQosBinary, GroupBinary,
    ParticipantBinary, TopicBinary,
};
use xrce_common::wire::{object_kind as k, status, ObjectId, Representation, VariantExtra};
use xrce_tests::{
    binaries, cyclone_python, output_within, unique_instance, workspace, AgentProcess, TestClient,
};

const SECOND: Duration = Duration::from_secs(1);

/// A running `ros_graph_layouts.py` with its output lines on a channel (killed when dropped):
/// stdout as the script prints it, stderr prefixed with `STDERR ` (Cyclone DDS itself logs
/// there a sample it cannot deserialize with the reader's type and drops it, before Python
/// sees it: that is how the decoder of one layout usually refuses the other).
struct LayoutDecoder {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl LayoutDecoder {
    /// Starts the decoder of `layout` (`humble` or `jazzy`) in `domain`, pinned to loopback
    /// like `dds_peer.py`, and waits for its READY line.
    fn start(layout: &'static str, domain: u16) -> Self {
        let xml = workspace().join("tests/python/cyclonedds-loopback.xml");
        let mut child = Command::new(cyclone_python())
            .arg(workspace().join("tests/python/ros_graph_layouts.py"))
            .args(["--layout", layout, "--domain", &domain.to_string()])
            .args(["--timeout", "90"])
            .env("CYCLONEDDS_URI", format!("file://{}", xml.display()))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start ros_graph_layouts.py");
        let stdout = child.stdout.take().expect("stdout");
        let stderr = child.stderr.take().expect("stderr");
        let (tx, lines) = mpsc::channel();
        let tx_err = tx.clone();
        std::thread::spawn(move || {
            for l in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        std::thread::spawn(move || {
            for l in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx_err.send(format!("STDERR {l}")).is_err() {
                    break;
                }
            }
        });
        let d = LayoutDecoder { child, lines };
        let ready = d.lines.recv_timeout(60 * SECOND).unwrap_or_default();
        assert!(
            ready.starts_with(&format!("READY {layout} ")),
            "{layout} decoder not ready: {ready:?}"
        );
        d
    }

    /// The lines printed since the last call.
    fn drain(&self) -> Vec<String> {
        self.lines.try_iter().collect()
    }
}

impl Drop for LayoutDecoder {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A decoded node: namespace, name, reader GIDs, writer GIDs (hex).
#[derive(Debug, Clone, PartialEq, Eq)]
struct Node {
    ns: String,
    name: String,
    readers: Vec<String>,
    writers: Vec<String>,
}

/// A `GRAPH {...}` line: the participant's GID and the nodes; None for any other line.
fn parse_graph(l: &str) -> Option<(String, Vec<Node>)> {
    let v: serde_json::Value = serde_json::from_str(l.strip_prefix("GRAPH ")?).ok()?;
    let gids = |n: &serde_json::Value, key: &str| -> Option<Vec<String>> {
        n[key]
            .as_array()?
            .iter()
            .map(|g| Some(g.as_str()?.to_string()))
            .collect()
    };
    let nodes = v["nodes"]
        .as_array()?
        .iter()
        .map(|n| {
            Some(Node {
                ns: n["ns"].as_str()?.to_string(),
                name: n["name"].as_str()?.to_string(),
                readers: gids(n, "readers")?,
                writers: gids(n, "writers")?,
            })
        })
        .collect::<Option<Vec<_>>>()?;
    Some((v["gid"].as_str()?.to_string(), nodes))
}

/// Whether `l` says the decoder could not parse a `ros_discovery_info` sample: the script's
/// `PARSE_FAILED`, or Cyclone DDS's own log line when it drops the sample first
/// (`... deserialization ros_discovery_info/rmw_dds_common::...ParticipantEntitiesInfo_
/// failed ...`).
fn is_parse_failure(l: &str) -> bool {
    l.starts_with("PARSE_FAILED ")
        || (l.starts_with("STDERR ")
            && l.contains("deserialization ros_discovery_info/")
            && l.contains("failed"))
}

/// The node this test creates, as a decoder should see it.
fn is_our_node(n: &Node) -> bool {
    n.ns == "/robot" && n.name == "arm_driver" && n.readers.len() == 1 && n.writers.len() == 1
}

/// Creates, as micro-ROS does (binary representations), a participant named
/// `/robot/arm_driver` in `domain` with a writer and a reader on `rt/chatter`: a ROS node
/// the agent announces.
fn create_ros_node(c: &mut TestClient, domain: u16) {
    let p = ObjectId::new(1, k::PARTICIPANT);
    let t = ObjectId::new(1, k::TOPIC);
    let publisher = ObjectId::new(1, k::PUBLISHER);
    let subscriber = ObjectId::new(1, k::SUBSCRIBER);
    let participant = ParticipantBinary {
        domain_reference: None,
        qos_profile_reference: Some("/robot/arm_driver".into()),
    };
    let topic = TopicBinary {
        topic_name: "rt/chatter".into(),
        type_reference: None,
        type_name: Some("std_msgs::msg::dds_::String_".into()),
    };
    let endpoint = EndpointBinary {
        topic_id: t,
        qos: Some(EndpointBinaryQos {
            base: EndpointQosBinary {
                flags: qos_flags::RELIABLE | qos_flags::HISTORY_KEEP_LAST,
                history_depth: Some(5),
                ..EndpointQosBinary::default()
            },
            ..EndpointBinaryQos::default()
        }),
    };
    let domain = i16::try_from(domain).expect("a small domain id");
    let steps = [
        (
            p,
            k::PARTICIPANT,
            participant.encode(true),
            VariantExtra::DomainId(domain),
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
            ObjectId::new(1, k::DATAWRITER),
            k::DATAWRITER,
            endpoint.encode(true, true),
            VariantExtra::Parent(publisher),
        ),
        (
            ObjectId::new(1, k::DATAREADER),
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
}

/// Runs an agent with `env`, creates the node in `domain`, and checks that the decoder of
/// `expected` (`humble` or `jazzy`) decodes it with GIDs of its length while the other
/// decoder decodes no such node (it fails to parse, or reads nonsense such as no node).
fn the_node_is_decoded_in(expected: &'static str, env: &[(&str, &str)], domain: u16) {
    let agent = AgentProcess::builder("roslayout").env(env).start();
    let other = if expected == "humble" {
        "jazzy"
    } else {
        "humble"
    };
    let right = LayoutDecoder::start(expected, domain);
    let wrong = LayoutDecoder::start(other, domain);
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x4C, 0x00, domain as u8]);
    c.connect(10 * SECOND);
    create_ros_node(&mut c, domain);

    let (mut right_lines, mut wrong_lines) = (Vec::new(), Vec::new());
    let mut found: Option<(String, Node)> = None;
    let ok = c.run_until(40 * SECOND, |c| {
        for l in right.drain() {
            if let Some((gid, nodes)) = parse_graph(&l) {
                if let Some(n) = nodes.into_iter().find(is_our_node) {
                    found = Some((gid, n));
                }
            }
            right_lines.push(l);
        }
        wrong_lines.extend(wrong.drain());
        c.step();
        std::thread::sleep(Duration::from_millis(5));
        // The other decoder has had a sample too (decoded or refused).
        found.is_some()
            && wrong_lines
                .iter()
                .any(|l| l.starts_with("GRAPH ") || is_parse_failure(l))
    });
    assert!(
        ok,
        "the {expected} decoder did not read the node, or the {other} decoder got nothing: \
         {expected}: {right_lines:?}; {other}: {wrong_lines:?}"
    );
    // Let the graph settle (the writer and the reader may come in two updates), then look
    // at everything the other decoder got.
    let settle = Instant::now() + SECOND;
    while Instant::now() < settle {
        c.step();
        std::thread::sleep(Duration::from_millis(10));
    }
    right_lines.extend(right.drain());
    wrong_lines.extend(wrong.drain());

    let (gid, node) = found.expect("found");
    let octets = if expected == "humble" { 24 } else { 16 };
    for g in [&gid, &node.readers[0], &node.writers[0]] {
        assert_eq!(g.len(), 2 * octets, "a {octets}-octet GID: {g}");
        assert_ne!(&g[..32], &"0".repeat(32), "the GUID is in front: {g}");
        if octets == 24 {
            // The 16-octet GUID padded with zeros, as rmw fills Humble's rmw_gid_t.
            assert_eq!(&g[32..], &"0".repeat(16), "zero padding: {g}");
        }
    }
    assert_ne!(node.readers[0], node.writers[0]);
    // The right decoder refused nothing.
    assert!(
        !right_lines.iter().any(|l| is_parse_failure(l)),
        "the {expected} decoder refused a sample: {right_lines:?}"
    );
    // The other layout never yields the node: its decoder fails, or reads something else.
    for l in &wrong_lines {
        if let Some((_, nodes)) = parse_graph(l) {
            assert!(
                !nodes.iter().any(|n| n.name == "arm_driver"),
                "the {other} decoder read the {expected} message as if it were its own: {l}"
            );
        } else {
            assert!(
                is_parse_failure(l) || l.starts_with("STDERR "),
                "unexpected {other} decoder line: {l}"
            );
        }
    }
    eprintln!("{other} decoder on the {expected} layout: {wrong_lines:?}");
    // The worker said which layout it publishes, and why.
    assert!(
        agent
            .output()
            .wait_for(0, "ROS 2 graph layout", 5 * SECOND)
            .is_some_and(|(_, l)| l.contains(&format!("gid_octets={octets}"))),
        "no layout line with {octets} octets"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn xrce_ros_distro_humble_publishes_24_octet_gids() {
    the_node_is_decoded_in("humble", &[("XRCE_ROS_DISTRO", "humble")], 105);
}

#[test]
fn by_default_the_graph_has_jazzy_s_16_octet_gids() {
    // An empty ROS_DISTRO counts as unset (whatever the shell running the tests sourced).
    the_node_is_decoded_in("jazzy", &[("ROS_DISTRO", "")], 106);
}

#[test]
fn ros_distro_from_a_sourced_humble_shell_reaches_the_worker() {
    // The supervisor passes its environment on: ROS_DISTRO needs no wiring.
    the_node_is_decoded_in("humble", &[("ROS_DISTRO", "humble")], 107);
}

#[test]
fn an_unknown_ros_distro_stops_the_worker_at_start_naming_the_accepted_ones() {
    let accepted = ["humble", "iron", "jazzy", "kilted", "rolling"];
    // From ROS_DISTRO (a Foxy shell, say): refused before any IPC or DDS starts.
    let out = output_within(
        Command::new(binaries().join("xrce-agent"))
            .args(["dds-worker", "--dds-interface", "127.0.0.1"])
            .args(["--instance", &unique_instance("rosdistro")])
            .env("ROS_DISTRO", "foxy")
            .env_remove("XRCE_ROS_DISTRO"),
        20 * SECOND,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "started with ROS_DISTRO=foxy: {err}");
    assert!(err.contains("\"foxy\""), "{err}");
    for a in accepted {
        assert!(err.contains(a), "{a} not named: {err}");
    }
    // From the option (or XRCE_ROS_DISTRO): refused by the command line.
    let out = output_within(
        Command::new(binaries().join("xrce-agent"))
            .args(["dds-worker", "--ros-distro", "galactic"])
            .env_remove("XRCE_ROS_DISTRO"),
        20 * SECOND,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "started with --ros-distro galactic: {err}"
    );
    for a in accepted {
        assert!(err.contains(a), "{a} not named: {err}");
    }
}
