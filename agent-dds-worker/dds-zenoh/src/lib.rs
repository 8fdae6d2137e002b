//! The Zenoh backend (`-m zenoh`): the worker's writers and readers become the publishers,
//! subscriptions, services and clients of an rmw_zenoh ROS 2 graph, so that XRCE devices
//! join a graph of ROS 2 nodes on rmw_zenoh, through a Zenoh router and past one LAN.
//!
//! What it does as rmw_zenoh 0.2.10 (Jazzy) and 0.6.7 (Kilted) do ([`naming`]):
//! * a data writer is a zenoh-ext advanced publisher on `<domain>/<topic>/<type>/<hash>`,
//!   with a cache of its history depth and publisher detection when transient local, and
//!   every sample carries the attachment (sequence number, source time, GID) and the CDR
//!   encapsulation header in front of the client's body;
//! * a data reader is an advanced subscriber on the same key, which for transient local asks
//!   the publishers' caches for their history (late joiners get it);
//! * a requester's request is a query on the service's key with the attachment, its reply
//!   goes to the requester's reader; a replier's reader is a queryable, and its reply
//!   answers the query the request came with;
//! * the ROS nodes the worker finds ([`DdsBackend::announce_graph`]) and their endpoints are
//!   liveliness tokens `@ros2_lv/...`, so `ros2 node list` and `ros2 topic info` on
//!   rmw_zenoh see them.
//!
//! One Zenoh session serves every domain (the domain is the first chunk of each key), made
//! at start as rmw_zenoh makes a node's ([`session`]). Type hashes come from [`type_hashes`].
//!
//! Differences from rmw_zenoh, by design: an endpoint's GID is the session's id and the
//! endpoint's number (rmw_zenoh hashes the endpoint's token, which names its node; the
//! backend makes an endpoint before it knows its node), unique all the same; a dispose has no
//! Zenoh counterpart (ROS topics have no instances) and is refused.
#![forbid(unsafe_code)]
#![warn(unreachable_pub, missing_docs)]

use std::cell::RefCell;
use std::collections::{BTreeMap, HashMap};
use std::os::fd::BorrowedFd;
use std::rc::Rc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use zenoh::Wait as _;
use zenoh_ext::{AdvancedPublisherBuilderExt as _, AdvancedSubscriberBuilderExt as _};

use xrce_dds_seam::policies::{Durability, History, Reliability};
use xrce_dds_seam::ros_nodes::DomainNodes;
use xrce_dds_seam::{
    BackendError, DdsBackend, DdsConfig, DdsReader, DdsWriter, EndpointQos, Endpoints, Guid,
    ReaderToken, TopicSpec,
};

mod endpoints;
mod graph;
mod inbox;
pub mod naming;
mod services;
pub mod session;
pub mod type_hashes;

use endpoints::{attachment_of, taken_of, Reader, Receiver, Sender, Writer};
use inbox::{lock, Inbox, Wakeup, WhenFull};
use naming::{EntityKind, RosName};
use services::{PendingService, ServiceLink};

/// How long a request waits for replies (rmw_zenoh's `queries_default_timeout`).
const QUERY_TIMEOUT: Duration = Duration::from_secs(600);

/// Largest reader queue, whatever history or resource limits a client asks for.
const READER_QUEUE_MAX: usize = 10_000;

/// Counters of what the backend dropped or refused (shared with callback threads).
#[derive(Debug, Default)]
struct Dropped {
    queue_full: Arc<AtomicU64>,
    /// Bytes queued for every reader together ([`inbox::MAX_ALL_QUEUED_BYTES`]).
    queued: Arc<inbox::QueuedBytes>,
    requests_without_attachment: AtomicU64,
    requests_unqueued: AtomicU64,
    requests_refused_in_flight: AtomicU64,
    replies_without_request: AtomicU64,
    pending_requests_evicted: AtomicU64,
}

