//! Who may hold a session, and how much one client may send: the operator's allow-list of
//! client keys, whether a session may follow its client to another endpoint, and per-client
//! input rate quotas (messages and bytes per second).
//!
//! Sans-IO like the rest of the session core: the caller passes the time.

use std::collections::HashMap;
use std::fmt;
use std::net::IpAddr;
use std::str::FromStr;
use std::time::Instant;

pub use ipnet::IpNet;

use crate::session::budget::OriginId;
use crate::wire::ClientKey;

/// Admission settings of a front-end's sessions.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Admission {
    /// Client keys that may create a session, each from anywhere (`None`) or only from
    /// the listed networks; `None` admits every key. Others get STATUS_ERR_DENIED (counted
    /// as `key_not_allowed`, or `key_wrong_network`).
    pub allowed_keys: Option<HashMap<ClientKey, Option<Vec<IpNet>>>>,
    /// Whether a message presenting a session's client key from another endpoint (a new
    /// source address or port, another connection) moves the session there. Off, only a
    /// CREATE_CLIENT moves a session; other messages from a foreign endpoint are dropped
    /// (counted as `foreign_endpoint`), so nobody who learns a key takes a session over.
    pub allow_roaming: bool,
    /// Input rate quota of each client.
    pub rate: RateQuota,
}

impl Admission {
    /// Whether this key may hold a session from an endpoint at `ip` (`None`: an endpoint
    /// without a network address, such as a serial line, which no network-bound key
    /// matches).
    pub fn admits(&self, key: ClientKey, ip: Option<IpAddr>) -> KeyCheck {
        let Some(keys) = &self.allowed_keys else {
            return KeyCheck::Admitted;
        };
        match keys.get(&key) {
            None => KeyCheck::NotListed,
            Some(None) => KeyCheck::Admitted,
            Some(Some(nets)) => match ip {
                Some(ip) if nets.iter().any(|n| n.contains(&unmapped(ip))) => KeyCheck::Admitted,
                _ => KeyCheck::WrongNetwork,
            },
        }
    }

    /// An allow-list from command-line keys (a key listed both bound and unbound is
    /// admitted from anywhere).
    pub fn allow_list(keys: &[KeyArg]) -> Option<HashMap<ClientKey, Option<Vec<IpNet>>>> {
        if keys.is_empty() {
            return None;
        }
        let mut map: HashMap<ClientKey, Option<Vec<IpNet>>> = HashMap::new();
        for k in keys {
            match (map.get_mut(&k.key), k.network) {
                (Some(None), _) => {}
                (Some(nets), None) => *nets = None,
                (Some(Some(nets)), Some(n)) => nets.push(n),
                (None, n) => {
                    map.insert(k.key, n.map(|n| vec![n]));
                }
            }
        }
        Some(map)
    }
}

/// What the allow-list says of a key at an address.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyCheck {
    /// It may hold a session.
    Admitted,
    /// It is not listed.
    NotListed,
    /// It is listed for other networks.
    WrongNetwork,
}

/// An IPv4-mapped IPv6 address as the IPv4 address it is (a dual-stack socket's view of an
/// IPv4 peer), so that IPv4 networks match it.
fn unmapped(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(ip, IpAddr::V4),
        v4 => v4,
    }
}

/// Most a client may send; beyond, its messages are dropped (counted as `rate_quota`):
/// reliable ones unacknowledged (the client sends them again later: delayed, not lost),
/// best-effort ones for good. Each bound allows a burst of one second's worth.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RateQuota {
    /// Messages (datagrams, or frames on a stream transport) per second.
    pub messages_per_second: Option<u32>,
    /// Bytes per second (of XRCE messages, headers included).
    pub bytes_per_second: Option<u64>,
}

impl RateQuota {
    /// Whether no bound is set.
    pub fn is_unlimited(&self) -> bool {
        self.messages_per_second.is_none() && self.bytes_per_second.is_none()
    }
}

/// A client key as an operator writes it: 8 hexadecimal digits, optionally `0x`-prefixed,
/// in the order the client's code writes the key (`0xAAAABBBB` is the key eProsima's examples
/// pass as `0xAAAABBBB`).
pub fn parse_client_key(s: &str) -> Result<ClientKey, KeyParseError> {
    let t = s.trim();
    let digits = t
        .strip_prefix("0x")
        .or_else(|| t.strip_prefix("0X"))
        .unwrap_or(t);
    if digits.len() != 8 || !digits.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(KeyParseError(s.to_string()));
    }
    u32::from_str_radix(digits, 16)
        .map(|v| ClientKey(v.to_be_bytes()))
        .map_err(|_| KeyParseError(s.to_string()))
}

