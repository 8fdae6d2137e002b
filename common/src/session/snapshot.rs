//! What a session needs to outlive its front-end process: the state a restarted front-end
//! takes over so that the client goes on without re-creating anything.
//!
//! A [`SessionSnapshot`] holds the session's identity and its streams' positions: the next
//! number expected on each reliable input stream (so what the client retransmits is taken
//! once, and what was acknowledged is not waited for again), the last number taken on each
//! best-effort input stream, and the next number of each output stream (a best-effort one
//! goes on from it, so the client does not drop what follows as old; a reliable one keeps
//! its unacknowledged messages, which the client gets again if it lacks them, and the output
//! waiting for window room). Early input messages and fragments being reassembled are not
//! kept: the client resends what was not acknowledged.
//!
//! The encoding is this crate's own (little endian, versioned); the endpoint is opaque bytes
//! that the transport encodes and decodes.

use std::time::Duration;

use crate::wire::{ClientKey, Dialect};

/// Version of the encoding.
const VERSION: u8 = 3;
/// The version before the epoch of the streams was stored: still read (its sessions' epoch
/// is 0, which no front-end issues), so an upgrade keeps the sessions.
const VERSION_WITHOUT_EPOCH: u8 = 2;
/// Most streams of each kind a snapshot carries (the session core allows fewer).
const MAX_STREAMS: usize = 256;
/// Most unacknowledged messages kept per reliable output stream (windows are at most 16).
const MAX_IN_FLIGHT: usize = 64;
/// Most submessages waiting for window room a snapshot carries per stream.
const MAX_QUEUED: usize = 4096;
/// Most bytes of them it carries per stream (a client far behind keeps its oldest output;
/// what is beyond is lost if the front-end dies).
const MAX_QUEUED_BYTES: usize = 128 << 10;

/// The state a front-end keeps of one session for its successor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SessionSnapshot {
    /// The client's key.
    pub key: ClientKey,
    /// Its session id.
    pub session_id: u8,
    /// Where it is reached, as its transport encodes endpoints (empty: not restorable).
    pub endpoint: Vec<u8>,
    /// Its MTU.
    pub mtu: u16,
    /// Its dialect.
    pub dialect: Dialect,
    /// Its dead time, if any.
    pub dead_time: Option<Duration>,
    /// Reliable input streams: (stream id, next number expected).
    pub reliable_in: Vec<(u8, u16)>,
    /// Best-effort input streams: (stream id, last number taken).
    pub best_effort_in: Vec<(u8, u16)>,
    /// Reliable output streams.
    pub reliable_out: Vec<OutputSnapshot>,
    /// Best-effort output streams: (stream id, next number).
    pub best_effort_out: Vec<(u8, u16)>,
    /// The run of its streams ([`crate::session::stream::InputPosition::epoch`]).
    pub epoch: u64,
}

/// A reliable output stream of a [`SessionSnapshot`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputSnapshot {
    /// Its stream id.
    pub stream_id: u8,
    /// The next number.
    pub next: u16,
    /// The messages not acknowledged yet (sequence number, whole message), if they were
    /// kept: then the client gets what it lacks again; without them, the stream asks the
    /// client where it is and goes on from there.
    pub in_flight: Option<Vec<(u16, Vec<u8>)>>,
    /// Submessages waiting for window room (not numbered yet), oldest first.
    pub queued: Vec<Vec<u8>>,
}

/// Why bytes are not a snapshot.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SnapshotError {
    /// Too short for what it says it holds.
    #[error("truncated session snapshot")]
    Truncated,
    /// Another version of the encoding.
    #[error("session snapshot version {0}, expected {VERSION}")]
    Version(u8),
    /// A value out of range.
    #[error("invalid session snapshot: {0}")]
    Invalid(&'static str),
}

