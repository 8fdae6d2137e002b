//! The RIHS01 type hashes rmw_zenoh puts in every key expression and token.
//!
//! An XRCE client names a type (`std_msgs::msg::dds_::String_`) but never sends its hash, and
//! rmw_zenoh (Jazzy and later) matches keys verbatim: a publisher whose hash differs from a
//! subscription's is never heard, without any error on either side. So the agent must put
//! the very hash the ROS installation of the other nodes computed. It looks for it, in order:
//!
//! 1. in the type description files of ROS installations: every `--zenoh-type-hashes`
//!    folder, then every prefix of `AMENT_PREFIX_PATH` (a sourced ROS shell sets it). ROS
//!    installs `share/<package>/msg/<Type>.json` (and `srv/`) with a `type_hashes` list;
//!    a folder may be an install prefix or its `share` folder;
//! 2. in `--zenoh-type-hashes` files: lines `<package>/msg/<Type> RIHS01_<hex>`;
//! 3. in the table built into the agent ([`BUILT_IN`]: ROS 2 Jazzy's common interfaces).
//!
//! A type found nowhere gets [`NOT_SUPPORTED`], which rmw_zenoh on Humble uses for every
//! type; Jazzy's and Kilted's nodes will not match it, and the agent says so once per type.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::naming::ros_type_name;

/// The hash of a type whose hash is not known.
pub const NOT_SUPPORTED: &str = "TypeHashNotSupported";

/// The built-in table: `<ros type name>\t<hash>` lines, `#` comments.
pub const BUILT_IN: &str = include_str!("type_hashes.tsv");

/// Largest type description file read (the biggest in a ROS installation are tens of KiB).
const MAX_FILE: u64 = 4 << 20;

/// Where a hash came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// A type description file of a ROS installation.
    Description(PathBuf),
    /// A table file given with `--zenoh-type-hashes`.
    Table(PathBuf),
    /// The agent's own table.
    BuiltIn,
    /// Nowhere: [`NOT_SUPPORTED`].
    Unknown,
}

/// The hashes found so far, and where to look for more.
#[derive(Debug, Default)]
pub struct TypeHashes {
    folders: Vec<PathBuf>,
    tables: HashMap<String, (String, PathBuf)>,
    built_in: HashMap<String, String>,
    found: HashMap<String, (String, Source)>,
    /// Bytes of the names and hashes in `found` ([`MAX_FOUND_BYTES`]).
    found_bytes: usize,
    /// Unknown types whose warning was logged (bounded; beyond, they are counted only).
    warned: std::collections::HashSet<String>,
    /// Unknown types not warned about (past [`MAX_WARNED`]).
    unwarned: u64,
}

/// Longest DDS type name looked up: a ROS type's (`pkg::msg::dds_::Name_`) is far shorter;
/// a longer one is refused at creation before anything is looked up.
pub const MAX_TYPE_NAME: usize = 256;
/// Bytes of names and hashes remembered from lookups; past it, lookups are not cached.
const MAX_FOUND_BYTES: usize = 4 << 20;
/// Unknown types warned about by name, one line each; the rest are counted.
const MAX_WARNED: usize = 256;

/// Whether `s` is a RIHS01 hash as rmw_zenoh writes it.
pub fn is_rihs01(s: &str) -> bool {
    s.strip_prefix("RIHS01_").is_some_and(|h| {
        h.len() == 64
            && h.bytes()
                .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    })
}

fn parse_table(text: &str) -> impl Iterator<Item = (&str, &str)> {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .filter_map(|l| {
            let mut parts = l.split_whitespace();
            let (name, hash) = (parts.next()?, parts.next()?);
            is_rihs01(hash).then_some((name, hash))
        })
}

/// A `--zenoh-type-hashes` entry that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TypeHashesError {
    /// Neither a folder nor a readable table file.
    #[error("--zenoh-type-hashes {path}: {reason}")]
    Unreadable {
        /// The path given.
        path: PathBuf,
        /// Why.
        reason: String,
    },
}

