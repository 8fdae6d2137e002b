//! iceoryx2 ports for the IPC contract: `[u8]` publish-subscribe paired with events.
//!
//! Every process opens the same services with the same settings (iceoryx2 requires it).
//! A [`Sender`] loans a shared-memory sample, lets the caller fill it in place (one copy from
//! wherever the bytes are) and publishes it; one [`Sender::notify`] per burst wakes the
//! receiver. A [`Receiver`] exposes the file descriptor of its event listener for `poll(2)`.
//!
//! Where iceoryx2's files are ([`IpcNode::new`]): its root, with the node and service files
//! and the event sockets, is the private `<runtime>/ipc/` (see [`crate::runtime_dir`]);
//! the shared-memory segments (`xrce_<instance>_*` in `/dev/shm`) are 0600.

use std::os::fd::{AsFd, AsRawFd, BorrowedFd, RawFd};

use iceoryx2::port::backpressure_strategy::BackpressureStrategy;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

use crate::{Encode, CHANNEL_DEPTH, HEADER_LEN, INITIAL_BODY, MAX_BODY};

/// An iceoryx2 failure, with what was being done.
#[derive(Debug, thiserror::Error)]
#[error("iceoryx2: {what}: {detail}")]
pub struct ShmError {
    what: &'static str,
    detail: String,
}

fn err<E: std::fmt::Debug>(what: &'static str) -> impl FnOnce(E) -> ShmError {
    move |e| ShmError {
        what,
        detail: format!("{e:?}"),
    }
}

/// How a service behaves when a receiver's queue is full, and for late joiners.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServiceKind {
    /// Operations to the worker: senders keep below the queue depth themselves
    /// ([`crate::IN_FLIGHT_WINDOW`]), so overflow cannot happen; no history.
    Data,
    /// Replies and samples to a front-end: a full queue refuses the message (never
    /// overwrites), and [`Sender::send`] reports it, so the worker can hold it back.
    Reply,
    /// Worker announcements: the last one is kept for front-ends that start later.
    Announce,
}

/// Most front-ends of one agent instance (each subscribes to the worker's announcements).
pub const MAX_FRONTENDS: usize = 64;

/// Receivers a service has: every front-end hears the announcements; requests have the
/// worker, replies their front-end (two each, so that a restarted process can subscribe
/// before its dead predecessor's port is cleaned up).
fn max_receivers(kind: ServiceKind) -> usize {
    match kind {
        ServiceKind::Announce => MAX_FRONTENDS + 2,
        ServiceKind::Data | ServiceKind::Reply => 2,
    }
}

/// Messages a receiver's queue holds. A worker announces itself once per start, so a few
/// are plenty there; the depth matters because iceoryx2 sizes a publisher's bookkeeping by
/// receivers times depth, times its possible segments, and fills it at once: with the
/// operations' depth the announcements alone took 34 MiB of the worker's memory.
fn queue_depth(kind: ServiceKind) -> usize {
    match kind {
        ServiceKind::Announce => 4,
        ServiceKind::Data | ServiceKind::Reply => CHANNEL_DEPTH,
    }
}

/// One iceoryx2 node of an agent instance.
#[derive(Debug)]
pub struct IpcNode {
    node: Node<ipc::Service>,
}

pub use crate::names::{file_prefix, node_prefix, valid_instance, EVENT_SUFFIX};

/// The directory of POSIX shared memory (where `shm_open` puts its objects).
const SHM_DIR: &str = "/dev/shm";

