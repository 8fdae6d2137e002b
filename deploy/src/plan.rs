//! What an agent is to run: the one value both front doors produce. A MicroXRCEAgent command
//! line ([`AgentPlan::from_command_line`]) and a gateway file ([`AgentPlan::from_gateway`])
//! each become an [`AgentPlan`]; [`crate::group::Group::new`] checks it ([`AgentPlan::check`])
//! and starts it. A setting the file leaves out takes what the command line's option would
//! take when left out: its environment variable, else its default (both read through the
//! command line's own parser, [`Common::from_environment`]), so a setting means the same
//! either way.
//!
//! The bounds of every setting are in [`crate::settings`], once: the command line's parsers
//! and the gateway parser call them (the latter to name the key and line),
//! [`AgentPlan::check`] for everything else.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;

use xrce_dds_worker::backend::BackendKind;
use xrce_dds_worker::domains::DomainSet;
use xrce_dds_worker::ros_graph::RosDistro;
use xrce_frontend::cli::{AdmissionArgs, FrontendArgs};

use crate::cli::{Common, FrontendPlan};
use crate::gateway::Gateway;
use crate::settings::{
    check_client_dead_time, check_frontend_grace, check_instance, check_max_domains,
    check_memory_limit_mib, check_processes, check_verbose, parse_domains,
};

/// Why a plan is refused: the setting (as the command line names it) and what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{setting} {problem}")]
pub struct PlanError {
    /// The setting, as its command-line option (`--client-dead-time`).
    pub setting: &'static str,
    /// What is wrong with its value.
    pub problem: String,
}

/// The agent as a whole: its instance, logging, processes' limits, metrics, worker and
/// front-ends.
#[derive(Debug, Clone, PartialEq)]
pub struct AgentPlan {
    /// Shared-memory name of the instance given by the user (`--instance`,
    /// `agent.instance`); `None`: [`Self::derived_instance`].
    pub instance: Option<String>,
    /// The name derived from what the agent serves (its transport and address, or the
    /// gateway file's path) and the network namespace: a restarted agent finds its
    /// predecessor's sessions, and two agents never share one by accident.
    pub derived_instance: String,
    /// Prefix of derived instance names (`udp4-8888-`, `gw-`): leftovers of dead agents
    /// with the same stem are removed at start.
    pub stem: String,
    /// Log verbosity 0..6 (`-v`, `agent.verbose`); `None`: XRCE_LOG, else info.
    pub verbose: Option<u8>,
    /// Private resident memory (MiB) beyond which a process is restarted.
    pub memory_limit_mib: Option<u64>,
    /// Start without the sessions a previous agent of the instance stored.
    pub discard_sessions: bool,
    /// The front-end and the worker in one process (one front-end only).
    pub single_process: bool,
    /// Where the metrics endpoint is served, if anywhere.
    pub metrics: Option<SocketAddr>,
    /// The DDS worker.
    pub worker: WorkerPlan,
    /// The front-ends, in order (ids unique).
    pub frontends: Vec<FrontendSpec>,
}

/// The DDS worker's settings as the user gave them (the environment's where not).
#[derive(Debug, Clone, PartialEq)]
pub struct WorkerPlan {
    /// References file (Fast DDS XML profiles).
    pub refs: Option<PathBuf>,
    /// Local addresses DDS is restricted to (empty: every interface).
    pub dds_interfaces: Vec<IpAddr>,
    /// Announce micro-ROS nodes in the ROS graph.
    pub ros_graph: bool,
    /// Map many clients' writers onto shared DDS writers.
    pub share_writers: bool,
    /// The worker's backend, from the middleware and the DDS backend named together
    /// ([`crate::cli::backend_for`]); `None`: the worker's default.
    pub backend: Option<BackendKind>,
    /// Where rmw_zenoh's type hashes are looked up (absolute paths).
    pub zenoh_type_hashes: Vec<PathBuf>,
    /// Seconds a gone front-end's entities are kept for it; `None`: the worker's default.
    pub frontend_grace: Option<f64>,
    /// The ROS 2 distribution of the graph's layout; `None`: ROS_DISTRO, else jazzy.
    pub ros_distro: Option<RosDistro>,
    /// Domain ids clients may use; `None`: any.
    pub domains: Option<DomainSet>,
    /// Most distinct domains in use at once; `None`: the worker's default.
    pub max_domains: Option<u16>,
    /// What clients may make the worker hold (each unset: the worker's default).
    pub bounds: xrce_dds_worker::cli::BoundsArgs,
}

