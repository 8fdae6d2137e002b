//! The QoS of an endpoint as the worker resolves it from XRCE descriptions, before any
//! backend maps it onto its own policies: the topic's settings overridden by the endpoint's,
//! and the defaults of the reference agent (Fast DDS) for what neither gives.

use std::time::Duration;

use crate::policies::{
    Durability, History, OwnershipKind, QosDesc, Reliability, ResourceLimitsDesc,
};

/// Which side an endpoint is on; defaults follow the reference agent (Fast DDS): writers
/// reliable and transient-local, readers best-effort and volatile.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum EndpointSide {
    /// A data writer.
    Writer,
    /// A data reader.
    Reader,
}

/// Samples a KEEP_ALL data reader keeps when the client gives no resource limits (RustDDS's
/// own default is 64). Bounded, so that a reader that is not drained cannot exhaust memory.
pub const KEEP_ALL_READER_SAMPLES: i32 = 1000;

/// How long a reliable write may block on a full resend window, unless said otherwise.
pub const MAX_BLOCKING: Duration = Duration::from_millis(100);

/// Depth of a keep-last history when none is described. Deeper than Fast DDS's keep-last 1:
/// the worker drains readers promptly, but bursts between two drains must not be cut to one
/// sample.
pub const DEFAULT_DEPTH: i32 = 64;

/// An endpoint's QoS, every policy a backend must set resolved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EndpointQos {
    /// Writer or reader.
    pub side: EndpointSide,
    /// Reliable or best-effort.
    pub reliability: Reliability,
    /// Volatile, transient-local, ...
    pub durability: Durability,
    /// Keep-last (with depth) or keep-all.
    pub history: History,
    /// Resource limits (a KEEP_ALL reader gets [`KEEP_ALL_READER_SAMPLES`] without any).
    pub resource_limits: Option<ResourceLimitsDesc>,
    /// How long a reliable write may block on a full resend window.
    pub max_blocking: Duration,
    /// The other policies as described (the topic's, overridden by the endpoint's); absent
    /// ones keep the DDS default. Normalised, so that equal QoS compares equal: the policies
    /// resolved above are cleared here, and so is an ownership strength without exclusive
    /// ownership (it means nothing then).
    pub described: QosDesc,
}

impl EndpointQos {
    /// Resolves an endpoint's QoS from its topic's and its own descriptions (its own win).
    pub fn resolve(side: EndpointSide, topic: &QosDesc, endpoint: &QosDesc) -> Self {
        let mut described = topic.overridden_by(*endpoint);
        let reliability = described.reliability.unwrap_or(match side {
            EndpointSide::Writer => Reliability::Reliable,
            EndpointSide::Reader => Reliability::BestEffort,
        });
        let durability = described.durability.unwrap_or(match side {
            EndpointSide::Writer => Durability::TransientLocal,
            EndpointSide::Reader => Durability::Volatile,
        });
        let history = described
            .history
            .unwrap_or(History::KeepLast(DEFAULT_DEPTH));
        let resource_limits = described.resource_limits.or_else(|| {
            // Without limits RustDDS kept 64 samples per topic for a KEEP_ALL reader: a burst
            // beyond that between two takes was lost (100 writers at 20,000 samples/s: 41 %).
            (side == EndpointSide::Reader && matches!(history, History::KeepAll)).then_some(
                ResourceLimitsDesc {
                    max_samples: KEEP_ALL_READER_SAMPLES,
                    max_instances: KEEP_ALL_READER_SAMPLES,
                    max_samples_per_instance: KEEP_ALL_READER_SAMPLES,
                },
            )
        });
        described.reliability = None;
        described.durability = None;
        described.history = None;
        described.resource_limits = None;
        if described.ownership != Some(OwnershipKind::Exclusive) {
            described.ownership_strength = None;
        }
        EndpointQos {
            side,
            reliability,
            durability,
            history,
            resource_limits,
            max_blocking: MAX_BLOCKING,
            described,
        }
    }

