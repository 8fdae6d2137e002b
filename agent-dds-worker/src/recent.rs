//! Samples recently handed to a front-end, for its successor.
//!
//! A sample the worker took from a DDS reader and published to a front-end is gone from the
//! reader. If that front-end process dies before it delivered the sample to its client (the
//! sample still in its queue, or not yet sent because its queue was full), the successor
//! that takes the session over would never see it. So the worker keeps the last samples it
//! handed to each front-end, and when a successor replays a read it sends that read's again
//! (the samples taken for the same read request, so a read the client started afresh gets
//! none of an earlier one's); the front-end drops those its predecessor had delivered (it
//! stores the identity of the last sample delivered from each writer before it transmits).
//! At most [`RECENT_MAX`] samples and [`RECENT_MAX_BYTES`] are kept per front-end: more than
//! its reply queue holds ([`xrce_ipc::CHANNEL_DEPTH`]) for samples up to 16 KiB;
//! of larger samples fewer than can be in flight are kept (the newest).

use std::borrow::Cow;
use std::collections::VecDeque;

use xrce_common::wire::RequestId;
use xrce_ipc::Sample;

use crate::adoption::EntityKey;

/// Most samples kept per front-end.
pub const RECENT_MAX: usize = 2 * xrce_ipc::CHANNEL_DEPTH;
/// Most bytes of samples kept per front-end.
pub const RECENT_MAX_BYTES: usize = 4 << 20;

/// One sample as it was handed over.
#[derive(Debug)]
struct Recent {
    key: EntityKey,
    /// The read request it was taken for.
    request: RequestId,
    sample: Sample<'static>,
}

impl Recent {
    fn len(&self) -> usize {
        self.sample.data.len()
    }
}

/// The last samples handed to one front-end, oldest first.
#[derive(Debug, Default)]
pub struct RecentSamples {
    entries: VecDeque<Recent>,
    bytes: usize,
}

impl RecentSamples {
    /// Keeps a sample of reader `key` taken for read `request`, forgetting the oldest beyond
    /// the bounds; a sample larger than the byte bound is not kept.
    pub fn record(&mut self, key: EntityKey, request: RequestId, sample: &Sample<'_>) {
        let len = sample.data.len();
        if len > RECENT_MAX_BYTES {
            return;
        }
        let mut reused = None;
        while self.entries.len() >= RECENT_MAX || self.bytes + len > RECENT_MAX_BYTES {
            let Some(old) = self.entries.pop_front() else {
                break;
            };
            self.bytes -= old.len();
            reused = Some(old.sample.data.into_owned());
        }
        // The evicted sample's buffer holds the new one (no allocation per sample once full),
        // unless it is much larger: a large sample's buffer would otherwise circulate under
        // small ones, and the memory held would grow past what `bytes` counts.
        let mut data = reused
            .filter(|b| b.capacity() <= 2 * len.max(64))
            .unwrap_or_default();
        data.clear();
        data.extend_from_slice(&sample.data);
        self.bytes += data.len();
        self.entries.push_back(Recent {
            key,
            request,
            sample: Sample {
                data: Cow::Owned(data),
                ..*sample
            },
        });
    }

    /// The kept samples of reader `key` taken for read `request`, oldest first.
    pub fn of(&self, key: &EntityKey, request: RequestId) -> Vec<Sample<'static>> {
        self.entries
            .iter()
            .filter(|r| r.key == *key && r.request == request)
            .map(|r| r.sample.clone())
            .collect()
    }

    /// Forgets the samples of reader `key` (it was deleted, or a new read starts on it whose
    /// client has no record of them).
    pub fn forget(&mut self, key: &EntityKey) {
        let mut bytes = self.bytes;
        self.entries.retain(|r| {
            let keep = r.key != *key;
            if !keep {
                bytes -= r.len();
            }
            keep
        });
        self.bytes = bytes;
    }

    /// How many samples are kept.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether none is.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Bytes kept.
    pub fn bytes(&self) -> usize {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_common::wire::{ClientKey, ObjectId};
    use xrce_ipc::SampleIdentity;

    fn key(n: u16) -> EntityKey {
        (0, ClientKey([1, 2, 3, 4]), ObjectId::new(n, 6))
    }

    const READ: RequestId = RequestId([0, 7]);

    fn sample(seq: i64, data: &[u8]) -> Sample<'_> {
        Sample {
            identity: SampleIdentity {
                writer: [1; 16],
                sequence_number: seq,
            },
            origin: None,
            data: Cow::Borrowed(data),
            little_endian: seq % 2 == 0,
            disposed: seq == 3,
            unregistered: false,
        }
    }

    #[test]
    fn the_samples_of_a_reader_come_back_in_order() {
        let mut r = RecentSamples::default();
        r.record(key(1), READ, &sample(1, b"a"));
        r.record(key(2), READ, &sample(2, b"b"));
        r.record(key(1), READ, &sample(3, b"c"));
        assert_eq!(r.of(&key(1), READ), vec![sample(1, b"a"), sample(3, b"c")]);
        assert!(
            r.of(&key(1), RequestId([0, 8])).is_empty(),
            "another read request gets none"
        );
        r.forget(&key(1));
        assert!(r.of(&key(1), READ).is_empty());
        assert_eq!(r.len(), 1);
        assert_eq!(r.bytes(), 1);
    }

    #[test]
    fn the_oldest_go_beyond_the_count_and_the_byte_bounds() {
        let mut r = RecentSamples::default();
        for i in 0..RECENT_MAX + 10 {
            r.record(key(1), READ, &sample(0, &(i as u32).to_le_bytes()));
        }
        assert_eq!(r.len(), RECENT_MAX);
        let first = r.of(&key(1), READ)[0].data.to_vec();
        assert_eq!(first, 10u32.to_le_bytes().to_vec());
        let big = vec![7u8; RECENT_MAX_BYTES / 2 + 1];
        r.record(key(2), READ, &sample(0, &big));
        r.record(key(2), READ, &sample(0, &big));
        assert!(r.bytes() <= RECENT_MAX_BYTES);
        assert_eq!(r.of(&key(2), READ).len(), 1, "the older large sample went");
        r.record(key(3), READ, &sample(0, &vec![0u8; RECENT_MAX_BYTES + 1]));
        assert!(
            r.of(&key(3), READ).is_empty(),
            "a sample above the bound is not kept"
        );
    }

    #[test]
    fn a_large_buffer_is_not_reused_for_small_samples() {
        let mut r = RecentSamples::default();
        r.record(key(1), READ, &sample(0, &vec![1u8; 1 << 20]));
        for _ in 0..RECENT_MAX {
            r.record(key(1), READ, &sample(0, b"small"));
        }
        let held: usize = r
            .entries
            .iter()
            .map(|e| match &e.sample.data {
                Cow::Owned(v) => v.capacity(),
                Cow::Borrowed(b) => b.len(),
            })
            .sum();
        assert!(
            held < 256 * RECENT_MAX,
            "{held} bytes held for small samples"
        );
    }
}
