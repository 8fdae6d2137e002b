//! The XRCE wire format: message header, submessages and their payloads (§8.3).
//!
//! Decoding never panics and never allocates more than the input implies (strings and
//! sequences are bounded by [`payload`]'s limits). Encoding emits exactly the layout the
//! decoder reads, so decoded captures re-encode to the same bytes.

pub mod binary;
pub mod cdr;
pub mod equivalence;
pub mod header;
pub mod info;
pub mod payload;
pub mod sample;
pub mod types;

pub use header::MessageHeader;
pub use payload::*;
pub use types::*;

/// Why bytes could not be decoded. Each variant is a drop reason the agent counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The input ended inside a field.
    #[error("truncated")]
    Truncated,
    /// A submessage length points past the end of the message.
    #[error("submessage length beyond the message")]
    BadSubmessageLength,
    /// A field holds a value the protocol does not allow.
    #[error("invalid {0}")]
    InvalidValue(&'static str),
    /// A string or sequence is longer than the configured bound.
    #[error("{0} too long")]
    TooLong(&'static str),
}

impl DecodeError {
    /// A short stable name, used as a metric label.
    pub fn reason(&self) -> &'static str {
        match self {
            DecodeError::Truncated => "truncated",
            DecodeError::BadSubmessageLength => "bad_submessage_length",
            DecodeError::InvalidValue(_) => "invalid_value",
            DecodeError::TooLong(_) => "too_long",
        }
    }
}

/// Why a message could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// A submessage payload does not fit the 16-bit length field.
    #[error("submessage payload of {0} bytes exceeds 65535")]
    PayloadTooLong(usize),
}

/// A submessage as framed on the wire, payload not decoded yet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RawSubmessage<'a> {
    /// Submessage id.
    pub id: u8,
    /// Flags (bit 0 = little endian).
    pub flags: u8,
    /// The payload, `submessageLength` bytes.
    pub payload: &'a [u8],
    /// Offset of the submessage header from the start of the message.
    pub offset: usize,
}

impl<'a> RawSubmessage<'a> {
    /// Decodes the payload.
    pub fn decode(&self) -> Result<Payload<'a>, DecodeError> {
        Payload::decode(self.id, self.flags, self.payload)
    }

    /// Whether the payload is little endian.
    pub fn little_endian(&self) -> bool {
        self.flags & flags::LITTLE_ENDIAN != 0
    }
}

/// Iterates over the submessages of a message.
///
/// Up to three trailing bytes after the last submessage (padding some clients send) end the
/// iteration; a header that claims more bytes than remain yields one error, then ends.
#[derive(Debug, Clone)]
pub struct Submessages<'a> {
    msg: &'a [u8],
    pos: usize,
    failed: bool,
    reassembled: bool,
}

impl<'a> Submessages<'a> {
    /// Iterates over `msg[start..]`, where `start` is the header length.
    pub fn new(msg: &'a [u8], start: usize) -> Self {
        Submessages {
            msg,
            pos: start,
            failed: false,
            reassembled: false,
        }
    }

    /// Iterates over a buffer reassembled from FRAGMENTs. There a WRITE_DATA or DATA whose
    /// `submessageLength` is 0 runs to the end of the buffer: eProsima's convention
    /// (`UCLIENT_TWEAK_XRCE_WRITE_LIMIT`, on by default) for samples beyond 64 KiB, which a
    /// 16-bit length cannot describe.
    pub fn reassembled(buf: &'a [u8]) -> Self {
        Submessages {
            reassembled: true,
            ..Submessages::new(buf, 0)
        }
    }

    /// Bytes left after the last submessage returned so far.
    pub fn trailing(&self) -> usize {
        self.msg.len().saturating_sub(self.pos)
    }
}

impl<'a> Iterator for Submessages<'a> {
    type Item = Result<RawSubmessage<'a>, DecodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let aligned = self.pos.div_ceil(4) * 4;
        if aligned + 4 > self.msg.len() {
            return None;
        }
        let h = &self.msg[aligned..aligned + 4];
        let start = aligned + 4;
        let mut len = u16::from_le_bytes([h[2], h[3]]) as usize;
        if len == 0
            && self.reassembled
            && (h[0] == submessage_id::WRITE_DATA || h[0] == submessage_id::DATA)
        {
            len = self.msg.len() - start;
        }
        if start + len > self.msg.len() {
            self.failed = true;
            return Some(Err(DecodeError::BadSubmessageLength));
        }
        self.pos = start + len;
        Some(Ok(RawSubmessage {
            id: h[0],
            flags: h[1],
            payload: &self.msg[start..start + len],
            offset: aligned,
        }))
    }
}

/// A decoded submessage with its endianness.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Submessage<'a> {
    /// Whether the payload was (or is to be) little endian.
    pub little_endian: bool,
    /// The payload.
    pub payload: Payload<'a>,
}

impl<'a> Submessage<'a> {
    /// A little-endian submessage.
    pub fn le(payload: Payload<'a>) -> Self {
        Submessage {
            little_endian: true,
            payload,
        }
    }
}

