use super::*;
use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant};
use xrce_dds_seam::fake::{keyed, keyed_spec};
use xrce_dds_seam::policies::{History, QosDesc, Reliability};
use xrce_dds_seam::DynEndpoints;
use xrce_dds_seam::EndpointSide;

fn addr(a: &str) -> IpAddr {
    a.parse().expect("address")
}

/// A backend pinned to loopback.
fn loopback() -> Cyclone {
    Cyclone::new(DdsConfig {
        interfaces: vec![addr("127.0.0.1")],
        ..Default::default()
    })
    .expect("backend")
}

/// Waits up to 5 s for `done` (discovery and acknowledgements run on Cyclone's
/// threads); the caller asserts what it waited for.
fn wait_until(mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(5);
    while !done() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Takes until `n` samples came or 5 s passed, waiting on the readiness descriptor.
fn take(dds: &mut Cyclone, r: &mut dyn DdsReader, n: usize) -> Vec<Taken> {
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut got = Vec::new();
    let mut tokens = Vec::new();
    while got.len() < n && Instant::now() < deadline {
        while let Some(t) = r.take_next().expect("take") {
            got.push(t);
        }
        if got.len() >= n {
            break;
        }
        if woken(dds.readiness_fd().as_raw_fd()) {
            dds.ready_readers(&mut tokens).expect("ready");
        }
    }
    got
}

/// Whether the readiness socket holds a wake-up, waiting up to 50 ms for one.
fn woken(fd: RawFd) -> bool {
    use nix::sys::socket::{recv, MsgFlags};
    let mut b = [0u8; 1];
    for _ in 0..10 {
        if recv(fd, &mut b, MsgFlags::MSG_PEEK | MsgFlags::MSG_DONTWAIT).unwrap_or(0) > 0 {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    false
}

#[test]
fn local_writers_reach_local_readers_with_keys_disposes_and_wake_ups() {
    let mut dds = loopback();
    let spec = keyed_spec("cyclone_unit_keyed");
    let keep_last_1 = QosDesc {
        reliability: Some(Reliability::Reliable),
        history: Some(History::KeepLast(1)),
        ..QosDesc::default()
    };
    let wq = EndpointQos::resolve(EndpointSide::Writer, &keep_last_1, &QosDesc::default());
    let rq = EndpointQos::resolve(EndpointSide::Reader, &keep_last_1, &QosDesc::default());
    let publisher = dds.create_publisher(89, &[]).expect("publisher");
    let subscriber = dds.create_subscriber(89, &[]).expect("subscriber");
    let mut reader = dds
        .create_reader(&subscriber, &spec, &rq, 7)
        .expect("reader");
    let writer = dds
        .create_writer(&publisher, &spec, &wq, true)
        .expect("writer");
    assert_eq!(dds.participants(), 1, "one participant per domain");
    wait_until(|| writer.matched_readers() > 0);
    assert_eq!(writer.matched_readers(), 1);
    // Two instances, two samples each: keep-last 1 per instance keeps the newest of each.
    for (id, v) in [(1, 10), (2, 20), (1, 11), (2, 21)] {
        writer
            .write(Sample::cdr(true, &keyed(id, v)))
            .expect("write");
    }
    let mut tokens = Vec::new();
    // Delivered inside the process on this thread (the loop's): the token is queued
    // without a byte through the socket pair, for the loop takes the queue after every
    // pass (listeners on Cyclone's threads write one: ffi's tests).
    assert!(
        !woken(dds.readiness_fd().as_raw_fd()),
        "no wake-up on the taking thread"
    );
    dds.ready_readers(&mut tokens).expect("ready");
    assert_eq!(tokens, vec![7], "the reader's data was queued once");
    let got = take(&mut dds, reader.as_mut(), 2);
    let bodies: Vec<_> = got.iter().map(|t| t.sample.body.to_vec()).collect();
    assert_eq!(bodies, vec![keyed(1, 11), keyed(2, 21)]);
    assert!(got.iter().all(|t| t.sample.encoding == Encoding::CDR_LE));
    assert!(got.iter().all(|t| !t.disposed && !t.unregistered));
    // Delivered inside the process: the writer's GUID and its own numbering of writes
    // (as Cyclone numbers them on the wire).
    let ids: Vec<_> = got.iter().map(|t| t.identity).collect();
    let guid = writer.guid();
    assert_eq!(
        ids,
        vec![
            SampleIdentity {
                writer: guid,
                sequence_number: 3
            },
            SampleIdentity {
                writer: guid,
                sequence_number: 4
            }
        ]
    );
    // What the worker records of its last write, to tell its readers' samples' origins.
    assert_eq!(writer.last_sequence_number(), Some(4));
    assert!(writer.all_acknowledged());
    assert_eq!(writer.writes(), 4);
    wait_until(|| writer.acknowledged_writes() >= 4);
    assert_eq!(
        writer.acknowledged_writes(),
        4,
        "counted by the acknowledgement thread"
    );
    writer
        .dispose(&Sample::cdr(true, &keyed(2, 0)))
        .expect("dispose");
    let got = take(&mut dds, reader.as_mut(), 1);
    assert_eq!(got.len(), 1);
    assert!(got[0].disposed, "{:?}", got[0]);
    assert_eq!(
        &got[0].sample.body[..4],
        &2i32.to_le_bytes(),
        "the key payload"
    );
    // A dispose of an instance whose sample is unread yet: Cyclone folds it into the
    // instance state; the reader still reports it, once, after the sample.
    writer
        .write(Sample::cdr(true, &keyed(1, 12)))
        .expect("write");
    writer
        .dispose(&Sample::cdr(true, &keyed(1, 0)))
        .expect("dispose");
    let got = take(&mut dds, reader.as_mut(), 2);
    assert_eq!(got.len(), 2, "{got:?}");
    assert!(!got[0].disposed && got[0].sample.body.to_vec() == keyed(1, 12));
    assert!(got[1].disposed && got[1].sample.body.to_vec() == 1i32.to_le_bytes());
    assert!(reader.take_next().expect("take").is_none(), "reported once");
    // A keyless topic of the same domain: its one instance (key hash zero) is not the
    // keyed topic's instance of key 0 (Cyclone's instance map is shared by the domain).
    let plain = TopicSpec {
        name: "cyclone_unit_plain".into(),
        type_name: "Plain".into(),
        key: None,
    };
    let plain_writer = dds
        .create_writer(&publisher, &plain, &wq, true)
        .expect("writer");
    plain_writer
        .write(Sample::cdr(true, &[9; 8]))
        .expect("write");
    writer
        .write(Sample::cdr(true, &keyed(0, 5)))
        .expect("write");
    // Taken before the dispose, so that Cyclone builds the dispose's invalid sample from
    // the instance it keeps for the key (the keyless topic's, were they merged).
    let got = take(&mut dds, reader.as_mut(), 1);
    assert_eq!(got.len(), 1, "{got:?}");
    writer
        .dispose(&Sample::cdr(true, &keyed(0, 0)))
        .expect("dispose");
    let got = take(&mut dds, reader.as_mut(), 1);
    assert_eq!(got.len(), 1, "{got:?}");
    assert!(got[0].disposed && got[0].sample.body.to_vec() == 0i32.to_le_bytes());
    // Disposed and written again before the reader looks: the disposal is reported
    // before the sample that revived the instance.
    writer
        .write(Sample::cdr(true, &keyed(7, 1)))
        .expect("write");
    assert_eq!(take(&mut dds, reader.as_mut(), 1).len(), 1);
    writer
        .dispose(&Sample::cdr(true, &keyed(7, 0)))
        .expect("dispose");
    writer
        .write(Sample::cdr(true, &keyed(7, 2)))
        .expect("write");
    let got = take(&mut dds, reader.as_mut(), 2);
    assert_eq!(got.len(), 2, "{got:?}");
    assert!(got[0].disposed && got[0].sample.body.to_vec() == 7i32.to_le_bytes());
    assert!(!got[1].disposed && got[1].sample.body.to_vec() == keyed(7, 2));
    assert!(writer
        .write_identified(Sample::cdr(true, &[0; 8]), None)
        .is_err());
    drop(reader);
    wait_until(|| writer.matched_readers() == 0);
    assert_eq!(writer.matched_readers(), 0, "the reader was deleted");
}

#[test]
fn loopback_configuration_discovers_by_unicast_and_others_keep_multicast() {
    let none = config_xml(&[], None, None).expect("valid");
    assert!(
        none.contains("HeartbeatInterval") && !none.contains("Interfaces"),
        "{none}"
    );
    let lo = config_xml(&[addr("127.0.0.1")], None, None).expect("valid");
    assert!(
        lo.contains("<NetworkInterface address=\"127.0.0.1\"/>"),
        "{lo}"
    );
    assert!(
        lo.contains("<AllowMulticast>false</AllowMulticast>"),
        "{lo}"
    );
    assert!(lo.contains("<Peer address=\"127.0.0.1\"/>"), "{lo}");
    let v6 = config_xml(&[addr("::1")], None, None).expect("valid");
    assert!(
        v6.contains("<Transport>udp6</Transport>") && v6.contains("[::1]"),
        "{v6}"
    );
    let lan = config_xml(&[addr("192.0.2.7")], None, None).expect("valid");
    assert!(
        !lan.contains("AllowMulticast") && !lan.contains("<Peers>"),
        "{lan}"
    );
    assert!(config_xml(&[addr("127.0.0.1"), addr("::1")], None, None).is_err());
    // The user's file first, so that the agent's settings and --dds-interface win.
    let with_uri = config_xml(&[], Some("file:///etc/cyclone.xml"), None).expect("valid");
    assert!(
        with_uri.starts_with("file:///etc/cyclone.xml,<CycloneDDS>"),
        "{with_uri}"
    );
}

#[test]
fn a_taken_user_multicast_port_moves_to_the_spare_offset_in_one_discovery_element() {
    let lan = config_xml(&[], None, Some(2)).expect("valid");
    assert!(
        lan.contains(
            "<Discovery><Ports><MulticastDataOffset>2</MulticastDataOffset></Ports>\
                 </Discovery>"
        ),
        "{lan}"
    );
    let lo = config_xml(&[addr("127.0.0.1")], None, Some(3)).expect("valid");
    assert_eq!(lo.matches("<Discovery>").count(), 1, "{lo}");
    assert!(
        lo.contains("<MulticastDataOffset>3</MulticastDataOffset>")
            && lo.contains("<Peer address=\"127.0.0.1\"/>"),
        "{lo}"
    );
    assert!(!config_xml(&[], None, None)
        .expect("valid")
        .contains("Discovery"));
}

#[test]
fn a_front_ends_free_port_is_not_taken_by_the_participant() {
    // Domain 98 on loopback: participant index 0 would listen on 31910 and 31911.
    let (disc, data) = (
        ports::port_at(98, ports::D1).expect("port"),
        ports::port_at(98, ports::D3).expect("port"),
    );
    let mut dds = loopback();
    dds.reserve_ports(ports::ReservedPorts::new([disc, data]));
    let _publisher = dds.create_publisher(98, &[]).expect("publisher");
    for p in [disc, data] {
        assert!(
            std::net::UdpSocket::bind(("0.0.0.0", p)).is_ok(),
            "Cyclone took port {p}, which a front-end serves"
        );
    }
}

#[test]
fn partitions_separate_writers_from_readers_of_other_partitions() {
    let mut dds = loopback();
    assert!(dds.supports_partitions());
    let spec = TopicSpec {
        name: "cyclone_unit_partitions".into(),
        type_name: "Plain".into(),
        key: None,
    };
    let wq = EndpointQos::resolve(
        EndpointSide::Writer,
        &QosDesc::default(),
        &QosDesc::default(),
    );
    let rq = EndpointQos::resolve(
        EndpointSide::Reader,
        &QosDesc::default(),
        &QosDesc::default(),
    );
    let a = ["robot_a".to_string()];
    let publisher = dds.create_publisher(90, &a).expect("publisher");
    let elsewhere = dds
        .create_subscriber(90, &["robot_b".to_string()])
        .expect("subscriber");
    let same = dds
        .create_subscriber(90, &["robot_*".to_string()])
        .expect("subscriber");
    let mut other = dds
        .create_reader(&elsewhere, &spec, &rq, 1)
        .expect("reader");
    let mut mine = dds.create_reader(&same, &spec, &rq, 2).expect("reader");
    let writer = dds
        .create_writer(&publisher, &spec, &wq, true)
        .expect("writer");
    wait_until(|| writer.matched_readers() > 0);
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(
        writer.matched_readers(),
        1,
        "only the reader of a matching partition"
    );
    writer
        .write(Sample::cdr(true, &[1, 2, 3, 4, 5]))
        .expect("write");
    let got = take(&mut dds, mine.as_mut(), 1);
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].sample.body.to_vec(), vec![1, 2, 3, 4, 5]);
    assert!(other.take_next().expect("take").is_none());
}

#[test]
fn a_dispose_after_more_samples_than_one_take_comes_after_the_last_of_them() {
    let mut dds = loopback();
    let spec = keyed_spec("cyclone_unit_batches");
    let all = QosDesc {
        reliability: Some(Reliability::Reliable),
        history: Some(History::KeepAll),
        ..QosDesc::default()
    };
    let wq = EndpointQos::resolve(EndpointSide::Writer, &all, &QosDesc::default());
    let rq = EndpointQos::resolve(EndpointSide::Reader, &all, &QosDesc::default());
    let publisher = dds.create_publisher(91, &[]).expect("publisher");
    let subscriber = dds.create_subscriber(91, &[]).expect("subscriber");
    let mut reader = dds
        .create_reader(&subscriber, &spec, &rq, 3)
        .expect("reader");
    let writer = dds
        .create_writer(&publisher, &spec, &wq, true)
        .expect("writer");
    wait_until(|| writer.matched_readers() > 0);
    let n = 2 * ffi::TAKE_BATCH as i32 + 5;
    for v in 0..n {
        writer
            .write(Sample::cdr(true, &keyed(v % 2, v)))
            .expect("write");
    }
    writer
        .dispose(&Sample::cdr(true, &keyed(0, 0)))
        .expect("dispose");
    writer
        .dispose(&Sample::cdr(true, &keyed(1, 0)))
        .expect("dispose");
    let got = take(&mut dds, reader.as_mut(), n as usize + 2);
    assert_eq!(got.len(), n as usize + 2);
    for id in [0, 1] {
        let of_id: Vec<_> = got
            .iter()
            .filter(|t| t.sample.body[..4] == i32::to_le_bytes(id))
            .collect();
        let disposes = of_id.iter().filter(|t| t.disposed).count();
        assert_eq!(disposes, 1, "key {id}: one dispose");
        assert!(
            of_id.last().is_some_and(|t| t.disposed),
            "key {id}: the dispose last"
        );
    }
    assert!(reader.take_next().expect("take").is_none());
}
