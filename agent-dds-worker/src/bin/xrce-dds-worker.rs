//! `xrce-dds-worker`: the process that owns the DDS entities of an XRCE agent instance.

use std::net::IpAddr;

use clap::Parser;
use xrce_dds_worker::dds::DdsConfig;
use xrce_dds_worker::worker::{Worker, WorkerConfig};

/// Owns every DDS entity of an XRCE agent instance; normally started by `xrce-agent`.
#[derive(Debug, Parser)]
#[command(version)]
struct Args {
    /// Agent instance name (all processes of one agent share it).
    #[arg(long, env = "XRCE_INSTANCE", default_value = "default")]
    instance: String,
    /// Restrict DDS to these local addresses (comma-separated or repeated); default: all.
    #[arg(long = "dds-interface", env = "XRCE_DDS_INTERFACES", value_delimiter = ',')]
    dds_interfaces: Vec<IpAddr>,
    /// Log filter (tracing syntax), e.g. `info` or `xrce_dds_worker=debug`.
    #[arg(long, env = "XRCE_LOG", default_value = "info")]
    log: String,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_new(&args.log).unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    let mut worker = Worker::new(WorkerConfig { instance: args.instance, dds: DdsConfig { interfaces: args.dds_interfaces } })?;
    worker.run()
}
