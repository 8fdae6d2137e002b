//! What an operator sees, through real processes: the Prometheus endpoint and `/status`
//! while clients exchange samples, `xrce-agent status` reading them, restarts counted, and
//! the supervisor's watchdog restarting a front-end whose loop stopped, and its memory limit.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::Command;
use std::time::{Duration, Instant};

use xrce_tests::{
    binaries, free_tcp_port, free_udp_port, hello_world, sigkill, AgentProcess, Deliveries,
    TestClient,
};

const SECOND: Duration = Duration::from_secs(1);

/// `GET path` on the metrics endpoint: (status code, body).
fn get(port: u16, path: &str) -> Option<(u16, String)> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(5 * SECOND)).ok()?;
    write!(s, "GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").ok()?;
    let mut text = String::new();
    s.read_to_string(&mut text).ok()?;
    let code = text.split_whitespace().nth(1)?.parse().ok()?;
    let body = text.split_once("\r\n\r\n").map(|(_, b)| b.to_string())?;
    Some((code, body))
}

/// The value of the exposition's sample `name{labels}` (the whole text before the value).
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

/// Scrapes until `done` holds for the exposition, up to `d`; returns the last one.
fn scrape_until(port: u16, d: Duration, done: impl Fn(&str) -> bool) -> String {
    let end = Instant::now() + d;
    let mut last = String::new();
    while Instant::now() < end {
        if let Some((200, body)) = get(port, "/metrics") {
            if done(&body) {
                return body;
            }
            last = body;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    panic!("the metrics never showed what was expected; last scrape:\n{last}");
}

fn status_command(args: &[&str]) -> (Option<i32>, String, String) {
    let out = xrce_tests::output_within(
        Command::new(binaries().join("xrce-agent"))
            .arg("status")
            .args(args),
        30 * SECOND,
    );
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn metrics_and_status_show_the_clients_their_samples_and_the_restarts() {
    let port = free_udp_port().to_string();
    let metrics_port = free_tcp_port();
    let listen = format!("127.0.0.1:{metrics_port}");
    let agent = AgentProcess::builder("metrics")
        .command_line(&[
            "udp4",
            "-p",
            &port,
            "--bind",
            "127.0.0.1",
            "--metrics",
            &listen,
            // Far above what any process uses: nothing is killed for it.
            "--memory-limit",
            "4096",
        ])
        .launch()
        .expect("agent");
    let mut sub = TestClient::new(agent.addr(), [0x11, 0x11, 0x11, 0x78]);
    sub.connect(10 * SECOND);
    sub.setup_subscriber(78);
    let mut publ = TestClient::new(agent.addr(), [0x22, 0x22, 0x22, 0x78]);
    publ.connect(10 * SECOND);
    let w = publ.setup_publisher(78);
    for i in 0..30 {
        publ.write_reliable(w, &hello_world(i, "ops"));
        sub.step();
    }
    let got = Deliveries::collect(30, 30 * SECOND, || {
        publ.step();
        sub.step();
        sub.take_samples().into_iter().map(|(i, _)| i).collect()
    });
    got.assert_exactly_once(0..30, "samples between two clients");

    // The exposition: both sessions, the 30 samples each way, the processes.
    let labels = format!("{{frontend=\"udp4-{port}\",transport=\"udp4\"}}");
    // Everything the two clients sent was received (loopback loses nothing), counted once.
    let sent = (publ.sent + sub.sent) as f64;
    let text = scrape_until(metrics_port, 15 * SECOND, |t| {
        sample(t, &format!("xrce_samples_delivered_total{labels}")) == Some(30.0)
            && sample(t, &format!("xrce_messages_received_total{labels}")) == Some(sent)
    });
    assert_eq!(
        sample(&text, &format!("xrce_samples_delivered_total{labels}")),
        Some(30.0),
        "{text}"
    );
    assert_eq!(
        sample(&text, &format!("xrce_messages_received_total{labels}")),
        Some(sent),
        "{text}"
    );
    assert_eq!(sample(&text, &format!("xrce_sessions{labels}")), Some(2.0));
    assert_eq!(
        sample(&text, &format!("xrce_samples_written_total{labels}")),
        Some(30.0),
        "{text}"
    );
    assert_eq!(
        sample(&text, &format!("xrce_frontend_connected{labels}")),
        Some(1.0)
    );
    assert_eq!(sample(&text, "xrce_worker_restarts_total"), Some(0.0));
    assert_eq!(
        sample(&text, "xrce_memory_limit_kills_total{process=\"worker\"}"),
        Some(0.0),
        "{text}"
    );
    for process in ["supervisor", "worker", &format!("udp4-{port}")] {
        let rss = sample(
            &text,
            &format!("xrce_process_resident_memory_bytes{{process=\"{process}\"}}"),
        );
        assert!(rss.is_some_and(|v| v > 0.0), "memory of {process}: {text}");
    }
    assert!(text.contains("# TYPE xrce_sessions gauge"), "{text}");
    assert!(
        text.contains("# TYPE xrce_samples_written_total counter"),
        "{text}"
    );
    assert_eq!(get(metrics_port, "/nothing-here").map(|r| r.0), Some(404));

    // `xrce-agent status` from the endpoint: both keys (redacted: their last four digits
    // only), their samples; and as JSON, asked to show the keys whole.
    let (code, table, stderr) = status_command(&["--metrics", &format!("http://{listen}")]);
    assert_eq!(code, Some(0), "{stderr}");
    let row = |key: &str| {
        table
            .lines()
            .find(|l| l.starts_with(key))
            .unwrap_or_else(|| panic!("no row for {key} in:\n{table}"))
            .split_whitespace()
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    // CLIENT KEY, SESSION, FRONT-END, PEER, AGE, ENTITIES, SAMPLES IN, SAMPLES OUT, ...
    let subscriber = row("0x****1178");
    let publisher = row("0x****2278");
    assert!(!table.contains("0x11111178"), "a key shown whole:\n{table}");
    assert_eq!(
        subscriber[7], "30",
        "samples out to the subscriber: {table}"
    );
    assert_eq!(publisher[6], "30", "samples in from the publisher: {table}");
    assert_eq!(subscriber[2], format!("udp4-{port}/udp4"));
    assert!(subscriber[3].starts_with("127.0.0.1:"), "{table}");
    let (code, json, stderr) = status_command(&["--metrics", &listen, "--json", "--show-keys"]);
    assert_eq!(code, Some(0), "{stderr}");
    let doc: serde_json::Value = serde_json::from_str(&json).expect("status JSON");
    let keys: Vec<&str> = doc["processes"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|p| p["frontend"]["sessions"].as_array())
        .flatten()
        .filter_map(|s| s["client_key"].as_str())
        .collect();
    assert_eq!(keys, ["0x11111178", "0x22222278"]);

    // A worker killed is restarted and counted.
    let out = agent.output().clone();
    let mark = out.len();
    let worker = agent
        .child_pid_with("dds-worker", "dds-worker")
        .expect("worker pid");
    sigkill(worker);
    out.wait_for(mark, "restarted name=xrce-dds-worker", 20 * SECOND)
        .expect("worker not restarted");
    scrape_until(metrics_port, 15 * SECOND, |t| {
        sample(t, "xrce_worker_restarts_total") == Some(1.0)
    });
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_front_end_whose_loop_stops_is_killed_and_restarted() {
    let port = free_udp_port().to_string();
    let agent = AgentProcess::builder("stall")
        .command_line(&["udp4", "-p", &port, "--bind", "127.0.0.1"])
        .env(&[("XRCE_STALL_TIMEOUT", "3")])
        .launch()
        .expect("agent");
    let out = agent.output().clone();
    let frontend = agent
        .child_pid_with("frontend", "udp4")
        .expect("front-end pid");
    // Wait for its first report, so the supervisor knows it reports.
    let dir = xrce_ipc::status::status_dir(agent.instance());
    let end = Instant::now() + 20 * SECOND;
    while !xrce_ipc::status::read_reports(&dir)
        .iter()
        .any(|r| r.pid == frontend as u32)
    {
        assert!(Instant::now() < end, "the front-end never wrote a report");
        std::thread::sleep(Duration::from_millis(50));
    }
    let mark = out.len();
    // A stopped process is what a wedged loop looks like from outside: alive, silent.
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(frontend),
        nix::sys::signal::Signal::SIGSTOP,
    )
    .expect("SIGSTOP");
    out.wait_for(mark, "child stopped reporting", 20 * SECOND)
        .expect("the stopped front-end was not noticed");
    out.wait_for(mark, "restarted name=xrce-frontend", 20 * SECOND)
        .expect("the stopped front-end was not restarted");
    assert!(agent.ping(20 * SECOND), "not serving after the restart");
    let (code, table, stderr) = status_command(&["--instance", agent.instance()]);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(table.contains(&format!("udp4-{port}")), "{table}");
    assert!(agent.stop(), "agent did not stop cleanly");
}

#[test]
fn a_process_over_the_memory_limit_is_killed_and_restarted() {
    // Every process of an agent is over 1 MiB: each is killed and restarted, with back-off.
    let port = free_udp_port();
    let metrics_port = free_tcp_port();
    let instance = xrce_tests::unique_instance("memlimit");
    let args = [
        "udp4",
        "-p",
        &port.to_string(),
        "--bind",
        "127.0.0.1",
        "--dds-interface",
        "127.0.0.1",
        "--instance",
        &instance,
        "--metrics",
        &format!("127.0.0.1:{metrics_port}"),
        "--memory-limit",
        "1",
    ];
    let agent = AgentProcess::exactly(
        &args,
        "each process is restarted beyond this private resident memory",
        SocketAddr::new("127.0.0.1".parse().expect("address"), port),
        &instance,
    )
    .launch()
    .expect("agent");
    let out = agent.output().clone();
    for name in ["xrce-dds-worker", &format!("xrce-frontend-udp4-{port}")] {
        out.wait_for(
            0,
            &format!("over the memory limit; killing it to restart it name={name}"),
            20 * SECOND,
        )
        .unwrap_or_else(|| panic!("{name} was not killed for its memory"));
        out.wait_for(0, &format!("restarted name={name}"), 20 * SECOND)
            .unwrap_or_else(|| panic!("{name} was not restarted"));
    }
    let text = scrape_until(metrics_port, 20 * SECOND, |t| {
        sample(t, "xrce_memory_limit_kills_total{process=\"worker\"}").is_some_and(|v| v >= 2.0)
    });
    assert!(
        // The second restart may still wait for its back-off.
        sample(&text, "xrce_worker_restarts_total").is_some_and(|v| v >= 1.0),
        "{text}"
    );
    // The restarts back off (50 ms doubling up to 5 s): a crash loop, not a busy loop.
    out.wait_for(0, "(SIGKILL) restart_in=800ms", 30 * SECOND)
        .expect("the restarts did not back off");
    assert!(agent.stop(), "agent did not stop cleanly");
}