/// A client key that is not 8 hexadecimal digits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyParseError(pub String);

impl fmt::Display for KeyParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "client key {:?} is not 8 hexadecimal digits, optionally followed by @ and a network (e.g. 0xAAAABBBB or 0xAAAABBBB@192.168.1.0/24)",
            self.0
        )
    }
}

impl std::error::Error for KeyParseError {}

/// A client key as the allow-list takes it: the key, and optionally the one network its
/// client may come from (`0xAAAABBBB@192.168.1.0/24`; a bare address is a /32 or /128).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct KeyArg {
    /// The key.
    pub key: ClientKey,
    /// The network its sessions must come from; `None`: anywhere.
    pub network: Option<IpNet>,
}

impl KeyArg {
    /// A key admitted from anywhere.
    pub fn anywhere(key: ClientKey) -> Self {
        KeyArg { key, network: None }
    }
}

impl fmt::Display for KeyArg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "0x{}", self.key)?;
        if let Some(n) = self.network {
            write!(f, "@{n}")?;
        }
        Ok(())
    }
}

impl FromStr for KeyArg {
    type Err = KeyParseError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (key, network) = match s.split_once('@') {
            Some((k, n)) => {
                let n = n.trim();
                let net = n
                    .parse::<IpNet>()
                    .or_else(|_| n.parse::<IpAddr>().map(IpNet::from))
                    .map_err(|_| KeyParseError(s.to_string()))?;
                (k, Some(net.trunc()))
            }
            None => (s, None),
        };
        Ok(KeyArg {
            key: parse_client_key(key)?,
            network,
        })
    }
}

/// Which bound of a [`RateQuota`] a message exceeded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QuotaHit {
    /// `messages_per_second`.
    Messages,
    /// `bytes_per_second`.
    Bytes,
}

impl QuotaHit {
    /// The bound's name, for logs.
    pub fn name(self) -> &'static str {
        match self {
            QuotaHit::Messages => "messages_per_second",
            QuotaHit::Bytes => "bytes_per_second",
        }
    }
}

/// One token, in the bucket's units: a bucket refills `rate` units a nanosecond, so whole
/// tokens are counted exactly (no drift from floating point).
const TOKEN: i128 = 1_000_000_000;

/// A token bucket: `rate` tokens a second, holding at most a second's worth; it may go into
/// debt by a message larger than that (which then waits its time out).
#[derive(Debug, Clone)]
struct Bucket {
    rate: i128,
    tokens: i128,
    last: Instant,
}

impl Bucket {
    fn new(rate: u64, now: Instant) -> Self {
        let rate = i128::from(rate);
        Bucket {
            rate,
            tokens: rate * TOKEN,
            last: now,
        }
    }

    fn refill(&mut self, now: Instant) {
        let elapsed = now.saturating_duration_since(self.last).as_nanos();
        let gained = i128::try_from(elapsed).unwrap_or(i128::MAX / 2) * self.rate;
        self.tokens = self.tokens.saturating_add(gained).min(self.rate * TOKEN);
        self.last = now;
    }

    /// Whether `n` tokens may be taken (at most a full bucket is asked for, so that a
    /// message larger than a second's worth can pass at all).
    fn has(&self, n: u64) -> bool {
        self.tokens >= i128::from(n).min(self.rate) * TOKEN
    }

    fn is_full(&self) -> bool {
        self.tokens >= self.rate * TOKEN
    }

    fn take(&mut self, n: u64) {
        self.tokens -= i128::from(n) * TOKEN;
    }
}

/// Origins whose creation rate is remembered at most; past it, origins with a full bucket
/// (nothing to remember) are forgotten, then all (a flood of forged sources gains at most a
/// fresh second's worth for each).
const MAX_METERED_ORIGINS: usize = 65_536;

/// How fast each origin (host) starts new sessions: a token bucket per origin, a second's
/// worth of burst.
#[derive(Debug, Clone)]
pub struct CreationMeter {
    per_second: u32,
    buckets: HashMap<OriginId, Bucket>,
}

impl CreationMeter {
    /// A meter allowing `per_second` new sessions per origin (0: unlimited).
    pub fn new(per_second: u32) -> Self {
        CreationMeter {
            per_second,
            buckets: HashMap::new(),
        }
    }

