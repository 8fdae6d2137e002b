//! What clients make the core hold, kept within the front-end's limits: the memory budget
//! (accounting, room asked before bytes are kept, eviction from sessions over their share,
//! reassemblies that stall), session caps, and sessions kept by the endpoint they live at
//! when someone else presents their key.

use super::*;

/// A session must have been silent this long to be evicted for a new one.
const EVICTABLE_SILENCE: Duration = Duration::from_secs(1);
/// Sessions looked at, at most, to free room for one request (each look is a scan).
const MAX_VICTIMS: usize = 16;
/// A takeover probe older than this is forgotten: the next CREATE_CLIENT probes again.
const TAKEOVER_MEMORY: Duration = Duration::from_secs(10);
/// A claim is refused (STATUS_ERR_DENIED) only once the session's endpoint has kept answering
/// for this long: an answer in the first moments may come from another client that was just
/// given that address and port and has not created its own session there yet (which, when it
/// does, ends the old session and lets the claim through).
const DENY_AFTER: Duration = Duration::from_secs(2);

/// Another endpoint's claim on a session (a CREATE_CLIENT with its key).
#[derive(Debug, Clone)]
pub(super) struct Claim<A> {
    /// Who claims it.
    pub(super) claimant: A,
    /// When it first did.
    pub(super) first: Instant,
    /// When the session's endpoint was last probed for it.
    pub(super) probed: Instant,
    /// The claimant's CREATE_CLIENT, answered by the core itself once the probe went
    /// unanswered for the probe wait: a client that reset and came back from a new port gets
    /// its session then, inside its first attempt's wait (eProsima's client waits 1 s for
    /// STATUS_AGENT), instead of at its next attempt.
    pub(super) request: Option<Box<CreateClientPayload>>,
    /// The session's endpoint's host said nothing listens there any more (ICMP port
    /// unreachable, in answer to the probe): the claim needs no longer wait.
    pub(super) endpoint_gone: bool,
}

impl<A> Claim<A> {
    /// When the core answers the claim itself, if it still has to.
    pub(super) fn answer_due(&self, wait: Duration) -> Option<Instant> {
        self.request.as_ref().map(|_| self.probed + wait)
    }
}

/// What a CREATE_CLIENT with a live session's key from another endpoint may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Takeover {
    /// Move the session (its endpoint did not answer, or roaming is allowed).
    Allow,
    /// The current endpoint was probed: no answer to the newcomer yet (it asks again).
    Probing,
    /// The current endpoint answered: the session stays with it.
    Refuse,
}

impl<A: Endpoint> Agent<A> {
    /// Bytes the core holds for a client.
    pub(super) fn held_bytes(c: &ProxyClient<A>) -> usize {
        let reassembly: usize = c.reassembly.values().map(Reassembly::capacity).sum();
        let early: usize = c.reliable_in.values().map(ReliableInput::early_bytes).sum();
        let output: usize = c
            .reliable_out
            .values()
            .map(|s| {
                s.queued_bytes
                    + s.reliable
                        .unacked_messages()
                        .map(<[u8]>::len)
                        .sum::<usize>()
            })
            .sum();
        reassembly + early + output + c.stored
    }

    /// Tells the core how many bytes the front-end's session store takes for a client
    /// beyond the page every session has (its records grow with what it holds, and its
    /// objects are stored): counted in the budget as the client's.
    pub fn set_stored_bytes(&mut self, key: ClientKey, bytes: usize) {
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        if c.stored != bytes {
            c.stored = bytes;
            self.account(key);
        }
    }

    /// Brings the budget's books up to date with what a client holds now.
    pub(super) fn account(&mut self, key: ClientKey) {
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let now_held = Self::held_bytes(c);
        let before = std::mem::replace(&mut c.held, now_held);
        self.budget.changed(c.origin, before, now_held);
    }

    /// Bytes held for every client together, and the budget.
    pub fn memory_held(&self) -> (usize, usize) {
        (self.budget.total(), self.budget.limit())
    }

    /// Whether a client may make the core keep `extra` more bytes; room is taken from
    /// sessions over their share if the budget is full. A refusal is counted as `reason`
    /// and logged once per episode.
    pub(super) fn make_room(
        &mut self,
        now: Instant,
        key: ClientKey,
        extra: usize,
        reason: &'static str,
    ) -> bool {
        let Some(c) = self.clients.get(&key) else {
            return false;
        };
        let (origin, held) = (c.origin, c.held);
        let ok = match self.budget.decide(origin, held, extra) {
            Decision::Grant => true,
            Decision::Evict(needed) => self.evict_over_share(now, needed, key) >= needed,
            Decision::Refuse => false,
        };
        if !ok {
            self.count_drop(reason);
            if let Some(previous) = self.episodes.bite(now, reason) {
                let (total, limit) = self.memory_held();
                tracing::warn!(client = %key, reason, wanted = extra, holds = held, share = self.budget.session_share(origin), held_total = total, budget = limit, previous_episode = previous, "memory budget: refused (further refusals of this kind are counted, not logged, until they stop for 10 s)");
            }
        }
        ok
    }