impl IpcNode {
    /// Creates the node `name` of agent instance `instance`; all its files carry a prefix
    /// derived from the instance, so instances never see each other.
    ///
    /// iceoryx2's root (its node and service files and its event sockets, `/tmp/iceoryx2/`
    /// by default) is the private [`crate::runtime_dir::ipc_root`] (0700); its shared-memory
    /// segments stay in `/dev/shm` (POSIX shared memory has no directory to choose), where
    /// iceoryx2 makes them 0600, except the 16-byte node counter it makes 0666, which is
    /// made 0600 here. Files with this instance's prefix in `/dev/shm` that are not this
    /// user's regular files (planted to be opened as the instance's) are refused.
    pub fn new(instance: &str, name: &str) -> Result<Self, ShmError> {
        if !valid_instance(instance) {
            return Err(ShmError {
                what: "instance name",
                detail: format!("{instance:?} is not [A-Za-z0-9_-]{{1,32}}"),
            });
        }
        let private = |e: crate::runtime_dir::RuntimeDirError| ShmError {
            what: "private runtime directory",
            detail: e.to_string(),
        };
        crate::runtime_dir::check_instance_dir(instance).map_err(private)?;
        let root = crate::runtime_dir::ensure_ipc_root(instance).map_err(private)?;
        let token =
            crate::runtime_dir::secret(instance, crate::runtime_dir::SHM_TOKEN).map_err(private)?;
        let prefix = node_prefix(instance, &token);
        check_shm_files(&prefix)?;
        set_log_level(LogLevel::Error);
        let mut config = Config::default();
        config.global.prefix = FileName::new(prefix.as_bytes()).map_err(err("prefix"))?;
        {
            use std::os::unix::ffi::OsStrExt;
            let root = Path::new(root.as_os_str().as_bytes()).map_err(err("root path"))?;
            config.global.set_root_path(&root);
        }
        config.global.service.event_connection_suffix =
            FileName::new(EVENT_SUFFIX.as_bytes()).map_err(err("event suffix"))?;
        let node = NodeBuilder::new()
            .name(&NodeName::new(name).map_err(err("node name"))?)
            .config(&config)
            .create::<ipc::Service>()
            .map_err(err("create node"))?;
        make_node_counter_private(&prefix);
        Ok(IpcNode { node })
    }

    /// How many other live nodes of this instance carry this node's name and were created
    /// before it: a second front-end with the same id, say, which this one must not replace.
    /// Ties (created in the same nanosecond) go to the lower id.
    pub fn older_namesakes(&self) -> usize {
        use iceoryx2::node::{NodeState, NodeView};
        let me = *self.node.id();
        let name = self.node.name().clone();
        let key = |id: &iceoryx2::identifiers::UniqueNodeId| {
            let t = id
                .creation_time::<ipc::Service>()
                .map(|t| t.as_duration())
                .unwrap_or_default();
            (t, id.value())
        };
        let mine = key(&me);
        let mut n = 0;
        let _ = Node::<ipc::Service>::list(self.node.config(), |state| {
            if let NodeState::Alive(v) = &state {
                let same_name = v.details().as_ref().is_some_and(|d| *d.name() == name);
                if *v.id() != me && same_name && key(v.id()) < mine {
                    n += 1;
                }
            }
            CallbackProgression::Continue
        });
        n
    }

    /// The names of this instance's live nodes, and of its dead ones (whose resources this
    /// call removes, as far as it can).
    pub fn nodes(&self) -> NodeCensus {
        use iceoryx2::node::{NodeState, NodeView};
        let mut census = NodeCensus::default();
        let _ = Node::<ipc::Service>::list(self.node.config(), |state| {
            match state {
                NodeState::Alive(v) => {
                    if let Some(d) = v.details() {
                        census.alive.push(d.name().to_string());
                    }
                }
                NodeState::Dead(v) => {
                    if let Some(d) = v.details() {
                        census.dead.push(d.name().to_string());
                    }
                    let _ = v.try_remove_stale_resources();
                }
                _ => {}
            }
            CallbackProgression::Continue
        });
        census
    }

    /// Whether SIGINT or SIGTERM arrived (iceoryx2's handler records them).
    pub fn termination_requested(&self) -> bool {
        self.node.wait(std::time::Duration::ZERO).is_err()
    }

