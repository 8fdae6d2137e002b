//! Stream state shared by the agent and client state machines (§8.4.14).
//!
//! Streams are per direction: an output stream belongs to the sender, an input stream to the
//! receiver. Reliable streams keep what was sent until acknowledged, and buffer what arrived
//! early; best-effort streams only drop what is not newer than the last delivered message.

use std::collections::{HashMap, VecDeque};

use super::seq;
use crate::wire::{AcknackPayload, HeartbeatPayload};

/// Where a WRITE_DATA stood in its client's reliable input stream: the message that carried
/// it and how many WRITE_DATA of that message came before it, in which run of the client's
/// streams. The worker keeps the last one it executed per client stream, so that a
/// front-end taking over from one that died between handing messages' writes over and
/// storing that it took them does not write them again when the client resends them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct InputPosition {
    /// The run of the client's streams: a new one each time they start again (a new
    /// session, a RESET, a client's restart), never issued twice by one front-end process
    /// and drawn at random across processes
    /// ([`crate::session::agent::AgentConfig::epoch_seed`]), so that a position of an
    /// earlier run is not taken for one of this run.
    pub epoch: u64,
    /// The reliable stream.
    pub stream_id: u8,
    /// The message's sequence number.
    pub sequence: u16,
    /// WRITE_DATA of the same message before this one (reassembled fragments included).
    pub write_index: u16,
}

/// The sender side of a reliable stream.
#[derive(Debug, Clone)]
pub struct ReliableOutput {
    stream_id: u8,
    next: u16,
    /// Sent and not yet acknowledged, oldest first: (sequence number, whole message).
    in_flight: VecDeque<(u16, Vec<u8>)>,
    window: usize,
    /// Taken over from a front-end that died: what the client received is unknown until its
    /// first ACKNACK, so nothing is sent meanwhile (see [`Self::resuming`]).
    resyncing: bool,
    /// Taken over (restored or resuming): an ACKNACK ahead of `next` moves it there.
    restored: bool,
}

impl ReliableOutput {
    /// A stream that keeps at most `window` unacknowledged messages.
    pub fn new(stream_id: u8, window: usize) -> Self {
        ReliableOutput {
            stream_id,
            next: 0,
            in_flight: VecDeque::new(),
            window: window.max(1),
            resyncing: false,
            restored: false,
        }
    }

    /// A new stream whose first message is numbered `first` (0 by the spec's "initialize
    /// to 0" as eProsima reads it; 1 for a client that reads it as "the last one sent").
    pub fn starting_at(stream_id: u8, window: usize, first: u16) -> Self {
        ReliableOutput {
            next: first,
            ..Self::new(stream_id, window)
        }
    }

    /// A stream taken over from a front-end that died after numbering up to `next`. The
    /// messages it had not seen acknowledged died with it, so the client may wait for
    /// numbers nobody will send again: until the client's ACKNACK says which number it
    /// expects, nothing is sent, and its HEARTBEAT (first `next`, last `next - 1`: nothing
    /// to resend) asks for that ACKNACK; numbering then goes on from the client's number.
    pub fn resuming(stream_id: u8, window: usize, next: u16) -> Self {
        ReliableOutput {
            next,
            resyncing: true,
            restored: true,
            ..Self::new(stream_id, window)
        }
    }

    /// A stream taken over from a front-end that died with `in_flight` (sequence number,
    /// whole message) unacknowledged and `next` to number: the normal HEARTBEAT and
    /// ACKNACK exchange resends what the client lacks.
    pub fn restored(
        stream_id: u8,
        window: usize,
        next: u16,
        in_flight: Vec<(u16, Vec<u8>)>,
    ) -> Self {
        ReliableOutput {
            next,
            in_flight: in_flight.into(),
            restored: true,
            ..Self::new(stream_id, window)
        }
    }

    /// The unacknowledged messages with their sequence numbers, oldest first.
    pub fn in_flight(&self) -> impl Iterator<Item = (u16, &[u8])> {
        self.in_flight.iter().map(|(s, m)| (*s, m.as_slice()))
    }

