//! `xrce-agent --single-process`: the front-end and the DDS worker in one process, one
//! thread, under the supervisor.
//!
//! Between processes every sample costs two wake-ups (the worker's, then the front-end's for
//! the reply), which on a 2-core gateway is most of its CPU (BENCHMARKS.md, "What the
//! process hops cost"). Here the worker is the relay's link ([`WorkerInline`]): a request is
//! executed as the relay hands it over, and the event loop reads the worker's replies back
//! in the same pass ([`InProcessSide`], a [`WorkerSide`]).
//!
//! Executing at the hand-over keeps the order the session store relies on: a client message
//! is stored as taken only after the worker took its operations, so a crash between the two
//! makes the client send it again. (A write the worker holds for a new or re-created
//! writer's readers is taken but not yet published: a crash loses it, docs/operations.md.)
//!
//! What changes for the user is what one crash takes down: both halves. The supervisor
//! restarts the process, whose front-end takes its predecessor's sessions over from the
//! session store and replays their objects into its new worker, as after a worker crash; the
//! replay marks are files, so a client whose replay crashed the process is refused by the
//! next one instead of crashing it again. Unlike after a worker crash alone, the writes the
//! front-end kept for a resend (those DDS readers had not acknowledged) die with it: a
//! sample already handed to the network but lost there is not sent again, and one executed
//! but not yet stored as taken is executed again by the successor (at least once, as after a
//! worker crash).
//!
//! The hidden subcommand `single-process` is what the supervisor starts: the worker's
//! arguments, `--frontend`, then the front-end's.

use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant};

use mio::event::Event;
use mio::unix::SourceFd;
use mio::{Interest, Registry, Token};
use xrce_common::session::agent::{Agent, Endpoint};
use xrce_dds_worker::cli::WorkerArgs;
use xrce_dds_worker::worker::{InProcessLink, Worker};
use xrce_frontend::cli::FrontendArgs;
use xrce_frontend::relay::link::{Link, LinkError};
use xrce_frontend::relay::Relay;
use xrce_frontend::worker_side::WorkerSide;
use xrce_ipc::shm::IpcNode;
use xrce_ipc::status::Reporter;
use xrce_ipc::{Encode, RequestMessage};

/// Separates the worker's arguments from the front-end's on the subcommand's line.
pub const FRONTEND_SEPARATOR: &str = "--frontend";

/// Rounds of passes and replies in one delivery: a reply can make the relay send more (a
/// replay's next object, a read resumed), whose replies come with the next pass; what is
/// left after these goes in the next loop pass, after the clients' input had its turn.
const MAX_ROUNDS: usize = 8;
/// Longest a stopping process waits for DDS readers to acknowledge its writes (below the
/// supervisor's stop grace of 5 s).
const DRAIN_MAX: Duration = Duration::from_secs(3);
/// How often a draining process looks again.
const DRAIN_TICK: Duration = Duration::from_millis(20);

/// The arguments of `xrce-agent single-process`: the worker's, [`FRONTEND_SEPARATOR`], the
/// front-end's.
#[derive(Debug, clap::Args)]
pub struct SingleProcessArgs {
    /// The worker's arguments, `--frontend`, the front-end's.
    #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
    pub args: Vec<String>,
}

#[derive(Debug, clap::Parser)]
#[command(name = "dds-worker")]
struct WorkerLine {
    #[command(flatten)]
    args: WorkerArgs,
}

#[derive(Debug, clap::Parser)]
#[command(name = "frontend")]
struct FrontendLine {
    #[command(flatten)]
    args: FrontendArgs,
}

/// The command line the supervisor starts a single process with.
pub fn command_line(worker: &[String], frontend: &[String]) -> Vec<String> {
    std::iter::once("single-process".to_string())
        .chain(worker.iter().cloned())
        .chain(std::iter::once(FRONTEND_SEPARATOR.to_string()))
        .chain(frontend.iter().cloned())
        .collect()
}

