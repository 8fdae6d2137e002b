//! The seam between the XRCE agent's DDS worker and a DDS implementation.
//!
//! The worker decides what exists (the XRCE entity tree, holds, reads, pacing, filters) and
//! a backend makes it exist in DDS: participants per domain, data writers and readers of
//! raw serialized samples (the client's CDR goes to the wire as it is, and received samples
//! come back as bytes with their identity), matched counts, acknowledgement status, and one
//! descriptor the worker's loop waits on for readers with data.
//!
//! This crate is what every backend and the worker share, and nothing else: the traits
//! ([`DdsBackend`], [`Endpoints`], [`DdsWriter`], [`DdsReader`]), publishers and
//! subscribers typed by role ([`groups`]), samples and GUIDs, the error kinds, the endpoint
//! QoS the worker resolves ([`qos`], [`policies`]), where DDS may talk ([`DdsConfig`],
//! [`confine`], [`ports`]), the XRCE type descriptions a backend extracts keys with
//! ([`types`]) and the ROS graph's plain data ([`ros_nodes`]). The backends are crates of
//! their own (`xrce-dds-cyclone`, `xrce-dds-rustdds`, `xrce-dds-zenoh`); with the `fake`
//! feature, `fake` is one that delivers between its own writers and readers in memory, for
//! unit tests.
#![deny(unsafe_code)]
// The exception: one function of `confine` (attaching a socket filter to a descriptor).
#![warn(unreachable_pub, missing_docs)]

use std::net::IpAddr;
use std::os::fd::BorrowedFd;
use std::sync::Arc;

use bytes::Bytes;
pub use xrce_ipc::SampleIdentity;

use crate::types::KeyDescriptor;

pub mod confine;
#[cfg(any(test, feature = "fake"))]
pub mod fake;
pub mod groups;
pub mod policies;
pub mod ports;
pub mod qos;
pub mod ros_nodes;
pub mod types;

pub use groups::{DynEndpoints, Endpoints, Publisher, Subscriber};
pub use qos::{EndpointQos, EndpointSide};

/// Where DDS may talk, whichever implementation the worker chose.
#[derive(Debug, Clone, Default)]
pub struct DdsConfig {
    /// Restrict DDS to these local addresses (empty = every interface, like any DDS app).
    pub interfaces: Vec<IpAddr>,
    /// The UDP ports the agent's front-ends serve, which DDS leaves to them ([`ports`]).
    pub reserved_ports: ports::ReservedPorts,
    /// The Zenoh backend's settings.
    pub zenoh: ZenohSettings,
    /// RustDDS delivers the agent's own samples through UDP loopback, as between processes,
    /// instead of inside the worker (`--local-delivery false`, to measure the difference or
    /// to rule the wrapper out when looking for a fault).
    pub rustdds_loopback: bool,
}

/// The Zenoh backend's settings.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ZenohSettings {
    /// `--zenoh-type-hashes`: ROS installations (install prefixes or share folders) and
    /// hash tables the RIHS01 type hashes are looked up in (before `AMENT_PREFIX_PATH` and
    /// the built-in table).
    pub type_hashes: Vec<std::path::PathBuf>,
}

/// Confines the UDP sockets a backend's new participant bound to the wildcard address to
/// the configured interfaces ([`confine`]). It fails closed: on an error the caller deletes
/// the participant (its sockets might take datagrams sent to any address of this host) and
/// refuses what needed it.
pub fn confine_new_sockets(config: &DdsConfig) -> Result<(), BackendError> {
    match confine::confine_udp_sockets(&config.interfaces) {
        Ok(0) => Ok(()),
        Ok(n) => {
            tracing::debug!(
                sockets = n,
                interfaces = ?config.interfaces,
                "DDS sockets bound to the wildcard address confined to the DDS interfaces"
            );
            Ok(())
        }
        Err(e) => {
            tracing::error!(
                interfaces = ?config.interfaces,
                "could not confine a new DDS participant to the DDS interfaces; it is deleted: {e}"
            );
            Err(BackendError::Placement(format!(
                "the DDS participant could not be confined to --dds-interface: {e}"
            )))
        }
    }
}

