//! The RustDDS backend: two participants per domain (one for writers, one for readers),
//! raw pass-through writers and readers ([`raw`]), and a mio poll of every reader as the
//! worker's readiness descriptor.
//!
//! Writers and readers live on different RustDDS participants: pinned to loopback, a RustDDS
//! participant cannot deliver from its own writer to its own reader (its proxies of itself
//! get no locators), so two XRCE clients in one domain would not hear each other.
#![forbid(unsafe_code)]
#![warn(unreachable_pub, missing_docs)]

use std::cell::Cell;
use std::collections::HashMap;
use std::os::fd::{AsFd, BorrowedFd};
use std::rc::Rc;
use std::sync::Arc;
use std::time::Duration;

use rustdds::mio1::{Events, Interest, Poll, Registry, Token};
use rustdds::{DomainParticipant, DomainParticipantBuilder, QosPolicies, RTPSEntity, TopicKind};

use xrce_dds_seam::ports;
use xrce_dds_seam::types::KeyDescriptor;
use xrce_dds_seam::{
    BackendError, DdsBackend, DdsConfig, DdsReader, DdsWriter, EndpointQos, Endpoints, Guid,
    ReaderToken, Sample, SampleIdentity, Taken, TopicSpec,
};

pub mod local;
pub mod qos;
pub mod raw;

use raw::{RawReader, RawSample, RawWriter};

/// Which participant of a domain an entity lives on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Role {
    /// Publishers and data writers.
    Publish,
    /// Subscribers and data readers.
    Subscribe,
}

/// DDS through RustDDS.
pub struct RustDds {
    config: DdsConfig,
    participants: HashMap<(u16, Role), DomainParticipant>,
    poll: Poll,
    /// The poll's registry, shared by every reader for its deregistration (one descriptor).
    registry: Rc<Registry>,
    events: Events,
    /// The last look filled `events`: more readers may be ready, which the descriptor does
    /// not announce again to a loop that waits on it edge-triggered.
    batch_full: bool,
}

/// Readers named per look at the poll.
const EVENT_BATCH: usize = 256;

impl std::fmt::Debug for RustDds {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RustDds")
            .field("participants", &self.participants.len())
            .finish()
    }
}

impl RustDds {
    /// A backend with no participant yet, leaving the ports the configuration reserves
    /// ([`DdsConfig::reserved_ports`]) to the front-ends.
    pub fn new(config: DdsConfig) -> std::io::Result<Self> {
        let poll = Poll::new()?;
        let registry = Rc::new(poll.registry().try_clone()?);
        Ok(RustDds {
            config,
            participants: HashMap::new(),
            poll,
            registry,
            events: Events::with_capacity(EVENT_BATCH),
            batch_full: false,
        })
    }

    /// Leaves these UDP ports to the agent's front-ends (instead of the configuration's).
    #[cfg(test)]
    pub fn reserve_ports(&mut self, reserved: ports::ReservedPorts) {
        self.config.reserved_ports = reserved;
    }

    /// The participant of `domain` for `role`, created on first use.
    ///
    /// RustDDS binds the domain's multicast ports sharing them (and goes on without a
    /// listener it cannot bind), and its unicast ports at the first participant index whose
    /// ports are free: so a front-end's port is left alone if the front-end holds it, and
    /// [`ports::PortGuard`] holds it meanwhile if not. A taken discovery multicast port
    /// refuses the domain ([`ports::plan`]) instead of leaving it deaf to the others'
    /// announcements.
    fn participant(&mut self, domain: u16, role: Role) -> Result<DomainParticipant, BackendError> {
        if let Some(p) = self.participants.get(&(domain, role)) {
            return Ok(p.clone());
        }
        // RustDDS's sockets are IPv4.
        let plan = ports::plan(
            domain,
            &self.config.reserved_ports,
            &self.config.interfaces,
            |p| ports::shareable(p, false),
        )
        .map_err(|clash| BackendError::Placement(clash.to_string()))?;
        if let Some(taken) = plan.user_multicast_taken {
            tracing::info!(
                domain,
                taken,
                "the domain's user-data multicast port is taken (an XRCE port?): RustDDS \
                 receives user data by unicast only there, as Fast DDS does by default"
            );
        }
        let mut b = DomainParticipantBuilder::new(domain);
        if !self.config.interfaces.is_empty() {
            b = b.with_only_networks(self.config.interfaces.clone());
        }
        let guard = plan.guard(false);
        let skip = discovery_ports_to_skip(domain, |p| {
            std::net::UdpSocket::bind((std::net::Ipv4Addr::UNSPECIFIED, p)).is_ok()
        });
        if !skip.is_empty() {
            tracing::debug!(
                domain,
                skipped = skip.len(),
                "participant indices whose user-data port is taken are skipped"
            );
        }
        let steering = ports::PortGuard::hold(&skip, false);
        let p = b.build();
        // Released before the sockets are confined (they are among the process's wildcard
        // sockets).
        drop(steering);
        drop(guard);
        let p = p.map_err(|e| {
            BackendError::Dds(format!(
                "creating DDS participant in domain {domain}: {e:?}"
            ))
        })?;
        // Fails closed: unconfined, the participant is dropped (deleted) here.
        xrce_dds_seam::confine_new_sockets(&self.config)
            .map_err(|e| e.context(&format!("DDS participant in domain {domain}")))?;
        tracing::info!(domain, ?role, "DDS participant created");
        self.participants.insert((domain, role), p.clone());
        Ok(p)
    }
}

