//! RustDDS policies for an endpoint's resolved QoS (see the crate documentation's table).

use rustdds::policy;
use rustdds::{QosPolicies, QosPolicyBuilder};

use xrce_dds_seam::policies::{
    AccessScope, DestinationOrderKind, Durability, History, LivelinessKind, OwnershipKind, Period,
    Reliability,
};
use xrce_dds_seam::EndpointQos;

/// The RustDDS policies of an endpoint.
pub fn to_rustdds(qos: &EndpointQos) -> QosPolicies {
    let merged = qos.described;
    let (reliability, durability, history) = (qos.reliability, qos.durability, qos.history);
    let mut b = QosPolicyBuilder::new();
    b = match reliability {
        Reliability::Reliable => b.reliable(rustdds::Duration::from_std(qos.max_blocking)),
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
    if let Some(r) = qos.resource_limits {
        b = b.resource_limits(policy::ResourceLimits {
            max_samples: r.max_samples,
            max_instances: r.max_instances,
            max_samples_per_instance: r.max_samples_per_instance,
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
    fn every_described_policy_reaches_rustdds_and_the_endpoint_overrides_the_topic() {
        use xrce_dds_seam::policies::{
            AccessScope, DestinationOrderKind, LivelinessKind, OwnershipKind, Period,
            PresentationDesc, QosDesc, ResourceLimitsDesc,
        };
        use xrce_dds_seam::EndpointSide;
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
        let q = to_rustdds(&EndpointQos::resolve(
            EndpointSide::Reader,
            &topic,
            &endpoint,
        ));
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
}
