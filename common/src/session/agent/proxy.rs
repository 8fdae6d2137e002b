//! One client's session as the agent keeps it: its streams, timers and counters.

use super::*;

/// Most CREATEs of one session waiting for their STATUS that are told apart; beyond, the
/// session is taken as one with objects.
pub(super) const MAX_PENDING_CREATES: usize = 32;

/// A reliable output stream and the submessages waiting for its window.
#[derive(Debug)]
pub(super) struct OutStream {
    /// Bytes in `queue`.
    pub(super) queued_bytes: usize,
    pub(super) reliable: ReliableOutput,
    /// Encoded submessages waiting for window room.
    pub(super) queue: VecDeque<Vec<u8>>,
}

/// Writes the worker executed on one reliable input stream for the front-end this one took
/// over from, which had not stored the messages that carried them as taken: every write of
/// the messages from `from` (the one the stored stream expected) up to `last.sequence`, and
/// those of that message up to `last.write_index`. The messages themselves are processed
/// again (their other operations were not necessarily executed); only these writes are not
/// handed over a second time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct ExecutedFloor {
    pub(super) from: u16,
    pub(super) last: InputPosition,
}

impl ExecutedFloor {
    /// Whether the write at `position` is one of them.
    pub(super) fn covers(&self, position: &InputPosition) -> bool {
        let last = &self.last;
        if (position.epoch, position.stream_id) != (last.epoch, last.stream_id) {
            return false;
        }
        let span = last.sequence.wrapping_sub(self.from);
        let offset = position.sequence.wrapping_sub(self.from);
        offset < span || (offset == span && position.write_index <= last.write_index)
    }

    /// Whether a message `sequence` processed on its stream ends it: the last of its
    /// messages, or one outside them (a HEARTBEAT made the client skip some; sequence
    /// numbers wrap, so it must not wait).
    pub(super) fn ends_with(&self, sequence: u16) -> bool {
        sequence.wrapping_sub(self.from) >= self.last.sequence.wrapping_sub(self.from)
    }
}

/// The agent's state of one client's session.
#[derive(Debug)]
pub(super) struct ProxyClient<A> {
    pub(super) key: ClientKey,
    pub(super) session_id: u8,
    pub(super) addr: A,
    pub(super) mtu: u16,
    /// Whether the client announced its MTU (eProsima's CREATE_CLIENT property); if not,
    /// `mtu` is assumed, and bounds its fragments but not its best-effort messages.
    pub(super) mtu_announced: bool,
    pub(super) last_heard: Instant,
    pub(super) reliable_in: HashMap<u8, ReliableInput>,
    pub(super) best_effort_in: HashMap<u8, BestEffortInput>,
    pub(super) reliable_out: HashMap<u8, OutStream>,
    pub(super) best_effort_out: HashMap<u8, u16>,
    pub(super) reassembly: HashMap<u8, Reassembly>,
    pub(super) heartbeat_due: Option<Instant>,
    /// The period of the next HEARTBEAT (backs off while the client does not answer).
    pub(super) heartbeat_interval: Duration,
    /// The entry of this client in the agent's timer heap, if any.
    pub(super) timer: Option<Instant>,
    /// Its input rate quota's consumption (none when unlimited).
    pub(super) meter: Option<RateMeter>,
    /// Messages dropped because they presented this client's key from another endpoint.
    pub(super) foreign_drops: u64,
    /// What this client sent, received and lost.
    pub(super) counters: ClientCounters,
    /// When its session was created (a CREATE_CLIENT of the same session keeps it).
    pub(super) created_at: Instant,
    pub(super) delete_requested: bool,
    /// When the session was created or its streams last reset by a CREATE_CLIENT.
    pub(super) established_at: Instant,
    /// Whether the client sent anything on a stream since then.
    pub(super) streams_used: bool,
    /// A CREATE_CLIENT repeating the session came soon after it was established (taken for
    /// a duplicate, its streams kept): if the client's next message on a stream is numbered
    /// from the start again, behind what was taken, it was the client's restart after all
    /// (a board that reset at once), and the streams start again then.
    pub(super) restart_suspected: bool,
    /// The run of the client's streams ([`InputPosition::epoch`]).
    pub(super) epoch: u64,
    /// Writes the worker executed on a reliable input stream that the front-end this one
    /// took over from had not stored as taken (it handed them over, then died); one entry
    /// per stream at most, each dropped once the last of its messages was processed.
    pub(super) executed_floor: Vec<ExecutedFloor>,
    /// Taken over from a stored session and nothing processed since: the worker's last
    /// executed writes may still be applied ([`Agent::skip_executed`]); a session made or
    /// restarted since numbers its streams afresh, and they would mean nothing there.
    pub(super) awaiting_executed: bool,
    pub(super) dialect: Dialect,
    /// Silence after which the client is dead (hard liveliness or the configured dead time).
    pub(super) dead_time: Option<Duration>,
    /// Its endpoint closed (a TCP connection): nothing is sent until it is heard again.
    pub(super) detached: bool,
    /// When the last GET_INFO liveliness probe went out.
    pub(super) last_probe: Option<Instant>,
    /// The last ACKNACK sent on each reliable input stream and when (see [`AckCause`]).
    pub(super) last_acknack: HashMap<u8, (u16, u16, Instant)>,
    /// The host its endpoint belongs to (the budget's books are kept by origin).
    pub(super) origin: OriginId,
    /// Bytes the core holds for it, as last accounted in the budget.
    pub(super) held: usize,
    /// Bytes the front-end's session store takes for it beyond its first page
    /// ([`Agent::set_stored_bytes`]); part of `held`.
    pub(super) stored: usize,
    /// Whether one of its CREATEs succeeded (sessions without objects are evicted first; a
    /// refused CREATE does not count, so refusals cannot pin a session).
    pub(super) has_objects: bool,
    /// Objects whose CREATE waits for its STATUS (bounded by [`MAX_PENDING_CREATES`]:
    /// beyond, the session counts as having objects); a session with one is not evicted.
    pub(super) pending_creates: Vec<ObjectId>,
    /// When each reliable input stream's unfinished reassembly last gained a fragment.
    pub(super) reassembly_at: HashMap<u8, Instant>,
    /// Another endpoint's claim on the session (CREATE_CLIENT with its key), and when the
    /// session's endpoint was probed for it.
    pub(super) takeover: Option<super::limits::Claim<A>>,
    /// Its dead time before its endpoint closed (the detached grace replaces it meanwhile).
    pub(super) attached_dead_time: Option<Option<Duration>>,
    /// When its endpoint closed (while detached).
    pub(super) closed_at: Option<Instant>,
    /// The number of the first message of each new stream, both ways: 0 as the spec's
    /// "initialize to 0" is read by eProsima, 1 for a client that reads it as the number
    /// before the first (RTI's nano-client: [`first_sequence_number`]).
    pub(super) first_seq: u16,
}