impl TypeHashes {
    /// Looks in `given` (folders and table files), then in `AMENT_PREFIX_PATH`'s prefixes
    /// (`ament`, the variable's value), then in the built-in table.
    pub fn new(given: &[PathBuf], ament: Option<&str>) -> Result<Self, TypeHashesError> {
        let mut hashes = TypeHashes {
            built_in: parse_table(BUILT_IN)
                .map(|(n, h)| (n.to_string(), h.to_string()))
                .collect(),
            ..Default::default()
        };
        for path in given {
            if path.is_dir() {
                hashes.folders.push(path.clone());
                continue;
            }
            let text = read_bounded(path).map_err(|reason| TypeHashesError::Unreadable {
                path: path.clone(),
                reason,
            })?;
            for (n, h) in parse_table(&text) {
                hashes
                    .tables
                    .insert(n.to_string(), (h.to_string(), path.clone()));
            }
        }
        for prefix in ament
            .unwrap_or_default()
            .split(':')
            .filter(|p| !p.is_empty())
        {
            hashes.folders.push(PathBuf::from(prefix));
        }
        Ok(hashes)
    }

    /// How many hashes the built-in table holds.
    pub fn built_in_len(&self) -> usize {
        self.built_in.len()
    }

    /// The hash of a DDS type name and where it came from. A name that is not a ROS type's
    /// (`pkg::msg::dds_::Name_`) or longer than [`MAX_TYPE_NAME`] has none, and is neither
    /// searched for nor remembered: what a client names costs nothing beyond its check.
    pub fn lookup(&mut self, dds_type: &str) -> (String, Source) {
        if let Some(found) = self.found.get(dds_type) {
            return found.clone();
        }
        let ros_type = dds_type.len() <= MAX_TYPE_NAME && ros_type_name(dds_type).is_some();
        let found = if ros_type {
            self.search(dds_type)
        } else {
            (NOT_SUPPORTED.to_string(), Source::Unknown)
        };
        match &found.1 {
            Source::Unknown => self.warn_unknown(dds_type),
            source => tracing::debug!(type_name = dds_type, hash = %found.0, ?source, "type hash"),
        }
        let cost = dds_type.len() + found.0.len();
        if ros_type && self.found_bytes + cost <= MAX_FOUND_BYTES {
            self.found_bytes += cost;
            self.found.insert(dds_type.to_string(), found.clone());
        }
        found
    }

    /// One warning per unknown type (its name cut to [`MAX_TYPE_NAME`] characters), for the
    /// first [`MAX_WARNED`] of them; the others are counted in the last line's total.
    fn warn_unknown(&mut self, dds_type: &str) {
        let shown: String = dds_type.chars().take(MAX_TYPE_NAME).collect();
        if self.warned.contains(&shown) {
            return;
        }
        if self.warned.len() >= MAX_WARNED {
            self.unwarned += 1;
            if self.unwarned.is_power_of_two() {
                tracing::warn!(
                    unknown_types_not_logged = self.unwarned,
                    "more types without a RIHS01 hash (logged at powers of two)"
                );
            }
            return;
        }
        tracing::warn!(
            type_name = %shown,
            "no RIHS01 hash known for this type: its key expressions end in \
             TypeHashNotSupported, which ROS 2 nodes on rmw_zenoh (Jazzy and later) do not \
             match; point --zenoh-type-hashes at the ROS installation's share folder, or \
             source it (AMENT_PREFIX_PATH)"
        );
        self.warned.insert(shown);
    }

    fn search(&self, dds_type: &str) -> (String, Source) {
        let Some(ros) = ros_type_name(dds_type) else {
            return (NOT_SUPPORTED.to_string(), Source::Unknown);
        };
        for folder in &self.folders {
            for share in [folder.join("share"), folder.clone()] {
                let file = share.join(format!("{ros}.json"));
                if let Some(hash) = hash_in_description(&file, &ros) {
                    return (hash, Source::Description(file));
                }
            }
        }
        if let Some((h, path)) = self.tables.get(&ros) {
            return (h.clone(), Source::Table(path.clone()));
        }
        if let Some(h) = self.built_in.get(&ros) {
            return (h.clone(), Source::BuiltIn);
        }
        (NOT_SUPPORTED.to_string(), Source::Unknown)
    }
}

fn read_bounded(path: &Path) -> Result<String, String> {
    use std::io::Read as _;
    use std::os::unix::fs::OpenOptionsExt as _;
    // Opened without blocking (a FIFO would block the worker), then a regular file only.
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| e.to_string())?;
    if !file.metadata().map_err(|e| e.to_string())?.is_file() {
        return Err("not a regular file".into());
    }
    let mut text = String::new();
    file.take(MAX_FILE)
        .read_to_string(&mut text)
        .map_err(|e| e.to_string())?;
    Ok(text)
}

