//! Origins: a sample this worker's writer wrote for a client carries the client write it
//! came from, so that a subscriber's front-end can tell a resent write it delivered.

use super::*;
use xrce_common::session::stream::InputPosition;

impl Harness {
    /// Hands the worker front-end operation `seq`, a write of `body` in `format` to the
    /// client's writer: on a reliable stream (it then has an origin) or a best-effort one,
    /// and a resend of operation `resend_of` if given.
    fn write_op(
        &mut self,
        seq: u64,
        format: u8,
        body: &[u8],
        reliable: bool,
        resend_of: Option<u64>,
    ) {
        let route = Route {
            op_seq: seq,
            incarnation: 5,
            ..Route::object(FE, CLIENT, Default::default(), WRITER)
        };
        let position = reliable.then_some(InputPosition {
            epoch: 1,
            stream_id: xrce_common::wire::stream_id::BUILTIN_RELIABLE,
            sequence: seq as u16,
            write_index: 0,
        });
        self.worker.process_request(RequestMessage {
            route,
            progress_can_wait: false,
            request: Request::Write {
                data: body.into(),
                data_format: format,
                little_endian: true,
                dialect: Dialect::Eprosima,
                status_requested: false,
                position,
                received_us: 0,
                resend_of,
            },
        });
        self.worker.flush();
    }

    /// The first bytes and origins of the samples the front-end got, in order.
    fn origins(&mut self) -> Vec<(u8, Option<ipc::SampleOrigin>)> {
        self.replies()
            .into_iter()
            .filter_map(|m| match m.reply {
                Reply::Sample(s) => Some((s.data[0], s.origin)),
                _ => None,
            })
            .collect()
    }
}

#[test]
fn samples_of_reliable_writes_carry_their_write_and_index_and_a_resend_its_first_number() {
    let mut t = reader_and_new_writer_of(Harness::new(false), "WITH_KEY");
    t.read(CLIENT, READER);
    use xrce_common::wire::data_format::{DATA, DATA_SEQ};
    // Operation 1: two samples in one WRITE_DATA; 2: best-effort (never resent: no
    // origin); 3: a reliable write this process first sent as operation 2 to a worker that
    // died, resent.
    let seq_of_two = [2u32.to_le_bytes().to_vec(), keyed(1, 10), keyed(2, 20)].concat();
    t.write_op(1, DATA_SEQ, &seq_of_two, true, None);
    t.write_op(2, DATA, &keyed(3, 30), false, None);
    t.write_op(3, DATA, &keyed(4, 40), true, Some(2));
    t.matched_long_ago(CLIENT, WRITER);
    t.advance(Duration::from_millis(5));
    let now = t.worker.now;
    t.worker.pass(now).expect("pass");
    let origin = |write: u64, index: u32, resent: bool| {
        Some(ipc::SampleOrigin {
            write: ipc::WriteOrigin {
                frontend: FE,
                incarnation: 5,
                write,
                index,
            },
            resent,
        })
    };
    assert_eq!(
        t.origins(),
        vec![
            (1, origin(1, 0, false)),
            (2, origin(1, 1, false)),
            (3, None),
            (4, origin(2, 0, true)),
        ]
    );
}
