//! What clients may make the worker hold: DDS entities, and the samples their caches keep.
//!
//! A DDS reader's cache is the client's to fill: a KEEP_ALL reader with unlimited resource
//! limits on a topic another participant publishes keeps every sample it is not asked for,
//! and a keyed topic keeps a history per instance for every instance anyone invents. So
//! every endpoint's QoS is clamped before a backend sees it (a keep-last depth, a keep-all
//! cache, the instances of a keyed topic: at most [`WorkerBounds::samples_per_endpoint`]
//! samples and [`WorkerBounds::instances_per_endpoint`] instances), and the samples an
//! endpoint may then hold are reserved against its client's share and the worker's total:
//! a creation that does not fit is refused with STATUS_ERR_RESOURCES. The bound is in
//! samples, not bytes (no DDS implementation bounds a cache in bytes): what a client can
//! make the worker hold is its share of samples times the size of the topic's samples.
//!
//! Sans-IO: plain values, no clock, no backend.

use std::collections::HashMap;

use crate::backend::policies::{History, ResourceLimitsDesc};
use crate::backend::qos::EndpointQos;

/// The worker's bounds on what clients make it hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WorkerBounds {
    /// Samples one endpoint's cache may keep (keep-last depth, keep-all cache, across its
    /// instances).
    pub samples_per_endpoint: i32,
    /// Instances one endpoint of a keyed topic may keep.
    pub instances_per_endpoint: i32,
    /// Samples the endpoints of one client may keep together.
    pub samples_per_client: u64,
    /// Samples the endpoints of every client may keep together.
    pub samples_total: u64,
    /// Entities (of any kind) of one client.
    pub entities_per_client: usize,
    /// Entities of every client together.
    pub entities_total: usize,
}

/// Default [`WorkerBounds::samples_per_endpoint`] (4 MiB of 1 KiB samples).
pub const DEFAULT_SAMPLES_PER_ENDPOINT: i32 = 4096;
/// Default [`WorkerBounds::instances_per_endpoint`].
pub const DEFAULT_INSTANCES_PER_ENDPOINT: i32 = 1024;
/// Default [`WorkerBounds::samples_per_client`] (64 MiB of 1 KiB samples).
pub const DEFAULT_SAMPLES_PER_CLIENT: u64 = 65_536;
/// Default [`WorkerBounds::samples_total`] (1 GiB of 1 KiB samples).
pub const DEFAULT_SAMPLES_TOTAL: u64 = 1 << 20;
/// Default [`WorkerBounds::entities_per_client`]: a front-end's default object quota.
pub const DEFAULT_ENTITIES_PER_CLIENT: usize = 1024;
/// Default [`WorkerBounds::entities_total`].
pub const DEFAULT_ENTITIES_TOTAL: usize = 32_768;

impl Default for WorkerBounds {
    fn default() -> Self {
        WorkerBounds {
            samples_per_endpoint: DEFAULT_SAMPLES_PER_ENDPOINT,
            instances_per_endpoint: DEFAULT_INSTANCES_PER_ENDPOINT,
            samples_per_client: DEFAULT_SAMPLES_PER_CLIENT,
            samples_total: DEFAULT_SAMPLES_TOTAL,
            entities_per_client: DEFAULT_ENTITIES_PER_CLIENT,
            entities_total: DEFAULT_ENTITIES_TOTAL,
        }
    }
}

/// An endpoint's QoS after [`clamp`]: what changed, and the samples its cache may keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Clamped {
    /// Samples the endpoint's cache may keep at most (what is reserved for it).
    pub samples: u32,
    /// Whether the client's QoS asked for more than the bounds (and was cut down).
    pub changed: bool,
}

/// A count of -1 or less than 1: unlimited in DDS's resource limits.
fn limit(v: i32, bound: i32) -> i32 {
    if v < 1 {
        bound
    } else {
        v.min(bound)
    }
}