    /// Whether it waits for the client's ACKNACK after a takeover.
    pub fn is_resyncing(&self) -> bool {
        self.resyncing
    }

    /// The stream id.
    pub fn stream_id(&self) -> u8 {
        self.stream_id
    }

    /// Whether another message may be sent now.
    pub fn has_room(&self) -> bool {
        !self.resyncing && self.in_flight.len() < self.window
    }

    /// Messages sent and not yet acknowledged.
    pub fn unacked(&self) -> usize {
        self.in_flight.len()
    }

    /// The sequence number the next message will carry.
    pub fn next_seq(&self) -> u16 {
        self.next
    }

    /// Records a message sent with [`Self::next_seq`] and advances the sequence number.
    pub fn record(&mut self, message: Vec<u8>) {
        self.in_flight.push_back((self.next, message));
        self.next = self.next.wrapping_add(1);
    }

    /// Applies an ACKNACK; returns the messages to send again.
    pub fn on_acknack(&mut self, a: &AcknackPayload) -> Vec<&[u8]> {
        if self.resyncing {
            // The client's number is the truth: go on from it.
            self.resyncing = false;
            self.next = a.first_unacked_seq_num;
            self.in_flight.clear();
            return Vec::new();
        }
        // Only accept acknowledgements of what was actually sent; after a takeover from
        // state a little behind, the client may be ahead: it is the truth then.
        if seq::lt(self.next, a.first_unacked_seq_num) {
            if self.restored {
                self.next = a.first_unacked_seq_num;
                self.in_flight.clear();
            }
            return Vec::new();
        }
        while let Some((s, _)) = self.in_flight.front() {
            if seq::lt(*s, a.first_unacked_seq_num) {
                self.in_flight.pop_front();
            } else {
                break;
            }
        }
        let mut out = Vec::new();
        for (s, m) in &self.in_flight {
            let i = s.wrapping_sub(a.first_unacked_seq_num);
            if i < 16 && a.nack_bitmap & (1 << i) != 0 {
                out.push(m.as_slice());
            }
        }
        out
    }

    /// The HEARTBEAT to send while messages are unacknowledged.
    pub fn heartbeat(&self) -> Option<HeartbeatPayload> {
        if self.resyncing {
            return Some(HeartbeatPayload {
                first_unacked_seq_num: self.next,
                last_unacked_seq_num: self.next.wrapping_sub(1),
                stream_id: self.stream_id,
            });
        }
        let (first, _) = self.in_flight.front()?;
        Some(HeartbeatPayload {
            first_unacked_seq_num: *first,
            last_unacked_seq_num: self.next.wrapping_sub(1),
            stream_id: self.stream_id,
        })
    }

    /// All unacknowledged messages, oldest first.
    pub fn unacked_messages(&self) -> impl Iterator<Item = &[u8]> {
        self.in_flight.iter().map(|(_, m)| m.as_slice())
    }

    /// Forgets everything (RESET): numbering restarts at 0.
    pub fn reset(&mut self) {
        self.next = 0;
        self.in_flight.clear();
        self.resyncing = false;
        self.restored = false;
    }
}

/// What the receiver of a reliable stream should do with an arriving message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arrival {
    /// It is the next expected one: process it now, then call [`ReliableInput::advance`].
    InOrder,
    /// It is ahead of a gap and within the window: keep it for later.
    Early,
    /// Already delivered (or already buffered): drop it.
    Duplicate,
    /// Too far ahead: drop it; the sender will resend.
    OutOfWindow,
}

/// The receiver side of a reliable stream.
#[derive(Debug, Clone)]
pub struct ReliableInput {
    expected: u16,
    highest_announced: Option<u16>,
    early: HashMap<u16, Vec<u8>>,
    window: u16,
}

impl ReliableInput {
    /// A stream buffering at most `window` (≤ 16) early messages.
    pub fn new(window: u16) -> Self {
        ReliableInput {
            expected: 0,
            highest_announced: None,
            early: HashMap::new(),
            window: window.clamp(1, 16),
        }
    }

