//! Which DDS domains clients may use, and how many at once.
//!
//! A DDS domain costs the worker a participant (or two), its threads (RustDDS 2 per
//! participant, Cyclone DDS about 5 per domain), sockets and discovery traffic. Clients choose
//! the domain id of their participants (0-232), so without a bound one client, or a few,
//! could make the worker hold 233 domains. The worker therefore admits a domain only if the
//! operator allowed it (`--domains 0-10,42`) and, by default, only while fewer than
//! [`DEFAULT_MAX_DOMAINS`] distinct domains are in use (`--max-domains N`). A domain is in
//! use while at least one XRCE participant lives in it; when the last one is deleted the
//! worker releases the domain's DDS participants, so its threads and sockets go back.
//!
//! A domain whose discovery multicast port a front-end serves XRCE on (`-p 22150` is domain
//! 59's) cannot have a DDS participant that discovers by multicast: it is refused too, and
//! the agent serves every other domain, as MicroXRCEAgent does on such a port.
//!
//! A refusal is answered `STATUS_ERR_DENIED` (a domain outside `--domains`, or one whose
//! discovery port is taken) or `STATUS_ERR_RESOURCES` (the cap), counted (`domain_denied`,
//! `domain_port_clash`, `domains_refused`) and logged once per episode ([`crate::episodes`]).

use std::collections::BTreeMap;
use std::fmt;
use std::ops::RangeInclusive;
use std::str::FromStr;

use xrce_common::wire::status;

/// The highest domain id DDS allows (RTPS 2.5 §9.6.1.1 with the default port mapping).
pub const MAX_DOMAIN_ID: u16 = 232;

/// How many domain ids DDS allows (0 to [`MAX_DOMAIN_ID`]): the most domains a worker could
/// be asked to serve at once.
pub const DOMAIN_COUNT: u16 = MAX_DOMAIN_ID + 1;

/// Distinct domains in use at once when the operator gave no `--domains` list: a gateway
/// usually serves one or two (ROS_DOMAIN_ID), and 8 Cyclone domains already cost about 40
/// threads.
pub const DEFAULT_MAX_DOMAINS: usize = 8;

/// Why a `--domains` list was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DomainListError {
    /// Nothing in the list.
    #[error("the domain list is empty (example: 0-10,42)")]
    Empty,
    /// An item that is neither a number nor a range `a-b`.
    #[error("{0:?} is not a domain id or a range of them (example: 0-10,42)")]
    Syntax(String),
    /// A domain id above [`MAX_DOMAIN_ID`].
    #[error("domain id {0} is out of range (0-{MAX_DOMAIN_ID})")]
    OutOfRange(u32),
    /// A range whose start is above its end.
    #[error("the range {0}-{1} is empty (its start is above its end)")]
    Reversed(u16, u16),
}

/// A set of domain ids, as `--domains` gives it: ids and inclusive ranges, comma-separated
/// (`0-10,42`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DomainSet(Vec<RangeInclusive<u16>>);

impl DomainSet {
    /// Whether `domain` is in the set.
    pub fn contains(&self, domain: u16) -> bool {
        self.0.iter().any(|r| r.contains(&domain))
    }
}

impl FromStr for DomainSet {
    type Err = DomainListError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let id = |t: &str| -> Result<u16, DomainListError> {
            let t = t.trim();
            if t.is_empty() || !t.bytes().all(|b| b.is_ascii_digit()) {
                return Err(DomainListError::Syntax(s.trim().to_string()));
            }
            // Saturates: a long run of digits is out of range, not a syntax error.
            let v = t.bytes().fold(0u32, |v, b| {
                v.saturating_mul(10).saturating_add(u32::from(b - b'0'))
            });
            u16::try_from(v)
                .ok()
                .filter(|d| *d <= MAX_DOMAIN_ID)
                .ok_or(DomainListError::OutOfRange(v))
        };
        let mut ranges = Vec::new();
        for item in s.split(',').map(str::trim).filter(|i| !i.is_empty()) {
            let range = match item.split_once('-') {
                Some((a, b)) => {
                    let (a, b) = (id(a)?, id(b)?);
                    if a > b {
                        return Err(DomainListError::Reversed(a, b));
                    }
                    a..=b
                }
                None => {
                    let d = id(item)?;
                    d..=d
                }
            };
            ranges.push(range);
        }
        if ranges.is_empty() {
            return Err(DomainListError::Empty);
        }
        Ok(DomainSet(ranges))
    }
}

