//! Lifecycles of real clients, as their public sources have them, held to what the reference
//! agent does (issue 42):
//!
//! * micro-ROS (rmw_microxrcedds): binary representations, every CREATE flagged
//!   `UXR_REPLACE | UXR_REUSE`, one request per round trip, ids from a counter per kind, a
//!   session 0x81 with the board's key. A board that resets comes back without a DELETE,
//!   with the same key and session, and creates the same objects again; its serializer does
//!   not clear its buffer, so the alignment padding of the second round's descriptions holds
//!   other bytes. The objects are those of `wire-traces/microros-reset.txt` (a talker on
//!   `rt/chatter` with an `/add_two_ints` replier), byte for byte, padding included.
//! * PX4 (uxrce_dds_client): a session-less ping until the agent answers, a participant and
//!   its writers created with `UXR_REPLACE` only, best-effort data, a ping in session every
//!   second, and after missed pings a DELETE sent without waiting and everything created
//!   again with the same key.
//! * eProsima's examples: XML, `UXR_REPLACE`, a DELETE of the session at the end, which waits
//!   for its STATUS and retries once a second.
//!
//! Each runs through resets without DELETE, restarts of every process and impaired links
//! (a UDP relay that drops, duplicates and reorders; a serial line that flips bits), and
//! asserts every sample once, in order, at an independent Cyclone DDS reader. The time each
//! recovery takes is printed (`RECOVERY ...` lines, gathered in BENCHMARKS.md).

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use xrce_agent::plan::PROCESS_ID_STEP;
use xrce_agent::shared_port::member_for;
use xrce_common::session::client::{ClientConfig, ClientEvent};
use xrce_common::wire::{
    object_kind, status, stream_id, BaseObjectRequest, ClientKey, CreatePayload, Message, ObjectId,
    Payload, ReadSpecification, Representation, VariantExtra,
};
use xrce_tests::impaired::{Direction, ImpairedUdp, Impairment, NoisyLine};
use xrce_tests::link::Link;
use xrce_tests::{
    free_tcp_port, free_udp_port, parse_sample_line, sigkill, workspace, AgentProcess, DdsPeer,
    Deliveries, TestClient, DUPLICATE_GRACE,
};

const SECOND: Duration = Duration::from_secs(1);

/// The board's key and session in `microros-reset.txt`.
const MICRO_ROS_KEY: [u8; 4] = [0x00, 0xAB, 0x00, 0x01];

/// What a micro-ROS client sends to set its node up, in order.
#[derive(Clone)]
enum Setup {
    Create(CreatePayload),
    Read(BaseObjectRequest, ReadSpecification),
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
        .collect()
}

/// The talker's set-up of each round of `microros-reset.txt`: its CREATEs (decoded from the
/// captured bytes: the binary bodies keep their padding) and its READ_DATA on the replier,
/// with the participant moved to `domain` (each test has its own: they run side by side).
fn micro_ros_rounds(domain: i16) -> Vec<Vec<Setup>> {
    let path = workspace().join("common/tests/data/wire-traces/microros-reset.txt");
    let text = std::fs::read_to_string(path).expect("the micro-ROS trace");
    let mut ports: Vec<String> = Vec::new();
    let mut rounds: Vec<Vec<Setup>> = Vec::new();
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f[1] != "C>A" {
            continue;
        }
        let bytes = unhex(f[3]);
        let m = Message::decode(&bytes).expect("a client message");
        if m.header.stream_id != stream_id::BUILTIN_RELIABLE {
            continue;
        }
        let round = match ports.iter().position(|p| p == f[2]) {
            Some(i) => i,
            None => {
                ports.push(f[2].to_string());
                rounds.push(Vec::new());
                ports.len() - 1
            }
        };
        for s in m.submessages {
            match s.payload {
                Payload::Create(mut c) => {
                    if c.variant.kind == object_kind::PARTICIPANT {
                        c.variant.extra = VariantExtra::DomainId(domain);
                    }
                    rounds[round].push(Setup::Create(c))
                }
                Payload::ReadData(r) => rounds[round].push(Setup::Read(r.base, r.spec)),
                _ => {}
            }
        }
    }
    assert_eq!(rounds.len(), 2, "two rounds in the trace");
    for r in &rounds {
        assert!(
            r.iter().filter(|s| matches!(s, Setup::Create(_))).count() == 5,
            "five CREATEs a round"
        );
    }
    rounds
}

/// The data writer the talker writes with (`rt/chatter`).
fn talker_writer(setup: &[Setup]) -> ObjectId {
    setup
        .iter()
        .find_map(|s| match s {
            Setup::Create(c) if c.variant.kind == object_kind::DATAWRITER => Some(c.base.object_id),
            _ => None,
        })
        .expect("a data writer")
}

