//! The event loop's seam to the DDS worker: what the loop waits on for it, when it wants the
//! loop without an event, and how the worker's answers reach the relay.
//!
//! Two sides implement it:
//! * [`ShmInbox`]: the worker is another process; requests go through iceoryx2 shared
//!   memory ([`crate::relay::link::ShmLink`]) and replies come back the same way, each
//!   direction with a wake-up of the other process;
//! * the worker in this same process (`xrce-agent --single-process`, in the `xrce-agent`
//!   crate, which depends on both front-end and worker): the worker is the relay's link, so a
//!   request is executed as it is handed over, in the loop's own thread, and the replies are
//!   read back in the same loop pass, without a process hop.

use std::time::Instant;

use mio::event::Event;
use mio::unix::SourceFd;
use mio::{Interest, Registry, Token};
use xrce_common::session::agent::{Agent, Endpoint};

use crate::relay::link::{Link, ShmInbox, ShmLink};
use crate::relay::Relay;

/// The worker as the front-end's event loop sees it.
pub trait WorkerSide {
    /// Where the relay's requests go.
    type Link: Link;
    /// Registers what the loop waits on for the worker, with tokens from `first` up to (not
    /// including) `end`. Called before every wait: a side whose descriptors come and go
    /// (a DDS backend made later) registers the new ones then.
    fn register(
        &mut self,
        registry: &Registry,
        tokens: (Token, Token),
        relay: &Relay<Self::Link>,
    ) -> std::io::Result<()>;
    /// One of the side's descriptors is ready.
    fn on_event(&mut self, event: &Event);
    /// The loop's wait ended with nothing ready after a wait of at least
    /// [`IDLE_WAIT`](crate::event_loop) (the side may consume wake-ups it missed).
    fn on_idle(&mut self);
    /// Whether SIGINT/SIGTERM arrived.
    fn termination_requested(&self) -> bool;
    /// When the side wants the loop again if nothing comes meanwhile (`None`: not before
    /// something comes).
    fn poll_timeout(&self, now: Instant, relay: &Relay<Self::Link>) -> Option<Instant>;
    /// Hands `relay` what the worker answered (and the announcements of new workers), then
    /// lets it apply the results to the session core. An error ends the front-end.
    fn deliver<A: Endpoint>(
        &mut self,
        now: Instant,
        relay: &mut Relay<Self::Link>,
        agent: &mut Agent<A>,
    ) -> anyhow::Result<()>;
    /// Once per loop pass, after the transmits: the side's own periodic work (a status
    /// report).
    fn maintain(&mut self, now: Instant, relay: &Relay<Self::Link>);
    /// The front-end stops serving (SIGINT/SIGTERM, or an error): what the side must finish
    /// first.
    fn stop(&mut self, relay: &mut Relay<Self::Link>);
}

/// The two tokens of an inbox: replies, then announcements.
const INBOX_TOKENS: usize = 2;

/// The worker in its own process.
#[derive(Debug)]
pub struct ShmSide {
    inbox: ShmInbox,
    first: Option<usize>,
    replies_ready: bool,
    announce_ready: bool,
}

impl ShmSide {
    /// The side around `inbox`.
    pub fn new(inbox: ShmInbox) -> Self {
        ShmSide {
            inbox,
            first: None,
            replies_ready: false,
            announce_ready: false,
        }
    }
}

impl WorkerSide for ShmSide {
    type Link = ShmLink;

    fn register(
        &mut self,
        registry: &Registry,
        (first, end): (Token, Token),
        _relay: &Relay<ShmLink>,
    ) -> std::io::Result<()> {
        if self.first.is_some() {
            return Ok(());
        }
        if first.0 + INBOX_TOKENS > end.0 {
            return Err(std::io::Error::other(
                "too few tokens for the worker's inbox",
            ));
        }
        let [replies_fd, announce_fd] = self.inbox.raw_fds();
        registry.register(&mut SourceFd(&replies_fd), first, Interest::READABLE)?;
        registry.register(
            &mut SourceFd(&announce_fd),
            Token(first.0 + 1),
            Interest::READABLE,
        )?;
        self.first = Some(first.0);
        Ok(())
    }

    fn on_event(&mut self, event: &Event) {
        match self.first.map(|f| event.token().0.wrapping_sub(f)) {
            Some(0) => self.replies_ready = true,
            Some(1) => self.announce_ready = true,
            _ => {}
        }
    }

    fn on_idle(&mut self) {
        // A race inside iceoryx2 0.10 can leave a listener marked notified with nothing to
        // read (a notifier that slips between the listener's reset and its second `recv`),
        // after which no notification would come again; consuming resets it.
        self.replies_ready = true;
        self.announce_ready = true;
    }

    fn termination_requested(&self) -> bool {
        self.inbox.termination_requested()
    }

    fn poll_timeout(&self, _now: Instant, _relay: &Relay<ShmLink>) -> Option<Instant> {
        None
    }

    fn deliver<A: Endpoint>(
        &mut self,
        now: Instant,
        relay: &mut Relay<ShmLink>,
        agent: &mut Agent<A>,
    ) -> anyhow::Result<()> {
        self.inbox.deliver(
            now,
            relay,
            agent,
            std::mem::take(&mut self.replies_ready),
            std::mem::take(&mut self.announce_ready),
        );
        Ok(())
    }

    fn maintain(&mut self, _now: Instant, _relay: &Relay<ShmLink>) {}

    fn stop(&mut self, _relay: &mut Relay<ShmLink>) {
        // The worker drains on its own (it stops with the supervisor).
    }
}
