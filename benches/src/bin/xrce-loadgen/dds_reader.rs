//! The independent DDS reader inside the generator: a RustDDS participant of its own, pinned
//! to loopback, reading the load topic, so the samples/s and latency *into DDS* (client →
//! agent → DDS) are measured by something that is not the agent.
//!
//! It is best-effort whatever the scenario: a reliable reader that falls behind (it shares
//! the generator's process) would hold back the agent's reliable writers (their send window
//! fills and `write()` blocks), disturbing what it measures. Its own losses are reported.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rustdds::mio1::{Events, Interest, Poll, Token};
use rustdds::{DomainParticipantBuilder, QosPolicyBuilder, TopicKind};
use xrce_dds_rustdds::raw::{RawLe, RawSample};

/// What the DDS reader saw.
#[derive(Debug)]
pub struct DdsCounts {
    /// Distinct measured samples (sequence numbers below the run's count).
    pub received: u64,
    /// Measured samples seen again.
    pub duplicates: u64,
    /// When the last measured sample arrived.
    pub last_rx: Option<Instant>,
    /// Latency from the client's send to the DDS reader, ns.
    pub latencies: hdrhistogram::Histogram<u64>,
    /// Which measured samples it got, by sequence number.
    pub seen: Vec<bool>,
}

/// A running DDS reader thread.
pub struct DdsReader {
    stop: Arc<AtomicBool>,
    probes: Arc<AtomicUsize>,
    counts: Arc<Mutex<Option<DdsCounts>>>,
    thread: Option<std::thread::JoinHandle<Result<(), String>>>,
}

/// What a reader counted so far: which measured samples and probes it saw, and when.
pub struct Tally {
    seen: Vec<bool>,
    heard: Vec<bool>,
    probes: Arc<AtomicUsize>,
    counts: DdsCounts,
}

impl Tally {
    fn new(samples: u32, publishers: usize, probes: Arc<AtomicUsize>) -> Result<Self, String> {
        Ok(Tally {
            seen: vec![false; samples as usize],
            heard: vec![false; publishers + 1],
            probes,
            counts: DdsCounts {
                received: 0,
                duplicates: 0,
                last_rx: None,
                latencies: hdrhistogram::Histogram::new_with_bounds(1, 60_000_000_000, 3)
                    .map_err(|e| e.to_string())?,
                seen: Vec::new(),
            },
        })
    }

    /// The counts, with which samples were seen.
    fn into_counts(self) -> DdsCounts {
        DdsCounts {
            seen: self.seen,
            ..self.counts
        }
    }

