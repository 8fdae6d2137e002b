//! TCP framing: every XRCE message is preceded by its length as a 2-byte little-endian
//! integer, as the eProsima client sends it (the prefix and the message usually arrive as
//! separate segments; several messages may arrive in one read). A zero length is skipped.
//!
//! [`LengthPrefixDecoder`] lets the caller read from the socket straight into its buffer
//! ([`LengthPrefixDecoder::spare`], [`LengthPrefixDecoder::filled`]) and hands out each whole
//! message as a slice of that buffer, so a message is copied once on its way in.

use super::FrameError;

/// Bytes of the length prefix.
pub const PREFIX_LEN: usize = 2;
/// Largest message the prefix can announce.
pub const MAX_MESSAGE: usize = u16::MAX as usize;
/// Room offered to each socket read at least.
const READ_CHUNK: usize = 2048;
/// A buffer this large or larger is given back when it empties.
const SHRINK_ABOVE: usize = READ_CHUNK + 1;

/// Splits a TCP byte stream into XRCE messages.
#[derive(Debug)]
pub struct LengthPrefixDecoder {
    buf: Vec<u8>,
    /// Start of the unconsumed bytes.
    head: usize,
    /// End of the bytes read so far.
    tail: usize,
    max_message: usize,
    /// Set after an over-long length: the stream cannot be resynchronised.
    failed: Option<FrameError>,
}

impl LengthPrefixDecoder {
    /// A decoder that refuses messages longer than `max_message` bytes (at most 65,535).
    pub fn new(max_message: usize) -> Self {
        LengthPrefixDecoder {
            buf: Vec::new(),
            head: 0,
            tail: 0,
            max_message: max_message.min(MAX_MESSAGE),
            failed: None,
        }
    }

    /// Bytes held that do not form a whole message yet.
    pub fn buffered(&self) -> usize {
        self.tail - self.head
    }

    /// Bytes of memory the decoder holds.
    pub fn capacity(&self) -> usize {
        self.buf.capacity()
    }

    /// Whether the stream broke the framing (an over-long message); nothing more decodes.
    pub fn failed(&self) -> Option<FrameError> {
        self.failed
    }

    /// Room to read more bytes into. Call [`Self::filled`] with how many were written, then
    /// drain [`Self::next_message`]; drained that way it is never empty, and the buffer never
    /// grows beyond the largest message plus one read.
    pub fn spare(&mut self) -> &mut [u8] {
        if self.head == self.tail {
            self.head = 0;
            self.tail = 0;
            if self.buf.len() >= SHRINK_ABOVE {
                self.buf = Vec::new();
            }
        }
        if self.buf.len() - self.tail < READ_CHUNK {
            if self.head > 0 {
                self.buf.copy_within(self.head..self.tail, 0);
                self.tail -= self.head;
                self.head = 0;
            }
            // Everything buffered belongs to one incomplete message (the caller drains whole
            // ones first), so this stays below max_message + prefix + one chunk.
            let want = (self.tail + READ_CHUNK).max(self.buf.len());
            let limit = self.max_message + PREFIX_LEN + READ_CHUNK;
            if want > self.buf.len() {
                // Grown by what arrives, exactly (no doubling): what it holds is what it
                // says it holds.
                let new_len = want.min(limit);
                self.buf.reserve_exact(new_len - self.buf.len());
                self.buf.resize(new_len, 0);
            }
        }
        &mut self.buf[self.tail..]
    }

    /// Records that `n` bytes were written at the start of [`Self::spare`].
    pub fn filled(&mut self, n: usize) {
        self.tail = (self.tail + n).min(self.buf.len());
    }

