//! Requesters and repliers: their DDS writer and reader pair, and how a request or a reply
//! goes out and comes back.

use super::*;

/// Most requests a requester keeps waiting for their reply (the oldest are forgotten).
pub(super) const PENDING_REQUESTS_MAX: usize = 4096;

/// The DDS side of an XRCE requester or replier.
pub(super) struct ServiceEndpoint {
    pub(super) requester: bool,
    pub(super) writer: Box<dyn backend::DdsWriter>,
    pub(super) reader: Box<dyn DdsReader>,
    pub(super) token: ReaderToken,
    /// Requester: the sequence number of each published request -> its XRCE request id.
    pub(super) pending: HashMap<i64, xrce_common::wire::RequestId>,
    pub(super) pending_order: std::collections::VecDeque<i64>,
    pub(super) _publisher: backend::Publisher,
    pub(super) _subscriber: backend::Subscriber,
}

/// What a requester or replier client gets for a DDS sample: a replier the request's
/// SampleIdentity in front of it (24 bytes, the sample's byte order); a requester the
/// BaseObjectRequest of its own request in front of the reply, and only replies to its own
/// requests (`None` for the others), as eProsima's agent does.
pub(super) fn service_sample(
    requester: bool,
    writer: &dyn backend::DdsWriter,
    pending: &mut HashMap<i64, xrce_common::wire::RequestId>,
    taken: &backend::Taken,
    object: ObjectId,
    s: Sample,
) -> Option<Sample> {
    let le = s.little_endian();
    let mut body = Vec::with_capacity(24 + s.body.len());
    if requester {
        let related = taken.related?;
        if related.writer != writer.guid() {
            return None;
        }
        let request_id = pending.remove(&related.sequence_number)?;
        body.extend_from_slice(&request_id.0);
        body.extend_from_slice(&object.0);
    } else {
        body.extend_from_slice(&backend::encode_sample_identity(&taken.identity, le));
    }
    body.extend_from_slice(&s.body);
    Some(Sample {
        encoding: s.encoding,
        body: bytes::Bytes::from(body),
    })
}

/// A WRITE_DATA to a requester (a request: remembered with its XRCE request id, so the reply
/// finds its way back) or to a replier (a reply: the request's SampleIdentity first).
pub(super) fn service_write(
    svc: &mut ServiceEndpoint,
    request_id: xrce_common::wire::RequestId,
    little_endian: bool,
    data: &[u8],
) -> Result<(), OpError> {
    if little_endian != svc.writer.little_endian() {
        return Err(OpError::InvalidData(
            "a sample in another byte order than the client's CREATE".into(),
        ));
    }
    let dds = |e: BackendError| OpError::from(e.context("DDS write"));
    if svc.requester {
        let sample = Sample::cdr(little_endian, data);
        let id = svc.writer.write_identified(sample, None).map_err(dds)?;
        let seq = id.sequence_number;
        svc.pending.insert(seq, request_id);
        svc.pending_order.push_back(seq);
        while svc.pending_order.len() > PENDING_REQUESTS_MAX {
            if let Some(old) = svc.pending_order.pop_front() {
                svc.pending.remove(&old);
            }
        }
        Ok(())
    } else {
        let related = backend::decode_sample_identity(data, little_endian).ok_or(
            OpError::InvalidData("a reply without the request's SampleIdentity".to_string()),
        )?;
        let sample = Sample::cdr(little_endian, data.get(24..).unwrap_or_default());
        svc.writer
            .write_identified(sample, Some(related))
            .map(drop)
            .map_err(dds)
    }
}

impl<L: WorkerLink> Worker<L> {
    /// The writer and reader of a requester or replier, on the DDS participants of `domain`.
    /// Both are reliable and volatile (as RPC over DDS); the writer publishes in the
    /// client's byte order.
    pub(super) fn create_service(
        &mut self,
        desc: &crate::xml::ServiceDesc,
        domain: u16,
        requester: bool,
        little_endian: bool,
    ) -> Result<ServiceEndpoint, OpError> {
        let dds_err = OpError::from;
        let token = self.readers.new_token();
        let dds = self.services_backend()?;
        let (out_topic, out_type, in_topic, in_type) = if requester {
            (
                &desc.request_topic,
                &desc.request_type,
                &desc.reply_topic,
                &desc.reply_type,
            )
        } else {
            (
                &desc.reply_topic,
                &desc.reply_type,
                &desc.request_topic,
                &desc.request_type,
            )
        };
        let spec = |name: &str, type_name: &str| TopicSpec {
            name: name.to_string(),
            type_name: type_name.to_string(),
            key: None,
        };
        let publisher = dds.create_publisher(domain, &[]).map_err(dds_err)?;
        let subscriber = dds.create_subscriber(domain, &[]).map_err(dds_err)?;
        let writer = dds
            .create_writer(
                &publisher,
                &spec(out_topic, out_type),
                &EndpointQos::service(EndpointSide::Writer),
                little_endian,
            )
            .map_err(dds_err)?;
        let reader = dds
            .create_reader(
                &subscriber,
                &spec(in_topic, in_type),
                &EndpointQos::service(EndpointSide::Reader),
                token,
            )
            .map_err(dds_err)?;
        Ok(ServiceEndpoint {
            requester,
            writer,
            reader,
            token,
            pending: HashMap::new(),
            pending_order: std::collections::VecDeque::new(),
            _publisher: publisher,
            _subscriber: subscriber,
        })
    }

    /// The backend requesters and repliers go through: the worker's own if it can serve
    /// them, otherwise the one [`backend::for_services`] makes beside it (once).
    fn services_backend(&mut self) -> Result<&mut dyn DdsBackend, OpError> {
        if self.dds.supports_services() {
            return Ok(&mut *self.dds);
        }
        if self.services_dds.is_none() {
            let beside = backend::for_services(&self.config.dds).map_err(|e| {
                OpError::Dds(format!("no DDS backend for requesters and repliers: {e:#}"))
            })?;
            tracing::info!(
                backend = beside.name(),
                beside = self.dds.name(),
                "requesters and repliers go through a backend of their own"
            );
            self.services_dds = Some(beside);
        }
        match self.services_dds.as_deref_mut() {
            Some(dds) => Ok(dds),
            None => Err(OpError::Dds("no DDS backend for services".into())),
        }
    }
}
