//! The worker's outside, behind one seam: the front-ends' reply channels, the announcement a
//! new worker makes, which front-end processes are gone, and the marks a replay leaves for
//! the next worker.
//!
//! The worker ([`super::Worker`]) is sans-IO: it decides what to send and when, the link
//! carries it. [`ShmWorkerLink`] is the process's link (iceoryx2 shared memory and the
//! instance's private directory); [`MemoryWorkerLink`] keeps everything in memory, so the
//! worker's unit and simulation tests run without shared memory or files.

use std::collections::{HashMap, HashSet, VecDeque};
use std::path::PathBuf;

use xrce_common::wire::ClientKey;

use super::replay_guard::{CrashedReplays, ReplayMark};
use xrce_ipc::shm::{IpcNode, Receiver, Sender, ServiceKind, ShmError};
use xrce_ipc::{self as ipc, Encode, ReplyMessage};

/// Why the link could not carry something.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// A front-end's reply channel could not be opened: what was meant for it is lost.
    #[error(
        "front-end {frontend}'s reply channel could not be opened{}",
        .source.as_ref().map(|e| format!(": {e}")).unwrap_or_default()
    )]
    Unreachable {
        /// The front-end.
        frontend: u32,
        /// What failed (none: a simulated failure, [`MemoryWorkerLink::set_unreachable`]).
        #[source]
        source: Option<ShmError>,
    },
    /// The shared-memory services failed.
    #[error(transparent)]
    Shm(#[from] ShmError),
}

