//! The DDS worker of the XRCE agent: it owns every DDS entity on behalf of the front-ends,
//! executes their operations, and streams samples of active reads back.
//!
//! It is not an XRCE endpoint: it never sees client datagrams, only the IPC contract of
//! `xrce_ipc`. Samples pass through as serialized bytes. The DDS implementation sits
//! behind [`backend`], the seam `xrce_dds_seam` that the backend crates implement (Cyclone DDS
//! by default, `xrce_dds_cyclone`; `xrce_dds_rustdds`; `xrce_dds_zenoh`).
//!
//! # QoS mapping
//!
//! Settings on the data writer or reader override those given with its topic; what neither
//! gives keeps the default in the last column (Fast DDS's, as the reference agent).
//!
//! | Policy | XML (Fast DDS / DDS-XML element) | Binary (`OBJK_*_Binary`) | RustDDS | Default |
//! |---|---|---|---|---|
//! | Reliability | `reliability/kind` | flags bit 0 | `Reliability` (max blocking 100 ms) | writer reliable, reader best-effort |
//! | Durability | `durability/kind` | flags bits 3–5 | `Durability` (all four kinds) | writer transient-local, reader volatile |
//! | History | `historyQos` / `history`: `kind`, `depth` | flags bit 1 + `history_depth` | `History` | keep-last 64 |
//! | Deadline | `deadline/period` | `deadline_msec` | `Deadline` | infinite |
//! | Lifespan | `lifespan/duration` | `lifespan_msec` | `Lifespan` | infinite |
//! | Liveliness | `liveliness`: `kind`, `lease_duration` | — | `Liveliness` | automatic, infinite |
//! | Ownership | `ownership/kind` | flags bit 2 (exclusive) | `Ownership` | shared |
//! | Ownership strength | `ownershipStrength` / `ownership_strength` `/value` | `ownership_strength` | in `Ownership::Exclusive` | 0 |
//! | Destination order | `destinationOrder` / `destination_order` `/kind` | — | `DestinationOrder` | by reception |
//! | Resource limits | `resourceLimitsQos` / `resource_limits` (≤ 0 = unlimited) | — | `ResourceLimits` | unlimited; 1,000 samples for a KEEP_ALL reader (RustDDS would keep 64) |
//! | Time-based filter | `timeBasedFilter` / `time_based_filter` `/minimum_separation` | `timebasedfilter_msec` | `TimeBasedFilter` | 0 |
//! | Latency budget | `latencyBudget` / `latency_budget` `/duration` | — | `LatencyBudget` | 0 |
//! | Presentation | `presentation`: `access_scope`, `coherent_access`, `ordered_access` | — | `Presentation` | instance, false, false |
//! | Partition | `partition/names/name` (publisher, subscriber) | publisher/subscriber `partitions` | Cyclone DDS: the publisher's or subscriber's `Partition`; RustDDS has none: the CREATE is refused with `STATUS_ERR_INCOMPATIBLE` (so is a partition on a data writer or reader, with either backend) | default partition |
//! | User / group / topic data | ignored | `user_data`, `group_data` ignored | not set | — |
//! | Content filter | `data_reader/content_filter/expression` | `contentbased_filter` | none: evaluated by the worker ([`filter`]) on the topic's type | no filter |
//!
//! # Types, keys and filters
//!
//! Type descriptions come from `<types>` (DDS-XML and Fast DDS spellings, [`types`]): a
//! client's TYPE objects (XML, or a reference to a type of the references file) and the
//! references file itself. A topic whose type is known and has key members is a WITH_KEY
//! topic: the worker extracts the key of every sample (KeyHash per XTypes 1.3 §7.6.8),
//! RustDDS keeps reader history per instance, a WRITE_DATA whose SampleInfo says disposed or
//! unregistered disposes the instance (RustDDS has no unregister; DDS's default
//! `autodispose_unregistered_instances` makes them equal), and DDS disposes reach SAMPLE-format
//! reads with their instance state. A WITH_KEY topic whose type is unknown is carried without
//! key (logged). Content filters (READ_DATA, reader XML or binary) need the type; without it
//! they are refused with `STATUS_ERR_INCOMPATIBLE`.
//!
//! RustDDS 0.15 keeps a writer's history per writer, not per instance: a late joiner of a
//! transient-local keyed writer may first get superseded samples of an instance before its
//! latest (a KEEP_LAST reader ends with the right values).
//!
//! Durations accept `<sec>` and `<nanosec>`, `DURATION_INFINITY` (and its `DURATION_INFINITE_*`
//! spellings), and values beyond 2³¹ s as infinite; a malformed value refuses the CREATE
//! with `STATUS_ERR_INVALID_DATA` naming the element.
//!
//! # Bounds against hostile clients
//!
//! What a client can make the worker hold or do is bounded (issue 29): DDS domains
//! ([`domains`]: `--domains`, `--max-domains`, 8 distinct domains at once by default, a
//! domain's DDS participants released with its last XRCE participant), content filters
//! ([`filter`]: clauses per filter, steps per evaluation, per reader and per pass of the
//! loop), and `--dds-interface`, which fails closed (`xrce_dds_seam::confine`). Refusals are
//! counted by reason in the worker's `dropped` counters (`xrce_dropped_total` in
//! `/metrics`) and logged once per episode ([`episodes`]).
#![forbid(unsafe_code)]
// What is `pub` is the crate's API, documented; an item only the crate uses says so (`pub(crate)`).
#![warn(unreachable_pub, missing_docs)]

pub mod acks;
pub mod adoption;
pub mod backend;
pub mod binary;
pub mod bounds;
pub mod cli;
pub mod domains;
pub mod episodes;
pub mod filter;
pub mod fuzzing;
pub mod process;
pub mod recent;
pub mod references;
pub mod representation;
pub mod ros_graph;
pub mod tree;
pub mod turns;
pub mod worker;
pub mod xml;

pub use xrce_dds_seam::{ros_nodes, types};
