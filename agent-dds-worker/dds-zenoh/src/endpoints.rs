//! The Zenoh backend's writers and readers as the worker uses them ([`DdsWriter`],
//! [`DdsReader`]), and the payloads and attachments they send and receive.

use std::sync::Arc;

use bytes::Bytes;
use zenoh::Wait as _;

use super::inbox::{lock, Inbox};
use super::naming::Attachment;
use super::services::{self, ServiceLink};
use super::{count_drop, zenoh_err, Dropped, GraphEntry};
use xrce_dds_seam::types::KeyDescriptor;
use xrce_dds_seam::{
    BackendError, DdsReader, DdsWriter, Encoding, Guid, Sample, SampleIdentity, Taken,
};

/// How a writer sends.
pub(super) enum Sender {
    /// A topic's advanced publisher.
    Publisher(zenoh_ext::AdvancedPublisher<'static>),
    /// A requester's querier: a request is a query; replies go to the link's reader.
    Querier(zenoh::query::Querier<'static>, Arc<ServiceLink>),
    /// A replier's writer: a reply answers the pending query of its request.
    Replies(zenoh::key_expr::KeyExpr<'static>, Arc<ServiceLink>),
}

/// A client's data writer, requester or replier, as Zenoh sends its samples.
pub(super) struct Writer {
    pub(super) sender: Sender,
    pub(super) gid: Guid,
    pub(super) topic_name: String,
    pub(super) little_endian: bool,
    pub(super) key: Option<Arc<KeyDescriptor>>,
    pub(super) seq: std::cell::Cell<i64>,
    pub(super) _graph: Option<GraphEntry>,
    pub(super) dropped: Arc<Dropped>,
}

/// What keeps a reader's Zenoh side alive.
pub(super) enum Receiver {
    Subscriber(#[allow(dead_code)] zenoh_ext::AdvancedSubscriber<()>),
    Queryable(#[allow(dead_code)] zenoh::query::Queryable<()>),
    /// A requester's reader: replies come through the link.
    Replies(Arc<ServiceLink>),
}

/// A client's data reader, requester or replier, with the queue its samples wait in.
pub(super) struct Reader {
    pub(super) inbox: Arc<Inbox>,
    pub(super) gid: Guid,
    pub(super) receiver: Receiver,
    pub(super) _graph: Option<GraphEntry>,
}

pub(super) fn now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

/// The payload rmw_zenoh sends: the CDR encapsulation header, then the body.
pub(super) fn payload(sample: &Sample) -> Vec<u8> {
    let mut p = Vec::with_capacity(4 + sample.body.len());
    p.extend_from_slice(&sample.encoding.0);
    p.extend_from_slice(&[0, 0]);
    p.extend_from_slice(&sample.body);
    p
}

/// A received payload as a sample: its encapsulation header read, the body after it.
pub(super) fn sample_of(payload: &[u8]) -> Result<Sample, BackendError> {
    match payload {
        [a, b, _, _, body @ ..] => Ok(Sample {
            encoding: Encoding([*a, *b]),
            body: Bytes::copy_from_slice(body),
        }),
        _ => Err(BackendError::InvalidInput(format!(
            "a Zenoh payload of {} bytes, shorter than a CDR encapsulation header",
            payload.len()
        ))),
    }
}

pub(super) fn taken_of(
    payload: &[u8],
    attachment: Option<Attachment>,
    related: Option<SampleIdentity>,
) -> Result<Taken, BackendError> {
    let sample = sample_of(payload)?;
    let identity = attachment
        .map(|a| SampleIdentity {
            writer: a.gid,
            sequence_number: a.sequence_number,
        })
        .unwrap_or_default();
    Ok(Taken {
        sample,
        identity,
        related,
        disposed: false,
        unregistered: false,
    })
}

pub(super) fn attachment_of(bytes: Option<&zenoh::bytes::ZBytes>) -> Option<Attachment> {
    bytes.and_then(|b| Attachment::decode(&b.to_bytes()))
}

impl Writer {
    fn attachment(&self, sequence_number: i64) -> zenoh::bytes::ZBytes {
        let a = Attachment {
            sequence_number,
            source_timestamp: now_ns(),
            gid: self.gid,
        };
        zenoh::bytes::ZBytes::from(a.encode().to_vec())
    }
}

impl DdsWriter for Writer {
    fn guid(&self) -> Guid {
        self.gid
    }
    fn topic_name(&self) -> &str {
        &self.topic_name
    }
    fn little_endian(&self) -> bool {
        self.little_endian
    }
    fn key(&self) -> Option<&Arc<KeyDescriptor>> {
        self.key.as_ref()
    }
    fn write(&self, sample: Sample) -> Result<(), BackendError> {
        self.write_identified(sample, None).map(drop)
    }
    fn dispose(&self, _sample: &Sample) -> Result<(), BackendError> {
        Err(BackendError::Unsupported(
            "Zenoh has no instances to dispose (ROS topics have no keys)",
        ))
    }
    fn write_identified(
        &self,
        sample: Sample,
        related: Option<SampleIdentity>,
    ) -> Result<SampleIdentity, BackendError> {
        let seq = self.seq.get() + 1;
        match &self.sender {
            Sender::Publisher(p) => {
                p.put(payload(&sample))
                    .attachment(self.attachment(seq))
                    .wait()
                    .map_err(zenoh_err("Zenoh put"))?;
            }
            Sender::Querier(querier, link) => {
                let Some(in_flight) = link.start_request() else {
                    count_drop(
                        &self.dropped.requests_refused_in_flight,
                        "a requester has 4,096 requests in flight in Zenoh: its writes are refused",
                    );
                    return Err(BackendError::Dds(format!(
                        "{} requests already wait for their replies in Zenoh",
                        services::IN_FLIGHT_MAX
                    )));
                };
                let link = link.clone();
                // The request this query carries: its replies answer it, whatever a replier
                // puts in their attachments.
                let related = SampleIdentity {
                    writer: self.gid,
                    sequence_number: seq,
                };
                querier
                    .get()
                    .payload(payload(&sample))
                    .attachment(self.attachment(seq))
                    .callback(move |reply: zenoh::query::Reply| {
                        let _in_flight = &in_flight;
                        let Ok(s) = reply.result() else { return };
                        let Some(inbox) = lock(&link.replies).clone() else {
                            return;
                        };
                        // The reply's own identity stays unknown: replies may come in any
                        // order, which the front-end would take for repeats.
                        inbox.push(taken_of(&s.payload().to_bytes(), None, Some(related)));
                    })
                    .wait()
                    .map_err(zenoh_err("Zenoh query"))?;
            }
            Sender::Replies(key, link) => {
                let related = related.ok_or(BackendError::InvalidInput(
                    "a reply without the request it answers".into(),
                ))?;
                let query = lock(&link.queries).take(&(related.writer, related.sequence_number));
                let Some(query) = query else {
                    count_drop(
                        &self.dropped.replies_without_request,
                        "a reply to a Zenoh request no longer waiting (answered or evicted): dropped",
                    );
                    tracing::debug!(
                        seq = related.sequence_number,
                        "a reply to a request no longer waiting (answered, timed out or \
                         evicted): dropped"
                    );
                    return Ok(SampleIdentity {
                        writer: self.gid,
                        sequence_number: seq,
                    });
                };
                let a = Attachment {
                    sequence_number: related.sequence_number,
                    source_timestamp: now_ns(),
                    gid: related.writer,
                };
                query
                    .reply(key.clone(), payload(&sample))
                    .attachment(zenoh::bytes::ZBytes::from(a.encode().to_vec()))
                    .wait()
                    .map_err(zenoh_err("Zenoh reply"))?;
            }
        }
        self.seq.set(seq);
        Ok(SampleIdentity {
            writer: self.gid,
            sequence_number: seq,
        })
    }
    fn all_acknowledged(&self) -> bool {
        // Zenoh has no acknowledgements to wait for: a put is done once sent.
        true
    }
    fn writes(&self) -> u64 {
        u64::try_from(self.seq.get()).unwrap_or(0)
    }
    fn last_sequence_number(&self) -> Option<i64> {
        // The number in the attachment, which the agent's own subscribers see.
        Some(self.seq.get())
    }
    fn acknowledged_writes(&self) -> u64 {
        self.writes()
    }
    fn matched_readers(&self) -> usize {
        let matching = match &self.sender {
            Sender::Publisher(p) => p.matching_status().wait().map(|m| m.matching()),
            Sender::Querier(q, _) => q.matching_status().wait().map(|m| m.matching()),
            Sender::Replies(..) => Ok(true),
        };
        usize::from(matching.unwrap_or(false))
    }
}

impl Drop for Reader {
    fn drop(&mut self) {
        if let Receiver::Replies(link) = &self.receiver {
            lock(&link.replies).take();
        }
    }
}

impl DdsReader for Reader {
    fn guid(&self) -> Guid {
        self.gid
    }
    fn take_next(&mut self) -> Result<Option<Taken>, BackendError> {
        self.inbox.pop().transpose()
    }
}
