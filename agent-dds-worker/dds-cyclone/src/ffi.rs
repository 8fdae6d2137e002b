//! The worker's only `unsafe` code: a safe API over Cyclone DDS's C library (through the
//! `cyclors` bindings) for the Cyclone backend.
//!
//! What it offers: domains pinned by configuration, participants, publishers, subscribers,
//! topics of raw serialized samples (keyed or not), writers that write and dispose raw
//! samples, readers that take them with their writer's GUID and sequence number, QoS, matched
//! counts, acknowledgement status, and a readiness descriptor fed by reader listeners.
//!
//! # Invariants
//!
//! * Every entity handle is owned by one Rust value ([`Entity`], [`Reader`]) that deletes it
//!   once. Deleting a parent first (Cyclone deletes children with it) makes a child's later
//!   `dds_delete` fail harmlessly with `BAD_PARAMETER`; it never touches freed memory, since a
//!   handle is a number looked up in Cyclone's table.
//! * Samples are this module's own serdata ([`Serdata`], `repr(C)` with Cyclone's
//!   `ddsi_serdata` first), made only by the functions of [`SERDATA_OPS`] and by
//!   [`Writer`], and freed only by `serdata_free` when Cyclone's reference count drops to
//!   zero. A serdata is read through a pointer only after checking that its `ops` are
//!   [`SERDATA_OPS`].
//! * Sertypes are this module's own ([`Sertype`], `ddsi_sertype` first), boxed, handed to
//!   `dds_create_topic_sertype`, which owns them from then on and frees them through
//!   `sertype_free`; if it fails, the box is taken back and freed here.
//! * The callbacks Cyclone makes (serdata/sertype operations on its receive and delivery
//!   threads, listeners on its event threads or inside `dds_writecdr` for local readers) touch
//!   only the object they are given, immutable data ([`KeyDescriptor`] behind an `Arc`), and
//!   the thread-safe [`ReadyShared`]; none calls back into Cyclone except `ddsi_serdata_init`
//!   and `ddsi_serdata_unref`. None panics on any input (the key walk returns errors), so no
//!   unwinding reaches C.
//! * A listener's argument (an `Arc<ReaderSignal>` turned into a raw pointer) outlives its
//!   reader: [`Reader`]'s `Drop` deletes the reader (Cyclone waits for a running listener
//!   call to finish) before taking the `Arc` back.
//! * `from_ser` reads Cyclone's receive buffer through [`Rdata`] and [`Rmsg`], mirrors of
//!   `struct ddsi_rdata` / `struct ddsi_rmsg` of Cyclone DDS 11.0.1 (`ddsi_radmin.h`), the
//!   version cyclors 0.4.0 bundles (pinned exactly in Cargo.toml). The writer's sequence
//!   number is read from the DATA / DATA_FRAG submessage only when the submessage id says it
//!   is one, and every offset is checked against the sizes Cyclone gives.

use std::collections::HashMap;
use std::ffi::{c_char, c_void, CStr, CString};
use std::io::{Read, Write};
use std::os::fd::{AsFd, BorrowedFd};
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use cyclors as c;

use xrce_dds_seam::types::KeyDescriptor;
use xrce_dds_seam::BackendError;

/// A Cyclone entity handle.
pub(super) type Handle = c::dds_entity_t;

/// Cyclone's text for a return code.
fn retcode(r: c::dds_return_t) -> String {
    // SAFETY: dds_strretcode returns a pointer to a static string for any value.
    let p = unsafe { c::dds_strretcode(r) };
    if p.is_null() {
        return format!("error {r}");
    }
    // SAFETY: non-null, NUL-terminated, static.
    unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned()
}

fn check(r: c::dds_return_t, what: &str) -> Result<(), BackendError> {
    if r < 0 {
        Err(BackendError::Dds(format!("{what}: {}", retcode(r))))
    } else {
        Ok(())
    }
}

fn cstring(s: &str, what: &str) -> Result<CString, BackendError> {
    CString::new(s)
        .map_err(|_| BackendError::InvalidInput(format!("{what} {s:?} contains a NUL byte")))
}

/// An owned entity, deleted when dropped.
#[derive(Debug)]
pub(super) struct Entity(Handle);

impl Entity {
    fn new(h: Handle, what: &str) -> Result<Self, BackendError> {
        if h < 0 {
            Err(BackendError::Dds(format!("{what}: {}", retcode(h))))
        } else {
            Ok(Entity(h))
        }
    }

    /// Its handle, for creating children.
    pub(super) fn handle(&self) -> Handle {
        self.0
    }

    /// Its GUID.
    pub(super) fn guid(&self) -> Result<[u8; 16], BackendError> {
        guid_of(self.0)
    }
}

impl Drop for Entity {
    fn drop(&mut self) {
        // SAFETY: a handle is looked up by number; a stale one returns an error.
        unsafe { c::dds_delete(self.0) };
    }
}

fn guid_of(h: Handle) -> Result<[u8; 16], BackendError> {
    let mut g = c::dds_guid_t { v: [0; 16] };
    // SAFETY: g is a valid out pointer.
    check(unsafe { c::dds_get_guid(h, &mut g) }, "get GUID")?;
    Ok(g.v)
}

/// A domain with its configuration and one participant in it.
#[derive(Debug)]
pub(super) struct Participant {
    // Declared first: dropped (deleted) before its domain.
    participant: Entity,
    _domain: Option<Entity>,
}

impl Participant {
    /// A participant in `domain`, whose domain is configured by `config_xml` (Cyclone's XML
    /// configuration; `None`: Cyclone's defaults and `CYCLONEDDS_URI`).
    pub(super) fn new(domain: u32, config_xml: Option<&str>) -> Result<Self, BackendError> {
        let domain_entity = match config_xml {
            Some(xml) => {
                let xml = cstring(xml, "configuration")?;
                // SAFETY: xml is a valid C string for the call's duration (Cyclone copies it).
                let h = unsafe { c::dds_create_domain(domain, xml.as_ptr()) };
                Some(Entity::new(h, "create DDS domain")?)
            }
            None => None,
        };
        // SAFETY: null QoS and listener are allowed.
        let h = unsafe { c::dds_create_participant(domain, std::ptr::null(), std::ptr::null()) };
        Ok(Participant {
            participant: Entity::new(h, "create DDS participant")?,
            _domain: domain_entity,
        })
    }

    /// Its handle.
    pub(super) fn handle(&self) -> Handle {
        self.participant.handle()
    }

    /// Its GUID.
    pub(super) fn guid(&self) -> Result<[u8; 16], BackendError> {
        self.participant.guid()
    }

    /// A publisher (`publish`) or subscriber with the given partitions (none: the default
    /// partition).
    pub(super) fn create_group(
        &self,
        publish: bool,
        partitions: &[String],
    ) -> Result<Entity, BackendError> {
        let mut qos = Qos::new()?;
        if !partitions.is_empty() {
            qos.partitions(partitions)?;
        }
        // SAFETY: valid participant handle number, valid QoS, null listener.
        let h = unsafe {
            if publish {
                c::dds_create_publisher(self.handle(), qos.0, std::ptr::null())
            } else {
                c::dds_create_subscriber(self.handle(), qos.0, std::ptr::null())
            }
        };
        Entity::new(
            h,
            if publish {
                "create publisher"
            } else {
                "create subscriber"
            },
        )
    }