/// Splits the subcommand's arguments into the worker's and the front-end's settings.
pub fn parse(args: &SingleProcessArgs) -> anyhow::Result<(WorkerArgs, FrontendArgs)> {
    let at = args
        .args
        .iter()
        .position(|a| a == FRONTEND_SEPARATOR)
        .ok_or_else(|| anyhow::anyhow!("single-process: {FRONTEND_SEPARATOR} is missing"))?;
    let (worker, frontend) = args.args.split_at(at);
    let worker = <WorkerLine as clap::Parser>::try_parse_from(
        std::iter::once("dds-worker").chain(worker.iter().map(String::as_str)),
    )?;
    let frontend = <FrontendLine as clap::Parser>::try_parse_from(
        std::iter::once("frontend").chain(frontend[1..].iter().map(String::as_str)),
    )?;
    Ok((worker.args, frontend.args))
}

/// Runs the front-end and the worker `args` name in this process until SIGINT/SIGTERM.
pub fn run(args: &SingleProcessArgs) -> anyhow::Result<()> {
    let (worker_args, frontend_args) = parse(args)?;
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_new(&frontend_args.log)
                .unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    xrce_common::fault::install_and_log("frontend")?;
    if worker_args.instance != frontend_args.instance {
        anyhow::bail!(
            "single-process: the worker's instance {:?} is not the front-end's {:?}",
            worker_args.instance,
            frontend_args.instance
        );
    }
    let (config, ros_distro) = xrce_dds_worker::cli::configure(worker_args)?;
    xrce_frontend::start::run_with(&frontend_args, move |args, _incarnation| {
        // The front-end's node: SIGINT/SIGTERM, and the refusal of a second process with
        // this front-end's id in the instance (it would take this one's clients).
        let node = IpcNode::new(
            &args.instance,
            &format!("xrce-frontend-{}", args.frontend_id),
        )?;
        if node.older_namesakes() > 0 {
            anyhow::bail!(
                "front-end {} already runs in agent instance {:?}; give each front-end its own id",
                args.frontend_id,
                args.instance
            );
        }
        let link = InProcessLink::new(&args.instance, args.frontend_id);
        let mut worker = xrce_dds_worker::process::start_worker(config, link)?;
        worker.set_ros_distro(ros_distro);
        Ok((
            WorkerInline {
                worker,
                encoded: Vec::new(),
            },
            InProcessSide {
                node,
                registered: Vec::new(),
                reporter: Reporter::new(&args.instance, "worker"),
            },
        ))
    })
}

/// The worker as the relay's link: each request is executed as it is sent.
pub struct WorkerInline {
    worker: Worker<InProcessLink>,
    /// The request being handed over, encoded (reused).
    encoded: Vec<u8>,
}

impl std::fmt::Debug for WorkerInline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorkerInline")
            .field("worker", &self.worker)
            .finish_non_exhaustive()
    }
}

impl Link for WorkerInline {
    fn send(&mut self, request: &RequestMessage<'_>) -> Result<(), LinkError> {
        // Through the IPC encoding, as between processes: the worker screens what it is
        // handed the same way whoever hands it.
        self.encoded.clear();
        self.encoded.resize(request.encoded_len(), 0);
        request.encode_into(&mut self.encoded);
        self.worker.handle_request(&self.encoded, Instant::now());
        Ok(())
    }

    fn wake(&mut self) -> Result<(), LinkError> {
        // The event loop delivers the replies in the same pass.
        Ok(())
    }
}

/// The worker inside the front-end's process, as its event loop sees it (the worker itself
/// is the relay's link, [`WorkerInline`]).
#[derive(Debug)]
pub struct InProcessSide {
    node: IpcNode,
    /// The DDS backends' readiness descriptors registered with the loop so far.
    registered: Vec<RawFd>,
    /// The worker's status report (`xrce-agent status`, metrics).
    reporter: Reporter,
}

