//! Serial-line framing, as the eProsima client's stream framing puts XRCE messages on a UART
//! (and as every deployed client and agent use it, not the CRC of the spec's Annex C):
//!
//! ```text
//! 0x7E | source | destination | length (u16 LE) | payload | CRC-16/ARC of the payload (LE)
//! ```
//!
//! There is no end flag. After the flag, every byte (header, payload and CRC) that is 0x7E or
//! 0x7D is sent as 0x7D followed by the byte XOR 0x20. A 0x7E anywhere starts a new frame.
//! Several nodes can share a line: each frame names its source and destination address, and
//! a receiver keeps only frames addressed to it. The agent is address 0.

use super::FrameError;

/// Starts every frame.
pub const FLAG: u8 = 0x7E;
/// Announces a stuffed byte.
pub const ESCAPE: u8 = 0x7D;
/// What a stuffed byte is XORed with.
pub const ESCAPE_XOR: u8 = 0x20;
/// The agent's address on a serial line.
pub const AGENT_ADDRESS: u8 = 0;
/// Largest payload the length field can announce.
pub const MAX_PAYLOAD: usize = u16::MAX as usize;

const CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_ARC);

/// CRC-16/ARC (polynomial 0x8005 reflected, initial value 0, no final XOR) of `bytes`.
pub fn crc16(bytes: &[u8]) -> u16 {
    CRC.checksum(bytes)
}

/// One whole, checked frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SerialFrame<'a> {
    /// Address of the sender.
    pub source: u8,
    /// Address it was sent to (the receiver's own).
    pub destination: u8,
    /// The XRCE message, unstuffed.
    pub payload: &'a [u8],
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Waiting for a flag.
    Idle,
    Source,
    Destination,
    LengthLow,
    LengthHigh,
    Payload,
    CrcLow,
    CrcHigh,
}

/// Splits a serial byte stream into frames addressed to one local address.
#[derive(Debug)]
pub struct SerialDecoder {
    local: u8,
    max_payload: usize,
    state: State,
    escaped: bool,
    source: u8,
    destination: u8,
    length: usize,
    crc_low: u8,
    payload: Vec<u8>,
    /// Bytes seen outside any frame (line noise, a client's boot messages).
    stray_bytes: u64,
}

impl SerialDecoder {
    /// A decoder for frames to `local` carrying at most `max_payload` bytes.
    pub fn new(local: u8, max_payload: usize) -> Self {
        SerialDecoder {
            local,
            max_payload: max_payload.min(MAX_PAYLOAD),
            state: State::Idle,
            escaped: false,
            source: 0,
            destination: 0,
            length: 0,
            crc_low: 0,
            payload: Vec::new(),
            stray_bytes: 0,
        }
    }

    /// Bytes seen outside any frame so far.
    pub fn stray_bytes(&self) -> u64 {
        self.stray_bytes
    }

    /// Forgets a frame in progress (the line was closed).
    pub fn reset(&mut self) {
        self.state = State::Idle;
        self.escaped = false;
        self.payload = Vec::new();
    }

