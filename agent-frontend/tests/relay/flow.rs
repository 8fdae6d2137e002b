//! How writes share the window: best-effort floods and stalls, writes that wait for an
//! object, overflows, a quiet client beside a flooding one, progress that may wait.

use super::*;

/// Best-effort writes that go to the worker at once, in hand-over mode.
fn best_effort_share() -> u64 {
    use xrce_frontend::relay::{BEST_EFFORT_RESERVE, HAND_OVER_HEADROOM};
    use xrce_ipc::IN_FLIGHT_WINDOW;
    IN_FLIGHT_WINDOW - HAND_OVER_HEADROOM - BEST_EFFORT_RESERVE
}

/// Sends `n` best-effort writes of `w` (`{tag} {i}`) from the rig's client at `now`.
fn best_effort_writes(rig: &mut Rig, now: Instant, w: ObjectId, tag: &str, n: u64) {
    for i in 0..n {
        rig.client
            .write(
                now,
                stream_id::BUILTIN_BEST_EFFORT,
                w,
                format!("{tag} {i}").as_bytes(),
            )
            .expect("write");
        rig.deliver(now);
    }
    rig.relay.pump();
}

#[test]
fn a_best_effort_flood_leaves_room_for_reliable_writes() {
    use xrce_frontend::relay::BEST_EFFORT_WAITING_MAX;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(5);
    // A worker that takes nothing for a while: best-effort writes fill what they may of
    // the window, a few wait for it, and the rest are dropped, counted.
    let now = Instant::now();
    let share = best_effort_share();
    let waiting = BEST_EFFORT_WAITING_MAX as u64;
    best_effort_writes(&mut rig, now, w, "flood", share + waiting + 100);
    assert_eq!(
        rig.relay.stats().ops_dropped,
        100,
        "the flood beyond the window's share and the waiting queue"
    );
    assert_eq!(rig.relay.backlog(), BEST_EFFORT_WAITING_MAX);
    // A reliable write is still taken at once, ahead of the waiting best-effort writes.
    rig.client
        .write(now, stream_id::BUILTIN_RELIABLE, w, b"urgent")
        .expect("write");
    rig.deliver(now);
    rig.relay.pump();
    let writes = write_bodies(&worker.serve(&mut rig));
    let flood = writes.iter().filter(|b| b.starts_with("flood")).count() as u64;
    assert_eq!(flood, share, "best-effort writes in flight");
    assert!(
        writes.iter().any(|b| b.ends_with("urgent")),
        "the reliable write was refused behind the flood ({flood} best-effort writes in flight)"
    );
    drop((rig, worker));
}

#[test]
fn best_effort_writes_wait_out_a_short_worker_stall_in_order() {
    let (worker, mut rig, w) = Rig::handing_over_with_writer(7);
    // The worker stalls while more best-effort writes come than the window's share holds.
    let n = best_effort_share() + 100;
    best_effort_writes(&mut rig, Instant::now(), w, "be", n);
    assert_eq!(rig.relay.stats().ops_dropped, 0, "nothing is dropped");
    assert_eq!(rig.relay.backlog(), 100, "the writes beyond the share wait");
    // It catches up: every write reaches it, once, in the order sent.
    let served = rig.serve_until(&worker, |_, s| write_bodies(s).len() as u64 >= n);
    let got: Vec<String> = write_bodies(&served)
        .iter()
        .map(|b| b[b.find("be ").expect("a write of this test")..].to_string())
        .collect();
    let expected: Vec<String> = (0..n).map(|i| format!("be {i}")).collect();
    assert_eq!(got, expected);
    assert_eq!(rig.relay.backlog(), 0);
    drop((rig, worker));
}

