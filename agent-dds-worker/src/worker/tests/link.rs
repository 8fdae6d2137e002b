//! What the worker does with its link and its clock, in memory: the announcement, front-ends
//! whose process is gone, a congested front-end, and a replay that crashed the last worker.

use super::*;
use xrce_common::session::stream::InputPosition;

/// The incarnation of the front-end's process in these tests.
const INCARNATION: u16 = 4;

impl Harness {
    /// Hands the worker front-end FE's request, encoded as it comes from shared memory.
    fn send(&mut self, route: Route, request: Request<'_>) {
        let route = Route {
            incarnation: INCARNATION,
            ..route
        };
        let bytes = RequestMessage::new(route, request).encode();
        let now = self.worker.now;
        self.worker.handle_request(&bytes, now);
    }

    /// A pass at the worker's time.
    fn pass(&mut self) {
        let now = self.worker.now;
        self.worker.pass(now).expect("pass");
    }

    /// A replayed participant of `client` (as a front-end replays it to a new worker).
    fn replayed_participant(&mut self, client: ClientKey) {
        let description = variant(
            object_kind::PARTICIPANT,
            "<dds><participant><rtps><name>p</name></rtps></participant></dds>",
            VariantExtra::DomainId(3),
        );
        self.send(
            Route::object(FE, client, Default::default(), PARTICIPANT),
            Request::Create {
                description: description.into(),
                client_little_endian: true,
                replay: true,
                readers_matched: 0,
            },
        );
    }

    /// The statuses the front-end got since the last call: (client, status, implementation
    /// status).
    fn statuses(&mut self) -> Vec<(ClientKey, u8, u8)> {
        self.replies()
            .into_iter()
            .filter_map(|m| match m.reply {
                Reply::Status { result, .. } => Some((
                    m.route.client_key,
                    result.status,
                    result.implementation_status,
                )),
                _ => None,
            })
            .collect()
    }
}

#[test]
fn a_new_worker_announces_its_generation() {
    let t = Harness::new(false);
    let announced: Vec<ReplyMessage<'_>> = t
        .worker
        .link
        .announced()
        .iter()
        .map(|m| ReplyMessage::decode(m).expect("announcement"))
        .collect();
    assert_eq!(announced.len(), 1);
    assert_eq!(announced[0].reply, Reply::WorkerHello);
    assert_eq!(announced[0].route.generation, GENERATION);
}

/// A front-end whose process is gone keeps its clients' entities for the grace period (a
/// supervisor restarts it within it); one that comes back in time keeps them, one that does
/// not loses them, and its channel closes.
#[test]
fn a_gone_front_ends_entities_are_kept_for_the_grace_then_deleted() {
    let grace = Duration::from_secs(30);
    let mut t = Harness::with(|c| c.frontend_grace = grace);
    t.send(Route::frontend(FE), Request::FrontendHello);
    t.participant(CLIENT);
    // It was replaying another client when its process went.
    t.replayed_participant(OTHER);
    assert_eq!(t.worker.link.marks().get(&FE), Some(&OTHER));
    t.writer(CLIENT, WRITER, &writer_xml(TOPIC, "NO_KEY", "VOLATILE"))
        .expect("writer");
    let entities = t.worker.entities.len();

    t.worker.link.set_gone(FE, true);
    t.advance(CENSUS_PERIOD);
    t.pass();
    assert!(t.worker.frontends.orphaned.contains_key(&FE));
    assert!(
        t.worker.link.marks().is_empty(),
        "a replay from a front-end that is gone did not crash the worker"
    );
    t.advance(grace - CENSUS_PERIOD);
    t.pass();
    assert_eq!(t.worker.entities.len(), entities, "kept within the grace");

    // Back in time (restarted): nothing lost, nothing orphaned any more.
    t.worker.link.set_gone(FE, false);
    t.advance(CENSUS_PERIOD);
    t.pass();
    assert!(t.worker.frontends.orphaned.is_empty());
    assert_eq!(t.bus.writers_of(TOPIC), 1);

    // Gone for good: the grace counts from the census that found it gone again.
    t.worker.link.set_gone(FE, true);
    t.advance(CENSUS_PERIOD);
    t.pass();
    t.advance(grace - Duration::from_millis(1));
    t.pass();
    assert_eq!(t.worker.entities.len(), entities);
    t.advance(CENSUS_PERIOD);
    t.pass();
    assert!(t.worker.entities.is_empty());
    assert_eq!(t.bus.writers_of(TOPIC), 0);
    assert!(t.worker.link.forgotten(FE));
    assert!(!t.worker.frontends.ports.contains_key(&FE));
    assert_eq!(t.worker.dropped.get("frontend_gone"), Some(&1));
}