/// The Zenoh backend.
pub struct Zenoh {
    session: zenoh::Session,
    zid: String,
    zid_bytes: [u8; 16],
    salt: u64,
    wakeup: Arc<Wakeup>,
    hashes: type_hashes::TypeHashes,
    next_id: u64,
    domains: BTreeMap<u16, ()>,
    /// What the graph needs to know of each live endpoint, by GUID.
    endpoints: Rc<RefCell<HashMap<Guid, graph::Endpoint>>>,
    graph: graph::Tokens,
    /// The service a requester's or replier's writer was just made for: its reader, made
    /// next, joins it (the worker makes a requester's or replier's writer, then its reader).
    last_service: Option<PendingService>,
    dropped: Arc<Dropped>,
}

impl std::fmt::Debug for Zenoh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Zenoh")
            .field("zid", &self.zid)
            .field("domains", &self.domains.len())
            .finish()
    }
}

fn zenoh_err(what: &str) -> impl Fn(zenoh::Error) -> BackendError + '_ {
    move |e| BackendError::Dds(format!("{what}: {e}"))
}

impl Zenoh {
    /// Opens the session as rmw_zenoh opens a node's (`ZENOH_SESSION_CONFIG_URI`,
    /// `ZENOH_CONFIG_OVERRIDE`, else a peer connecting to `tcp/localhost:7447`).
    pub fn new(config: &DdsConfig) -> anyhow::Result<Self> {
        let env = |name: &str| std::env::var(name).ok();
        let zconfig = session::config(
            env(session::CONFIG_URI_ENV).as_deref(),
            env(session::CONFIG_OVERRIDE_ENV).as_deref(),
        )?;
        let hashes = type_hashes::TypeHashes::new(
            &config.zenoh.type_hashes,
            env("AMENT_PREFIX_PATH").as_deref(),
        )?;
        let session = zenoh::open(zconfig)
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot open the Zenoh session: {e}"))?;
        let zid_value = session.zid();
        let zid = zid_value.to_string();
        let zid_bytes = zid_value.to_le_bytes();
        tracing::info!(
            zid = %zid,
            built_in_hashes = hashes.built_in_len(),
            "Zenoh session open (rmw_zenoh 0.2.10/0.6.7 conventions)"
        );
        Ok(Zenoh {
            session,
            zid,
            zid_bytes,
            salt: {
                use std::hash::{BuildHasher as _, Hasher as _};
                let mut h = std::collections::hash_map::RandomState::new().build_hasher();
                h.write_u32(std::process::id());
                h.finish()
            },
            wakeup: Arc::new(Wakeup::new()?),
            hashes,
            next_id: 0,
            domains: BTreeMap::new(),
            endpoints: Rc::default(),
            graph: graph::Tokens::default(),
            last_service: None,
            dropped: Arc::default(),
        })
    }

    /// The session's Zenoh id, as tokens carry it.
    pub fn zid(&self) -> &str {
        &self.zid
    }