#[test]
fn waiting_writes_of_a_deleted_writer_are_dropped_not_sent_after_the_delete() {
    let (worker, mut rig, w) = Rig::handing_over_with_writer(9);
    let share = best_effort_share();
    best_effort_writes(&mut rig, Instant::now(), w, "be", share + 10);
    assert_eq!(rig.relay.backlog(), 10);
    // The client deletes the writer while ten of its writes wait: the delete goes to the
    // worker now, the ten are dropped (they would reach no writer, or a new one with the id).
    rig.client.delete(Instant::now(), w).expect("delete");
    rig.deliver(Instant::now());
    assert_eq!(rig.relay.backlog(), 0);
    assert_eq!(rig.relay.stats().ops_dropped, 10);
    let is_delete = |m: &Served| is(m, "Delete");
    let mut served = rig.serve_until(&worker, |_, s| s.iter().any(is_delete));
    let delete = served
        .iter()
        .position(is_delete)
        .expect("the delete reached the worker");
    served.extend(worker.serve(&mut rig));
    assert!(
        served[delete..].iter().all(|m| !is(m, "Write")),
        "a write reached the worker after the delete of its writer"
    );
    assert_eq!(write_bodies(&served).len() as u64, share);
    drop((rig, worker));
}

#[test]
fn waiting_writes_to_an_id_are_dropped_when_it_is_created() {
    let (worker, mut rig, w) = Rig::handing_over_with_writer(13);
    best_effort_writes(&mut rig, Instant::now(), w, "be", best_effort_share() + 10);
    // Five writes to a writer the client has not created yet wait behind the ten.
    let early = ObjectId::new(2, k::DATAWRITER);
    best_effort_writes(&mut rig, Instant::now(), early, "early", 5);
    assert_eq!(rig.relay.backlog(), 15);
    // Its CREATE goes to the worker now: the five must not reach the new writer after it.
    rig.create(
        early,
        k::DATAWRITER,
        "<dds/>",
        VariantExtra::Parent(ObjectId::new(1, k::PUBLISHER)),
    );
    rig.deliver(Instant::now());
    assert_eq!(
        rig.relay.backlog(),
        10,
        "only the writes to the new id are dropped"
    );
    assert_eq!(rig.relay.stats().ops_dropped, 5);
    drop((rig, worker));
}

#[test]
fn waiting_writes_are_dropped_when_their_worker_is_replaced() {
    let (first, mut rig, w) = Rig::handing_over_with_writer(10);
    best_effort_writes(&mut rig, Instant::now(), w, "be", best_effort_share() + 10);
    assert_eq!(rig.relay.backlog(), 10);
    // The worker dies with the window full; its successor gets the replay, not stale data.
    drop(first);
    let second = FakeWorker::start(30);
    let replay = rig.run(&[&second], |_, s| s.iter().any(|m| is(m, "ReplayDone")));
    assert!(
        write_bodies(&replay).is_empty(),
        "stale best-effort writes replayed"
    );
    assert_eq!(rig.relay.backlog(), 0);
    assert_eq!(rig.relay.stats().ops_dropped, 10);
    drop((rig, second));
}

/// Overflows the best-effort wait of a relay whose shedding lasts `hold`, lets the worker
/// catch up, then sends ten writes more than the window's share: how many of those wait.
fn waiting_after_an_overflow(generation: u32, hold: Duration) -> usize {
    use xrce_frontend::relay::BEST_EFFORT_WAITING_MAX;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(generation);
    rig.relay.set_best_effort_shed_hold(hold);
    let share = best_effort_share();
    let waiting = BEST_EFFORT_WAITING_MAX as u64;
    best_effort_writes(&mut rig, Instant::now(), w, "flood", share + waiting + 1);
    assert_eq!(rig.relay.stats().ops_dropped, 1);
    assert_eq!(rig.relay.stats().best_effort_sheds, 1);
    rig.catch_up(&worker);
    best_effort_writes(&mut rig, Instant::now(), w, "after", share + 10);
    let queued = rig.relay.backlog();
    assert_eq!(
        rig.relay.stats().ops_dropped,
        1 + 10 - queued as u64,
        "what does not wait is dropped"
    );
    drop((rig, worker));
    queued
}

#[test]
fn after_an_overflow_best_effort_writes_are_shed_not_queued_until_the_hold_ends() {
    // Within the hold (an hour: no machine is that slow), nothing beyond the share waits.
    assert_eq!(waiting_after_an_overflow(8, Duration::from_secs(3600)), 0);
    // A hold that has ended (none at all) queues again.
    assert_eq!(waiting_after_an_overflow(14, Duration::ZERO), 10);
}

