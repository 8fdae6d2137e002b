//! The message header (§8.3.2): session, stream, sequence number and optional client key.

use super::{ClientKey, DecodeError};

/// The header that starts every XRCE message.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct MessageHeader {
    /// Session id; 0x00..=0x7F carry a client key in the header.
    pub session_id: u8,
    /// Stream id (0 = none).
    pub stream_id: u8,
    /// Sequence number within the stream, always little endian on the wire.
    pub sequence_nr: u16,
    /// Present if and only if `session_id <= 0x7F`.
    pub client_key: Option<ClientKey>,
}

impl MessageHeader {
    /// Whether a session id implies a client key in the header.
    pub fn session_has_key(session_id: u8) -> bool {
        session_id < 0x80
    }

    /// The encoded length of a header for this session id.
    pub fn encoded_len(session_id: u8) -> usize {
        if Self::session_has_key(session_id) {
            8
        } else {
            4
        }
    }

    /// Builds a header; the key is kept only when the session id calls for it.
    pub fn new(session_id: u8, stream_id: u8, sequence_nr: u16, key: ClientKey) -> Self {
        let client_key = Self::session_has_key(session_id).then_some(key);
        MessageHeader {
            session_id,
            stream_id,
            sequence_nr,
            client_key,
        }
    }

    /// Decodes a header, returning it and its length.
    pub fn decode(buf: &[u8]) -> Result<(Self, usize), DecodeError> {
        if buf.len() < 4 {
            return Err(DecodeError::Truncated);
        }
        let session_id = buf[0];
        let stream_id = buf[1];
        let sequence_nr = u16::from_le_bytes([buf[2], buf[3]]);
        if Self::session_has_key(session_id) {
            if buf.len() < 8 {
                return Err(DecodeError::Truncated);
            }
            let key = ClientKey([buf[4], buf[5], buf[6], buf[7]]);
            Ok((
                MessageHeader {
                    session_id,
                    stream_id,
                    sequence_nr,
                    client_key: Some(key),
                },
                8,
            ))
        } else {
            Ok((
                MessageHeader {
                    session_id,
                    stream_id,
                    sequence_nr,
                    client_key: None,
                },
                4,
            ))
        }
    }

    /// Appends the encoded header.
    pub fn encode(&self, out: &mut Vec<u8>) {
        out.push(self.session_id);
        out.push(self.stream_id);
        out.extend_from_slice(&self.sequence_nr.to_le_bytes());
        if Self::session_has_key(self.session_id) {
            out.extend_from_slice(&self.client_key.unwrap_or_default().0);
        }
    }
}