/// A whole decoded message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Message<'a> {
    /// The header.
    pub header: MessageHeader,
    /// The submessages in order.
    pub submessages: Vec<Submessage<'a>>,
}

impl<'a> Message<'a> {
    /// Decodes a whole message, failing on the first malformed submessage.
    pub fn decode(bytes: &'a [u8]) -> Result<Self, DecodeError> {
        let (header, hlen) = MessageHeader::decode(bytes)?;
        let mut submessages = Vec::new();
        for raw in Submessages::new(bytes, hlen) {
            let raw = raw?;
            submessages.push(Submessage {
                little_endian: raw.little_endian(),
                payload: raw.decode()?,
            });
        }
        Ok(Message {
            header,
            submessages,
        })
    }

    /// Encodes the message.
    pub fn encode(&self) -> Result<Vec<u8>, EncodeError> {
        let mut b = MessageBuilder::new(self.header);
        for s in &self.submessages {
            b.push(&s.payload, s.little_endian)?;
        }
        Ok(b.finish())
    }
}

impl CreateClientPayload {
    /// This CREATE_CLIENT alone in a message whose header carries the client's key (session
    /// id 0x00), little-endian: what a client with a key sends to open its session.
    pub fn message(self) -> Result<Vec<u8>, EncodeError> {
        let header = MessageHeader::new(0x00, 0, 0, self.client_key);
        MessageBuilder::single(header, &Payload::CreateClient(self))
    }
}

/// Builds a message one submessage at a time, with padding and lengths filled in.
#[derive(Debug, Clone)]
pub struct MessageBuilder {
    buf: Vec<u8>,
}

impl MessageBuilder {
    /// Starts a message with `header`.
    pub fn new(header: MessageHeader) -> Self {
        let mut buf = Vec::with_capacity(64);
        header.encode(&mut buf);
        MessageBuilder { buf }
    }

    /// A message of `payload` alone after `header`, little-endian (what tests and tools send
    /// one submessage at a time).
    pub fn single(header: MessageHeader, payload: &Payload<'_>) -> Result<Vec<u8>, EncodeError> {
        let mut b = MessageBuilder::new(header);
        b.push(payload, true)?;
        Ok(b.finish())
    }

    /// Length so far.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Whether only the header was written.
    pub fn is_empty(&self) -> bool {
        self.buf.len() <= 8
    }

    /// Appends a submessage, padding the message to a 4-byte boundary first.
    pub fn push(&mut self, payload: &Payload<'_>, little_endian: bool) -> Result<(), EncodeError> {
        let aligned = self.buf.len().div_ceil(4) * 4;
        self.buf.resize(aligned, 0);
        let flags = payload.extra_flags()
            | if little_endian {
                flags::LITTLE_ENDIAN
            } else {
                0
            };
        self.buf.extend_from_slice(&[payload.id(), flags, 0, 0]);
        let start = self.buf.len();
        payload.encode(&mut self.buf, little_endian);
        let len = self.buf.len() - start;
        if len > u16::MAX as usize {
            self.buf.truncate(aligned);
            return Err(EncodeError::PayloadTooLong(len));
        }
        self.buf[start - 2..start].copy_from_slice(&(len as u16).to_le_bytes());
        Ok(())
    }

    /// The finished message.
    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// Encodes one submessage (header and payload) on its own, laid out as it would be at any
/// 4-byte-aligned offset of a message; used to queue, fragment or batch submessages.
pub fn encode_submessage(
    payload: &Payload<'_>,
    little_endian: bool,
) -> Result<Vec<u8>, EncodeError> {
    let mut b = MessageBuilder::new(MessageHeader {
        session_id: 0x80,
        stream_id: 0,
        sequence_nr: 0,
        client_key: None,
    });
    b.push(payload, little_endian)?;
    let mut v = b.finish();
    v.drain(..4);
    Ok(v)
}

/// Encodes one submessage like [`encode_submessage`], except that a WRITE_DATA or DATA
/// payload beyond 65,535 bytes gets `submessageLength` 0 (see [`Submessages::reassembled`]);
/// such a submessage must be sent in FRAGMENTs.
pub fn encode_large_submessage(
    payload: &Payload<'_>,
    little_endian: bool,
) -> Result<Vec<u8>, EncodeError> {
    match encode_submessage(payload, little_endian) {
        Err(EncodeError::PayloadTooLong(_))
            if matches!(payload, Payload::WriteData(_) | Payload::Data(_)) =>
        {
            let flags = payload.extra_flags()
                | if little_endian {
                    flags::LITTLE_ENDIAN
                } else {
                    0
                };
            let mut v = vec![payload.id(), flags, 0, 0];
            payload.encode(&mut v, little_endian);
            Ok(v)
        }
        other => other,
    }
}

/// Formats bytes as lowercase hex (for logs at trace level).
pub fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    let mut s = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        let _ = write!(s, "{b:02x}");
    }
    s
}
