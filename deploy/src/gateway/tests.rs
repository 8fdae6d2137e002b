use super::*;

fn check(text: &str) -> Result<Gateway, ConfigError> {
    parse(Path::new("gw.toml"), text)
}

#[test]
fn the_documented_example_is_valid() {
    let g = check(
        r#"
[agent]
memory_limit_mib = 512
[worker]
dds_interfaces = ["127.0.0.1"]
[[frontend]]
transport = "udp4"
port = 8888
bind = "0.0.0.0"
discovery = 7400
[[frontend]]
transport = "serial"
device = "/dev/ttyACM0"
baudrate = 921600
[[frontend]]
transport = "multiserial"
devices = ["/dev/ttyUSB0", "/dev/ttyUSB1"]
baudrate = 115200
[[frontend]]
name = "companion"
id = 7
transport = "tcp6"
port = 9999
max_connections = 50
client_dead_time = 30
dialect = "spec"
allow_keys = ["0xAAAABBBB", "dead0001"]
allow_roaming = true
max_objects_per_client = 64
max_client_messages_per_second = 500
max_client_bytes_per_second = 100000
"#,
    )
    .expect("valid");
    assert_eq!(g.frontends.len(), 4);
    assert_eq!(
        g.agent.memory_limit_mib.as_ref().map(|m| *m.get_ref()),
        Some(512)
    );
    assert_eq!(g.frontends[0].name, "udp4-0");
    assert_eq!(g.frontends[1].id, 1);
    assert_eq!(g.frontends[3].name, "companion");
    assert_eq!(g.frontends[3].id, 7);
    let plan = crate::plan::AgentPlan::from_gateway(&g).expect("plan");
    let args = plan.frontends[3].settings().to_args();
    assert!(args.iter().any(|a| a == "--max-connections=50"));
    assert!(args.iter().any(|a| a == "--dialect=spec"));
    assert!(args.iter().any(|a| a == "--client-dead-time=30"));
    assert!(args
        .windows(2)
        .any(|w| w == ["--allow-keys", "0xAAAABBBB,0xDEAD0001"]));
    assert!(args.iter().any(|a| a == "--allow-roaming"));
    assert!(args
        .windows(2)
        .any(|w| w == ["--max-objects-per-client", "64"]));
    assert!(args
        .windows(2)
        .any(|w| w == ["--max-client-messages-per-second", "500"]));
    assert!(args
        .windows(2)
        .any(|w| w == ["--max-client-bytes-per-second", "100000"]));
    // The defaults add nothing.
    assert!(!plan.frontends[0]
        .settings()
        .to_args()
        .iter()
        .any(|a| a.starts_with("--allow") || a.starts_with("--max-client")));
}

fn refused(text: &str) -> ConfigError {
    check(text).expect_err("refused")
}

/// A value of the wrong type or out of range is refused naming the key by its path in
/// the file, what it expects in words, and what it got.
#[test]
fn wrong_values_name_the_key_and_what_it_expects() {
    let cases = [
            (
                "[agent]\nverbose = 1\n\n[[frontend]]\ntransport = \"udp4\"\nport = \"not a number\"\n",
                6,
                "frontend[0].port: expected a port number 1-65535, got \"not a number\"",
            ),
            (
                "[[frontend]]\ntransport = \"udp4\"\nport = 1\n[[frontend]]\ntransport = \"udp4\"\nport = 70000\n",
                6,
                "frontend[1].port: expected a port number 1-65535, got 70000",
            ),
            (
                "[agent]\nverbose = \"loud\"\n",
                2,
                "agent.verbose: expected a whole number 0-255, got \"loud\"",
            ),
            (
                "[worker]\nros_graph = \"yes\"\n",
                2,
                "worker.ros_graph: expected true or false, got \"yes\"",
            ),
            (
                "[worker]\ndds_interfaces = \"127.0.0.1\"\n",
                2,
                "worker.dds_interfaces: expected a list ([...]), got \"127.0.0.1\"",
            ),
            (
                "[[frontend]]\ntransport = \"udp4\"\nport = 1\nclient_dead_time = \"1s\"\n",
                4,
                "frontend[0].client_dead_time: expected a number, got \"1s\"",
            ),
        ];
    for (text, line, message) in cases {
        let e = refused(text);
        assert_eq!(
            e.to_string(),
            format!("gw.toml:{line}: {message}"),
            "{text}"
        );
    }
    // Port 0 and a grace out of range are refused too (by the checks after parsing).
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 0\n");
    assert!(e.message.contains("`port` must be 1 to 65535"), "{e}");
    assert_eq!(e.line, 3, "{e}");
    let e =
        refused("[worker]\nfrontend_grace = -1\n[[frontend]]\ntransport = \"pseudoterminal\"\n");
    assert!(
        e.message.contains("frontend_grace must be 0 to 86400"),
        "{e}"
    );
    assert_eq!(e.line, 2, "the key's line: {e}");
    let e = refused(
        "[agent]\nverbose = 1\n[worker]\nros_graph = true\nmax_samples = 0\n[[frontend]]\ntransport = \"pseudoterminal\"\n",
    );
    assert!(e.message.contains("max_samples must be at least 1"), "{e}");
    assert_eq!(e.line, 5, "the key's line: {e}");
    // An unknown key is named by its path, with the keys its table takes.
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 1\nprot = 2\n");
    assert!(
        e.message
            .starts_with("frontend[0].prot: unknown field `prot`, expected one of"),
        "{e}"
    );
}