/// What the worker sends and asks of the world outside it.
pub trait WorkerLink {
    /// Puts `reply` in front-end `frontend`'s queue; `Ok(false)` when the queue is full (the
    /// worker keeps the reply and tries again once the front-end drained it).
    fn send(&mut self, frontend: u32, reply: &ReplyMessage<'_>) -> Result<bool, LinkError>;
    /// [`WorkerLink::send`] of a reply encoded earlier (one a full queue refused).
    fn send_encoded(&mut self, frontend: u32, message: &[u8]) -> Result<bool, LinkError>;
    /// Wakes front-end `frontend` for what was sent to it since its last wake-up.
    fn wake(&mut self, frontend: u32) -> Result<(), LinkError>;
    /// Announces `message` (the worker's hello) to every front-end, and wakes them.
    fn announce(&mut self, message: &ReplyMessage<'_>) -> Result<(), LinkError>;
    /// Which of the front-ends `served` have no live process any more.
    fn gone(&mut self, served: &HashSet<u32>) -> HashSet<u32>;
    /// The worker will send nothing more to `frontend` (gone for good): its channel closes.
    fn forget(&mut self, frontend: u32);
    /// Writes down that front-end `frontend` is replaying `client`'s objects now (`None`:
    /// its replay is over), for the next worker if this one dies meanwhile.
    fn mark_replay(&mut self, frontend: u32, mark: Option<ReplayMark>);
    /// The (front-end, client) pairs whose replay was under way when the last worker died
    /// (read once, at the start; the marks are gone afterwards).
    fn take_crashed_replays(&mut self) -> CrashedReplays;
}

/// The process's link: iceoryx2 services of the agent instance, and its private directory.
#[derive(Debug)]
pub struct ShmWorkerLink {
    node: IpcNode,
    instance: String,
    announce: Sender,
    /// Each front-end's reply channel, opened on first use.
    replies: HashMap<u32, Sender>,
    marks: ReplayMarks,
}

impl ShmWorkerLink {
    /// Opens the worker's services in agent instance `instance`: the link, and the receiver of
    /// the front-ends' requests (which the caller polls and drains).
    pub fn open(instance: &str) -> Result<(Self, Receiver), ShmError> {
        let node = IpcNode::new(instance, "xrce-dds-worker")?;
        let requests = node.receiver(&ipc::request_service(instance), ServiceKind::Data)?;
        let announce = node.sender(&ipc::announce_service(instance), ServiceKind::Announce)?;
        let link = ShmWorkerLink {
            node,
            instance: instance.to_string(),
            announce,
            replies: HashMap::new(),
            marks: ReplayMarks::of(instance),
        };
        Ok((link, requests))
    }

    /// Whether SIGINT or SIGTERM arrived.
    pub fn termination_requested(&self) -> bool {
        self.node.termination_requested()
    }

    /// Removes the shared-memory files of the instance's dead processes (a front-end killed
    /// since the last census would leave them behind a stopped agent); their names.
    pub fn remove_dead(&self) -> Vec<String> {
        self.node.nodes().dead
    }

    fn reply_channel(&mut self, frontend: u32) -> Result<&Sender, LinkError> {
        use std::collections::hash_map::Entry;
        match self.replies.entry(frontend) {
            Entry::Occupied(e) => Ok(e.into_mut()),
            Entry::Vacant(v) => {
                let service = ipc::reply_service(&self.instance, frontend);
                let sender = self
                    .node
                    .sender(&service, ServiceKind::Reply)
                    .map_err(|e| LinkError::Unreachable {
                        frontend,
                        source: Some(e),
                    })?;
                Ok(v.insert(sender))
            }
        }
    }
}

impl WorkerLink for ShmWorkerLink {
    fn send(&mut self, frontend: u32, reply: &ReplyMessage<'_>) -> Result<bool, LinkError> {
        Ok(self.reply_channel(frontend)?.send(reply)?)
    }

    fn send_encoded(&mut self, frontend: u32, message: &[u8]) -> Result<bool, LinkError> {
        Ok(self.reply_channel(frontend)?.send_encoded(message)?)
    }

    fn wake(&mut self, frontend: u32) -> Result<(), LinkError> {
        Ok(self.reply_channel(frontend)?.notify()?)
    }

    fn announce(&mut self, message: &ReplyMessage<'_>) -> Result<(), LinkError> {
        self.announce.send(message)?;
        Ok(self.announce.notify()?)
    }

    fn gone(&mut self, served: &HashSet<u32>) -> HashSet<u32> {
        let census = self.node.nodes();
        let alive: HashSet<&str> = census.alive.iter().map(String::as_str).collect();
        served
            .iter()
            .copied()
            .filter(|fe| !alive.contains(format!("xrce-frontend-{fe}").as_str()))
            .collect()
    }

    fn forget(&mut self, frontend: u32) {
        self.replies.remove(&frontend);
    }

    fn mark_replay(&mut self, frontend: u32, mark: Option<ReplayMark>) {
        match mark {
            Some(mark) => self.marks.write(frontend, mark),
            None => self.marks.remove(frontend),
        }
    }

    fn take_crashed_replays(&mut self) -> CrashedReplays {
        self.marks.take()
    }
}

/// Prefix of the replay marks in the instance directory (`replaying-<front-end>`, holding
/// the 4 octets of the client key and one of the workers in a row dead replaying it; a mark
/// of 4 octets, from an agent before, counts one).
const MARK: &str = "replaying-";

/// The replay marks of an instance ([`super::replay_guard`]): one file per front-end
/// replaying, naming the client whose objects it is replaying.
#[derive(Debug)]
pub(super) struct ReplayMarks {
    dir: PathBuf,
}

impl ReplayMarks {
    /// The marks in agent instance `instance`'s private directory.
    pub(super) fn of(instance: &str) -> Self {
        ReplayMarks {
            dir: xrce_ipc::runtime_dir::instance_dir(instance),
        }
    }

    /// Reads and removes the marks a worker that died left.
    pub(super) fn take(&self) -> CrashedReplays {
        let mut found = CrashedReplays::new();
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return found;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let Some(fe) = name.strip_prefix(MARK).and_then(|f| f.parse::<u32>().ok()) else {
                continue;
            };
            // Read only if it is the agent user's own regular file, and 4 or 5 octets.
            if let Ok(bytes) = xrce_ipc::runtime_dir::read_owned(&e.path(), 5) {
                let deaths = match bytes.get(4) {
                    Some(d) => (*d).max(1),
                    None => 1,
                };
                if let Some(key) = bytes.get(..4).and_then(|k| <[u8; 4]>::try_from(k).ok()) {
                    found.insert((fe, ClientKey(key)), deaths);
                }
            }
            let _ = std::fs::remove_file(e.path());
        }
        found
    }

    pub(super) fn write(&self, frontend: u32, mark: ReplayMark) {
        let path = self.dir.join(format!("{MARK}{frontend}"));
        let tmp = self
            .dir
            .join(format!(".{MARK}{frontend}.{}", std::process::id()));
        let [a, b, c, d] = mark.client.0;
        let bytes = [a, b, c, d, mark.deaths];
        if let Err(e) = xrce_ipc::runtime_dir::write_atomically(&path, &tmp, &bytes) {
            tracing::debug!(error = %e, "replay mark not written");
        }
    }

    pub(super) fn remove(&self, frontend: u32) {
        let _ = std::fs::remove_file(self.dir.join(format!("{MARK}{frontend}")));
    }
}

/// A link in memory: each front-end's queue of encoded replies (optionally bounded, to
/// simulate a congested front-end), its wake-ups, the announcements, the front-ends whose
/// process is gone, and the replay marks (which a link made by
/// [`MemoryWorkerLink::after_crash`] hands to the next worker).
#[derive(Debug, Default)]
pub struct MemoryWorkerLink {
    queues: HashMap<u32, VecDeque<Vec<u8>>>,
    /// Most replies a front-end's queue holds (`None`: no bound).
    capacity: Option<usize>,
    woken: HashSet<u32>,
    announced: Vec<Vec<u8>>,
    gone: HashSet<u32>,
    forgotten: HashSet<u32>,
    marks: HashMap<u32, ReplayMark>,
    crashed_replays: CrashedReplays,
    unreachable: HashSet<u32>,
}

impl MemoryWorkerLink {
    /// A link whose front-end queues hold at most `capacity` replies each.
    pub fn bounded(capacity: usize) -> Self {
        MemoryWorkerLink {
            capacity: Some(capacity),
            ..Default::default()
        }
    }

