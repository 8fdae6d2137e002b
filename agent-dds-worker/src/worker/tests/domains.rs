//! Bounds on DDS domains: participants released, caps, allowed lists, replay.

use super::*;

/// A participant object of `client` in `domain`, named `name`.
fn participant_in(domain: i16, name: &str) -> Vec<u8> {
    variant(
        object_kind::PARTICIPANT,
        &format!("<dds><participant><rtps><name>{name}</name></rtps></participant></dds>"),
        VariantExtra::DomainId(domain),
    )
}

impl Harness {
    /// A participant of `client` in `domain` with a publisher and a writer of `topic`.
    fn publisher_in(&mut self, client: ClientKey, domain: i16, topic: &str) {
        self.create(client, PARTICIPANT, &participant_in(domain, "talker"))
            .expect("participant");
        let g = variant(
            object_kind::PUBLISHER,
            "",
            VariantExtra::Parent(PARTICIPANT),
        );
        self.create(client, PUBLISHER, &g).expect("publisher");
        self.writer(client, WRITER, &writer_xml(topic, "NO_KEY", "VOLATILE"))
            .expect("writer");
    }

    /// The backend's domains with a participant now.
    fn backend_domains(&self) -> Vec<u16> {
        self.worker.dds.participant_domains()
    }
}

fn client(n: u8) -> ClientKey {
    ClientKey([0xd0, 0, 0, n])
}

/// The DDS participant of a domain goes when the last XRCE participant in it is deleted
/// (and not before): its threads and sockets go back. The ROS graph writer it had goes too.
#[test]
fn the_last_participant_of_a_domain_releases_the_domains_dds_participant() {
    let mut t = Harness::with(|c| c.ros_graph = true);
    // Two clients in domain 5, one in domain 6; ROS nodes (an rt/ topic), so the graph
    // writer of domain 5 exists too.
    t.publisher_in(CLIENT, 5, "rt/chatter");
    t.publisher_in(OTHER, 5, "rt/chatter");
    t.publisher_in(client(9), 6, "rt/other");
    t.advance(crate::ros_graph::REFRESH);
    t.worker.publish_graph();
    assert_eq!(t.bus.writers_of("ros_discovery_info"), 2, "one per domain");
    assert_eq!(t.backend_domains(), vec![5, 6]);

    t.worker.remove_where(|c| c.1 == CLIENT);
    assert_eq!(t.backend_domains(), vec![5, 6], "domain 5 still has a user");
    assert!(t.bus.released.borrow().is_empty());

    // The last user of domain 5 deletes its participant (a DELETE of the object).
    t.worker.frontends.greeted.insert((FE, 0));
    t.worker.process_request(RequestMessage::new(
        Route::object(FE, OTHER, Default::default(), PARTICIPANT),
        Request::Delete,
    ));
    assert_eq!(t.backend_domains(), vec![6], "no participant for domain 5");
    assert_eq!(t.bus.released.borrow().as_slice(), &[5]);
    assert_eq!(
        t.bus.endpoints_in(5),
        0,
        "nothing of the worker is left in domain 5 (graph writer included)"
    );
    assert_eq!(t.worker.domains.in_use().collect::<Vec<_>>(), vec![6]);
    // The graph of domain 5 is not published again (no writer, no node).
    t.advance(crate::ros_graph::REFRESH);
    t.worker.publish_graph();
    assert_eq!(t.backend_domains(), vec![6]);

    // Used again, the domain gets a new participant.
    t.publisher_in(CLIENT, 5, "rt/chatter");
    assert_eq!(t.backend_domains(), vec![5, 6]);
    t.worker.remove_where(|_| true);
    assert!(t.backend_domains().is_empty());
    let mut released = t.bus.released.borrow().clone();
    released.sort_unstable();
    assert_eq!(released, vec![5, 5, 6]);
    assert!(t.worker.domains.in_use().next().is_none());
}

