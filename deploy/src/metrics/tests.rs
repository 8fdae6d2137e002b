use super::*;
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::time::{Duration, Instant};
use xrce_ipc::status::{ChildStatus, FrontendStatus, WorkerStatus};

fn snapshot() -> AgentStatus {
    AgentStatus {
        instance: "t".into(),
        processes: vec![
            ProcessReport {
                name: "supervisor".into(),
                role: "supervisor".into(),
                children: vec![
                    ChildStatus {
                        name: "xrce-dds-worker".into(),
                        role: "worker".into(),
                        restarts: 2,
                        memory_kills: 1,
                        ..Default::default()
                    },
                    ChildStatus {
                        name: "xrce-frontend-udp4-8888".into(),
                        role: "frontend".into(),
                        restarts: 1,
                        ..Default::default()
                    },
                ],
                ..Default::default()
            },
            ProcessReport {
                name: "worker".into(),
                role: "worker".into(),
                pid: 2,
                cpu_seconds: 1.5,
                worker: Some(WorkerStatus {
                    entities: BTreeMap::from([("writer".to_string(), 3)]),
                    dropped: BTreeMap::from([("frontend_gone".to_string(), 1)]),
                    ..Default::default()
                }),
                ..Default::default()
            },
            ProcessReport {
                name: "udp4-8888".into(),
                role: "frontend".into(),
                pid: 3,
                resident_bytes: 4096,
                frontend: Some(FrontendStatus {
                    transport: "udp4".into(),
                    connected: true,
                    counters: BTreeMap::from([("samples_written".to_string(), 42)]),
                    dropped: BTreeMap::from([("bad_header".to_string(), 5)]),
                    sessions: vec![Default::default(), Default::default()],
                    ..Default::default()
                }),
                ..Default::default()
            },
        ],
    }
}

#[test]
fn the_exposition_names_counters_with_total_and_labels_them() {
    let text = render(&snapshot()).expect("render");
    for line in [
        "# TYPE xrce_sessions gauge",
        "xrce_sessions{frontend=\"udp4-8888\",transport=\"udp4\"} 2",
        "# TYPE xrce_samples_written_total counter",
        "xrce_samples_written_total{frontend=\"udp4-8888\",transport=\"udp4\"} 42",
        "xrce_samples_delivered_total{frontend=\"udp4-8888\",transport=\"udp4\"} 0",
        "xrce_dropped_total{process=\"udp4-8888\",reason=\"bad_header\"} 5",
        "xrce_dropped_total{process=\"worker\",reason=\"frontend_gone\"} 1",
        "xrce_worker_restarts_total 2",
        "xrce_memory_limit_kills_total{process=\"worker\"} 1",
        "xrce_frontend_restarts_total{frontend=\"udp4-8888\"} 1",
        "xrce_worker_entities{kind=\"writer\"} 3",
        "xrce_process_cpu_seconds_total{process=\"worker\"} 1.5",
        "xrce_process_resident_memory_bytes{process=\"udp4-8888\"} 4096",
        "xrce_frontend_connected{frontend=\"udp4-8888\",transport=\"udp4\"} 1",
    ] {
        assert!(
            text.lines().any(|l| l == line),
            "missing {line:?} in:\n{text}"
        );
    }
}

#[test]
fn a_frontend_is_connected_only_to_the_running_workers_generation() {
    let connected = |s: &AgentStatus| {
        let text = render(s).expect("render");
        let line = text
            .lines()
            .find(|l| l.starts_with("xrce_frontend_connected{"))
            .map(str::to_string);
        line.expect("connected gauge").ends_with(" 1")
    };
    let mut s = snapshot();
    let set = |s: &mut AgentStatus, fe: Option<u32>, worker: u32| {
        for p in &mut s.processes {
            if let Some(f) = &mut p.frontend {
                f.generation = fe;
            }
            if let Some(w) = &mut p.worker {
                w.generation = worker;
            }
        }
    };
    set(&mut s, Some(6), 6);
    assert!(connected(&s));
    // The worker was restarted and the front-end has not seen the new one yet.
    set(&mut s, Some(6), 7);
    assert!(!connected(&s));
    // The worker is gone (its report is read only while it lives).
    set(&mut s, Some(6), 6);
    s.processes.retain(|p| p.worker.is_none());
    assert!(!connected(&s));
}

