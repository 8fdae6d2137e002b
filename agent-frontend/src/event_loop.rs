//! The front-end's one event loop: a single thread blocked in epoll (through mio) on the
//! transport's sockets or devices, what its worker side waits on (the two IPC event
//! descriptors, or an in-process worker's DDS descriptors: [`crate::worker_side`]) and the
//! discovery socket, with the earliest timer as timeout. After each wake-up it drains what is
//! ready: client messages into the session core, the worker's replies, timers; then it hands
//! the core's transmits to the transport. No busy polling: idle, it sleeps.
//!
//! mio's readiness is edge-triggered: a source read only up to a batch limit stays marked
//! ready inside its transport, and the loop then polls without waiting.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use mio::{Events, Poll, Token};
use xrce_common::session::agent::{Agent, AgentConfig};

use xrce_ipc::status::{Reporter, Watchdog};

use crate::relay::Relay;
use crate::report::StatsReport;
use crate::session_store::SessionStore;
use crate::status::Identity;
use crate::transport::discovery::Discovery;
use crate::transport::Transport;
use crate::worker_side::WorkerSide;

/// A discovery request arrived.
const DISCOVERY: Token = Token(0);
/// The worker side's tokens start here (up to the transport's).
const WORKER_TOKENS: usize = 1;
/// The transport's tokens start here.
const TRANSPORT_TOKENS: usize = 16;
/// Messages handled per wake-up before IPC and timers get a turn.
const RECV_BATCH: usize = 256;
/// Longest sleep: a stop signal that lands just before the loop blocks is seen this late.
const MAX_SLEEP: Duration = Duration::from_secs(1);
/// A wait at least this long that ended with nothing ready is reported to the worker side
/// ([`WorkerSide::on_idle`]).
const IDLE_WAIT: Duration = Duration::from_millis(10);

/// Called once the front-end serves: its transport is registered and a worker answered.
pub type OnServing = Box<dyn FnOnce()>;

/// Where a front-end runs and what it keeps.
#[derive(Debug, Clone)]
pub struct Placement {
    /// The agent instance.
    pub instance: String,
    /// Store the sessions for a successor, and take a predecessor's over.
    pub keep_sessions: bool,
}

/// What a front-end serves with: the transport its clients reach it over, its link to the
/// worker (the relay, and the worker side that carries its requests and brings the replies),
/// the session core's settings, the discovery responder if any, and what to do once the
/// worker serves it.
pub struct Serving<T: Transport, W: WorkerSide> {
    /// Its clients' transport.
    pub transport: T,
    /// The relay to the worker.
    pub relay: Relay<W::Link>,
    /// The worker: its replies and announcements.
    pub worker: W,
    /// The session core's settings.
    pub config: AgentConfig,
    /// Answers multicast discovery, if asked to.
    pub discovery: Option<Discovery>,
    /// Called once, when a worker first serves this front-end.
    pub on_serving: Option<OnServing>,
}

impl<T: Transport, W: WorkerSide> std::fmt::Debug for Serving<T, W> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Serving")
            .field("transport", &self.transport.name())
            .field("discovery", &self.discovery.is_some())
            .finish_non_exhaustive()
    }
}