/// By default at most 8 distinct domains are in use at once: a 9th is refused with
/// STATUS_ERR_RESOURCES and counted, a domain in use still takes participants, and a domain
/// released makes room.
#[test]
fn a_ninth_distinct_domain_is_refused_for_resources_until_one_is_released() {
    let mut t = Harness::new(false);
    for d in 0..8u8 {
        t.publisher_in(client(d), i16::from(d) + 10, "T");
    }
    let refused = t
        .create(client(8), PARTICIPANT, &participant_in(30, "p"))
        .expect_err("a 9th domain");
    assert_eq!(refused.status(), status::ERR_RESOURCES, "{}", refused);
    assert_eq!(t.worker.dropped.get("domains_refused"), Some(&1));
    assert!(!t
        .worker
        .entities
        .contains_key(&(FE, client(8), PARTICIPANT)));
    // Refused again: counted, and the episode's one log line is behind us.
    assert!(t
        .create(client(8), PARTICIPANT, &participant_in(31, "p"))
        .is_err());
    assert_eq!(t.worker.dropped.get("domains_refused"), Some(&2));
    // A domain in use takes more participants.
    t.create(client(8), PARTICIPANT, &participant_in(12, "p"))
        .expect("a domain in use");
    // Released, domain 10 makes room for domain 30.
    t.worker.remove_where(|c| c.1 == client(0));
    assert!(!t.backend_domains().contains(&10));
    t.create(client(9), PARTICIPANT, &participant_in(30, "p"))
        .expect("room again");
    assert_eq!(t.worker.domains.in_use().count(), 8);
}

/// With `--domains`, a domain outside the list is refused with STATUS_ERR_DENIED (and the
/// list replaces the default cap).
#[test]
fn a_domain_outside_the_allowed_list_is_denied() {
    let mut t = Harness::with(|c| {
        c.domains = DomainPolicy::from_options(Some("0-10,42".parse().expect("list")), None)
    });
    for d in (0..=10).chain([42]) {
        t.create(client(d as u8), PARTICIPANT, &participant_in(d, "p"))
            .expect("an allowed domain");
    }
    let refused = t
        .create(client(50), PARTICIPANT, &participant_in(11, "p"))
        .expect_err("not in the list");
    assert_eq!(refused.status(), status::ERR_DENIED, "{}", refused);
    assert_eq!(t.worker.dropped.get("domain_denied"), Some(&1));
    // The reply status is the refusal's.
    t.worker.frontends.greeted.insert((FE, 0));
    t.worker.process_request(RequestMessage::new(
        Route::object(FE, client(51), Default::default(), PARTICIPANT),
        Request::Create {
            description: participant_in(200, "p").into(),
            client_little_endian: true,
            replay: false,
            readers_matched: 0,
        },
    ));
    t.worker.flush();
    let statuses: Vec<u8> = t
        .replies()
        .into_iter()
        .filter_map(|m| match m.reply {
            Reply::Status { result, .. } => Some(result.status),
            _ => None,
        })
        .collect();
    assert_eq!(statuses, vec![status::ERR_DENIED]);
}

/// A restarted worker gets the object graphs replayed: the domains in use before (within the
/// cap, since the old worker kept to it) are all admitted again.
#[test]
fn a_replay_to_a_new_worker_recreates_every_domain_in_use() {
    let mut before = Harness::new(false);
    for d in 0..8u8 {
        before.publisher_in(client(d), i16::from(d), "T");
    }
    assert_eq!(before.backend_domains().len(), 8);
    let mut after = Harness::new(false);
    for d in 0..8u8 {
        for (id, body) in [
            (PARTICIPANT, participant_in(i16::from(d), "talker")),
            (
                PUBLISHER,
                variant(
                    object_kind::PUBLISHER,
                    "",
                    VariantExtra::Parent(PARTICIPANT),
                ),
            ),
            (
                WRITER,
                variant(
                    object_kind::DATAWRITER,
                    &writer_xml("T", "NO_KEY", "VOLATILE"),
                    VariantExtra::Parent(PUBLISHER),
                ),
            ),
        ] {
            after
                .worker
                .create((FE, client(d), id), &body, true, true, 0)
                .expect("replayed");
        }
    }
    assert_eq!(after.backend_domains(), before.backend_domains());
    assert_eq!(after.bus.writers_of("T"), 8);
}