/// Datagrams between a second client (at `addr`) and the rig's session core, and the rig's
/// IPC, once (the rig's own client gets what is meant for it).
fn exchange_with(rig: &mut Rig, worker: &FakeWorker, other: &mut Client, addr: u32) {
    let now = Instant::now();
    while let Some(d) = other.poll_transmit() {
        rig.agent.handle_datagram(now, addr, &d, &mut rig.relay);
    }
    rig.relay.pump();
    worker.serve(rig);
    rig.poll_ipc(now, &[worker]);
    rig.agent.handle_timeout(now, &mut rig.relay);
    while let Some(t) = rig.agent.poll_transmit() {
        if t.destination == addr {
            other.handle_datagram(now, &t.data);
        } else {
            rig.client.handle_datagram(now, &t.data);
        }
    }
}

#[test]
fn a_quiet_clients_best_effort_writes_wait_while_a_flooding_client_is_shed() {
    use xrce_frontend::relay::BEST_EFFORT_WAITING_MAX;
    const QUIET: u32 = 8;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(16);
    rig.relay
        .set_best_effort_shed_hold(Duration::from_secs(3600));
    let mut quiet = Client::new(ClientConfig::new(ClientKey([0xC3, 0, 0, 2])));
    quiet.connect(Instant::now());
    let end = Instant::now() + Duration::from_secs(10);
    while !quiet.is_connected() {
        assert!(Instant::now() < end, "the second client did not connect");
        exchange_with(&mut rig, &worker, &mut quiet, QUIET);
    }
    // The worker stalls; the rig's client floods it: the window's share goes, the wait
    // fills, and the write that overflows it is dropped and starts the flooder's hold.
    let share = best_effort_share();
    let waiting = BEST_EFFORT_WAITING_MAX as u64;
    best_effort_writes(&mut rig, Instant::now(), w, "flood", share + waiting + 1);
    assert_eq!(rig.relay.stats().ops_dropped, 1);
    assert_eq!(rig.relay.stats().best_effort_sheds, 1);
    // The quiet client's writes still wait, each in place of the flood's newest, and the
    // flooder's further writes are dropped.
    let now = Instant::now();
    for i in 0..10 {
        quiet
            .write(
                now,
                stream_id::BUILTIN_BEST_EFFORT,
                w,
                format!("quiet {i}").as_bytes(),
            )
            .expect("write");
    }
    while let Some(d) = quiet.poll_transmit() {
        rig.agent.handle_datagram(now, QUIET, &d, &mut rig.relay);
    }
    best_effort_writes(&mut rig, now, w, "late", 5);
    assert_eq!(rig.relay.backlog(), BEST_EFFORT_WAITING_MAX);
    assert_eq!(rig.relay.stats().ops_dropped, 1 + 10 + 5);
    assert_eq!(rig.relay.stats().best_effort_sheds, 1);
    // When the worker catches up, the two take turns: the quiet client's writes arrive
    // among the first waiting ones, in order, not behind the flood's backlog.
    let served = rig.serve_until(&worker, |_, s| {
        write_bodies(s).len() as u64 >= share + waiting
    });
    let bodies = write_bodies(&served);
    let quiet_at: Vec<usize> = (0..10)
        .map(|i| {
            let tag = format!("quiet {i}");
            bodies
                .iter()
                .position(|b| b.ends_with(&tag))
                .unwrap_or_else(|| panic!("{tag} did not reach the worker"))
        })
        .collect();
    assert!(
        quiet_at.windows(2).all(|p| p[0] < p[1]),
        "out of order: {quiet_at:?}"
    );
    assert!(
        quiet_at[9] < (share + 20) as usize,
        "the quiet client waited behind the flood: {quiet_at:?}"
    );
    // The flood kept its oldest writes, in order; its newest ten made the room.
    let flood: Vec<u64> = bodies
        .iter()
        .filter_map(|b| b.find("flood ").map(|at| &b[at + 6..]))
        .map(|n| n.parse().expect("a flood write's number"))
        .collect();
    let expected: Vec<u64> = (0..share + waiting - 10).collect();
    assert_eq!(flood, expected);
    assert!(!bodies.iter().any(|b| b.contains("late ")));
    drop((rig, worker));
}