/// Participant indices RustDDS tries (RTPS's default port mapping has room for 120).
const PARTICIPANT_INDICES: u32 = 120;

/// The discovery ports that must look taken while RustDDS makes a participant of `domain`:
/// those `free` says are free but whose participant index has its user-data port taken.
///
/// RustDDS takes the first index whose discovery port it can bind; when that index's
/// user-data port is taken, it listens for user data on a port the kernel picks, which may
/// be another domain's discovery port (domains above 101 reach into Linux's default
/// ephemeral range). It sends and checks no domain id, so that participant would discover,
/// and match, the other domain's participants. Held while the participant is made, these
/// steer it to an index whose two ports are free.
fn discovery_ports_to_skip(domain: u16, free: impl Fn(u16) -> bool) -> Vec<u16> {
    let mut skip = Vec::new();
    for index in 0..PARTICIPANT_INDICES {
        let (Some(discovery), Some(user)) = (
            ports::port_at(domain, ports::D1 + 2 * index),
            ports::port_at(domain, ports::D3 + 2 * index),
        ) else {
            break;
        };
        if !free(discovery) {
            // RustDDS passes it by itself.
            continue;
        }
        if free(user) {
            // RustDDS takes this one.
            break;
        }
        skip.push(discovery);
    }
    skip
}

/// A RustDDS topic on `dp` (RustDDS makes topics per participant).
fn topic(dp: &DomainParticipant, spec: &TopicSpec) -> Result<rustdds::Topic, BackendError> {
    dp.create_topic(
        spec.name.clone(),
        spec.type_name.clone(),
        &QosPolicies::qos_none(),
        if spec.key.is_some() {
            TopicKind::WithKey
        } else {
            TopicKind::NoKey
        },
    )
    .map_err(|e| BackendError::Dds(format!("create topic: {e:?}")))
}

/// A RustDDS publisher, with the participant its writers' topics are made on.
#[allow(missing_debug_implementations)] // RustDDS's publisher has none
pub struct Publisher {
    publisher: rustdds::Publisher,
    participant: DomainParticipant,
}

/// A RustDDS subscriber, with the participant its readers' topics are made on.
#[allow(missing_debug_implementations)] // RustDDS's subscriber has none
pub struct Subscriber {
    subscriber: rustdds::Subscriber,
    participant: DomainParticipant,
}

/// A RustDDS data writer and what its status events said.
struct Writer {
    raw: RawWriter,
    topic_name: String,
    /// How many readers it matches (from its status events, read on demand).
    matched: Cell<usize>,
    /// Writes made, and how many of them are known acknowledged.
    written: Cell<u64>,
    acked: Cell<u64>,
}

impl Writer {
    /// Counts a write that succeeded.
    fn count<T>(&self, done: Result<T, BackendError>) -> Result<T, BackendError> {
        if done.is_ok() {
            self.written.set(self.written.get() + 1);
        }
        done
    }
}

impl DdsWriter for Writer {
    fn guid(&self) -> Guid {
        self.raw.guid().to_bytes()
    }
    fn topic_name(&self) -> &str {
        &self.topic_name
    }
    fn little_endian(&self) -> bool {
        self.raw.little_endian()
    }
    fn key(&self) -> Option<&Arc<KeyDescriptor>> {
        self.raw.key()
    }
    fn write(&self, sample: Sample) -> Result<(), BackendError> {
        self.count(self.raw.write(RawSample::from(sample)))
    }
    fn dispose(&self, sample: &Sample) -> Result<(), BackendError> {
        self.count(self.raw.dispose(&RawSample::from(sample.clone())))
    }
    fn write_identified(
        &self,
        sample: Sample,
        related: Option<SampleIdentity>,
    ) -> Result<SampleIdentity, BackendError> {
        self.count(
            self.raw
                .write_identified(RawSample::from(sample), related.map(to_rustdds_identity))
                .map(from_rustdds_identity),
        )
    }
    fn all_acknowledged(&self) -> bool {
        self.raw.all_acknowledged()
    }
    fn writes(&self) -> u64 {
        self.written.get()
    }
    fn acknowledged_writes(&self) -> u64 {
        // RustDDS tells only "everything": its readers acknowledge each heartbeat at once,
        // which its writer sends with every sample, so that is true between most writes.
        if self.raw.all_acknowledged() {
            self.acked.set(self.written.get());
        }
        self.acked.get()
    }
    fn matched_readers(&self) -> usize {
        while let Some(st) = self.raw.try_recv_status() {
            if let rustdds::dds::statusevents::DataWriterStatus::PublicationMatched {
                current,
                ..
            } = st
            {
                self.matched.set(current.count().max(0) as usize);
            }
        }
        self.matched.get()
    }
}