    /// Reliable and volatile on both sides, as RPC over DDS (requesters and repliers).
    pub fn service(side: EndpointSide) -> Self {
        let rpc = QosDesc {
            reliability: Some(Reliability::Reliable),
            durability: Some(Durability::Volatile),
            ..QosDesc::default()
        };
        Self::resolve(side, &rpc, &QosDesc::default())
    }

    /// The writer of `ros_discovery_info`, as ROS 2 makes it: reliable, transient-local,
    /// keep-last 1, shared ownership, a write never blocks (the worker's loop would stall).
    pub fn ros_discovery_writer() -> Self {
        let graph = QosDesc {
            reliability: Some(Reliability::Reliable),
            durability: Some(Durability::TransientLocal),
            history: Some(History::KeepLast(1)),
            ownership: Some(OwnershipKind::Shared),
            ..QosDesc::default()
        };
        EndpointQos {
            max_blocking: Duration::ZERO,
            ..Self::resolve(EndpointSide::Writer, &graph, &QosDesc::default())
        }
    }

    /// Whether XRCE writers with this QoS may share a DDS writer without changing what DDS
    /// readers get beyond the writer's identity: a volatile writer keeps no history for late
    /// joiners (a shared transient one would keep its depth over all clients together), and
    /// exclusive ownership picks one writer per instance (sharing would merge the contenders).
    pub fn shareable(&self) -> bool {
        self.durability == Durability::Volatile
            && !matches!(self.described.ownership, Some(OwnershipKind::Exclusive))
    }

