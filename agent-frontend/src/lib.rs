//! The XRCE front-end: terminates one client transport, runs the XRCE sessions of its
//! clients with the sans-IO core of `xrce_common`, and exchanges operations with the DDS
//! worker over iceoryx2 ([`relay`]). It never touches DDS.
//!
//! * [`transport`]: the seam between the event loop and each way of reaching clients (UDP,
//!   TCP, serial lines, pseudoterminals) and the discovery responder;
//! * [`event_loop`]: the one loop driving a transport, the session core and the relay;
//! * [`worker_side`]: the loop's seam to the worker, in its own process or in this one;
//! * [`relay`]: operations to the worker, replies back, replay after a worker restart (a
//!   sans-IO state machine; its iceoryx2 link is [`relay::link`]);
//! * [`waiting_writes`]: best-effort writes waiting for the worker, shared fairly among
//!   clients;
//! * [`cli`]: the front-end's settings and start-up;
//! * [`report`]: counters in the log;
//! * [`status`]: the status report (sessions, counters) for `xrce-agent status` and metrics;
//! * [`session_store`] and [`takeover`]: sessions kept for, and taken over by, the next
//!   front-end process after a crash or an upgrade.
#![deny(unsafe_code)]
// What is `pub` is the crate's API, documented; an item only the crate uses says so (`pub(crate)`).
#![warn(unreachable_pub, missing_docs)]

pub mod cli;
pub mod event_loop;
pub mod object_budget;
pub mod relay;
pub mod report;
pub mod session_store;
pub mod start;
pub mod status;
mod sys;
pub mod takeover;
pub mod transport;
pub mod waiting_writes;
pub mod worker_side;