/// The number a client's streams start at, by its vendor: RTI's nano-client sends its
/// first reliable message as 1 and drops a first message numbered 0 (its stream state
/// starts at 0 = nothing received); every other client starts at 0.
pub(super) fn first_sequence_number(vendor: [u8; 2]) -> u16 {
    u16::from(vendor == crate::wire::VENDOR_RTI)
}

/// What a session is opened with: what the client's CREATE_CLIENT (or a stored snapshot)
/// says of it.
#[derive(Debug, Clone, Copy)]
pub(super) struct SessionTerms {
    /// The client's key.
    pub(super) key: ClientKey,
    /// Its session id.
    pub(super) session_id: u8,
    /// Largest message it takes.
    pub(super) mtu: u16,
    /// How its messages are written (the spec's or eProsima's).
    pub(super) dialect: Dialect,
    /// How long it may stay silent before it is probed and then dropped.
    pub(super) dead_time: Option<Duration>,
}

impl<A: Origin> ProxyClient<A> {
    /// A fresh session at `addr`: no stream used yet.
    pub(super) fn new(terms: SessionTerms, addr: A, now: Instant, config: &AgentConfig) -> Self {
        let SessionTerms {
            key,
            session_id,
            mtu,
            dialect,
            dead_time,
        } = terms;
        ProxyClient {
            key,
            session_id,
            mtu,
            mtu_announced: false,
            last_heard: now,
            reliable_in: HashMap::new(),
            best_effort_in: HashMap::new(),
            reliable_out: HashMap::new(),
            best_effort_out: HashMap::new(),
            reassembly: HashMap::new(),
            heartbeat_due: None,
            heartbeat_interval: config.heartbeat_period,
            timer: None,
            meter: (!config.admission.rate.is_unlimited())
                .then(|| RateMeter::new(config.admission.rate, now)),
            foreign_drops: 0,
            counters: ClientCounters::default(),
            created_at: now,
            delete_requested: false,
            established_at: now,
            streams_used: false,
            restart_suspected: false,
            epoch: 0,
            executed_floor: Vec::new(),
            awaiting_executed: false,
            dialect,
            dead_time,
            detached: false,
            last_probe: None,
            last_acknack: HashMap::new(),
            origin: addr.origin(),
            held: 0,
            stored: 0,
            has_objects: false,
            pending_creates: Vec::new(),
            reassembly_at: HashMap::new(),
            takeover: None,
            attached_dead_time: None,
            first_seq: 0,
            closed_at: None,
            addr,
        }
    }

