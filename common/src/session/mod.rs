//! Sans-IO session state machines.
//!
//! * [`agent`]: the agent side of every session of one front-end.
//! * [`admission`]: the allow-list of client keys, roaming, per-client rate quotas.
//! * [`budget`]: the memory budget shared fairly between hosts and sessions, session caps.
//! * [`client`]: a client side, for tests, simulation and the load generator.
//! * [`discovery`]: answers to multicast agent discovery.
//! * [`graph`]: a client's object graph and active reads, kept for replay.
//! * [`fragment`]: FRAGMENT splitting and reassembly.
//! * [`stream`] and [`seq`]: reliable and best-effort stream state, serial numbers.

pub mod admission;
pub mod agent;
pub mod budget;
pub mod client;
pub mod discovery;
pub mod fragment;
pub mod graph;
pub mod origin;
pub mod seq;
pub mod snapshot;
pub mod stream;
