//! The DDS worker bounded against hostile clients (issue 29 item 2), end to end: with default
//! options at most 8 distinct DDS domains are in use at once (a 9th is refused with
//! STATUS_ERR_RESOURCES), a worker killed and restarted takes every domain in use back from
//! the front-end's replay, and deleting the last participant of each domain gives the
//! domains' threads back. And a client's QoS cannot grow the worker (issue 43): a KEEP_ALL
//! reader with unlimited resource limits that never reads keeps a bounded cache.

use std::time::{Duration, Instant};

use xrce_common::wire::{object_kind as k, status, ObjectId, VariantExtra};
use xrce_tests::{rss_kib, sigkill, xml, AgentProcess, DdsPeer, TestClient};

/// Threads of process `pid`.
fn threads(pid: i32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .map(|d| d.count())
        .unwrap_or(0)
}

/// Steps every client until `done` or `d` passed; whether `done` came.
fn run_all(clients: &mut [TestClient], d: Duration, mut done: impl FnMut() -> bool) -> bool {
    let end = Instant::now() + d;
    while Instant::now() < end {
        for c in clients.iter_mut() {
            c.step();
        }
        if done() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    false
}

/// The first of this module's 8 consecutive domains (no other module uses them: the suite's
/// tests run side by side, `xrce_tests::domains`).
const FIRST_DOMAIN: i16 = 110;

#[test]
fn a_ninth_domain_is_refused_the_domains_survive_a_restart_and_deleted_ones_give_threads_back() {
    let agent = AgentProcess::builder("wbounds").start();
    let first_worker = *agent
        .child_pids("dds-worker")
        .first()
        .expect("the worker process");
    let idle = threads(first_worker);
    let participant = ObjectId::new(1, k::PARTICIPANT);
    let mut clients = Vec::new();
    for i in 0..8u8 {
        let mut c = TestClient::new(agent.addr(), [0x5b, 0x0d, 0, i]);
        c.connect(Duration::from_secs(10));
        c.setup_publisher(FIRST_DOMAIN + i16::from(i));
        clients.push(c);
    }
    let busy = threads(first_worker);
    assert!(
        busy > idle,
        "8 DDS domains cost threads ({idle} before, {busy} with them)"
    );

    // A 9th distinct domain is refused; a domain in use is not.
    let mut ninth = TestClient::new(agent.addr(), [0x5b, 0x0d, 0, 9]);
    ninth.connect(Duration::from_secs(10));
    let beyond = VariantExtra::DomainId(FIRST_DOMAIN + 8);
    assert_eq!(
        ninth.create(participant, k::PARTICIPANT, xml::PARTICIPANT, beyond),
        status::ERR_RESOURCES
    );
    let in_use = VariantExtra::DomainId(FIRST_DOMAIN);
    assert_eq!(
        ninth.create(participant, k::PARTICIPANT, xml::PARTICIPANT, in_use),
        status::OK
    );
    assert_eq!(
        threads(first_worker),
        busy,
        "a refused domain made no DDS participant"
    );
    clients.push(ninth);

    // The worker is killed; its successor gets every client's objects replayed, and admits
    // all 8 domains again (the old worker kept to the cap, so the replay fits in it).
    let mark = agent.output().len();
    sigkill(first_worker);
    let mut worker = None;
    let replaced = run_all(&mut clients, Duration::from_secs(60), || {
        worker = agent
            .child_pids("dds-worker")
            .into_iter()
            .find(|p| *p != first_worker);
        worker.is_some()
            && agent
                .output()
                .wait_for(mark, "in_use=8", Duration::ZERO)
                .is_some()
    });
    assert!(
        replaced,
        "the restarted worker took the 8 domains back from the replay"
    );
    let worker = worker.expect("the new worker");
    let ninth = clients.last_mut().expect("the ninth client");
    let another = ObjectId::new(2, k::PARTICIPANT);
    assert_eq!(
        ninth.create(another, k::PARTICIPANT, xml::PARTICIPANT, beyond),
        status::ERR_RESOURCES,
        "the cap holds after the restart"
    );

    // Every participant deleted: every domain released, its threads gone.
    for c in clients.iter_mut() {
        let req = c
            .client
            .delete(Instant::now(), participant)
            .expect("delete");
        assert_eq!(c.wait_status(req, Duration::from_secs(20)), status::OK);
    }
    let released = run_all(&mut clients, Duration::from_secs(20), || {
        threads(worker) <= idle
    });
    assert!(
        released,
        "the worker's threads went back to {idle} (now {})",
        threads(worker)
    );
    eprintln!(
        "worker threads: {idle} idle, {busy} with 8 domains, {} after they were released",
        threads(worker)
    );
    // Room again for a new domain.
    let ninth = clients.last_mut().expect("the ninth client");
    assert_eq!(
        ninth.create(another, k::PARTICIPANT, xml::PARTICIPANT, beyond),
        status::OK
    );
}

#[test]
fn a_keep_all_reader_with_unlimited_resources_that_never_reads_keeps_the_worker_bounded() {
    let domain = 120;
    let agent = AgentProcess::builder("keepall").start();
    let worker = *agent
        .child_pids("dds-worker")
        .first()
        .expect("the worker process");
    let mut c = TestClient::new(agent.addr(), *b"KALL");
    c.connect(Duration::from_secs(10));
    // KEEP_ALL and an empty <resourceLimitsQos/> (every limit unlimited), and no READ_DATA:
    // every sample stays in the DDS reader's cache unless the worker bounds it.
    let reader = "<dds><data_reader><topic><kind>NO_KEY</kind><name>HelloWorldTopic</name>\
        <dataType>HelloWorld</dataType></topic><qos><historyQos><kind>KEEP_ALL_HISTORY_QOS\
        </kind></historyQos><resourceLimitsQos/></qos></data_reader></dds>";
    c.setup_chain(domain, k::SUBSCRIBER, k::DATAREADER, reader);
    let before = rss_kib(worker);
    // 150,000 samples of about 1 KiB from an independent Cyclone DDS participant.
    let domain_arg = domain.to_string();
    let mut peer = DdsPeer::start(&[
        "write",
        "--domain",
        &domain_arg,
        "--best-effort",
        "--wait-match",
        "--count",
        "150000",
        "--interval-ms",
        "0",
        "--message",
        "x",
        "--message-repeat",
        "1024",
        "--linger-ms",
        "500",
        "--timeout",
        "60",
    ]);
    assert_eq!(
        peer.wait(Duration::from_secs(180), || {
            c.step();
        }),
        Some(0),
        "the DDS writer did not finish"
    );
    run_all(std::slice::from_mut(&mut c), Duration::from_secs(1), || {
        false
    });
    let grown = rss_kib(worker).saturating_sub(before);
    eprintln!("worker grew by {grown} KiB for 150,000 samples of 1 KiB not read");
    assert!(
        grown < 64 << 10,
        "the worker grew by {grown} KiB: the reader's cache is not bounded"
    );
    assert!(
        agent
            .output()
            .logged("QoS clamped", 1, xrce_tests::LOG_WAIT),
        "the clamp was not logged"
    );
    assert!(agent.stop(), "agent did not stop cleanly");
}

/// The worker's bounds are settings of the agent (here from the environment, as a unit's
/// `Environment=` gives them; the command line and a gateway file give the same, see
/// `deploy/src/plan.rs`): with 3 entities per client, a client's 4th is refused, and another
/// client still has its own 3.
#[test]
fn the_entity_bound_per_client_is_a_setting_of_the_agent() {
    let agent = AgentProcess::builder("entcap")
        .env(&[("XRCE_MAX_ENTITIES_PER_CLIENT", "3")])
        .start();
    let p = ObjectId::new(1, k::PARTICIPANT);
    let t = ObjectId::new(1, k::TOPIC);
    let g = ObjectId::new(1, k::PUBLISHER);
    let w = ObjectId::new(1, k::DATAWRITER);
    for key in [*b"ENT1", *b"ENT2"] {
        let mut c = TestClient::new(agent.addr(), key);
        c.connect(Duration::from_secs(10));
        let domain = VariantExtra::DomainId(119);
        assert_eq!(
            c.create(p, k::PARTICIPANT, xml::PARTICIPANT, domain),
            status::OK
        );
        assert_eq!(
            c.create(t, k::TOPIC, xml::TOPIC, VariantExtra::Parent(p)),
            status::OK
        );
        assert_eq!(
            c.create(g, k::PUBLISHER, "", VariantExtra::Parent(p)),
            status::OK
        );
        assert_eq!(
            c.create(w, k::DATAWRITER, xml::WRITER, VariantExtra::Parent(g)),
            status::ERR_RESOURCES,
            "the 4th entity of client {key:?}"
        );
    }
    assert!(agent.stop(), "agent did not stop cleanly");
}