/// Clamps an endpoint's QoS to `bounds` (`keyed`: its topic has a key, so it keeps a history
/// per instance) and says what the endpoint may keep.
pub fn clamp(qos: &mut EndpointQos, keyed: bool, bounds: &WorkerBounds) -> Clamped {
    let per_endpoint = bounds.samples_per_endpoint.max(1);
    let mut changed = false;
    if let History::KeepLast(depth) = qos.history {
        if depth > per_endpoint {
            qos.history = History::KeepLast(per_endpoint);
            changed = true;
        }
    }
    let depth = match qos.history {
        History::KeepLast(d) => Some(d.max(1)),
        History::KeepAll => None,
    };
    let asked = qos.resource_limits;
    // Unkeyed and keep-last within the bound, with no limits asked: the depth is the bound
    // already, and the QoS stays as described.
    if !keyed && depth.is_some() && asked.is_none() {
        return Clamped {
            samples: depth.unwrap_or(1) as u32,
            changed,
        };
    }
    let asked = asked.unwrap_or(ResourceLimitsDesc {
        max_samples: -1,
        max_instances: -1,
        max_samples_per_instance: -1,
    });
    let instances = if keyed {
        limit(asked.max_instances, bounds.instances_per_endpoint.max(1))
    } else {
        asked.max_instances
    };
    // Unlimited samples on a keyed keep-last endpoint: its depth times its instances.
    let max_samples = match depth {
        Some(d) if keyed && asked.max_samples < 1 => {
            per_endpoint.min(d.saturating_mul(instances.max(1)))
        }
        _ => limit(asked.max_samples, per_endpoint),
    };
    // DDS wants a depth within the samples per instance, and those within the samples.
    // (Unlimited per instance is the depth for keep-last: the history bounds it already.)
    let per_instance = match asked.max_samples_per_instance {
        v if v < 1 => depth.unwrap_or(max_samples),
        v => v.min(max_samples),
    }
    .max(depth.unwrap_or(1));
    let max_samples = max_samples.max(per_instance.min(per_endpoint));
    let per_instance = per_instance.min(max_samples);
    let clamped = ResourceLimitsDesc {
        max_samples,
        max_instances: instances,
        max_samples_per_instance: per_instance,
    };
    changed |= qos.resource_limits != Some(clamped);
    qos.resource_limits = Some(clamped);
    let samples = match depth {
        Some(d) if !keyed => d.min(max_samples),
        _ => max_samples,
    };
    Clamped {
        samples: samples.max(1) as u32,
        changed,
    }
}

/// Why a creation does not fit the bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OverBound {
    /// The client has [`WorkerBounds::entities_per_client`] entities.
    EntitiesPerClient,
    /// The worker has [`WorkerBounds::entities_total`] entities.
    EntitiesTotal,
    /// The client's endpoints keep [`WorkerBounds::samples_per_client`] samples.
    SamplesPerClient,
    /// Past half of [`WorkerBounds::samples_total`], the front-end's clients keep their
    /// front-end's equal share of it.
    SamplesPerFrontend,
    /// Every endpoint together keeps [`WorkerBounds::samples_total`] samples.
    SamplesTotal,
}

impl OverBound {
    /// The refusal's counter name.
    pub fn reason(self) -> &'static str {
        match self {
            OverBound::EntitiesPerClient => "entities_per_client",
            OverBound::EntitiesTotal => "entities_total",
            OverBound::SamplesPerClient => "samples_per_client",
            OverBound::SamplesPerFrontend => "samples_per_frontend",
            OverBound::SamplesTotal => "samples_total",
        }
    }
}

/// The samples reserved by each client's endpoints, by each front-end's (a group of
/// clients), and in all. Shared as a front-end's memory budget is: below half the total a
/// front-end takes what its clients ask for (within the per-client bound); beyond, each
/// front-end holding samples is entitled to an equal share, so one front-end's clients
/// cannot take the worker from the others'.
#[derive(Debug)]
pub struct Holdings<G, C> {
    by_client: HashMap<(G, C), u64>,
    by_group: HashMap<G, u64>,
    total: u64,
}

impl<G, C> Default for Holdings<G, C> {
    fn default() -> Self {
        Holdings {
            by_client: HashMap::new(),
            by_group: HashMap::new(),
            total: 0,
        }
    }
}

impl<G: std::hash::Hash + Eq + Copy, C: std::hash::Hash + Eq + Copy> Holdings<G, C> {
    /// Whether `samples` more fit the share of `client` (of front-end `group`), its
    /// front-end's and the total.
    pub fn check(
        &self,
        group: G,
        client: C,
        samples: u32,
        bounds: &WorkerBounds,
    ) -> Result<(), OverBound> {
        let more = u64::from(samples);
        let held = self.by_client.get(&(group, client)).copied().unwrap_or(0);
        if held + more > bounds.samples_per_client {
            return Err(OverBound::SamplesPerClient);
        }
        if self.total + more > bounds.samples_total {
            return Err(OverBound::SamplesTotal);
        }
        if self.total + more > bounds.samples_total / 2 {
            let group_held = self.by_group.get(&group).copied().unwrap_or(0);
            let groups = self.by_group.len() + usize::from(group_held == 0);
            let share = bounds.samples_total / groups.max(1) as u64;
            if group_held + more > share {
                return Err(OverBound::SamplesPerFrontend);
            }
        }
        Ok(())
    }

    /// Reserves `samples` for `client` of front-end `group`.
    pub fn reserve(&mut self, group: G, client: C, samples: u32) {
        if samples == 0 {
            return;
        }
        *self.by_client.entry((group, client)).or_default() += u64::from(samples);
        *self.by_group.entry(group).or_default() += u64::from(samples);
        self.total += u64::from(samples);
    }

    /// Gives back what [`Self::reserve`] took.
    pub fn release(&mut self, group: G, client: C, samples: u32) {
        if samples == 0 {
            return;
        }
        let less = u64::from(samples);
        if let Some(h) = self.by_client.get_mut(&(group, client)) {
            *h = h.saturating_sub(less);
            if *h == 0 {
                self.by_client.remove(&(group, client));
            }
        }
        if let Some(h) = self.by_group.get_mut(&group) {
            *h = h.saturating_sub(less);
            if *h == 0 {
                self.by_group.remove(&group);
            }
        }
        self.total = self.total.saturating_sub(less);
    }