impl SessionSnapshot {
    /// Encodes it.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(32 + self.endpoint.len());
        out.push(VERSION);
        out.extend_from_slice(&self.key.0);
        out.push(self.session_id);
        out.extend_from_slice(&self.mtu.to_le_bytes());
        out.push(match self.dialect {
            Dialect::Spec => 0,
            Dialect::Eprosima => 1,
        });
        let dead_ms = self
            .dead_time
            .map_or(u64::MAX, |d| d.as_millis().min(u64::MAX as u128 - 1) as u64);
        out.extend_from_slice(&dead_ms.to_le_bytes());
        out.extend_from_slice(&(self.endpoint.len() as u16).to_le_bytes());
        out.extend_from_slice(&self.endpoint);
        for streams in [
            &self.reliable_in,
            &self.best_effort_in,
            &self.best_effort_out,
        ] {
            let n = streams.len().min(MAX_STREAMS);
            out.extend_from_slice(&(n as u16).to_le_bytes());
            for (id, seq) in &streams[..n] {
                out.push(*id);
                out.extend_from_slice(&seq.to_le_bytes());
            }
        }
        let n = self.reliable_out.len().min(MAX_STREAMS);
        out.extend_from_slice(&(n as u16).to_le_bytes());
        for o in &self.reliable_out[..n] {
            out.push(o.stream_id);
            out.extend_from_slice(&o.next.to_le_bytes());
            match &o.in_flight {
                None => out.extend_from_slice(&u16::MAX.to_le_bytes()),
                Some(messages) => {
                    let m = messages.len().min(MAX_IN_FLIGHT);
                    out.extend_from_slice(&(m as u16).to_le_bytes());
                    for (seq, bytes) in &messages[..m] {
                        out.extend_from_slice(&seq.to_le_bytes());
                        out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
                        out.extend_from_slice(bytes);
                    }
                }
            }
            let mut bytes = 0;
            let q = o
                .queued
                .iter()
                .take(MAX_QUEUED)
                .take_while(|s| {
                    bytes += s.len();
                    bytes <= MAX_QUEUED_BYTES
                })
                .count();
            out.extend_from_slice(&(q as u32).to_le_bytes());
            for sub in &o.queued[..q] {
                out.extend_from_slice(&(sub.len() as u32).to_le_bytes());
                out.extend_from_slice(sub);
            }
        }
        out.extend_from_slice(&self.epoch.to_le_bytes());
        out
    }

    /// Decodes what [`Self::encode`] made.
    pub fn decode(bytes: &[u8]) -> Result<Self, SnapshotError> {
        let mut r = Reader(bytes);
        let version = r.u8()?;
        if version != VERSION && version != VERSION_WITHOUT_EPOCH {
            return Err(SnapshotError::Version(version));
        }
        let key = ClientKey(
            r.take(4)?
                .try_into()
                .map_err(|_| SnapshotError::Truncated)?,
        );
        let session_id = r.u8()?;
        let mtu = r.u16()?;
        let dialect = match r.u8()? {
            0 => Dialect::Spec,
            1 => Dialect::Eprosima,
            _ => return Err(SnapshotError::Invalid("dialect")),
        };
        let dead_ms = r.u64()?;
        let dead_time = (dead_ms != u64::MAX).then(|| Duration::from_millis(dead_ms));
        let len = r.u16()? as usize;
        let endpoint = r.take(len)?.to_vec();
        let mut lists: [Vec<(u8, u16)>; 3] = Default::default();
        for list in &mut lists {
            let n = r.u16()? as usize;
            if n > MAX_STREAMS {
                return Err(SnapshotError::Invalid("stream count"));
            }
            for _ in 0..n {
                list.push((r.u8()?, r.u16()?));
            }
        }
        let n = r.u16()? as usize;
        if n > MAX_STREAMS {
            return Err(SnapshotError::Invalid("stream count"));
        }
        let mut reliable_out = Vec::with_capacity(n);
        for _ in 0..n {
            let stream_id = r.u8()?;
            let next = r.u16()?;
            let in_flight = match r.u16()? {
                u16::MAX => None,
                m if m as usize > MAX_IN_FLIGHT => {
                    return Err(SnapshotError::Invalid("messages in flight"))
                }
                m => {
                    let mut messages = Vec::with_capacity(m as usize);
                    for _ in 0..m {
                        let seq = r.u16()?;
                        let len = r.u32()? as usize;
                        messages.push((seq, r.take(len)?.to_vec()));
                    }
                    Some(messages)
                }
            };
            let q = r.u32()? as usize;
            if q > MAX_QUEUED {
                return Err(SnapshotError::Invalid("queued submessages"));
            }
            let mut queued = Vec::with_capacity(q.min(64));
            for _ in 0..q {
                let len = r.u32()? as usize;
                queued.push(r.take(len)?.to_vec());
            }
            reliable_out.push(OutputSnapshot {
                stream_id,
                next,
                in_flight,
                queued,
            });
        }
        let epoch = if version == VERSION { r.u64()? } else { 0 };
        if !r.0.is_empty() {
            return Err(SnapshotError::Invalid("trailing bytes"));
        }
        let [reliable_in, best_effort_in, best_effort_out] = lists;
        Ok(SessionSnapshot {
            key,
            session_id,
            endpoint,
            mtu,
            dialect,
            dead_time,
            reliable_in,
            best_effort_in,
            reliable_out,
            best_effort_out,
            epoch,
        })
    }
}

struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], SnapshotError> {
        if self.0.len() < n {
            return Err(SnapshotError::Truncated);
        }
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Ok(head)
    }

    fn u8(&mut self) -> Result<u8, SnapshotError> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> Result<u16, SnapshotError> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&mut self) -> Result<u32, SnapshotError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> Result<u64, SnapshotError> {
        let b = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_le_bytes(a))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> SessionSnapshot {
        crate::fuzzing::example_snapshot()
    }

    #[test]
    fn a_snapshot_round_trips() {
        let s = sample();
        assert_eq!(SessionSnapshot::decode(&s.encode()), Ok(s.clone()));
        let none = SessionSnapshot {
            dead_time: None,
            dialect: Dialect::Spec,
            ..s
        };
        assert_eq!(SessionSnapshot::decode(&none.encode()), Ok(none));
    }

    /// A session a front-end of the version before stored is taken over, in no run of its
    /// streams the worker could know (epoch 0).
    #[test]
    fn a_snapshot_without_the_epoch_is_read_with_epoch_0() {
        let s = sample();
        let mut old = s.encode();
        old[0] = VERSION_WITHOUT_EPOCH;
        old.truncate(old.len() - 8);
        assert_eq!(
            SessionSnapshot::decode(&old),
            Ok(SessionSnapshot { epoch: 0, ..s })
        );
    }

    #[test]
    fn damaged_snapshots_are_refused_not_misread() {
        let bytes = sample().encode();
        for cut in 0..bytes.len() {
            assert!(
                SessionSnapshot::decode(&bytes[..cut]).is_err(),
                "cut at {cut}"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(SessionSnapshot::decode(&longer).is_err());
        let mut other = bytes;
        other[0] = 9;
        assert_eq!(
            SessionSnapshot::decode(&other),
            Err(SnapshotError::Version(9))
        );
    }
}