/// Why a backend could not do what the worker asked. The variant says whose the fault is,
/// which decides the XRCE status a client gets (`OpError`'s `From`): only
/// [`InvalidInput`](BackendError::InvalidInput) is the client's.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BackendError {
    /// The DDS implementation refused or failed the call; the message names the call and
    /// gives the implementation's reason.
    #[error("{0}")]
    Dds(String),
    /// Input the implementation cannot take: a sample whose key cannot be read, a dispose
    /// on a topic without a key, a name with a NUL byte.
    #[error("{0}")]
    InvalidInput(String),
    /// DDS cannot go where the configuration puts it: a participant that could not be
    /// confined to `--dds-interface`, ports the front-ends hold, IPv4 and IPv6 together.
    #[error("{0}")]
    Placement(String),
    /// Something this backend does not do (the worker asks another for it).
    #[error("{0}")]
    Unsupported(&'static str),
    /// An entity made by another backend was passed in (a fault in the worker, not the
    /// client's).
    #[error("{0}")]
    ForeignEntity(&'static str),
}

impl BackendError {
    /// The same error, its message preceded by what was being done (`"DDS write"`); the
    /// kinds whose message is fixed (`Unsupported`, `ForeignEntity`) become `Dds`, which the
    /// client sees the same way (DDS_ERROR).
    pub fn context(self, what: &str) -> Self {
        match self {
            BackendError::Dds(m) => BackendError::Dds(format!("{what}: {m}")),
            BackendError::InvalidInput(m) => BackendError::InvalidInput(format!("{what}: {m}")),
            BackendError::Placement(m) => BackendError::Placement(format!("{what}: {m}")),
            BackendError::Unsupported(m) => BackendError::Dds(format!("{what}: {m}")),
            BackendError::ForeignEntity(m) => BackendError::Dds(format!("{what}: {m}")),
        }
    }
}

/// A DDS GUID (participant prefix and entity id), as on the wire.
pub type Guid = [u8; 16];

/// How a sample body is serialized: the two bytes of its RTPS representation identifier.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Encoding(pub [u8; 2]);

impl Encoding {
    /// Plain CDR (XCDR1), big endian.
    pub const CDR_BE: Encoding = Encoding([0, 0]);
    /// Plain CDR (XCDR1), little endian.
    pub const CDR_LE: Encoding = Encoding([0, 1]);
    /// Plain XCDR2, big endian: 0x0006, what DDS implementations send (RustDDS, Cyclone
    /// DDS and Fast DDS alike; XTypes 1.3's table says 0x0010, its erratum 0x0006).
    pub const XCDR2_BE: Encoding = Encoding([0, 0x06]);
    /// Plain XCDR2, little endian (0x0007).
    pub const XCDR2_LE: Encoding = Encoding([0, 0x07]);

    /// Plain CDR in the given byte order (what a client's samples are).
    pub fn cdr(little_endian: bool) -> Self {
        if little_endian {
            Self::CDR_LE
        } else {
            Self::CDR_BE
        }
    }

    /// Whether the body is little endian (every representation identifier ends in 1 then).
    pub fn little_endian(self) -> bool {
        self.0[1] & 1 == 1
    }

    /// Whether it is XCDR version 2.
    pub fn is_xcdr2(self) -> bool {
        self == Self::XCDR2_LE || self == Self::XCDR2_BE
    }
}

/// A serialized sample body (no encapsulation header) and its encoding.
#[derive(Debug, Clone)]
pub struct Sample {
    /// CDR_LE, CDR_BE, ...
    pub encoding: Encoding,
    /// The serialized body.
    pub body: Bytes,
}

impl Sample {
    /// A client's sample: plain CDR in its byte order, copied.
    pub fn cdr(little_endian: bool, body: &[u8]) -> Self {
        Sample {
            encoding: Encoding::cdr(little_endian),
            body: Bytes::copy_from_slice(body),
        }
    }

    /// Whether the body is little endian.
    pub fn little_endian(&self) -> bool {
        self.encoding.little_endian()
    }
}

/// A sample taken from a [`DdsReader`].
#[derive(Debug)]
pub struct Taken {
    /// The sample; for a dispose or unregister, the key-only payload.
    pub sample: Sample,
    /// Which writer wrote it, and its sequence number there.
    pub identity: SampleIdentity,
    /// The request it answers, for a reply (RPC over DDS).
    pub related: Option<SampleIdentity>,
    /// The instance was disposed (no data).
    pub disposed: bool,
    /// The instance has no writers any more (no data).
    pub unregistered: bool,
}

/// A topic as a backend makes it: name, type name and whether it has a key.
#[derive(Debug, Clone)]
pub struct TopicSpec {
    /// The DDS topic name.
    pub name: String,
    /// The DDS type name.
    pub type_name: String,
    /// Its type and key, for a WITH_KEY topic whose type is known (the backend extracts
    /// each sample's key with it); `None` makes a NO_KEY topic.
    pub key: Option<Arc<KeyDescriptor>>,
}

/// Which readers a worker's loop wakes up for: a number the worker chooses per reader.
pub type ReaderToken = u64;

/// A data writer of raw samples in one byte order (the client's).
pub trait DdsWriter {
    /// Its GUID (announced in the ROS graph; replies name it).
    fn guid(&self) -> Guid;
    /// The name of the topic it writes.
    fn topic_name(&self) -> &str;
    /// Whether it publishes little-endian samples.
    fn little_endian(&self) -> bool;
    /// The key description of a keyed writer.
    fn key(&self) -> Option<&Arc<KeyDescriptor>>;
    /// Publishes a sample (already in the writer's byte order).
    fn write(&self, sample: Sample) -> Result<(), BackendError>;
    /// Disposes the instance of `sample` (a whole sample, or its key fields alone).
    fn dispose(&self, sample: &Sample) -> Result<(), BackendError>;
    /// Publishes a sample, optionally as the reply to `related`; returns its identity.
    fn write_identified(
        &self,
        sample: Sample,
        related: Option<SampleIdentity>,
    ) -> Result<SampleIdentity, BackendError>;
    /// Whether every matched reliable reader acknowledged everything written (true without
    /// any, and for a best-effort writer). Never waits.
    fn all_acknowledged(&self) -> bool;
    /// How many writes (samples and disposes that succeeded) it made since its creation.
    fn writes(&self) -> u64;
    /// The sequence number of the write or dispose it made last, as its readers in this
    /// process see it in [`Taken::identity`] (the worker asks right after one that
    /// succeeded: a backend may count failed attempts too); `None` where the backend cannot
    /// tell. The worker tells by it which client write a sample it takes came from.
    fn last_sequence_number(&self) -> Option<i64> {
        None
    }
    /// How many of its first [`writes`](DdsWriter::writes) every matched reliable reader
    /// acknowledged (all of them without any, and for a best-effort writer). Never waits;
    /// may lag behind the readers, never run ahead of them.
    fn acknowledged_writes(&self) -> u64;
    /// How many readers it matches now.
    fn matched_readers(&self) -> usize;
}

/// A data reader of raw samples, keyed or not. Dropping it deletes it and stops its
/// wake-ups.
pub trait DdsReader {
    /// Its GUID.
    fn guid(&self) -> Guid;
    /// Takes the next sample, if any; an error is one sample that could not be taken
    /// (undecodable), the next call goes on.
    fn take_next(&mut self) -> Result<Option<Taken>, BackendError>;
}

/// A DDS implementation as the worker uses it: its publishers, subscribers, writers and
/// readers ([`DynEndpoints`], which a backend gets by implementing [`Endpoints`]), and the
/// rest here.
pub trait DdsBackend: DynEndpoints {
    /// Its name in logs.
    fn name(&self) -> &'static str;
    /// Whether its groups can have partitions.
    fn supports_partitions(&self) -> bool {
        false
    }
    /// Whether it can serve requesters and repliers ([`DdsWriter::write_identified`] with a
    /// related identity, and readers that report one).
    fn supports_services(&self) -> bool {
        true
    }
    /// Whether every sample of its own writers reaches its own matched readers inside the
    /// write call, each reader's volatile samples of a topic without a key then taken in
    /// the order written, whatever the QoS of the pair. The worker then counts what such a
    /// reader took of its writes to acknowledge them sooner; a backend that sends some
    /// pairs through the network (RustDDS's in-process delivery pairs only some QoS) or
    /// delivers later (Zenoh) must say no, or writes would be acknowledged before they were
    /// taken.
    fn delivers_locally_in_write_order(&self) -> bool {
        false
    }
    /// The GUID of the participant the domain's writers live on (the ROS graph names it).
    fn participant_guid(&mut self, domain: u16) -> Result<Guid, BackendError>;
    /// A descriptor that polls readable when some reader may have data.
    fn readiness_fd(&self) -> BorrowedFd<'_>;
    /// Adds the tokens of readers that may have data since the last call (never blocks;
    /// a reader may be named without data, and the worker takes from it until empty).
    fn ready_readers(&mut self, out: &mut Vec<ReaderToken>) -> std::io::Result<()>;
    /// Whether readers wait to be named by [`ready_readers`](DdsBackend::ready_readers)
    /// without the descriptor announcing them (a backend that delivers the loop's own writes
    /// inside the process may queue those readers without a wake-up); the loop then does
    /// not block.
    fn readers_queued(&self) -> bool {
        false
    }
    /// How many DDS participants it holds now.
    fn participants(&self) -> usize;
    /// The domains it holds a DDS participant in now (in increasing order).
    fn participant_domains(&self) -> Vec<u16>;
    /// Lets the DDS participant(s) of `domain` go: the worker calls this when the domain's
    /// last XRCE participant was deleted, after dropping every group, writer and reader it
    /// made in the domain, so that the participant is deleted and its threads and sockets
    /// go back (a client could otherwise make the worker keep one per domain id for ever).
    /// A participant something still holds is deleted when that is dropped; a later use of
    /// the domain makes a new one.
    fn release_domain(&mut self, domain: u16);
    /// Samples it dropped, by reason, since it started (for the worker's status).
    fn dropped(&self) -> Vec<(&'static str, u64)> {
        Vec::new()
    }
    /// Whether it announces the ROS graph itself ([`announce_graph`](DdsBackend::announce_graph),
    /// as rmw_zenoh's liveliness tokens) rather than through a `ros_discovery_info` writer
    /// the worker makes on it.
    fn announces_graph(&self) -> bool {
        false
    }
    /// Announces the ROS nodes of `domain` with their endpoints (the GUIDs of writers and
    /// readers it made), replacing what it announced for the domain before; called when they
    /// change. Only asked of a backend that [announces the graph](DdsBackend::announces_graph).
    fn announce_graph(
        &mut self,
        _domain: u16,
        _nodes: &crate::ros_nodes::DomainNodes,
    ) -> Result<(), BackendError> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodings_say_their_byte_order_and_version() {
        assert!(Encoding::CDR_LE.little_endian() && !Encoding::CDR_LE.is_xcdr2());
        assert!(!Encoding::CDR_BE.little_endian());
        assert!(Encoding::XCDR2_LE.little_endian() && Encoding::XCDR2_LE.is_xcdr2());
        assert!(!Encoding::XCDR2_BE.little_endian() && Encoding::XCDR2_BE.is_xcdr2());
        assert_eq!(Encoding::cdr(false), Encoding::CDR_BE);
    }
}
