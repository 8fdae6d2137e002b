//! What the simulated clients send: their entities' bodies, tagged samples and the pacing
//! of one publishing thread.

use std::time::{Duration, Instant};

use xrce_common::wire::binary::{
    qos_flags, EndpointBinary, EndpointBinaryQos, EndpointQosBinary, GroupBinary,
    ParticipantBinary, TopicBinary,
};
use xrce_common::wire::{object_kind as k, stream_id, ObjectId, Representation};

use crate::peer::Group;
use crate::soak::Track;
use crate::{Args, Creation};

/// Sequence numbers of warm-up samples start here (measured ones are below `--samples`,
/// probes at the top of the range).
pub(super) const WARMUP_TAG: u32 = 0x8000_0000;

pub(super) const PARTICIPANT: ObjectId = ObjectId::new(1, k::PARTICIPANT);
pub(super) const TOPIC: ObjectId = ObjectId::new(1, k::TOPIC);
pub(super) const PUBLISHER: ObjectId = ObjectId::new(1, k::PUBLISHER);
pub(super) const SUBSCRIBER: ObjectId = ObjectId::new(1, k::SUBSCRIBER);
pub(super) const WRITER: ObjectId = ObjectId::new(1, k::DATAWRITER);
pub(super) const READER: ObjectId = ObjectId::new(1, k::DATAREADER);

/// The CREATE representations of one client's entities, in the scenario's creation mode.
pub(super) struct Bodies {
    pub(super) participant: Representation,
    pub(super) topic: Representation,
    pub(super) group: Representation,
    pub(super) writer: Representation,
    pub(super) reader: Representation,
}

impl Bodies {
    pub(super) fn new(a: &Args) -> Self {
        match a.creation {
            Creation::Xml => {
                let history = if a.history == 0 {
                    "<kind>KEEP_ALL</kind>".to_string()
                } else {
                    format!("<kind>KEEP_LAST</kind><depth>{}</depth>", a.history)
                };
                // The DDS endpoints follow the scenario: reliable, or best-effort end to end.
                let reliability = if a.best_effort {
                    "BEST_EFFORT"
                } else {
                    "RELIABLE"
                };
                // Fast DDS's form (what the reference agent parses): the history inside the
                // endpoint's <topic>, reliability and durability inside its <qos>.
                let endpoint = |e: &str| {
                    Representation::Xml(format!(
                        "<dds><{e}><topic><kind>NO_KEY</kind><name>LoadTopic</name><dataType>Load</dataType><historyQos>{history}</historyQos></topic><qos><reliability><kind>{reliability}</kind></reliability><durability><kind>VOLATILE</kind></durability></qos></{e}></dds>"
                    ))
                };
                Bodies {
                    participant: Representation::Xml(
                        "<dds><participant><rtps><name>load</name></rtps></participant></dds>"
                            .into(),
                    ),
                    topic: Representation::Xml(
                        "<dds><topic><name>LoadTopic</name><dataType>Load</dataType></topic></dds>"
                            .into(),
                    ),
                    group: Representation::Xml(String::new()),
                    writer: endpoint("data_writer"),
                    reader: endpoint("data_reader"),
                }
            }
            Creation::Binary => {
                let mut flags = 0;
                if !a.best_effort {
                    flags |= qos_flags::RELIABLE;
                }
                if a.history > 0 {
                    flags |= qos_flags::HISTORY_KEEP_LAST;
                }
                let endpoint = EndpointBinary {
                    topic_id: TOPIC,
                    qos: Some(EndpointBinaryQos {
                        base: EndpointQosBinary {
                            flags,
                            history_depth: (a.history > 0)
                                .then(|| u16::try_from(a.history).unwrap_or(u16::MAX)),
                            ..EndpointQosBinary::default()
                        },
                        ..EndpointBinaryQos::default()
                    }),
                };
                Bodies {
                    participant: Representation::Binary(
                        ParticipantBinary {
                            domain_reference: None,
                            qos_profile_reference: Some("load".into()),
                        }
                        .encode(true),
                    ),
                    topic: Representation::Binary(
                        TopicBinary {
                            topic_name: "LoadTopic".into(),
                            type_reference: None,
                            type_name: Some("Load".into()),
                        }
                        .encode(true),
                    ),
                    group: Representation::Binary(GroupBinary::default().encode(true)),
                    writer: Representation::Binary(endpoint.encode(true, true)),
                    reader: Representation::Binary(endpoint.encode(false, true)),
                }
            }
        }
    }
}