/// A client configured as the eProsima library micro-ROS builds on: CREATE_CLIENT retried
/// every second (`UXR_CONFIG_MIN_SESSION_CONNECTION_INTERVAL`), HEARTBEATs every 100 ms,
/// 4 messages of reliable history (`RMW_UXRCE_STREAM_HISTORY`).
fn micro_ros_config() -> ClientConfig {
    ClientConfig {
        output_window: 4,
        heartbeat_period: Duration::from_millis(100),
        connect_retry: SECOND,
        ..ClientConfig::new(ClientKey(MICRO_ROS_KEY))
    }
}

/// A `std_msgs/String` sample as rmw_microxrcedds serializes it (CDR, little endian).
fn ros_string(text: &str) -> Vec<u8> {
    let mut v = (text.len() as u32 + 1).to_le_bytes().to_vec();
    v.extend_from_slice(text.as_bytes());
    v.push(0);
    v
}

/// Connects and sets the talker up as rmw_microxrcedds does (one request per round trip);
/// returns each CREATE's status.
fn set_up_talker(c: &mut TestClient, setup: &[Setup]) -> Vec<u8> {
    c.connect(20 * SECOND);
    let mut statuses = Vec::new();
    for s in setup {
        match s {
            Setup::Create(p) => {
                let req = c
                    .client
                    .create(
                        Instant::now(),
                        p.base.object_id,
                        p.variant.clone(),
                        p.reuse,
                        p.replace,
                    )
                    .expect("create");
                statuses.push(c.wait_status(req, 20 * SECOND));
            }
            Setup::Read(base, spec) => {
                c.client
                    .read(Instant::now(), base.object_id, spec.clone())
                    .expect("read");
                c.step();
            }
        }
    }
    statuses
}

/// Reads `rt/chatter` (std_msgs/String) in `domain` with an independent Cyclone DDS reader,
/// which goes on past the `expected` count (a repeat must show, not end the reading).
fn chatter_reader(expected: usize, domain: i16) -> DdsPeer {
    DdsPeer::start(&[
        "read",
        "--domain",
        &domain.to_string(),
        "--ros-string",
        "--topic",
        "rt/chatter",
        "--count",
        &(10 * expected).to_string(),
        "--reliable",
        "--timeout",
        "120",
    ])
}

/// Samples the reader printed so far.
fn drain(reader: &DdsPeer, got: &mut Deliveries) -> Option<u32> {
    let mut last = None;
    while let Some(l) = reader.line(Duration::ZERO) {
        if let Some((i, _)) = parse_sample_line(&l) {
            got.record(i);
            last = Some(i);
        }
    }
    last
}

/// Where the board is when it resets, and what happened to the agent meanwhile.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reset {
    /// A reset from a new client port (a new socket or connection).
    NewPort,
    /// A reset from the port it had (a UDP stack with a fixed source port; a serial line).
    SamePort,
    /// The front-end was killed (and restarted by the supervisor) before the reset.
    FrontEndKilled,
    /// The worker was killed before the reset.
    WorkerKilled,
    /// The whole agent was killed and started again before the reset.
    AgentRestarted,
}

/// How the board reaches the agent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wire {
    Udp,
    /// A UDP port served by [`SHARED_PROCESSES`] front-end processes (`--processes`), the
    /// board at an address steered to the last of them.
    UdpShared,
    Tcp,
    Serial,
}

/// Front-end processes of [`Wire::UdpShared`]'s port.
const SHARED_PROCESSES: u16 = 3;

/// The board's address on [`Wire::UdpShared`]: one of 127.0.0.0/8 that the port's steering
/// gives to its last process (not the first, which has the front-end's own id and name).
fn shared_board_address() -> std::net::IpAddr {
    (2..=254u8)
        .map(|last| std::net::IpAddr::from([127, 0, 0, last]))
        .find(|a| member_for(*a, SHARED_PROCESSES) == SHARED_PROCESSES - 1)
        .expect("an address of the last process")
}

/// The agent under test and how a client reaches it.
struct Rig {
    wire: Wire,
    agent: Option<AgentProcess>,
    addr: SocketAddr,
    line: Option<xrce_tests::PtyPair>,
}

impl Drop for Rig {
    /// Stops the agent and removes its stored sessions (a test's agent leaves none behind).
    fn drop(&mut self) {
        if let Some(agent) = self.agent.take() {
            let clean = agent.stop();
            if !std::thread::panicking() {
                assert!(clean, "the agent did not stop cleanly");
            }
        }
    }
}

