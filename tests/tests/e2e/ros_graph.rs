//! The ROS 2 graph: a participant created the way micro-ROS creates a node (binary, named
//! `/ns/name`) is announced on `ros_discovery_info` with the GIDs of its writer and reader,
//! which Cyclone DDS decodes with the rmw_dds_common IDL and finds among the endpoints it
//! discovered; deleting the participant removes the node.

use std::time::Duration;

use xrce_common::wire::binary::{
    qos_flags, EndpointBinary, EndpointBinaryQos, EndpointQosBinary, GroupBinary,
    ParticipantBinary, TopicBinary,
};
use xrce_common::wire::{object_kind as k, status, ObjectId, Representation, VariantExtra};
use xrce_tests::{AgentProcess, DdsPeer, TestClient};

const SECOND: Duration = Duration::from_secs(1);

/// A node as announced: namespace, name, writer GIDs, reader GIDs (hex).
type Node = (String, String, Vec<String>, Vec<String>);

/// A `GRAPH {...}` line: its nodes.
fn parse_graph(l: &str) -> Option<Vec<Node>> {
    let v: serde_json::Value = serde_json::from_str(l.strip_prefix("GRAPH ")?).ok()?;
    let strings = |n: &serde_json::Value, key: &str| -> Vec<String> {
        n[key]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|g| Some(g.as_str()?.to_string()))
                    .collect()
            })
            .unwrap_or_default()
    };
    v["nodes"]
        .as_array()?
        .iter()
        .map(|n| {
            Some((
                n["ns"].as_str()?.to_string(),
                n["name"].as_str()?.to_string(),
                strings(n, "writers"),
                strings(n, "readers"),
            ))
        })
        .collect()
}

#[test]
fn a_micro_ros_node_is_announced_with_its_endpoints_and_removed_with_them() {
    let agent = AgentProcess::builder("rosgraph").start();
    let peer = DdsPeer::start(&[
        "graph",
        "--domain",
        "44",
        "--count",
        "100",
        "--timeout",
        "60",
    ]);
    // A plain XRCE application (participant `default_xrce_participant`, topic
    // HelloWorldTopic) in the same domain is not a ROS node.
    let mut plain = TestClient::new(agent.addr(), [0xF0, 0x4F, 0x00, 0x02]);
    plain.connect(10 * SECOND);
    plain.setup_publisher(44);
    let mut c = TestClient::new(agent.addr(), [0xF0, 0x4F, 0x00, 0x01]);
    c.connect(10 * SECOND);
    let p = ObjectId::new(1, k::PARTICIPANT);
    let t = ObjectId::new(1, k::TOPIC);
    let publisher = ObjectId::new(1, k::PUBLISHER);
    let subscriber = ObjectId::new(1, k::SUBSCRIBER);
    let w = ObjectId::new(1, k::DATAWRITER);
    let r = ObjectId::new(1, k::DATAREADER);
    let participant = ParticipantBinary {
        domain_reference: None,
        // Where eProsima's uxr_buffer_create_participant_bin puts the node name.
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
    let steps = [
        (
            p,
            k::PARTICIPANT,
            participant.encode(true),
            VariantExtra::DomainId(44),
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
    // The node with one writer and one reader, whose GIDs are endpoints Cyclone discovered
    // on rt/chatter.
    let mut lines = Vec::new();
    let mut node = None;
    let ok = c.run_until(40 * SECOND, |c| {
        while let Some(l) = peer.line(Duration::from_millis(1)) {
            if let Some(nodes) = parse_graph(&l) {
                node = nodes.into_iter().find(|n| {
                    n.0 == "/robot" && n.1 == "arm_driver" && n.2.len() == 1 && n.3.len() == 1
                });
            }
            lines.push(l);
        }
        c.step();
        node.as_ref().is_some_and(|(_, _, w, r)| {
            let seen = |kind: &str, gid: &str| {
                lines
                    .iter()
                    .any(|l| l == &format!("ENDPOINT {kind} {gid} rt/chatter"))
            };
            seen("pub", &w[0]) && seen("sub", &r[0])
        })
    });
    assert!(ok, "graph and endpoints seen: {node:?} in {lines:?}");
    assert!(
        lines
            .iter()
            .filter_map(|l| parse_graph(l))
            .flatten()
            .all(|n| n.1 == "arm_driver"),
        "only the micro-ROS node is announced: {lines:?}"
    );
    // Deleting the participant (and its endpoints) empties the node list.
    let del = c
        .client
        .delete(std::time::Instant::now(), p)
        .expect("delete");
    assert_eq!(c.wait_status(del, 10 * SECOND), status::OK);
    let mut emptied = false;
    let ok = c.run_until(20 * SECOND, |c| {
        while let Some(l) = peer.line(Duration::from_millis(1)) {
            if let Some(nodes) = parse_graph(&l) {
                emptied = nodes.iter().all(|n| n.1 != "arm_driver");
            }
            lines.push(l);
        }
        c.step();
        emptied
    });
    assert!(ok, "the node was not removed: {lines:?}");
    assert!(agent.stop(), "agent did not stop cleanly");
}