    fn pubsub(
        &self,
        service: &str,
        kind: ServiceKind,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [u8], ()>,
        ShmError,
    > {
        let name = ServiceName::new(service).map_err(err("service name"))?;
        self.node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .max_publishers(64)
            .max_subscribers(max_receivers(kind))
            .subscriber_max_buffer_size(queue_depth(kind))
            .subscriber_max_borrowed_samples(2)
            .history_size(if kind == ServiceKind::Announce { 1 } else { 0 })
            .enable_safe_overflow(kind != ServiceKind::Reply)
            .open_or_create()
            .map_err(err("open publish-subscribe service"))
    }

    fn event(
        &self,
        service: &str,
        kind: ServiceKind,
    ) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, ShmError> {
        let name = ServiceName::new(&crate::event_service(service)).map_err(err("service name"))?;
        self.node
            .service_builder(&name)
            .event()
            .max_notifiers(64)
            .max_listeners(max_receivers(kind).max(4))
            .open_or_create()
            .map_err(err("open event service"))
    }

    /// A sender on `service`.
    pub fn sender(&self, service: &str, kind: ServiceKind) -> Result<Sender, ShmError> {
        let publisher = self
            .pubsub(service, kind)?
            .publisher_builder()
            // Sized for ordinary samples; a bigger one (up to MAX_BODY) makes the publisher
            // map a larger segment, which receivers follow.
            .initial_max_slice_len(HEADER_LEN + INITIAL_BODY)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(4)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(err("create publisher"))?;
        let notifier = self
            .event(service, kind)?
            .notifier_builder()
            .create()
            .map_err(err("create notifier"))?;
        Ok(Sender {
            publisher,
            notifier,
        })
    }

    /// A receiver on `service`.
    pub fn receiver(&self, service: &str, kind: ServiceKind) -> Result<Receiver, ShmError> {
        let subscriber = self
            .pubsub(service, kind)?
            .subscriber_builder()
            .create()
            .map_err(err("create subscriber"))?;
        let listener = self
            .event(service, kind)?
            .listener_builder()
            .create()
            .map_err(err("create listener"))?;
        Ok(Receiver {
            subscriber,
            listener,
        })
    }
}

/// Refuses to open an instance whose names of this run (`prefix`, its random part
/// included) in `/dev/shm` are taken by something that is not this user's regular file:
/// someone who saw them could have made it so that the agent maps memory that user reads
/// or writes. Files of another user under the instance's other names (an earlier run's,
/// or planted under a guess) are not the instance's and are left alone.
fn check_shm_files(prefix: &str) -> Result<(), ShmError> {
    use std::os::unix::fs::MetadataExt;
    let Ok(dir) = std::fs::read_dir(SHM_DIR) else {
        return Ok(());
    };
    let me = crate::runtime_dir::euid();
    for e in dir.flatten() {
        let named = e
            .file_name()
            .to_str()
            .is_some_and(|n| n.starts_with(prefix));
        if !named {
            continue;
        }
        let Ok(m) = std::fs::symlink_metadata(e.path()) else {
            continue;
        };
        if m.uid() != me || !m.is_file() {
            return Err(ShmError {
                what: "shared memory not ours",
                detail: format!(
                    "{} is {} of uid {} (this user is uid {me}): another user may have \
                     planted it to read or forge this instance's messages; remove it (as its \
                     owner or root), or start the agent again (a new start draws new names)",
                    e.path().display(),
                    if m.is_file() {
                        "a file"
                    } else {
                        "not a regular file"
                    },
                    m.uid()
                ),
            });
        }
    }
    Ok(())
}

/// iceoryx2 makes its per-prefix node counter (`<prefix>node.<version>.global_mgmt` in
/// `/dev/shm`) readable and writable by everyone, for processes of other users in the same
/// iceoryx2 domain; an agent's processes all run as one user, so it is made 0600 (opened
/// without following links, and only if it is ours).
fn make_node_counter_private(prefix: &str) {
    use std::os::unix::fs::{MetadataExt, OpenOptionsExt, PermissionsExt};
    let Ok(dir) = std::fs::read_dir(SHM_DIR) else {
        return;
    };
    for e in dir.flatten() {
        let counter = e
            .file_name()
            .to_str()
            .is_some_and(|n| n.starts_with(prefix) && n.ends_with(".global_mgmt"));
        if !counter {
            continue;
        }
        let opened = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
            .open(e.path());
        let Ok(f) = opened else { continue };
        let Ok(m) = f.metadata() else { continue };
        if m.is_file() && m.uid() == crate::runtime_dir::euid() && m.mode() & 0o077 != 0 {
            if let Err(err) = f.set_permissions(std::fs::Permissions::from_mode(0o600)) {
                tracing::debug!(path = %e.path().display(), error = %err, "iceoryx2's node counter stays shared");
            }
        }
    }
}

/// Removes what an instance leaves after its last node is gone: in `/dev/shm`, the 16-byte
/// `global_mgmt` object iceoryx2 keeps per prefix; in iceoryx2's root, whatever files of the
/// instance are left (a process killed while it created its node leaves the node's monitor
/// files without its details, which iceoryx2's census lists neither alive nor dead, so no
/// new node removes them). Call only when no process of the instance runs any more.
/// Returns how many files were removed.
pub fn remove_instance_leftovers(instance: &str) -> usize {
    if !valid_instance(instance) {
        return 0;
    }
    let prefix = file_prefix(instance);
    let remove_in = |dir: &std::path::Path, keep: &dyn Fn(&str) -> bool| -> usize {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return 0;
        };
        entries
            .flatten()
            .filter(|e| {
                let ours = e.file_type().is_ok_and(|t| !t.is_dir());
                ours && e
                    .file_name()
                    .to_str()
                    .is_some_and(|n| n.starts_with(&prefix) && !keep(n))
            })
            .filter(|e| std::fs::remove_file(e.path()).is_ok())
            .count()
    };
    let mut removed = remove_in(std::path::Path::new(SHM_DIR), &|n| {
        !n.ends_with(".global_mgmt")
    });
    let root = crate::runtime_dir::ipc_root(instance);
    for sub in ["", "services", "nodes"] {
        removed += remove_in(&root.join(sub), &|_| false);
    }
    removed
}