    /// A topic of raw samples: keyed by `key` when given.
    pub(super) fn create_topic(
        &self,
        name: &str,
        type_name: &str,
        key: Option<Arc<KeyDescriptor>>,
    ) -> Result<Entity, BackendError> {
        let cname = cstring(name, "topic name")?;
        let ctype = cstring(type_name, "type name")?;
        let flags = if key.is_none() {
            c::DDSI_SERTYPE_FLAG_TOPICKIND_NO_KEY
        } else {
            0
        };
        let st = Box::new(Sertype {
            // SAFETY: an all-zero ddsi_sertype is what ddsi_sertype_init_flags expects to
            // fill in (plain data and null pointers).
            common: unsafe { std::mem::zeroed() },
            tag: fnv1a(
                fnv1a(0x811c_9dc5, type_name.as_bytes()),
                &[u8::from(key.is_some())],
            ),
            key,
        });
        let st = Box::into_raw(st);
        // SAFETY: st points to a live Sertype whose first field is the ddsi_sertype; the
        // type name is copied by Cyclone; the ops are 'static.
        unsafe {
            c::ddsi_sertype_init_flags(
                &mut (*st).common,
                ctype.as_ptr(),
                &SERTYPE_OPS.0,
                &SERDATA_OPS.0,
                flags,
            );
        }
        let mut ptr = st as *mut c::ddsi_sertype;
        // SAFETY: ptr is a fully initialised sertype; on success Cyclone owns it (or an equal
        // one it already had, releasing ours through sertype_free).
        let h = unsafe {
            c::dds_create_topic_sertype(
                self.handle(),
                cname.as_ptr(),
                &mut ptr,
                std::ptr::null(),
                std::ptr::null(),
                std::ptr::null(),
            )
        };
        if h < 0 {
            // SAFETY: on failure Cyclone did not take the sertype: finish and free it here.
            unsafe { sertype_free(st as *mut c::ddsi_sertype) };
        }
        Entity::new(h, &format!("create topic {name:?}"))
    }
}

/// A QoS object, deleted when dropped.
#[derive(Debug)]
pub struct Qos(*mut c::dds_qos_t);

/// How reliable an endpoint is.
#[derive(Debug, Clone, Copy)]
pub enum ReliabilityKind {
    /// Best effort.
    BestEffort,
    /// Reliable, blocking a write at most this many nanoseconds.
    Reliable(i64),
}

/// Durability kinds.
#[derive(Debug, Clone, Copy)]
pub enum DurabilityKind {
    /// Volatile.
    Volatile,
    /// Transient local.
    TransientLocal,
    /// Transient.
    Transient,
    /// Persistent.
    Persistent,
}

/// Liveliness kinds.
#[derive(Debug, Clone, Copy)]
pub enum LivelinessKind {
    /// Automatic.
    Automatic,
    /// Manual by participant.
    ManualByParticipant,
    /// Manual by topic.
    ManualByTopic,
}

/// Presentation access scopes.
#[derive(Debug, Clone, Copy)]
pub enum AccessScope {
    /// Instance.
    Instance,
    /// Topic.
    Topic,
    /// Group.
    Group,
}

/// Nanoseconds meaning "infinite".
pub(super) const INFINITY: i64 = i64::MAX;

impl Qos {
    /// An empty QoS (every policy Cyclone's default).
    pub fn new() -> Result<Self, BackendError> {
        // SAFETY: allocates; null on out of memory.
        let q = unsafe { c::dds_create_qos() };
        if q.is_null() {
            return Err(BackendError::Dds("out of memory creating a QoS".into()));
        }
        Ok(Qos(q))
    }

    /// Reliability.
    pub fn reliability(&mut self, kind: ReliabilityKind) {
        let (k, blocking) = match kind {
            ReliabilityKind::BestEffort => (c::dds_reliability_kind_DDS_RELIABILITY_BEST_EFFORT, 0),
            ReliabilityKind::Reliable(ns) => (c::dds_reliability_kind_DDS_RELIABILITY_RELIABLE, ns),
        };
        // SAFETY: self.0 is a live QoS (here and in every setter below).
        unsafe { c::dds_qset_reliability(self.0, k, blocking) };
    }

    /// Durability.
    pub fn durability(&mut self, kind: DurabilityKind) {
        let k = match kind {
            DurabilityKind::Volatile => c::dds_durability_kind_DDS_DURABILITY_VOLATILE,
            DurabilityKind::TransientLocal => c::dds_durability_kind_DDS_DURABILITY_TRANSIENT_LOCAL,
            DurabilityKind::Transient => c::dds_durability_kind_DDS_DURABILITY_TRANSIENT,
            DurabilityKind::Persistent => c::dds_durability_kind_DDS_DURABILITY_PERSISTENT,
        };
        unsafe { c::dds_qset_durability(self.0, k) };
    }

    /// What a transient-local (or stronger) writer keeps for late-joining readers:
    /// keep-last `depth` or keep-all (`None`) per instance, within the limits (-1:
    /// unlimited). Cyclone's default keeps the last sample only.
    pub fn durability_service(
        &mut self,
        depth: Option<i32>,
        samples: i32,
        instances: i32,
        per_instance: i32,
    ) {
        let (kind, depth) = match depth {
            Some(d) => (c::dds_history_kind_DDS_HISTORY_KEEP_LAST, d),
            None => (c::dds_history_kind_DDS_HISTORY_KEEP_ALL, -1),
        };
        unsafe {
            c::dds_qset_durability_service(self.0, 0, kind, depth, samples, instances, per_instance)
        };
    }

    /// History: keep-last `depth`, or keep-all (`None`).
    pub fn history(&mut self, depth: Option<i32>) {
        match depth {
            Some(d) => unsafe {
                c::dds_qset_history(self.0, c::dds_history_kind_DDS_HISTORY_KEEP_LAST, d)
            },
            None => unsafe {
                c::dds_qset_history(self.0, c::dds_history_kind_DDS_HISTORY_KEEP_ALL, -1)
            },
        }
    }

    /// Deadline period.
    pub fn deadline(&mut self, ns: i64) {
        unsafe { c::dds_qset_deadline(self.0, ns) };
    }

    /// Lifespan.
    pub fn lifespan(&mut self, ns: i64) {
        unsafe { c::dds_qset_lifespan(self.0, ns) };
    }

    /// Latency budget.
    pub fn latency_budget(&mut self, ns: i64) {
        unsafe { c::dds_qset_latency_budget(self.0, ns) };
    }

    /// Time-based filter.
    pub fn time_based_filter(&mut self, ns: i64) {
        unsafe { c::dds_qset_time_based_filter(self.0, ns) };
    }

    /// Liveliness with its lease duration.
    pub fn liveliness(&mut self, kind: LivelinessKind, lease_ns: i64) {
        let k = match kind {
            LivelinessKind::Automatic => c::dds_liveliness_kind_DDS_LIVELINESS_AUTOMATIC,
            LivelinessKind::ManualByParticipant => {
                c::dds_liveliness_kind_DDS_LIVELINESS_MANUAL_BY_PARTICIPANT
            }
            LivelinessKind::ManualByTopic => c::dds_liveliness_kind_DDS_LIVELINESS_MANUAL_BY_TOPIC,
        };
        unsafe { c::dds_qset_liveliness(self.0, k, lease_ns) };
    }

