//! The DDS worker of the XRCE agent: it owns every DDS entity (RustDDS) on behalf of the
//! front-ends, executes their operations, and streams samples of active reads back.
//!
//! It is not an XRCE endpoint: it never sees client datagrams, only the IPC contract of
//! `xrce_common::ipc`. Samples pass through as serialized bytes ([`raw`]).

pub mod binary;
pub mod cli;
pub mod dds;
pub mod fuzzing;
pub mod raw;
pub mod references;
pub mod representation;
pub mod worker;
pub mod xml;
