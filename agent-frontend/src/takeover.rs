//! Sessions handed from one front-end process to the next: stored as they change
//! ([`persist`]), taken over when a front-end starts ([`take_over`]). A front-end killed
//! hard is restarted by the supervisor on the same socket or device, takes its clients'
//! sessions, objects and reads over, and replays the objects to the worker like after a
//! worker restart; the clients go on without re-creating anything.
//!
//! A client's state record is the session core's snapshot followed by its reads (with the
//! marks of what each read delivered, so a replayed read does not hand the client a sample
//! twice); its objects are stored apart, only when they change.

use std::time::{Duration, Instant};

/// How often output-side changes of sessions (output streams, reads' delivered marks) are
/// stored; input positions are stored at once. Zero: before the transmits of every loop
/// pass. (With 20 ms the short kill soak saw a repeat at the subscriber: output that left a
/// stream's queue after the last store went out again from the restored queue.)
pub const OUTPUT_STORE_PERIOD: Duration = Duration::ZERO;

use xrce_common::session::agent::Agent;
use xrce_common::session::graph::ObjectGraph;
use xrce_common::session::snapshot::SessionSnapshot;

use crate::relay::{Link, Relay};
use crate::session_store::SessionStore;
use crate::transport::{StoredEndpoint, Transport};

/// Stores what changed since the last call and forgets ended sessions. Sessions whose input
/// positions moved are stored after each client message (right after its operations went
/// to the worker: a crash in between makes the client resend one message, whose writes the
/// worker executed already; it tells the successor the last one it executed on each client
/// stream, [`xrce_ipc::Reply::Executed`], and the successor does not hand those over
/// again) and before anything acknowledges it; `with_output` also stores the
/// sessions whose output or reads changed (the event loop does so at most every
/// [`OUTPUT_STORE_PERIOD`]: a successor finds output state that much behind at worst, which
/// the clients' ACKNACKs correct). Changed objects are always stored.
pub fn persist<A: xrce_common::session::agent::Endpoint + StoredEndpoint>(
    store: &mut SessionStore,
    agent: &mut Agent<A>,
    relay: &mut Relay<impl Link>,
    with_output: bool,
) {
    let (mut changed, removed) = agent.take_session_changes(with_output);
    // Objects at once: a CREATE acknowledged must be found by a successor.
    let objects = relay.take_objects_changed();
    let reads = if with_output {
        relay.take_reads_changed()
    } else {
        Vec::new()
    };
    for key in removed {
        store.remove(key);
    }
    changed.extend(reads);
    changed.sort_unstable();
    changed.dedup();
    for key in objects {
        if let Some(g) = relay.graph(key) {
            // Not for a client whose connection dies with this process (TCP).
            let storable = agent
                .snapshot(key, |e| e.stored())
                .is_some_and(|s| !s.endpoint.is_empty());
            if storable {
                // No objects, no file.
                let encoded = if g.is_empty() {
                    Vec::new()
                } else {
                    g.encode_objects()
                };
                store.save_objects(key, &encoded);
                if !changed.contains(&key) {
                    changed.push(key);
                }
            }
        }
    }
    for key in changed {
        let Some(snapshot) = agent.snapshot(key, |e| e.stored()) else {
            continue;
        };
        if snapshot.endpoint.is_empty() {
            // Its connection dies with this process: nothing to take over.
            continue;
        }
        let Some(graph) = relay.graph(key) else {
            continue;
        };
        let snap = snapshot.encode();
        let reads = graph.encode_reads();
        let mut record = Vec::with_capacity(4 + snap.len() + reads.len());
        record.extend_from_slice(&(snap.len() as u32).to_le_bytes());
        record.extend_from_slice(&snap);
        record.extend_from_slice(&reads);
        store.save_state(key, &record);
        agent.set_stored_bytes(key, store.client_bytes(key) as usize);
    }
}

/// Takes over the sessions a predecessor stored; returns how many. Each goes to the core
/// (its streams where they were) and its graph to the relay, before the first worker is
/// seen, so the replay to it recreates the objects and restarts the reads.
pub fn take_over<T: Transport>(
    store: &mut SessionStore,
    now: Instant,
    agent: &mut Agent<T::Endpoint>,
    relay: &mut Relay<impl Link>,
    transport: &T,
) -> usize {
    let mut taken = 0;
    for stored in store.take_over() {
        let parsed = split_record(&stored.state).and_then(|(snap, reads)| {
            let snapshot = SessionSnapshot::decode(snap).ok()?;
            // No objects file: no objects.
            let objects = if stored.objects.is_empty() {
                ObjectGraph::default().encode_objects()
            } else {
                stored.objects
            };
            let graph = ObjectGraph::decode(&objects, reads).ok()?;
            Some((snapshot, graph))
        });
        let Some((snapshot, graph)) = parsed else {
            tracing::warn!(client = %stored.key, "stored session unreadable; the client will have to create it again");
            store.remove(stored.key);
            continue;
        };
        let endpoint = transport.decode_endpoint(&snapshot.endpoint);
        match endpoint {
            Some(e) if snapshot.key == stored.key && agent.restore(now, &snapshot, e) => {
                tracing::debug!(client = %snapshot.key, objects = graph.len(), reads = graph.reads().count(), "stored session taken over");
                relay.restore_graph(snapshot.key, graph);
                agent.set_stored_bytes(snapshot.key, store.client_bytes(snapshot.key) as usize);
                taken += 1;
            }
            _ => {
                tracing::warn!(client = %stored.key, "stored session does not fit this front-end's transport; not taken over");
                store.remove(stored.key);
            }
        }
    }
    taken
}

fn split_record(record: &[u8]) -> Option<(&[u8], &[u8])> {
    let len = u32::from_le_bytes(record.get(..4)?.try_into().ok()?) as usize;
    let snap = record.get(4..4 + len)?;
    Some((snap, &record[4 + len..]))
}
