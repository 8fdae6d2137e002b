//! The front-end's status report: its sessions, counters and drops, written every second
//! from the event loop for `xrce-agent status` and the metrics endpoint (see
//! [`xrce_ipc::status`]). Written from the loop itself, the report's age also tells
//! the supervisor's watchdog whether the loop still turns.

use std::collections::BTreeMap;
use std::time::Instant;

use xrce_common::session::agent::Agent;
use xrce_common::wire::Dialect;
use xrce_ipc::status::{FrontendStatus, ProcessReport, SessionStatus};

use crate::relay::{Link, Relay};
use crate::transport::Transport;

/// Who this front-end is, for its reports.
#[derive(Debug, Clone)]
pub struct Identity {
    /// Its name in the group.
    pub name: String,
    /// Its id within the instance.
    pub id: u32,
}

/// Builds the report of one front-end as of `now`.
pub fn report<T: Transport>(
    who: &Identity,
    now: Instant,
    transport: &T,
    agent: &Agent<T::Endpoint>,
    relay: &Relay<impl Link>,
) -> ProcessReport {
    let core = agent.stats();
    let b = relay.stats();
    let t = transport.stats();
    let counters: BTreeMap<String, u64> = [
        ("messages_received", core.datagrams_in),
        ("messages_sent", core.datagrams_out),
        ("samples_written", core.samples_in),
        ("samples_delivered", core.samples_out),
        ("retransmissions", core.retransmissions),
        ("reads_paused", b.reads_paused),
        ("best_effort_sheds", b.best_effort_sheds),
        ("replays", b.replays),
        ("writes_resent", b.writes_resent),
        ("writes_acknowledged", b.writes_acknowledged),
        (
            "writes_settled_unacknowledged",
            b.writes_settled_unacknowledged,
        ),
        ("samples_already_delivered", b.samples_already_delivered),
        (
            "resent_samples_already_delivered",
            b.resent_samples_already_delivered,
        ),
        ("link_refusals", b.link_refusals),
        ("transport_opened", t.opened),
        ("transport_closed", t.closed),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    let mut dropped: BTreeMap<String, u64> = BTreeMap::new();
    let mut add = |reason: &str, n: u64| {
        if n > 0 {
            *dropped.entry(reason.to_string()).or_default() += n;
        }
    };
    for (reason, n) in &core.dropped {
        add(reason, *n);
    }
    for (reason, n) in &t.dropped {
        add(reason, *n);
    }
    add("ipc_dropped", b.ipc_dropped);
    add("operations_dropped", b.ops_dropped);
    add("samples_dropped", b.samples_dropped);
    add("instance_ends_skipped", b.instance_ends_skipped);
    add("objects_over_quota", b.objects_over_quota);
    add("objects_over_budget", b.objects_over_budget);
    let mut sessions: Vec<SessionStatus> = agent
        .sessions(now)
        .map(|s| SessionStatus {
            client_key: format!("0x{}", s.key),
            session_id: s.session_id,
            peer: transport.describe(s.endpoint),
            dialect: match s.dialect {
                Dialect::Spec => "spec".into(),
                Dialect::Eprosima => "eprosima".into(),
            },
            age_seconds: round_ms(s.age.as_secs_f64()),
            last_heard_seconds: round_ms(s.silent_for.as_secs_f64()),
            detached: s.detached,
            entities: relay.object_count(s.key) as u64,
            messages_in: s.counters.messages_in,
            samples_in: s.counters.samples_in,
            samples_out: s.counters.samples_out,
            dropped: s.counters.dropped,
        })
        .collect();
    sessions.sort_by(|a, b| a.client_key.cmp(&b.client_key));
    ProcessReport {
        name: who.name.clone(),
        role: "frontend".into(),
        frontend: Some(FrontendStatus {
            id: who.id,
            transport: transport.name().into(),
            serving: transport.serving(),
            connected: relay.generation().is_some(),
            generation: relay.generation(),
            counters,
            dropped,
            sessions,
        }),
        ..Default::default()
    }
}

/// Seconds kept to the millisecond (reports stay short and readable).
fn round_ms(s: f64) -> f64 {
    (s * 1000.0).round() / 1000.0
}