/// CPU seconds the calling thread has used.
pub(super) fn thread_cpu_seconds() -> f64 {
    use nix::time::{clock_gettime, ClockId};
    clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map_or(0.0, |t| t.tv_sec() as f64 + t.tv_nsec() as f64 * 1e-9)
}

/// A sample: its sequence number and send time (ns since `base`), then zeros.
pub(super) fn sample(payload: usize, seq: u32, base: Instant) -> Vec<u8> {
    let mut v = vec![0u8; payload];
    v[0..4].copy_from_slice(&seq.to_le_bytes());
    v[4..12].copy_from_slice(&(base.elapsed().as_nanos() as u64).to_le_bytes());
    v
}

/// The sequence number and send time of a received sample.
pub(super) fn tag(data: &[u8]) -> Option<(u32, u64)> {
    let seq = u32::from_le_bytes(data.get(0..4)?.try_into().ok()?);
    let ts = u64::from_le_bytes(data.get(4..12)?.try_into().ok()?);
    Some((seq, ts))
}

/// What each sample sent is: its stream, its payload's size, and the instant its timestamp
/// counts from.
#[derive(Debug, Clone, Copy)]
pub(super) struct SampleForm {
    pub(super) stream: u8,
    pub(super) payload: usize,
    pub(super) base: Instant,
}

/// What a group of publishers sends in the measured phase: the sequence numbers
/// `first, first + step, …` below `samples`, paced at `rate` (0 = unpaced).
pub(super) struct Share {
    pub(super) next: u32,
    pub(super) step: u32,
    pub(super) samples: u32,
    pub(super) rate: f64,
    pub(super) sent: u32,
    /// The publisher (index in the group) to use next.
    pub(super) next_pub: usize,
}

impl Share {
    pub(super) fn done(&self) -> bool {
        self.next >= self.samples
    }

    /// When the next sample is due (None: all sent or unpaced).
    pub(super) fn next_due(&self, t0: Instant) -> Option<Instant> {
        (self.rate > 0.0 && !self.done())
            .then(|| t0 + Duration::from_secs_f64(f64::from(self.sent + 1) / self.rate))
    }

    /// How long the group may wait for data before its next send: until the next sample is
    /// due, but at least 1 ms (then the samples due by then go out together), or not at all
    /// when unpaced.
    pub(super) fn wait(&self, t0: Instant) -> Duration {
        if self.done() {
            return Duration::from_millis(1);
        }
        match self.next_due(t0) {
            None => Duration::ZERO,
            Some(t) => t
                .saturating_duration_since(Instant::now())
                .max(Duration::from_millis(1)),
        }
    }

    /// Sends what is due by now (at most 64 per call), round robin over `pubs`.
    pub(super) fn send_due(
        &mut self,
        group: &mut Group,
        pubs: std::ops::Range<usize>,
        t0: Instant,
        form: SampleForm,
        track: Option<(&Track, u32)>,
    ) {
        let SampleForm {
            stream,
            payload,
            base,
        } = form;
        if pubs.is_empty() {
            return;
        }
        let allowed = if self.rate > 0.0 {
            (t0.elapsed().as_secs_f64() * self.rate) as u32
        } else {
            u32::MAX
        };
        let mut tries = 0;
        let mut burst = 0;
        while !self.done() && self.sent < allowed && tries < pubs.len() && burst < 64 {
            if self.next_pub < pubs.start || self.next_pub >= pubs.end {
                self.next_pub = pubs.start;
            }
            let i = self.next_pub;
            self.next_pub += 1;
            if stream == stream_id::BUILTIN_RELIABLE
                && !group.peers[i].client.can_send_reliable(stream)
            {
                tries += 1;
                continue;
            }
            tries = 0;
            group.write(i, stream, WRITER, &sample(payload, self.next, base));
            if let Some((t, thread)) = track {
                t.sent(
                    self.next,
                    (thread << 16) | i as u32,
                    base.elapsed().as_nanos() as u64,
                );
            }
            self.next += self.step;
            self.sent += 1;
            burst += 1;
        }
    }
}
