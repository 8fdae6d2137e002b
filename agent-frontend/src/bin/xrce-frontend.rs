//! `xrce-frontend`: one XRCE transport endpoint of an agent instance; normally started by
//! `xrce-agent`.

use std::net::{SocketAddr, UdpSocket};

use clap::Parser;
use xrce_common::session::agent::AgentConfig;
use xrce_frontend::bridge::Bridge;

/// Serves XRCE clients on one UDP address and forwards their operations to the DDS worker.
#[derive(Debug, Parser)]
#[command(version)]
struct Args {
    /// Agent instance name (all processes of one agent share it).
    #[arg(long, env = "XRCE_INSTANCE", default_value = "default")]
    instance: String,
    /// This front-end's id within the instance (unique per front-end).
    #[arg(long, default_value_t = 0)]
    frontend_id: u32,
    /// UDP address to serve, e.g. 0.0.0.0:8888 or [::]:8888.
    #[arg(long)]
    udp: SocketAddr,
    /// Log filter (tracing syntax), e.g. `info` or `xrce_common=debug`.
    #[arg(long, env = "XRCE_LOG", default_value = "info")]
    log: String,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_new(&args.log).unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    let socket = UdpSocket::bind(args.udp).map_err(|e| anyhow::anyhow!("binding UDP {}: {e}", args.udp))?;
    let bridge = Bridge::new(&args.instance, args.frontend_id)?;
    xrce_frontend::udp::run(socket, bridge, AgentConfig::default())
}