impl Rig {
    /// The agent at `addr` as this wire has it.
    fn agent_at(wire: Wire, addr: SocketAddr) -> AgentProcess {
        let processes = SHARED_PROCESSES.to_string();
        match wire {
            Wire::UdpShared => AgentProcess::at(addr)
                .extra(&["--processes", &processes])
                .start(),
            _ => AgentProcess::at(addr).start(),
        }
    }

    fn start(wire: Wire) -> Self {
        match wire {
            Wire::Udp | Wire::UdpShared => {
                let addr: SocketAddr = ([127, 0, 0, 1], free_udp_port()).into();
                let agent = Self::agent_at(wire, addr);
                Rig {
                    wire,
                    addr,
                    agent: Some(agent),
                    line: None,
                }
            }
            Wire::Tcp => {
                let port = free_tcp_port();
                let agent = AgentProcess::builder("life-tcp")
                    .command_line(&["tcp4", "-p", &port.to_string()])
                    .launch()
                    .expect("the TCP agent did not start");
                Rig {
                    wire,
                    addr: agent.addr(),
                    agent: Some(agent),
                    line: None,
                }
            }
            Wire::Serial => {
                let pty = xrce_tests::PtyPair::open();
                let dev = pty.slave_path.display().to_string();
                let agent = AgentProcess::builder("life-serial")
                    .command_line(&["serial", "--dev", &dev, "-b", "921600"])
                    .launch()
                    .expect("the serial agent did not start");
                Rig {
                    wire,
                    addr: agent.addr(),
                    agent: Some(agent),
                    line: Some(pty),
                }
            }
        }
    }

    fn agent(&self) -> &AgentProcess {
        self.agent.as_ref().expect("agent")
    }

    /// A board's link: a new socket or connection, or (`same`) the UDP port it had before.
    fn link(&self, before: Option<SocketAddr>, same: bool) -> Link {
        match self.wire {
            Wire::Udp => match before.filter(|_| same) {
                Some(local) => Link::udp_at(self.addr, local).expect("the board's old port"),
                None => Link::udp(self.addr),
            },
            Wire::UdpShared => match before.filter(|_| same) {
                Some(local) => Link::udp_at(self.addr, local).expect("the board's old port"),
                None => Link::udp_from(self.addr, shared_board_address()),
            },
            Wire::Tcp => Link::tcp(self.addr).expect("TCP connection"),
            Wire::Serial => {
                let line = self.line.as_ref().expect("pty");
                Link::serial(line.master.try_clone().expect("the line"), 1)
            }
        }
    }

    /// What happens to the agent before the board resets.
    fn before_reset(&mut self, reset: Reset) {
        let transport = match self.wire {
            Wire::Udp => "udp4".to_string(),
            // The board's process (its id, as its command line gives it).
            Wire::UdpShared => format!(
                "--frontend-id={} ",
                u32::from(SHARED_PROCESSES - 1) * PROCESS_ID_STEP
            ),
            Wire::Tcp => "tcp4".to_string(),
            Wire::Serial => "serial".to_string(),
        };
        match reset {
            Reset::NewPort | Reset::SamePort => {}
            Reset::FrontEndKilled => {
                let pid = self
                    .agent()
                    .child_pid_with("frontend", &transport)
                    .expect("the front-end");
                let from = self.agent().output().len();
                sigkill(pid);
                // The board comes back once the supervisor has the front-end serving again
                // (a TCP connection made to the dying one would only be reset).
                assert!(
                    self.agent()
                        .output()
                        .wait_for(from, "front-end serving again", 20 * SECOND)
                        .is_some(),
                    "the front-end was not restarted"
                );
            }
            Reset::WorkerKilled => {
                let pid = *self
                    .agent()
                    .child_pids("dds-worker")
                    .first()
                    .expect("the worker");
                sigkill(pid);
            }
            Reset::AgentRestarted => {
                assert!(
                    matches!(self.wire, Wire::Udp | Wire::UdpShared),
                    "restarted here on UDP only"
                );
                let old = self.agent.take().expect("agent");
                sigkill(old.pid() as i32);
                drop(old);
                // The same command line: it finds its predecessor's stored sessions.
                self.agent = Some(Self::agent_at(self.wire, self.addr));
            }
        }
    }
}

