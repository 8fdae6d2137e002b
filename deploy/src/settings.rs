//! Each setting of the agent as a value: its parser and its bounds, written once and used
//! by the command line ([`crate::cli`]), the gateway file ([`crate::gateway`]) and the plan
//! both produce ([`crate::plan`]). A leaf: it names none of them.

use xrce_dds_worker::domains::{DomainSet, DOMAIN_COUNT};

/// The largest `--memory-limit` (and `memory_limit_mib`): 1 TiB.
pub const MAX_MEMORY_LIMIT_MIB: u64 = 1 << 20;

/// `--verbose`, `agent.verbose`.
pub fn check_verbose(v: u8) -> Result<u8, String> {
    (v <= 6)
        .then_some(v)
        .ok_or_else(|| "must be 0 to 6".to_string())
}

/// `-v`'s parser: a number, then [`check_verbose`].
pub fn parse_verbose(text: &str) -> Result<u8, String> {
    text.parse::<u8>()
        .map_err(|e| format!("{e}"))
        .and_then(check_verbose)
}

/// `--memory-limit`'s parser: a number, then [`check_memory_limit_mib`].
pub fn parse_memory_limit_mib(text: &str) -> Result<u64, String> {
    text.parse::<u64>()
        .map_err(|e| format!("{e}"))
        .and_then(check_memory_limit_mib)
}

/// `--client-dead-time`, `client_dead_time`: seconds, 0 (never) to a year.
pub fn check_client_dead_time(s: f64) -> Result<f64, String> {
    (s.is_finite() && (0.0..=31_536_000.0).contains(&s))
        .then_some(s)
        .ok_or_else(|| format!("must be 0 to 31536000 seconds (a year), got {s}"))
}

/// `--frontend-grace`, `worker.frontend_grace`: seconds, 0 to a day.
pub fn check_frontend_grace(s: f64) -> Result<f64, String> {
    (s.is_finite() && (0.0..=86_400.0).contains(&s))
        .then_some(s)
        .ok_or_else(|| format!("must be 0 to 86400 seconds (a day), got {s}"))
}

/// `--memory-limit`, `agent.memory_limit_mib`: MiB.
pub fn check_memory_limit_mib(m: u64) -> Result<u64, String> {
    (1..=MAX_MEMORY_LIMIT_MIB)
        .contains(&m)
        .then_some(m)
        .ok_or_else(|| format!("must be 1 to {MAX_MEMORY_LIMIT_MIB} (MiB), got {m}"))
}

/// `--max-domains`, `worker.max_domains`: 1 to as many domains as DDS has.
pub fn check_max_domains(n: u16) -> Result<u16, String> {
    (1..=DOMAIN_COUNT)
        .contains(&n)
        .then_some(n)
        .ok_or_else(|| format!("must be 1 to {DOMAIN_COUNT}, got {n}"))
}

/// `--processes`' parser: a count ([`check_processes`]) or `auto` ([`auto_processes`]).
pub fn parse_processes(text: &str) -> Result<u16, String> {
    if text == "auto" {
        return Ok(auto_processes());
    }
    text.parse::<u16>()
        .map_err(|e| format!("{e} (a count, or `auto`)"))
        .and_then(check_processes)
}

/// `--processes`, `frontend.processes`: how many front-end processes serve one UDP port.
pub fn check_processes(n: u16) -> Result<u16, String> {
    let most = crate::shared_port::MAX_PROCESSES;
    (1..=most)
        .contains(&n)
        .then_some(n)
        .ok_or_else(|| format!("must be 1 to {most}, got {n}"))
}

/// Processes for a UDP port chosen from the cores: one per four (one worker thread serves
/// them all, and each front-end's thread needs a core beside it), from 1 to 8.
pub fn auto_processes() -> u16 {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (cores / 4).clamp(1, 8) as u16
}

/// `--instance`, `agent.instance`.
pub fn check_instance(name: &str) -> Result<(), String> {
    xrce_ipc::shm::valid_instance(name)
        .then_some(())
        .ok_or_else(|| format!("{name:?} must be 1-32 characters of [A-Za-z0-9_-]"))
}

/// `--domains`, `worker.domains`: ids and ranges (`0-10,42`).
pub fn parse_domains(list: &str) -> Result<DomainSet, String> {
    list.parse::<DomainSet>()
        .map_err(|e| format!("{list:?}: {e}"))
}
