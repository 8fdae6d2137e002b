//! Writes what `xrce-agent --version` says about this build: the commit it was built from
//! (`XRCE_AGENT_COMMIT` when set, as a build outside a checkout does; else git's; else
//! "unknown") and the DDS backends built in.

use std::path::PathBuf;
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    if !out.status.success() {
        return None;
    }
    let s = String::from_utf8(out.stdout).ok()?.trim().to_string();
    (!s.is_empty()).then_some(s)
}

fn main() {
    println!("cargo:rerun-if-env-changed=XRCE_AGENT_COMMIT");
    // A new commit (or checkout) changes HEAD, the branch it names, or the packed refs
    // (git's own paths for them, right in a worktree too). Only files that exist are named:
    // cargo reruns the script on every build for one that does not.
    let mut watched = vec!["HEAD".to_string(), "packed-refs".to_string()];
    if let Some(reference) = git(&["symbolic-ref", "-q", "HEAD"]) {
        watched.push(reference);
    }
    for name in watched {
        if let Some(path) = git(&["rev-parse", "--git-path", &name]) {
            if PathBuf::from(&path).exists() {
                println!("cargo:rerun-if-changed={path}");
            }
        }
    }
    // The commit, and its date when git knows it.
    let (commit, date) = match std::env::var("XRCE_AGENT_COMMIT") {
        Ok(c) if !c.trim().is_empty() => (c.trim().to_string(), None),
        _ => match git(&["rev-parse", "--short=12", "HEAD"]) {
            Some(hash) => (hash, git(&["log", "-1", "--format=%cs", "HEAD"])),
            None => ("unknown".to_string(), None),
        },
    };
    let (short_commit, long_commit) = match date {
        Some(d) => (format!("{commit} {d}"), format!("{commit} ({d})")),
        None => (commit.clone(), commit),
    };
    let backends = if std::env::var_os("CARGO_FEATURE_CYCLONE").is_some() {
        "cyclone (Cyclone DDS, the default), rustdds (RustDDS)"
    } else {
        "rustdds (RustDDS, the default; built without the cyclone feature)"
    };
    let middlewares = if std::env::var_os("CARGO_FEATURE_ZENOH").is_some() {
        "dds, zenoh (rmw_zenoh 0.2.10/0.6.7 conventions)"
    } else {
        "dds (built without the zenoh feature)"
    };
    let version = std::env::var("CARGO_PKG_VERSION").unwrap_or_default();
    let long = format!(
        "{version}\ncommit: {long_commit}\nDDS backends: {backends}\nmiddlewares: {middlewares}"
    );
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    std::fs::write(
        out.join("version.rs"),
        format!(
            "/// `--version`: the version, the commit and the DDS backends of this build.\n\
             pub const LONG_VERSION: &str = {long:?};\n\
             /// `-V`: the version and the commit.\n\
             pub const SHORT_VERSION: &str = {short:?};\n",
            short = format!("{version} ({short_commit})"),
        ),
    )
    .expect("writing version.rs");
}
