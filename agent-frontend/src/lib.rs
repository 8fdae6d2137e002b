//! The XRCE front-end: terminates one client transport, runs the XRCE sessions of its
//! clients with the sans-IO core of `xrce_common`, and exchanges operations with the DDS
//! worker over iceoryx2 ([`bridge`]). It never touches DDS.

pub mod bridge;
pub mod cli;
pub mod udp;