    fn next_id(&mut self) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        id
    }

    /// An endpoint's GID: 8 bytes of the session id mixed with a number random to this
    /// process (a restarted worker's GIDs differ even with a configured Zenoh id, so its
    /// sequence numbers, from 1 again, are not taken for repeats), and the endpoint's number.
    fn gid(&self, id: u64) -> Guid {
        let mut g = [0u8; 16];
        let zid = u64::from_le_bytes(self.zid_bytes[..8].try_into().unwrap_or_default());
        g[..8].copy_from_slice(&(zid ^ self.salt).to_le_bytes());
        g[8..].copy_from_slice(&id.to_le_bytes());
        g
    }

    /// The key and graph entry of an endpoint on `spec` in `domain`.
    fn resolve(
        &mut self,
        domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        kind: EntityKind,
        id: u64,
    ) -> Result<(RosName, String, graph::Endpoint), BackendError> {
        let name = RosName::from_dds(&spec.name);
        let type_name = if name.is_service() {
            naming::service_type_name(&spec.type_name)
        } else {
            spec.type_name.clone()
        };
        if type_name.len() > type_hashes::MAX_TYPE_NAME {
            return Err(BackendError::InvalidInput(format!(
                "type name of {} bytes: at most {} (a ROS type's is far shorter)",
                type_name.len(),
                type_hashes::MAX_TYPE_NAME
            )));
        }
        let (hash, _) = self.hashes.lookup(&type_name);
        let key = naming::data_key(domain, &name, &type_name, &hash)
            .map_err(|e| BackendError::InvalidInput(format!("topic {:?}: {e}", spec.name)))?;
        let endpoint = graph::Endpoint {
            kind,
            id,
            name: name.qualified(),
            type_name,
            hash,
            qos: naming::qos_text(qos),
        };
        Ok((name, key, endpoint))
    }

    /// Puts an endpoint in the graph for as long as the returned entry lives.
    fn graph_entry(&self, guid: Guid, endpoint: graph::Endpoint) -> GraphEntry {
        self.endpoints.borrow_mut().insert(guid, endpoint);
        GraphEntry {
            guid,
            endpoints: self.endpoints.clone(),
        }
    }

    /// Notes a domain a group was made in (Zenoh has no partitions).
    fn enter(&mut self, domain: u16, partitions: &[String]) -> Result<Group, BackendError> {
        if !partitions.is_empty() {
            return Err(BackendError::Unsupported("Zenoh has no partitions"));
        }
        self.domains.insert(domain, ());
        Ok(Group)
    }

    fn inbox(&self, token: ReaderToken, qos: &EndpointQos) -> Arc<Inbox> {
        let (capacity, when_full) = match qos.history {
            History::KeepLast(d) => (usize::try_from(d).unwrap_or(1), WhenFull::DropOldest),
            History::KeepAll => (
                qos.resource_limits
                    .map(|r| usize::try_from(r.max_samples).unwrap_or(READER_QUEUE_MAX))
                    .unwrap_or(xrce_dds_seam::qos::KEEP_ALL_READER_SAMPLES as usize),
                WhenFull::DropNewest,
            ),
        };
        Arc::new(Inbox::new(
            token,
            capacity.clamp(1, READER_QUEUE_MAX),
            when_full,
            self.wakeup.clone(),
            self.dropped.queue_full.clone(),
            self.dropped.queued.clone(),
        ))
    }

    /// The link of the service whose writer was made just before this reader: a requester's
    /// (`requester`, its writer on `rq/<s>Request`, this reader on `rr/<s>Reply`) or a
    /// replier's. Anything else on those topics is refused: on Zenoh they exist only as the
    /// two halves of a service (a reader alone could never be answered, or answer).
    fn service_link(
        pending: Option<PendingService>,
        domain: u16,
        service: &str,
        requester: bool,
    ) -> Result<Arc<ServiceLink>, BackendError> {
        match pending {
            Some(p) if p.domain == domain && p.service == service && p.requester == requester => {
                Ok(p.link)
            }
            _ => Err(BackendError::Unsupported(
                "on Zenoh, rq/ and rr/ topics are services: only a requester or replier (its \
                 request and reply topics rq/<name>Request and rr/<name>Reply) may use them",
            )),
        }
    }
}

/// A publisher or subscriber: Zenoh has no groups (the seam keeps the domain).
#[derive(Debug)]
pub struct Group;

/// Removes an endpoint from the graph when it goes.
struct GraphEntry {
    guid: Guid,
    endpoints: Rc<RefCell<HashMap<Guid, graph::Endpoint>>>,
}

impl Drop for GraphEntry {
    fn drop(&mut self) {
        self.endpoints.borrow_mut().remove(&self.guid);
    }
}

