//! The worker's process around the sans-IO [`Worker`]: it opens the shared memory and the DDS
//! backend, waits on the front-ends' requests and the backends' readers, hands the worker
//! each request and a pass with the time, writes the status report, pings systemd's
//! watchdog, and drains on SIGINT or SIGTERM.

use std::time::{Duration, Instant};

use xrce_ipc::shm::Receiver;
use xrce_ipc::status::{Reporter, Watchdog, REPORT_PERIOD};

use crate::backend;
use crate::worker::{ShmWorkerLink, Worker, WorkerConfig, WorkerLink};

/// A pass longer than this is logged (front-ends' operations wait meanwhile, and a
/// front-end drops best-effort writes once its window to the worker is full).
const SLOW_PASS: Duration = Duration::from_millis(50);
/// At most one such line in this period (with the count of slow passes so far).
const SLOW_PASS_LOG_PERIOD: Duration = Duration::from_secs(10);
/// A stopping worker stops once no operation came for this long (and DDS readers have
/// acknowledged every write).
const DRAIN_QUIET: Duration = Duration::from_millis(100);
/// Longest a stopping worker drains (below the supervisor's stop grace of 5 s).
const DRAIN_MAX: Duration = Duration::from_secs(3);
/// How often a draining worker looks at the clock, at least (to stop on time).
const DRAIN_TICK_MS: i32 = 20;
/// A wait at least this long that ended with nothing ready consumes the requests' wake-ups
/// anyway ([`WorkerProcess::serve`]).
const IDLE_WAIT_MS: i32 = 10;

/// The worker's process: its worker, the requests' receiver, its status report.
pub struct WorkerProcess {
    worker: Worker<ShmWorkerLink>,
    requests: Receiver,
    /// Writes this process's status report.
    reporter: Reporter,
    /// Pings systemd's watchdog when the worker is a unit of its own.
    watchdog: Watchdog,
    /// Passes that took [`SLOW_PASS`] or longer, and when one was last logged.
    slow_passes: u64,
    slow_logged: Option<Instant>,
}

impl std::fmt::Debug for WorkerProcess {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerProcess")
            .field("worker", &self.worker)
            .finish()
    }
}

impl WorkerProcess {
    /// Makes the DDS backend `config.backend` names, opens the IPC services, and announces a
    /// new generation.
    pub fn start(config: WorkerConfig) -> anyhow::Result<Self> {
        let (link, requests) = ShmWorkerLink::open(&config.instance)?;
        let reporter = Reporter::new(&config.instance, "worker");
        let worker = start_worker(config, link)?;
        Ok(WorkerProcess {
            worker,
            requests,
            reporter,
            watchdog: Watchdog::from_env(),
            slow_passes: 0,
            slow_logged: None,
        })
    }

    /// The worker, to finish setting it up before [`WorkerProcess::run`].
    pub fn worker_mut(&mut self) -> &mut Worker<ShmWorkerLink> {
        &mut self.worker
    }

    /// Runs until SIGINT or SIGTERM, then drains: until the front-ends have been quiet for
    /// 100 ms and DDS readers acknowledged every write, 3 s at most.
    pub fn run(mut self) -> anyhow::Result<()> {
        let result = self.serve();
        // Replays that began during the drain (or before an error) did not crash it either.
        self.worker.stop();
        // The files of a front-end killed since the last census (once a second) would outlive
        // the agent: the census removes them now.
        let dead = self.worker.link().remove_dead();
        if !dead.is_empty() {
            tracing::debug!(?dead, "dead front-ends' shared-memory files removed");
        }
        self.reporter.remove();
        result
    }

