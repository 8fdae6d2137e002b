//! Reading the representation of a CREATE, XML or binary, into the descriptions the worker
//! maps to DDS. Creation by reference is not supported yet and answered as an unknown
//! reference.

use xrce_common::wire::{object_kind, status, Representation};

use crate::binary;
use crate::xml::{self, TopicDesc};

/// Why an operation failed: the XRCE status and a reason for the log.
pub type OpError = (u8, String);

fn invalid_xml(e: xml::XmlError) -> OpError {
    (status::ERR_INVALID_DATA, e.to_string())
}

fn invalid_binary(e: xrce_common::wire::DecodeError) -> OpError {
    (
        status::ERR_INVALID_DATA,
        format!("binary representation: {e}"),
    )
}

fn unknown_reference(r: &str) -> OpError {
    (
        status::ERR_UNKNOWN_REFERENCE,
        format!("reference {r:?}: no references are loaded (not supported yet)"),
    )
}

/// Checks the representation of a participant, publisher or subscriber (whose settings the
/// worker takes from elsewhere: publishers and subscribers from their endpoints, and the
/// reference client sends them an empty string).
pub fn check_plain(repr: &Representation, kind: u8) -> Result<(), OpError> {
    match (repr, kind) {
        (Representation::Xml(x), object_kind::PARTICIPANT) => {
            xml::parse_participant(x).map(drop).map_err(invalid_xml)
        }
        (Representation::Xml(_), _) => Ok(()),
        (Representation::Binary(b), object_kind::PARTICIPANT) => {
            binary::parse_participant(b).map_err(invalid_binary)
        }
        (Representation::Binary(b), _) => {
            binary::parse_publisher_or_subscriber(b).map_err(invalid_binary)
        }
        (Representation::Reference(r), _) => Err(unknown_reference(r)),
    }
}

/// Reads a topic representation.
pub fn describe_topic(repr: &Representation) -> Result<TopicDesc, OpError> {
    match repr {
        Representation::Xml(x) => xml::parse_topic(x).map_err(invalid_xml),
        Representation::Binary(b) => binary::parse_topic(b).map_err(invalid_binary),
        Representation::Reference(r) => Err(unknown_reference(r)),
    }
}

/// Reads a data writer or data reader representation.
pub fn describe_endpoint(
    repr: &Representation,
    writer: bool,
) -> Result<xml::EndpointDesc, OpError> {
    match repr {
        Representation::Xml(x) => {
            xml::parse_endpoint(x, if writer { "data_writer" } else { "data_reader" })
                .map_err(invalid_xml)
        }
        Representation::Binary(b) => binary::parse_endpoint(b, writer).map_err(invalid_binary),
        Representation::Reference(r) => Err(unknown_reference(r)),
    }
}
