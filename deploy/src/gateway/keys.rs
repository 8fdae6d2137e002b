//! Every key of the gateway file, described once: `xrce-agent generate gateway-reference`
//! writes `docs/gateway.md` from this table (a test checks the committed file is current),
//! and a unit test checks that the table names exactly the keys the file's parser takes.
//! Defaults that are settings of a process are read from that process's own built-in
//! defaults, so they cannot drift either.

use xrce_frontend::cli::FrontendArgs;

/// One key of the gateway file.
#[derive(Debug, Clone, Copy)]
pub struct KeyDoc {
    /// Its table: `agent`, `worker`, `metrics` or `frontend` (each `[[frontend]]`).
    pub table: &'static str,
    /// The key.
    pub key: &'static str,
    /// What its value is.
    pub value: &'static str,
    /// Its default, in words.
    pub default: fn() -> String,
    /// What it does (and the command-line option it stands for).
    pub meaning: &'static str,
}

fn none() -> String {
    "unset".to_string()
}

fn frontend() -> FrontendArgs {
    FrontendArgs::built_in()
}

/// Every key, table by table, in the order of the reference.
pub const KEYS: &[KeyDoc] = &[
    KeyDoc {
        table: "agent",
        key: "instance",
        value: "1-32 characters of `[A-Za-z0-9_-]`",
        default: || "derived from the file's path and the network namespace".into(),
        meaning: "Name shared by the agent's processes (shared memory, runtime directory); required when the processes run as separate systemd units (`--process`). `--instance`.",
    },
    KeyDoc {
        table: "agent",
        key: "verbose",
        value: "0-6",
        default: || "4 (info), or `XRCE_LOG`".into(),
        meaning: "Log verbosity of every process, like `-v`.",
    },
    KeyDoc {
        table: "agent",
        key: "memory_limit_mib",
        value: "MiB, 1 or more",
        default: none,
        meaning: "Private resident memory beyond which a process is restarted (its clients keep their sessions). `--memory-limit`.",
    },
    KeyDoc {
        table: "agent",
        key: "discard_sessions",
        value: "true or false",
        default: || "false, or `XRCE_DISCARD_SESSIONS`".into(),
        meaning: "Start without the sessions a previous agent of the instance stored (its clients create them again). `--discard-sessions`.",
    },
    KeyDoc {
        table: "agent",
        key: "single_process",
        value: "true or false",
        default: || "false, or `XRCE_SINGLE_PROCESS`".into(),
        meaning: "Run the front-end and the DDS worker in one process: less CPU per sample; a crash takes both down (sessions survive it). One front-end only. `--single-process`.",
    },
    KeyDoc {
        table: "worker",
        key: "refs",
        value: "path",
        default: none,
        meaning: "Fast DDS XML profiles clients may create entities from by reference, relative to the gateway file. `-r`.",
    },
    KeyDoc {
        table: "worker",
        key: "dds_interfaces",
        value: "list of local addresses",
        default: || "every interface".into(),
        meaning: "Restrict DDS to these local addresses. `--dds-interface`.",
    },
    KeyDoc {
        table: "worker",
        key: "ros_graph",
        value: "true or false",
        default: || "true".into(),
        meaning: "Announce XRCE participants named like ROS 2 nodes on `ros_discovery_info`. `--ros-graph`.",
    },
    KeyDoc {
        table: "worker",
        key: "share_writers",
        value: "true or false",
        default: || "false".into(),
        meaning: "Map the writers of many clients on one topic onto shared DDS writers, one per 32 clients. `--share-writers`.",
    },
    KeyDoc {
        table: "worker",
        key: "dds_backend",
        value: "`cyclone`, `rustdds` or `zenoh`",
        default: || "cyclone (rustdds in a build without the `cyclone` feature)".into(),
        meaning: "The DDS implementation. `--dds-backend`.",
    },
    KeyDoc {
        table: "worker",
        key: "middleware",
        value: "`dds` or `zenoh`",
        default: || "dds".into(),
        meaning: "`zenoh` joins an rmw_zenoh ROS 2 graph instead of DDS (rmw_zenoh's keys, attachments and liveliness tokens; a router at tcp/localhost:7447 unless `ZENOH_SESSION_CONFIG_URI`/`ZENOH_CONFIG_OVERRIDE` say otherwise). `-m`.",
    },
    KeyDoc {
        table: "worker",
        key: "zenoh_type_hashes",
        value: "list of paths",
        default: || "none".into(),
        meaning: "With `middleware = \"zenoh\"`: ROS installations (`/opt/ros/jazzy` or its `share`) and `pkg/msg/Type RIHS01_...` tables the type hashes are looked up in, before `AMENT_PREFIX_PATH` and the built-in Jazzy table; relative to this file. `--zenoh-type-hashes`.",
    },
    KeyDoc {
        table: "worker",
        key: "frontend_grace",
        value: "seconds, 0 to 86400",
        default: || xrce_dds_worker::cli::WorkerArgs::built_in().frontend_grace.to_string(),
        meaning: "How long the entities of a front-end whose process is gone are kept for it to come back. `--frontend-grace`.",
    },
    KeyDoc {
        table: "worker",
        key: "ros_distro",
        value: "`humble`, `iron`, `jazzy`, `kilted`, `rolling`",
        default: || "`ROS_DISTRO`, else jazzy".into(),
        meaning: "The layout of `ros_discovery_info` (Humble's GIDs are 24 octets, later ones 16). `--ros-distro`.",
    },
    KeyDoc {
        table: "worker",
        key: "domains",
        value: "ids and ranges, `\"0-10,42\"`",
        default: || "any".into(),
        meaning: "The DDS domain ids clients may use; a participant in another is refused (STATUS_ERR_DENIED). `--domains`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_domains",
        value: "1-233",
        default: || "8, none with `domains`".into(),
        meaning: "Most distinct DDS domains in use at once (STATUS_ERR_RESOURCES beyond). `--max-domains`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_entities_per_client",
        value: "1 or more",
        default: || xrce_dds_worker::bounds::WorkerBounds::default().entities_per_client.to_string(),
        meaning: "DDS entities (participants, topics, publishers, subscribers, writers, readers, requesters, repliers) of one client; one more is refused with STATUS_ERR_RESOURCES. `--max-entities-per-client`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_entities",
        value: "1 or more",
        default: || xrce_dds_worker::bounds::WorkerBounds::default().entities_total.to_string(),
        meaning: "DDS entities of every client together. `--max-entities`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_samples_per_endpoint",
        value: "1 or more",
        default: || xrce_dds_worker::bounds::WorkerBounds::default().samples_per_endpoint.to_string(),
        meaning: "Samples one DDS reader's or writer's cache may keep: a deeper history, KEEP_ALL and unlimited resource limits are clamped to it (logged). `--max-samples-per-endpoint`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_instances_per_endpoint",
        value: "1 or more",
        default: || xrce_dds_worker::bounds::WorkerBounds::default().instances_per_endpoint.to_string(),
        meaning: "Instances one DDS endpoint of a keyed topic may keep (clamped as above). `--max-instances-per-endpoint`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_samples_per_client",
        value: "1 or more",
        default: || xrce_dds_worker::bounds::WorkerBounds::default().samples_per_client.to_string(),
        meaning: "Samples the endpoints of one client may keep together, reserved at creation (STATUS_ERR_RESOURCES beyond). `--max-samples-per-client`.",
    },
    KeyDoc {
        table: "worker",
        key: "max_samples",
        value: "1 or more",
        default: || xrce_dds_worker::bounds::WorkerBounds::default().samples_total.to_string(),
        meaning: "Samples the endpoints of every client may keep together; past half, each front-end keeps to an equal share. `--max-samples`.",
    },
    KeyDoc {
        table: "metrics",
        key: "listen",
        value: "address:port",
        default: || "off".into(),
        meaning: "Serve Prometheus metrics at `/metrics` and the live sessions at `/status` (`xrce-agent status --metrics URL`). `--metrics`.",
    },
    KeyDoc {
        table: "frontend",
        key: "name",
        value: "text, unique",
        default: || "its transport and id".into(),
        meaning: "The front-end's name in logs, readiness and `--process`.",
    },
    KeyDoc {
        table: "frontend",
        key: "id",
        value: "whole number, unique",
        default: || "its place in the file".into(),
        meaning: "The front-end's id (the worker keys its clients' entities by it; keep it when editing the file).",
    },
    KeyDoc {
        table: "frontend",
        key: "transport",
        value: "`udp4`, `udp6`, `tcp4`, `tcp6`, `serial`, `multiserial`, `pseudoterminal`",
        default: || "required".into(),
        meaning: "What the front-end serves.",
    },
    KeyDoc {
        table: "frontend",
        key: "port",
        value: "1-65535",
        default: || "required for udp and tcp".into(),
        meaning: "The UDP or TCP port (udp and tcp only). `-p`.",
    },
    KeyDoc {
        table: "frontend",
        key: "bind",
        value: "local address",
        default: || "every interface of the transport's family".into(),
        meaning: "The address to serve on (udp and tcp only).",
    },
    KeyDoc {
        table: "frontend",
        key: "discovery",
        value: "port",
        default: none,
        meaning: "Answer XRCE multicast discovery (group 239.255.0.2) on this port (udp and tcp only). `-d`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_connections",
        value: "whole number",
        default: || frontend().max_connections.to_string(),
        meaning: "TCP connections served at once (tcp only).",
    },
    KeyDoc {
        table: "frontend",
        key: "processes",
        value: "1-64, or \"auto\" (one per four cores, at most 8)",
        default: || "1".into(),
        meaning: "Front-end processes that serve the port (udp only), each with its own socket on it: a client is served by the one its source address hashes to, so a client whose port changes stays where its session is and one address's clients share one process. The first keeps the front-end's id and name; the one named `<name>-n` (n from 2) has the id plus (n - 1) × 1,048,576. `auto` is counted again at each start (from the cores this process may use): a change moves clients. `--processes`.",
    },
    KeyDoc {
        table: "frontend",
        key: "device",
        value: "path",
        default: || "required for serial".into(),
        meaning: "The serial device (serial only; a `/dev/serial/by-id/` name survives replugs). `--dev`.",
    },
    KeyDoc {
        table: "frontend",
        key: "devices",
        value: "list of paths",
        default: || "required for multiserial".into(),
        meaning: "The serial devices (multiserial only). `--devs`.",
    },
    KeyDoc {
        table: "frontend",
        key: "baudrate",
        value: "bits per second",
        default: || frontend().baudrate.to_string(),
        meaning: "Line speed (serial transports). `-b`.",
    },
    KeyDoc {
        table: "frontend",
        key: "flow_control",
        value: "true or false",
        default: || frontend().flow_control.to_string(),
        meaning: "RTS/CTS hardware flow control (serial transports).",
    },
    KeyDoc {
        table: "frontend",
        key: "client_dead_time",
        value: "seconds",
        default: || frontend().client_dead_time.to_string(),
        meaning: "Delete the session and entities of a client silent this long (probed first; 0: never). `--client-dead-time`.",
    },
    KeyDoc {
        table: "frontend",
        key: "dialect",
        value: "`spec` or `eprosima`",
        default: || "per session, from the client's vendor id".into(),
        meaning: "Force the protocol dialect of every session. `--dialect`.",
    },
    KeyDoc {
        table: "frontend",
        key: "allow_keys",
        value: "list of client keys, `\"0xAAAABBBB\"`",
        default: || "any key".into(),
        meaning: "Only these client keys get a session. `--allow-keys`.",
    },
    KeyDoc {
        table: "frontend",
        key: "allow_roaming",
        value: "true or false",
        default: || frontend().admission.allow_roaming.to_string(),
        meaning: "Let a session follow its client to a new address without a new CREATE_CLIENT (otherwise only a client that proves its key moves it). `--allow-roaming`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_objects_per_client",
        value: "1 or more",
        default: || frontend().admission.max_objects_per_client.to_string(),
        meaning: "Most XRCE objects one client may create (STATUS_ERR_RESOURCES beyond). `--max-objects-per-client`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_client_messages_per_second",
        value: "whole number, 0 = no bound",
        default: || frontend().admission.max_client_messages_per_second.to_string(),
        meaning: "Messages per second one client may send; beyond, they are dropped and counted. `--max-client-messages-per-second`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_client_bytes_per_second",
        value: "whole number, 0 = no bound",
        default: || frontend().admission.max_client_bytes_per_second.to_string(),
        meaning: "Bytes per second one client may send. `--max-client-bytes-per-second`.",
    },
    KeyDoc {
        table: "frontend",
        key: "memory_budget_mib",
        value: "MiB, 1 or more",
        default: || frontend().admission.memory_budget_mib.to_string(),
        meaning: "What this front-end's clients may make it hold, shared fairly between addresses (docs/security.md). `--memory-budget`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_sessions",
        value: "1 or more",
        default: || frontend().admission.max_sessions.to_string(),
        meaning: "Most sessions the front-end holds. `--max-sessions`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_sessions_per_address",
        value: "1 or more",
        default: || frontend().admission.max_sessions_per_address.to_string(),
        meaning: "Most sessions from one address (a serial line is one address). `--max-sessions-per-address`.",
    },
    KeyDoc {
        table: "frontend",
        key: "new_sessions_per_second",
        value: "0 or more",
        default: || frontend().admission.new_sessions_per_second.to_string(),
        meaning: "New sessions one address may start per second; beyond, CREATE_CLIENTs go unanswered until the rate falls (0: no limit). `--new-sessions-per-second`.",
    },
    KeyDoc {
        table: "frontend",
        key: "max_connections_per_address",
        value: "1 or more",
        default: || frontend().admission.max_connections_per_address.to_string(),
        meaning: "Most TCP connections from one address (tcp only). `--max-connections-per-address`.",
    },
    KeyDoc {
        table: "frontend",
        key: "tcp_idle_timeout",
        value: "seconds, 0 = none",
        default: || frontend().admission.tcp_idle_timeout.to_string(),
        meaning: "Close a TCP connection with nothing in or out this long (tcp only). `--tcp-idle-timeout`.",
    },
    KeyDoc {
        table: "frontend",
        key: "closed_session_grace",
        value: "seconds, 0 = for ever",
        default: || frontend().admission.closed_session_grace.to_string(),
        meaning: "How long the session of a client whose TCP connection closed waits for it (tcp only). `--closed-session-grace`.",
    },
];

