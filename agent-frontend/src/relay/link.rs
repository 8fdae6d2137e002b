//! Where the relay's requests go, and where the worker's replies come from: the one seam
//! between the relay's state machine and the shared memory of the process.
//!
//! * [`Link`]: what the relay needs to send (a request, and a wake-up of the worker).
//! * [`ShmLink`] and [`ShmInbox`]: the iceoryx2 services of a front-end (requests out; its
//!   reply service and the announcements in), opened together by [`open`].
//! * [`MemoryLink`]: requests kept in memory, for simulation tests of the relay.

use std::time::Instant;

use xrce_common::session::agent::{Agent, Endpoint};
use xrce_ipc::shm::{IpcNode, Receiver, Sender, ServiceKind, ShmError};
use xrce_ipc::{self as ipc, Encode, Request, RequestMessage, Route};

use super::Relay;

/// Why a link could not be opened or used.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The shared-memory services failed.
    #[error(transparent)]
    Shm(#[from] ShmError),
    /// Another live front-end of the instance has this id.
    #[error("front-end {id} already runs in agent instance {instance:?}; give each front-end its own id")]
    DuplicateId {
        /// The id.
        id: u32,
        /// The instance.
        instance: String,
    },
    /// A simulated failure ([`MemoryLink::fail`]).
    #[error("the link is down")]
    Down,
}

/// Where the relay's requests go.
pub trait Link {
    /// Hands `request` to the worker (encoding it in place where it can). An error leaves
    /// the request with the relay, which tries again later.
    fn send(&mut self, request: &RequestMessage<'_>) -> Result<(), LinkError>;
    /// Wakes the worker for what was sent since the last wake-up.
    fn wake(&mut self) -> Result<(), LinkError>;
}

/// The request side of a front-end's shared memory.
#[derive(Debug)]
pub struct ShmLink {
    requests: Sender,
}

impl Link for ShmLink {
    fn send(&mut self, request: &RequestMessage<'_>) -> Result<(), LinkError> {
        // Without a receiver (no worker yet, or its queue full) the request is dropped by
        // iceoryx2: the window keeps the queue from filling, and a worker that is not there
        // yet gets the replay when it comes.
        self.requests.send(request)?;
        Ok(())
    }

    fn wake(&mut self) -> Result<(), LinkError> {
        self.requests.notify()?;
        Ok(())
    }
}

/// The reply side of a front-end's shared memory: its reply service, the announcements, and
/// the node that holds them.
#[derive(Debug)]
pub struct ShmInbox {
    node: IpcNode,
    replies: Receiver,
    announce: Receiver,
}

/// Opens the services of front-end `frontend_id` in agent instance `instance`, as its process
/// `incarnation`, and asks any worker there for its hello.
pub fn open(
    instance: &str,
    frontend_id: u32,
    incarnation: u16,
) -> Result<(ShmLink, ShmInbox), LinkError> {
    let node = IpcNode::new(instance, &format!("xrce-frontend-{frontend_id}"))?;
    // Another live front-end with this id would lose its clients' entities to our hello: the
    // later one refuses to start.
    if node.older_namesakes() > 0 {
        return Err(LinkError::DuplicateId {
            id: frontend_id,
            instance: instance.to_string(),
        });
    }
    let replies = node.receiver(
        &ipc::reply_service(instance, frontend_id),
        ServiceKind::Reply,
    )?;
    let announce = node.receiver(&ipc::announce_service(instance), ServiceKind::Announce)?;
    let requests = node.sender(&ipc::request_service(instance), ServiceKind::Data)?;
    // Announcements made before we subscribed are not delivered (iceoryx2 hands history to
    // late subscribers only when the publisher next acts), so ask: a worker answers every
    // FrontendHello with its WorkerHello on our reply service. Our subscribers exist already,
    // so either this probe or the worker's own announcement reaches us.
    let probe = RequestMessage::new(
        Route {
            incarnation,
            ..Route::frontend(frontend_id)
        },
        Request::FrontendHello,
    );
    requests.send(&probe)?;
    requests.notify()?;
    Ok((
        ShmLink { requests },
        ShmInbox {
            node,
            replies,
            announce,
        },
    ))
}

impl ShmInbox {
    /// Whether SIGINT/SIGTERM arrived.
    pub fn termination_requested(&self) -> bool {
        self.node.termination_requested()
    }

    /// Descriptors to wait on: replies and announcements.
    pub fn raw_fds(&self) -> [i32; 2] {
        [self.replies.raw_fd(), self.announce.raw_fd()]
    }

    /// Hands `relay` the announcements and replies waiting (consuming their wake-ups when
    /// their descriptors were readable: `replies_ready`, `announce_ready`), straight from
    /// shared memory; then lets it apply the results to the session core.
    pub fn deliver<L: Link, A: Endpoint>(
        &self,
        now: Instant,
        relay: &mut Relay<L>,
        agent: &mut Agent<A>,
        replies_ready: bool,
        announce_ready: bool,
    ) {
        // Wake-ups are consumed only when there are some (a system call each time, and the
        // loop runs per datagram under load); the queues themselves are read every time.
        if announce_ready {
            self.announce.clear_events();
        }
        if let Err(e) = self.announce.drain(|m| relay.handle_announcement(m)) {
            tracing::warn!(error = %e, "receiving announcements failed");
        }
        if let Err(e) = self.replies.drain(|m| relay.handle_reply(now, m, agent)) {
            tracing::warn!(error = %e, "receiving from the worker failed");
        }
        if replies_ready {
            // After the drain, not before: by then the worker has finished notifying, and
            // iceoryx2 takes its one datagram with one `recv` (consumed at once, a second
            // `recv` failed on most wake-ups). Replies that came after the drain notified
            // nobody (folded into the notification consumed here): taken now.
            self.replies.clear_events();
            if let Err(e) = self.replies.drain(|m| relay.handle_reply(now, m, agent)) {
                tracing::warn!(error = %e, "receiving from the worker failed");
            }
        }
        relay.after_replies(now, agent);
    }
}

/// A link that keeps every request it is given, encoded, until taken: the worker's end of a
/// simulation.
#[derive(Debug, Default)]
pub struct MemoryLink {
    sent: Vec<Vec<u8>>,
    wakes: u64,
    down: bool,
}

impl MemoryLink {
    /// The requests sent since the last call, oldest first.
    pub fn take(&mut self) -> Vec<Vec<u8>> {
        std::mem::take(&mut self.sent)
    }

    /// How many wake-ups the worker got.
    pub fn wakes(&self) -> u64 {
        self.wakes
    }

    /// Makes every send and wake-up fail (`true`) or work again.
    pub fn fail(&mut self, down: bool) {
        self.down = down;
    }
}

impl Link for MemoryLink {
    fn send(&mut self, request: &RequestMessage<'_>) -> Result<(), LinkError> {
        if self.down {
            return Err(LinkError::Down);
        }
        self.sent.push(request.encode());
        Ok(())
    }

    fn wake(&mut self) -> Result<(), LinkError> {
        if self.down {
            return Err(LinkError::Down);
        }
        self.wakes += 1;
        Ok(())
    }
}
