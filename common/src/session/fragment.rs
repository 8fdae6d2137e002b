//! FRAGMENT (§8.3.5.14): splitting a serialized submessage that does not fit the MTU into
//! FRAGMENT submessages on a reliable stream, and putting them back together.

use crate::wire::{flags, submessage_id};

/// Collects the fragments of one reliable input stream, with a bounded size.
#[derive(Debug, Clone, Default)]
pub struct Reassembly {
    buf: Vec<u8>,
    /// A message was given up part way (too large, stalled, evicted): its remaining
    /// fragments, up to its last, are dropped too, or their bytes would be taken for a
    /// message of their own.
    discarding: bool,
}

/// Why reassembly gave up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ReassemblyError {
    /// The fragments add up to more than the configured bound; they are discarded.
    #[error("reassembled message exceeds {0} bytes")]
    TooLarge(usize),
    /// A fragment of a message given up before: dropped with it.
    #[error("fragment of a message given up")]
    Discarded,
}

impl Reassembly {
    /// Adds the payload of a FRAGMENT; on the last one returns the whole serialized
    /// submessage(s). More than `max` bytes discards everything collected so far.
    pub fn push(
        &mut self,
        data: &[u8],
        last: bool,
        max: usize,
    ) -> Result<Option<Vec<u8>>, ReassemblyError> {
        if self.discarding {
            self.discarding = !last;
            return Err(ReassemblyError::Discarded);
        }
        if self.buf.len() + data.len() > max {
            self.buf = Vec::new();
            self.discarding = !last;
            return Err(ReassemblyError::TooLarge(max));
        }
        self.buf.extend_from_slice(data);
        Ok(last.then(|| std::mem::take(&mut self.buf)))
    }

    /// Bytes collected so far.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Bytes of memory it holds (what a memory budget counts: a growing buffer holds more
    /// than it has collected).
    pub fn capacity(&self) -> usize {
        self.buf.capacity()
    }

    /// Bytes of memory it would take on if `n` more bytes were collected (a buffer grows by
    /// doubling).
    pub fn growth_for(&self, n: usize) -> usize {
        let (len, cap) = (self.buf.len(), self.buf.capacity());
        if len + n <= cap {
            0
        } else {
            (cap * 2).max(len + n).max(8) - cap
        }
    }

    /// Whether nothing is being collected.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// Forgets a partial message (stream reset).
    pub fn clear(&mut self) {
        self.buf = Vec::new();
        self.discarding = false;
    }

    /// Gives up the message being collected: its memory goes now, and its fragments still
    /// to come are dropped up to its last one.
    pub fn abandon(&mut self) {
        if !self.buf.is_empty() {
            self.discarding = true;
        }
        self.buf = Vec::new();
    }
}

/// Splits a serialized submessage (header included) into FRAGMENT submessages whose
/// payloads are at most `max_chunk` bytes; each result is a whole FRAGMENT submessage.
pub fn fragments(submessage: &[u8], max_chunk: usize) -> Vec<Vec<u8>> {
    let max_chunk = max_chunk.clamp(1, u16::MAX as usize);
    let n = submessage.len().div_ceil(max_chunk);
    submessage
        .chunks(max_chunk)
        .enumerate()
        .map(|(i, chunk)| {
            let last = i + 1 == n;
            let f = flags::LITTLE_ENDIAN | if last { flags::LAST_FRAGMENT } else { 0 };
            let mut v = Vec::with_capacity(4 + chunk.len());
            v.extend_from_slice(&[submessage_id::FRAGMENT, f]);
            v.extend_from_slice(&(chunk.len() as u16).to_le_bytes());
            v.extend_from_slice(chunk);
            v
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_and_join() {
        let sub: Vec<u8> = (0..1234u32).map(|i| i as u8).collect();
        let frags = fragments(&sub, 500);
        assert_eq!(frags.len(), 3);
        assert_eq!(frags[0][1], 0x01);
        assert_eq!(frags[2][1], 0x03);
        let mut r = Reassembly::default();
        let mut out = None;
        for f in &frags {
            out = r.push(&f[4..], f[1] & 0x02 != 0, 10_000).expect("fits");
        }
        assert_eq!(out, Some(sub));
        assert!(r.is_empty());
    }

    #[test]
    fn the_rest_of_a_message_given_up_is_dropped_up_to_its_last_fragment() {
        let mut r = Reassembly::default();
        assert_eq!(r.push(b"abc", false, 100), Ok(None));
        r.abandon();
        assert_eq!(r.push(b"def", false, 100), Err(ReassemblyError::Discarded));
        assert_eq!(r.push(b"ghi", true, 100), Err(ReassemblyError::Discarded));
        // The next message is whole again.
        assert_eq!(r.push(b"jk", false, 100), Ok(None));
        assert_eq!(r.push(b"l", true, 100), Ok(Some(b"jkl".to_vec())));
        // Too large: the rest of that message is dropped too.
        assert_eq!(r.push(&[0; 80], false, 100), Ok(None));
        assert_eq!(
            r.push(&[0; 80], false, 100),
            Err(ReassemblyError::TooLarge(100))
        );
        assert_eq!(r.push(b"tail", true, 100), Err(ReassemblyError::Discarded));
        assert_eq!(r.push(b"x", true, 100), Ok(Some(b"x".to_vec())));
    }

    #[test]
    fn bounded() {
        let mut r = Reassembly::default();
        assert_eq!(r.push(&[0; 600], false, 1000), Ok(None));
        assert_eq!(
            r.push(&[0; 600], false, 1000),
            Err(ReassemblyError::TooLarge(1000))
        );
        assert!(r.is_empty());
    }
}