/// A RustDDS data reader registered with the backend's poll (deregistered when dropped).
struct Reader {
    raw: RawReader,
    registry: Rc<Registry>,
}

impl Drop for Reader {
    fn drop(&mut self) {
        let _ = self.registry.deregister(&mut self.raw);
    }
}

impl DdsReader for Reader {
    fn guid(&self) -> Guid {
        self.raw.guid().to_bytes()
    }
    fn take_next(&mut self) -> Result<Option<Taken>, BackendError> {
        let Some(t) = self
            .raw
            .take_next()
            .map_err(|e| BackendError::Dds(format!("{e:?}")))?
        else {
            return Ok(None);
        };
        Ok(Some(Taken {
            sample: t.sample.into(),
            identity: from_rustdds_identity(t.info.sample_identity()),
            related: t.info.related_sample_identity().map(from_rustdds_identity),
            disposed: t.disposed,
            unregistered: t.unregistered,
        }))
    }
}

fn from_rustdds_identity(id: rustdds::SampleIdentity) -> SampleIdentity {
    SampleIdentity {
        writer: id.writer_guid.to_bytes(),
        sequence_number: i64::from(id.sequence_number),
    }
}

fn to_rustdds_identity(id: SampleIdentity) -> rustdds::SampleIdentity {
    rustdds::SampleIdentity {
        writer_guid: rustdds::GUID::from_bytes(id.writer),
        sequence_number: rustdds::SequenceNumber::from(id.sequence_number),
    }
}

impl Endpoints for RustDds {
    type Publisher = Publisher;
    type Subscriber = Subscriber;

    fn new_publisher(
        &mut self,
        domain: u16,
        _partitions: &[String],
    ) -> Result<Publisher, BackendError> {
        let participant = self.participant(domain, Role::Publish)?;
        let publisher = participant
            .create_publisher(&QosPolicies::qos_none())
            .map_err(|e| BackendError::Dds(format!("create publisher: {e:?}")))?;
        Ok(Publisher {
            publisher,
            participant,
        })
    }

    fn new_subscriber(
        &mut self,
        domain: u16,
        _partitions: &[String],
    ) -> Result<Subscriber, BackendError> {
        let participant = self.participant(domain, Role::Subscribe)?;
        let subscriber = participant
            .create_subscriber(&QosPolicies::qos_none())
            .map_err(|e| BackendError::Dds(format!("create subscriber: {e:?}")))?;
        Ok(Subscriber {
            subscriber,
            participant,
        })
    }

    fn new_writer(
        &mut self,
        publisher: &Publisher,
        _domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError> {
        let t = topic(&publisher.participant, spec)?;
        let raw = RawWriter::create(
            &publisher.publisher,
            &t,
            qos::to_rustdds(qos),
            little_endian,
            spec.key.clone(),
        )
        .map_err(|e| BackendError::Dds(format!("create data writer: {e:?}")))?;
        Ok(Box::new(Writer {
            raw,
            topic_name: spec.name.clone(),
            matched: Cell::new(0),
            written: Cell::new(0),
            acked: Cell::new(0),
        }))
    }

    fn new_reader(
        &mut self,
        subscriber: &Subscriber,
        _domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError> {
        let t = topic(&subscriber.participant, spec)?;
        let mut raw = RawReader::create(
            &subscriber.subscriber,
            &t,
            qos::to_rustdds(qos),
            spec.key.clone(),
        )
        .map_err(|e| BackendError::Dds(format!("create data reader: {e:?}")))?;
        let token = usize::try_from(token)
            .map_err(|_| BackendError::Dds("reader token out of range".into()))?;
        self.registry
            .register(&mut raw, Token(token), Interest::READABLE)
            .map_err(|e| BackendError::Dds(format!("register reader: {e}")))?;
        Ok(Box::new(Reader {
            raw,
            registry: self.registry.clone(),
        }))
    }
}

impl DdsBackend for RustDds {
    fn name(&self) -> &'static str {
        "rustdds"
    }

    fn participant_guid(&mut self, domain: u16) -> Result<Guid, BackendError> {
        Ok(self.participant(domain, Role::Publish)?.guid().to_bytes())
    }

    fn readiness_fd(&self) -> BorrowedFd<'_> {
        self.poll.registry().as_fd()
    }