    /// The same QoS with `times` the keep-last depth (a shared writer's: every client keeps
    /// the resend window of a writer of its own).
    pub fn deeper(&self, times: usize) -> Self {
        let times = i32::try_from(times).unwrap_or(i32::MAX);
        match self.history {
            History::KeepLast(depth) => EndpointQos {
                history: History::KeepLast(depth.saturating_mul(times)),
                // The limits scale with it: a depth beyond the samples per instance is a
                // policy DDS refuses as inconsistent.
                resource_limits: self.resource_limits.map(|r| ResourceLimitsDesc {
                    max_samples: r.max_samples.saturating_mul(times),
                    max_instances: r.max_instances,
                    max_samples_per_instance: r.max_samples_per_instance.saturating_mul(times),
                }),
                ..*self
            },
            History::KeepAll => *self,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_follow_fast_dds_with_a_deeper_history() {
        let none = QosDesc::default();
        let w = EndpointQos::resolve(EndpointSide::Writer, &none, &none);
        assert_eq!(w.reliability, Reliability::Reliable);
        assert_eq!(w.durability, Durability::TransientLocal);
        assert_eq!(w.history, History::KeepLast(DEFAULT_DEPTH));
        let r = EndpointQos::resolve(EndpointSide::Reader, &none, &none);
        assert_eq!(r.reliability, Reliability::BestEffort);
        assert_eq!(r.durability, Durability::Volatile);
        let explicit = QosDesc {
            reliability: Some(Reliability::Reliable),
            ..Default::default()
        };
        let r = EndpointQos::resolve(EndpointSide::Reader, &none, &explicit);
        assert_eq!(r.reliability, Reliability::Reliable);
    }

    #[test]
    fn the_endpoint_overrides_the_topic() {
        let topic = QosDesc {
            reliability: Some(Reliability::BestEffort),
            history: Some(History::KeepLast(3)),
            ownership_strength: Some(4),
            ..Default::default()
        };
        let endpoint = QosDesc {
            reliability: Some(Reliability::Reliable),
            ..Default::default()
        };
        let q = EndpointQos::resolve(EndpointSide::Writer, &topic, &endpoint);
        assert_eq!(q.reliability, Reliability::Reliable);
        assert_eq!(q.history, History::KeepLast(3));
        // A strength without exclusive ownership means nothing.
        assert_eq!(q.described.ownership_strength, None);
        let exclusive = QosDesc {
            ownership: Some(OwnershipKind::Exclusive),
            ..endpoint
        };
        let q = EndpointQos::resolve(EndpointSide::Writer, &topic, &exclusive);
        assert_eq!(q.described.ownership_strength, Some(4));
    }

    #[test]
    fn equal_qos_compares_equal_however_it_was_spelt() {
        // What shared writers are matched by: an explicit default is the default.
        let none = QosDesc::default();
        let explicit = QosDesc {
            reliability: Some(Reliability::Reliable),
            durability: Some(Durability::TransientLocal),
            history: Some(History::KeepLast(DEFAULT_DEPTH)),
            ownership_strength: Some(3),
            ..QosDesc::default()
        };
        assert_eq!(
            EndpointQos::resolve(EndpointSide::Writer, &none, &none),
            EndpointQos::resolve(EndpointSide::Writer, &none, &explicit)
        );
        let deeper = QosDesc {
            history: Some(History::KeepLast(5)),
            ..QosDesc::default()
        };
        assert_ne!(
            EndpointQos::resolve(EndpointSide::Writer, &none, &none),
            EndpointQos::resolve(EndpointSide::Writer, &none, &deeper)
        );
        assert_eq!(
            EndpointQos::ros_discovery_writer().max_blocking,
            Duration::ZERO
        );
        assert_eq!(
            EndpointQos::resolve(EndpointSide::Writer, &none, &none).max_blocking,
            MAX_BLOCKING
        );
    }

    #[test]
    fn a_keep_all_reader_without_limits_keeps_a_bounded_thousand_samples() {
        let keep_all = QosDesc {
            history: Some(History::KeepAll),
            ..QosDesc::default()
        };
        let none = QosDesc::default();
        let reader = EndpointQos::resolve(EndpointSide::Reader, &none, &keep_all);
        assert_eq!(
            reader.resource_limits.map(|r| r.max_samples),
            Some(KEEP_ALL_READER_SAMPLES)
        );
        // Writers and keep-last readers are left as described.
        let writer = EndpointQos::resolve(EndpointSide::Writer, &none, &keep_all);
        assert_eq!(writer.resource_limits, None);
        let keep_last = QosDesc {
            history: Some(History::KeepLast(5)),
            ..QosDesc::default()
        };
        let reader = EndpointQos::resolve(EndpointSide::Reader, &none, &keep_last);
        assert_eq!(reader.resource_limits, None);
        // Limits the client gave are kept.
        let limited = QosDesc {
            history: Some(History::KeepAll),
            resource_limits: Some(ResourceLimitsDesc {
                max_samples: 7,
                max_instances: -1,
                max_samples_per_instance: -1,
            }),
            ..QosDesc::default()
        };
        let reader = EndpointQos::resolve(EndpointSide::Reader, &none, &limited);
        assert_eq!(reader.resource_limits.map(|r| r.max_samples), Some(7));
    }

    #[test]
    fn only_volatile_shared_ownership_writers_are_shareable_and_deeper_multiplies_keep_last() {
        let none = QosDesc::default();
        let transient = EndpointQos::resolve(EndpointSide::Writer, &none, &none);
        assert!(!transient.shareable());
        let volatile = QosDesc {
            durability: Some(Durability::Volatile),
            ..Default::default()
        };
        let v = EndpointQos::resolve(EndpointSide::Writer, &none, &volatile);
        assert!(v.shareable());
        let exclusive = QosDesc {
            ownership: Some(OwnershipKind::Exclusive),
            ..volatile
        };
        assert!(!EndpointQos::resolve(EndpointSide::Writer, &none, &exclusive).shareable());
        assert_eq!(v.deeper(32).history, History::KeepLast(DEFAULT_DEPTH * 32));
        let keep_all = QosDesc {
            history: Some(History::KeepAll),
            ..volatile
        };
        let k = EndpointQos::resolve(EndpointSide::Writer, &none, &keep_all);
        assert_eq!(k.deeper(32), k);
        let huge = QosDesc {
            history: Some(History::KeepLast(i32::MAX / 2)),
            ..volatile
        };
        let h = EndpointQos::resolve(EndpointSide::Writer, &none, &huge);
        assert_eq!(h.deeper(32).history, History::KeepLast(i32::MAX));
    }
}