/// A micro-ROS talker that writes `per_round` strings, then resets as each of `resets` says
/// and creates its node again (with the other round's bytes: other padding), every CREATE
/// after the first round answered STATUS_OK_MATCHED; every string reaches a Cyclone DDS
/// reader once and in order. Prints the time from each reset to the first string of the
/// next round in DDS.
fn talker_resets(wire: Wire, domain: i16, resets: &[Reset], per_round: u32) {
    let rounds = micro_ros_rounds(domain);
    let writer = talker_writer(&rounds[0]);
    let total = per_round * (resets.len() as u32 + 1);
    let mut rig = Rig::start(wire);
    let reader = chatter_reader(total as usize, domain);
    let mut got = Deliveries::default();
    let mut link = Some(rig.link(None, false));
    let mut next = 0u32;
    for round in 0..=resets.len() {
        let mut c = TestClient::on_link(link.take().expect("link"), micro_ros_config());
        let reset_at = Instant::now();
        let statuses = set_up_talker(&mut c, &rounds[round % 2]);
        let created = reset_at.elapsed();
        // A TCP session ends with its connection when its front-end dies (a new
        // front-end has no connection to take over): there the objects are created again.
        let want =
            if round == 0 || (wire == Wire::Tcp && resets[round - 1] == Reset::FrontEndKilled) {
                status::OK
            } else {
                status::OK_MATCHED
            };
        assert_eq!(
            statuses,
            vec![want; statuses.len()],
            "{wire:?} round {round}: the statuses of the talker's CREATEs"
        );
        if round == 0 {
            assert!(
                reader
                    .wait_for("MATCHED", 30 * SECOND, || c.step())
                    .is_some(),
                "the Cyclone reader never matched the talker's writer"
            );
        }
        let first = next;
        let mut in_dds = None;
        let look = |got: &mut Deliveries, in_dds: &mut Option<Duration>| {
            drain(&reader, got);
            if in_dds.is_none() && got.count(first) > 0 {
                *in_dds = Some(reset_at.elapsed());
            }
        };
        for _ in 0..per_round {
            c.write_reliable(writer, &ros_string(&format!("Hello World: {next}")));
            next += 1;
            let pause = Instant::now() + Duration::from_millis(20);
            while Instant::now() < pause {
                c.step();
                look(&mut got, &mut in_dds);
            }
        }
        // Every string of the round in DDS before the next reset (the board keeps running).
        let end = Instant::now() + 30 * SECOND;
        while Instant::now() < end && (first..next).any(|i| got.count(i) == 0) {
            c.step();
            look(&mut got, &mut in_dds);
        }
        if round > 0 {
            println!(
                "RECOVERY micro-ros {wire:?} after {:?}: session and objects {} ms, first \
                 sample in DDS {} ms after the reset",
                resets[round - 1],
                created.as_millis(),
                in_dds.map_or(-1, |d| d.as_millis() as i64)
            );
        }
        let Some(&reset) = resets.get(round) else {
            break;
        };
        // The board runs on a moment (the agent learns that its readers acknowledged
        // everything: a crash meanwhile may repeat what they had not, by design).
        let settle = Instant::now() + Duration::from_millis(300);
        while Instant::now() < settle {
            c.step();
            drain(&reader, &mut got);
        }
        // The board goes silent (its socket closed) before the agent's trouble, and comes
        // back after it.
        let old = c.link.local_udp_addr();
        drop(c);
        rig.before_reset(reset);
        link = Some(rig.link(old, reset == Reset::SamePort));
    }
    // A late duplicate would show within the grace.
    let end = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < end {
        drain(&reader, &mut got);
        std::thread::sleep(Duration::from_millis(10));
    }
    got.assert_exactly_once(0..total, &format!("{wire:?}: the talker's strings"));
    got.assert_in_order(&format!("{wire:?}: the talker's strings"));
}

/// A UDP port served by three front-end processes: the board is served by the one its
/// address is steered to, so a reset from a new port finds its session and objects there
/// (every CREATE answered STATUS_OK_MATCHED; another process would create them anew), as
/// do its restarted successor and, after a restart of the whole agent, the process that
/// took its place (the sockets bound again in the same order).
#[test]
fn a_board_on_a_port_of_several_processes_keeps_its_process_through_resets() {
    talker_resets(
        Wire::UdpShared,
        140,
        &[
            Reset::NewPort,
            Reset::SamePort,
            Reset::FrontEndKilled,
            Reset::WorkerKilled,
            Reset::AgentRestarted,
            Reset::NewPort,
        ],
        10,
    );
}