/// The gateway file reference, as `docs/gateway.md` holds it: one table per section, then
/// the example file.
pub fn reference() -> String {
    let mut out = String::from(
        "<!-- Generated by `xrce-agent generate gateway-reference` from the gateway file's key\n     \
         table (deploy/src/gateway/keys.rs); do not edit (XRCE_WRITE_DOCS=1 cargo test -p\n     \
         xrce-agent --test docs_current rewrites it). -->\n\n\
         # The gateway file\n\n\
         `xrce-agent --config FILE` runs one DDS worker and one front-end process per \
         `[[frontend]]` of a TOML file; `xrce-agent --config FILE --check` checks it and prints \
         what it would run. An unknown key, a value of the wrong type or out of range, two \
         front-ends on one port or device are refused with the file's line and the key's \
         path (`frontend[0].port: expected a port number 1-65535, got \"x\"`).\n\n\
         A key left out means what its command-line option means when left out: the \
         option's environment variable if it is set (`XRCE_INSTANCE`, `XRCE_DDS_BACKEND`, \
         `XRCE_CLIENT_DEAD_TIME`, ...; `xrce-agent udp4 --help` names each one), else the \
         default below. `--check` checks the variables too.\n",
    );
    for (table, heading) in [
        ("agent", "`[agent]`: the agent as a whole"),
        ("worker", "`[worker]`: the DDS side"),
        ("metrics", "`[metrics]`: the metrics endpoint"),
        ("frontend", "`[[frontend]]`: one per interface or transport"),
    ] {
        out.push_str(&format!(
            "\n## {heading}\n\n| key | value | default | meaning |\n|---|---|---|---|\n"
        ));
        for k in KEYS.iter().filter(|k| k.table == table) {
            out.push_str(&format!(
                "| `{}` | {} | {} | {} |\n",
                k.key,
                k.value,
                (k.default)(),
                k.meaning
            ));
        }
    }
    out.push_str(
        "\n## An example\n\nThe example the package installs as `/etc/xrce-agent/gateway.toml` \
         (`deploy/gateway.example.toml`):\n\n```toml\n",
    );
    out.push_str(include_str!("../../gateway.example.toml"));
    out.push_str("```\n");
    out
}