/// The history a transient-local publisher caches, or subscriber asks for: its depth
/// (keep-all: [`xrce_dds_seam::qos::KEEP_ALL_READER_SAMPLES`]), at most [`READER_QUEUE_MAX`], so that
/// a client's QoS cannot make the worker cache without bound.
fn history_depth(qos: &EndpointQos) -> usize {
    match qos.history {
        History::KeepLast(d) => usize::try_from(d).unwrap_or(1),
        History::KeepAll => xrce_dds_seam::qos::KEEP_ALL_READER_SAMPLES as usize,
    }
    .clamp(1, READER_QUEUE_MAX)
}

/// Counts one drop in `counter` and says so in the log on the first one (the counter, in the
/// worker's status and metrics, tells how many followed).
fn count_drop(counter: &AtomicU64, what: &str) {
    if counter.fetch_add(1, Ordering::Relaxed) == 0 {
        tracing::warn!("{what} (further ones counted in the worker's status)");
    }
}

impl Endpoints for Zenoh {
    type Publisher = Group;
    type Subscriber = Group;

    fn new_publisher(&mut self, domain: u16, partitions: &[String]) -> Result<Group, BackendError> {
        self.enter(domain, partitions)
    }

    fn new_subscriber(
        &mut self,
        domain: u16,
        partitions: &[String],
    ) -> Result<Group, BackendError> {
        self.enter(domain, partitions)
    }

    fn new_writer(
        &mut self,
        _publisher: &Group,
        domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        little_endian: bool,
    ) -> Result<Box<dyn DdsWriter>, BackendError> {
        // A service's reader comes right after its writer: nothing older may pair.
        self.last_service = None;
        let id = self.next_id();
        let gid = self.gid(id);
        let kind = match RosName::from_dds(&spec.name) {
            RosName::Request(_) => EntityKind::Client,
            RosName::Reply(_) => EntityKind::Service,
            _ => EntityKind::Publisher,
        };
        let (name, key, endpoint) = self.resolve(domain, spec, qos, kind, id)?;
        let key = zenoh::key_expr::KeyExpr::try_from(key)
            .map_err(|e| BackendError::InvalidInput(format!("key expression: {e}")))?;
        let mut in_graph = true;
        let sender = match name {
            RosName::Request(service) => {
                let link = Arc::new(ServiceLink::default());
                let querier = self
                    .session
                    .declare_querier(key)
                    .target(zenoh::query::QueryTarget::AllComplete)
                    .consolidation(zenoh::query::ConsolidationMode::None)
                    .timeout(QUERY_TIMEOUT)
                    .wait()
                    .map_err(zenoh_err("Zenoh querier"))?;
                self.last_service = Some(PendingService {
                    domain,
                    service,
                    requester: true,
                    link: link.clone(),
                });
                Sender::Querier(querier, link)
            }
            RosName::Reply(service) => {
                // The replier's reader (made next) holds the queryable and its token.
                in_graph = false;
                let link = Arc::new(ServiceLink::default());
                self.last_service = Some(PendingService {
                    domain,
                    service,
                    requester: false,
                    link: link.clone(),
                });
                Sender::Replies(key, link)
            }
            _ => {
                let reliable = qos.reliability == Reliability::Reliable;
                // rmw_zenoh blocks a keep-all reliable publisher on congestion; here one slow
                // subscriber would stall the worker and every client: the agent drops.
                let congestion = zenoh::qos::CongestionControl::Drop;
                let builder = self
                    .session
                    .declare_publisher(key)
                    .congestion_control(congestion)
                    .reliability(if reliable {
                        zenoh::qos::Reliability::Reliable
                    } else {
                        zenoh::qos::Reliability::BestEffort
                    })
                    .advanced();
                let publisher = if qos.durability != Durability::Volatile {
                    let depth = history_depth(qos);
                    let b = builder
                        .cache(zenoh_ext::CacheConfig::default().max_samples(depth))
                        .publisher_detection();
                    if reliable {
                        b.sample_miss_detection(
                            zenoh_ext::MissDetectionConfig::default()
                                .sporadic_heartbeat(Duration::from_millis(500)),
                        )
                        .wait()
                    } else {
                        b.wait()
                    }
                } else {
                    builder.wait()
                };
                Sender::Publisher(publisher.map_err(zenoh_err("Zenoh publisher"))?)
            }
        };
        let graph = in_graph.then(|| self.graph_entry(gid, endpoint));
        Ok(Box::new(Writer {
            sender,
            gid,
            topic_name: spec.name.clone(),
            little_endian,
            key: spec.key.clone(),
            seq: std::cell::Cell::new(0),
            _graph: graph,
            dropped: self.dropped.clone(),
        }))
    }