impl WorkerSide for InProcessSide {
    type Link = WorkerInline;

    fn register(
        &mut self,
        registry: &Registry,
        (first, end): (Token, Token),
        relay: &Relay<WorkerInline>,
    ) -> std::io::Result<()> {
        // Made with the backends, which live as long as the worker: registered once each.
        // Edge-triggered (mio), where the worker's own process polls them level-triggered: a
        // pass that leaves readers with samples says so in its timeout (zero), and every
        // loop pass runs one.
        for fd in relay
            .link()
            .worker
            .readiness_fds()
            .iter()
            .map(AsRawFd::as_raw_fd)
        {
            if self.registered.contains(&fd) {
                continue;
            }
            let token = Token(first.0 + self.registered.len());
            if token.0 >= end.0 {
                return Err(std::io::Error::other(
                    "too many DDS descriptors for the worker's tokens",
                ));
            }
            registry.register(&mut SourceFd(&fd), token, Interest::READABLE)?;
            self.registered.push(fd);
        }
        Ok(())
    }

    fn on_event(&mut self, _event: &Event) {
        // Every delivery runs a pass of the worker, which asks the backends which readers
        // have samples.
    }

    fn on_idle(&mut self) {}

    fn termination_requested(&self) -> bool {
        self.node.termination_requested()
    }

    fn poll_timeout(&self, now: Instant, relay: &Relay<WorkerInline>) -> Option<Instant> {
        let worker = &relay.link().worker;
        if worker.link().has_messages() {
            return Some(now);
        }
        let due = worker.poll_timeout(now).map(|d| now + d);
        Some(due.map_or(self.reporter.due(), |t| t.min(self.reporter.due())))
    }

    fn deliver<A: Endpoint>(
        &mut self,
        now: Instant,
        relay: &mut Relay<WorkerInline>,
        agent: &mut Agent<A>,
    ) -> anyhow::Result<()> {
        for _ in 0..MAX_ROUNDS {
            let worker = &mut relay.link_mut().worker;
            worker.pass(now)?;
            let link = worker.link_mut();
            let announcements: Vec<Vec<u8>> = link.take_announcements().collect();
            let replies: Vec<Vec<u8>> = link.take_replies().collect();
            for a in &announcements {
                relay.handle_announcement(a);
            }
            for m in &replies {
                relay.handle_reply(now, m, agent);
            }
            // Every time, as between processes: it also settles kept writes by their age.
            relay.after_replies(now, agent);
            if announcements.is_empty() && replies.is_empty() {
                break;
            }
            if relay.take_generation_change() {
                agent.announce_streams(now);
            }
            relay.resume_reads(agent);
            relay.pump();
        }
        Ok(())
    }

    fn maintain(&mut self, now: Instant, relay: &Relay<WorkerInline>) {
        if now >= self.reporter.due() {
            let report = relay.link().worker.status_report();
            self.reporter.maybe_write(now, || report);
        }
    }

    fn stop(&mut self, relay: &mut Relay<WorkerInline>) {
        // What the relay handed over was taken by the worker as it went, and acknowledged to
        // its clients: held samples are released and everything given DDS's time to reach
        // its readers before the entities go with this process.
        let worker = &mut relay.link_mut().worker;
        worker.stop();
        let start = Instant::now();
        loop {
            if let Err(e) = worker.pass(Instant::now()) {
                tracing::warn!(error = %e, "the worker's last pass failed");
                break;
            }
            if worker.unacknowledged_writes() == 0 || start.elapsed() >= DRAIN_MAX {
                break;
            }
            std::thread::sleep(DRAIN_TICK);
        }
        tracing::info!(
            drained_ms = start.elapsed().as_millis() as u64,
            unacknowledged_writes = worker.unacknowledged_writes(),
            "stopping"
        );
        self.reporter.remove();
    }
}