/// The scenario: 15 strings, a reset from a new port, 15 more (the reference
/// delivers 30 of 30; this agent delivered 15 of them and none after the reset). Then the
/// board resets from its old port, after a front-end crash, after a worker crash and after
/// the whole agent was killed and started again.
#[test]
fn a_micro_ros_board_that_resets_keeps_publishing_over_udp() {
    talker_resets(
        Wire::Udp,
        143,
        &[
            Reset::NewPort,
            Reset::SamePort,
            Reset::FrontEndKilled,
            Reset::WorkerKilled,
            Reset::AgentRestarted,
        ],
        15,
    );
}

#[test]
fn a_micro_ros_board_that_resets_keeps_publishing_over_tcp() {
    talker_resets(
        Wire::Tcp,
        144,
        &[Reset::NewPort, Reset::FrontEndKilled, Reset::WorkerKilled],
        5,
    );
}

#[test]
fn a_micro_ros_board_that_resets_keeps_publishing_over_serial() {
    talker_resets(
        Wire::Serial,
        145,
        &[Reset::SamePort, Reset::FrontEndKilled, Reset::WorkerKilled],
        5,
    );
}

/// REUSE|REPLACE with another description replaces the data writer (STATUS_OK): the strings
/// written before and after the replacement reach DDS once each, in order.
#[test]
fn a_data_writer_replaced_by_a_new_description_loses_and_repeats_nothing() {
    let rounds = micro_ros_rounds(142);
    let writer = talker_writer(&rounds[0]);
    let rig = Rig::start(Wire::Udp);
    let reader = chatter_reader(20, 142);
    let mut c = TestClient::on_link(rig.link(None, false), micro_ros_config());
    assert!(set_up_talker(&mut c, &rounds[0])
        .iter()
        .all(|s| *s == status::OK));
    assert!(reader
        .wait_for("MATCHED", 30 * SECOND, || c.step())
        .is_some());
    let mut got = Deliveries::default();
    for i in 0..10 {
        c.write_reliable(writer, &ros_string(&format!("Hello World: {i}")));
    }
    // The same writer with a history of 7 instead of 10.
    let Some(Setup::Create(mut again)) = rounds[0]
        .iter()
        .find(|s| matches!(s, Setup::Create(p) if p.base.object_id == writer))
        .cloned()
    else {
        panic!("the writer's CREATE")
    };
    let Representation::Binary(body) = &again.variant.representation else {
        panic!("a binary writer")
    };
    let mut decoded =
        xrce_common::wire::binary::EndpointBinary::decode(body, true, true).expect("decodes");
    if let Some(q) = decoded.qos.as_mut() {
        q.base.history_depth = Some(7);
    }
    again.variant.representation = Representation::Binary(decoded.encode(true, true));
    let req = c
        .client
        .create(Instant::now(), writer, again.variant, true, true)
        .expect("create");
    assert_eq!(
        c.wait_status(req, 20 * SECOND),
        status::OK,
        "replaced, not matched"
    );
    for i in 10..20 {
        c.write_reliable(writer, &ros_string(&format!("Hello World: {i}")));
    }
    let end = Instant::now() + 30 * SECOND;
    while Instant::now() < end && got.distinct() < 20 {
        c.step();
        drain(&reader, &mut got);
    }
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        c.step();
        drain(&reader, &mut got);
    }
    got.assert_exactly_once(0..20, "strings around a replaced writer");
    got.assert_in_order("strings around a replaced writer");
}