    /// Copies bytes in (for callers that do not read into [`Self::spare`]) and returns the
    /// messages they complete, in order, through `on_message`. Stops at the first error.
    pub fn push(
        &mut self,
        mut bytes: &[u8],
        mut on_message: impl FnMut(&[u8]),
    ) -> Result<(), FrameError> {
        while !bytes.is_empty() {
            if let Some(e) = self.failed {
                return Err(e);
            }
            let spare = self.spare();
            let n = spare.len().min(bytes.len());
            spare[..n].copy_from_slice(&bytes[..n]);
            self.filled(n);
            bytes = &bytes[n..];
            while let Some(m) = self.next_message() {
                on_message(m?);
            }
        }
        Ok(())
    }

    /// The next whole message, if one is buffered. An `Err` is final: the connection's
    /// framing is lost and it should be closed.
    pub fn next_message(&mut self) -> Option<Result<&[u8], FrameError>> {
        if let Some(e) = self.failed {
            return Some(Err(e));
        }
        loop {
            let avail = self.tail - self.head;
            if avail < PREFIX_LEN {
                return None;
            }
            let len = u16::from_le_bytes([self.buf[self.head], self.buf[self.head + 1]]) as usize;
            if len == 0 {
                self.head += PREFIX_LEN;
                continue;
            }
            if len > self.max_message {
                self.failed = Some(FrameError::TooLong(len));
                return Some(Err(FrameError::TooLong(len)));
            }
            if avail < PREFIX_LEN + len {
                return None;
            }
            let start = self.head + PREFIX_LEN;
            self.head = start + len;
            return Some(Ok(&self.buf[start..start + len]));
        }
    }
}

/// Appends `message` with its length prefix to `out`.
pub fn encode(message: &[u8], out: &mut Vec<u8>) -> Result<(), FrameError> {
    let len = u16::try_from(message.len()).map_err(|_| FrameError::TooLong(message.len()))?;
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(message);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_all(d: &mut LengthPrefixDecoder, bytes: &[u8]) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        d.push(bytes, |m| out.push(m.to_vec()))
            .expect("valid stream");
        out
    }

    #[test]
    fn prefix_and_message_in_separate_reads() {
        let mut d = LengthPrefixDecoder::new(MAX_MESSAGE);
        assert!(decode_all(&mut d, &[3, 0]).is_empty());
        assert_eq!(decode_all(&mut d, &[1, 2, 3]), vec![vec![1, 2, 3]]);
        assert_eq!(d.buffered(), 0);
    }

    #[test]
    fn several_messages_in_one_read_and_zero_lengths_skipped() {
        let mut d = LengthPrefixDecoder::new(MAX_MESSAGE);
        let got = decode_all(&mut d, &[1, 0, 9, 0, 0, 2, 0, 7, 8, 1]);
        assert_eq!(got, vec![vec![9], vec![7, 8]]);
        assert_eq!(d.buffered(), 1);
    }

    #[test]
    fn over_long_length_fails_the_stream() {
        let mut d = LengthPrefixDecoder::new(100);
        let r = d.push(&[101, 0, 1, 2], |_| panic!("no message expected"));
        assert_eq!(r, Err(FrameError::TooLong(101)));
        assert_eq!(d.failed(), Some(FrameError::TooLong(101)));
        assert!(d.push(&[1, 0, 1], |_| {}).is_err());
    }

    #[test]
    fn largest_message_fits_and_memory_is_given_back() {
        let mut d = LengthPrefixDecoder::new(MAX_MESSAGE);
        let msg = vec![0xAB; MAX_MESSAGE];
        let mut framed = Vec::new();
        encode(&msg, &mut framed).expect("fits");
        let got = decode_all(&mut d, &framed);
        assert_eq!(got.len(), 1);
        assert_eq!(got[0], msg);
        assert!(d.capacity() <= MAX_MESSAGE + PREFIX_LEN + READ_CHUNK);
        let _ = d.spare();
        assert!(d.capacity() <= READ_CHUNK);
    }

    #[test]
    fn encode_refuses_what_the_prefix_cannot_say() {
        assert_eq!(
            encode(&vec![0; MAX_MESSAGE + 1], &mut Vec::new()),
            Err(FrameError::TooLong(MAX_MESSAGE + 1))
        );
    }
}