impl fmt::Display for DomainSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, r) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            if r.start() == r.end() {
                write!(f, "{}", r.start())?;
            } else {
                write!(f, "{}-{}", r.start(), r.end())?;
            }
        }
        Ok(())
    }
}

/// Which domains the worker admits (`--domains`, `--max-domains`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DomainPolicy {
    /// Only these domains (None: any domain id).
    pub allowed: Option<DomainSet>,
    /// At most this many distinct domains in use at once (None: no cap).
    pub max_in_use: Option<usize>,
    /// Domains DDS cannot serve, with why (their discovery multicast port is an XRCE port
    /// of this agent: [`crate::backend::ports::unservable_domains`]).
    pub unservable: BTreeMap<u16, String>,
}

impl Default for DomainPolicy {
    /// Any domain id, at most [`DEFAULT_MAX_DOMAINS`] at once.
    fn default() -> Self {
        DomainPolicy {
            allowed: None,
            max_in_use: Some(DEFAULT_MAX_DOMAINS),
            unservable: BTreeMap::new(),
        }
    }
}

impl DomainPolicy {
    /// The policy of the command line: with a `--domains` list the cap applies only if
    /// `--max-domains` is given too (the list is the operator's bound); without one, the cap
    /// is `--max-domains` or [`DEFAULT_MAX_DOMAINS`].
    pub fn from_options(allowed: Option<DomainSet>, max_in_use: Option<usize>) -> Self {
        let max_in_use = match (&allowed, max_in_use) {
            (_, Some(n)) => Some(n),
            (Some(_), None) => None,
            (None, None) => Some(DEFAULT_MAX_DOMAINS),
        };
        DomainPolicy {
            allowed,
            max_in_use,
            unservable: BTreeMap::new(),
        }
    }
}

/// Why a domain was not admitted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DomainRefusal {
    /// The domain is not in `--domains`.
    #[error("domain {domain} is not among the domains this agent serves (--domains {allowed})")]
    NotAllowed {
        /// The domain asked for.
        domain: u16,
        /// The operator's list.
        allowed: String,
    },
    /// As many domains as allowed are in use already.
    #[error(
        "domain {domain} refused: {in_use} DDS domains are in use, the most this agent serves \
         at once (--max-domains {max}, or --domains)"
    )]
    TooMany {
        /// The domain asked for.
        domain: u16,
        /// Domains in use.
        in_use: usize,
        /// The cap.
        max: usize,
    },
    /// DDS cannot serve the domain on this host while the agent serves XRCE where it is.
    #[error("domain {domain} cannot be served: {why}")]
    PortClash {
        /// The domain asked for.
        domain: u16,
        /// The clash, with the ways out.
        why: String,
    },
}

impl DomainRefusal {
    /// The XRCE status a refused CREATE gets.
    pub fn status(&self) -> u8 {
        match self {
            DomainRefusal::NotAllowed { .. } | DomainRefusal::PortClash { .. } => {
                status::ERR_DENIED
            }
            DomainRefusal::TooMany { .. } => status::ERR_RESOURCES,
        }
    }

    /// The counter it is counted under (the worker's `dropped`, `xrce_dropped_total`).
    pub fn reason(&self) -> &'static str {
        match self {
            DomainRefusal::NotAllowed { .. } => "domain_denied",
            DomainRefusal::TooMany { .. } => "domains_refused",
            DomainRefusal::PortClash { .. } => "domain_port_clash",
        }
    }
}

/// The domains in use (their XRCE participants) and the policy that admits new ones.
#[derive(Debug, Clone, Default)]
pub struct Domains {
    policy: DomainPolicy,
    /// XRCE participants per domain in use (never zero: a domain without one is removed).
    users: BTreeMap<u16, usize>,
}

impl Domains {
    /// No domain in use yet.
    pub fn new(policy: DomainPolicy) -> Self {
        Domains {
            policy,
            users: BTreeMap::new(),
        }
    }

    /// Whether a new XRCE participant may live in `domain` (it changes nothing: a
    /// participant that is then made is counted by [`join`](Self::join)).
    pub fn admit(&self, domain: u16) -> Result<(), DomainRefusal> {
        if self.users.contains_key(&domain) {
            return Ok(());
        }
        if let Some(allowed) = &self.policy.allowed {
            if !allowed.contains(domain) {
                return Err(DomainRefusal::NotAllowed {
                    domain,
                    allowed: allowed.to_string(),
                });
            }
        }
        if let Some(why) = self.policy.unservable.get(&domain) {
            return Err(DomainRefusal::PortClash {
                domain,
                why: why.clone(),
            });
        }
        match self.policy.max_in_use {
            Some(max) if self.users.len() >= max => Err(DomainRefusal::TooMany {
                domain,
                in_use: self.users.len(),
                max,
            }),
            _ => Ok(()),
        }
    }