    /// Ownership: exclusive with a strength, or shared.
    pub fn ownership(&mut self, exclusive_strength: Option<i32>) {
        match exclusive_strength {
            Some(s) => unsafe {
                c::dds_qset_ownership(self.0, c::dds_ownership_kind_DDS_OWNERSHIP_EXCLUSIVE);
                c::dds_qset_ownership_strength(self.0, s);
            },
            None => unsafe {
                c::dds_qset_ownership(self.0, c::dds_ownership_kind_DDS_OWNERSHIP_SHARED)
            },
        }
    }

    /// Destination order: by source timestamp (`true`) or by reception.
    pub fn destination_order(&mut self, by_source: bool) {
        let k = if by_source {
            c::dds_destination_order_kind_DDS_DESTINATIONORDER_BY_SOURCE_TIMESTAMP
        } else {
            c::dds_destination_order_kind_DDS_DESTINATIONORDER_BY_RECEPTION_TIMESTAMP
        };
        unsafe { c::dds_qset_destination_order(self.0, k) };
    }

    /// Resource limits (-1: unlimited).
    pub fn resource_limits(&mut self, samples: i32, instances: i32, per_instance: i32) {
        unsafe { c::dds_qset_resource_limits(self.0, samples, instances, per_instance) };
    }

    /// Presentation.
    pub fn presentation(&mut self, scope: AccessScope, coherent: bool, ordered: bool) {
        let k = match scope {
            AccessScope::Instance => {
                c::dds_presentation_access_scope_kind_DDS_PRESENTATION_INSTANCE
            }
            AccessScope::Topic => c::dds_presentation_access_scope_kind_DDS_PRESENTATION_TOPIC,
            AccessScope::Group => c::dds_presentation_access_scope_kind_DDS_PRESENTATION_GROUP,
        };
        unsafe { c::dds_qset_presentation(self.0, k, coherent, ordered) };
    }

    /// Partition names.
    pub fn partitions(&mut self, names: &[String]) -> Result<(), BackendError> {
        let owned = names
            .iter()
            .map(|n| cstring(n, "partition name"))
            .collect::<Result<Vec<_>, _>>()?;
        let mut ptrs: Vec<*const c_char> = owned.iter().map(|s| s.as_ptr()).collect();
        let n = u32::try_from(ptrs.len())
            .map_err(|_| BackendError::InvalidInput("too many partitions".into()))?;
        // SAFETY: n valid C strings, copied by Cyclone.
        unsafe { c::dds_qset_partition(self.0, n, ptrs.as_mut_ptr()) };
        Ok(())
    }
}

impl Drop for Qos {
    fn drop(&mut self) {
        // SAFETY: self.0 came from dds_create_qos and is deleted once.
        unsafe { c::dds_delete_qos(self.0) };
    }
}

/// A data writer of raw samples on one of this module's topics.
#[derive(Debug)]
pub(super) struct Writer {
    entity: Entity,
    sertype: *const c::ddsi_sertype,
    /// The sequence number of its last write attempt, as Cyclone numbers them (it counts
    /// every write from 1 and this writer is only written here), put in the samples it
    /// delivers inside the process, which carry none otherwise. One per attempt, so the
    /// numbers a reader sees of this writer only grow; a write that fails (most fail before
    /// Cyclone numbers them: a throttled write that times out) puts ours ahead of Cyclone's.
    sequence: std::cell::Cell<i64>,
}

impl Writer {
    /// A writer in `publisher` on `topic`.
    pub(super) fn new(publisher: Handle, topic: &Entity, qos: &Qos) -> Result<Self, BackendError> {
        // SAFETY: handles are numbers; QoS is live; null listener.
        let h = unsafe { c::dds_create_writer(publisher, topic.handle(), qos.0, std::ptr::null()) };
        let entity = Entity::new(h, "create data writer")?;
        let mut sertype: *const c::ddsi_sertype = std::ptr::null();
        // SAFETY: out pointer valid; the sertype lives as long as the writer's topic.
        check(
            unsafe { c::dds_get_entity_sertype(entity.handle(), &mut sertype) },
            "writer's type",
        )?;
        if sertype.is_null() || !is_ours(sertype) {
            return Err(BackendError::ForeignEntity(
                "the topic's type is not a raw-sample type",
            ));
        }
        Ok(Writer {
            entity,
            sertype,
            sequence: std::cell::Cell::new(0),
        })
    }

    /// Its GUID.
    pub(super) fn guid(&self) -> Result<[u8; 16], BackendError> {
        self.entity.guid()
    }

    /// The sequence number of its last write attempt (the one the samples it delivers
    /// inside the process carry).
    pub(super) fn sequence(&self) -> i64 {
        self.sequence.get()
    }

    /// Writes a sample with representation identifier `encoding` and body `body`; with
    /// `dispose`, disposes the instance whose key payload `body` is instead.
    pub(super) fn write(
        &self,
        encoding: [u8; 2],
        body: &[u8],
        dispose: bool,
    ) -> Result<(), BackendError> {
        let data = encapsulate(encoding, body);
        let kind = if dispose {
            c::ddsi_serdata_kind_SDK_KEY
        } else {
            c::ddsi_serdata_kind_SDK_DATA
        };
        // SAFETY: self.sertype is one of ours (checked at creation); Cyclone keeps it while
        // the writer's topic exists, and the backend writes only through live writers.
        let keyhash = unsafe { key_of(self.sertype, kind, &data) };
        let sequence = self.sequence.get() + 1;
        self.sequence.set(sequence);
        // SAFETY: a fresh serdata with one reference, which the write consumes.
        unsafe {
            let sd = new_serdata(self.sertype, kind, data, keyhash, sequence);
            let r = if dispose {
                (*sd).statusinfo = DDSI_STATUSINFO_DISPOSE;
                (*sd).timestamp.v = c::dds_time();
                c::dds_forwardcdr(self.entity.handle(), sd)
            } else {
                c::dds_writecdr(self.entity.handle(), sd)
            };
            check(r, if dispose { "dispose" } else { "write" })
        }
    }

    /// Whether every matched reliable reader acknowledged everything (never waits).
    pub(super) fn all_acknowledged(&self) -> bool {
        wait_for_acks(self.entity.handle(), 0)
    }

    /// Its handle (for [`wait_for_acks`] from another thread).
    pub(super) fn handle(&self) -> Handle {
        self.entity.handle()
    }

    /// How many readers it matches.
    pub(super) fn matched(&self) -> usize {
        // SAFETY: zeroed status is a valid out value.
        let mut st: c::dds_publication_matched_status_t = unsafe { std::mem::zeroed() };
        let r = unsafe { c::dds_get_publication_matched_status(self.entity.handle(), &mut st) };
        if r < 0 {
            0
        } else {
            st.current_count as usize
        }
    }
}

const DDSI_STATUSINFO_DISPOSE: u32 = 1;

