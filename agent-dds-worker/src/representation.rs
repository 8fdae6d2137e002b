//! Reading the representation of a CREATE (XML, binary, or a reference to a profile of the
//! references file) into the descriptions the worker maps to DDS.

use xrce_common::wire::{object_kind, status, Representation};

use crate::binary;
use crate::references::References;
use crate::xml::{self, TopicDesc};

/// Why an operation failed: each variant is the XRCE status the client gets (STATUS_ERR_...),
/// with what went wrong for the log.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OpError {
    /// STATUS_ERR_INVALID_DATA: a representation, sample or read the worker cannot read.
    #[error("{0}")]
    InvalidData(String),
    /// STATUS_ERR_UNKNOWN_REFERENCE: an object, profile or type not there.
    #[error("{0}")]
    UnknownReference(String),
    /// STATUS_ERR_INCOMPATIBLE: an operation this object does not take.
    #[error("{0}")]
    Incompatible(String),
    /// STATUS_ERR_MISMATCH: an object that exists with another description.
    #[error("{0}")]
    Mismatch(String),
    /// STATUS_ERR_RESOURCES: one of the worker's bounds (counted where decided).
    #[error("{0}")]
    Resources(String),
    /// STATUS_ERR_DENIED: refused by the configuration (a domain not allowed).
    #[error("{0}")]
    Denied(String),
    /// STATUS_ERR_DDS_ERROR: the DDS implementation failed.
    #[error("{0}")]
    Dds(String),
}

impl OpError {
    /// The XRCE status the client gets.
    pub fn status(&self) -> u8 {
        match self {
            OpError::InvalidData(_) => status::ERR_INVALID_DATA,
            OpError::UnknownReference(_) => status::ERR_UNKNOWN_REFERENCE,
            OpError::Incompatible(_) => status::ERR_INCOMPATIBLE,
            OpError::Mismatch(_) => status::ERR_MISMATCH,
            OpError::Resources(_) => status::ERR_RESOURCES,
            OpError::Denied(_) => status::ERR_DENIED,
            OpError::Dds(_) => status::ERR_DDS_ERROR,
        }
    }

    /// Whether it is a refusal of one of the worker's bounds or of its configuration (which
    /// a client causes at will: logged once per episode where it is decided, not per reply).
    pub fn is_refusal(&self) -> bool {
        matches!(self, OpError::Resources(_) | OpError::Denied(_))
    }
}

impl From<crate::backend::BackendError> for OpError {
    /// Input the backend could not take is the client's fault (INVALID_DATA); anything else
    /// is DDS's (DDS_ERROR).
    fn from(e: crate::backend::BackendError) -> Self {
        match e {
            crate::backend::BackendError::InvalidInput(m) => OpError::InvalidData(m),
            other => OpError::Dds(other.to_string()),
        }
    }
}

fn invalid_xml(e: xml::XmlError) -> OpError {
    OpError::InvalidData(e.to_string())
}

fn invalid_binary(e: xrce_common::wire::DecodeError) -> OpError {
    OpError::InvalidData(format!("binary representation: {e}"))
}

/// The XML a representation stands for: its own, or the referenced profile's.
fn as_xml<'a>(
    repr: &'a Representation,
    refs: &'a References,
    element: &str,
) -> Result<Option<&'a str>, OpError> {
    match repr {
        Representation::Xml(x) => Ok(Some(x)),
        Representation::Reference(r) => refs
            .resolve(r, element)
            .map(Some)
            .map_err(OpError::UnknownReference),
        Representation::Binary(_) => Ok(None),
    }
}

