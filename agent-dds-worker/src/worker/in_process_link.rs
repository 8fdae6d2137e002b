//! The link of a worker that runs inside its one front-end's process (`xrce-agent
//! --single-process`): replies and announcements wait in memory until the front-end's event
//! loop, the same thread, takes them; the replay marks are files in the instance's private
//! directory as for a worker of its own, because they are for the next process, which starts
//! after this one crashed.

use std::collections::{HashSet, VecDeque};

use xrce_ipc::{Encode, ReplyMessage, CHANNEL_DEPTH};

use super::link::{LinkError, ReplayMarks, WorkerLink};
use super::replay_guard::{CrashedReplays, ReplayMark};

/// The worker's end of an in-process front-end.
#[derive(Debug)]
pub struct InProcessLink {
    /// The one front-end: a reply meant for another (none is, unless by a defect) is dropped,
    /// counted and logged.
    frontend: u32,
    replies: VecDeque<Vec<u8>>,
    announcements: VecDeque<Vec<u8>>,
    marks: ReplayMarks,
    misdirected: u64,
}

impl InProcessLink {
    /// The link of front-end `frontend` in agent instance `instance`.
    pub fn new(instance: &str, frontend: u32) -> Self {
        InProcessLink {
            frontend,
            replies: VecDeque::new(),
            announcements: VecDeque::new(),
            marks: ReplayMarks::of(instance),
            misdirected: 0,
        }
    }

    /// Whether replies or announcements wait to be taken.
    pub fn has_messages(&self) -> bool {
        !self.replies.is_empty() || !self.announcements.is_empty()
    }

    /// Takes the replies waiting, oldest first.
    pub fn take_replies(&mut self) -> impl Iterator<Item = Vec<u8>> + '_ {
        self.replies.drain(..)
    }

    /// Takes the announcements waiting, oldest first.
    pub fn take_announcements(&mut self) -> impl Iterator<Item = Vec<u8>> + '_ {
        self.announcements.drain(..)
    }

    fn push(&mut self, frontend: u32, message: Vec<u8>) -> Result<bool, LinkError> {
        if frontend != self.frontend {
            self.misdirected += 1;
            // Logged at the first and then at each doubling (a defect, not a client's doing,
            // but the log must not grow with it).
            if self.misdirected.is_power_of_two() {
                tracing::warn!(
                    frontend,
                    misdirected = self.misdirected,
                    "a reply for a front-end this process is not dropped"
                );
            }
            return Err(LinkError::Unreachable {
                frontend,
                source: None,
            });
        }
        // The same depth as a reply queue in shared memory: a front-end that does not keep
        // up makes the worker hold the rest in its backlog, as between processes.
        if self.replies.len() >= CHANNEL_DEPTH {
            return Ok(false);
        }
        self.replies.push_back(message);
        Ok(true)
    }
}

impl WorkerLink for InProcessLink {
    fn send(&mut self, frontend: u32, reply: &ReplyMessage<'_>) -> Result<bool, LinkError> {
        self.push(frontend, reply.encode())
    }

    fn send_encoded(&mut self, frontend: u32, message: &[u8]) -> Result<bool, LinkError> {
        self.push(frontend, message.to_vec())
    }

    fn wake(&mut self, _frontend: u32) -> Result<(), LinkError> {
        // The front-end's loop reads the replies after every pass of the worker.
        Ok(())
    }

    fn announce(&mut self, message: &ReplyMessage<'_>) -> Result<(), LinkError> {
        self.announcements.push_back(message.encode());
        Ok(())
    }

    fn gone(&mut self, _served: &HashSet<u32>) -> HashSet<u32> {
        // The front-end is this process: it is never gone while the worker runs.
        HashSet::new()
    }

    fn forget(&mut self, _frontend: u32) {}

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

#[cfg(test)]
mod tests {
    use super::*;
    use xrce_ipc::{Reply, Route};

    fn hello() -> ReplyMessage<'static> {
        ReplyMessage {
            route: Route::frontend(3),
            reply: Reply::WorkerHello,
        }
    }

    #[test]
    fn replies_wait_for_the_front_end_up_to_a_queue_depth_and_go_nowhere_else() {
        let mut link = InProcessLink::new("in-process-link-test", 3);
        assert!(!link.has_messages());
        for _ in 0..CHANNEL_DEPTH {
            assert!(link.send(3, &hello()).expect("sent"));
        }
        assert!(
            !link.send(3, &hello()).expect("full"),
            "a full queue refuses"
        );
        assert!(matches!(
            link.send(4, &hello()),
            Err(LinkError::Unreachable { frontend: 4, .. })
        ));
        assert!(link.gone(&HashSet::from([3, 4])).is_empty());
        link.announce(&hello()).expect("announced");
        assert!(link.has_messages());
        assert_eq!(link.take_replies().count(), CHANNEL_DEPTH);
        assert_eq!(link.take_announcements().count(), 1);
        assert!(!link.has_messages());
    }
}