    /// Charges one new session to `origin` if its bucket has a token.
    pub fn admit(&mut self, now: Instant, origin: OriginId) -> bool {
        if self.per_second == 0 {
            return true;
        }
        if !self.buckets.contains_key(&origin) && self.buckets.len() >= MAX_METERED_ORIGINS {
            self.buckets.retain(|_, b| {
                b.refill(now);
                !b.is_full()
            });
            if self.buckets.len() >= MAX_METERED_ORIGINS {
                self.buckets.clear();
            }
        }
        let rate = u64::from(self.per_second);
        let bucket = self
            .buckets
            .entry(origin)
            .or_insert_with(|| Bucket::new(rate, now));
        bucket.refill(now);
        if bucket.has(1) {
            bucket.take(1);
            true
        } else {
            false
        }
    }
}

/// One client's consumption of its [`RateQuota`], with the episode bookkeeping that keeps
/// the log to one line when a client goes over and one when it is back within.
#[derive(Debug, Clone)]
pub struct RateMeter {
    messages: Option<Bucket>,
    bytes: Option<Bucket>,
    /// Messages dropped since the client went over, if it is over.
    over: Option<u64>,
}

/// What [`RateMeter::admit`] decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Metered {
    /// Within the quota.
    Admitted,
    /// Within the quota again after `dropped` messages were refused.
    BackWithin {
        /// Messages dropped while over.
        dropped: u64,
    },
    /// Over the quota: the first message refused since the client was last within it.
    WentOver(QuotaHit),
    /// Still over the quota.
    StillOver,
}

impl RateMeter {
    /// A meter for `quota`, full (a second's burst available) at `now`.
    pub fn new(quota: RateQuota, now: Instant) -> Self {
        RateMeter {
            messages: quota
                .messages_per_second
                .map(|r| Bucket::new(u64::from(r), now)),
            bytes: quota.bytes_per_second.map(|r| Bucket::new(r, now)),
            over: None,
        }
    }

