//! The end-to-end suite as one test binary: real agent processes (front-ends, worker,
//! supervisor), real sockets on loopback, ptys and shared memory, independent DDS and Zenoh
//! peers; and one module (`simulation`) that runs the agent's code in this process, in
//! memory, in simulated time. One module per subject; every test of every module runs side by side with the others
//! (libtest's threads), so a module keeps to DDS domains no other module uses: the harness
//! checks this as domains are claimed (`xrce_tests::domains`). One binary links once and lets
//! a slow test of one subject overlap the others.
//!
//! One subject: `cargo test --workspace --test e2e -- lifecycle::` (README's test command
//! builds the same binary).

mod admission;
mod big_endian;
mod data_formats;
mod dds_interfaces;
mod dds_port_clash;
mod delivery_control;
mod discovery_cli;
mod domain_override;
mod edge_attacks;
mod fastdds_interop;
mod frontend_restart;
mod gateway;
mod heartbeats;
mod helloworld_e2e;
mod independent_client;
mod instances;
mod keyed_topics;
mod large_samples;
mod late_joiner;
mod lifecycle;
mod many_clients;
mod operations;
mod partitions;
mod private_files;
mod references;
mod request_reply;
mod ros_graph;
mod ros_graph_layouts;
mod serial_e2e;
mod shared_writers;
mod simulation;
mod single_process;
mod supervision;
mod supervisor_restart;
mod tcp_e2e;
mod trace_replay;
mod worker_bounds;
mod worker_restart;
mod zenoh_graph;