/// One front-end: what it serves and its settings.
#[derive(Debug, Clone, PartialEq)]
pub struct FrontendSpec {
    /// Unique name (for logs, readiness and `--process`).
    pub name: String,
    /// Unique front-end id (the worker keys its entities by it).
    pub id: u32,
    /// What it serves.
    pub plan: FrontendPlan,
    /// Answer multicast discovery on this port (UDP and TCP; on another transport, a
    /// command line's `-d` is warned about and ignored, as MicroXRCEAgent ignores it).
    pub discovery: Option<u16>,
    /// Seconds of silence before a client's session is deleted (0 = never).
    pub client_dead_time: f64,
    /// Forced protocol dialect.
    pub dialect: Option<xrce_common::wire::Dialect>,
    /// Allow-list, roaming and quotas of its clients.
    pub admission: AdmissionArgs,
}

/// Id step between the processes of one front-end (`processes`): the first keeps the
/// front-end's id, the `k`th (counted from 0) has that id plus `k` times this.
pub const PROCESS_ID_STEP: u32 = 1 << 20;

impl FrontendSpec {
    /// How many processes serve it (a UDP front-end's `processes`; 1 otherwise).
    pub fn processes(&self) -> u16 {
        match self.plan {
            FrontendPlan::Ip { processes, .. } => processes,
            _ => 1,
        }
    }

    /// The id and name of its `k`th process (from 0): the first has the front-end's own,
    /// the others the id [`PROCESS_ID_STEP`] apart and the name with `-2`, `-3`...; `None`
    /// where the id would pass `u32::MAX`.
    pub fn process(&self, k: u16) -> Option<(u32, String)> {
        let id = self
            .id
            .checked_add(u32::from(k).checked_mul(PROCESS_ID_STEP)?)?;
        let name = if k == 0 {
            self.name.clone()
        } else {
            format!("{}-{}", self.name, k + 1)
        };
        Some((id, name))
    }

    /// The front-end process's settings: the environment's front-end settings with this
    /// front-end's own on top (its instance and log filter are the supervisor's to set).
    pub fn settings(&self) -> FrontendArgs {
        let mut s = FrontendArgs::defaults();
        s.frontend_id = self.id;
        s.name = Some(self.name.clone());
        self.plan.apply_to(&mut s);
        s.discovery = self.discovery;
        s.client_dead_time = self.client_dead_time;
        s.dialect = self.dialect;
        s.admission = self.admission.clone();
        s
    }
}

fn refused(setting: &'static str) -> impl Fn(String) -> PlanError {
    move |problem| PlanError { setting, problem }
}

/// Paths made absolute against the current directory (the worker may run elsewhere).
fn absolute_paths(paths: &[PathBuf]) -> Vec<PathBuf> {
    paths
        .iter()
        .map(|p| std::path::absolute(p).unwrap_or_else(|_| p.clone()))
        .collect()
}

impl AgentPlan {
    /// One front-end, from a MicroXRCEAgent command line.
    pub fn from_command_line(frontend: FrontendPlan, common: &Common) -> anyhow::Result<Self> {
        let backend = crate::cli::backend_for(&common.middleware, common.dds_backend)?;
        Ok(AgentPlan {
            instance: common.instance.clone(),
            derived_instance: xrce_ipc::derived_instance(&frontend.label(), &frontend.identity()),
            stem: format!("{}-", frontend.label()),
            verbose: common.verbose,
            memory_limit_mib: common.memory_limit,
            discard_sessions: common.discard_sessions,
            single_process: common.single_process,
            metrics: common.metrics,
            worker: WorkerPlan {
                refs: common.refs.clone(),
                dds_interfaces: common.dds_interfaces.clone(),
                ros_graph: common.ros_graph,
                share_writers: common.share_writers,
                backend,
                zenoh_type_hashes: absolute_paths(&common.zenoh_type_hashes),
                frontend_grace: common.frontend_grace,
                ros_distro: common.ros_distro,
                domains: common
                    .domains
                    .as_deref()
                    .map(parse_domains)
                    .transpose()
                    .map_err(refused("--domains (or XRCE_DOMAINS)"))?,
                max_domains: common.max_domains,
                bounds: common.bounds.clone(),
            },
            frontends: vec![FrontendSpec {
                name: frontend.label(),
                id: 0,
                discovery: common.discovery,
                client_dead_time: common.client_dead_time,
                dialect: common.dialect,
                admission: common.admission.clone(),
                plan: frontend,
            }],
        })
    }

