//! `xrce-dds-worker`: the process that owns the DDS entities of an XRCE agent instance
//! (for deployments that supervise each process themselves, e.g. with systemd).

use clap::Parser;

/// Owns every DDS entity of an XRCE agent instance.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    #[command(flatten)]
    args: xrce_dds_worker::cli::WorkerArgs,
}

fn main() -> anyhow::Result<()> {
    xrce_dds_worker::cli::run(Cli::parse().args)
}