/// Replies a congested front-end's full queue refuses wait in the worker, and reach it in
/// order, before its progress, as it drains its queue; it is woken for them.
#[test]
fn a_congested_front_end_gets_every_reply_in_order_as_it_drains() {
    let mut t = Harness::over(config(), MemoryWorkerLink::bounded(2));
    for n in 0..5u8 {
        let route = Route::object(FE, CLIENT, xrce_common::wire::RequestId([0, n]), WRITER);
        t.worker.reply(
            route,
            Reply::Status {
                result: ResultStatus::new(status::OK),
                replay: false,
            },
        );
    }
    assert_eq!(t.worker.frontends.ports[&FE].backlog.len(), 3);
    let now = t.worker.now;
    assert_eq!(
        t.worker.poll_timeout(now),
        Some(Duration::from_millis(1)),
        "a congested front-end signals nothing when it drained: the worker looks again soon"
    );
    // Two at a time: the queue's capacity.
    let mut got = Vec::new();
    for _ in 0..3 {
        t.worker.flush();
        assert!(t.worker.link.take_wake(FE), "woken for what it got");
        got.extend(t.replies());
    }
    let order: Vec<Option<u8>> = got
        .iter()
        .map(|m| match m.reply {
            Reply::Status { .. } => Some(m.route.request_id.0[1]),
            _ => None,
        })
        .collect();
    assert_eq!(
        order,
        vec![Some(0), Some(1), Some(2), Some(3), Some(4), None]
    );
    assert!(matches!(got[5].reply, Reply::Progress { .. }));
    assert_eq!(t.worker.dropped.get("reply_backlog_overflow"), None);
    t.worker.flush();
    assert!(!t.worker.link.take_wake(FE), "nothing new");
    assert_eq!(t.worker.poll_timeout(now), None, "nothing to do");
}

/// A front-end whose reply channel cannot be opened loses its replies (counted), and the
/// worker does not keep looking at it; once it can be reached, replies get through.
#[test]
fn replies_to_a_front_end_that_cannot_be_reached_are_counted_and_ask_for_no_pass() {
    let mut t = Harness::new(false);
    t.worker.link.set_unreachable(FE, true);
    t.send(Route::frontend(FE), Request::FrontendHello);
    t.pass();
    assert_eq!(t.worker.dropped.get("reply_send_failed"), Some(&1));
    let now = t.worker.now;
    assert_eq!(t.worker.poll_timeout(now), None, "no pass asked for it");
    t.worker.link.set_unreachable(FE, false);
    t.send(Route::frontend(FE), Request::FrontendHello);
    t.pass();
    let got = t.replies();
    assert_eq!(got[0].reply, Reply::WorkerHello);
    assert!(matches!(got[1].reply, Reply::Progress { .. }));
}

/// A worker that stops of its own accord was not crashed by the replays under way: it
/// leaves no mark for the next one.
#[test]
fn a_worker_that_stops_leaves_no_replay_mark() {
    let mut t = Harness::new(false);
    t.send(Route::frontend(FE), Request::FrontendHello);
    t.replayed_participant(CLIENT);
    assert_eq!(t.worker.link.marks().get(&FE), Some(&CLIENT));
    t.worker.stop();
    assert!(t.worker.link.marks().is_empty());
    // The next worker replays the client as usual.
    let mut next = Harness::over(config(), t.worker.link.after_crash());
    next.send(Route::frontend(FE), Request::FrontendHello);
    next.replayed_participant(CLIENT);
    next.worker.flush();
    assert_eq!(next.statuses(), vec![(CLIENT, status::OK, 0)]);
}

/// The client whose replay was under way when two workers in a row died is refused by the
/// next one (its session ends, the client creates it again); the others are replayed. One
/// death is not enough: a worker killed from outside dies wherever its replay stands.
#[test]
fn a_replay_that_crashed_two_workers_is_refused_by_the_next_one() {
    let mut first = Harness::new(false);
    first.send(Route::frontend(FE), Request::FrontendHello);
    first.replayed_participant(CLIENT);
    first.replayed_participant(OTHER);
    assert_eq!(first.worker.link.marks().get(&FE), Some(&OTHER));
    // The worker dies while OTHER's objects are being replayed: the next one replays them.
    let replayed_by_the_next = |last: &Harness| {
        let mut next = Harness::over(config(), last.worker.link.after_crash());
        next.send(Route::frontend(FE), Request::FrontendHello);
        next.replayed_participant(CLIENT);
        next.replayed_participant(OTHER);
        next.worker.flush();
        next
    };
    let mut second = replayed_by_the_next(&first);
    assert_eq!(
        second.statuses(),
        vec![(CLIENT, status::OK, 0), (OTHER, status::OK, 0)]
    );
    assert_eq!(second.worker.dropped.get("replay_crash"), None);
    // It dies on OTHER too.
    let mut next = replayed_by_the_next(&second);
    assert_eq!(
        next.statuses(),
        vec![
            (CLIENT, status::OK, 0),
            (OTHER, status::ERR_RESOURCES, ipc::REPLAY_REFUSED),
        ]
    );
    assert_eq!(next.worker.dropped.get("replay_crash"), Some(&1));
    // The replay ends: no mark is left, and OTHER creates as usual again.
    next.send(Route::frontend(FE), Request::ReplayDone);
    assert!(next.worker.link.marks().is_empty());
    next.replayed_participant(OTHER);
    next.worker.flush();
    assert_eq!(next.statuses(), vec![(OTHER, status::OK, 0)]);
}

