//! The seam between the worker and a DDS implementation.
//!
//! The worker decides what exists (the XRCE entity tree, holds, reads, pacing, filters) and
//! a backend makes it exist in DDS: participants per domain, data writers and readers of
//! raw serialized samples (the client's CDR goes to the wire as it is, and received samples
//! come back as bytes with their identity), matched counts, acknowledgement status, and one
//! descriptor the worker's loop waits on for readers with data. The worker's modules use only
//! these traits and types (`Worker::new` picks the one the configuration names,
//! `Worker::with_backend` any other).
//!
//! Implementations: `cyclone` (Cyclone DDS, the default, with the `cyclone` feature, on by
//! default), [`rustdds`] (RustDDS, always built; it also serves requesters and repliers
//! beside a backend that cannot, [`for_services`]) and, for the worker's unit tests, a fake
//! that delivers between its own writers and readers in memory. [`confine`] keeps either's
//! sockets to the configured interfaces; [`local`] delivers between the worker's own writers
//! and readers inside the process for RustDDS, which would send those samples through UDP
//! loopback. [`ports`] keeps DDS off the UDP ports the agent's front-ends serve (an XRCE port
//! that is also a well-known DDS port, such as 7401, domain 0's user-data multicast port).

use std::net::IpAddr;
use std::os::fd::BorrowedFd;
use std::sync::Arc;

use bytes::Bytes;
pub use xrce_ipc::SampleIdentity;

use crate::types::KeyDescriptor;

pub mod confine;
#[cfg(feature = "cyclone")]
pub mod cyclone;
pub mod local;
pub mod policies;
pub mod ports;
pub mod qos;
pub mod rustdds;
#[cfg(feature = "zenoh")]
pub mod zenoh;

#[cfg(test)]
pub mod fake;

pub use qos::{EndpointQos, EndpointSide};

/// Where DDS may talk, and through which implementation.
#[derive(Debug, Clone, Default)]
pub struct DdsConfig {
    /// Restrict DDS to these local addresses (empty = every interface, like any DDS app).
    pub interfaces: Vec<IpAddr>,
    /// The DDS implementation.
    pub backend: BackendKind,
    /// The UDP ports the agent's front-ends serve, which DDS leaves to them ([`ports`]).
    pub reserved_ports: ports::ReservedPorts,
    /// The Zenoh backend's settings.
    pub zenoh: ZenohSettings,
    /// RustDDS delivers the agent's own samples through UDP loopback, as between processes,
    /// instead of inside the worker ([`local`]): `--local-delivery false`, to measure the
    /// difference or to rule the wrapper out when looking for a fault.
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

/// The DDS implementations a worker can use. The default is Cyclone DDS when the build has
/// it (the `cyclone` feature, on by default), RustDDS otherwise.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// RustDDS (always built).
    #[cfg_attr(not(feature = "cyclone"), default)]
    Rustdds,
    /// Cyclone DDS (built with the `cyclone` feature).
    #[cfg_attr(feature = "cyclone", default)]
    Cyclone,
    /// Zenoh, as ROS 2's rmw_zenoh uses it (built with the `zenoh` feature; `-m zenoh`).
    Zenoh,
}

impl BackendKind {
    /// Its name on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            BackendKind::Rustdds => "rustdds",
            BackendKind::Cyclone => "cyclone",
            BackendKind::Zenoh => "zenoh",
        }
    }

    /// Whether this build has it.
    pub fn is_built(self) -> bool {
        match self {
            BackendKind::Rustdds => true,
            BackendKind::Cyclone => cfg!(feature = "cyclone"),
            BackendKind::Zenoh => cfg!(feature = "zenoh"),
        }
    }
}

