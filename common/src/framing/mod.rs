//! Byte-stream framers: how XRCE messages travel over transports that carry a stream of bytes
//! instead of datagrams. Sans-IO like the rest of this crate: bytes in, whole messages out.
//!
//! * [`length_prefix`]: TCP, each message preceded by its length (2 bytes, little endian).
//! * [`serial`]: serial lines, eProsima's stream framing (flag, addresses, length, byte
//!   stuffing, CRC-16/ARC).
//!
//! Neither allocates beyond a bound fixed at construction, and neither panics on any input.

pub mod length_prefix;
pub mod serial;

/// Why a framer dropped bytes or refused a message. Each variant is a counted drop reason.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A frame announced a length above the configured maximum.
    #[error("frame of {0} bytes exceeds the maximum")]
    TooLong(usize),
    /// A serial frame's CRC did not match its payload.
    #[error("bad CRC")]
    BadCrc,
    /// A serial frame was addressed to another node.
    #[error("frame for address {0}")]
    ForeignDestination(u8),
    /// A serial frame was cut short by a new flag.
    #[error("frame interrupted by a new flag")]
    Interrupted,
}

impl FrameError {
    /// A short stable name, used as a counter label.
    pub fn reason(&self) -> &'static str {
        match self {
            FrameError::TooLong(_) => "frame_too_long",
            FrameError::BadCrc => "bad_crc",
            FrameError::ForeignDestination(_) => "foreign_destination",
            FrameError::Interrupted => "frame_interrupted",
        }
    }
}
