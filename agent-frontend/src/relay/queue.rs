//! The queues of the relay: operations waiting for the window, weighed in bytes so that
//! memory is bounded by what they hold, not by how many they are.

use std::collections::VecDeque;

use xrce_ipc::{Encode, Request, RequestMessage};

/// Whether a client waits for the STATUS of an operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Awaited {
    /// The client waits for a STATUS.
    Yes,
    /// Internal or replayed: do not forward the STATUS.
    No,
}

/// What a client waits for the STATUS of, by kind of operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum PendingKind {
    Create,
    Delete,
    Write,
    Other,
}

impl PendingKind {
    pub(super) fn of(request: &Request<'_>) -> Self {
        match request {
            Request::Create { .. } => PendingKind::Create,
            Request::Delete => PendingKind::Delete,
            Request::Write { .. } => PendingKind::Write,
            _ => PendingKind::Other,
        }
    }
}

/// An operation waiting to be sent, and what it asks of the relay once it was.
#[derive(Debug)]
pub(super) struct OwnedOp {
    pub(super) message: RequestMessage<'static>,
    /// Kept for a resend to a new worker (a reliable write).
    pub(super) retain: bool,
    pub(super) awaited: Awaited,
}

/// What an entry of a [`ByteQueue`] weighs.
pub(super) trait Weighed {
    /// Its bytes.
    fn weight(&self) -> usize;
}

impl Weighed for OwnedOp {
    fn weight(&self) -> usize {
        self.message.encoded_len()
    }
}

/// A FIFO that knows how many bytes it holds (so memory is bounded by bytes, not entries).
#[derive(Debug)]
pub(super) struct ByteQueue<T> {
    items: VecDeque<T>,
    pub(super) bytes: usize,
}

impl<T> Default for ByteQueue<T> {
    fn default() -> Self {
        ByteQueue {
            items: VecDeque::new(),
            bytes: 0,
        }
    }
}

impl<T: Weighed> ByteQueue<T> {
    pub(super) fn push_back(&mut self, t: T) {
        self.bytes += t.weight();
        self.items.push_back(t);
    }

    pub(super) fn push_front(&mut self, t: T) {
        self.bytes += t.weight();
        self.items.push_front(t);
    }

    pub(super) fn pop_front(&mut self) -> Option<T> {
        let t = self.items.pop_front()?;
        self.bytes -= t.weight();
        Some(t)
    }

    pub(super) fn front(&self) -> Option<&T> {
        self.items.front()
    }

    /// Entries in order; callers must not change their weight.
    pub(super) fn iter_mut(&mut self) -> impl Iterator<Item = &mut T> {
        self.items.iter_mut()
    }

    pub(super) fn len(&self) -> usize {
        self.items.len()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    pub(super) fn take(&mut self) -> VecDeque<T> {
        self.bytes = 0;
        std::mem::take(&mut self.items)
    }

    pub(super) fn extend(&mut self, items: impl IntoIterator<Item = T>) {
        for t in items {
            self.push_back(t);
        }
    }
}