/// Refuses a configuration DDS cannot be confined by (`--dds-interface`: an address this
/// host does not hold, too many, no socket filters; see [`confine`]), or that the backend
/// cannot use (Cyclone DDS: IPv4 and IPv6 addresses together), before anything is made:
/// the worker then refuses to start rather than run DDS on interfaces it was not given.
pub fn check_config(config: &DdsConfig) -> anyhow::Result<()> {
    use anyhow::Context as _;
    let plan = confine::check(&config.interfaces).with_context(|| {
        format!(
            "cannot confine DDS to --dds-interface {}",
            config
                .interfaces
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(",")
        )
    })?;
    match plan {
        confine::Plan::Everywhere if config.interfaces.is_empty() => {}
        confine::Plan::Everywhere => {
            tracing::info!("DDS on every interface (an unspecified --dds-interface address)")
        }
        confine::Plan::Confined {
            addresses,
            interfaces,
            ..
        } => tracing::info!(
            ?addresses,
            ?interfaces,
            "DDS confined to these addresses and interfaces"
        ),
    }
    #[cfg(feature = "cyclone")]
    if config.backend == BackendKind::Cyclone {
        cyclone::config_xml(&config.interfaces, None, None).map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    Ok(())
}

/// Refuses, before anything starts, what would stop a Zenoh backend at its start: a Zenoh
/// configuration (`ZENOH_SESSION_CONFIG_URI`, `ZENOH_CONFIG_OVERRIDE`) it cannot use, or a
/// `--zenoh-type-hashes` path that is neither a folder nor a readable table.
pub fn check_zenoh(type_hashes: &[std::path::PathBuf]) -> anyhow::Result<()> {
    #[cfg(feature = "zenoh")]
    {
        let env = |name: &str| std::env::var(name).ok();
        zenoh::session::config(
            env(zenoh::session::CONFIG_URI_ENV).as_deref(),
            env(zenoh::session::CONFIG_OVERRIDE_ENV).as_deref(),
        )?;
        zenoh::type_hashes::TypeHashes::new(type_hashes, None)?;
        Ok(())
    }
    #[cfg(not(feature = "zenoh"))]
    {
        let _ = type_hashes;
        anyhow::bail!("this build has no Zenoh backend: build it with the `zenoh` feature")
    }
}

/// The domains DDS cannot serve with this configuration, with why: those whose discovery
/// multicast port a front-end serves XRCE on ([`ports::unservable_domains`]; none with Zenoh,
/// which uses no DDS port).
pub fn unservable_domains(config: &DdsConfig) -> std::collections::BTreeMap<u16, String> {
    if config.backend == BackendKind::Zenoh {
        return Default::default();
    }
    ports::unservable_domains(&config.reserved_ports, &config.interfaces)
}

/// The backend `config` names, once [`check_config`] accepted the configuration.
pub fn create(config: &DdsConfig) -> anyhow::Result<Box<dyn DdsBackend>> {
    check_config(config)?;
    ports::log_reserved(&config.reserved_ports, &config.interfaces);
    match config.backend {
        BackendKind::Rustdds => rustdds_delivering_locally(config.clone()),
        #[cfg(feature = "cyclone")]
        BackendKind::Cyclone => Ok(Box::new(cyclone::Cyclone::new(config.clone())?)),
        #[cfg(not(feature = "cyclone"))]
        BackendKind::Cyclone => anyhow::bail!(
            "this build has no Cyclone DDS backend: build it with the `cyclone` feature \
             (on by default; needs cmake and libclang: deploy/build-deps), or use \
             --dds-backend rustdds"
        ),
        #[cfg(feature = "zenoh")]
        BackendKind::Zenoh => Ok(Box::new(zenoh::Zenoh::new(config)?)),
        #[cfg(not(feature = "zenoh"))]
        BackendKind::Zenoh => anyhow::bail!(
            "this build has no Zenoh backend: build it with the `zenoh` feature (on by default)"
        ),
    }
}

/// A backend for requesters and repliers, beside one that cannot serve them
/// ([`DdsBackend::supports_services`] false): RustDDS, which puts a reply's related sample
/// identity on the wire (Fast DDS's convention, what eProsima's client and agent use) and
/// reports it, in the same domains and on the same interfaces.
pub fn for_services(config: &DdsConfig) -> anyhow::Result<Box<dyn DdsBackend>> {
    let config = DdsConfig {
        backend: BackendKind::Rustdds,
        ..config.clone()
    };
    check_config(&config)?;
    rustdds_delivering_locally(config)
}

/// The RustDDS backend, which sends samples between its own writers and readers through
/// UDP loopback, wrapped so that they are delivered inside the process ([`local`]), unless
/// the configuration says otherwise ([`DdsConfig::rustdds_loopback`]).
fn rustdds_delivering_locally(config: DdsConfig) -> anyhow::Result<Box<dyn DdsBackend>> {
    let loopback = config.rustdds_loopback;
    let rustdds = Box::new(rustdds::RustDds::new(config)?);
    if loopback {
        tracing::info!("local delivery off: RustDDS delivers the agent's own samples");
        return Ok(rustdds);
    }
    Ok(Box::new(local::LocalDelivery::new(rustdds)))
}

/// Confines the UDP sockets a backend's new participant bound to the wildcard address to
/// the configured interfaces ([`confine`]). It fails closed: on an error the caller deletes
/// the participant (its sockets might take datagrams sent to any address of this host) and
/// refuses what needed it.
pub(crate) fn confine_new_sockets(config: &DdsConfig) -> Result<(), BackendError> {
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

/// The domain id XRCE clients use to mean "the agent's default" (reference agent behaviour).
pub const DOMAIN_ID_DEFAULT_MARKER: i16 = 255;

/// Maps the domain id a client asked for to the DDS domain used: the marker of "the agent's
/// default" to `default` (`--default-domain`, else ROS_DOMAIN_ID, else 0), another id to
/// itself if DDS allows it.
pub fn effective_domain(requested: i16, default: u16) -> Result<u16, String> {
    if requested == DOMAIN_ID_DEFAULT_MARKER {
        return Ok(default);
    }
    u16::try_from(requested)
        .ok()
        .filter(|d| *d <= crate::domains::MAX_DOMAIN_ID)
        .ok_or_else(|| format!("domain id {requested} out of range"))
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

/// A group of endpoints (a DDS publisher or subscriber) on the participant of a domain.
pub trait DdsGroup {
    /// The domain it is in.
    fn domain(&self) -> u16;
    /// For the backend that made it, to find its own type again.
    fn as_any(&self) -> &dyn std::any::Any;
}

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

/// A DDS implementation as the worker uses it.
pub trait DdsBackend {
    /// Its name in logs.
    fn name(&self) -> &'static str;
    /// A publisher (`publish`) or subscriber in `domain` with the given partitions (empty:
    /// the default partition; only asked of a backend that [supports
    /// them](DdsBackend::supports_partitions)), making the domain's participant on first use.
    fn create_group(
        &mut self,
        domain: u16,
        publish: bool,
        partitions: &[String],
    ) -> Result<Box<dyn DdsGroup>, BackendError>;
    /// Whether its groups can have partitions.
    fn supports_partitions(&self) -> bool {
        false
    }
    /// Whether it can serve requesters and repliers ([`DdsWriter::write_identified`] with a
    /// related identity, and readers that report one).
    fn supports_services(&self) -> bool {
        true
    }
    /// A data writer in `group` (a publisher of this backend) publishing in the given byte
    /// order.
    fn create_writer(
        &mut self,
        group: &dyn DdsGroup,
        topic: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError>;
    /// A data reader in `group` (a subscriber of this backend), whose data wakes the loop
    /// with `token`.
    fn create_reader(
        &mut self,
        group: &dyn DdsGroup,
        topic: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError>;
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

/// A `SampleIdentity` as eProsima's client carries it in front of request and reply data:
/// the writer GUID's 16 octets, then the sequence number as `int32 high`, `uint32 low` in the
/// given byte order (24 bytes).
pub fn encode_sample_identity(id: &SampleIdentity, little_endian: bool) -> [u8; 24] {
    let mut out = [0u8; 24];
    out[..16].copy_from_slice(&id.writer);
    let (high, low) = ((id.sequence_number >> 32) as i32, id.sequence_number as u32);
    let (h, l) = if little_endian {
        (high.to_le_bytes(), low.to_le_bytes())
    } else {
        (high.to_be_bytes(), low.to_be_bytes())
    };
    out[16..20].copy_from_slice(&h);
    out[20..24].copy_from_slice(&l);
    out
}

/// Reads the 24-byte identity [`encode_sample_identity`] writes; `None` if too short.
pub fn decode_sample_identity(b: &[u8], little_endian: bool) -> Option<SampleIdentity> {
    let writer: [u8; 16] = b.get(..16)?.try_into().ok()?;
    let h: [u8; 4] = b.get(16..20)?.try_into().ok()?;
    let l: [u8; 4] = b.get(20..24)?.try_into().ok()?;
    let (high, low) = if little_endian {
        (i32::from_le_bytes(h), u32::from_le_bytes(l))
    } else {
        (i32::from_be_bytes(h), u32::from_be_bytes(l))
    };
    Some(SampleIdentity {
        writer,
        sequence_number: (i64::from(high) << 32) | i64::from(low),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::representation::OpError;
    use xrce_common::wire::status;

    #[test]
    fn only_input_the_backend_cannot_take_is_the_clients_fault() {
        let input = BackendError::InvalidInput("key of a Keyed sample: too short".into());
        let with_context = input.context("DDS write");
        assert_eq!(
            with_context,
            BackendError::InvalidInput("DDS write: key of a Keyed sample: too short".into())
        );
        assert_eq!(
            OpError::from(with_context).status(),
            status::ERR_INVALID_DATA
        );
        for other in [
            BackendError::Dds("create data writer: out of resources".into()),
            BackendError::Placement("UDP port 7401 is taken".into()),
            BackendError::Unsupported("no services here"),
            BackendError::ForeignEntity("a data writer needs a publisher of this backend"),
        ] {
            let op = OpError::from(other.clone().context("DDS write"));
            assert_eq!(op.status(), status::ERR_DDS_ERROR, "{other:?}");
            assert!(op.to_string().starts_with("DDS write: "), "{op}");
        }
    }

    #[test]
    fn sample_identities_round_trip_in_both_byte_orders() {
        let id = SampleIdentity {
            writer: [7; 16],
            sequence_number: (1 << 32) | 0x0102_0304,
        };
        for le in [true, false] {
            let b = encode_sample_identity(&id, le);
            assert_eq!(decode_sample_identity(&b, le), Some(id));
        }
        assert_eq!(
            &encode_sample_identity(&id, true)[16..],
            &[1, 0, 0, 0, 4, 3, 2, 1]
        );
        assert_eq!(
            &encode_sample_identity(&id, false)[16..],
            &[0, 0, 0, 1, 1, 2, 3, 4]
        );
        let negative = SampleIdentity {
            writer: [1; 16],
            sequence_number: -2,
        };
        assert_eq!(
            decode_sample_identity(&encode_sample_identity(&negative, true), true),
            Some(negative)
        );
        assert_eq!(decode_sample_identity(&[0; 23], true), None);
    }

    #[test]
    fn encodings_say_their_byte_order_and_version() {
        assert!(Encoding::CDR_LE.little_endian() && !Encoding::CDR_LE.is_xcdr2());
        assert!(!Encoding::CDR_BE.little_endian());
        assert!(Encoding::XCDR2_LE.little_endian() && Encoding::XCDR2_LE.is_xcdr2());
        assert!(!Encoding::XCDR2_BE.little_endian() && Encoding::XCDR2_BE.is_xcdr2());
        assert_eq!(Encoding::cdr(false), Encoding::CDR_BE);
    }

    #[test]
    fn domain_ids() {
        assert_eq!(effective_domain(7, 3), Ok(7));
        assert_eq!(effective_domain(DOMAIN_ID_DEFAULT_MARKER, 3), Ok(3));
        assert!(effective_domain(-1, 0).is_err());
        assert!(effective_domain(300, 0).is_err());
    }
}