    /// Feeds bytes read from the line; every frame they complete, or drop, is reported to
    /// `on_frame` in order.
    pub fn push(
        &mut self,
        bytes: &[u8],
        mut on_frame: impl FnMut(Result<SerialFrame<'_>, FrameError>),
    ) {
        for &raw in bytes {
            if raw == FLAG {
                if !matches!(self.state, State::Idle | State::Source) {
                    on_frame(Err(FrameError::Interrupted));
                }
                self.state = State::Source;
                self.escaped = false;
                self.payload.clear();
                continue;
            }
            if self.state == State::Idle {
                self.stray_bytes += 1;
                continue;
            }
            let b = if self.escaped {
                self.escaped = false;
                raw ^ ESCAPE_XOR
            } else if raw == ESCAPE {
                self.escaped = true;
                continue;
            } else {
                raw
            };
            match self.state {
                State::Idle => {}
                State::Source => {
                    self.source = b;
                    self.state = State::Destination;
                }
                State::Destination => {
                    self.destination = b;
                    self.state = State::LengthLow;
                }
                State::LengthLow => {
                    self.length = b as usize;
                    self.state = State::LengthHigh;
                }
                State::LengthHigh => {
                    self.length |= (b as usize) << 8;
                    if self.length > self.max_payload {
                        self.state = State::Idle;
                        on_frame(Err(FrameError::TooLong(self.length)));
                    } else if self.length == 0 {
                        self.state = State::CrcLow;
                    } else {
                        self.payload.reserve(self.length);
                        self.state = State::Payload;
                    }
                }
                State::Payload => {
                    self.payload.push(b);
                    if self.payload.len() == self.length {
                        self.state = State::CrcLow;
                    }
                }
                State::CrcLow => {
                    self.crc_low = b;
                    self.state = State::CrcHigh;
                }
                State::CrcHigh => {
                    self.state = State::Idle;
                    let crc = u16::from_le_bytes([self.crc_low, b]);
                    if crc != crc16(&self.payload) {
                        on_frame(Err(FrameError::BadCrc));
                    } else if self.destination != self.local {
                        on_frame(Err(FrameError::ForeignDestination(self.destination)));
                    } else {
                        on_frame(Ok(SerialFrame {
                            source: self.source,
                            destination: self.destination,
                            payload: &self.payload,
                        }));
                    }
                    if self.payload.capacity() > 4 * self.length.max(1024) {
                        // A rare huge frame does not pin its buffer for ever.
                        self.payload = Vec::new();
                    }
                }
            }
        }
    }
}

fn push_stuffed(out: &mut Vec<u8>, b: u8) {
    if b == FLAG || b == ESCAPE {
        out.push(ESCAPE);
        out.push(b ^ ESCAPE_XOR);
    } else {
        out.push(b);
    }
}

/// Appends one frame carrying `payload` from `source` to `destination` to `out`.
pub fn encode(
    source: u8,
    destination: u8,
    payload: &[u8],
    out: &mut Vec<u8>,
) -> Result<(), FrameError> {
    let len = u16::try_from(payload.len()).map_err(|_| FrameError::TooLong(payload.len()))?;
    out.reserve(payload.len() + payload.len() / 16 + 12);
    out.push(FLAG);
    push_stuffed(out, source);
    push_stuffed(out, destination);
    for b in len.to_le_bytes() {
        push_stuffed(out, b);
    }
    for &b in payload {
        push_stuffed(out, b);
    }
    for b in crc16(payload).to_le_bytes() {
        push_stuffed(out, b);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(d: &mut SerialDecoder, bytes: &[u8]) -> Vec<Result<(u8, Vec<u8>), FrameError>> {
        let mut out = Vec::new();
        d.push(bytes, |f| {
            out.push(f.map(|f| (f.source, f.payload.to_vec())))
        });
        out
    }

    #[test]
    fn crc_check_value() {
        assert_eq!(crc16(b"123456789"), 0xBB3D);
    }

    #[test]
    fn stuffed_bytes_round_trip() {
        let payload = [0x7E, 0x7D, 0x20, 0x5E, 0x00];
        let mut wire = Vec::new();
        encode(3, AGENT_ADDRESS, &payload, &mut wire).expect("fits");
        assert_eq!(wire.iter().filter(|&&b| b == FLAG).count(), 1);
        let mut d = SerialDecoder::new(AGENT_ADDRESS, 512);
        assert_eq!(frames(&mut d, &wire), vec![Ok((3, payload.to_vec()))]);
    }

    #[test]
    fn drops_are_reported_and_the_next_frame_decodes() {
        let mut d = SerialDecoder::new(AGENT_ADDRESS, 8);
        let mut wire = Vec::new();
        encode(1, AGENT_ADDRESS, &[1, 2, 3], &mut wire).expect("fits");
        let mut bad_crc = wire.clone();
        let last = bad_crc.len() - 1;
        bad_crc[last] ^= 1;
        let mut foreign = Vec::new();
        encode(1, 9, &[1], &mut foreign).expect("fits");
        let mut long = Vec::new();
        encode(1, AGENT_ADDRESS, &[0; 9], &mut long).expect("fits");
        let mut all = b"noise".to_vec();
        all.extend(&bad_crc);
        all.extend(&foreign);
        all.extend(&long);
        all.extend(&wire[..4]); // cut short by the next flag
        all.extend(&wire);
        assert_eq!(
            frames(&mut d, &all),
            vec![
                Err(FrameError::BadCrc),
                Err(FrameError::ForeignDestination(9)),
                Err(FrameError::TooLong(9)),
                Err(FrameError::Interrupted),
                Ok((1, vec![1, 2, 3])),
            ]
        );
        assert_eq!(d.stray_bytes(), 5 + 9 + 2);
    }

    #[test]
    fn encode_refuses_what_the_length_cannot_say() {
        assert_eq!(
            encode(0, 1, &vec![0; MAX_PAYLOAD + 1], &mut Vec::new()),
            Err(FrameError::TooLong(MAX_PAYLOAD + 1))
        );
    }
}
