//! The link and the replies: requests the link refuses, replies of a predecessor or a dead
//! worker, creations a dead worker took, the settle time on the caller's clock.

use super::*;

/// The STATUS replies the rig's client got for `object`.
fn statuses_of(rig: &Rig, object: ObjectId) -> Vec<u8> {
    rig.events
        .iter()
        .filter_map(|e| match e {
            ClientEvent::Status(r) if r.related.object_id == object => Some(r.result.status),
            _ => None,
        })
        .collect()
}

/// Requests the link refuses (its shared memory failed) wait in the outbox, the relay asks to
/// be called again soon, and they go in order once the link works again.
#[test]
fn requests_the_link_refuses_wait_and_go_in_order_once_it_works() {
    let worker = FakeWorker::start(41);
    let mut rig = Rig::connected(&worker, 41);
    let [.., w] = rig.create_writer();
    rig.run(&[&worker], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 4
    });
    rig.relay.link_mut().fail(true);
    for i in 0..5 {
        reliable_write(&mut rig, w, format!("w{i}").as_bytes());
    }
    assert_eq!(rig.relay.backlog(), 5, "all five wait");
    // A retry is asked for, later after each refusal in a row, never later than the cap.
    let now = Instant::now();
    let mut waits = Vec::new();
    for _ in 0..12 {
        let wait = rig
            .relay
            .poll_timeout(now)
            .map(|t| t - now)
            .expect("a retry is asked for");
        waits.push(wait);
        rig.relay.pump();
    }
    assert!(waits.windows(2).all(|w| w[0] <= w[1]), "{waits:?}");
    assert!(waits[0] < waits[11], "{waits:?}");
    assert_eq!(waits[11], xrce_frontend::relay::LINK_RETRY_MAX, "{waits:?}");
    assert!(rig.relay.stats().link_refusals >= 12);
    assert_eq!(rig.relay.backlog(), 5, "nothing dropped while refused");
    let refusals_before_recovery = rig.relay.stats().link_refusals;
    rig.relay.link_mut().fail(false);
    let served = rig.run(&[&worker], |_, s| {
        s.iter().filter(|m| is(m, "Write")).count() >= 5
    });
    assert_eq!(write_bodies(&served), ["w0", "w1", "w2", "w3", "w4"]);
    assert_eq!(rig.relay.backlog(), 0);
    // Working again, the refusals start a new run: the next one is retried soon again
    // (its submission and the pass after it are two refusals: 2 ms), not after the cap.
    assert_eq!(rig.relay.stats().link_refusals, refusals_before_recovery);
    rig.relay.link_mut().fail(true);
    reliable_write(&mut rig, w, b"w5");
    let now = Instant::now();
    let wait = rig
        .relay
        .poll_timeout(now)
        .map(|t| t - now)
        .expect("a retry is asked for");
    assert!(
        wait <= 4 * xrce_frontend::relay::LINK_RETRY_MIN,
        "{wait:?} after {} refusals",
        rig.relay.stats().link_refusals - refusals_before_recovery
    );
}

/// A reply meant for the front-end process this one took over from, one from a worker
/// generation no longer served and bytes that are no message change nothing a client sees.
#[test]
fn replies_of_a_predecessor_a_dead_worker_or_no_worker_are_not_applied() {
    use xrce_common::wire::{status, RequestId, ResultStatus};
    let worker = FakeWorker::start(42);
    let mut rig = Rig::connected(&worker, 42);
    let w = ObjectId::new(1, k::DATAWRITER);
    let failed = |incarnation: u16, generation: u32| {
        let route = Route {
            incarnation,
            generation,
            op_seq: 1,
            ..Route::object(0, ClientKey([0xB2, 0, 0, 1]), RequestId([0, 1]), w)
        };
        let reply = Reply::Status {
            result: ResultStatus::new(status::ERR_DDS_ERROR),
            replay: false,
        };
        ReplyMessage::new(route, reply).encode()
    };
    let now = Instant::now();
    let before = rig.relay.stats().clone();
    rig.relay.handle_reply(now, &failed(9, 42), &mut rig.agent);
    rig.relay.handle_reply(now, &failed(1, 41), &mut rig.agent);
    rig.relay
        .handle_reply(now, b"not a message", &mut rig.agent);
    rig.relay.after_replies(now, &mut rig.agent);
    let after = rig.relay.stats();
    assert_eq!(after.predecessor_replies, before.predecessor_replies + 1);
    assert_eq!(after.ipc_dropped, before.ipc_dropped + 2);
    rig.run(&[&worker], |_, _| true);
    assert!(statuses_of(&rig, w).is_empty(), "{:?}", rig.events);
}