    pub(super) fn header(&self, stream: u8, seq: u16) -> MessageHeader {
        MessageHeader::new(self.session_id, stream, seq, self.key)
    }

    pub(super) fn reset_streams(&mut self, epoch: u64) {
        self.epoch = epoch;
        self.reliable_in.clear();
        self.best_effort_in.clear();
        self.reliable_out.clear();
        self.best_effort_out.clear();
        self.reassembly.clear();
        self.reassembly_at.clear();
        self.heartbeat_due = None;
        self.streams_used = false;
        self.restart_suspected = false;
        self.executed_floor.clear();
        self.awaiting_executed = false;
        self.last_acknack.clear();
    }

    /// When this client's timers have something to do next: a HEARTBEAT, a liveliness
    /// probe, or (detached: nobody to probe) the end of its dead time.
    pub(super) fn next_due(
        &self,
        reassembly_timeout: Duration,
        takeover_probe_wait: Duration,
    ) -> Option<Instant> {
        let liveliness = if self.detached {
            self.dead_time
                .map(|d| self.closed_at.unwrap_or(self.last_heard) + d)
        } else {
            self.liveliness_due()
        };
        let stale = self
            .reassembly_at
            .values()
            .min()
            .map(|at| *at + reassembly_timeout);
        let claim = self
            .takeover
            .as_ref()
            .and_then(|c| c.answer_due(takeover_probe_wait));
        [
            self.heartbeat_due.filter(|_| !self.detached),
            liveliness,
            stale,
            claim,
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Its endpoint is back: the dead time it had before it closed applies again.
    pub(super) fn reattach(&mut self) {
        self.detached = false;
        self.closed_at = None;
        if let Some(d) = self.attached_dead_time.take() {
            self.dead_time = d;
        }
    }

    /// When the liveliness check of this client has something to do next.
    pub(super) fn liveliness_due(&self) -> Option<Instant> {
        let dead = self.dead_time?;
        let probe_every = probe_period(dead);
        let first_probe = self.last_heard + probe_every;
        let next_probe = self
            .last_probe
            .filter(|p| *p >= self.last_heard)
            .map_or(first_probe, |p| (p + probe_every).max(first_probe));
        Some(next_probe.min(self.last_heard + dead))
    }
}

/// How often a silent client is probed: four times within its dead time, at most every 10 s.
pub(super) fn probe_period(dead_time: Duration) -> Duration {
    (dead_time / 4).clamp(Duration::from_millis(25), Duration::from_secs(10))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(sequence: u16, write_index: u16) -> InputPosition {
        InputPosition {
            epoch: 7,
            stream_id: 0x80,
            sequence,
            write_index,
        }
    }

    /// Sequence numbers wrap: a floor from 0xFFFE up to message 1 covers 0xFFFE, 0xFFFF and
    /// 0 whole and message 1 up to its write, nothing before 0xFFFE or after; it ends with
    /// message 1 or one past it, not with those inside.
    #[test]
    fn a_floor_across_the_wrap_of_sequence_numbers() {
        let floor = ExecutedFloor {
            from: 0xFFFE,
            last: at(1, 2),
        };
        for covered in [at(0xFFFE, 9), at(0xFFFF, 0), at(0, 5), at(1, 0), at(1, 2)] {
            assert!(floor.covers(&covered), "{covered:?}");
        }
        for not in [at(0xFFFD, 0), at(1, 3), at(2, 0), at(0x8000, 0)] {
            assert!(!floor.covers(&not), "{not:?}");
        }
        let other_run = InputPosition {
            epoch: 8,
            ..at(0, 0)
        };
        assert!(!floor.covers(&other_run));
        let other_stream = InputPosition {
            stream_id: 0x81,
            ..at(0, 0)
        };
        assert!(!floor.covers(&other_stream));
        assert!(!floor.ends_with(0xFFFF) && !floor.ends_with(0));
        assert!(floor.ends_with(1) && floor.ends_with(2));
        assert!(floor.ends_with(0xFFFD), "behind it: skipped by a HEARTBEAT");
    }
}