    /// A stream taken over from a front-end that died expecting `expected` next.
    pub fn resuming(window: u16, expected: u16) -> Self {
        ReliableInput {
            expected,
            ..Self::new(window)
        }
    }

    /// The next sequence number expected.
    pub fn expected(&self) -> u16 {
        self.expected
    }

    /// Whether `s` is behind what was taken (a copy of a message already processed).
    pub fn is_behind(&self, s: u16) -> bool {
        s.wrapping_sub(self.expected) >= 0x8000
    }

    /// Classifies an arriving sequence number (and notes it as announced).
    pub fn classify(&mut self, s: u16) -> Arrival {
        let d = s.wrapping_sub(self.expected);
        if d >= 0x8000 {
            return Arrival::Duplicate;
        }
        self.announce(s);
        if d == 0 {
            // A copy kept earlier (before a HEARTBEAT moved `expected` onto it) is stale now.
            self.early.remove(&s);
            Arrival::InOrder
        } else if self.early.contains_key(&s) {
            Arrival::Duplicate
        } else if d < self.window {
            Arrival::Early
        } else {
            Arrival::OutOfWindow
        }
    }

    /// Bytes of early messages kept.
    pub fn early_bytes(&self) -> usize {
        self.early.values().map(Vec::len).sum()
    }

    /// Gives up the early messages kept (they are not acknowledged: their sender sends them
    /// again); returns their bytes.
    pub fn drop_early(&mut self) -> usize {
        let bytes = self.early_bytes();
        self.early.clear();
        bytes
    }

    /// Keeps an early message.
    pub fn store_early(&mut self, s: u16, message: Vec<u8>) {
        self.early.insert(s, message);
    }

    /// Marks the expected message as delivered.
    pub fn advance(&mut self) {
        self.expected = self.expected.wrapping_add(1);
    }

    /// Takes the expected message if it arrived early; deliver it, then [`Self::advance`].
    /// A receiver that cannot deliver it now takes it anyway and drops it: the next ACKNACK
    /// then reports it missing, so the sender resends it.
    pub fn take_ready(&mut self) -> Option<Vec<u8>> {
        self.early.remove(&self.expected)
    }

    /// Notes a sequence number the sender says it has sent.
    pub fn announce(&mut self, s: u16) {
        self.highest_announced = Some(match self.highest_announced {
            Some(h) => seq::max(h, s),
            None => s,
        });
    }

    /// Applies a HEARTBEAT: messages before `first` are no longer available, so skip them.
    pub fn on_heartbeat(&mut self, h: &HeartbeatPayload) {
        if seq::lt(self.expected, h.first_unacked_seq_num) {
            // The sender gave up on them; never wait for them.
            self.expected = h.first_unacked_seq_num;
            let exp = self.expected;
            self.early.retain(|s, _| seq::le(exp, *s));
        }
        self.announce(h.last_unacked_seq_num);
    }

    /// Whether messages are known to be missing.
    pub fn has_gap(&self) -> bool {
        self.highest_announced
            .is_some_and(|h| seq::le(self.expected, h))
    }

    /// The ACKNACK describing this stream.
    pub fn acknack(&self, stream_id: u8) -> AcknackPayload {
        let mut bitmap = 0u16;
        if let Some(h) = self.highest_announced {
            for i in 0..16u16 {
                let s = self.expected.wrapping_add(i);
                if !seq::le(s, h) {
                    break;
                }
                if !self.early.contains_key(&s) {
                    bitmap |= 1 << i;
                }
            }
        }
        AcknackPayload {
            first_unacked_seq_num: self.expected,
            nack_bitmap: bitmap,
            stream_id,
        }
    }

    /// Forgets everything (RESET).
    pub fn reset(&mut self) {
        self.expected = 0;
        self.highest_announced = None;
        self.early.clear();
    }
}

/// The receiver side of a best-effort stream: newer messages only.
#[derive(Debug, Clone, Default)]
pub struct BestEffortInput {
    last: Option<u16>,
}

