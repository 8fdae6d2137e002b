//! What a front-end lets its clients make it hold: one memory budget shared fairly between
//! the hosts that send to it and between the sessions of each host, and caps on sessions.
//!
//! The budget covers what a client's messages and reads make the session core keep:
//! partial FRAGMENT reassemblies, reliable messages that arrived early, output waiting for
//! the client's window and output the client has not acknowledged. Under no pressure (less
//! than half the budget in use) a session takes what it asks for; beyond, only up to its
//! fair share: the budget split evenly between the hosts that hold sessions, and a host's
//! part evenly between its sessions. A session within its share that finds the budget full
//! takes room from the sessions furthest over theirs (what they hold that can be given up:
//! early messages, which the client sends again, then unfinished reassemblies), so one host
//! opening many sessions, or one session stuffing its streams, cannot take the others' room.
//!
//! Sans-IO: no clock; the caller passes the time where one is needed.

use std::collections::HashMap;
use std::fmt::Debug;
use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

/// The host a message came from, as far as the transport tells: sessions and memory are
/// shared fairly between origins. For IP transports the peer's address (any port), for a
/// serial line the line (everyone on it shares one wire).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct OriginId(pub u128);

impl std::fmt::Display for OriginId {
    /// An IPv4 address, an IPv6 /64, or a small number (a serial line, a test's endpoint).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let v6 = std::net::Ipv6Addr::from(self.0);
        match v6.to_ipv4_mapped() {
            Some(v4) => write!(f, "{v4}"),
            None if self.0 < 1 << 16 => write!(f, "#{}", self.0),
            None => write!(f, "{v6}/64"),
        }
    }
}

/// What the session core needs to know of an endpoint beyond its identity.
pub trait Origin {
    /// The host it belongs to.
    fn origin(&self) -> OriginId;
    /// Its network address, if it has one (a serial line has none): checked against the
    /// networks an operator bound a client key to.
    fn ip(&self) -> Option<IpAddr>;
}

/// The origin of an IP address: IPv4 addresses as their IPv4-mapped IPv6 form, so that a
/// dual-stack socket's two views of one peer are one origin; an IPv6 address by its /64
/// (one host commonly holds a whole /64 and may use any address of it).
pub fn ip_origin(ip: IpAddr) -> OriginId {
    let bits = match ip {
        IpAddr::V4(v4) => u128::from(v4.to_ipv6_mapped()),
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => u128::from(v4.to_ipv6_mapped()),
            None => u128::from(v6) & !((1u128 << 64) - 1),
        },
    };
    OriginId(bits)
}

impl Origin for SocketAddr {
    fn origin(&self) -> OriginId {
        ip_origin(self.ip())
    }
    fn ip(&self) -> Option<IpAddr> {
        Some(SocketAddr::ip(self))
    }
}

/// Small integers as endpoints (tests, fuzzing, benchmarks): each value its own host.
macro_rules! integer_origin {
    ($($t:ty),*) => {$(
        impl Origin for $t {
            fn origin(&self) -> OriginId {
                OriginId(u128::from(*self))
            }
            fn ip(&self) -> Option<IpAddr> {
                None
            }
        }
    )*};
}
integer_origin!(u8, u16, u32, u64);

/// Resource limits of one front-end's sessions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Bytes the session core may hold for all clients together (see the module docs).
    pub memory_budget: usize,
    /// Most sessions from one origin; a new one beyond evicts that origin's most silent
    /// session without objects, or is refused with STATUS_ERR_RESOURCES.
    pub max_sessions_per_origin: usize,
    /// A FRAGMENT reassembly that gains nothing for this long is dropped.
    pub reassembly_timeout: Duration,
    /// How long the session of a client whose connection closed (TCP) waits for it to come
    /// back before it and its objects are deleted; `None` keeps it.
    pub detached_grace: Option<Duration>,
    /// How long the session's current endpoint has to answer a liveliness probe before a
    /// CREATE_CLIENT with its key from another endpoint may move it there.
    pub takeover_probe_wait: Duration,
    /// New sessions one origin may start per second (a second's worth at once); beyond,
    /// CREATE_CLIENTs that would start one (or replace another key's session at their
    /// endpoint) go unanswered, counted as `session_creation_rate`. 0: no limit.
    pub new_sessions_per_second: u32,
}

/// Default [`Limits::memory_budget`]: 64 MiB, which a small gateway can spare.
pub const DEFAULT_MEMORY_BUDGET: usize = 64 << 20;
/// Default [`Limits::max_sessions_per_origin`].
pub const DEFAULT_MAX_SESSIONS_PER_ORIGIN: usize = 2048;
/// Default most sessions of one front-end.
pub const DEFAULT_MAX_SESSIONS: usize = 8192;
/// Default [`Limits::new_sessions_per_second`]: far above any fleet's reconnection storm
/// from one host, far below a flood.
pub const DEFAULT_NEW_SESSIONS_PER_SECOND: u32 = 1000;