#[test]
fn small_reliable_messages_may_fill_the_window() {
    use xrce_frontend::relay::HAND_OVER_HEADROOM;
    use xrce_ipc::IN_FLIGHT_WINDOW;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(6);
    // The worker takes nothing meanwhile; each message carries one WRITE_DATA, so each
    // needs room for one operation, not for the largest message.
    let mut now = Instant::now();
    for i in 0..IN_FLIGHT_WINDOW + 40 {
        let _ = rig.client.write(
            now,
            stream_id::BUILTIN_RELIABLE,
            w,
            format!("r{i}").as_bytes(),
        );
        for _ in 0..4 {
            rig.deliver(now);
            rig.relay.pump();
            rig.agent.handle_timeout(now, &mut rig.relay);
            while let Some(t) = rig.agent.poll_transmit() {
                rig.client.handle_datagram(now, &t.data);
            }
            now += Duration::from_millis(60);
            rig.client.handle_timeout(now);
        }
    }
    let writes = worker
        .serve(&mut rig)
        .iter()
        .filter(|m| is(m, "Write"))
        .count() as u64;
    // Room for two operations a submessage is asked for: all but the last slot fill (the
    // room for the largest message would have stopped them at 145).
    assert!(
        (IN_FLIGHT_WINDOW - 2..=IN_FLIGHT_WINDOW).contains(&writes),
        "{writes} writes in flight (the largest message needs {HAND_OVER_HEADROOM})"
    );
    drop((rig, worker));
}

/// A best-effort write tells the worker its progress can wait only while most of the window
/// is free; reliable writes and control operations never do.
#[test]
fn only_best_effort_writes_with_the_window_mostly_free_let_their_progress_wait() {
    use xrce_frontend::relay::PROGRESS_CAN_WAIT_BELOW;
    let (worker, mut rig, w) = Rig::handing_over_with_writer(8);
    rig.catch_up(&worker);
    let can_wait = |m: &Served| m.progress_can_wait;
    // With the window free: a CREATE (its client waits for the STATUS) and a reliable write
    // (retained until executed) wait for their progress.
    let r = ObjectId::new(2, k::DATAWRITER);
    rig.create(
        r,
        k::DATAWRITER,
        "<dds/>",
        VariantExtra::Parent(ObjectId::new(1, k::PUBLISHER)),
    );
    rig.deliver(Instant::now());
    let served = rig.serve_until(&worker, |_, s| s.iter().any(|m| is(m, "Create")));
    assert!(!served.iter().any(can_wait));
    rig.catch_up(&worker);
    reliable_write(&mut rig, w, b"reliable");
    let served = worker.serve(&mut rig);
    assert_eq!(served.len(), 1);
    assert!(!can_wait(&served[0]), "a reliable write");
    rig.catch_up(&worker);
    // The worker takes nothing meanwhile: the window fills one write at a time.
    let n = PROGRESS_CAN_WAIT_BELOW + 10;
    best_effort_writes(&mut rig, Instant::now(), w, "be", n);
    reliable_write(&mut rig, w, b"reliable");
    let served = worker.serve(&mut rig);
    let writes: Vec<&Served> = served.iter().filter(|m| is(m, "Write")).collect();
    assert_eq!(writes.len() as u64, n + 1);
    let flagged: Vec<bool> = writes.iter().map(|m| can_wait(m)).collect();
    let mut expected = vec![true; PROGRESS_CAN_WAIT_BELOW as usize];
    expected.resize(n as usize + 1, false);
    assert_eq!(
        flagged, expected,
        "flagged while fewer than {PROGRESS_CAN_WAIT_BELOW} were in flight"
    );
    drop((rig, worker));
}
