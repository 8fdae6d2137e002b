//! The DDS side: one RustDDS participant per domain, shared by every XRCE participant in it,
//! and the mapping of XML QoS onto RustDDS policies.

use std::collections::HashMap;
use std::net::IpAddr;

use rustdds::policy;
use rustdds::{DomainParticipant, DomainParticipantBuilder, QosPolicies, QosPolicyBuilder};

use crate::xml::{
    AccessScope, DestinationOrderKind, Durability, History, LivelinessKind, OwnershipKind, Period,
    QosDesc, Reliability,
};

/// Where DDS may talk.
#[derive(Debug, Clone, Default)]
pub struct DdsConfig {
    /// Restrict DDS to these local addresses (empty = every interface, like any DDS app).
    pub interfaces: Vec<IpAddr>,
}

/// Which participant of a domain an entity lives on.
///
/// Writers and readers live on different RustDDS participants: pinned to loopback, a RustDDS
/// participant cannot deliver from its own writer to its own reader (its proxies of itself
/// get no locators), so two XRCE clients in one domain would not hear each other.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// Publishers and data writers.
    Publish,
    /// Subscribers and data readers.
    Subscribe,
}

/// Participants by domain id and role.
#[derive(Debug)]
pub struct ParticipantPool {
    config: DdsConfig,
    participants: HashMap<(u16, Role), DomainParticipant>,
}

/// The domain id XRCE clients use to mean "the agent's default" (reference agent behaviour).
pub const DOMAIN_ID_DEFAULT_MARKER: i16 = 255;

/// Maps the domain id a client asked for to the DDS domain used.
pub fn effective_domain(requested: i16) -> Result<u16, String> {
    if requested == DOMAIN_ID_DEFAULT_MARKER {
        for var in ["XRCE_DOMAIN_ID_OVERRIDE", "ROS_DOMAIN_ID"] {
            if let Ok(v) = std::env::var(var) {
                return v
                    .trim()
                    .parse::<u16>()
                    .map_err(|_| format!("{var}={v:?} is not a domain id"));
            }
        }
        return Ok(0);
    }
    u16::try_from(requested)
        .ok()
        .filter(|d| *d <= 232)
        .ok_or_else(|| format!("domain id {requested} out of range"))
}

impl ParticipantPool {
    /// An empty pool.
    pub fn new(config: DdsConfig) -> Self {
        ParticipantPool {
            config,
            participants: HashMap::new(),
        }
    }

    /// The participant of `domain` for `role`, created on first use.
    pub fn get(&mut self, domain: u16, role: Role) -> Result<DomainParticipant, String> {
        if let Some(p) = self.participants.get(&(domain, role)) {
            return Ok(p.clone());
        }
        let mut b = DomainParticipantBuilder::new(domain);
        if !self.config.interfaces.is_empty() {
            b = b.with_only_networks(self.config.interfaces.clone());
        }
        let p = b
            .build()
            .map_err(|e| format!("creating DDS participant in domain {domain}: {e:?}"))?;
        tracing::info!(domain, ?role, "DDS participant created");
        self.participants.insert((domain, role), p.clone());
        Ok(p)
    }

    /// Number of participants.
    pub fn len(&self) -> usize {
        self.participants.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.participants.is_empty()
    }
}

/// Which side an endpoint is on; defaults follow the reference agent (Fast DDS): writers
/// reliable and transient-local, readers best-effort and volatile, history keep-last 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EndpointSide {
    /// A data writer.
    Writer,
    /// A data reader.
    Reader,
}

/// Samples a KEEP_ALL data reader keeps when the client gives no resource limits (RustDDS's
/// own default is 64). Bounded, so that a reader that is not drained cannot exhaust memory.
pub const KEEP_ALL_READER_SAMPLES: i32 = 1000;