/// PX4's uxrce_dds_client: a session-less ping until the agent answers, everything created
/// with REPLACE (participant by XML, the rest binary), best-effort data, a ping in session
/// every second; on three missed pings a DELETE sent once without waiting, then the same
/// again. Here the flight controller reboots (it says nothing) and the agent restarts under
/// it: its pings in session keep being answered as in session (the session was taken over),
/// and after its reboot its data flows again.
#[test]
fn a_px4_flight_controller_keeps_its_session_through_an_agent_restart_and_its_own_reboot() {
    let rounds = micro_ros_rounds(141);
    let mut rig = Rig::start(Wire::Udp);
    let reader = chatter_reader(1_000, 141);
    let key = ClientKey([0, 0, 0, 1]);
    let px4 = || ClientConfig {
        connect_retry: SECOND,
        heartbeat_period: Duration::from_millis(100),
        ..ClientConfig::new(key)
    };
    // Objects as PX4 creates them: REPLACE only (the talker's bodies serve as its topic).
    let replace_only: Vec<Setup> = rounds[0]
        .iter()
        .filter_map(|s| match s {
            Setup::Create(c)
                if c.variant.kind != object_kind::REPLIER
                    && c.variant.kind != object_kind::REQUESTER =>
            {
                Some(Setup::Create(CreatePayload {
                    reuse: false,
                    replace: true,
                    ..c.clone()
                }))
            }
            _ => None,
        })
        .collect();
    let writer = talker_writer(&replace_only);
    let mut got = Deliveries::default();
    let mut next = 0u32;
    let mut phase_started = Vec::new();
    for phase in 0..3 {
        let mut c = TestClient::on_link(rig.link(None, false), px4());
        // Session-less ping until the agent answers (uxr_ping_agent_attempts, 1 s, 1 try).
        let pinged = Instant::now();
        let mut answered = false;
        while !answered && pinged.elapsed() < 30 * SECOND {
            c.client.ping();
            answered = c.run_until(SECOND, |c| {
                c.events.iter().any(|e| matches!(e, ClientEvent::Info(_)))
            });
        }
        assert!(answered, "phase {phase}: the session-less ping");
        c.events.clear();
        let statuses = set_up_talker(&mut c, &replace_only);
        assert!(
            statuses.iter().all(|s| *s == status::OK),
            "phase {phase}: REPLACE re-creates: {statuses:?}"
        );
        if phase == 0 {
            assert!(reader
                .wait_for("MATCHED", 30 * SECOND, || c.step())
                .is_some());
        }
        phase_started.push(next);
        // 50 Hz best-effort for 2 s, a ping in session every second.
        let mut last_ping = Instant::now();
        let mut pongs = 0;
        for _ in 0..100 {
            c.write_best_effort(writer, &ros_string(&format!("Hello World: {next}")));
            next += 1;
            let t = Instant::now() + Duration::from_millis(20);
            while Instant::now() < t {
                c.step();
            }
            if last_ping.elapsed() >= SECOND {
                last_ping = Instant::now();
                c.client.ping();
            }
            pongs += c
                .events
                .iter()
                .filter(
                    |e| matches!(e, ClientEvent::Info(i) if i.result.implementation_status == 1),
                )
                .count();
            c.events.retain(|e| !matches!(e, ClientEvent::Info(_)));
            drain(&reader, &mut got);
        }
        assert!(pongs >= 1, "phase {phase}: no pong in session");
        if phase == 0 {
            // The agent restarted under the flight controller, which goes on.
            let restarted = Instant::now();
            rig.before_reset(Reset::AgentRestarted);
            let mut pong = false;
            while !pong && restarted.elapsed() < 10 * SECOND {
                c.client.ping();
                pong = c.run_until(SECOND, |c| {
                    c.events
                        .iter()
                        .any(|e| matches!(e, ClientEvent::Info(i) if i.result.implementation_status == 1))
                });
            }
            assert!(
                pong,
                "the session was not taken over: the ping says no session"
            );
            println!(
                "RECOVERY px4 agent restart: ping in session answered {} ms after the kill",
                restarted.elapsed().as_millis()
            );
        }
        // A reboot: nothing said, a new socket, the same key.
        drop(c);
    }
    let end = Instant::now() + 5 * SECOND;
    while Instant::now() < end {
        drain(&reader, &mut got);
        std::thread::sleep(Duration::from_millis(10));
    }
    // Best effort: nothing repeated, in order, and each phase's data in DDS.
    assert!(got.repeated().is_empty(), "repeated: {:?}", got.repeated());
    got.assert_in_order("PX4's samples");
    for (phase, first) in phase_started.iter().enumerate() {
        let arrived = (*first..first + 100).filter(|i| got.count(*i) > 0).count();
        assert!(
            arrived >= 90,
            "phase {phase}: {arrived} of 100 best-effort samples in DDS"
        );
    }
}

/// eProsima's `uxr_delete_session` waits up to a second for the STATUS of its DELETE and
/// tries 10 times. The agent's first STATUS lost, the next attempt meets a session that is
/// gone: it is answered (STATUS_OK, as the reference does) instead of dropped, so the client
/// finishes at its second attempt, not after ten seconds.
#[test]
fn a_delete_whose_reply_was_lost_is_answered_again() {
    let agent = AgentProcess::builder("life-del").start();
    let relay = ImpairedUdp::start(agent.addr(), Impairment::clean());
    let mut dropped = false;
    // The agent's first reply to a DELETE_CLIENT: a STATUS (0x05) on stream 0.
    relay.drop_when(move |dir, b| {
        let hit = dir == Direction::ToClient && b.len() > 8 && b[1] == 0 && b[4] == 0x05;
        let first = hit && !dropped;
        dropped |= hit;
        first
    });
    let mut c = TestClient::on_link(
        Link::udp(relay.addr()),
        ClientConfig {
            connect_retry: SECOND,
            ..ClientConfig::new(ClientKey(*b"DEL1"))
        },
    );
    c.connect(10 * SECOND);
    let started = Instant::now();
    let mut attempts = 0;
    let mut done = false;
    while !done && attempts < 10 {
        attempts += 1;
        let req = c
            .client
            .delete_session(Instant::now())
            .expect("DELETE_CLIENT");
        done = c.run_until(SECOND, |c| {
            c.events.iter().any(
                |e| matches!(e, ClientEvent::Status(s) if s.related.request_id == req && s.result.status == status::OK),
            )
        });
    }
    println!(
        "RECOVERY delete with its first reply lost: {attempts} attempts, {} ms",
        started.elapsed().as_millis()
    );
    assert!(done, "the DELETE was never answered");
    assert_eq!(attempts, 2, "answered at the second attempt");
    assert_eq!(relay.counts().ruled_out, 1);
    assert!(agent.stop(), "the agent did not stop cleanly");
}

