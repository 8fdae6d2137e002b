//! Requesters and repliers: their DDS writer and reader pair, and how a request or a reply
//! goes out and comes back.

use super::*;

/// Most requests a requester keeps waiting for their reply (the oldest are forgotten).
pub(super) const PENDING_REQUESTS_MAX: usize = 4096;

/// The DDS side of an XRCE requester or replier.
pub(super) struct ServiceEndpoint {
    pub(super) requester: bool,
    pub(super) writer: RawWriter,
    pub(super) reader: RawReader,
    pub(super) token: Token,
    /// Requester: the sequence number of each published request -> its XRCE request id.
    pub(super) pending: HashMap<i64, xrce_common::wire::RequestId>,
    pub(super) pending_order: std::collections::VecDeque<i64>,
    pub(super) _publisher: Publisher,
    pub(super) _subscriber: Subscriber,
}

/// What a requester or replier client gets for a DDS sample: a replier the request's
/// SampleIdentity in front of it (24 bytes, the sample's byte order); a requester the
/// BaseObjectRequest of its own request in front of the reply, and only replies to its own
/// requests (`None` for the others), as eProsima's agent does.
pub(super) fn service_sample(
    requester: bool,
    writer: &RawWriter,
    pending: &mut HashMap<i64, xrce_common::wire::RequestId>,
    info: &rustdds::SampleInfo,
    object: ObjectId,
    s: RawSample,
) -> Option<RawSample> {
    let le = s.little_endian();
    let mut body = Vec::with_capacity(24 + s.body.len());
    if requester {
        let related = info.related_sample_identity()?;
        if related.writer_guid != writer.guid() {
            return None;
        }
        let request_id = pending.remove(&i64::from(related.sequence_number))?;
        body.extend_from_slice(&request_id.0);
        body.extend_from_slice(&object.0);
    } else {
        body.extend_from_slice(&crate::raw::encode_sample_identity(
            &info.sample_identity(),
            le,
        ));
    }
    body.extend_from_slice(&s.body);
    Some(RawSample {
        encoding: s.encoding,
        body: rustdds::bytes::Bytes::from(body),
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
        return Err((
            status::ERR_INVALID_DATA,
            "a sample in another byte order than the client's CREATE".into(),
        ));
    }
    let encoding = if little_endian {
        rustdds::RepresentationIdentifier::CDR_LE
    } else {
        rustdds::RepresentationIdentifier::CDR_BE
    };
    let dds = |e: String| (status::ERR_DDS_ERROR, format!("DDS write: {e}"));
    if svc.requester {
        let sample = RawSample {
            encoding,
            body: rustdds::bytes::Bytes::copy_from_slice(data),
        };
        let id = svc.writer.write_identified(sample, None).map_err(dds)?;
        let seq = i64::from(id.sequence_number);
        svc.pending.insert(seq, request_id);
        svc.pending_order.push_back(seq);
        while svc.pending_order.len() > PENDING_REQUESTS_MAX {
            if let Some(old) = svc.pending_order.pop_front() {
                svc.pending.remove(&old);
            }
        }
        Ok(())
    } else {
        let related = crate::raw::decode_sample_identity(data, little_endian).ok_or((
            status::ERR_INVALID_DATA,
            "a reply without the request's SampleIdentity".to_string(),
        ))?;
        let sample = RawSample {
            encoding,
            body: rustdds::bytes::Bytes::copy_from_slice(data.get(24..).unwrap_or_default()),
        };
        svc.writer
            .write_identified(sample, Some(related))
            .map(drop)
            .map_err(dds)
    }
}

impl Worker {
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
        let dds_err =
            |what: &str, e: &dyn std::fmt::Debug| (status::ERR_DDS_ERROR, format!("{what}: {e:?}"));
        let pub_dp = self
            .pool
            .get(domain, Role::Publish)
            .map_err(|e| (status::ERR_DDS_ERROR, e))?;
        let sub_dp = self
            .pool
            .get(domain, Role::Subscribe)
            .map_err(|e| (status::ERR_DDS_ERROR, e))?;
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
        let qos_desc = crate::xml::QosDesc {
            reliability: Some(crate::xml::Reliability::Reliable),
            durability: Some(crate::xml::Durability::Volatile),
            ..Default::default()
        };
        let make = |dp: &DomainParticipant, name: &str, type_name: &str| {
            dp.create_topic(
                name.to_string(),
                type_name.to_string(),
                &QosPolicies::qos_none(),
                TopicKind::NoKey,
            )
            .map_err(|e| dds_err("create topic", &e))
        };
        let publisher = pub_dp
            .create_publisher(&QosPolicies::qos_none())
            .map_err(|e| dds_err("create publisher", &e))?;
        let subscriber = sub_dp
            .create_subscriber(&QosPolicies::qos_none())
            .map_err(|e| dds_err("create subscriber", &e))?;
        let wt = make(&pub_dp, out_topic, out_type)?;
        let rt = make(&sub_dp, in_topic, in_type)?;
        let wq = endpoint_qos(
            EndpointSide::Writer,
            &qos_desc,
            &crate::xml::QosDesc::default(),
        );
        let rq = endpoint_qos(
            EndpointSide::Reader,
            &qos_desc,
            &crate::xml::QosDesc::default(),
        );
        let writer = RawWriter::create(&publisher, &wt, wq, little_endian, None)
            .map_err(|e| dds_err("create data writer", &e))?;
        let mut reader = RawReader::create(&subscriber, &rt, rq, None)
            .map_err(|e| dds_err("create data reader", &e))?;
        let token = Token(self.next_token);
        self.next_token += 1;
        self.poll
            .registry()
            .register(&mut reader, token, Interest::READABLE)
            .map_err(|e| dds_err("register reader", &e))?;
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
}
