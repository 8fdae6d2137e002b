//! How a supervisor hands each of its processes its settings: as one typed value per process
//! (a clap `Args` struct: the front-end's, the worker's) written out as that process's own
//! command line, with every field given, so that what the supervisor decided is what the
//! process runs with. These helpers give such a type's defaults.

use clap::{Args, FromArgMatches};

/// Every setting of `T` as an empty command line gives them: the environment variables its
/// arguments name included. A variable with a value `T` refuses is an error.
pub fn from_environment<T: Args + FromArgMatches>(program: &'static str) -> Result<T, clap::Error> {
    let command = T::augment_args(clap::Command::new(program));
    let matches = command.try_get_matches_from([program])?;
    T::from_arg_matches(&matches)
}

/// Every setting of `T` at its built-in default, whatever the environment says.
///
/// `T` must accept an empty command line (every argument optional or with a default); a type
/// that does not is a programming error, reported by clap and the process exits.
pub fn built_in<T: Args + FromArgMatches>(program: &'static str) -> T {
    let mut command = T::augment_args(clap::Command::new(program));
    let ids: Vec<clap::Id> = command
        .get_arguments()
        .map(|a| a.get_id().clone())
        .collect();
    for id in ids {
        command = command.mut_arg(id, |a| a.env(None));
    }
    let matches = command.get_matches_from([program]);
    T::from_arg_matches(&matches).unwrap_or_else(|e| e.exit())
}
