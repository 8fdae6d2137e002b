//! Command-line settings of a front-end, shared by `xrce-frontend` and `xrce-agent frontend`.

use std::net::{SocketAddr, UdpSocket};

use xrce_common::session::agent::AgentConfig;

use crate::bridge::Bridge;

/// Settings of a front-end process.
#[derive(Debug, Clone, clap::Args)]
pub struct FrontendArgs {
    /// Agent instance name (all processes of one agent share it).
    #[arg(long, env = "XRCE_INSTANCE", default_value = "default")]
    pub instance: String,
    /// This front-end's id within the instance (unique per front-end).
    #[arg(long, default_value_t = 0)]
    pub frontend_id: u32,
    /// UDP address to serve, e.g. 0.0.0.0:8888 or [::]:8888.
    #[arg(long)]
    pub udp: SocketAddr,
    /// Log filter (tracing syntax), e.g. `info` or `xrce_common=debug`.
    #[arg(long, env = "XRCE_LOG", default_value = "info")]
    pub log: String,
}

/// Runs a front-end until SIGINT/SIGTERM.
pub fn run(args: FrontendArgs) -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&args.log).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let socket =
        UdpSocket::bind(args.udp).map_err(|e| anyhow::anyhow!("binding UDP {}: {e}", args.udp))?;
    let bridge = Bridge::new(&args.instance, args.frontend_id)?;
    crate::udp::run(socket, bridge, AgentConfig::default())
}
