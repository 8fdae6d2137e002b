//! Progress reports to the front-end: which ones wake it and which can wait.

use super::*;
use crate::acks::ACK_POLL_PERIOD;

/// A little-endian WRITE_DATA of one bare sample.
fn write(sample: &[u8]) -> Request<'_> {
    Request::Write {
        data: sample.into(),
        data_format: xrce_common::wire::data_format::DATA,
        little_endian: true,
        dialect: Dialect::Eprosima,
        status_requested: false,
        position: None,
        received_us: 0,
        resend_of: None,
    }
}

impl Harness {
    /// Hands the worker a request of the front-end (its current process) and ends the pass.
    fn request(&mut self, request: Request<'_>, seq: u64, progress_can_wait: bool) {
        let route = Route {
            op_seq: seq,
            ..Route::object(FE, CLIENT, Default::default(), WRITER)
        };
        self.worker.process_request(RequestMessage {
            route,
            progress_can_wait,
            request,
        });
        self.worker.flush();
    }

    /// What the front-end was told executed since the last call (each progress message's
    /// first number), and whether it was woken for it.
    fn progress(&mut self) -> (Vec<u64>, bool) {
        let executed = self
            .replies()
            .into_iter()
            .filter_map(|m| match m.reply {
                Reply::Progress { executed, .. } => Some(executed),
                _ => None,
            })
            .collect();
        (executed, self.worker.link.take_wake(FE))
    }
}

/// Progress of an operation whose progress can wait goes out without waking the
/// front-end; progress that covers any other operation wakes it.
#[test]
fn progress_wakes_the_front_end_only_for_operations_that_wait_for_it() {
    let mut t = Harness::new(false);
    // Operations that need no reply (a pause of a read that is not there).
    t.request(Request::PauseRead, 1, true);
    assert_eq!(t.progress(), (vec![1], false));
    t.request(Request::PauseRead, 2, true);
    t.request(Request::PauseRead, 3, false);
    assert_eq!(t.progress(), (vec![2, 3], true));
    // Nothing new: no message, no wake-up.
    t.worker.flush();
    assert_eq!(t.progress(), (vec![], false));
    // A reply always wakes (a write to a writer that does not exist fails with a STATUS).
    t.request(write(&keyed(1, 1)), 4, true);
    assert_eq!(t.progress(), (vec![4], true));
}

/// A write the worker holds (its writer waits for its readers to match again) is not
/// executed yet: progress that stops short of it still owes the front-end a wake-up, paid
/// when the write is released; nothing is sent while nothing changes.
#[test]
fn progress_owed_for_a_held_write_wakes_when_the_write_is_executed() {
    let mut t = reader_and_new_writer();
    // No acknowledgement by DDS readers, which would wake the front-end by itself.
    t.bus.acknowledged.set(false);
    let _ = t.progress();
    t.request(write(&keyed(1, 1)), 10, false);
    assert!(t.bus.written.borrow().is_empty(), "held");
    assert_eq!(t.progress(), (vec![9], true));
    t.worker.flush();
    assert_eq!(t.progress(), (vec![], false), "nothing new while held");
    t.matched_long_ago(CLIENT, WRITER);
    assert_eq!(t.bus.samples_on(TOPIC), vec![keyed(1, 1)]);
    t.worker.flush();
    assert_eq!(t.progress(), (vec![10], true), "executed: the owed wake-up");
    t.worker.flush();
    assert_eq!(t.progress(), (vec![], false));
}

/// Held writes whose progress can wait: their progress goes out when they are released,
/// without a wake-up.
#[test]
fn progress_of_released_writes_that_can_wait_goes_out_without_a_wake_up() {
    let mut t = reader_and_new_writer();
    t.bus.acknowledged.set(false);
    let _ = t.progress();
    t.request(write(&keyed(1, 1)), 1, true);
    t.request(write(&keyed(2, 1)), 2, true);
    assert_eq!(t.progress(), (vec![0, 0], false), "both held");
    // The first held sample goes alone (the second waits for its acknowledgement).
    t.matched_long_ago(CLIENT, WRITER);
    assert_eq!(t.bus.samples_on(TOPIC), vec![keyed(1, 1)]);
    t.worker.flush();
    assert_eq!(t.progress(), (vec![1], false));
}

