//! Cyclone DDS policies for an endpoint's resolved QoS.

use super::ffi::{self, Qos, INFINITY};
use xrce_dds_seam::policies::{
    AccessScope, DestinationOrderKind, Durability, History, LivelinessKind, OwnershipKind, Period,
    Reliability,
};
use xrce_dds_seam::{BackendError, EndpointQos};

/// Nanoseconds of a period (infinite beyond `i64`).
fn ns(p: Period) -> i64 {
    match p {
        Period::Finite(d) => i64::try_from(d.as_nanos()).unwrap_or(INFINITY),
        _ => INFINITY,
    }
}

/// The Cyclone policies of an endpoint.
pub fn to_cyclone(qos: &EndpointQos) -> Result<Qos, BackendError> {
    let mut q = Qos::new()?;
    let d = qos.described;
    q.reliability(match qos.reliability {
        Reliability::Reliable => ffi::ReliabilityKind::Reliable(
            i64::try_from(qos.max_blocking.as_nanos()).unwrap_or(INFINITY),
        ),
        Reliability::BestEffort => ffi::ReliabilityKind::BestEffort,
    });
    q.durability(match qos.durability {
        Durability::Volatile => ffi::DurabilityKind::Volatile,
        Durability::TransientLocal => ffi::DurabilityKind::TransientLocal,
        Durability::Transient => ffi::DurabilityKind::Transient,
        Durability::Persistent => ffi::DurabilityKind::Persistent,
    });
    let history = match qos.history {
        History::KeepLast(depth) => Some(depth.max(1)),
        History::KeepAll => None,
    };
    q.history(history);
    if qos.durability != Durability::Volatile {
        // Late joiners get the writer's history, as with Fast DDS and RustDDS (Cyclone
        // would keep only the last sample of each instance for them: found when a
        // transient-local reader joining after the hold got 1 of 8 samples).
        let (samples, instances, per_instance) = qos.resource_limits.map_or((-1, -1, -1), |r| {
            (r.max_samples, r.max_instances, r.max_samples_per_instance)
        });
        q.durability_service(history, samples, instances, per_instance);
    }
    if let Some(p) = d.deadline {
        q.deadline(ns(p));
    }
    if let Some(p) = d.lifespan {
        q.lifespan(ns(p));
    }
    if let Some(p) = d.latency_budget {
        q.latency_budget(ns(p));
    }
    if let Some(p) = d.time_based_filter {
        q.time_based_filter(ns(p));
    }
    if let Some((kind, lease)) = d.liveliness {
        q.liveliness(
            match kind {
                LivelinessKind::Automatic => ffi::LivelinessKind::Automatic,
                LivelinessKind::ManualByParticipant => ffi::LivelinessKind::ManualByParticipant,
                LivelinessKind::ManualByTopic => ffi::LivelinessKind::ManualByTopic,
            },
            ns(lease),
        );
    }
    match d.ownership {
        Some(OwnershipKind::Exclusive) => q.ownership(Some(d.ownership_strength.unwrap_or(0))),
        Some(OwnershipKind::Shared) => q.ownership(None),
        None => {}
    }
    if let Some(o) = d.destination_order {
        q.destination_order(matches!(o, DestinationOrderKind::BySource));
    }
    if let Some(r) = qos.resource_limits {
        q.resource_limits(r.max_samples, r.max_instances, r.max_samples_per_instance);
    }
    if let Some(p) = d.presentation {
        q.presentation(
            match p.access_scope {
                AccessScope::Instance => ffi::AccessScope::Instance,
                AccessScope::Topic => ffi::AccessScope::Topic,
                AccessScope::Group => ffi::AccessScope::Group,
            },
            p.coherent_access,
            p.ordered_access,
        );
    }
    Ok(q)
}
