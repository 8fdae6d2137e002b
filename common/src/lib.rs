//! The DDS-XRCE protocol core of the agent, with no I/O.
//!
//! * [`wire`]: encode and decode XRCE messages (header, submessages, payloads).
//! * [`session`]: sans-IO state machines: the agent side (client registry, streams,
//!   reliability) and a client side used by tests and the load generator.
//! * [`framing`]: byte-stream framers for TCP (length prefix) and serial lines.
//! * [`fault`]: faults injected on purpose (feature `fault-injection`, test builds only).
//! * [`fuzzing`]: invariant-checking entry points for the fuzz targets and their corpus tests.
//!
//! This crate owns no socket, no thread and no clock: callers pass bytes, sources and
//! `Instant`s in, and take transmits, operations and timer deadlines out. The contract between
//! the agent's processes and its shared memory are the `xrce-ipc` crate's, beside this one.
#![forbid(unsafe_code)]
// What is `pub` is the crate's API, documented; an item only the crate uses says so (`pub(crate)`).
#![warn(unreachable_pub, missing_docs)]

pub mod fault;
pub mod framing;
pub mod fuzzing;
pub mod session;
pub mod wire;