impl Harness {
    /// A pass `by` after the last; the newest `acknowledged` the front-end was told since
    /// the last call, and how many samples it got.
    fn acknowledged_after(&mut self, by: Duration) -> (Option<u64>, usize) {
        self.advance(by);
        let now = self.worker.now;
        self.worker.pass(now).expect("pass");
        let mut acknowledged = None;
        let mut samples = 0;
        for m in self.replies() {
            match m.reply {
                Reply::Progress {
                    acknowledged: a, ..
                } => acknowledged = Some(a),
                Reply::Sample(_) => samples += 1,
                _ => {}
            }
        }
        (acknowledged, samples)
    }
}

impl Harness {
    /// `passes` passes, each after more writes than a pump takes (numbered on from
    /// `written`, progress allowed to wait); the newest write acknowledged and the samples
    /// the front-end got.
    fn more_than_a_pump_each_pass(&mut self, written: u64, passes: usize) -> (u64, u64) {
        let mut seq = written;
        let mut acknowledged = written;
        let mut samples = 0;
        for _ in 0..passes {
            for _ in 0..crate::worker::reads::PUMP_BATCH + 44 {
                seq += 1;
                self.request(write(&keyed(seq as i32, 1)), seq, true);
            }
            let (a, n) = self.acknowledged_after(ACK_POLL_PERIOD);
            acknowledged = a.unwrap_or(acknowledged);
            samples += n as u64;
        }
        (acknowledged, samples)
    }
}

/// A client's reader with a read and a writer of one topic; its first write was taken for
/// the read and acknowledged.
fn first_write_taken() -> Harness {
    let mut t = reader_and_new_writer();
    t.read(CLIENT, READER);
    t.request(write(&keyed(1, 1)), 1, false);
    t.matched_long_ago(CLIENT, WRITER);
    assert_eq!(
        t.acknowledged_after(ACK_POLL_PERIOD),
        (Some(1), 1),
        "taken at once"
    );
    t
}

/// DDS counts a reader inside this worker as acknowledging at once, but its samples die
/// with the worker until they were taken for the client's read: a write is reported
/// acknowledged only once the worker's own readers of its topic were drained past it, so
/// the front-end keeps it for a new worker meanwhile.
#[test]
fn a_write_is_acknowledged_only_once_the_workers_own_readers_took_it() {
    let mut t = first_write_taken();
    t.pause_read(true);
    t.request(write(&keyed(2, 1)), 2, false);
    t.request(write(&keyed(3, 1)), 3, false);
    assert_eq!(t.bus.samples_on(TOPIC).len(), 3, "written to DDS");
    for _ in 0..3 {
        let (acknowledged, samples) = t.acknowledged_after(ACK_POLL_PERIOD);
        assert_eq!(acknowledged.unwrap_or(1), 1, "still in the paused reader");
        assert_eq!(samples, 0);
    }
    t.pause_read(false);
    assert_eq!(t.acknowledged_after(ACK_POLL_PERIOD), (Some(3), 2));
}

/// A reader with no read does not hold writes back: its samples may wait for a read that
/// never comes.
#[test]
fn a_reader_without_a_read_holds_no_acknowledgement_back() {
    let mut t = reader_and_new_writer();
    t.request(write(&keyed(1, 1)), 1, false);
    t.matched_long_ago(CLIENT, WRITER);
    t.request(write(&keyed(2, 1)), 2, false);
    assert_eq!(t.acknowledged_after(ACK_POLL_PERIOD).0, Some(2));
}

/// A reader the writes do not reach (another partition, incompatible QoS) is never named
/// ready: it holds no acknowledgement back once it was emptied.
#[test]
fn a_reader_the_writes_do_not_reach_holds_no_acknowledgement_back() {
    let mut t = first_write_taken();
    t.bus.unheard.set(true);
    t.request(write(&keyed(2, 1)), 2, false);
    assert_eq!(t.acknowledged_after(ACK_POLL_PERIOD), (Some(2), 0));
}

/// A paced read (its client asked for at most one sample so often) holds no acknowledgement
/// back: what waits in its reader is its client's choice.
#[test]
fn a_paced_read_holds_no_acknowledgement_back() {
    let mut t = reader_and_new_writer();
    t.read_paced(CLIENT, READER, 1000);
    t.request(write(&keyed(1, 1)), 1, false);
    t.matched_long_ago(CLIENT, WRITER);
    t.request(write(&keyed(2, 1)), 2, false);
    t.request(write(&keyed(3, 1)), 3, false);
    assert_eq!(t.acknowledged_after(ACK_POLL_PERIOD), (Some(3), 1));
}