    /// Counts one sample body (sequence number, send time relative to `base`, padding).
    fn count(&mut self, body: &[u8], base: Instant) {
        let now_ns = base.elapsed().as_nanos() as u64;
        let (Some(seq), Some(ts)) = (body.get(..4), body.get(4..12)) else {
            return;
        };
        let seq = u32::from_le_bytes([seq[0], seq[1], seq[2], seq[3]]);
        let publishers = self.heard.len() - 1;
        if is_probe(seq, publishers) {
            let i = (u32::MAX - seq) as usize;
            if i < self.heard.len() && !self.heard[i] {
                self.heard[i] = true;
                self.probes.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        let Some(slot) = self.seen.get_mut(seq as usize) else {
            return;
        };
        let c = &mut self.counts;
        if *slot {
            c.duplicates += 1;
            return;
        }
        *slot = true;
        c.received += 1;
        c.last_rx = Some(Instant::now());
        let mut t = [0u8; 8];
        t.copy_from_slice(ts);
        let ns = now_ns.saturating_sub(u64::from_le_bytes(t)).max(1);
        let _ = c.latencies.record(ns.min(60_000_000_000));
    }
}

/// Probe samples carry `u32::MAX - publisher` as their sequence number.
pub fn is_probe(seq: u32, publishers: usize) -> bool {
    seq > u32::MAX - publishers as u32 - 1
}

impl DdsReader {
    /// Starts reading `topic` of type `type_name` in `domain`; measured samples are those
    /// with a sequence number below `samples`, their send time relative to `base`.
    pub fn start(
        domain: u16,
        topic: &str,
        type_name: &str,
        samples: u32,
        publishers: usize,
        base: Instant,
    ) -> Result<Self, String> {
        let stop = Arc::new(AtomicBool::new(false));
        let probes = Arc::new(AtomicUsize::new(0));
        let counts = Arc::new(Mutex::new(None));
        let dp = DomainParticipantBuilder::new(domain)
            .with_only_networks(vec![std::net::IpAddr::from([127, 0, 0, 1])])
            .build()
            .map_err(|e| format!("DDS participant: {e:?}"))?;
        let qos = QosPolicyBuilder::new()
            .best_effort()
            // Measured with 100 writers: with KEEP_ALL or a depth of 100,000 this reader fell
            // to a few hundred samples/s; with 1,000 it keeps up. It takes as they come.
            .history(rustdds::policy::History::KeepLast { depth: 1000 })
            .build();
        let t = dp
            .create_topic(topic.into(), type_name.into(), &qos, TopicKind::NoKey)
            .map_err(|e| format!("DDS topic: {e:?}"))?;
        let sub = dp
            .create_subscriber(&qos)
            .map_err(|e| format!("DDS subscriber: {e:?}"))?;
        let mut reader = sub
            .create_datareader_no_key::<RawSample, RawLe>(&t, Some(qos))
            .map_err(|e| format!("DDS reader: {e:?}"))?;
        let (stop2, probes2, counts2) = (stop.clone(), probes.clone(), counts.clone());
        let thread = std::thread::spawn(move || -> Result<(), String> {
            let _keep = (dp, sub, t);
            let mut poll = Poll::new().map_err(|e| e.to_string())?;
            poll.registry()
                .register(&mut reader, Token(0), Interest::READABLE)
                .map_err(|e| e.to_string())?;
            let mut events = Events::with_capacity(8);
            let mut tally = Tally::new(samples, publishers, probes2)?;
            while !stop2.load(Ordering::Relaxed) {
                let _ = poll.poll(&mut events, Some(Duration::from_millis(50)));
                while let Ok(Some(s)) = reader.take_next_sample() {
                    tally.count(&s.value().body, base);
                }
            }
            let c = tally.into_counts();
            if let Ok(mut g) = counts2.lock() {
                *g = Some(c);
            }
            Ok(())
        });
        Ok(DdsReader {
            stop,
            probes,
            counts,
            thread: Some(thread),
        })
    }

    /// Starts a Zenoh reader instead (`--zenoh-router`): a Zenoh router of its own listening
    /// on `endpoint`, which an agent on `-m zenoh` connects to, subscribing to the load
    /// topic's key in `domain` (`<domain>/LoadTopic/Load/*`: any type hash). Payloads carry
    /// the CDR encapsulation header before the body.
    pub fn start_zenoh(
        endpoint: &str,
        domain: u16,
        samples: u32,
        publishers: usize,
        base: Instant,
    ) -> Result<Self, String> {
        use zenoh::Wait as _;
        let stop = Arc::new(AtomicBool::new(false));
        let probes = Arc::new(AtomicUsize::new(0));
        let counts = Arc::new(Mutex::new(None));
        let mut config = zenoh::Config::default();
        for (k, v) in [
            ("mode", "\"router\"".to_string()),
            ("listen/endpoints", format!("[\"{endpoint}\"]")),
            ("scouting/multicast/enabled", "false".to_string()),
        ] {
            config
                .insert_json5(k, &v)
                .map_err(|e| format!("Zenoh configuration {k}: {e}"))?;
        }
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| format!("Zenoh router: {e}"))?;
        let tally = Arc::new(Mutex::new(Tally::new(samples, publishers, probes.clone())?));
        let in_callback = tally.clone();
        let subscriber = session
            .declare_subscriber(format!("{domain}/LoadTopic/Load/*"))
            .callback(move |s: zenoh::sample::Sample| {
                let payload = s.payload().to_bytes();
                if let (Some(body), Ok(mut t)) = (payload.get(4..), in_callback.lock()) {
                    t.count(body, base);
                }
            })
            .wait()
            .map_err(|e| format!("Zenoh subscriber: {e}"))?;
        let (stop2, counts2) = (stop.clone(), counts.clone());
        let thread = std::thread::spawn(move || -> Result<(), String> {
            while !stop2.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(20));
            }
            drop(subscriber);
            let _ = session.close().wait();
            // A callback that was running as the subscriber went may still hold the tally:
            // take its counts under the lock.
            let counts = {
                let mut t = tally
                    .lock()
                    .map_err(|_| "Zenoh reader counts poisoned".to_string())?;
                let empty = Tally::new(0, 0, Arc::new(AtomicUsize::new(0)))?;
                std::mem::replace(&mut *t, empty).into_counts()
            };
            if let Ok(mut g) = counts2.lock() {
                *g = Some(counts);
            }
            Ok(())
        });
        Ok(DdsReader {
            stop,
            probes,
            counts,
            thread: Some(thread),
        })
    }

    /// Publishers whose probe the DDS reader has received.
    pub fn probes_heard(&self) -> usize {
        self.probes.load(Ordering::Relaxed)
    }

    /// Stops the reader and returns its counts.
    pub fn finish(mut self) -> Result<DdsCounts, String> {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            t.join()
                .map_err(|_| "DDS reader thread panicked".to_string())??;
        }
        self.counts
            .lock()
            .map_err(|_| "DDS reader counts poisoned".to_string())?
            .take()
            .ok_or_else(|| "DDS reader left no counts".to_string())
    }
}

impl Drop for DdsReader {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}
