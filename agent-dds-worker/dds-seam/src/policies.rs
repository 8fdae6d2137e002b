//! The DDS QoS policies an XRCE object can ask for, in the worker's own vocabulary: what the
//! XML and binary representations are read into, what the topic's and the endpoint's
//! settings are merged as ([`QosDesc::overridden_by`]), and what each backend maps onto its
//! own policies. `None` is "not given": the reference agent's defaults apply
//! ([`crate::qos`]).

/// Reliability kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reliability {
    /// RELIABLE.
    Reliable,
    /// BEST_EFFORT.
    BestEffort,
}

/// Durability kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    /// VOLATILE.
    Volatile,
    /// TRANSIENT_LOCAL.
    TransientLocal,
    /// TRANSIENT.
    Transient,
    /// PERSISTENT.
    Persistent,
}

/// History kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum History {
    /// KEEP_LAST with a depth.
    KeepLast(i32),
    /// KEEP_ALL.
    KeepAll,
}

/// A QoS duration: finite, or `DURATION_INFINITY`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Period {
    /// A finite duration.
    Finite(std::time::Duration),
    /// Infinite.
    Infinite,
}

/// Liveliness kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LivelinessKind {
    /// AUTOMATIC.
    Automatic,
    /// MANUAL_BY_PARTICIPANT.
    ManualByParticipant,
    /// MANUAL_BY_TOPIC.
    ManualByTopic,
}

/// Ownership kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OwnershipKind {
    /// SHARED.
    Shared,
    /// EXCLUSIVE.
    Exclusive,
}

/// Destination order kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DestinationOrderKind {
    /// BY_RECEPTION_TIMESTAMP.
    ByReception,
    /// BY_SOURCE_TIMESTAMP.
    BySource,
}

/// Presentation access scopes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AccessScope {
    /// INSTANCE.
    Instance,
    /// TOPIC.
    Topic,
    /// GROUP.
    Group,
}

/// Presentation QoS.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PresentationDesc {
    /// Access scope.
    pub access_scope: AccessScope,
    /// Coherent access.
    pub coherent_access: bool,
    /// Ordered access.
    pub ordered_access: bool,
}

/// Resource limits; -1 is unlimited.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResourceLimitsDesc {
    /// Samples in the cache.
    pub max_samples: i32,
    /// Instances in the cache.
    pub max_instances: i32,
    /// Samples per instance.
    pub max_samples_per_instance: i32,
}

/// QoS settings found in a representation (absent = the entity's default). See the crate
/// documentation for how each maps to RustDDS.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct QosDesc {
    /// `<reliability><kind>`.
    pub reliability: Option<Reliability>,
    /// `<durability><kind>`.
    pub durability: Option<Durability>,
    /// `<historyQos>` / `<history>`.
    pub history: Option<History>,
    /// `<deadline><period>`.
    pub deadline: Option<Period>,
    /// `<lifespan><duration>`.
    pub lifespan: Option<Period>,
    /// `<latencyBudget><duration>`.
    pub latency_budget: Option<Period>,
    /// `<timeBasedFilter><minimum_separation>`.
    pub time_based_filter: Option<Period>,
    /// `<liveliness>`: kind and lease duration.
    pub liveliness: Option<(LivelinessKind, Period)>,
    /// `<ownership><kind>`.
    pub ownership: Option<OwnershipKind>,
    /// `<ownershipStrength><value>`.
    pub ownership_strength: Option<i32>,
    /// `<destinationOrder><kind>`.
    pub destination_order: Option<DestinationOrderKind>,
    /// `<resourceLimitsQos>`.
    pub resource_limits: Option<ResourceLimitsDesc>,
    /// `<presentation>`.
    pub presentation: Option<PresentationDesc>,
    /// Whether `<partition>` names were given (RustDDS has no partitions).
    pub partitions: bool,
}

impl QosDesc {
    /// These settings, with every one that `over` sets replaced by its value.
    pub fn overridden_by(self, over: QosDesc) -> QosDesc {
        QosDesc {
            reliability: over.reliability.or(self.reliability),
            durability: over.durability.or(self.durability),
            history: over.history.or(self.history),
            deadline: over.deadline.or(self.deadline),
            lifespan: over.lifespan.or(self.lifespan),
            latency_budget: over.latency_budget.or(self.latency_budget),
            time_based_filter: over.time_based_filter.or(self.time_based_filter),
            liveliness: over.liveliness.or(self.liveliness),
            ownership: over.ownership.or(self.ownership),
            ownership_strength: over.ownership_strength.or(self.ownership_strength),
            destination_order: over.destination_order.or(self.destination_order),
            resource_limits: over.resource_limits.or(self.resource_limits),
            presentation: over.presentation.or(self.presentation),
            partitions: over.partitions || self.partitions,
        }
    }
}
