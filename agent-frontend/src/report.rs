//! The front-end's counters in the log: reported at info when something was dropped since the
//! last report, at most every [`STATS_PERIOD`], so that drops are visible without debug
//! logging and an idle or healthy agent stays silent.

use std::time::{Duration, Instant};

use xrce_common::session::agent::Agent;

use crate::relay::{Link, Relay};
use crate::transport::TransportStats;

/// How often changed drop counters are reported.
pub const STATS_PERIOD: Duration = Duration::from_secs(10);

/// When the counters were last reported, and their drop total then.
#[derive(Debug)]
pub struct StatsReport {
    last: Instant,
    last_dropped: u64,
}

impl StatsReport {
    /// Nothing reported yet.
    pub fn new(now: Instant) -> Self {
        StatsReport {
            last: now,
            last_dropped: 0,
        }
    }

    /// Everything counted as not delivered: the core's drops by reason, the relay's and the
    /// transport's.
    fn total<A: xrce_common::session::agent::Endpoint>(
        agent: &Agent<A>,
        relay: &Relay<impl Link>,
        transport: &TransportStats,
    ) -> u64 {
        let b = relay.stats();
        agent.stats().dropped.values().sum::<u64>()
            + b.ops_dropped
            + b.samples_dropped
            + b.ipc_dropped
            + b.instance_ends_skipped
            + b.reads_paused
            + transport.total_dropped()
    }

    /// A deadline only while there is something new to report.
    pub fn due<A: xrce_common::session::agent::Endpoint>(
        &self,
        agent: &Agent<A>,
        relay: &Relay<impl Link>,
        transport: &TransportStats,
    ) -> Option<Instant> {
        (Self::total(agent, relay, transport) != self.last_dropped)
            .then_some(self.last + STATS_PERIOD)
    }

    /// Logs the counters if they changed and the period passed.
    pub fn maybe_log<A: xrce_common::session::agent::Endpoint>(
        &mut self,
        now: Instant,
        agent: &Agent<A>,
        relay: &Relay<impl Link>,
        transport_name: &str,
        transport: &TransportStats,
    ) {
        let total = Self::total(agent, relay, transport);
        if total == self.last_dropped || now < self.last + STATS_PERIOD {
            return;
        }
        let s = agent.stats();
        let mut reasons: Vec<_> = s.dropped.iter().collect();
        reasons.sort();
        let b = relay.stats();
        tracing::info!(
            transport = transport_name,
            sessions = agent.client_count(),
            datagrams_in = s.datagrams_in,
            datagrams_out = s.datagrams_out,
            retransmissions = s.retransmissions,
            dropped = ?reasons,
            transport_opened = transport.opened,
            transport_closed = transport.closed,
            transport_dropped = ?transport.dropped,
            replays = b.replays,
            ops_dropped = b.ops_dropped,
            samples_dropped = b.samples_dropped,
            reads_paused = b.reads_paused,
            instance_ends_skipped = b.instance_ends_skipped,
            samples_already_delivered = b.samples_already_delivered,
            resent_samples_already_delivered = b.resent_samples_already_delivered,
            "front-end counters"
        );
        self.last = now;
        self.last_dropped = total;
    }
}