impl Default for Limits {
    fn default() -> Self {
        Limits {
            memory_budget: DEFAULT_MEMORY_BUDGET,
            max_sessions_per_origin: DEFAULT_MAX_SESSIONS_PER_ORIGIN,
            reassembly_timeout: Duration::from_secs(5),
            detached_grace: Some(Duration::from_secs(60)),
            takeover_probe_wait: Duration::from_millis(300),
            new_sessions_per_second: DEFAULT_NEW_SESSIONS_PER_SECOND,
        }
    }
}

/// How a front-end's memory budget is split between the parts that hold what clients
/// send: the session core, object descriptions, operations waiting for the worker and
/// reliable writes retained until DDS acknowledges them (the last two are flow control:
/// full, they refuse reliable input unacknowledged, so clients send it again later).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BudgetSplit {
    /// The session core ([`Limits::memory_budget`]): half.
    pub core: usize,
    /// Object descriptions kept for replay: an eighth.
    pub objects: usize,
    /// Operations waiting to be handed to the worker: three sixteenths.
    pub outbox: usize,
    /// Reliable writes retained for a worker crash: three sixteenths.
    pub retained: usize,
}

impl BudgetSplit {
    /// The parts of a budget of `total` bytes.
    pub fn of(total: usize) -> Self {
        let sixteenth = total / 16;
        BudgetSplit {
            core: total / 2,
            objects: total / 8,
            outbox: 3 * sixteenth,
            retained: 3 * sixteenth,
        }
    }
}

/// A session may always hold this much while the budget has room, whatever its share: a
/// few messages of the largest MTU.
const MIN_GRANT: usize = 16 << 10;

/// What [`Budget::decide`] says of a request for more room.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decision {
    /// Take it.
    Grant,
    /// The session is within its share but the budget is full: free this many bytes held
    /// by sessions over their share, then take it.
    Evict(usize),
    /// Refused: the session is over its share and the budget is under pressure.
    Refuse,
}

#[derive(Debug, Clone, Copy, Default)]
struct OriginUse {
    held: usize,
    sessions: usize,
}

/// The bookkeeping of one memory budget: bytes held per origin and in total, sessions per
/// origin. The session core tells it every change; it decides nothing by itself but
/// [`Budget::decide`].
#[derive(Debug, Clone)]
pub struct Budget {
    limit: usize,
    total: usize,
    origins: HashMap<OriginId, OriginUse>,
}

impl Budget {
    /// An empty budget of `limit` bytes.
    pub fn new(limit: usize) -> Self {
        Budget {
            limit: limit.max(MIN_GRANT),
            total: 0,
            origins: HashMap::new(),
        }
    }

    /// The limit in bytes.
    pub fn limit(&self) -> usize {
        self.limit
    }

    /// Bytes held in total.
    pub fn total(&self) -> usize {
        self.total
    }

    /// Sessions of an origin.
    pub fn sessions_of(&self, origin: OriginId) -> usize {
        self.origins.get(&origin).map_or(0, |u| u.sessions)
    }

    /// Bytes held by an origin's sessions.
    pub fn held_by(&self, origin: OriginId) -> usize {
        self.origins.get(&origin).map_or(0, |u| u.held)
    }

    /// The origin with the most sessions, and how many.
    pub fn busiest_origin(&self) -> Option<(OriginId, usize)> {
        self.origins
            .iter()
            .max_by_key(|(o, u)| (u.sessions, **o))
            .map(|(o, u)| (*o, u.sessions))
    }

    /// A session of `origin` began.
    pub fn session_added(&mut self, origin: OriginId) {
        self.origins.entry(origin).or_default().sessions += 1;
    }

    /// A session of `origin` that held `held` bytes ended.
    pub fn session_removed(&mut self, origin: OriginId, held: usize) {
        self.total = self.total.saturating_sub(held);
        if let Some(u) = self.origins.get_mut(&origin) {
            u.held = u.held.saturating_sub(held);
            u.sessions = u.sessions.saturating_sub(1);
            if u.sessions == 0 {
                self.origins.remove(&origin);
            }
        }
    }

    /// A session of `origin` went from holding `before` to holding `after` bytes.
    pub fn changed(&mut self, origin: OriginId, before: usize, after: usize) {
        if before == after {
            return;
        }
        let u = self.origins.entry(origin).or_default();
        u.held = u.held.saturating_sub(before).saturating_add(after);
        self.total = self.total.saturating_sub(before).saturating_add(after);
    }

    /// The fair share of one session of `origin`: the budget split evenly between origins,
    /// an origin's part evenly between its sessions.
    pub fn session_share(&self, origin: OriginId) -> usize {
        let origins = self.origins.len().max(1);
        let sessions = self.sessions_of(origin).max(1);
        self.limit / origins / sessions
    }

    /// Whether a session of `origin` holding `held` bytes is over its fair share, and by
    /// how much.
    pub fn over_share(&self, origin: OriginId, held: usize) -> usize {
        held.saturating_sub(self.session_share(origin))
    }

