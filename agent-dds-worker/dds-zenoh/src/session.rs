//! The Zenoh session's configuration, made as rmw_zenoh makes a node's: a peer that connects
//! to a router at `tcp/localhost:7447`, without multicast scouting, unless
//! `ZENOH_SESSION_CONFIG_URI` names a configuration file, and with `ZENOH_CONFIG_OVERRIDE`'s
//! `key=value;key=value` changes on top (values in JSON5, keys as paths such as
//! `connect/endpoints`).

/// Names of the environment variables rmw_zenoh reads, which the agent honours the same way.
pub const CONFIG_URI_ENV: &str = "ZENOH_SESSION_CONFIG_URI";
/// See [`CONFIG_URI_ENV`].
pub const CONFIG_OVERRIDE_ENV: &str = "ZENOH_CONFIG_OVERRIDE";

/// The router a session connects to without a configuration file.
pub const DEFAULT_ROUTER: &str = "tcp/localhost:7447";

/// A configuration the agent cannot use.
#[derive(Debug, thiserror::Error)]
pub enum SessionConfigError {
    /// The file `ZENOH_SESSION_CONFIG_URI` names could not be read or parsed.
    #[error("{CONFIG_URI_ENV}={path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// Zenoh's reason.
        reason: String,
    },
    /// An entry of `ZENOH_CONFIG_OVERRIDE` is not `key=value`, or Zenoh refused it.
    #[error("{CONFIG_OVERRIDE_ENV}: {entry:?}: {reason}")]
    Override {
        /// The entry.
        entry: String,
        /// Why.
        reason: String,
    },
}

/// Splits `ZENOH_CONFIG_OVERRIDE` into its `(key, value)` pairs (`;` between them; a value
/// may hold `;` inside brackets or quotes, as in `connect/endpoints=["tcp/a:1";"tcp/b:2"]`
/// is not: lists use commas).
pub fn override_entries(text: &str) -> Result<Vec<(String, String)>, SessionConfigError> {
    let mut out = Vec::new();
    for entry in text.split(';').map(str::trim).filter(|e| !e.is_empty()) {
        let (key, value) = entry
            .split_once('=')
            .filter(|(k, v)| !k.trim().is_empty() && !v.trim().is_empty())
            .ok_or_else(|| SessionConfigError::Override {
                entry: entry.chars().take(200).collect(),
                reason: "expected key=value".into(),
            })?;
        out.push((key.trim().to_string(), value.trim().to_string()));
    }
    Ok(out)
}

/// The session's configuration from `uri` (`ZENOH_SESSION_CONFIG_URI`) and `overrides`
/// (`ZENOH_CONFIG_OVERRIDE`).
pub fn config(
    uri: Option<&str>,
    overrides: Option<&str>,
) -> Result<zenoh::Config, SessionConfigError> {
    let mut config = match uri.filter(|u| !u.is_empty()) {
        Some(path) => zenoh::Config::from_file(path).map_err(|e| SessionConfigError::File {
            path: path.to_string(),
            reason: e.to_string(),
        })?,
        None => {
            let mut c = zenoh::Config::default();
            let defaults = [
                ("mode", "\"peer\"".to_string()),
                ("connect/endpoints", format!("[\"{DEFAULT_ROUTER}\"]")),
                // Other peers reach this one on loopback only, unless configured otherwise.
                ("listen/endpoints", "[\"tcp/localhost:0\"]".to_string()),
                ("scouting/multicast/enabled", "false".to_string()),
                // Samples carry source timestamps in their attachment; Zenoh's own are not
                // needed, but rmw_zenoh's routers and peers enable them: so does the agent.
                (
                    "timestamping/enabled",
                    "{ router: true, peer: true, client: true }".to_string(),
                ),
            ];
            for (key, value) in defaults {
                c.insert_json5(key, &value)
                    .map_err(|e| SessionConfigError::Override {
                        entry: format!("{key}={value}"),
                        reason: format!("built-in default refused: {e}"),
                    })?;
            }
            c
        }
    };
    for (key, value) in override_entries(overrides.unwrap_or_default())? {
        config
            .insert_json5(&key, &value)
            .map_err(|e| SessionConfigError::Override {
                entry: format!("{key}={value}"),
                reason: e.to_string(),
            })?;
    }
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_connects_to_a_local_router_as_a_peer() {
        let c = config(None, None).expect("config");
        let text = format!("{c}");
        assert!(text.contains("tcp/localhost:7447"), "{text}");
        assert!(text.contains("peer"), "{text}");
    }

    #[test]
    fn overrides_apply_and_bad_ones_are_refused() {
        let c = config(
            None,
            Some("connect/endpoints=[\"tcp/127.0.0.1:7999\"];mode=\"client\""),
        )
        .expect("config");
        let text = format!("{c}");
        assert!(text.contains("tcp/127.0.0.1:7999"), "{text}");
        assert!(!text.contains("tcp/localhost:7447"), "{text}");
        assert!(config(None, Some("connect/endpoints")).is_err());
        assert!(config(None, Some("no/such/key=1")).is_err());
        assert!(config(Some("/nonexistent/zenoh.json5"), None).is_err());
        assert_eq!(
            override_entries(" a=1 ; b = \"x\" ;").expect("entries"),
            vec![("a".into(), "1".into()), ("b".into(), "\"x\"".into())]
        );
    }
}