/// A reliable publisher through a link that loses, duplicates and reorders: every sample
/// once and in order; the time it took is printed.
fn through_impaired_link(impairment: Impairment, domain: i16, what: &str, n: u32) {
    let agent = AgentProcess::builder("life-lossy").start();
    let relay = ImpairedUdp::start(agent.addr(), impairment);
    let reader = DdsPeer::start(&[
        "read",
        "--domain",
        &domain.to_string(),
        "--topic",
        &format!("lossy-{}", std::process::id()),
        "--count",
        &(10 * n).to_string(),
        "--reliable",
        "--timeout",
        "120",
    ]);
    let mut c = TestClient::on_link(
        Link::udp(relay.addr()),
        ClientConfig {
            connect_retry: SECOND,
            heartbeat_period: Duration::from_millis(100),
            output_window: 8,
            ..ClientConfig::new(ClientKey(*b"LOSS"))
        },
    );
    let started = Instant::now();
    c.connect(60 * SECOND);
    let topic = format!("lossy-{}", std::process::id());
    let w = c.setup_chain(
        domain,
        object_kind::PUBLISHER,
        object_kind::DATAWRITER,
        &format!(
            "<dds><data_writer><topic><kind>NO_KEY</kind><name>{topic}</name>\
             <dataType>HelloWorld</dataType></topic></data_writer></dds>"
        ),
    );
    let _ = c.run_until(5 * SECOND, |_| {
        reader
            .line(Duration::ZERO)
            .is_some_and(|l| l.starts_with("MATCHED"))
    });
    for i in 0..n {
        c.write_reliable(w, &xrce_tests::hello_world(i, what));
    }
    let mut got = Deliveries::default();
    let end = Instant::now() + 120 * SECOND;
    while Instant::now() < end
        && (got.distinct() < n as usize || c.client.unacked(stream_id::BUILTIN_RELIABLE) > 0)
    {
        c.step();
        drain(&reader, &mut got);
    }
    println!(
        "RECOVERY {what}: {n} reliable samples in {} ms ({:?})",
        started.elapsed().as_millis(),
        relay.counts()
    );
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        c.step();
        drain(&reader, &mut got);
    }
    got.assert_exactly_once(0..n, what);
    got.assert_in_order(what);
    assert!(agent.stop(), "the agent did not stop cleanly");
}

#[test]
fn a_link_losing_30_percent_each_way_loses_and_repeats_nothing() {
    through_impaired_link(Impairment::lossy(0.3, 42), 147, "30 % loss", 20);
}

#[test]
fn a_link_that_duplicates_and_reorders_loses_and_repeats_nothing() {
    through_impaired_link(
        Impairment {
            loss: 0.05,
            duplicate: 0.2,
            reorder: 0.2,
            hold: Duration::from_millis(30),
            seed: 7,
        },
        148,
        "20 % duplicates, 20 % reordered, 5 % lost",
        50,
    );
}