    /// Frees what sessions over their fair share hold that can be given up (early
    /// messages, which their clients send again; then unfinished reassemblies, lost to
    /// them), the furthest over first, until `needed` bytes are free. Returns the bytes
    /// freed.
    fn evict_over_share(&mut self, now: Instant, needed: usize, except: ClientKey) -> usize {
        // One scan: the sessions over their share that hold something they can give up,
        // the furthest over first.
        let mut victims: Vec<(usize, ClientKey)> = self
            .clients
            .values()
            .filter(|c| c.key != except)
            .filter(|c| {
                c.reliable_in.values().any(|i| i.early_bytes() > 0)
                    || c.reassembly.values().any(|r| !r.is_empty())
            })
            .map(|c| (self.budget.over_share(c.origin, c.held), c.key))
            .filter(|(over, _)| *over > 0)
            .collect();
        victims.sort_unstable_by(|a, b| b.cmp(a));
        let mut freed = 0;
        for (_, victim) in victims.into_iter().take(MAX_VICTIMS) {
            let Some(c) = self.clients.get_mut(&victim) else {
                continue;
            };
            let mut early = 0;
            for input in c.reliable_in.values_mut() {
                early += input.drop_early();
            }
            let mut partial = 0;
            for r in c.reassembly.values_mut() {
                if !r.is_empty() {
                    partial += 1;
                    r.abandon();
                }
            }
            c.reassembly_at.clear();
            let before = c.held;
            self.account(victim);
            let after = self.clients.get(&victim).map_or(0, |c| c.held);
            if early > 0 {
                self.count_drop("early_evicted");
            }
            for _ in 0..partial {
                self.count_drop("reassembly_evicted");
            }
            if let Some(previous) = self.episodes.bite(now, "reassembly_evicted") {
                tracing::warn!(client = %victim, freed = before.saturating_sub(after), previous_episode = previous, "memory budget full: what a session over its share held was given up for another (logged once per episode)");
            }
            freed += before.saturating_sub(after);
            if freed >= needed {
                break;
            }
        }
        freed
    }

    /// Drops a client's reassemblies that gained nothing for the reassembly timeout.
    pub(super) fn drop_stale_reassemblies(&mut self, now: Instant, key: ClientKey) {
        let timeout = self.config.limits.reassembly_timeout;
        let Some(c) = self.clients.get_mut(&key) else {
            return;
        };
        let stale: Vec<u8> = c
            .reassembly_at
            .iter()
            .filter(|(_, at)| now.saturating_duration_since(**at) >= timeout)
            .map(|(s, _)| *s)
            .collect();
        if stale.is_empty() {
            return;
        }
        for s in &stale {
            c.reassembly_at.remove(s);
            if let Some(r) = c.reassembly.get_mut(s) {
                r.abandon();
            }
        }
        for _ in 0..stale.len() {
            self.count_drop("reassembly_stale");
        }
        if let Some(previous) = self.episodes.bite(now, "reassembly_stale") {
            tracing::warn!(client = %key, streams = stale.len(), timeout_ms = timeout.as_millis() as u64, previous_episode = previous, "unfinished FRAGMENT reassembly dropped: no fragment came for too long (logged once per episode)");
        }
        self.account(key);
    }

    /// Whether a new session from `src` fits the session caps, after evicting, if need
    /// be, a silent session without objects: at the per-origin cap one of the newcomer's
    /// origin; at the front-end's cap one of the origin with the most sessions if it holds
    /// more than the newcomer's would (a flood from one host pays first), else the most
    /// silent one anywhere, whatever its origin holds (thousands of hosts with one silent
    /// session each cannot lock a new host out). On `false` the refusal is counted and
    /// logged.
    pub(super) fn admit_session(
        &mut self,
        now: Instant,
        src: A,
        sink: &mut impl OperationSink,
    ) -> bool {
        let origin = src.origin();
        let per_origin = self.config.limits.max_sessions_per_origin;
        if self.budget.sessions_of(origin) >= per_origin
            && !self.evict_session(now, Some(origin), sink)
        {
            self.refuse_session(now, "session_cap_per_address", origin);
            return false;
        }
        if self.clients.len() >= self.config.max_clients {
            let busiest = self.budget.busiest_origin();
            let evicted = busiest.is_some_and(|(o, n)| {
                (o == origin || n > self.budget.sessions_of(origin) + 1)
                    && self.evict_session(now, Some(o), sink)
            }) || self.evict_session(now, None, sink);
            if !evicted {
                self.refuse_session(now, "session_cap", origin);
                return false;
            }
        }
        true
    }