    fn new_reader(
        &mut self,
        _subscriber: &Group,
        domain: u16,
        spec: &TopicSpec,
        qos: &EndpointQos,
        token: ReaderToken,
    ) -> Result<Box<dyn DdsReader>, BackendError> {
        // Only the reader made right after a service's writer may pair with it.
        let pending = self.last_service.take();
        let id = self.next_id();
        let gid = self.gid(id);
        let kind = match RosName::from_dds(&spec.name) {
            RosName::Request(_) => EntityKind::Service,
            RosName::Reply(_) => EntityKind::Client,
            _ => EntityKind::Subscription,
        };
        let (name, key, endpoint) = self.resolve(domain, spec, qos, kind, id)?;
        let key = zenoh::key_expr::KeyExpr::try_from(key)
            .map_err(|e| BackendError::InvalidInput(format!("key expression: {e}")))?;
        let inbox = self.inbox(token, qos);
        let mut in_graph = true;
        let receiver = match name {
            RosName::Request(service) => {
                let link = Self::service_link(pending, domain, &service, false)?;
                let (inbox2, link2, dropped) = (inbox.clone(), link.clone(), self.dropped.clone());
                let queryable = self
                    .session
                    .declare_queryable(key)
                    .complete(true)
                    .callback(move |query: zenoh::query::Query| {
                        let Some(a) = attachment_of(query.attachment()) else {
                            count_drop(
                                &dropped.requests_without_attachment,
                                "a Zenoh request without rmw_zenoh's attachment: not answered",
                            );
                            return;
                        };
                        let body = query.payload().map(|p| p.to_bytes().to_vec());
                        let body = body.unwrap_or_default();
                        let taken = match taken_of(&body, Some(a), None) {
                            Ok(t) => t,
                            Err(_) => {
                                // Unreadable: the query ends unanswered at once.
                                count_drop(
                                    &dropped.requests_unqueued,
                                    "an unreadable Zenoh request: not answered",
                                );
                                return;
                            }
                        };
                        let id = (a.gid, a.sequence_number);
                        // Kept before the request is queued: the worker may answer at once.
                        let evicted = lock(&link2.queries).insert(id, body.len(), query);
                        if evicted > 0 {
                            count_drop(
                                &dropped.pending_requests_evicted,
                                "a replier holds 4,096 requests (or 64 MiB) waiting for replies: \
                                 the oldest go unanswered",
                            );
                            dropped
                                .pending_requests_evicted
                                .fetch_add(evicted as u64 - 1, Ordering::Relaxed);
                        }
                        let pushed = inbox2.push(Ok(taken));
                        let mut queries = lock(&link2.queries);
                        if !pushed.queued {
                            count_drop(
                                &dropped.requests_unqueued,
                                "a Zenoh request dropped by its replier's full queue: not answered",
                            );
                            queries.take(&id);
                        }
                        // Requests given up for it will never be answered: let them go.
                        for old in pushed.evicted.into_iter().flatten() {
                            queries.take(&(old.identity.writer, old.identity.sequence_number));
                        }
                    })
                    .wait()
                    .map_err(zenoh_err("Zenoh queryable"))?;
                Receiver::Queryable(queryable)
            }
            RosName::Reply(service) => {
                in_graph = false;
                let link = Self::service_link(pending, domain, &service, true)?;
                *lock(&link.replies) = Some(inbox.clone());
                Receiver::Replies(link)
            }
            _ => {
                if let Some(p) = pending {
                    tracing::warn!(
                        service = %p.service,
                        "a requester's or replier's reader is not on its rr/ or rq/ topic: \
                         on Zenoh it cannot serve the service"
                    );
                }
                let inbox2 = inbox.clone();
                let builder = self
                    .session
                    .declare_subscriber(key)
                    .callback(move |s: zenoh::sample::Sample| {
                        let attachment = attachment_of(s.attachment());
                        inbox2.push(taken_of(&s.payload().to_bytes(), attachment, None));
                    })
                    .advanced();
                let subscriber = if qos.durability != Durability::Volatile {
                    let depth = history_depth(qos);
                    let b = builder
                        .history(
                            zenoh_ext::HistoryConfig::default()
                                .detect_late_publishers()
                                .max_samples(depth),
                        )
                        .subscriber_detection()
                        .query_timeout(Duration::from_secs(u32::MAX as u64));
                    if qos.reliability == Reliability::Reliable {
                        b.recovery(zenoh_ext::RecoveryConfig::default().heartbeat())
                            .wait()
                    } else {
                        b.wait()
                    }
                } else {
                    builder.wait()
                };
                Receiver::Subscriber(subscriber.map_err(zenoh_err("Zenoh subscriber"))?)
            }
        };
        let graph = in_graph.then(|| self.graph_entry(gid, endpoint));
        Ok(Box::new(Reader {
            inbox,
            gid,
            receiver,
            _graph: graph,
        }))
    }
}