/// Instances named `<stem><pid>` with files in `/dev/shm` whose process no longer exists
/// (agents that died without cleaning up).
pub fn dead_instances(stem: &str) -> Vec<String> {
    let prefix = format!("xrce_{stem}");
    let mut out: Vec<String> = Vec::new();
    let Ok(dir) = std::fs::read_dir(SHM_DIR) else {
        return out;
    };
    for e in dir.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(&prefix) else {
            continue;
        };
        let pid: String = rest.chars().take_while(char::is_ascii_digit).collect();
        if pid.is_empty() || !rest[pid.len()..].starts_with('_') {
            continue;
        }
        let alive = std::path::Path::new("/proc").join(&pid).exists();
        let instance = format!("{stem}{pid}");
        if !alive && valid_instance(&instance) && !out.contains(&instance) {
            out.push(instance);
        }
    }
    out
}

/// Files of an instance still present in `/dev/shm` and in iceoryx2's root (its event
/// sockets, service and node files), for tests and diagnostics; those in the root are
/// named by their path under it.
pub fn instance_files(instance: &str) -> Vec<String> {
    let prefix = file_prefix(instance);
    let named = |dir: &std::path::Path, shown: &str| -> Vec<String> {
        std::fs::read_dir(dir)
            .map(|d| {
                d.flatten()
                    .filter_map(|e| e.file_name().into_string().ok())
                    .filter(|n| n.starts_with(&prefix))
                    .map(|n| format!("{shown}{n}"))
                    .collect()
            })
            .unwrap_or_default()
    };
    let mut out = named(std::path::Path::new(SHM_DIR), "");
    if valid_instance(instance) {
        let root = crate::runtime_dir::ipc_root(instance);
        for sub in ["", "services/", "nodes/"] {
            out.extend(named(&root.join(sub), &format!("{}{sub}", root.display())));
        }
    }
    out
}

/// Publishes IPC messages on one service.
#[derive(Debug)]
pub struct Sender {
    publisher: Publisher<ipc::Service, [u8], ()>,
    notifier: Notifier<ipc::Service>,
}

impl Sender {
    /// Publishes `message`, encoded in place in shared memory. Returns whether a receiver
    /// took it (false: no receiver, or its queue is full).
    pub fn send(&self, message: &impl Encode) -> Result<bool, ShmError> {
        let len = message.encoded_len();
        if len > HEADER_LEN + MAX_BODY {
            return Err(ShmError {
                what: "send",
                detail: format!(
                    "body of {} bytes exceeds {MAX_BODY}",
                    len.saturating_sub(HEADER_LEN)
                ),
            });
        }
        let mut sample = self.publisher.loan_slice(len).map_err(err("loan"))?;
        message.encode_into(sample.payload_mut());
        let receivers = sample.send().map_err(err("send"))?;
        Ok(receivers > 0)
    }

    /// Publishes a message encoded already (header and body); returns whether a receiver
    /// took it.
    pub fn send_encoded(&self, message: &[u8]) -> Result<bool, ShmError> {
        let mut sample = self
            .publisher
            .loan_slice(message.len())
            .map_err(err("loan"))?;
        sample.payload_mut().copy_from_slice(message);
        let receivers = sample.send().map_err(err("send"))?;
        Ok(receivers > 0)
    }