    /// Charges one message of `len` bytes if both bounds have room for it (neither is
    /// charged otherwise).
    pub fn admit(&mut self, now: Instant, len: usize) -> Metered {
        let len = len as u64;
        let mut hit = None;
        if let Some(b) = &mut self.messages {
            b.refill(now);
            if !b.has(1) {
                hit = Some(QuotaHit::Messages);
            }
        }
        if let Some(b) = &mut self.bytes {
            b.refill(now);
            if hit.is_none() && !b.has(len) {
                hit = Some(QuotaHit::Bytes);
            }
        }
        match (hit, self.over) {
            (Some(_), Some(n)) => {
                self.over = Some(n + 1);
                Metered::StillOver
            }
            (Some(h), None) => {
                self.over = Some(1);
                Metered::WentOver(h)
            }
            (None, over) => {
                if let Some(b) = &mut self.messages {
                    b.take(1);
                }
                if let Some(b) = &mut self.bytes {
                    b.take(len);
                }
                self.over = None;
                match over {
                    Some(dropped) => Metered::BackWithin { dropped },
                    None => Metered::Admitted,
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn keys_parse_with_or_without_prefix_in_the_clients_order() {
        assert_eq!(
            parse_client_key("0xAAAABBBB"),
            Ok(ClientKey([0xAA, 0xAA, 0xBB, 0xBB]))
        );
        assert_eq!(
            parse_client_key("dead0001"),
            Ok(ClientKey([0xDE, 0xAD, 0x00, 0x01]))
        );
        for bad in [
            "",
            "0x",
            "AAAABBB",
            "AAAABBBBC",
            "0xGGGGGGGG",
            "+AAABBBB",
            "0x-AABBCC",
        ] {
            assert!(parse_client_key(bad).is_err(), "{bad:?}");
        }
        // The error says what is expected.
        let e = parse_client_key("12").expect_err("too short").to_string();
        assert!(e.contains("8 hexadecimal digits"), "{e}");
    }

    #[test]
    fn a_second_of_burst_then_the_rate() {
        let t0 = Instant::now();
        let quota = RateQuota {
            messages_per_second: Some(10),
            bytes_per_second: None,
        };
        let mut m = RateMeter::new(quota, t0);
        for _ in 0..10 {
            assert_eq!(m.admit(t0, 100), Metered::Admitted);
        }
        assert_eq!(m.admit(t0, 100), Metered::WentOver(QuotaHit::Messages));
        assert_eq!(m.admit(t0, 100), Metered::StillOver);
        // 100 ms later one message's worth came back.
        let t1 = t0 + Duration::from_millis(100);
        assert_eq!(m.admit(t1, 100), Metered::BackWithin { dropped: 2 });
        assert_eq!(m.admit(t1, 100), Metered::WentOver(QuotaHit::Messages));
        // Over a long run the rate holds: 10 a second.
        let mut admitted = 0;
        for i in 1..=1000u64 {
            let t = t1 + Duration::from_millis(i * 10);
            if matches!(
                m.admit(t, 1),
                Metered::Admitted | Metered::BackWithin { .. }
            ) {
                admitted += 1;
            }
        }
        assert_eq!(admitted, 100);
    }

    #[test]
    fn bytes_are_charged_only_when_both_bounds_have_room() {
        let t0 = Instant::now();
        let quota = RateQuota {
            messages_per_second: Some(1000),
            bytes_per_second: Some(1000),
        };
        let mut m = RateMeter::new(quota, t0);
        assert_eq!(m.admit(t0, 600), Metered::Admitted);
        assert_eq!(m.admit(t0, 600), Metered::WentOver(QuotaHit::Bytes));
        // The refused message cost nothing: 400 bytes are still there.
        assert_eq!(m.admit(t0, 400), Metered::BackWithin { dropped: 1 });
        // A message above a second's worth passes on a full bucket.
        let mut big = RateMeter::new(quota, t0);
        assert_eq!(big.admit(t0, 5000), Metered::Admitted);
        assert_eq!(big.admit(t0, 1), Metered::WentOver(QuotaHit::Bytes));
    }

    #[test]
    fn an_allow_list_admits_only_its_keys() {
        let open = Admission::default();
        assert_eq!(
            open.admits(ClientKey([1, 2, 3, 4]), None),
            KeyCheck::Admitted
        );
        let listed = Admission {
            allowed_keys: Some([(ClientKey([1, 2, 3, 4]), None)].into_iter().collect()),
            ..Admission::default()
        };
        assert_eq!(
            listed.admits(ClientKey([1, 2, 3, 4]), None),
            KeyCheck::Admitted
        );
        assert_eq!(
            listed.admits(ClientKey([1, 2, 3, 5]), None),
            KeyCheck::NotListed
        );
    }

    #[test]
    fn a_key_bound_to_a_network_is_admitted_only_from_it() {
        let keys: Vec<KeyArg> = [
            "0xAAAABBBB@192.168.1.0/24",
            "0xAAAABBBB@10.0.0.7",
            "0x01020304",
        ]
        .iter()
        .map(|s| s.parse().expect("key"))
        .collect();
        assert_eq!(keys[1].network, Some("10.0.0.7/32".parse().expect("net")));
        assert_eq!(keys[0].to_string(), "0xAAAABBBB@192.168.1.0/24");
        let a = Admission {
            allowed_keys: Admission::allow_list(&keys),
            ..Admission::default()
        };
        let key = ClientKey([0xAA, 0xAA, 0xBB, 0xBB]);
        let ip = |s: &str| Some(s.parse::<IpAddr>().expect("ip"));
        assert_eq!(a.admits(key, ip("192.168.1.77")), KeyCheck::Admitted);
        assert_eq!(a.admits(key, ip("::ffff:192.168.1.77")), KeyCheck::Admitted);
        assert_eq!(a.admits(key, ip("10.0.0.7")), KeyCheck::Admitted);
        assert_eq!(a.admits(key, ip("10.0.0.8")), KeyCheck::WrongNetwork);
        assert_eq!(
            a.admits(key, None),
            KeyCheck::WrongNetwork,
            "a serial line has no network"
        );
        assert_eq!(a.admits(ClientKey([1, 2, 3, 4]), None), KeyCheck::Admitted);
        // Listed once unbound: admitted from anywhere.
        let both: Vec<KeyArg> = ["0x01020304@10.0.0.0/8", "0x01020304"]
            .iter()
            .map(|s| s.parse().expect("key"))
            .collect();
        let a = Admission {
            allowed_keys: Admission::allow_list(&both),
            ..Admission::default()
        };
        assert_eq!(
            a.admits(ClientKey([1, 2, 3, 4]), ip("192.0.2.1")),
            KeyCheck::Admitted
        );
        assert!("0xAAAABBBB@not-a-net".parse::<KeyArg>().is_err());
    }
}
