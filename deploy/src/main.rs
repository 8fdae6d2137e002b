//! `xrce-agent`: the user-facing command, a drop-in for eProsima's `MicroXRCEAgent`
//! (`xrce-agent udp4 -p 8888`, `xrce-agent serial --dev /dev/ttyACM0 -b 921600`, ...), and
//! a gateway of several front-ends on one DDS worker from a file (`xrce-agent --config
//! gateway.toml`). It supervises the worker and the front-ends, which are this same
//! executable started with the hidden `dds-worker` and `frontend` subcommands, so one binary
//! is all a user needs.

use std::process::ExitCode;

use clap::Parser;
use xrce_agent::cli::{check_supported, plan, Cli, Command, Unsupported};
use xrce_agent::group::{init_logging, log_filter, Group};
use xrce_agent::plan::AgentPlan;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.downcast_ref::<Unsupported>().is_some() => {
            eprintln!("xrce-agent: {e}");
            ExitCode::from(2)
        }
        Err(e) => {
            eprintln!("Error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    if let Some(path) = &cli.config {
        let gateway = xrce_agent::gateway::load(path)?;
        if cli.check {
            // What the file leaves to the environment is checked too, as a start would.
            let group = Group::new(AgentPlan::from_gateway(&gateway)?)?;
            println!("{}: valid", path.display());
            for f in &gateway.frontends {
                println!(
                    "  front-end {} (id {}): {}",
                    f.name,
                    f.id,
                    f.plan.describe()
                );
                // The processes of a shared port, as logs, status and --process name them.
                for p in group
                    .frontends
                    .iter()
                    .filter(|p| p.share.is_some_and(|s| s.member > 0) && p.plan == f.plan)
                {
                    println!("    process {} (id {})", p.name, p.id);
                }
            }
            return Ok(());
        }
        let plan = AgentPlan::from_gateway(&gateway)?;
        init_logging(&log_filter(plan.verbose));
        let group = Group::new(plan)?;
        return match &cli.process {
            Some(name) => group.exec_one(name),
            None => group.supervise(),
        };
    }
    let Some(command) = cli.command else {
        return Err(Unsupported(
            "name a transport (udp4, udp6, tcp4, tcp6, serial, multiserial, pseudoterminal) or --config FILE; see --help".into(),
        )
        .into());
    };
    let Some((frontend, common)) = plan(&command)? else {
        return match command {
            Command::DdsWorker(args) => xrce_dds_worker::cli::run(args),
            Command::Frontend(args) => xrce_frontend::start::run(args),
            Command::SingleProcess(args) => xrce_agent::in_process::run(&args),
            Command::Status(args) => xrce_agent::status_view::run(&args),
            Command::Sweep(args) => xrce_agent::sweep::run(&args),
            Command::Generate(args) => xrce_agent::docs::run(&args),
            _ => Ok(()),
        };
    };
    check_supported(&common)?;
    let plan = AgentPlan::from_command_line(frontend, &common)?;
    init_logging(&log_filter(plan.verbose));
    Group::new(plan)?.supervise()
}