    /// An XRCE participant was made in `domain`; whether the domain was not in use before.
    pub fn join(&mut self, domain: u16) -> bool {
        let n = self.users.entry(domain).or_default();
        *n += 1;
        *n == 1
    }

    /// An XRCE participant of `domain` was deleted; whether it was the domain's last (the
    /// domain is no longer in use, and its DDS participants can go).
    pub fn leave(&mut self, domain: u16) -> bool {
        match self.users.get_mut(&domain) {
            Some(n) if *n > 1 => {
                *n -= 1;
                false
            }
            Some(_) => {
                self.users.remove(&domain);
                true
            }
            None => false,
        }
    }

    /// The domains in use, in order.
    pub fn in_use(&self) -> impl Iterator<Item = u16> + '_ {
        self.users.keys().copied()
    }

    /// The policy.
    pub fn policy(&self) -> &DomainPolicy {
        &self.policy
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn domain_lists_parse_ids_and_ranges_and_refuse_the_rest() {
        let s: DomainSet = "0-10, 42".parse().expect("a list");
        assert!(s.contains(0) && s.contains(10) && s.contains(42));
        assert!(!s.contains(11) && !s.contains(41) && !s.contains(232));
        assert_eq!(s.to_string(), "0-10,42");
        assert_eq!("232".parse::<DomainSet>().expect("one").to_string(), "232");
        assert_eq!("".parse::<DomainSet>(), Err(DomainListError::Empty));
        assert_eq!(" , ".parse::<DomainSet>(), Err(DomainListError::Empty));
        assert_eq!(
            "233".parse::<DomainSet>(),
            Err(DomainListError::OutOfRange(233))
        );
        assert_eq!(
            "99999999999999999999".parse::<DomainSet>(),
            Err(DomainListError::OutOfRange(u32::MAX))
        );
        assert_eq!(
            "10-2".parse::<DomainSet>(),
            Err(DomainListError::Reversed(10, 2))
        );
        for bad in ["a", "1-", "-1", "1-2-3", "+4", "0x10", "1 2"] {
            assert!(
                matches!(bad.parse::<DomainSet>(), Err(DomainListError::Syntax(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn the_cap_applies_by_default_and_a_list_replaces_it_unless_both_are_given() {
        assert_eq!(
            DomainPolicy::from_options(None, None).max_in_use,
            Some(DEFAULT_MAX_DOMAINS)
        );
        let list: DomainSet = "1-3".parse().expect("a list");
        assert_eq!(
            DomainPolicy::from_options(Some(list.clone()), None).max_in_use,
            None
        );
        assert_eq!(
            DomainPolicy::from_options(Some(list), Some(2)).max_in_use,
            Some(2)
        );
        assert_eq!(
            DomainPolicy::from_options(None, Some(3)).max_in_use,
            Some(3)
        );
    }

    #[test]
    fn a_new_domain_beyond_the_cap_is_refused_until_one_is_released() {
        let mut d = Domains::new(DomainPolicy::from_options(None, Some(2)));
        assert_eq!(d.admit(1), Ok(()));
        assert!(d.join(1));
        assert!(!d.join(1), "a second participant in domain 1");
        assert!(d.join(2));
        let refused = d.admit(3).expect_err("a third domain");
        assert_eq!(refused.status(), status::ERR_RESOURCES);
        assert_eq!(refused.reason(), "domains_refused");
        assert_eq!(
            d.admit(1),
            Ok(()),
            "a domain in use takes more participants"
        );
        assert!(!d.leave(1), "one participant of domain 1 is left");
        assert!(d.admit(3).is_err());
        assert!(d.leave(1), "the last participant of domain 1");
        assert!(!d.leave(1), "nothing left to leave");
        assert_eq!(d.in_use().collect::<Vec<_>>(), vec![2]);
        assert_eq!(d.admit(3), Ok(()));
    }

    #[test]
    fn a_domain_outside_the_list_is_denied() {
        let d = Domains::new(DomainPolicy::from_options(
            Some("0-10,42".parse().expect("a list")),
            None,
        ));
        assert_eq!(d.admit(42), Ok(()));
        let refused = d.admit(11).expect_err("not listed");
        assert_eq!(refused.status(), status::ERR_DENIED);
        assert_eq!(refused.reason(), "domain_denied");
        assert!(
            refused.to_string().contains("--domains 0-10,42"),
            "{refused}"
        );
    }
}