/// A server on an ephemeral loopback port, serving for ever from a thread of its own,
/// with no report to read (its directory does not exist).
fn start() -> (SocketAddr, Arc<ServerStats>) {
    let dir = std::env::temp_dir().join(format!(
        "xrce-metrics-test-no-reports-{}",
        std::process::id()
    ));
    let listen = "127.0.0.1:0".parse().expect("address");
    let server = Server::bind(listen, "t", dir).expect("bind");
    let addr = server.local_addr().expect("bound address");
    let stats = server.stats();
    std::thread::spawn(move || server.run());
    (addr, stats)
}

/// Far longer than any deadline of the server: a test fails, it does not hang.
const CLIENT_TIMEOUT: Duration = Duration::from_secs(15);

/// Sends `request` on a new connection and reads the response until the server closes.
fn exchange(addr: SocketAddr, request: &[u8]) -> std::io::Result<String> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(CLIENT_TIMEOUT))?;
    s.write_all(request)?;
    let mut out = Vec::new();
    s.read_to_end(&mut out)?;
    Ok(String::from_utf8_lossy(&out).into_owned())
}

/// A response's head and body.
fn split(response: &str) -> (&str, &str) {
    response.split_once("\r\n\r\n").expect("a head and a body")
}

const SCRAPE: &[u8] = b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: */*\r\n\r\n";

#[test]
fn idle_connections_do_not_lock_a_scrape_out() {
    let (addr, stats) = start();
    let mut idle: Vec<TcpStream> = (0..40)
        .map(|_| TcpStream::connect(addr).expect("connect"))
        .collect();
    // The 41st connection, a scrape, is answered while the 40 are still open.
    let response = exchange(addr, SCRAPE).expect("the scrape is answered");
    assert!(response.starts_with("HTTP/1.1 200 OK\r\n"), "{response}");
    assert!(split(&response)
        .1
        .contains("xrce_metrics_connections_refused_total{reason=\"evicted\"}"));
    // At most MAX_CONNECTIONS were open when the scrape was: the others were closed to
    // make room (or, on a very slow machine, timed out).
    let closed = stats.refused(Refusal::Evicted) + stats.refused(Refusal::Timeout);
    assert!(
        closed >= (41 - MAX_CONNECTIONS) as u64,
        "only {closed} idle connections closed"
    );
    // And none of the idle ones holds a slot for long: each is closed by the server.
    for s in &mut idle {
        s.set_read_timeout(Some(CLIENT_TIMEOUT)).expect("timeout");
        let mut byte = [0u8; 1];
        match s.read(&mut byte) {
            Ok(0) => {}
            Ok(_) => panic!("an idle connection got data"),
            Err(e) => assert!(
                !matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ),
                "an idle connection is still open: {e}"
            ),
        }
    }
    assert!(stats.refused(Refusal::Evicted) + stats.refused(Refusal::Timeout) >= 40);
    assert_eq!(stats.refused(Refusal::Busy), 0);
}

#[test]
fn a_request_dribbled_byte_by_byte_is_cut_at_the_request_timeout() {
    let (addr, stats) = start();
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_millis(100)))
        .expect("timeout");
    let started = Instant::now();
    let mut closed = false;
    // A request line, a byte every 100 ms, never the blank line that ends the head.
    for &b in b"GET /metrics HTTP/1.1\r\nX-Slow: ".iter().cycle() {
        if started.elapsed() > CLIENT_TIMEOUT {
            break;
        }
        if s.write_all(&[b]).is_err() {
            closed = true;
            break;
        }
        let mut byte = [0u8; 1];
        match s.read(&mut byte) {
            Ok(0) => {
                closed = true;
                break;
            }
            Ok(_) => panic!("a partial request was answered"),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => {
                closed = true;
                break;
            }
        }
    }
    assert!(closed, "the server never closed a dribbling connection");
    assert!(stats.refused(Refusal::Timeout) >= 1);
}

#[test]
fn a_request_over_the_size_cap_is_refused() {
    let (addr, stats) = start();
    // A head that never ends within the cap.
    let mut request = b"GET /metrics HTTP/1.1\r\nX-Filler: ".to_vec();
    request.resize(MAX_REQUEST_BYTES + 1024, b'a');
    let response = exchange(addr, &request).expect("answered");
    assert!(
        response.starts_with("HTTP/1.1 431 "),
        "{}",
        &response[..response.len().min(200)]
    );
    assert!(
        !response.contains("xrce_"),
        "metrics sent to a refused request"
    );
    assert_eq!(stats.refused(Refusal::TooLarge), 1);
    // A whole head, but over the cap.
    request.extend_from_slice(b"\r\n\r\n");
    let response = exchange(addr, &request).expect("answered");
    assert!(response.starts_with("HTTP/1.1 431 "));
    assert_eq!(stats.refused(Refusal::TooLarge), 2);
    // Just under the cap is served.
    let mut request = b"GET /metrics HTTP/1.1\r\nX-Filler: ".to_vec();
    request.resize(MAX_REQUEST_BYTES - 4, b'a');
    request.extend_from_slice(b"\r\n\r\n");
    let response = exchange(addr, &request).expect("answered");
    assert!(response.starts_with("HTTP/1.1 200 OK\r\n"));
    assert_eq!(stats.refused(Refusal::TooLarge), 2);
}

#[test]
fn a_scrape_gets_the_metrics_text_and_the_status() {
    let (addr, stats) = start();
    let response = exchange(addr, SCRAPE).expect("answered");
    let (head, body) = split(&response);
    assert!(head.starts_with("HTTP/1.1 200 OK\r\n"), "{head}");
    let content_type = format!(
        "Content-Type: {}",
        prometheus_client::encoding::prometheus_text::CONTENT_TYPE
    );
    assert!(head.lines().any(|l| l == content_type), "{head}");
    assert!(head
        .lines()
        .any(|l| l == format!("Content-Length: {}", body.len())));
    assert!(head.lines().any(|l| l == "Connection: close"));
    for reason in ["busy", "evicted", "timeout", "too_large"] {
        let line = format!("xrce_metrics_connections_refused_total{{reason=\"{reason}\"}} 0");
        assert!(
            body.lines().any(|l| l == line),
            "missing {line:?} in:\n{body}"
        );
    }
    assert!(
        body.lines()
            .any(|l| l == "# TYPE xrce_metrics_connections_refused_total counter"),
        "{body}"
    );
    // The status document, query string ignored.
    let response = exchange(addr, b"GET /status?x=1 HTTP/1.0\r\n\r\n").expect("answered");
    let (head, body) = split(&response);
    assert!(head.starts_with("HTTP/1.1 200 OK\r\n"), "{head}");
    let status: AgentStatus = serde_json::from_str(body).expect("a status document");
    assert_eq!(status.instance, "t");
    // Anything else.
    let response = exchange(addr, b"GET /nothing HTTP/1.1\r\n\r\n").expect("answered");
    assert!(response.starts_with("HTTP/1.1 404 "));
    let response = exchange(addr, b"POST /metrics HTTP/1.1\r\n\r\n").expect("answered");
    assert!(response.starts_with("HTTP/1.1 405 "));
    let response = exchange(addr, b"\xff\xfe garbage\r\n\r\n").expect("answered");
    assert!(response.starts_with("HTTP/1.1 400 "));
    for r in Refusal::ALL {
        assert_eq!(stats.refused(r), 0, "{r:?}");
    }
}

#[test]
fn status_keys_are_redacted_unless_asked_for() {
    let mut s = snapshot();
    let key = |s: &AgentStatus| {
        s.processes
            .iter()
            .filter_map(|p| p.frontend.as_ref())
            .flat_map(|f| f.sessions.iter())
            .map(|x| x.client_key.clone())
            .collect::<Vec<_>>()
    };
    for p in &mut s.processes {
        if let Some(f) = &mut p.frontend {
            for x in &mut f.sessions {
                x.client_key = "0xAAAABBBB".into();
            }
        }
    }
    assert!(!key(&s).is_empty());
    s.redact_keys();
    assert!(key(&s).iter().all(|k| k == "0x****BBBB"), "{:?}", key(&s));
}

#[test]
fn the_status_document_round_trips() {
    let s = snapshot();
    let json = serde_json::to_string(&s).expect("encode");
    let back: AgentStatus = serde_json::from_str(&json).expect("decode");
    assert_eq!(back, s);
}