/// Runs front-end `who` of `place` with `serving` until SIGINT/SIGTERM.
pub fn run<T: Transport, W: WorkerSide>(
    place: &Placement,
    who: Identity,
    mut serving: Serving<T, W>,
) -> anyhow::Result<()> {
    // Every line this front-end logs names it (a gateway's front-ends share one log).
    let _span = tracing::info_span!("frontend", name = %who.name).entered();
    let instance = place.instance.as_str();
    let mut reporter = Reporter::new(instance, &format!("frontend-{}", who.id));
    let mut watchdog = Watchdog::from_env();
    // Refused, not worked around: a store another front-end holds, or a directory someone
    // else planted or loosened, must not be used, and running without one would lose the
    // sessions at the next restart without anyone having asked for that.
    let mut store = if place.keep_sessions {
        match SessionStore::open(instance, who.id) {
            Ok(s) => Some(s),
            Err(e) => {
                reporter.remove();
                anyhow::bail!(
                    "the session store of front-end {}: {e} (or run with --keep-sessions false)",
                    who.id
                );
            }
        }
    } else {
        None
    };
    serving.config.track_sessions = store.is_some();
    serving.relay.set_hand_over_at_once(store.is_some());
    // Who started this process: it is gone when it died (its death is what asks this one to
    // stop, PR_SET_PDEATHSIG), not when it stops the agent on purpose.
    let supervisor = nix::unistd::getppid();
    let result = serve(&who, &mut reporter, &mut watchdog, &mut store, &mut serving);
    // What the worker side must finish (an in-process worker's DDS writes), whatever ended
    // the loop.
    serving.worker.stop(&mut serving.relay);
    if result.is_ok() {
        // The transport is still open here (and this process's report still says it runs,
        // so that a successor waits for it).
        hold_for_successor(instance, supervisor);
    }
    reporter.remove();
    result
}

fn serve<T: Transport, W: WorkerSide>(
    who: &Identity,
    reporter: &mut Reporter,
    watchdog: &mut Watchdog,
    store: &mut Option<SessionStore>,
    serving: &mut Serving<T, W>,
) -> anyhow::Result<()> {
    let Serving {
        transport,
        relay,
        worker,
        config,
        discovery,
        on_serving,
    } = serving;
    config.max_message_size = transport.max_message_size();
    let mut poll = Poll::new()?;
    let worker_tokens = (Token(WORKER_TOKENS), Token(TRANSPORT_TOKENS));
    worker.register(poll.registry(), worker_tokens, relay)?;
    if let Some(d) = discovery.as_mut() {
        d.register(poll.registry(), DISCOVERY)?;
    }
    transport.register(poll.registry(), TRANSPORT_TOKENS)?;
    let name = transport.name();
    let mut agent: Agent<T::Endpoint> = Agent::new(config.clone());
    let mut events = Events::with_capacity(1024);
    let mut report = StatsReport::new(Instant::now());
    let mut input_left = true;
    let mut discovery_left = true;
    let mut output_stored = Instant::now();
    if let Some(s) = store.as_mut() {
        let taken = crate::takeover::take_over(s, Instant::now(), &mut agent, relay, &*transport);
        if taken > 0 {
            tracing::info!(
                sessions = taken,
                "sessions taken over from the previous front-end"
            );
        }
    }
    // Pick up a worker that announced itself before we started.
    worker.on_idle();
    worker.deliver(Instant::now(), relay, &mut agent)?;
    relay.pump();
    loop {
        if worker.termination_requested() {
            tracing::info!(transport = name, "termination requested");
            return Ok(());
        }
        if relay.generation().is_some() {
            if let Some(f) = on_serving.take() {
                f();
            }
        }
        let now = Instant::now();
        let timeout = if input_left || discovery_left {
            Duration::ZERO
        } else {
            [
                agent.poll_timeout(),
                relay.poll_timeout(now),
                transport.poll_timeout(),
                report.due(&agent, relay, transport.stats()),
                Some(reporter.due()),
                watchdog.due(),
                worker.poll_timeout(now, relay),
            ]
            .into_iter()
            .flatten()
            .min()
            // mio rounds the timeout up to whole milliseconds, so no early wake-up spins.
            .map_or(MAX_SLEEP, |d| {
                d.saturating_duration_since(now).min(MAX_SLEEP)
            })
        };
        match poll.poll(&mut events, Some(timeout)) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e.into()),
        }
        // Only after an idle wait: what the side does then (consuming wake-ups it may have
        // missed) costs system calls.
        if events.is_empty() && timeout >= IDLE_WAIT {
            worker.on_idle();
        }
        for event in events.iter() {
            match event.token() {
                DISCOVERY => {
                    if let Some(d) = discovery.as_mut() {
                        d.on_event(event);
                    }
                }
                t if t.0 < TRANSPORT_TOKENS => worker.on_event(event),
                _ => transport.on_event(event),
            }
        }
        let now = Instant::now();
        if let Ok(d) = SystemTime::now().duration_since(UNIX_EPOCH) {
            agent.set_wall_clock(now, d);
        }
        input_left = transport.receive(now, RECV_BATCH, &mut |from, bytes| {
            agent.handle_datagram(now, from, bytes, relay);
            if let Some(s) = store.as_mut() {
                crate::takeover::persist(s, &mut agent, relay, false);
            }
        });
        while let Some(closed) = transport.poll_closed() {
            agent.endpoint_closed(Instant::now(), closed);
        }
        while let Some(gone) = transport.poll_unreachable() {
            agent.endpoint_unreachable(now, gone, relay);
        }
        discovery_left = discovery.as_mut().is_some_and(Discovery::answer_pending);
        relay.apply_replies(now, &mut agent);
        worker.deliver(now, relay, &mut agent)?;
        if relay.take_generation_change() {
            agent.announce_streams(now);
        }
        relay.resume_reads(&agent);
        if transport.poll_timeout().is_some_and(|t| t <= now) {
            transport.handle_timeout(now);
            // A timer may have made input ready (a device reopened, accepting resumed).
            input_left = true;
        }
        agent.handle_timeout(now, relay);
        // After the timers: what they hand over (a dead client's deletion) goes out now.
        relay.pump();
        report.maybe_log(now, &agent, relay, name, transport.stats());
        reporter.maybe_write(now, || {
            crate::status::report(who, now, &*transport, &agent, relay)
        });
        watchdog.maybe_ping(now);
        match store.as_mut() {
            // Before anything goes out: a successor never finds the streams behind what
            // the clients saw.
            Some(s) => {
                let with_output = now >= output_stored + crate::takeover::OUTPUT_STORE_PERIOD;
                if with_output {
                    output_stored = now;
                }
                crate::takeover::persist(s, &mut agent, relay, with_output);
                s.keep_alive(now);
            }
            None => {
                let _ = (relay.take_objects_changed(), relay.take_reads_changed());
            }
        }
        while let Some(t) = agent.poll_transmit() {
            transport.send(t.destination, &t.data);
        }
        worker.maintain(now, relay);
        worker.register(poll.registry(), worker_tokens, relay)?;
    }
}