/// Waits up to `timeout_ns` until every matched reliable reader of `writer` acknowledged
/// every sample written before the call; whether they did. A handle is a number, so this may
/// be called from any thread, also for a writer deleted meanwhile (false).
pub(super) fn wait_for_acks(writer: Handle, timeout_ns: i64) -> bool {
    // SAFETY: no pointers; Cyclone looks the handle up and pins the writer while it waits.
    unsafe { c::dds_wait_for_acks(writer, timeout_ns) == 0 }
}

/// A sample taken from a [`Reader`].
#[derive(Debug, Clone)]
pub(super) struct TakenRaw {
    /// The representation identifier of the sample.
    pub encoding: [u8; 2],
    /// The body after the encapsulation header (a key payload for an invalid sample).
    pub body: Vec<u8>,
    /// The writer's GUID, when Cyclone knows the writer.
    pub writer: Option<[u8; 16]>,
    /// The writer's sequence number, when the sample came over the network (0: unknown).
    pub sequence: i64,
    /// Whether it carries data (otherwise it tells an instance state change).
    pub valid: bool,
    /// The instance is disposed.
    pub disposed: bool,
    /// Cyclone's handle of the sample's instance.
    pub instance: u64,
    /// How often the instance was disposed and written again before this sample.
    pub disposed_generation: u32,
}

/// A data reader of raw samples whose data-available listener signals a [`Readiness`].
#[derive(Debug)]
pub(super) struct Reader {
    handle: Handle,
    signal: *const ReaderSignal,
    /// Writer GUIDs by publication handle (asked of Cyclone once per writer).
    writers: HashMap<c::dds_instance_handle_t, [u8; 16]>,
}

/// Samples taken per call.
pub(super) const TAKE_BATCH: usize = 32;

impl Reader {
    /// A reader in `subscriber` on `topic` whose data signals `token` on `readiness`.
    pub(super) fn new(
        subscriber: Handle,
        topic: &Entity,
        qos: &Qos,
        readiness: &Readiness,
        token: u64,
    ) -> Result<Self, BackendError> {
        let signal = Arc::into_raw(Arc::new(ReaderSignal {
            token,
            queued: AtomicBool::new(false),
            shared: readiness.shared.clone(),
        }));
        // SAFETY: the listener's argument is the signal, alive until after the reader is
        // deleted (see Drop); Cyclone copies the listener into the reader.
        let h = unsafe {
            let l = c::dds_create_listener(signal as *mut c_void);
            c::dds_lset_data_available(l, Some(on_data_available));
            let h = c::dds_create_reader(subscriber, topic.handle(), qos.0, l);
            c::dds_delete_listener(l);
            h
        };
        if h < 0 {
            // SAFETY: no reader was made, nothing else holds the pointer.
            drop(unsafe { Arc::from_raw(signal) });
            return Err(BackendError::Dds(format!(
                "create data reader: {}",
                retcode(h)
            )));
        }
        Ok(Reader {
            handle: h,
            signal,
            writers: HashMap::new(),
        })
    }

    /// Its GUID.
    pub(super) fn guid(&self) -> Result<[u8; 16], BackendError> {
        guid_of(self.handle)
    }

    /// Takes up to a batch of samples into `out`; returns how many.
    pub(super) fn take(&mut self, out: &mut Vec<TakenRaw>) -> Result<usize, BackendError> {
        // Data arriving from now on signals the reader again (what arrived before is taken
        // below).
        // SAFETY: the signal lives as long as the reader.
        unsafe { (*self.signal).queued.store(false, Ordering::SeqCst) };
        let mut bufs: [*mut c::ddsi_serdata; TAKE_BATCH] = [std::ptr::null_mut(); TAKE_BATCH];
        // SAFETY: zeroed sample infos are valid out values.
        let mut infos: [c::dds_sample_info_t; TAKE_BATCH] = unsafe { std::mem::zeroed() };
        // SAFETY: both arrays hold TAKE_BATCH elements; mask 0 means any state.
        let n = unsafe {
            c::dds_takecdr(
                self.handle,
                bufs.as_mut_ptr(),
                TAKE_BATCH as u32,
                infos.as_mut_ptr(),
                0,
            )
        };
        check(n, "take")?;
        let n = n as usize;
        for (sd, info) in bufs.iter().zip(infos.iter()).take(n) {
            // SAFETY: Cyclone returned n serdata references, each released here once.
            let raw = unsafe { read_serdata(*sd) };
            unsafe { c::ddsi_serdata_unref(*sd) };
            let Some((data, sequence)) = raw else {
                continue;
            };
            let writer = self.writer_guid(info.publication_handle);
            let (encoding, body) = decapsulate(&data);
            out.push(TakenRaw {
                encoding,
                body,
                writer,
                sequence,
                valid: info.valid_data,
                disposed: info.instance_state == c::dds_instance_state_DDS_IST_NOT_ALIVE_DISPOSED,
                instance: info.instance_handle,
                disposed_generation: info.disposed_generation_count,
            });
        }
        Ok(n)
    }

    fn writer_guid(&mut self, ih: c::dds_instance_handle_t) -> Option<[u8; 16]> {
        if ih == 0 {
            return None;
        }
        if let Some(g) = self.writers.get(&ih) {
            return Some(*g);
        }
        // SAFETY: returns null or an endpoint description we free once.
        let g = unsafe {
            let ep = c::dds_get_matched_publication_data(self.handle, ih);
            if ep.is_null() {
                return None;
            }
            let g = (*ep).key.v;
            c::dds_builtintopic_free_endpoint(ep);
            g
        };
        if self.writers.len() >= 4096 {
            self.writers.clear();
        }
        self.writers.insert(ih, g);
        Some(g)
    }
}

impl Drop for Reader {
    fn drop(&mut self) {
        // SAFETY: delete first (Cyclone waits for a listener call in progress), then the
        // listener's argument can go.
        unsafe {
            c::dds_delete(self.handle);
            drop(Arc::from_raw(self.signal));
        }
    }
}

/// Where reader listeners say "this reader has data", and the descriptor the worker polls.
#[derive(Debug)]
pub(super) struct Readiness {
    shared: Arc<ReadyShared>,
    rx: UnixStream,
    /// Bytes read from the socket pair so far (compared with `ReadyShared::written`).
    read: std::cell::Cell<u64>,
}

#[derive(Debug)]
struct ReadyShared {
    queued: Mutex<Vec<u64>>,
    /// A byte is on its way through the socket pair (set by listeners, cleared by the taker
    /// after it read what was written).
    armed: AtomicBool,
    /// Bytes listeners wrote to the socket pair so far (counted just before each write,
    /// taken back if it failed).
    written: AtomicU64,
    tx: UnixStream,
    /// The thread that takes the tokens (the worker's loop). A listener called on it (a
    /// sample one of the agent's own writers delivered inside the process, synchronously in
    /// `dds_writecdr`) only queues the token: the loop takes the queue after every pass, so
    /// it needs no wake-up, and two system calls per sample are saved.
    taker: std::thread::ThreadId,
}

#[derive(Debug)]
struct ReaderSignal {
    token: u64,
    /// The token is in the queue already.
    queued: AtomicBool,
    shared: Arc<ReadyShared>,
}