    fn refuse_session(&mut self, now: Instant, reason: &'static str, origin: OriginId) {
        self.count_drop(reason);
        if let Some(previous) = self.episodes.bite(now, reason) {
            tracing::warn!(reason, sessions = self.clients.len(), max_sessions = self.config.max_clients, from_this_origin = self.budget.sessions_of(origin), max_per_origin = self.config.limits.max_sessions_per_origin, previous_episode = previous, "CREATE_CLIENT refused with STATUS_ERR_RESOURCES: session cap reached and no silent session without objects to evict (logged once per episode)");
        }
    }

    /// Evicts the most silent session without objects (none created, none being created)
    /// of `origin`, or of any origin with `None`, silent for at least
    /// [`EVICTABLE_SILENCE`]; whether there was one.
    fn evict_session(
        &mut self,
        now: Instant,
        origin: Option<OriginId>,
        sink: &mut impl OperationSink,
    ) -> bool {
        let victim = self
            .clients
            .values()
            .filter(|c| origin.is_none_or(|o| c.origin == o))
            .filter(|c| !c.has_objects && c.pending_creates.is_empty())
            .filter(|c| now.saturating_duration_since(c.last_heard) >= EVICTABLE_SILENCE)
            .min_by_key(|c| (c.last_heard, c.key))
            .map(|c| c.key);
        let Some(victim) = victim else {
            return false;
        };
        self.count_drop("session_evicted");
        if let Some(previous) = self.episodes.bite(now, "session_evicted") {
            tracing::warn!(client = %victim, previous_episode = previous, "session cap reached: a silent session without objects was deleted for a new one (logged once per episode)");
        }
        self.remove_client(now, victim, sink);
        true
    }

    /// What a CREATE_CLIENT with `key`'s live session from `src`, another endpoint than
    /// the session's, may do: the session's endpoint is probed first, and the session moves
    /// only if it stays silent for the probe wait (a client that restarted from a new port
    /// asks again a second later and gets it); one that keeps answering for [`DENY_AFTER`]
    /// keeps it, and the claimant is refused.
    pub(super) fn takeover(
        &mut self,
        now: Instant,
        key: ClientKey,
        src: A,
        request: &CreateClientPayload,
    ) -> Takeover {
        if self.config.admission.allow_roaming {
            return Takeover::Allow;
        }
        let wait = self.config.limits.takeover_probe_wait;
        let Some(c) = self.clients.get_mut(&key) else {
            return Takeover::Allow;
        };
        if c.addr == src || c.detached {
            return Takeover::Allow;
        }
        let since = |t: Instant| now.saturating_duration_since(t);
        let request = Some(Box::new(request.clone()));
        let claim = match c.takeover.take() {
            Some(claim) if claim.claimant == src && since(claim.probed) < TAKEOVER_MEMORY => {
                if c.last_heard <= claim.probed {
                    if since(claim.probed) >= wait || claim.endpoint_gone {
                        return Takeover::Allow;
                    }
                    // The latest request is the one answered.
                    c.takeover = Some(Claim { request, ..claim });
                    return Takeover::Probing;
                }
                if since(claim.first) >= DENY_AFTER {
                    return Takeover::Refuse;
                }
                // Alive so far: probed again, asked again.
                Claim {
                    probed: now,
                    request,
                    ..claim
                }
            }
            _ => Claim {
                claimant: src,
                first: now,
                probed: now,
                request,
                endpoint_gone: false,
            },
        };
        c.takeover = Some(claim);
        let mut b = MessageBuilder::new(c.header(stream_id::NONE, 0));
        let probe = crate::wire::GetInfoPayload {
            base: BaseObjectRequest {
                request_id: LIVELINESS_PROBE_ID,
                object_id: ObjectId::AGENT,
            },
            info_mask: 0x02,
        };
        let _ = b.push(&Payload::GetInfo(probe), true);
        let addr = c.addr;
        self.push_transmit(addr, b.finish());
        Takeover::Probing
    }
}