/// The hash of `ros_type` in a type description file (`{"type_hashes": [{"type_name": ...,
/// "hash_string": ...}], ...}`), if the file is there and holds one.
fn hash_in_description(file: &Path, ros_type: &str) -> Option<String> {
    let text = read_bounded(file).ok()?;
    #[derive(serde::Deserialize)]
    struct Entry {
        type_name: String,
        hash_string: String,
    }
    #[derive(serde::Deserialize)]
    struct Description {
        type_hashes: Vec<Entry>,
    }
    let parsed: Description = match serde_json::from_str(&text) {
        Ok(d) => d,
        Err(e) => {
            tracing::warn!(file = %file.display(), "unreadable type description: {e}");
            return None;
        }
    };
    parsed
        .type_hashes
        .into_iter()
        .find(|e| e.type_name == ros_type && is_rihs01(&e.hash_string))
        .map(|e| e.hash_string)
}

#[cfg(test)]
mod tests {
    use super::*;

    const STRING: &str = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18";

    #[test]
    fn the_built_in_table_knows_std_msgs_string() {
        let mut h = TypeHashes::new(&[], None).expect("hashes");
        assert!(h.built_in_len() > 50, "{}", h.built_in_len());
        assert_eq!(
            h.lookup("std_msgs::msg::dds_::String_"),
            (STRING.to_string(), Source::BuiltIn)
        );
        assert_eq!(
            h.lookup("HelloWorld"),
            (NOT_SUPPORTED.to_string(), Source::Unknown)
        );
        for (name, hash) in parse_table(BUILT_IN) {
            assert!(is_rihs01(hash), "{name}");
            assert!(name.split('/').count() == 3, "{name}");
        }
    }

    #[test]
    fn names_a_client_invents_are_neither_searched_nor_remembered() {
        let mut h = TypeHashes::new(&[], None).expect("hashes");
        let huge = format!("pkg::msg::dds_::{}_", "x".repeat(900 << 10));
        assert_eq!(
            h.lookup(&huge),
            (NOT_SUPPORTED.to_string(), Source::Unknown)
        );
        for i in 0..1000 {
            h.lookup(&format!("Invented{i}"));
        }
        assert!(h.found.is_empty(), "{} remembered", h.found.len());
        assert_eq!(h.warned.len(), MAX_WARNED);
        assert!(h.warned.iter().all(|w| w.len() <= MAX_TYPE_NAME));
        // Known ROS types are remembered, within the bound in bytes.
        h.lookup("std_msgs::msg::dds_::String_");
        assert_eq!(h.found.len(), 1);
        assert!(h.found_bytes <= MAX_FOUND_BYTES);
    }

    #[test]
    fn an_installation_wins_over_tables_and_bad_files_are_skipped() {
        let dir = std::env::temp_dir().join(format!("xrce-type-hashes-{}", std::process::id()));
        let msg = dir.join("share/my_msgs/msg");
        std::fs::create_dir_all(&msg).expect("dir");
        let mine = format!("RIHS01_{}", "ab".repeat(32));
        std::fs::write(
            msg.join("Thing.json"),
            format!(
                r#"{{"type_description_msg": {{}}, "type_hashes": [
                    {{"type_name": "my_msgs/msg/Thing", "hash_string": "{mine}"}},
                    {{"type_name": "other/msg/X", "hash_string": "{STRING}"}}]}}"#
            ),
        )
        .expect("write");
        std::fs::write(msg.join("Broken.json"), "{ not json").expect("write");
        let table = dir.join("table.tsv");
        let theirs = format!("RIHS01_{}", "cd".repeat(32));
        std::fs::write(
            &table,
            format!("# mine\nmy_msgs/msg/Thing {theirs}\nmy_msgs/msg/Other\t{theirs}\nbad line\n"),
        )
        .expect("write");
        let ament = format!("/nonexistent:{}", dir.display());
        let mut h = TypeHashes::new(std::slice::from_ref(&table), Some(&ament)).expect("hashes");
        assert_eq!(
            h.lookup("my_msgs::msg::dds_::Thing_"),
            (mine, Source::Description(msg.join("Thing.json")))
        );
        assert_eq!(
            h.lookup("my_msgs::msg::dds_::Other_"),
            (theirs, Source::Table(table))
        );
        assert_eq!(h.lookup("my_msgs::msg::dds_::Broken_").1, Source::Unknown);
        assert!(TypeHashes::new(&[dir.join("missing.tsv")], None).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn only_rihs01_hashes_are_taken() {
        assert!(is_rihs01(STRING));
        assert!(!is_rihs01(&STRING.to_uppercase()));
        assert!(!is_rihs01("RIHS01_abc"));
        assert!(!is_rihs01(NOT_SUPPORTED));
    }
}
