//! Command-line settings of a front-end, shared by `xrce-frontend` and `xrce-agent frontend`.

use std::net::{SocketAddr, UdpSocket};

use std::time::Duration;

use xrce_common::session::agent::AgentConfig;
use xrce_common::wire::Dialect;

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
    /// Protocol dialect for every session (`spec` or `eprosima`); by default chosen per session
    /// from the client's vendor id.
    #[arg(long, env = "XRCE_DIALECT")]
    pub dialect: Option<Dialect>,
    /// Seconds of silence after which a client's session and its DDS entities are deleted
    /// (probed with GET_INFO from a quarter of it on); 0 keeps silent sessions for ever.
    /// Clients built with hard liveliness use their own timeout.
    #[arg(long, env = "XRCE_CLIENT_DEAD_TIME", default_value_t = 0.0)]
    pub client_dead_time: f64,
}

impl FrontendArgs {
    /// The session-core settings these arguments ask for.
    pub fn agent_config(&self) -> anyhow::Result<AgentConfig> {
        let dead = self.client_dead_time;
        // At most a year: longer is "never" in practice, and keeps Instant arithmetic safe.
        if !(dead.is_finite() && (0.0..=31_536_000.0).contains(&dead)) {
            anyhow::bail!("--client-dead-time must be 0 to 31536000 seconds, got {dead}");
        }
        Ok(AgentConfig {
            dialect: self.dialect,
            client_dead_time: (dead > 0.0).then(|| Duration::from_secs_f64(dead.max(0.1))),
            ..AgentConfig::default()
        })
    }
}

/// Runs a front-end until SIGINT/SIGTERM.
pub fn run(args: FrontendArgs) -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&args.log).unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let config = args.agent_config()?;
    let socket =
        UdpSocket::bind(args.udp).map_err(|e| anyhow::anyhow!("binding UDP {}: {e}", args.udp))?;
    let bridge = Bridge::new(&args.instance, args.frontend_id)?;
    crate::udp::run(socket, bridge, config)
}
