//! The last write the worker executed on each reliable stream of each client, per front-end:
//! what a front-end process that takes over from one that died is told before the answer to
//! its hello ([`ipc::Reply::Executed`]). The process that died handed a client message's
//! writes over before storing that it took the message; the client sends that message
//! again, and its successor must not hand those writes over a second time.

use std::collections::HashMap;

use xrce_common::session::stream::InputPosition;
use xrce_common::wire::ClientKey;

/// Most clients whose positions are kept, over all front-ends (16 front-ends of 8,192
/// sessions, a front-end's default bound): beyond, a new client's are not kept (counted,
/// logged once per episode), so its writes could repeat at a front-end crash, as before
/// positions were kept. At most about 20 MiB.
pub(super) const MAX_CLIENTS: usize = 1 << 17;

/// Reliable streams of a client whose position is kept: twice the input streams a
/// front-end's session core takes from one client (8).
const MAX_STREAMS: usize = 16;

/// What [`ExecutedWrites::record`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Recorded {
    /// Kept.
    Yes,
    /// Not kept: [`MAX_CLIENTS`] clients have positions already, or this client has
    /// [`MAX_STREAMS`].
    Full,
}

/// The positions, by front-end and client.
#[derive(Debug, Default)]
pub(super) struct ExecutedWrites {
    clients: HashMap<(u32, ClientKey), Vec<InputPosition>>,
}

impl ExecutedWrites {
    /// `position` of `client` of front-end `frontend` was executed (the latest of its
    /// stream: a front-end hands a stream's writes over in order).
    pub(super) fn record(
        &mut self,
        frontend: u32,
        client: ClientKey,
        position: InputPosition,
    ) -> Recorded {
        let full = self.clients.len() >= MAX_CLIENTS;
        let streams = match self.clients.get_mut(&(frontend, client)) {
            Some(s) => s,
            None if full => return Recorded::Full,
            None => self.clients.entry((frontend, client)).or_default(),
        };
        if let Some(p) = streams
            .iter_mut()
            .find(|p| p.stream_id == position.stream_id)
        {
            *p = position;
        } else if streams.len() < MAX_STREAMS {
            streams.push(position);
        } else {
            return Recorded::Full;
        }
        Recorded::Yes
    }

    /// The session of `client` ended: its positions mean nothing any more.
    pub(super) fn forget_client(&mut self, frontend: u32, client: ClientKey) {
        self.clients.remove(&(frontend, client));
    }

    /// Front-end `frontend` is gone for good.
    pub(super) fn forget_frontend(&mut self, frontend: u32) {
        self.clients.retain(|(fe, _), _| *fe != frontend);
    }

    /// Every position kept for front-end `frontend`.
    pub(super) fn of_frontend(&self, frontend: u32) -> Vec<(ClientKey, InputPosition)> {
        self.clients
            .iter()
            .filter(|((fe, _), _)| *fe == frontend)
            .flat_map(|((_, c), streams)| streams.iter().map(move |p| (*c, *p)))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(stream_id: u8, sequence: u16, write_index: u16) -> InputPosition {
        InputPosition {
            epoch: 1,
            stream_id,
            sequence,
            write_index,
        }
    }

    #[test]
    fn keeps_the_latest_position_of_each_stream_of_each_client() {
        let mut e = ExecutedWrites::default();
        let (a, b) = (ClientKey([1, 0, 0, 0]), ClientKey([2, 0, 0, 0]));
        e.record(1, a, at(0x80, 4, 0));
        e.record(1, a, at(0x80, 5, 1));
        e.record(1, a, at(0x81, 9, 0));
        e.record(2, b, at(0x80, 1, 0));
        let mut of_1 = e.of_frontend(1);
        of_1.sort_by_key(|(_, p)| p.stream_id);
        assert_eq!(of_1, vec![(a, at(0x80, 5, 1)), (a, at(0x81, 9, 0))]);
        e.forget_client(1, a);
        assert!(e.of_frontend(1).is_empty());
        assert_eq!(e.of_frontend(2), vec![(b, at(0x80, 1, 0))]);
        e.forget_frontend(2);
        assert!(e.of_frontend(2).is_empty());
    }

    #[test]
    fn a_full_table_keeps_the_clients_it_has_and_takes_no_new_one() {
        let mut e = ExecutedWrites::default();
        for n in 0..MAX_CLIENTS as u32 {
            e.record(1, ClientKey(n.to_le_bytes()), at(0x80, 0, 0));
        }
        let new = ClientKey([0xFF; 4]);
        assert_eq!(e.record(1, new, at(0x80, 0, 0)), Recorded::Full);
        let old = ClientKey(7u32.to_le_bytes());
        assert_eq!(e.record(1, old, at(0x80, 1, 0)), Recorded::Yes);
        assert_eq!(e.record(1, old, at(0x81, 1, 0)), Recorded::Yes);
        for stream in 0x82..0x80 + MAX_STREAMS as u8 {
            assert_eq!(e.record(1, old, at(stream, 1, 0)), Recorded::Yes);
        }
        let beyond = 0x80 + MAX_STREAMS as u8;
        assert_eq!(e.record(1, old, at(beyond, 1, 0)), Recorded::Full);
    }
}
