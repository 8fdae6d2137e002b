//! `xrce-frontend`: one XRCE transport endpoint of an agent instance (for deployments that
//! supervise each process themselves, e.g. with systemd).

use clap::Parser;

/// Serves XRCE clients on one UDP address and forwards their operations to the DDS worker.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    #[command(flatten)]
    args: xrce_frontend::cli::FrontendArgs,
}

fn main() -> anyhow::Result<()> {
    xrce_frontend::start::run(Cli::parse().args)
}