    fn ready_readers(&mut self, out: &mut Vec<ReaderToken>) -> std::io::Result<()> {
        self.poll.poll(&mut self.events, Some(Duration::ZERO))?;
        let before = out.len();
        out.extend(self.events.iter().map(|e| e.token().0 as ReaderToken));
        self.batch_full = out.len() - before >= EVENT_BATCH;
        Ok(())
    }

    fn readers_queued(&self) -> bool {
        self.batch_full
    }

    fn participants(&self) -> usize {
        self.participants.len()
    }

    fn participant_domains(&self) -> Vec<u16> {
        let mut d: Vec<u16> = self.participants.keys().map(|(d, _)| *d).collect();
        d.sort_unstable();
        d.dedup();
        d
    }

    fn release_domain(&mut self, domain: u16) {
        // A RustDDS participant is a handle on shared state: the last clone dropped (here,
        // its groups and endpoints being gone already) stops its threads and closes its
        // sockets.
        let before = self.participants.len();
        self.participants.retain(|(d, _), _| *d != domain);
        if self.participants.len() != before {
            tracing::info!(domain, "DDS participants released");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_whose_user_data_port_is_taken_are_skipped() {
        let at = |offset| ports::port_at(40, offset).expect("port");
        let (d0, u0) = (at(ports::D1), at(ports::D3));
        let (d1, u1) = (at(ports::D1 + 2), at(ports::D3 + 2));
        // Index 0 taken whole (another participant), index 1's user-data port taken: 1 is
        // held, 2 is RustDDS's.
        let taken = [d0, u0, u1];
        let skip = discovery_ports_to_skip(40, |p| !taken.contains(&p));
        assert_eq!(skip, vec![d1]);
        // Nothing taken: nothing held.
        assert!(discovery_ports_to_skip(40, |_| true).is_empty());
        // Two in a row.
        let taken = [u0, u1];
        assert_eq!(
            discovery_ports_to_skip(40, |p| !taken.contains(&p)),
            vec![d0, d1]
        );
    }

    #[test]
    fn a_participant_skips_an_index_whose_user_data_port_is_taken() {
        // Without the skip, RustDDS would take index 0 and listen for user data on a port
        // the kernel picks.
        // A domain whose index 0 is free (other processes may hold some), with its user-data
        // port then taken here.
        let free = |p: u16| std::net::UdpSocket::bind(("0.0.0.0", p)).is_ok();
        let start = 42 + (std::process::id() % 40) as u16;
        let (domain, discovery0, _occupant) = (start..start + 40)
            .find_map(|domain| {
                let discovery0 = ports::port_at(domain, ports::D1)?;
                let user0 = ports::port_at(domain, ports::D3)?;
                if !free(discovery0) {
                    return None;
                }
                let occupant = std::net::UdpSocket::bind(("0.0.0.0", user0)).ok()?;
                Some((domain, discovery0, occupant))
            })
            .expect("a domain whose participant index 0 is free");
        let mut dds = RustDds::new(DdsConfig {
            interfaces: vec!["127.0.0.1".parse().expect("address")],
            ..Default::default()
        })
        .expect("backend");
        let _publisher = Endpoints::new_publisher(&mut dds, domain, &[]).expect("publisher");
        let p = dds.participants.values().next().expect("a participant");
        assert_ne!(p.participant_id(), 0, "index 0 has no user-data port");
        assert!(
            std::net::UdpSocket::bind(("0.0.0.0", discovery0)).is_ok(),
            "index 0's discovery port is free again"
        );
    }

    #[test]
    fn a_front_ends_free_ports_are_not_taken_by_the_participants() {
        // Domain 99 on loopback: RustDDS would bind the user-data multicast port 32151 and
        // give its first participant 32160 and 32161.
        let reserved: Vec<u16> = [ports::D2, ports::D1, ports::D3]
            .iter()
            .filter_map(|o| ports::port_at(99, *o))
            .collect();
        let mut dds = RustDds::new(DdsConfig {
            interfaces: vec!["127.0.0.1".parse().expect("address")],
            ..Default::default()
        })
        .expect("backend");
        dds.reserve_ports(ports::ReservedPorts::new(reserved.iter().copied()));
        let _publisher = Endpoints::new_publisher(&mut dds, 99, &[]).expect("publisher");
        let _subscriber = Endpoints::new_subscriber(&mut dds, 99, &[]).expect("subscriber");
        assert_eq!(dds.participants(), 2);
        for p in reserved {
            assert!(
                std::net::UdpSocket::bind(("0.0.0.0", p)).is_ok(),
                "RustDDS took port {p}, which a front-end serves"
            );
        }
    }
}