    /// Every front-end of a checked gateway file; what the file leaves out is taken as a
    /// command line would take it ([`Common::from_environment`]).
    pub fn from_gateway(g: &Gateway) -> anyhow::Result<Self> {
        let env = Common::from_environment()?;
        let w = &g.worker;
        let backend = crate::cli::backend_for(
            w.middleware.as_deref().unwrap_or(&env.middleware),
            w.dds_backend.or(env.dds_backend),
        )
        .map_err(|e| anyhow::anyhow!("[worker] {e}"))?;
        let file = std::fs::canonicalize(&g.path).unwrap_or_else(|_| g.path.clone());
        let zenoh_type_hashes = if w.zenoh_type_hashes.is_empty() {
            env.zenoh_type_hashes.clone()
        } else {
            w.zenoh_type_hashes.clone()
        };
        Ok(AgentPlan {
            instance: g.agent.instance.clone().or(env.instance.clone()),
            derived_instance: xrce_ipc::derived_instance("gw", &file.display().to_string()),
            stem: "gw-".to_string(),
            verbose: g
                .agent
                .verbose
                .as_ref()
                .map(|v| *v.get_ref())
                .or(env.verbose),
            memory_limit_mib: g
                .agent
                .memory_limit_mib
                .as_ref()
                .map(|m| *m.get_ref())
                .or(env.memory_limit),
            discard_sessions: g.agent.discard_sessions.unwrap_or(env.discard_sessions),
            single_process: g.agent.single_process.unwrap_or(env.single_process),
            metrics: g.metrics.or(env.metrics),
            worker: WorkerPlan {
                refs: w.refs.as_ref().map(|r| r.get_ref().clone()).or(env.refs),
                dds_interfaces: if w.dds_interfaces.is_empty() {
                    env.dds_interfaces.clone()
                } else {
                    w.dds_interfaces.clone()
                },
                ros_graph: w.ros_graph.unwrap_or(env.ros_graph),
                share_writers: w.share_writers.unwrap_or(env.share_writers),
                backend,
                zenoh_type_hashes: absolute_paths(&zenoh_type_hashes),
                frontend_grace: w.frontend_grace.or(env.frontend_grace),
                ros_distro: match &w.ros_distro {
                    Some(d) => Some(
                        d.parse::<RosDistro>()
                            .map_err(|e| anyhow::anyhow!("[worker] ros_distro: {e}"))?,
                    ),
                    None => env.ros_distro,
                },
                domains: w
                    .domains
                    .as_deref()
                    .or(env.domains.as_deref())
                    .map(parse_domains)
                    .transpose()
                    // The file's own list was checked with its line: this one is the
                    // environment's.
                    .map_err(refused("XRCE_DOMAINS"))?,
                max_domains: w.max_domains.or(env.max_domains),
                bounds: w.bounds().or(&env.bounds),
            },
            frontends: g
                .frontends
                .iter()
                .map(|f| FrontendSpec {
                    name: f.name.clone(),
                    id: f.id,
                    plan: f.plan.clone(),
                    discovery: f.discovery,
                    client_dead_time: f.client_dead_time.unwrap_or(env.client_dead_time),
                    dialect: f.dialect.or(env.dialect),
                    admission: f.admission.clone(),
                })
                .collect(),
        })
    }

    /// The instance's shared-memory name: the given one, else the derived one.
    pub fn instance(&self) -> &str {
        self.instance.as_deref().unwrap_or(&self.derived_instance)
    }