/// Operations a front-end sent before its hello reached this worker were meant for the one
/// that died: ignored (the front-end replays after its hello).
#[test]
fn operations_before_the_front_ends_hello_are_ignored() {
    let mut t = Harness::new(false);
    t.replayed_participant(CLIENT);
    assert!(t.worker.entities.is_empty());
    assert_eq!(t.worker.dropped.get("operation_before_hello"), Some(&1));
    t.send(Route::frontend(FE), Request::FrontendHello);
    t.replayed_participant(CLIENT);
    assert_eq!(t.worker.entities.len(), 1);
}

/// A write of `client` on stream `stream` at message `sequence`, write `index` of it (a
/// writer that does not exist: the position counts all the same).
fn positioned_write(stream: u8, sequence: u16, index: u16) -> Request<'static> {
    Request::Write {
        data: keyed(1, 1).into(),
        data_format: xrce_common::wire::data_format::DATA,
        little_endian: true,
        dialect: Dialect::Eprosima,
        status_requested: false,
        position: Some(InputPosition {
            epoch: 1,
            stream_id: stream,
            sequence,
            write_index: index,
        }),
        received_us: 0,
        resend_of: None,
    }
}

/// A process that takes a front-end over is told, before the answer to its hello, the last
/// write the worker executed on each reliable stream of each client of its predecessor;
/// not those of a client whose session ended, nor anything of best-effort streams.
#[test]
fn a_successor_is_told_the_last_write_executed_on_each_clients_reliable_stream() {
    let mut t = Harness::new(false);
    t.send(Route::frontend(FE), Request::FrontendHello);
    let to = |client| Route::object(FE, client, Default::default(), WRITER);
    t.send(to(CLIENT), positioned_write(0x80, 7, 0));
    t.send(to(CLIENT), positioned_write(0x80, 7, 1));
    t.send(to(CLIENT), positioned_write(0x81, 2, 0));
    t.send(to(CLIENT), positioned_write(0x01, 9, 0));
    t.send(to(OTHER), positioned_write(0x80, 3, 0));
    t.send(to(OTHER), Request::DeleteClient);
    t.pass();
    let _ = t.replies();

    let successor = Route {
        incarnation: INCARNATION + 1,
        ..Route::frontend(FE)
    };
    let hello = RequestMessage::new(successor, Request::FrontendHello).encode();
    let now = t.worker.now;
    t.worker.handle_request(&hello, now);
    t.pass();
    let replies = t.replies();
    let hello = replies
        .iter()
        .position(|m| m.reply == Reply::WorkerHello)
        .expect("the answer to the hello");
    let mut executed: Vec<_> = replies[..hello]
        .iter()
        .map(|m| {
            assert_eq!(m.route.incarnation, INCARNATION + 1);
            match m.reply {
                Reply::Executed(p) => (m.route.client_key, p.stream_id, p.sequence, p.write_index),
                ref r => panic!("{r:?} before the hello"),
            }
        })
        .collect();
    executed.sort_unstable();
    assert_eq!(executed, [(CLIENT, 0x80, 7, 1), (CLIENT, 0x81, 2, 0)]);
}

/// A client whose objects the successor's replay did not take back (its session was not
/// taken over) has no session here any more: its positions go with its entities, and the
/// next process of the front-end is not told them.
#[test]
fn a_client_the_replay_did_not_take_back_loses_its_positions() {
    let mut t = Harness::new(false);
    t.send(Route::frontend(FE), Request::FrontendHello);
    t.participant(CLIENT);
    let to = Route::object(FE, CLIENT, Default::default(), WRITER);
    t.send(to, positioned_write(0x80, 7, 0));
    t.pass();
    let hello = |t: &mut Harness, incarnation: u16| {
        let route = Route {
            incarnation,
            ..Route::frontend(FE)
        };
        let now = t.worker.now;
        let bytes = RequestMessage::new(route, Request::FrontendHello).encode();
        t.worker.handle_request(&bytes, now);
        t.pass();
        t.replies()
            .into_iter()
            .filter(|m| matches!(m.reply, Reply::Executed(_)))
            .count()
    };
    assert_eq!(hello(&mut t, INCARNATION + 1), 1);
    // The successor's replay ends without the client's participant.
    let done = Route {
        incarnation: INCARNATION + 1,
        ..Route::frontend(FE)
    };
    let now = t.worker.now;
    t.worker.handle_request(
        &RequestMessage::new(done, Request::ReplayDone).encode(),
        now,
    );
    t.pass();
    assert!(t.worker.entities.is_empty(), "its entities removed");
    assert_eq!(hello(&mut t, INCARNATION + 2), 0);
}