#[test]
fn mistakes_are_refused_naming_the_key_and_line() {
    for (value, words) in [
        ("0", "`processes` must be 1 to 64, got 0"),
        ("65", "`processes` must be 1 to 64, got 65"),
        ("-1", "`processes` must be 1 to 64, got -1"),
        ("\"many\"", "(a count, or `auto`)"),
    ] {
        let e = refused(&format!(
            "[[frontend]]\ntransport = \"udp4\"\nport = 1\nprocesses = {value}\n"
        ));
        assert!(e.message.contains(words), "{value}: {e}");
        assert_eq!(e.line, 4, "{e}");
    }
    let e = refused("[[frontend]]\ntransport = \"tcp4\"\nport = 1\nprocesses = 2\n");
    assert!(e.message.contains("`processes` applies to udp only"), "{e}");
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 1\nprocesses = true\n");
    assert_eq!(e.line, 4, "{e}");
    assert!(e.message.contains("a count 1-64 or \"auto\""), "{e}");
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 1\nprot = 2\n");
    assert_eq!(e.line, 4, "{e}");
    assert!(e.to_string().contains("prot"), "{e}");
    let e = refused("[[frontend]]\ntransport = \"tcp4\"\n");
    assert!(e.to_string().contains("`port` is required"), "{e}");
    assert_eq!(e.line, 1, "{e}");
    let e = refused(
            "[[frontend]]\ntransport = \"udp4\"\nport = 1\nid = 3\n\n[[frontend]]\ntransport = \"udp4\"\nport = 2\nid = 3\n",
        );
    assert_eq!(e.line, 9, "{e}");
    assert!(e.to_string().contains("`id` 3 is also frontend 1's"), "{e}");
    let e = refused("[[frontend]]\ntransport = \"serial\"\ndevice = \"/dev/a\"\nport = 5\n");
    assert!(
        e.to_string().contains("`port` applies to udp and tcp only"),
        "{e}"
    );
    assert_eq!(e.line, 4);
    let e = refused("[[frontend]]\ntransport = \"can\"\n");
    assert!(e.to_string().contains("transport \"can\""), "{e}");
    let e = refused(
            "[[frontend]]\ntransport = \"udp4\"\nport = 8888\n[[frontend]]\ntransport = \"udp4\"\nport = 8888\nbind = \"127.0.0.1\"\n",
        );
    assert!(e.to_string().contains("also served by frontend 1"), "{e}");
    // TCP and UDP may share a port number.
    check("[[frontend]]\ntransport = \"udp4\"\nport = 8888\n[[frontend]]\ntransport = \"tcp4\"\nport = 8888\n")
            .expect("udp and tcp on one port number");
    let e = refused(
            "[[frontend]]\ntransport = \"serial\"\ndevice = \"/dev/a\"\n[[frontend]]\ntransport = \"multiserial\"\ndevices = [\"/dev/b\", \"/dev/a\"]\n",
        );
    assert!(e.to_string().contains("by frontend 1 too"), "{e}");
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 70000\n");
    assert_eq!(e.line, 3, "{e}");
    let e =
        refused("[worker]\nrefs = \"missing.xml\"\n[[frontend]]\ntransport = \"pseudoterminal\"\n");
    assert!(e.to_string().contains("worker.refs"), "{e}");
    assert_eq!(e.line, 2);
    let e = refused("[agent]\nverbose = 9\n[[frontend]]\ntransport = \"pseudoterminal\"\n");
    assert!(e.to_string().contains("verbose"), "{e}");
    let e =
        refused("[agent]\nmemory_limit_mib = 0\n[[frontend]]\ntransport = \"pseudoterminal\"\n");
    assert!(
        e.to_string().contains("memory_limit_mib must be 1 to"),
        "{e}"
    );
    assert_eq!(e.line, 2, "{e}");
    let e = refused("[worker]\n");
    assert!(e.to_string().contains("no [[frontend]]"), "{e}");
    let e = refused("[[frontend]]\ntransport = \"udp6\"\nport = 1\nbind = \"127.0.0.1\"\n");
    assert!(e.to_string().contains("not an address of udp6"), "{e}");
    let e =
        refused("[[frontend]]\ntransport = \"udp4\"\nport = 1\n\nallow_keys = [\"0xAAAABBB\"]\n");
    assert_eq!(e.line, 5, "{e}");
    assert!(
        e.to_string()
            .contains("`allow_keys` client key \"0xAAAABBB\""),
        "{e}"
    );
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 1\nallow_keys = []\n");
    assert!(e.to_string().contains("names no key"), "{e}");
    let e = refused("[[frontend]]\ntransport = \"udp4\"\nport = 1\nmax_objects_per_client = 0\n");
    assert!(e.to_string().contains("at least 1"), "{e}");
}

/// The keys the parser takes in `table`, from its refusal of an unknown one (serde lists the
/// keys it expects).
fn parser_keys(table: &str) -> Vec<String> {
    let text = if table == "frontend" {
        "[[frontend]]\ntransport = \"udp4\"\nport = 1\nno_such_key = 1\n".to_string()
    } else {
        format!("[{table}]\nno_such_key = 1\n")
    };
    let e = refused(&text);
    let expected = e
        .message
        .split_once("expected ")
        .map(|(_, rest)| rest)
        .unwrap_or_default();
    expected
        .split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect()
}

/// The reference's key table names exactly the keys the parser takes, table by table.
#[test]
fn the_key_reference_names_every_key_the_parser_takes() {
    for table in ["agent", "worker", "metrics", "frontend"] {
        let mut documented: Vec<String> = KEYS
            .iter()
            .filter(|k| k.table == table)
            .map(|k| k.key.to_string())
            .collect();
        let mut parsed = parser_keys(table);
        assert!(!parsed.is_empty(), "{table}");
        documented.sort();
        parsed.sort();
        assert_eq!(documented, parsed, "[{table}]");
    }
    let reference = reference();
    for k in KEYS {
        assert!(reference.contains(&format!("| `{}` |", k.key)), "{}", k.key);
    }
}