    fn serve(&mut self) -> anyhow::Result<()> {
        // Since when the worker drains before it stops, and when it last took a request.
        let mut draining: Option<Instant> = None;
        let mut last_request = Instant::now();
        loop {
            let now = Instant::now();
            if let Some(since) = draining {
                // Stop once the front-ends have sent nothing for a moment (they stop with
                // it: a supervisor that stops or dies stops them all) and DDS readers have
                // acknowledged every write, or after DRAIN_MAX whatever is left.
                let quiet = now.saturating_duration_since(last_request) >= DRAIN_QUIET;
                let acknowledged = self.worker.unacknowledged_writes() == 0;
                let drained = now.saturating_duration_since(since);
                if (quiet && acknowledged) || drained >= DRAIN_MAX {
                    tracing::info!(
                        drained_ms = drained.as_millis() as u64,
                        unacknowledged_writes = self.worker.unacknowledged_writes(),
                        "stopping"
                    );
                    return Ok(());
                }
            } else if self.worker.link().termination_requested() {
                // Operations a front-end handed over were acknowledged to its clients: they
                // are executed, and their samples given DDS's time to reach its readers,
                // before the DDS entities go with this process.
                tracing::info!(
                    "termination requested; executing what the front-ends handed over first"
                );
                draining = Some(now);
                self.worker.stop();
            }
            if now >= self.reporter.due() {
                let report = self.worker.status_report();
                self.reporter.maybe_write(now, || report);
            }
            self.watchdog.maybe_ping(now);
            // At least once per report period: the report's age is the loop's heartbeat.
            // (The clock again: writing the report may have taken a while.)
            let period = REPORT_PERIOD.as_millis() as i32;
            let mut timeout = self
                .worker
                .poll_timeout(Instant::now())
                .map_or(period, |d| d.as_millis().min(period as u128) as i32);
            if draining.is_some() {
                timeout = timeout.min(DRAIN_TICK_MS);
            }
            let (requests_ready, anything_ready) = self.wait(timeout)?;
            // An idle wait that ended with nothing ready: a race inside iceoryx2 0.10 can
            // leave the listener marked notified with nothing to read (a notifier that slips
            // between the listener's reset and its second `recv`), after which no
            // notification would come again; consuming the wake-ups resets it. Only when
            // idle: that costs failed `recv`s.
            let idle = !anything_ready && timeout >= IDLE_WAIT_MS;
            let pass = Instant::now();
            // The queue is read every time; wake-ups are consumed only when there are some (a
            // system call each time, and the loop runs per sample under load).
            let worker = &mut self.worker;
            let mut taken = self
                .requests
                .drain(|m| worker.handle_request(m, Instant::now()))?;
            let after_requests = pass.elapsed();
            let mut pumped = self.worker.pass(Instant::now())?;
            if requests_ready || idle {
                // After the pass, not before the drain: by then the front-end that woke this
                // worker has finished notifying, and iceoryx2 takes its one datagram with one
                // `recv` (consumed at once, a second `recv` failed on most wake-ups: the
                // notifier had not yet marked its notification sent). Requests that came
                // after the drain notified nobody (folded into the notification consumed
                // here): taken now, with a pass of their own.
                self.requests.clear_events();
                let worker = &mut self.worker;
                let late = self
                    .requests
                    .drain(|m| worker.handle_request(m, Instant::now()))?;
                if late > 0 {
                    taken += late;
                    pumped += self.worker.pass(Instant::now())?;
                }
            }
            if taken > 0 {
                last_request = Instant::now();
            }
            self.log_if_slow(pass, after_requests, taken, pumped);
        }
    }

    /// Logs a pass that took [`SLOW_PASS`] or longer (one line per
    /// [`SLOW_PASS_LOG_PERIOD`]).
    fn log_if_slow(
        &mut self,
        pass: Instant,
        after_requests: Duration,
        taken: usize,
        pumped: usize,
    ) {
        let took = pass.elapsed();
        if took < SLOW_PASS {
            return;
        }
        self.slow_passes += 1;
        let now = Instant::now();
        if self
            .slow_logged
            .is_some_and(|t| now.saturating_duration_since(t) < SLOW_PASS_LOG_PERIOD)
        {
            return;
        }
        self.slow_logged = Some(now);
        tracing::warn!(
            took_ms = took.as_millis() as u64,
            slow_passes = self.slow_passes,
            requests_ms = after_requests.as_millis() as u64,
            pass_ms = took.saturating_sub(after_requests).as_millis() as u64,
            requests = taken,
            readers = pumped,
            "a worker loop pass took long; front-ends' operations waited meanwhile"
        );
    }

    /// Blocks until the front-ends' requests or a DDS backend's readers may have something,
    /// `timeout_ms` passes, or a signal arrives (then the caller checks for termination);
    /// whether the requests' descriptor polled readable, and whether any did.
    ///
    /// poll(2), level-triggered, not an edge-triggered poller as the front-end's: the
    /// backends' descriptors signal a condition (a Cyclone reader queue, a RustDDS poller)
    /// that each pass drains only up to a batch, and must wake the next wait as long as it
    /// holds.
    fn wait(&self, timeout_ms: i32) -> std::io::Result<(bool, bool)> {
        use nix::poll::{PollFd, PollFlags, PollTimeout};
        use std::os::fd::AsFd;
        let mut fds = vec![PollFd::new(self.requests.as_fd(), PollFlags::POLLIN)];
        fds.extend(
            self.worker
                .readiness_fds()
                .into_iter()
                .map(|fd| PollFd::new(fd, PollFlags::POLLIN)),
        );
        let timeout = PollTimeout::try_from(timeout_ms.max(0)).unwrap_or(PollTimeout::MAX);
        match nix::poll::poll(&mut fds, timeout) {
            Ok(n) => Ok((fds[0].revents().is_some_and(|r| !r.is_empty()), n > 0)),
            // Interrupted: the caller looks for termination (nothing consumed).
            Err(nix::errno::Errno::EINTR) => Ok((false, true)),
            Err(e) => Err(e.into()),
        }
    }
}

/// A new worker over `link`: makes the DDS backend `config.backend` names (and learns the
/// domains it cannot serve), and announces a new generation.
pub fn start_worker<L: WorkerLink>(mut config: WorkerConfig, link: L) -> anyhow::Result<Worker<L>> {
    let dds = backend::create(config.backend, &config.dds)?;
    config.domains.unservable = backend::unservable_domains(config.backend, &config.dds);
    Ok(Worker::new(
        config,
        dds,
        link,
        fresh_generation(),
        Instant::now(),
    )?)
}

/// A generation id for a new worker: odd (never 0, the "no worker" of a route), and unlike
/// its predecessor's (the clock's nanoseconds mixed with the process id).
fn fresh_generation() -> u32 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    (nanos ^ std::process::id().rotate_left(16)) | 1
}