    /// Wakes the receiver (once per burst is enough).
    pub fn notify(&self) -> Result<(), ShmError> {
        self.notifier.notify().map(|_| ()).map_err(err("notify"))
    }
}

/// The nodes of an instance by state ([`IpcNode::nodes`]).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeCensus {
    /// Names of the live nodes.
    pub alive: Vec<String>,
    /// Names of the nodes whose process died without removing them.
    pub dead: Vec<String>,
}

/// Receives IPC messages of one service.
#[derive(Debug)]
pub struct Receiver {
    subscriber: Subscriber<ipc::Service, [u8], ()>,
    listener: Listener<ipc::Service>,
}

/// The listener's descriptor, borrowed for as long as the receiver lives.
impl AsFd for Receiver {
    fn as_fd(&self) -> BorrowedFd<'_> {
        crate::sys::listener_fd(&self.listener)
    }
}

impl Receiver {
    /// A file descriptor that becomes readable when a sender notifies (see [`AsFd`]).
    pub fn raw_fd(&self) -> RawFd {
        self.as_fd().as_raw_fd()
    }

    /// Consumes pending wake-ups (otherwise the descriptor stays readable).
    pub fn clear_events(&self) {
        let _ = self.listener.try_wait(|_| {});
    }

    /// Consumes pending wake-ups; whether a sender notified since they were last consumed.
    pub fn take_events(&self) -> bool {
        let mut any = false;
        let _ = self.listener.try_wait(|_| any = true);
        any
    }

    /// Calls `f` with every message received so far; returns how many.
    pub fn drain(&self, mut f: impl FnMut(&[u8])) -> Result<usize, ShmError> {
        let mut n = 0;
        while let Some(sample) = self.subscriber.receive().map_err(err("receive"))? {
            f(sample.payload());
            n += 1;
        }
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A node killed while it was being made leaves monitor files without details, which
    /// no census lists as dead: the last clean-up of the instance removes them.
    #[test]
    fn the_last_clean_up_removes_a_half_made_nodes_files() {
        let instance = format!("shmleft-{}", std::process::id());
        drop(IpcNode::new(&instance, "test").expect("node"));
        let nodes = crate::runtime_dir::ipc_root(&instance).join("nodes");
        let half = nodes.join(format!("{}0123_abc.node_monitor", file_prefix(&instance)));
        std::fs::write(&half, b"").expect("a half-made node's file");
        assert!(!instance_files(&instance).is_empty());
        assert!(remove_instance_leftovers(&instance) >= 1);
        assert_eq!(instance_files(&instance), Vec::<String>::new());
        let _ = std::fs::remove_dir_all(crate::runtime_dir::instance_dir(&instance));
    }

    #[test]
    fn bodies_beyond_the_initial_segment_size_get_through() {
        use crate::{ReplyMessage, Route, Sample, SampleIdentity};
        use std::borrow::Cow;
        let sample = |data: Vec<u8>| {
            ReplyMessage::new(
                Route::frontend(1),
                crate::Reply::Sample(Sample {
                    identity: SampleIdentity::default(),
                    origin: None,
                    data: Cow::Owned(data),
                    little_endian: true,
                    disposed: false,
                    unregistered: false,
                }),
            )
        };
        let instance = format!("shmtest-{}", std::process::id());
        {
            let node = IpcNode::new(&instance, "test").expect("node");
            let rx = node.receiver("big", ServiceKind::Reply).expect("receiver");
            let tx = node.sender("big", ServiceKind::Reply).expect("sender");
            let identity = 24;
            let sizes = [10, INITIAL_BODY + 1, 300_000, MAX_BODY - identity, 20];
            for (i, n) in sizes.iter().enumerate() {
                let body: Vec<u8> = (0..*n).map(|k| (k * 7 + i) as u8).collect();
                let m = sample(body);
                assert!(tx.send(&m).expect("send"), "{n} bytes");
                let mut got = Vec::new();
                rx.drain(|m| got.push(m.to_vec())).expect("drain");
                assert_eq!(got.len(), 1);
                let back = ReplyMessage::decode(&got[0]).expect("decodes");
                assert_eq!(back, m, "{n} bytes");
            }
            let too_big = sample(vec![0u8; MAX_BODY + 1 - identity]);
            assert!(tx.send(&too_big).is_err());
        }
        remove_instance_leftovers(&instance);
    }
}