impl Readiness {
    /// An empty readiness queue.
    pub(super) fn new() -> std::io::Result<Self> {
        let (tx, rx) = UnixStream::pair()?;
        tx.set_nonblocking(true)?;
        rx.set_nonblocking(true)?;
        Ok(Readiness {
            shared: Arc::new(ReadyShared {
                queued: Mutex::new(Vec::new()),
                armed: AtomicBool::new(false),
                written: AtomicU64::new(0),
                tx,
                taker: std::thread::current().id(),
            }),
            rx,
            read: std::cell::Cell::new(0),
        })
    }

    /// The descriptor that polls readable when a reader was signalled.
    pub(super) fn fd(&self) -> BorrowedFd<'_> {
        self.rx.as_fd()
    }

    /// Whether tokens wait in the queue (some were queued on the taking thread, which the
    /// descriptor does not announce).
    pub(super) fn has_queued(&self) -> bool {
        match self.shared.queued.lock() {
            Ok(q) => !q.is_empty(),
            Err(p) => !p.into_inner().is_empty(),
        }
    }

    /// Moves the signalled readers' tokens to `out`. A reader is signalled again only
    /// after its token was handed out here, so callers take from it until empty. Call it
    /// from the thread that made the queue, after every pass of its loop.
    pub(super) fn drain(&self, out: &mut Vec<u64>) {
        // The socket is read only when listeners counted more bytes than were read (no
        // system call otherwise), and before `armed` is cleared. A listener that armed before
        // the clear pushed its token before arming, so the take below gets it (its byte, if
        // not read here, makes one spurious wake-up); one that arms after the clear writes a
        // byte of its own. So a queued token always has a byte on its way or is taken here.
        if self.shared.written.load(Ordering::SeqCst) != self.read.get() {
            let mut buf = [0u8; 64];
            while let Ok(n) = (&self.rx).read(&mut buf) {
                self.read.set(self.read.get().wrapping_add(n as u64));
                if n < buf.len() {
                    break;
                }
            }
        }
        self.shared.armed.store(false, Ordering::SeqCst);
        let tokens = match self.shared.queued.lock() {
            Ok(mut q) => std::mem::take(&mut *q),
            Err(p) => std::mem::take(&mut *p.into_inner()),
        };
        out.extend_from_slice(&tokens);
    }
}

impl ReaderSignal {
    fn notify(&self) {
        if !self.queued.swap(true, Ordering::SeqCst) {
            match self.shared.queued.lock() {
                Ok(mut q) => q.push(self.token),
                Err(p) => p.into_inner().push(self.token),
            }
        }
        if std::thread::current().id() == self.shared.taker {
            return;
        }
        if !self.shared.armed.swap(true, Ordering::SeqCst) {
            // Counted before it is written, so a byte the loop polls readable is always one
            // the drain reads (counted and not there yet costs one empty read).
            self.shared.written.fetch_add(1, Ordering::SeqCst);
            match (&self.shared.tx).write(&[1]) {
                Ok(_) => {}
                // A full socket already holds a wake-up: nothing lost.
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    self.shared.written.fetch_sub(1, Ordering::SeqCst);
                }
                Err(_) => {
                    // No byte on its way: disarmed, so the next listener writes one (the
                    // token is queued; the loop's own timeout takes it at the latest).
                    self.shared.written.fetch_sub(1, Ordering::SeqCst);
                    self.shared.armed.store(false, Ordering::SeqCst);
                }
            }
        }
    }
}

unsafe extern "C" fn on_data_available(_reader: c::dds_entity_t, arg: *mut c_void) {
    if arg.is_null() {
        return;
    }
    // SAFETY: arg is the reader's ReaderSignal, alive while the reader exists.
    let signal = unsafe { &*(arg as *const ReaderSignal) };
    signal.notify();
}

// ---------------------------------------------------------------------------------------
// The raw-sample type: sertype and serdata operations.

/// Cyclone's sertype with the key description of the topic's type.
#[repr(C)]
struct Sertype {
    common: c::ddsi_sertype,
    key: Option<Arc<KeyDescriptor>>,
    /// Tells this type's instances from other types' in Cyclone's domain-wide instance map,
    /// which compares only serdata operations (the same for every type of ours) and keys.
    tag: u32,
}

/// A sample (or key) as Cyclone holds it: the encapsulation header and body as received or
/// written, its key hash, and the writer's sequence number when it was read off the wire.
#[repr(C)]
struct Serdata {
    common: c::ddsi_serdata,
    /// Its type's [`Sertype::tag`] (kept by untyped copies, which have no type).
    tag: u32,
    keyhash: [u8; 16],
    sequence: i64,
    data: Vec<u8>,
}

struct SertypeOps(c::ddsi_sertype_ops);
// SAFETY: the table is immutable and holds only function pointers and a null argument.
unsafe impl Sync for SertypeOps {}
struct SerdataOps(c::ddsi_serdata_ops);
// SAFETY: as above.
unsafe impl Sync for SerdataOps {}

static SERTYPE_OPS: SertypeOps = SertypeOps(c::ddsi_sertype_ops {
    version: Some(c::ddsi_sertype_v0),
    arg: std::ptr::null_mut(),
    free: Some(sertype_free),
    zero_samples: Some(sertype_zero_samples),
    realloc_samples: Some(sertype_realloc_samples),
    free_samples: Some(sertype_free_samples),
    equal: Some(sertype_equal),
    hash: Some(sertype_hash),
    type_id: None,
    type_map: None,
    type_info: None,
    derive_sertype: None,
    get_serialized_size: None,
    serialize_into: None,
});

static SERDATA_OPS: SerdataOps = SerdataOps(c::ddsi_serdata_ops {
    eqkey: Some(serdata_eqkey),
    get_size: Some(serdata_size),
    from_ser: Some(serdata_from_ser),
    from_ser_iov: Some(serdata_from_ser_iov),
    from_keyhash: Some(serdata_from_keyhash),
    from_sample: Some(serdata_from_sample),
    to_ser: Some(serdata_to_ser),
    to_ser_ref: Some(serdata_to_ser_ref),
    to_ser_unref: Some(serdata_to_ser_unref),
    to_sample: Some(serdata_to_sample),
    to_untyped: Some(serdata_to_untyped),
    untyped_to_sample: Some(serdata_untyped_to_sample),
    free: Some(serdata_free),
    print: Some(serdata_print),
    get_keyhash: Some(serdata_get_keyhash),
    from_loaned_sample: None,
    from_psmx: None,
});

fn is_ours(tp: *const c::ddsi_sertype) -> bool {
    // SAFETY: tp is a live sertype (callers' contract).
    !tp.is_null() && std::ptr::eq(unsafe { (*tp).serdata_ops }, &SERDATA_OPS.0)
}