    /// The link the next worker finds once this one's process died: the replay marks left
    /// are its crashed replays; the front-ends are as they were (bounds, gone, unreachable);
    /// what waited in their queues died with the worker.
    pub fn after_crash(&self) -> Self {
        MemoryWorkerLink {
            capacity: self.capacity,
            gone: self.gone.clone(),
            unreachable: self.unreachable.clone(),
            crashed_replays: self
                .marks
                .iter()
                .map(|(fe, m)| ((*fe, m.client), m.deaths))
                .collect(),
            ..Default::default()
        }
    }

    /// Takes what front-end `frontend`'s queue holds, oldest first.
    pub fn take(&mut self, frontend: u32) -> Vec<Vec<u8>> {
        self.queues
            .get_mut(&frontend)
            .map(|q| q.drain(..).collect())
            .unwrap_or_default()
    }

    /// Whether `frontend` was woken since the last call.
    pub fn take_wake(&mut self, frontend: u32) -> bool {
        self.woken.remove(&frontend)
    }

    /// The announcements made, encoded.
    pub fn announced(&self) -> &[Vec<u8>] {
        &self.announced
    }

    /// Front-end `frontend`'s process is gone (`true`) or back.
    pub fn set_gone(&mut self, frontend: u32, gone: bool) {
        if gone {
            self.gone.insert(frontend);
        } else {
            self.gone.remove(&frontend);
        }
    }

    /// Whether the worker let go of `frontend`'s channel.
    pub fn forgotten(&self, frontend: u32) -> bool {
        self.forgotten.contains(&frontend)
    }

    /// The replay marks standing now.
    pub fn marks(&self) -> HashMap<u32, ClientKey> {
        self.marks.iter().map(|(fe, m)| (*fe, m.client)).collect()
    }

    /// Front-end `frontend`'s channel cannot be opened (`true`: what is sent to it fails
    /// with [`LinkError::Unreachable`]) or can again.
    pub fn set_unreachable(&mut self, frontend: u32, unreachable: bool) {
        if unreachable {
            self.unreachable.insert(frontend);
        } else {
            self.unreachable.remove(&frontend);
        }
    }

    fn reach(&mut self, frontend: u32) -> Result<(), LinkError> {
        if self.unreachable.contains(&frontend) {
            return Err(LinkError::Unreachable {
                frontend,
                source: None,
            });
        }
        // Sent to again: its channel is open again.
        self.forgotten.remove(&frontend);
        Ok(())
    }

    fn push(&mut self, frontend: u32, message: Vec<u8>) -> Result<bool, LinkError> {
        self.reach(frontend)?;
        let queue = self.queues.entry(frontend).or_default();
        if self.capacity.is_some_and(|c| queue.len() >= c) {
            return Ok(false);
        }
        queue.push_back(message);
        Ok(true)
    }
}

impl WorkerLink for MemoryWorkerLink {
    fn send(&mut self, frontend: u32, reply: &ReplyMessage<'_>) -> Result<bool, LinkError> {
        self.push(frontend, reply.encode())
    }

    fn send_encoded(&mut self, frontend: u32, message: &[u8]) -> Result<bool, LinkError> {
        self.push(frontend, message.to_vec())
    }

    fn wake(&mut self, frontend: u32) -> Result<(), LinkError> {
        self.reach(frontend)?;
        self.woken.insert(frontend);
        Ok(())
    }

    fn announce(&mut self, message: &ReplyMessage<'_>) -> Result<(), LinkError> {
        self.announced.push(message.encode());
        Ok(())
    }

    fn gone(&mut self, served: &HashSet<u32>) -> HashSet<u32> {
        served.intersection(&self.gone).copied().collect()
    }

    fn forget(&mut self, frontend: u32) {
        // What it did not read stays in its queue, as in shared memory.
        self.forgotten.insert(frontend);
    }

    fn mark_replay(&mut self, frontend: u32, mark: Option<ReplayMark>) {
        match mark {
            Some(m) => self.marks.insert(frontend, m),
            None => self.marks.remove(&frontend),
        };
    }

    fn take_crashed_replays(&mut self) -> CrashedReplays {
        std::mem::take(&mut self.crashed_replays)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replay_marks_are_read_once_by_the_next_worker() {
        let dir = std::env::temp_dir().join(format!("xrce-replay-marks-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let marks = ReplayMarks { dir: dir.clone() };
        let mark = |key: &[u8; 4], deaths| ReplayMark {
            client: ClientKey(*key),
            deaths,
        };
        marks.write(3, mark(b"AAAA", 1));
        marks.write(3, mark(b"BBBB", 2));
        marks.write(4, mark(b"CCCC", 1));
        marks.remove(4);
        std::fs::write(dir.join("replaying-x"), b"DDDD").expect("a stray file");
        std::fs::write(dir.join("replaying-5"), b"too long").expect("a bad mark");
        // An agent before wrote the key alone: one death.
        std::fs::write(dir.join("replaying-6"), b"EEEE").expect("an old mark");
        let taken = marks.take();
        assert_eq!(
            taken,
            CrashedReplays::from([((3, ClientKey(*b"BBBB")), 2), ((6, ClientKey(*b"EEEE")), 1)])
        );
        assert!(marks.take().is_empty(), "read once");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