impl BestEffortInput {
    /// Whether a message with this sequence number is to be delivered (and records it).
    pub fn accept(&mut self, s: u16) -> bool {
        match self.last {
            Some(l) if !seq::lt(l, s) => false,
            _ => {
                self.last = Some(s);
                true
            }
        }
    }

    /// Whether a message with this sequence number would be refused as stale.
    pub fn is_stale(&self, s: u16) -> bool {
        matches!(self.last, Some(l) if !seq::lt(l, s))
    }

    /// Forgets the last sequence number (RESET).
    pub fn reset(&mut self) {
        self.last = None;
    }

    /// The last sequence number delivered.
    pub fn last(&self) -> Option<u16> {
        self.last
    }

    /// A stream taken over from a front-end that died after delivering `last`.
    pub fn resuming(last: u16) -> Self {
        BestEffortInput { last: Some(last) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn input_reorders_within_window_and_drops_duplicates() {
        let mut i = ReliableInput::new(16);
        assert_eq!(i.classify(1), Arrival::Early);
        i.store_early(1, vec![1]);
        assert_eq!(i.classify(1), Arrival::Duplicate);
        assert_eq!(i.acknack(0x80).nack_bitmap, 0b01);
        assert_eq!(i.classify(0), Arrival::InOrder);
        i.advance();
        assert_eq!(i.take_ready(), Some(vec![1]));
        i.advance();
        assert_eq!(i.take_ready(), None);
        assert_eq!(i.expected(), 2);
        assert_eq!(i.classify(0), Arrival::Duplicate);
        assert_eq!(i.classify(40), Arrival::OutOfWindow);
    }

    #[test]
    fn heartbeat_skipping_onto_a_buffered_message_does_not_stall() {
        let mut i = ReliableInput::new(16);
        assert_eq!(i.classify(5), Arrival::Early);
        i.store_early(5, vec![5]);
        i.on_heartbeat(&HeartbeatPayload {
            first_unacked_seq_num: 5,
            last_unacked_seq_num: 5,
            stream_id: 0x80,
        });
        assert_eq!(i.take_ready(), Some(vec![5]));
        i.advance();
        assert_eq!(i.expected(), 6);
    }

    #[test]
    fn a_dropped_ready_message_is_reported_missing() {
        let mut i = ReliableInput::new(16);
        i.classify(1);
        i.store_early(1, vec![1]);
        assert_eq!(i.classify(0), Arrival::InOrder);
        i.advance();
        // No room to deliver 1: it is taken and dropped; the ACKNACK must ask for it again.
        assert!(i.take_ready().is_some());
        let a = i.acknack(0x80);
        assert_eq!((a.first_unacked_seq_num, a.nack_bitmap & 1), (1, 1));
    }

    #[test]
    fn output_retransmits_nacked_and_drops_acked() {
        let mut o = ReliableOutput::new(0x80, 8);
        for k in 0..4u8 {
            o.record(vec![k]);
        }
        let re = o.on_acknack(&AcknackPayload {
            first_unacked_seq_num: 1,
            nack_bitmap: 0b101,
            stream_id: 0x80,
        });
        assert_eq!(re, vec![&[1u8][..], &[3u8][..]]);
        assert_eq!(o.unacked(), 3);
        assert_eq!(
            o.heartbeat()
                .map(|h| (h.first_unacked_seq_num, h.last_unacked_seq_num)),
            Some((1, 3))
        );
        // An acknowledgement of something never sent is ignored.
        assert!(o
            .on_acknack(&AcknackPayload {
                first_unacked_seq_num: 100,
                nack_bitmap: 0,
                stream_id: 0x80
            })
            .is_empty());
        assert_eq!(o.unacked(), 3);
    }

    #[test]
    fn best_effort_drops_old() {
        let mut b = BestEffortInput::default();
        assert!(b.accept(5));
        assert!(!b.accept(5));
        assert!(!b.accept(4));
        assert!(b.accept(9));
    }
}