/// A serial line that flips one bit in about one byte of 400 (a frame in ten or so): the
/// framing's CRC drops the damaged frames, the reliable streams resend them, and the
/// talker's strings reach DDS once each, in order.
#[test]
fn a_serial_line_that_flips_bits_loses_and_repeats_nothing() {
    let line = NoisyLine::open(1.0 / 400.0, 11);
    let agent = AgentProcess::builder("life-noisy")
        .command_line(&["serial", "--dev", &line.agent_path, "-b", "115200"])
        .launch()
        .expect("the serial agent did not start");
    let rounds = micro_ros_rounds(146);
    let writer = talker_writer(&rounds[0]);
    let reader = chatter_reader(30, 146);
    let mut line = line;
    let end_file = line.client_end.take().expect("the client's end");
    let mut c = TestClient::on_link(Link::serial(end_file, 1), micro_ros_config());
    let statuses = set_up_talker(&mut c, &rounds[0]);
    assert!(statuses.iter().all(|s| *s == status::OK), "{statuses:?}");
    assert!(reader
        .wait_for("MATCHED", 30 * SECOND, || c.step())
        .is_some());
    let mut got = Deliveries::default();
    for i in 0..30 {
        c.write_reliable(writer, &ros_string(&format!("Hello World: {i}")));
        drain(&reader, &mut got);
    }
    let end = Instant::now() + 60 * SECOND;
    while Instant::now() < end && got.distinct() < 30 {
        c.step();
        drain(&reader, &mut got);
    }
    let grace = Instant::now() + DUPLICATE_GRACE;
    while Instant::now() < grace {
        c.step();
        drain(&reader, &mut got);
    }
    let (bytes, flipped) = line.counts();
    assert!(
        flipped > 0,
        "no bit flipped in {bytes} bytes: the line is not noisy"
    );
    got.assert_exactly_once(0..30, "strings over a noisy serial line");
    got.assert_in_order("strings over a noisy serial line");
    assert!(agent.stop(), "the agent did not stop cleanly");
}

/// A front-end that takes sessions over tells each client at once where its reliable
/// streams stand: a client that stays silent through a restart of the whole agent gets an
/// ACKNACK of its reliable stream from the new front-end without asking, so it resumes
/// inside its own timeouts (eProsima's example publisher ends its session when a sample
/// stays unconfirmed through its one-second window).
#[test]
fn an_agent_that_comes_back_tells_its_clients_where_their_streams_stand() {
    let mut rig = Rig::start(Wire::Udp);
    let mut c = TestClient::on_link(
        rig.link(None, false),
        ClientConfig {
            connect_retry: SECOND,
            ..ClientConfig::new(ClientKey(*b"BACK"))
        },
    );
    c.connect(10 * SECOND);
    let w = c.setup_publisher(149);
    c.write_reliable(w, &xrce_tests::hello_world(0, "before"));
    assert!(c.run_until(5 * SECOND, |c| c
        .client
        .unacked(stream_id::BUILTIN_RELIABLE)
        == 0));
    let killed = Instant::now();
    rig.before_reset(Reset::AgentRestarted);
    // Silent: nothing sent, only what arrives is looked at.
    let mut buf = vec![0u8; 65_536];
    let mut told = None;
    while told.is_none() && killed.elapsed() < 10 * SECOND {
        for m in c.link.receive(Duration::from_millis(10), &mut buf) {
            let Ok(msg) = Message::decode(&m) else {
                continue;
            };
            if msg
                .submessages
                .iter()
                .any(|s| matches!(&s.payload, Payload::Acknack(a) if a.stream_id == stream_id::BUILTIN_RELIABLE))
            {
                told = Some(killed.elapsed());
            }
        }
    }
    let told = told.expect("no ACKNACK from the agent that came back");
    println!(
        "RECOVERY agent restart: the client was told where its stream stands {} ms after the kill",
        told.as_millis()
    );
}

/// A front-end whose supervisor died keeps its port until the next supervisor starts:
/// datagrams meanwhile land in a socket, not on a closed port (whose ICMP errors eProsima's
/// client counts as time waited, so that it gave up before the agent was back), and the
/// next supervisor does not wait out the hold: it says it is there, and the port is let go.
#[test]
fn a_front_end_whose_supervisor_died_holds_its_port_for_the_successor() {
    let addr: SocketAddr = ([127, 0, 0, 1], free_udp_port()).into();
    let old = AgentProcess::at(addr).start();
    let probe = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
    probe.connect(addr).expect("connect");
    probe
        .set_read_timeout(Some(Duration::from_millis(100)))
        .expect("timeout");
    sigkill(old.pid() as i32);
    std::thread::sleep(Duration::from_millis(300));
    // Nothing answers, and nothing refuses: a closed port would draw ECONNREFUSED here.
    for _ in 0..3 {
        probe.send(b"ping?").expect("send");
        let mut buf = [0u8; 64];
        match probe.recv(&mut buf) {
            Err(e) => assert!(
                matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ),
                "the port was closed while the successor was not there yet: {e}"
            ),
            Ok(n) => panic!("the dying front-end answered: {:?}", &buf[..n]),
        }
    }
    let from = old.output().len();
    let next = AgentProcess::at(addr).start();
    assert!(
        old.output()
            .wait_for(from, "a successor waits: letting the port go", 10 * SECOND)
            .is_some(),
        "the old front-end did not see its successor"
    );
    assert!(next.stop(), "the successor did not stop cleanly");
    drop(old);
}