/// A reader whose front-end's queue stays full is seldom seen empty with that queue empty
/// at once: its writes are acknowledged as what it took, when it emptied, reaches the queue,
/// not only after [`crate::acks::ACK_GIVE_UP`] (a worker dying meanwhile would have them
/// resent, and its subscribers get them twice).
#[test]
fn a_congested_readers_writes_are_acknowledged_as_its_backlog_is_sent() {
    // Three writes a round against a queue of four that also carries progress: each pass
    // leaves samples waiting in the worker.
    let mut t = reader_and_new_writer_over(Harness::over(config(), MemoryWorkerLink::bounded(4)));
    t.read(CLIENT, READER);
    t.request(write(&keyed(1, 1)), 1, false);
    t.matched_long_ago(CLIENT, WRITER);
    let mut seq = 1;
    let mut acknowledged = 0;
    let mut samples = 0;
    // For a tenth of the give-up time.
    for _ in 0..50 {
        for _ in 0..3 {
            seq += 1;
            t.request(write(&keyed(seq as i32, 1)), seq, false);
        }
        let (a, n) = t.acknowledged_after(ACK_POLL_PERIOD);
        assert!(
            !t.worker.frontends.ports[&FE].backlog.is_empty(),
            "congested throughout"
        );
        acknowledged = a.unwrap_or(acknowledged);
        samples += n;
    }
    assert!(samples >= 140, "the reader kept delivering: {samples}");
    // What was delivered, less the last pass's backlog.
    assert!(
        acknowledged + 6 >= samples as u64,
        "acknowledged through {acknowledged} of {seq} written, {samples} delivered"
    );
}

/// A reader that more comes to than a pump takes is never seen empty: taking in write order
/// (its topic has no key), what it took of the worker's writes is known all the same, and
/// those writes are acknowledged, not only after [`crate::acks::ACK_GIVE_UP`].
#[test]
fn writes_a_never_empty_reader_took_in_write_order_are_acknowledged() {
    let mut t = first_write_taken();
    let (acknowledged, samples) = t.more_than_a_pump_each_pass(1, 10);
    assert_eq!(
        samples,
        10 * crate::worker::reads::PUMP_BATCH as u64,
        "a pump's worth each pass: never emptied"
    );
    assert_eq!(
        acknowledged,
        1 + samples,
        "acknowledged through what was taken"
    );
}

/// A keyed topic's reader takes instance by instance, not in write order: what it took
/// tells nothing of the writes before, and they wait until it is seen empty.
#[test]
fn a_never_empty_keyed_reader_holds_its_writes_back() {
    let mut t = reader_and_new_writer_of(Harness::new(false), "WITH_KEY");
    t.read(CLIENT, READER);
    t.request(write(&keyed(1, 1)), 1, false);
    t.matched_long_ago(CLIENT, WRITER);
    assert_eq!(t.acknowledged_after(ACK_POLL_PERIOD), (Some(1), 1));
    let mut seq = 1;
    let mut acknowledged = 1;
    for _ in 0..3 {
        for _ in 0..crate::worker::reads::PUMP_BATCH + 44 {
            seq += 1;
            t.request(write(&keyed(seq as i32 % 7, 1)), seq, true);
        }
        acknowledged = t
            .acknowledged_after(ACK_POLL_PERIOD)
            .0
            .unwrap_or(acknowledged);
    }
    assert_eq!(acknowledged, 1, "never seen empty");
}

/// A new reader holds nothing: it is placed in the topic's take log from its creation, so a
/// replayed subscriber whose path lags (never seen empty after a worker restart) still has
/// what it took acknowledged.
#[test]
fn a_new_readers_takes_count_before_it_was_ever_seen_empty() {
    let mut t = reader_and_new_writer();
    t.read(CLIENT, READER);
    t.matched_long_ago(CLIENT, WRITER);
    let (acknowledged, samples) = t.more_than_a_pump_each_pass(0, 5);
    assert_eq!(
        samples,
        5 * crate::worker::reads::PUMP_BATCH as u64,
        "never emptied"
    );
    assert_eq!(acknowledged, samples);
}