    /// Whether a session of `origin` holding `held` bytes may take `extra` more.
    pub fn decide(&self, origin: OriginId, held: usize, extra: usize) -> Decision {
        let after = self.total.saturating_add(extra);
        let wanted = held.saturating_add(extra);
        let within_share = wanted <= self.session_share(origin).max(MIN_GRANT);
        if after <= self.limit {
            if after <= self.limit / 2 || within_share {
                Decision::Grant
            } else {
                Decision::Refuse
            }
        } else if within_share && extra <= self.limit {
            Decision::Evict(after - self.limit)
        } else {
            Decision::Refuse
        }
    }
}

/// How long a kind of refusal must stay quiet before the next one starts a new episode
/// (and a new log line).
pub const EPISODE_QUIET: Duration = Duration::from_secs(10);

/// Log lines of refusals, one per episode: the first refusal of a kind is logged, the
/// following ones counted until the kind has been quiet for [`EPISODE_QUIET`].
#[derive(Debug, Default, Clone)]
pub struct Episodes {
    open: HashMap<&'static str, (Instant, u64)>,
}

impl Episodes {
    /// Notes a refusal of kind `reason` at `now`. Returns `Some(n)` when it starts a new
    /// episode (log it), `n` being the refusals of the episode before, if any.
    pub fn bite(&mut self, now: Instant, reason: &'static str) -> Option<u64> {
        match self.open.get_mut(reason) {
            Some((last, n)) if now.saturating_duration_since(*last) < EPISODE_QUIET => {
                *last = now;
                *n += 1;
                None
            }
            Some((last, n)) => {
                let before = *n;
                *last = now;
                *n = 1;
                Some(before)
            }
            None => {
                self.open.insert(reason, (now, 1));
                Some(0)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: OriginId = OriginId(1);
    const B: OriginId = OriginId(2);

    #[test]
    fn shares_split_between_origins_then_sessions() {
        let mut b = Budget::new(1 << 20);
        for _ in 0..4 {
            b.session_added(A);
        }
        b.session_added(B);
        assert_eq!(b.session_share(B), 512 << 10);
        assert_eq!(b.session_share(A), 128 << 10);
    }

    #[test]
    fn no_pressure_grants_over_share() {
        let mut b = Budget::new(1 << 20);
        b.session_added(A);
        b.session_added(B);
        assert_eq!(b.decide(A, 0, 500 << 10), Decision::Grant);
        b.changed(A, 0, 500 << 10);
        // Past half the budget, A (over its half) is refused, B is not.
        assert_eq!(b.decide(A, 500 << 10, 100 << 10), Decision::Refuse);
        assert_eq!(b.decide(B, 0, 100 << 10), Decision::Grant);
    }

    #[test]
    fn full_budget_evicts_for_a_session_within_share() {
        let mut b = Budget::new(1 << 20);
        b.session_added(A);
        b.session_added(B);
        b.changed(A, 0, 1 << 20);
        assert_eq!(b.decide(B, 0, 4096), Decision::Evict(4096));
        assert_eq!(b.decide(A, 1 << 20, 4096), Decision::Refuse);
    }

    #[test]
    fn removal_returns_room() {
        let mut b = Budget::new(1 << 20);
        b.session_added(A);
        b.changed(A, 0, 1000);
        b.session_removed(A, 1000);
        assert_eq!(b.total(), 0);
        assert_eq!(b.sessions_of(A), 0);
        assert!(b.busiest_origin().is_none());
    }

    #[test]
    fn episodes_log_once_until_quiet() {
        let mut e = Episodes::default();
        let t = Instant::now();
        assert_eq!(e.bite(t, "x"), Some(0));
        assert_eq!(e.bite(t + Duration::from_secs(1), "x"), None);
        assert_eq!(e.bite(t + Duration::from_secs(9), "x"), None);
        assert_eq!(e.bite(t + Duration::from_secs(30), "x"), Some(3));
        assert_eq!(e.bite(t, "y"), Some(0));
    }

    #[test]
    fn mapped_and_plain_ipv4_are_one_origin() {
        let v4: IpAddr = "192.0.2.1".parse().expect("ip");
        let mapped: IpAddr = "::ffff:192.0.2.1".parse().expect("ip");
        assert_eq!(ip_origin(v4), ip_origin(mapped));
        let a: IpAddr = "2001:db8:1:2::1".parse().expect("ip");
        let b: IpAddr = "2001:db8:1:2:ffff::9".parse().expect("ip");
        let c: IpAddr = "2001:db8:1:3::1".parse().expect("ip");
        assert_eq!(ip_origin(a), ip_origin(b), "one /64, one host");
        assert_ne!(ip_origin(a), ip_origin(c));
        assert_ne!(ip_origin(v4), ip_origin("192.0.2.2".parse().expect("ip")));
    }
}