/// Longest a front-end whose supervisor died holds its transport for a successor.
const SUCCESSOR_HOLD: Duration = Duration::from_secs(2);

/// How many times (5 ms apart) a stopping front-end looks whether its supervisor is gone.
const PARENT_LOOKS: u32 = 20;

/// After the supervisor died (not after a stop it asked for): keeps the transport open,
/// reading nothing, until a new supervisor of the instance waits for this process to stop
/// ([`xrce_ipc::runtime_dir::successor_waiting`]) or [`SUCCESSOR_HOLD`] passed. Its clients'
/// datagrams meanwhile land in a socket that is still there instead of drawing ICMP port
/// unreachable errors: eProsima's client counts each such error as a wait of its own, so a
/// sample written just before the crash would run out of its confirmation window before
/// the restarted agent could answer (clients resend what was not acknowledged). The
/// session store is already final: nothing is taken meanwhile.
fn hold_for_successor(instance: &str, supervisor: nix::unistd::Pid) {
    // The death signal comes when the thread that started this process ends, which may be a
    // moment before its whole process is gone and this one handed to another parent: look
    // for a short while (a supervisor that stops the agent on purpose stays, and the stop
    // costs this wait).
    let gone = || {
        nix::unistd::getppid() != supervisor
            || !xrce_ipc::status::is_alive(supervisor.as_raw().unsigned_abs())
    };
    let mut looked = 0;
    while !gone() {
        if looked == PARENT_LOOKS {
            return;
        }
        looked += 1;
        std::thread::sleep(Duration::from_millis(5));
    }
    tracing::info!(
        "the supervisor is gone: the clients' port is held until its successor starts (at most {} s)",
        SUCCESSOR_HOLD.as_secs()
    );
    let end = Instant::now() + SUCCESSOR_HOLD;
    while Instant::now() < end {
        if xrce_ipc::runtime_dir::successor_waiting(instance) {
            tracing::info!("a successor waits: letting the port go");
            return;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}