/// The key hash of `data` (header and body) for a sertype of ours: zero for a keyless type or
/// a sample whose key cannot be read.
///
/// # Safety
/// `tp` is null or one of this module's sertypes.
unsafe fn key_of(tp: *const c::ddsi_sertype, kind: c::ddsi_serdata_kind, data: &[u8]) -> [u8; 16] {
    if tp.is_null() || kind == c::ddsi_serdata_kind_SDK_EMPTY || data.len() < 4 {
        return [0; 16];
    }
    // SAFETY: ours, so a Sertype starts at tp.
    let Some(key) = (unsafe { &(*(tp as *const Sertype)).key }) else {
        return [0; 16];
    };
    let le = data[1] & 1 == 1;
    let xcdr2 = matches!(data[1], 6 | 7);
    match key.of_received(&data[4..], le, xcdr2, kind == c::ddsi_serdata_kind_SDK_KEY) {
        Ok(k) => k.hash,
        Err(e) => {
            tracing::debug!(error = %e, r#type = %key.ty().name, "sample without a readable key");
            [0; 16]
        }
    }
}

/// A new serdata of ours with one reference.
///
/// # Safety
/// `tp` is a live sertype of ours.
unsafe fn new_serdata(
    tp: *const c::ddsi_sertype,
    kind: c::ddsi_serdata_kind,
    data: Vec<u8>,
    keyhash: [u8; 16],
    sequence: i64,
) -> *mut c::ddsi_serdata {
    // SAFETY: tp is ours (caller's contract).
    let tag = unsafe { (*(tp as *const Sertype)).tag };
    let sd = Box::into_raw(Box::new(Serdata {
        // SAFETY: filled in by ddsi_serdata_init below.
        common: unsafe { std::mem::zeroed() },
        tag,
        keyhash,
        sequence,
        data,
    }));
    // SAFETY: sd is live; tp is a live sertype.
    unsafe {
        c::ddsi_serdata_init(&mut (*sd).common, tp, kind);
        (*sd).common.hash = instance_hash(tag, &keyhash);
    }
    sd as *mut c::ddsi_serdata
}

/// FNV-1a over `bytes`, from `h`.
fn fnv1a(h: u32, bytes: &[u8]) -> u32 {
    bytes
        .iter()
        .fold(h, |h, b| (h ^ u32::from(*b)).wrapping_mul(0x0100_0193))
}

/// The hash Cyclone files an instance under: every octet of the key hash, and the type (its
/// instance map is a hopscotch table: more than 32 live instances of one hash would make it
/// grow without end, so the hash must not ignore any part of the key).
fn instance_hash(tag: u32, keyhash: &[u8; 16]) -> u32 {
    fnv1a(tag, keyhash)
}

/// The data and sequence number of a serdata, if it is one of ours.
///
/// # Safety
/// `sd` is null or a live serdata.
unsafe fn read_serdata(sd: *const c::ddsi_serdata) -> Option<(Vec<u8>, i64)> {
    if sd.is_null() || !std::ptr::eq(unsafe { (*sd).ops }, &SERDATA_OPS.0) {
        return None;
    }
    // SAFETY: ours, so a Serdata starts at sd.
    let s = unsafe { &*(sd as *const Serdata) };
    Some((s.data.clone(), s.sequence))
}

/// # Safety
/// `sd` is a live serdata of ours.
unsafe fn ours<'a>(sd: *const c::ddsi_serdata) -> &'a Serdata {
    // SAFETY: caller's contract.
    unsafe { &*(sd as *const Serdata) }
}

unsafe extern "C" fn sertype_free(tp: *mut c::ddsi_sertype) {
    // SAFETY: tp is a boxed Sertype of ours, freed once (by Cyclone's last unref or by a
    // failed topic creation).
    unsafe {
        c::ddsi_sertype_fini(tp);
        drop(Box::from_raw(tp as *mut Sertype));
    }
}

unsafe extern "C" fn sertype_zero_samples(_: *const c::ddsi_sertype, _: *mut c_void, _: usize) {}

unsafe extern "C" fn sertype_realloc_samples(
    ptrs: *mut *mut c_void,
    _: *const c::ddsi_sertype,
    _: *mut c_void,
    _: usize,
    count: usize,
) {
    // Typed samples are never used with raw topics (only *cdr calls); hand out nulls.
    if !ptrs.is_null() {
        for i in 0..count {
            // SAFETY: Cyclone passes an array of `count` pointers.
            unsafe { *ptrs.add(i) = std::ptr::null_mut() };
        }
    }
}

unsafe extern "C" fn sertype_free_samples(
    _: *const c::ddsi_sertype,
    _: *mut *mut c_void,
    _: usize,
    _: c::dds_free_op_t,
) {
}

unsafe extern "C" fn sertype_equal(a: *const c::ddsi_sertype, b: *const c::ddsi_sertype) -> bool {
    // Cyclone compared the common fields (type name, flags, ops) already.
    // SAFETY: both are ours (same ops).
    let (a, b) = unsafe { (&(*(a as *const Sertype)).key, &(*(b as *const Sertype)).key) };
    match (a, b) {
        (None, None) => true,
        (Some(a), Some(b)) => Arc::ptr_eq(a, b) || a.ty().name == b.ty().name,
        _ => false,
    }
}

unsafe extern "C" fn sertype_hash(tp: *const c::ddsi_sertype) -> u32 {
    // SAFETY: tp is live; its type name is a C string Cyclone copied.
    let name = unsafe { CStr::from_ptr((*tp).type_name) }.to_bytes();
    // FNV-1a.
    name.iter().fold(0x811c_9dc5u32, |h, b| {
        (h ^ u32::from(*b)).wrapping_mul(0x0100_0193)
    })
}

unsafe extern "C" fn serdata_eqkey(a: *const c::ddsi_serdata, b: *const c::ddsi_serdata) -> bool {
    // SAFETY: Cyclone compares serdata with the same operations: ours. Its instance map is
    // shared by every topic of the domain, hence the type tag.
    unsafe {
        let (a, b) = (ours(a), ours(b));
        a.tag == b.tag && a.keyhash == b.keyhash
    }
}

unsafe extern "C" fn serdata_size(sd: *const c::ddsi_serdata) -> u32 {
    // SAFETY: ours.
    unsafe { ours(sd).data.len() as u32 }
}

/// A mirror of Cyclone 11.0.1's `struct ddsi_rmsg_chunk` (`ddsi_radmin.h`).
#[repr(C)]
struct RmsgChunk {
    rbuf: *mut c_void,
    next: *mut RmsgChunk,
    /// `union { uint32_t size; int64_t l; double d; void *p; } u`.
    u: u64,
}

/// A mirror of Cyclone 11.0.1's `struct ddsi_rmsg`; the packet follows it in memory.
#[repr(C)]
struct Rmsg {
    refcount: u32,
    lastchunk: *mut RmsgChunk,
    trace: bool,
    chunk: RmsgChunk,
}

/// A mirror of the leading fields of Cyclone 11.0.1's `struct ddsi_rdata`.
#[repr(C)]
struct Rdata {
    rmsg: *const Rmsg,
    nextfrag: *const Rdata,
    min: u32,
    maxp1: u32,
    submsg_zoff: u16,
    payload_zoff: u16,
    keyhash_zoff: u16,
}

/// `DDSI_RMSG_PAYLOADOFF(rmsg, off)`.
///
/// # Safety
/// `rmsg` is a live receive message.
unsafe fn rmsg_at(rmsg: *const Rmsg, off: usize) -> *const u8 {
    // SAFETY: the packet follows the struct (caller's contract).
    unsafe { (rmsg.add(1) as *const u8).add(off) }
}

const SMID_DATA: u8 = 0x15;
const SMID_DATA_FRAG: u8 = 0x16;

/// The writer sequence number in the DATA or DATA_FRAG submessage of `rd` (0: unknown).
///
/// # Safety
/// `rd` is a live rdata from Cyclone's receive path.
unsafe fn sequence_of(rd: *const Rdata) -> i64 {
    // SAFETY: caller's contract; the submessage lies inside the received packet.
    unsafe {
        let rd = &*rd;
        if rd.submsg_zoff == 0 || rd.rmsg.is_null() {
            return 0;
        }
        let sm = rmsg_at(rd.rmsg, usize::from(rd.submsg_zoff));
        let id = *sm;
        if id != SMID_DATA && id != SMID_DATA_FRAG {
            return 0;
        }
        // writerSN is at offset 16 (header 4, extraFlags 2, octetsToInlineQos 2, readerId 4,
        // writerId 4); its end (24) is below the payload's offset, so it lies in the packet.
        if usize::from(rd.payload_zoff) < usize::from(rd.submsg_zoff) + 24 {
            return 0;
        }
        // In this host's byte order whatever the flags say: Cyclone's validate_Data /
        // validate_DataFrag swap it in place (and leave the flags) before making the rdata.
        let mut b = [0u8; 8];
        std::ptr::copy_nonoverlapping(sm.add(16), b.as_mut_ptr(), 8);
        let (h, l): ([u8; 4], [u8; 4]) = ([b[0], b[1], b[2], b[3]], [b[4], b[5], b[6], b[7]]);
        (i64::from(i32::from_ne_bytes(h)) << 32) | i64::from(u32::from_ne_bytes(l))
    }
}

unsafe extern "C" fn serdata_from_ser(
    tp: *const c::ddsi_sertype,
    kind: c::ddsi_serdata_kind,
    fragchain: *const c::ddsi_rdata,
    size: usize,
) -> *mut c::ddsi_serdata {
    let first = fragchain as *const Rdata;
    let mut data = Vec::with_capacity(size);
    // SAFETY: Cyclone hands a chain of live fragments covering [0, size); each fragment's
    // bytes [min, maxp1) are in its message at its payload offset.
    unsafe {
        let mut off: u32 = 0;
        let mut frag = first;
        while !frag.is_null() && (off as usize) < size {
            let f = &*frag;
            if f.maxp1 > off && f.min <= off {
                let payload = rmsg_at(f.rmsg, usize::from(f.payload_zoff));
                let n = (f.maxp1 - off).min((size - off as usize) as u32);
                let src = payload.add((off - f.min) as usize);
                data.extend_from_slice(std::slice::from_raw_parts(src, n as usize));
                off += n;
            }
            frag = f.nextfrag;
        }
        let sequence = if first.is_null() {
            0
        } else {
            sequence_of(first)
        };
        let keyhash = key_of(tp, kind, &data);
        new_serdata(tp, kind, data, keyhash, sequence)
    }
}

unsafe extern "C" fn serdata_from_ser_iov(
    tp: *const c::ddsi_sertype,
    kind: c::ddsi_serdata_kind,
    niov: c::ddsrt_msg_iovlen_t,
    iov: *const c::ddsrt_iovec_t,
    size: usize,
) -> *mut c::ddsi_serdata {
    let mut data = Vec::with_capacity(size);
    // SAFETY: Cyclone passes niov live buffers.
    unsafe {
        #[allow(clippy::unnecessary_cast)] // a usize on Linux, an int elsewhere
        for i in 0..(niov as usize) {
            let v = &*iov.add(i);
            #[allow(clippy::unnecessary_cast)]
            let n = (v.iov_len as usize).min(size.saturating_sub(data.len()));
            data.extend_from_slice(std::slice::from_raw_parts(v.iov_base as *const u8, n));
        }
        let keyhash = key_of(tp, kind, &data);
        new_serdata(tp, kind, data, keyhash, 0)
    }
}

unsafe extern "C" fn serdata_from_keyhash(
    tp: *const c::ddsi_sertype,
    keyhash: *const c::ddsi_keyhash_t,
) -> *mut c::ddsi_serdata {
    // SAFETY: keyhash is a live 16-octet key hash; tp is ours.
    unsafe {
        let kh = (*keyhash).value;
        new_serdata(tp, c::ddsi_serdata_kind_SDK_KEY, Vec::new(), kh, 0)
    }
}

unsafe extern "C" fn serdata_from_sample(
    _: *const c::ddsi_sertype,
    _: c::ddsi_serdata_kind,
    _: *const c_void,
) -> *mut c::ddsi_serdata {
    // Raw topics have no typed samples.
    std::ptr::null_mut()
}

unsafe extern "C" fn serdata_to_ser(
    sd: *const c::ddsi_serdata,
    off: usize,
    sz: usize,
    buf: *mut c_void,
) {
    // SAFETY: ours; buf holds sz bytes; the copy is bounded by the data.
    unsafe {
        let d = &ours(sd).data;
        let start = off.min(d.len());
        let n = sz.min(d.len() - start);
        std::ptr::copy_nonoverlapping(d.as_ptr().add(start), buf as *mut u8, n);
    }
}

unsafe extern "C" fn serdata_to_ser_ref(
    sd: *const c::ddsi_serdata,
    off: usize,
    sz: usize,
    iov: *mut c::ddsrt_iovec_t,
) -> *mut c::ddsi_serdata {
    // SAFETY: ours; the reference taken here keeps the data alive until to_ser_unref.
    unsafe {
        let d = &ours(sd).data;
        let start = off.min(d.len());
        (*iov).iov_base = d.as_ptr().add(start) as *mut c_void;
        (*iov).iov_len = sz.min(d.len() - start) as _;
        let refc = &*(std::ptr::addr_of!((*sd).refc) as *const AtomicU32);
        refc.fetch_add(1, Ordering::SeqCst);
    }
    sd as *mut c::ddsi_serdata
}

unsafe extern "C" fn serdata_to_ser_unref(sd: *mut c::ddsi_serdata, _: *const c::ddsrt_iovec_t) {
    // SAFETY: releases the reference to_ser_ref took.
    unsafe { c::ddsi_serdata_unref(sd) };
}

unsafe extern "C" fn serdata_to_sample(
    _: *const c::ddsi_serdata,
    _: *mut c_void,
    _: *mut *mut c_void,
    _: *mut c_void,
) -> bool {
    false
}

unsafe extern "C" fn serdata_untyped_to_sample(
    _: *const c::ddsi_sertype,
    _: *const c::ddsi_serdata,
    _: *mut c_void,
    _: *mut *mut c_void,
    _: *mut c_void,
) -> bool {
    false
}

unsafe extern "C" fn serdata_to_untyped(sd: *const c::ddsi_serdata) -> *mut c::ddsi_serdata {
    // SAFETY: ours, with a live type (Cyclone makes untyped copies of typed samples); the
    // copy keeps the key (hash and key payload) and drops the type, as Cyclone requires.
    unsafe {
        let s = ours(sd);
        let tp = (*sd).type_;
        let data = if (*sd).kind == c::ddsi_serdata_kind_SDK_KEY {
            s.data.clone()
        } else {
            key_payload(tp, &s.data).unwrap_or_default()
        };
        // No sequence number: an untyped key stands for its instance, not for a sample.
        let u = new_serdata(tp, c::ddsi_serdata_kind_SDK_KEY, data, s.keyhash, 0);
        (*u).type_ = std::ptr::null();
        (*u).hash = (*sd).hash;
        (*u).timestamp.v = i64::MIN;
        u
    }
}

/// The key-only payload (header and key fields, little-endian XCDR1) of a whole sample.
///
/// # Safety
/// `tp` is null or one of ours.
unsafe fn key_payload(tp: *const c::ddsi_sertype, data: &[u8]) -> Option<Vec<u8>> {
    if tp.is_null() || data.len() < 4 {
        return None;
    }
    // SAFETY: ours.
    let key = unsafe { (*(tp as *const Sertype)).key.as_ref()? };
    let le = data[1] & 1 == 1;
    let xcdr2 = matches!(data[1], 6 | 7);
    let k = key.of_received(&data[4..], le, xcdr2, false).ok()?;
    Some(encapsulate(xrce_dds_seam::Encoding::CDR_LE.0, &k.payload))
}

/// A serialized sample as DDS carries it: the encapsulation header, the body, and zeros up to
/// a multiple of 4 octets, their count in the options' two low bits (XTypes 1.3 §7.6.3.1.2).
/// Cyclone DDS drops DATA whose payload is not so padded as malformed, and XRCE clients send
/// unpadded bodies (a 34-octet HelloWorld, say).
fn encapsulate(encoding: [u8; 2], body: &[u8]) -> Vec<u8> {
    let pad = (4 - body.len() % 4) % 4;
    let mut data = Vec::with_capacity(4 + body.len() + pad);
    data.extend_from_slice(&[encoding[0], encoding[1], 0, pad as u8]);
    data.extend_from_slice(body);
    data.resize(data.len() + pad, 0);
    data
}

/// The representation identifier and body of an encapsulated sample, without its padding.
fn decapsulate(data: &[u8]) -> ([u8; 2], Vec<u8>) {
    if data.len() < 4 {
        return ([0, 1], Vec::new());
    }
    let pad = usize::from(data[3] & 3);
    let end = data.len().saturating_sub(pad).max(4);
    ([data[0], data[1]], data[4..end].to_vec())
}

unsafe extern "C" fn serdata_free(sd: *mut c::ddsi_serdata) {
    // SAFETY: the last reference of a boxed Serdata of ours.
    drop(unsafe { Box::from_raw(sd as *mut Serdata) });
}

unsafe extern "C" fn serdata_print(
    _: *const c::ddsi_sertype,
    sd: *const c::ddsi_serdata,
    buf: *mut c_char,
    size: usize,
) -> usize {
    if buf.is_null() || size == 0 {
        return 0;
    }
    // SAFETY: ours; buf holds size bytes; the text is cut to fit with its NUL.
    unsafe {
        let text = format!("({} raw bytes)", ours(sd).data.len());
        let n = text.len().min(size - 1);
        std::ptr::copy_nonoverlapping(text.as_ptr(), buf as *mut u8, n);
        *buf.add(n) = 0;
        n
    }
}

unsafe extern "C" fn serdata_get_keyhash(
    sd: *const c::ddsi_serdata,
    buf: *mut c::ddsi_keyhash,
    _force_md5: bool,
) {
    // SAFETY: ours; buf is a live key hash.
    unsafe { (*buf).value = ours(sd).keyhash };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_padded_to_four_octets_and_unpadded_again() {
        for n in 0..9 {
            let body: Vec<u8> = (1..=n).collect();
            let data = encapsulate([0, 1], &body);
            assert_eq!(data.len() % 4, 0, "{n}");
            assert_eq!(usize::from(data[3]), (4 - n as usize % 4) % 4);
            assert_eq!(decapsulate(&data), ([0, 1], body));
        }
        assert_eq!(decapsulate(&[0, 1]), ([0, 1], Vec::new()));
        // A padding count beyond the body never underflows.
        assert_eq!(decapsulate(&[0, 1, 0, 3]), ([0, 1], Vec::new()));
    }

    #[test]
    fn instance_hashes_use_every_octet_of_the_key_and_the_type() {
        // Keys that differ only in the middle octets (an int64 below 2^32, say) must not
        // share a hash: Cyclone's instance map cannot hold more than 32 of one hash.
        let mut seen = std::collections::HashSet::new();
        for i in 0..64u8 {
            let mut kh = [0u8; 16];
            kh[7] = i;
            assert!(seen.insert(instance_hash(1, &kh)), "{i}");
        }
        assert_ne!(instance_hash(1, &[0; 16]), instance_hash(2, &[0; 16]));
    }

    /// Whether the readiness socket holds a wake-up, waiting up to 100 ms for one.
    fn woken(r: &Readiness) -> bool {
        let mut fds = [nix::poll::PollFd::new(
            std::os::fd::AsFd::as_fd(&r.rx),
            nix::poll::PollFlags::POLLIN,
        )];
        nix::poll::poll(&mut fds, 100u16).unwrap_or(0) > 0
    }

    fn signal(r: &Readiness, token: u64) -> Arc<ReaderSignal> {
        Arc::new(ReaderSignal {
            token,
            queued: AtomicBool::new(false),
            shared: r.shared.clone(),
        })
    }

    #[test]
    fn listeners_on_other_threads_wake_the_loop_once_and_its_own_thread_does_not() {
        let r = Readiness::new().expect("readiness");
        let (a, b) = (signal(&r, 1), signal(&r, 2));
        let mut out = Vec::new();
        // On the taking thread (a local writer's sample, delivered inside dds_writecdr):
        // queued, no wake-up.
        a.notify();
        assert!(!woken(&r), "no byte through the socket pair");
        r.drain(&mut out);
        assert_eq!(out, vec![1]);
        a.queued.store(false, Ordering::SeqCst);
        // On Cyclone's threads: one wake-up for any number of notifications until drained.
        out.clear();
        let (a2, b2) = (a.clone(), b.clone());
        std::thread::spawn(move || {
            for _ in 0..3 {
                a2.notify();
                b2.notify();
            }
        })
        .join()
        .expect("listener thread");
        assert!(woken(&r), "the descriptor polls readable");
        r.drain(&mut out);
        assert_eq!(out, vec![1, 2], "each reader once");
        assert!(!woken(&r), "drained: nothing left in the socket pair");
        assert!(
            !r.shared.armed.load(Ordering::SeqCst),
            "disarmed after the bytes were read"
        );
        // A listener after that drain writes again (a queue left armed with no byte on its
        // way would swallow every later wake-up).
        a.queued.store(false, Ordering::SeqCst);
        let a3 = a.clone();
        std::thread::spawn(move || a3.notify())
            .join()
            .expect("listener thread");
        assert!(woken(&r), "woken again");
        r.drain(&mut out);
        assert!(!woken(&r));
        // Armed but the byte not written yet (the listener is between arming and writing):
        // the drain reads nothing, and the byte, once written, wakes the next pass.
        r.shared.armed.store(true, Ordering::SeqCst);
        r.drain(&mut out);
        r.shared.written.fetch_add(1, Ordering::SeqCst);
        (&r.shared.tx).write_all(&[1]).expect("write");
        assert!(woken(&r), "the late byte wakes the loop");
        r.drain(&mut out);
        assert!(!woken(&r), "the late byte was read");
        assert!(!r.shared.armed.load(Ordering::SeqCst));
    }
}