/// Checks the representation of a participant, publisher or subscriber (whose settings the
/// worker takes from elsewhere: publishers and subscribers from their endpoints, and the
/// reference client sends them an empty string); returns the partitions a publisher or
/// subscriber names (none for a participant, or the default partition).
pub fn check_plain(
    repr: &Representation,
    kind: u8,
    refs: &References,
    little_endian: bool,
) -> Result<Vec<String>, OpError> {
    let participant = kind == object_kind::PARTICIPANT;
    let element = if participant {
        "participant"
    } else if kind == object_kind::PUBLISHER {
        "publisher"
    } else {
        "subscriber"
    };
    match (as_xml(repr, refs, element)?, repr) {
        (Some(x), _) if participant => xml::parse_participant(x)
            .map(|_| Vec::new())
            .map_err(invalid_xml),
        // The reference client sends publishers and subscribers an empty string; what parses
        // is read for partitions, the one group policy that matters here.
        (Some(x), _) => Ok(xml::group_partitions(x, element).unwrap_or_default()),
        (None, Representation::Binary(b)) if participant => {
            binary::parse_participant(b, little_endian)
                .map(|_| Vec::new())
                .map_err(invalid_binary)
        }
        (None, Representation::Binary(b)) => {
            binary::parse_publisher_or_subscriber(b, little_endian).map_err(invalid_binary)
        }
        (None, _) => Ok(Vec::new()),
    }
}

/// The name a participant was created with (XML `<name>`, or the binary form's
/// `qos_profile_reference`, where eProsima's client puts it), if any.
pub fn participant_name(
    repr: &Representation,
    refs: &References,
    little_endian: bool,
) -> Option<String> {
    let name = match repr {
        Representation::Binary(b) => {
            xrce_common::wire::binary::ParticipantBinary::decode(b, little_endian)
                .ok()?
                .qos_profile_reference
        }
        _ => xml::parse_participant(as_xml(repr, refs, "participant").ok()??).ok()?,
    };
    name.filter(|n| !n.trim().is_empty())
}

/// Reads a topic representation.
pub fn describe_topic(
    repr: &Representation,
    refs: &References,
    little_endian: bool,
) -> Result<TopicDesc, OpError> {
    match (as_xml(repr, refs, "topic")?, repr) {
        (Some(x), _) => xml::parse_topic(x).map_err(invalid_xml),
        (None, Representation::Binary(b)) => {
            binary::parse_topic(b, little_endian).map_err(invalid_binary)
        }
        (None, _) => Err(OpError::InvalidData("empty topic representation".into())),
    }
}

/// Reads a data writer or data reader representation.
pub fn describe_endpoint(
    repr: &Representation,
    writer: bool,
    refs: &References,
    little_endian: bool,
) -> Result<xml::EndpointDesc, OpError> {
    let element = if writer { "data_writer" } else { "data_reader" };
    let desc = match (as_xml(repr, refs, element)?, repr) {
        (Some(x), _) => xml::parse_endpoint(x, element).map_err(invalid_xml),
        (None, Representation::Binary(b)) => {
            binary::parse_endpoint(b, writer, little_endian).map_err(invalid_binary)
        }
        (None, _) => Err(OpError::InvalidData("empty endpoint representation".into())),
    }?;
    if desc.qos.partitions {
        // A partition is a publisher's or subscriber's policy in DDS; an endpoint's own
        // would need a group of its own, which the worker does not make.
        return Err(OpError::Incompatible(
            "the PARTITION QoS is a publisher's or subscriber's: give it there, not on a data \
             writer or reader"
                .into(),
        ));
    }
    Ok(desc)
}

/// Reads a requester or replier representation.
pub fn describe_service(
    repr: &Representation,
    requester: bool,
    refs: &References,
    little_endian: bool,
) -> Result<xml::ServiceDesc, OpError> {
    let element = if requester { "requester" } else { "replier" };
    match (as_xml(repr, refs, element)?, repr) {
        (Some(x), _) => xml::parse_service(x, element).map_err(invalid_xml),
        (None, Representation::Binary(b)) => {
            let s = xrce_common::wire::binary::ServiceBinary::decode(b, little_endian)
                .map_err(invalid_binary)?;
            xml::ServiceDesc::new(
                s.service_name,
                s.request_type,
                s.reply_type,
                s.request_topic_name,
                s.reply_topic_name,
            )
            .map_err(invalid_xml)
        }
        (None, _) => Err(OpError::InvalidData(format!(
            "empty {element} representation"
        ))),
    }
}