    /// Every setting within its bounds: the one check, whichever front door the plan came
    /// through.
    pub fn check(&self) -> Result<(), PlanError> {
        check_instance(self.instance()).map_err(refused("--instance (or XRCE_INSTANCE)"))?;
        if let Some(v) = self.verbose {
            check_verbose(v).map_err(refused("--verbose"))?;
        }
        if let Some(m) = self.memory_limit_mib {
            check_memory_limit_mib(m).map_err(refused("--memory-limit (or XRCE_MEMORY_LIMIT)"))?;
        }
        if let Some(g) = self.worker.frontend_grace {
            check_frontend_grace(g)
                .map_err(refused("--frontend-grace (or XRCE_FRONTEND_GRACE)"))?;
        }
        if let Some(n) = self.worker.max_domains {
            check_max_domains(n).map_err(refused("--max-domains (or XRCE_MAX_DOMAINS)"))?;
        }
        if self.frontends.is_empty() {
            return Err(PlanError {
                setting: "--config",
                problem: "names no front-end".into(),
            });
        }
        let processes: usize = self
            .frontends
            .iter()
            .map(|f| usize::from(f.processes()))
            .sum();
        if self.single_process && processes > 1 {
            return Err(PlanError {
                setting: "--single-process (or single_process)",
                problem: format!(
                    "runs one front-end process with its worker; this agent has {processes}"
                ),
            });
        }
        let mut ids = std::collections::HashSet::new();
        let mut names = std::collections::HashSet::new();
        for f in &self.frontends {
            check_client_dead_time(f.client_dead_time)
                .map_err(refused("--client-dead-time (or XRCE_CLIENT_DEAD_TIME)"))?;
            check_processes(f.processes()).map_err(refused("--processes (or processes)"))?;
            if let FrontendPlan::Ip { listen, .. } = &f.plan {
                if f.processes() > 1 && listen.port() == 0 {
                    return Err(PlanError {
                        setting: "--processes (or processes)",
                        problem: "needs a port (not 0: each process's socket would get \
                                  a port of its own)"
                            .into(),
                    });
                }
            }
            for k in 0..f.processes() {
                let (id, name) = f.process(k).ok_or_else(|| PlanError {
                    setting: "--processes (or processes)",
                    problem: format!(
                        "gives front-end {} {} processes: their ids would pass {}",
                        f.name,
                        f.processes(),
                        u32::MAX
                    ),
                })?;
                if !ids.insert(id) {
                    return Err(PlanError {
                        setting: "--config",
                        problem: format!("front-end id {id} is used twice"),
                    });
                }
                if !names.insert(name.clone()) {
                    return Err(PlanError {
                        setting: "--config",
                        problem: format!("front-end name {name} is used twice"),
                    });
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::group::Group;
    use clap::Parser;

    fn from_command_line(args: &str) -> anyhow::Result<Group> {
        let cli = crate::cli::Cli::try_parse_from(
            ["xrce-agent", "udp4", "-p", "8888", "--instance", "same"]
                .into_iter()
                .chain(args.split_whitespace()),
        )?;
        let command = cli.command.expect("a transport");
        let (frontend, common) = crate::cli::plan(&command)?.expect("a front-end");
        Group::new(AgentPlan::from_command_line(frontend, &common)?)
    }

    fn from_file(agent: &str, worker: &str, frontend: &str) -> anyhow::Result<Group> {
        let text = format!(
            "[agent]\ninstance = \"same\"\n{agent}\n[worker]\n{worker}\n\
             [[frontend]]\nname = \"udp4-8888\"\ntransport = \"udp4\"\nport = 8888\n{frontend}\n"
        );
        let g = crate::gateway::parse(std::path::Path::new("/etc/xrce-agent/gw.toml"), &text)?;
        Group::new(AgentPlan::from_gateway(&g)?)
    }

    /// What a process is started with: its settings as arguments, and the group's own.
    fn started_with(g: &Group) -> String {
        format!(
            "worker {:?}\nfront-ends {:?}\nmemory {:?} discard {} single {} metrics {:?} named {} {}",
            g.worker.to_args(),
            g.frontends
                .iter()
                .map(|f| (f.name.clone(), f.id, f.share, f.settings.to_args()))
                .collect::<Vec<_>>(),
            g.memory_limit,
            g.discard_sessions,
            g.single_process,
            g.metrics,
            g.instance,
            g.explicit_instance,
        )
    }

    /// Each setting, given as an option and as a key of a gateway file, starts the same
    /// processes with the same settings; and so does leaving every one out.
    #[test]
    fn every_setting_means_the_same_from_the_command_line_and_from_a_file() {
        // (option, [agent] or [metrics], [worker], [[frontend]])
        let cases: &[(&str, &str, &str, &str)] = &[
            ("", "", "", ""),
            ("-v 6", "verbose = 6", "", ""),
            ("--memory-limit 512", "memory_limit_mib = 512", "", ""),
            ("--discard-sessions", "discard_sessions = true", "", ""),
            ("--single-process", "single_process = true", "", ""),
            (
                "--metrics 127.0.0.1:9464",
                "[metrics]\nlisten = \"127.0.0.1:9464\"",
                "",
                "",
            ),
            (
                "--dds-interface 127.0.0.1",
                "",
                "dds_interfaces = [\"127.0.0.1\"]",
                "",
            ),
            ("--ros-graph false", "", "ros_graph = false", ""),
            ("--share-writers true", "", "share_writers = true", ""),
            ("--ros-distro humble", "", "ros_distro = \"humble\"", ""),
            (
                "--domains 0-10,42 --max-domains 4",
                "",
                "domains = \"0-10,42\"\nmax_domains = 4",
                "",
            ),
            ("--dds-backend rustdds", "", "dds_backend = \"rustdds\"", ""),
            ("-m zenoh", "", "middleware = \"zenoh\"", ""),
            (
                "--zenoh-type-hashes /opt/ros/jazzy",
                "",
                "zenoh_type_hashes = [\"/opt/ros/jazzy\"]",
                "",
            ),
            ("--frontend-grace 2.5", "", "frontend_grace = 2.5", ""),
            ("--client-dead-time 30", "", "", "client_dead_time = 30.0"),
            ("--dialect spec", "", "", "dialect = \"spec\""),
            ("-d 7400", "", "", "discovery = 7400"),
            (
                "--allow-keys 0xAAAABBBB,dead0001",
                "",
                "",
                "allow_keys = [\"0xAAAABBBB\", \"dead0001\"]",
            ),
            ("--allow-roaming", "", "", "allow_roaming = true"),
            (
                "--max-objects-per-client 64",
                "",
                "",
                "max_objects_per_client = 64",
            ),
            (
                "--max-client-messages-per-second 500",
                "",
                "",
                "max_client_messages_per_second = 500",
            ),
            (
                "--max-client-bytes-per-second 100000",
                "",
                "",
                "max_client_bytes_per_second = 100000",
            ),
            ("--memory-budget 32", "", "", "memory_budget_mib = 32"),
            ("--processes 3", "", "", "processes = 3"),
            ("--max-sessions 100", "", "", "max_sessions = 100"),
            (
                "--max-sessions-per-address 10",
                "",
                "",
                "max_sessions_per_address = 10",
            ),
            (
                "--new-sessions-per-second 5",
                "",
                "",
                "new_sessions_per_second = 5",
            ),
        ];
        let plain = started_with(&from_command_line("").expect("plain"));
        for (option, agent, worker, frontend) in cases {
            let cli = started_with(
                &from_command_line(option).unwrap_or_else(|e| panic!("{option}: {e:#}")),
            );
            let file = started_with(
                &from_file(agent, worker, frontend).unwrap_or_else(|e| panic!("{option}: {e:#}")),
            );
            assert_eq!(cli, file, "{option}");
            if !option.is_empty() {
                assert_ne!(cli, plain, "{option} changes nothing");
            }
        }
    }

    /// A UDP port of several processes: one launch each, ids a step apart, the first with
    /// the front-end's own id and name and the only one answering discovery; `auto` is
    /// the count from the cores through either door; refused with one process alone.
    #[test]
    fn a_port_of_several_processes_is_one_launch_per_process() {
        let g = from_file("", "", "processes = 3\ndiscovery = 7400\nid = 5").expect("file");
        let launched: Vec<_> = g
            .frontends
            .iter()
            .map(|f| {
                (
                    f.name.as_str(),
                    f.id,
                    f.share.map(|s| (s.member, s.members)),
                )
            })
            .collect();
        assert_eq!(
            launched,
            vec![
                ("udp4-8888", 5, Some((0, 3))),
                ("udp4-8888-2", 5 + PROCESS_ID_STEP, Some((1, 3))),
                ("udp4-8888-3", 5 + 2 * PROCESS_ID_STEP, Some((2, 3))),
            ]
        );
        let discovery: Vec<_> = g.frontends.iter().map(|f| f.settings.discovery).collect();
        assert_eq!(discovery, vec![Some(7400), None, None]);
        for f in &g.frontends {
            assert_eq!(f.settings.frontend_id, f.id);
            assert_eq!(f.settings.name.as_deref(), Some(f.name.as_str()));
        }
        let auto = crate::settings::auto_processes();
        for g in [
            from_command_line("--processes auto").expect("auto"),
            from_file("", "", "processes = \"auto\"").expect("auto"),
        ] {
            assert_eq!(g.frontends.len(), usize::from(auto));
        }
        let e = from_command_line("--processes 2 --single-process").expect_err("single");
        assert!(format!("{e:#}").contains("one front-end process"), "{e:#}");
        // Port 0: each socket would get a port of its own.
        let cli =
            crate::cli::Cli::try_parse_from(["xrce-agent", "udp4", "-p", "0", "--processes", "2"])
                .expect("parses");
        let (frontend, common) = crate::cli::plan(&cli.command.expect("a transport"))
            .expect("plan")
            .expect("a front-end");
        let e = Group::new(AgentPlan::from_command_line(frontend, &common).expect("plan"))
            .expect_err("port 0");
        assert!(format!("{e:#}").contains("needs a port"), "{e:#}");
        // Ids a step apart that pass u32::MAX.
        let e = from_file("", "", "processes = 2\nid = 4294967295").expect_err("overflow");
        assert!(format!("{e:#}").contains("would pass"), "{e:#}");
    }

    /// A value out of bounds is refused the same way through either door.
    #[test]
    fn each_bound_is_the_same_through_either_door() {
        let cases: &[(&str, &str, &str, &str, &str)] = &[
            (
                "--frontend-grace 100000",
                "",
                "frontend_grace = 100000.0",
                "",
                "must be 0 to 86400 seconds",
            ),
            (
                "--frontend-grace=-1",
                "",
                "frontend_grace = -1.0",
                "",
                "must be 0 to 86400 seconds",
            ),
            (
                "--client-dead-time 40000000",
                "",
                "",
                "client_dead_time = 40000000.0",
                "must be 0 to 31536000 seconds",
            ),
            ("--max-domains 234", "", "max_domains = 234", "", "1 to 233"),
            ("--domains 0-300", "", "domains = \"0-300\"", "", "0-300"),
            (
                "--memory-limit 0",
                "memory_limit_mib = 0",
                "",
                "",
                "1 to 1048576",
            ),
            ("-v 7", "verbose = 7", "", "", "0 to 6"),
            (
                "--processes 65",
                "",
                "",
                "processes = 65",
                "must be 1 to 64",
            ),
            ("--processes 0", "", "", "processes = 0", "must be 1 to 64"),
            ("--max-entities 0", "", "max_entities = 0", "", "at least 1"),
        ];
        for (option, agent, worker, frontend, words) in cases {
            let cli = from_command_line(option).map(|_| ()).expect_err(option);
            let file = from_file(agent, worker, frontend)
                .map(|_| ())
                .expect_err(option);
            for e in [&cli, &file] {
                assert!(format!("{e:#}").contains(words), "{option}: {e:#}");
            }
        }
        assert!(PlanError::to_string(&PlanError {
            setting: "--instance",
            problem: check_instance("no/slash").expect_err("refused"),
        })
        .contains("[A-Za-z0-9_-]"));
    }

    /// One process holds one front-end and the worker: a gateway of two front-ends in one
    /// process is refused, saying why; with one front-end the supervisor runs no worker of
    /// its own.
    #[test]
    fn a_single_process_serves_one_front_end() {
        let text = "[agent]\ninstance = \"same\"\nsingle_process = true\n\
                    [[frontend]]\ntransport = \"udp4\"\nport = 8888\n\
                    [[frontend]]\ntransport = \"tcp4\"\nport = 8888\n";
        let g = crate::gateway::parse(std::path::Path::new("/etc/xrce-agent/gw.toml"), text)
            .expect("parsed");
        let e = Group::new(AgentPlan::from_gateway(&g).expect("a plan")).expect_err("refused");
        assert!(
            format!("{e:#}")
                .contains("runs one front-end process with its worker; this agent has 2"),
            "{e:#}"
        );
        let one = from_file("single_process = true", "", "").expect("one front-end");
        assert!(one.single_process);
    }
}