/// A worker that dies with CREATEs taken and not answered: its successor gets them again as
/// creations a client waits for (not as a replay), and the client gets one STATUS for each.
#[test]
fn creations_a_dead_worker_did_not_answer_are_answered_once_by_its_successor() {
    let first = FakeWorker::start(43);
    let mut rig = Rig::connected(&first, 43);
    let ids = rig.create_writer();
    let now = Instant::now();
    rig.deliver(now);
    rig.relay.pump();
    let taken = first.serve(&mut rig);
    assert_eq!(taken.iter().filter(|m| is(m, "Create")).count(), 4);
    // It dies with its answers.
    drop(first);
    let second = FakeWorker::start(44);
    let replay = rig.run(&[&second], |r, _| {
        ids.iter().all(|id| !statuses_of(r, *id).is_empty())
    });
    let creates: Vec<&Served> = replay.iter().filter(|m| is(m, "Create")).collect();
    assert_eq!(creates.len(), 4);
    assert!(
        !creates.iter().any(|m| replayed(m)),
        "the client waits for them"
    );
    // A while longer: nothing more comes.
    let end = Instant::now() + Duration::from_millis(200);
    rig.run(&[&second], |_, _| Instant::now() >= end);
    for id in ids {
        assert_eq!(statuses_of(&rig, id), [0], "{id:?}");
    }
}

/// Time is the caller's: an executed write no DDS reader acknowledges is released
/// [`SETTLE_TIME`] after the worker reported it executed, whatever the wall clock says, once
/// the worker was heard from after that; a worker silent since (it may have died before its
/// readers took the write) leaves it kept for a resend.
#[test]
fn an_unacknowledged_write_is_released_after_the_settle_time_once_the_worker_is_heard_from() {
    use xrce_frontend::relay::SETTLE_TIME;
    let worker = FakeWorker::start(45);
    let mut rig = Rig::connected(&worker, 45);
    let [.., w] = rig.create_writer();
    rig.run(&[&worker], |_, s| {
        s.iter().filter(|m| is(m, "Create")).count() == 4
    });
    let before = Instant::now();
    reliable_write(&mut rig, w, b"kept");
    let served = rig.run(&[&worker], |_, s| s.iter().any(|m| is(m, "Write")));
    let write = served
        .iter()
        .find(|m| is(m, "Write"))
        .expect("the write")
        .route;
    let executed = Instant::now();
    // No word from the worker since: kept, however late, and no timer waits for it.
    let late = executed + 10 * SETTLE_TIME;
    rig.relay.after_replies(late, &mut rig.agent);
    assert_eq!(rig.relay.stats().writes_settled_unacknowledged, 0);
    assert_eq!(rig.relay.poll_timeout(executed), None);
    // The worker reports progress (nothing acknowledged) before the settle time: kept.
    let progress = |last: u64| {
        let route = Route {
            op_seq: last,
            generation: 45,
            ..Route::default()
        };
        ReplyMessage::new(
            route,
            Reply::Progress {
                executed: last,
                acknowledged: 0,
            },
        )
        .encode()
    };
    let early = before + SETTLE_TIME - Duration::from_millis(1);
    rig.relay
        .handle_reply(early, &progress(write.op_seq), &mut rig.agent);
    rig.relay.after_replies(early, &mut rig.agent);
    assert_eq!(rig.relay.stats().writes_settled_unacknowledged, 0);
    // Heard from once the settle time passed: released.
    rig.relay
        .handle_reply(late, &progress(write.op_seq), &mut rig.agent);
    rig.relay.after_replies(late, &mut rig.agent);
    assert_eq!(rig.relay.stats().writes_settled_unacknowledged, 1);
    assert_eq!(rig.relay.poll_timeout(late), None);
}