    /// Samples reserved in all.
    pub fn total(&self) -> u64 {
        self.total
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::policies::QosDesc;
    use crate::backend::qos::EndpointSide;

    fn reader(history: History, limits: Option<ResourceLimitsDesc>) -> EndpointQos {
        let desc = QosDesc {
            history: Some(history),
            resource_limits: limits,
            ..QosDesc::default()
        };
        EndpointQos::resolve(EndpointSide::Reader, &QosDesc::default(), &desc)
    }

    const UNLIMITED: ResourceLimitsDesc = ResourceLimitsDesc {
        max_samples: -1,
        max_instances: -1,
        max_samples_per_instance: -1,
    };

    #[test]
    fn keep_all_with_unlimited_resources_is_bounded() {
        let b = WorkerBounds::default();
        let mut q = reader(History::KeepAll, Some(UNLIMITED));
        let c = clamp(&mut q, false, &b);
        assert!(c.changed);
        assert_eq!(c.samples, 4096);
        let r = q.resource_limits.expect("limits");
        assert_eq!((r.max_samples, r.max_samples_per_instance), (4096, 4096));
        assert_eq!(q.history, History::KeepAll, "keep-all stays keep-all");
    }

    #[test]
    fn a_modest_keep_last_is_left_alone() {
        let b = WorkerBounds::default();
        let mut q = reader(History::KeepLast(10), None);
        let before = q;
        let c = clamp(&mut q, false, &b);
        assert_eq!(
            c,
            Clamped {
                samples: 10,
                changed: false
            }
        );
        assert_eq!(q, before);
    }

    #[test]
    fn a_deep_history_is_cut_to_the_bound() {
        let b = WorkerBounds::default();
        let mut q = reader(History::KeepLast(1_000_000), None);
        let c = clamp(&mut q, false, &b);
        assert!(c.changed);
        assert_eq!(q.history, History::KeepLast(4096));
        assert_eq!(c.samples, 4096);
    }

    #[test]
    fn keyed_topics_bound_their_instances_and_samples() {
        let b = WorkerBounds::default();
        let mut q = reader(History::KeepLast(64), None);
        let c = clamp(&mut q, true, &b);
        assert!(c.changed);
        let r = q.resource_limits.expect("limits");
        assert_eq!(r.max_instances, 1024);
        assert_eq!(r.max_samples, 4096);
        assert_eq!(r.max_samples_per_instance, 64);
        assert_eq!(c.samples, 4096);
        // Keep-last 1: one sample per instance, so no more than the instances.
        let mut q = reader(History::KeepLast(1), None);
        let c = clamp(&mut q, true, &b);
        assert_eq!(c.samples, 1024);
        let r = q.resource_limits.expect("limits");
        assert_eq!((r.max_samples, r.max_samples_per_instance), (1024, 1));
    }

    #[test]
    fn limits_within_the_bounds_are_kept() {
        let b = WorkerBounds::default();
        let asked = ResourceLimitsDesc {
            max_samples: 100,
            max_instances: 10,
            max_samples_per_instance: 10,
        };
        let mut q = reader(History::KeepAll, Some(asked));
        let c = clamp(&mut q, true, &b);
        assert!(!c.changed);
        assert_eq!(q.resource_limits, Some(asked));
        assert_eq!(c.samples, 100);
    }

    #[test]
    fn reservations_are_bounded_per_client_and_in_all() {
        let b = WorkerBounds {
            samples_per_client: 100,
            samples_total: 150,
            ..WorkerBounds::default()
        };
        let mut h = Holdings::default();
        assert_eq!(h.check(0, 1, 60, &b), Ok(()));
        h.reserve(0, 1, 60);
        assert_eq!(h.check(0, 1, 60, &b), Err(OverBound::SamplesPerClient));
        h.reserve(0, 2, 80);
        assert_eq!(h.check(0, 3, 20, &b), Err(OverBound::SamplesTotal));
        h.release(0, 1, 60);
        assert_eq!(h.check(0, 3, 20, &b), Ok(()));
        assert_eq!(h.total(), 80);
    }

    #[test]
    fn past_half_the_total_each_front_end_keeps_to_its_share() {
        let b = WorkerBounds {
            samples_per_client: 1000,
            samples_total: 1000,
            ..WorkerBounds::default()
        };
        let mut h = Holdings::default();
        // Alone, a front-end may go past half.
        h.reserve(1, 1, 400);
        assert_eq!(h.check(1, 2, 300, &b), Ok(()));
        h.reserve(1, 2, 300);
        // A second front-end is entitled to half: the first may not grow further...
        assert_eq!(h.check(2, 9, 200, &b), Ok(()));
        h.reserve(2, 9, 200);
        assert_eq!(h.check(1, 3, 50, &b), Err(OverBound::SamplesPerFrontend));
        // ...while the second still may, up to its half.
        assert_eq!(h.check(2, 9, 100, &b), Ok(()));
        assert_eq!(h.check(2, 9, 301, &b), Err(OverBound::SamplesTotal));
    }
}