/// Builds RustDDS QoS from topic and endpoint descriptions (endpoint settings win).
pub fn endpoint_qos(side: EndpointSide, topic: &QosDesc, endpoint: &QosDesc) -> QosPolicies {
    let merged = topic.overridden_by(*endpoint);
    let reliability = endpoint
        .reliability
        .or(topic.reliability)
        .unwrap_or(match side {
            EndpointSide::Writer => Reliability::Reliable,
            EndpointSide::Reader => Reliability::BestEffort,
        });
    let durability = endpoint
        .durability
        .or(topic.durability)
        .unwrap_or(match side {
            EndpointSide::Writer => Durability::TransientLocal,
            EndpointSide::Reader => Durability::Volatile,
        });
    // A deeper default than Fast DDS's keep-last 1: the worker drains readers promptly, but
    // bursts between two drains must not be cut to one sample.
    let history = endpoint
        .history
        .or(topic.history)
        .unwrap_or(History::KeepLast(64));
    let mut b = QosPolicyBuilder::new();
    b = match reliability {
        Reliability::Reliable => b.reliable(rustdds::Duration::from_millis(100)),
        Reliability::BestEffort => b.best_effort(),
    };
    b = b.durability(match durability {
        Durability::Volatile => policy::Durability::Volatile,
        Durability::TransientLocal => policy::Durability::TransientLocal,
        Durability::Transient => policy::Durability::Transient,
        Durability::Persistent => policy::Durability::Persistent,
    });
    b = b.history(match history {
        History::KeepLast(depth) => policy::History::KeepLast { depth },
        History::KeepAll => policy::History::KeepAll,
    });
    // Beyond 2^31 s a DDS duration is infinite (and RustDDS's conversion would wrap).
    let d = |p: Period| match p {
        Period::Finite(d) if d.as_secs() < i32::MAX as u64 => rustdds::Duration::from_std(d),
        _ => rustdds::Duration::INFINITE,
    };
    // A deadline under 1 ms would re-arm RustDDS's deadline timer without pause on the
    // participant's event thread, shared by every client of the domain: treated as none.
    match merged.deadline {
        Some(Period::Finite(p)) if p < std::time::Duration::from_millis(1) => {
            tracing::warn!(deadline = ?p, "deadline below 1 ms ignored (treated as infinite)");
        }
        Some(p) => b = b.deadline(policy::Deadline(d(p))),
        None => {}
    }
    if let Some(p) = merged.lifespan {
        b = b.lifespan(policy::Lifespan { duration: d(p) });
    }
    if let Some(p) = merged.latency_budget {
        b = b.latency_budget(policy::LatencyBudget { duration: d(p) });
    }
    if let Some(p) = merged.time_based_filter {
        b = b.time_based_filter(policy::TimeBasedFilter {
            minimum_separation: d(p),
        });
    }
    if let Some((kind, lease)) = merged.liveliness {
        let lease_duration = d(lease);
        b = b.liveliness(match kind {
            LivelinessKind::Automatic => policy::Liveliness::Automatic { lease_duration },
            LivelinessKind::ManualByParticipant => {
                policy::Liveliness::ManualByParticipant { lease_duration }
            }
            LivelinessKind::ManualByTopic => policy::Liveliness::ManualByTopic { lease_duration },
        });
    }
    match merged.ownership {
        Some(OwnershipKind::Exclusive) => {
            b = b.ownership(policy::Ownership::Exclusive {
                strength: merged.ownership_strength.unwrap_or(0),
            });
        }
        Some(OwnershipKind::Shared) => b = b.ownership(policy::Ownership::Shared),
        None => {}
    }
    if let Some(o) = merged.destination_order {
        b = b.destination_order(match o {
            DestinationOrderKind::ByReception => policy::DestinationOrder::ByReceptionTimestamp,
            DestinationOrderKind::BySource => policy::DestinationOrder::BySourceTimeStamp,
        });
    }
    if let Some(r) = merged.resource_limits {
        b = b.resource_limits(policy::ResourceLimits {
            max_samples: r.max_samples,
            max_instances: r.max_instances,
            max_samples_per_instance: r.max_samples_per_instance,
        });
    } else if side == EndpointSide::Reader && matches!(history, History::KeepAll) {
        // Without limits RustDDS keeps 64 samples per topic for a KEEP_ALL reader: a burst
        // beyond that between two takes was lost (100 writers at 20,000 samples/s: 41 %).
        b = b.resource_limits(policy::ResourceLimits {
            max_samples: KEEP_ALL_READER_SAMPLES,
            max_instances: KEEP_ALL_READER_SAMPLES,
            max_samples_per_instance: KEEP_ALL_READER_SAMPLES,
        });
    }
    if let Some(p) = merged.presentation {
        b = b.presentation(policy::Presentation {
            access_scope: match p.access_scope {
                AccessScope::Instance => policy::PresentationAccessScope::Instance,
                AccessScope::Topic => policy::PresentationAccessScope::Topic,
                AccessScope::Group => policy::PresentationAccessScope::Group,
            },
            coherent_access: p.coherent_access,
            ordered_access: p.ordered_access,
        });
    }
    b.build()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_keep_all_reader_without_limits_keeps_a_bounded_thousand_samples() {
        let keep_all = QosDesc {
            history: Some(History::KeepAll),
            ..QosDesc::default()
        };
        let reader = endpoint_qos(EndpointSide::Reader, &QosDesc::default(), &keep_all);
        assert_eq!(reader.history(), Some(policy::History::KeepAll));
        assert_eq!(
            reader.resource_limits().map(|r| r.max_samples),
            Some(KEEP_ALL_READER_SAMPLES)
        );
        // Writers and keep-last readers are left as described.
        let writer = endpoint_qos(EndpointSide::Writer, &QosDesc::default(), &keep_all);
        assert_eq!(writer.resource_limits(), None);
        let keep_last = QosDesc {
            history: Some(History::KeepLast(5)),
            ..QosDesc::default()
        };
        let reader = endpoint_qos(EndpointSide::Reader, &QosDesc::default(), &keep_last);
        assert_eq!(reader.resource_limits(), None);
    }

    #[test]
    fn every_described_policy_reaches_rustdds_and_the_endpoint_overrides_the_topic() {
        use crate::xml::{
            AccessScope, DestinationOrderKind, LivelinessKind, OwnershipKind, Period,
            PresentationDesc, ResourceLimitsDesc,
        };
        let ms = |v| Period::Finite(std::time::Duration::from_millis(v));
        let topic = QosDesc {
            deadline: Some(ms(100)),
            resource_limits: Some(ResourceLimitsDesc {
                max_samples: 50,
                max_instances: -1,
                max_samples_per_instance: -1,
            }),
            ..QosDesc::default()
        };
        let endpoint = QosDesc {
            deadline: Some(ms(20)),
            lifespan: Some(Period::Infinite),
            latency_budget: Some(ms(1)),
            time_based_filter: Some(ms(5)),
            liveliness: Some((LivelinessKind::ManualByParticipant, ms(2000))),
            ownership: Some(OwnershipKind::Exclusive),
            ownership_strength: Some(9),
            destination_order: Some(DestinationOrderKind::BySource),
            presentation: Some(PresentationDesc {
                access_scope: AccessScope::Topic,
                coherent_access: false,
                ordered_access: true,
            }),
            ..QosDesc::default()
        };
        let q = endpoint_qos(EndpointSide::Reader, &topic, &endpoint);
        let d = rustdds::Duration::from_millis;
        assert_eq!(q.deadline(), Some(policy::Deadline(d(20))));
        assert_eq!(
            q.lifespan(),
            Some(policy::Lifespan {
                duration: rustdds::Duration::INFINITE
            })
        );
        assert_eq!(
            q.latency_budget(),
            Some(policy::LatencyBudget { duration: d(1) })
        );
        assert_eq!(
            q.time_based_filter(),
            Some(policy::TimeBasedFilter {
                minimum_separation: d(5)
            })
        );
        assert_eq!(
            q.liveliness(),
            Some(policy::Liveliness::ManualByParticipant {
                lease_duration: d(2000)
            })
        );
        assert_eq!(
            q.ownership(),
            Some(policy::Ownership::Exclusive { strength: 9 })
        );
        assert_eq!(
            q.destination_order(),
            Some(policy::DestinationOrder::BySourceTimeStamp)
        );
        assert_eq!(
            q.resource_limits(),
            Some(policy::ResourceLimits {
                max_samples: 50,
                max_instances: -1,
                max_samples_per_instance: -1
            })
        );
        assert_eq!(
            q.presentation(),
            Some(policy::Presentation {
                access_scope: policy::PresentationAccessScope::Topic,
                coherent_access: false,
                ordered_access: true
            })
        );
    }

    #[test]
    fn defaults_follow_fast_dds() {
        let w = endpoint_qos(
            EndpointSide::Writer,
            &QosDesc::default(),
            &QosDesc::default(),
        );
        assert!(w.is_reliable());
        assert_eq!(w.durability(), Some(policy::Durability::TransientLocal));
        let r = endpoint_qos(
            EndpointSide::Reader,
            &QosDesc::default(),
            &QosDesc::default(),
        );
        assert!(!r.is_reliable());
        let explicit = QosDesc {
            reliability: Some(Reliability::Reliable),
            ..Default::default()
        };
        assert!(endpoint_qos(EndpointSide::Reader, &QosDesc::default(), &explicit).is_reliable());
    }

    #[test]
    fn domain_ids() {
        assert_eq!(effective_domain(7), Ok(7));
        assert!(effective_domain(-1).is_err());
        assert!(effective_domain(300).is_err());
    }
}