impl DdsBackend for Zenoh {
    fn name(&self) -> &'static str {
        "zenoh"
    }

    fn participant_guid(&mut self, domain: u16) -> Result<Guid, BackendError> {
        let mut g = [0u8; 16];
        g[..14].copy_from_slice(&self.zid_bytes[..14]);
        g[14..].copy_from_slice(&domain.to_be_bytes());
        Ok(g)
    }

    fn readiness_fd(&self) -> BorrowedFd<'_> {
        self.wakeup.fd()
    }

    fn ready_readers(&mut self, out: &mut Vec<ReaderToken>) -> std::io::Result<()> {
        self.wakeup.drain(out)
    }

    fn participants(&self) -> usize {
        self.domains.len()
    }

    fn participant_domains(&self) -> Vec<u16> {
        self.domains.keys().copied().collect()
    }

    fn release_domain(&mut self, domain: u16) {
        self.domains.remove(&domain);
        self.graph.forget(domain);
    }

    fn announces_graph(&self) -> bool {
        true
    }

    fn announce_graph(&mut self, domain: u16, nodes: &DomainNodes) -> Result<(), BackendError> {
        let endpoints = self.endpoints.borrow();
        let wanted = self
            .graph
            .wanted(domain, &self.zid, nodes, &endpoints, &mut self.next_id);
        drop(endpoints);
        self.graph.apply(domain, wanted, &self.session)
    }

    fn dropped(&self) -> Vec<(&'static str, u64)> {
        let d = &self.dropped;
        vec![
            (
                "zenoh_reader_queue_full",
                d.queue_full.load(Ordering::Relaxed),
            ),
            (
                "zenoh_request_without_attachment",
                d.requests_without_attachment.load(Ordering::Relaxed),
            ),
            (
                "zenoh_request_not_queued",
                d.requests_unqueued.load(Ordering::Relaxed),
            ),
            (
                "zenoh_request_in_flight_refused",
                d.requests_refused_in_flight.load(Ordering::Relaxed),
            ),
            (
                "zenoh_reply_without_request",
                d.replies_without_request.load(Ordering::Relaxed),
            ),
            (
                "zenoh_request_evicted",
                d.pending_requests_evicted.load(Ordering::Relaxed),
            ),
        ]
    }
}
