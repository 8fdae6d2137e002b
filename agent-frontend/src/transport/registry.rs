//! Every transport a front-end serves, one line each: its names, how it reaches clients, and
//! the function of its module that opens it from the front-end's settings and serves. The
//! front-end's start-up, the supervisor's plans and the gateway file's names all read this
//! table; a new transport is its module, its line here and its [`TransportKind`] variant
//! (which the command line's value list is derived from).

use xrce_common::session::agent::AgentConfig;

use crate::cli::{FrontendArgs, TransportKind};
use crate::event_loop::OnServing;

/// How a transport reaches its clients (what the supervisor plans for it: an address and
/// port, devices, or a pseudoterminal it opens).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Medium {
    /// Datagrams at an address and port (UDP).
    Datagrams,
    /// Connections to an address and port (TCP).
    Streams,
    /// Serial lines (tty devices).
    SerialLines,
    /// A pseudoterminal the front-end (or its supervisor) opens.
    Pseudoterminal,
}

/// Opens a transport from the front-end's settings and serves its clients until
/// SIGINT/SIGTERM.
pub type Serve = fn(&FrontendArgs, AgentConfig, Option<OnServing>) -> anyhow::Result<()>;

/// One transport.
#[derive(Debug)]
pub struct TransportSpec {
    /// Its kind (the command line's value).
    pub kind: TransportKind,
    /// Its name on the command line, in gateway files, logs and metrics.
    pub name: &'static str,
    /// Other names accepted in gateway files (MicroXRCEAgent's own spellings).
    pub aliases: &'static [&'static str],
    /// How it reaches clients.
    pub medium: Medium,
    /// IPv6 (IP transports).
    pub ipv6: bool,
    /// Exactly one device (serial lines).
    pub one_device: bool,
    /// Its module's start-up.
    pub serve: Serve,
}

use crate::transport::{multiserial, pty, tcp, udp};
use Medium::*;
use TransportKind as K;

/// The transports, in [`TransportKind`]'s declaration order.
pub const TRANSPORTS: [TransportSpec; 7] = [
    spec(K::Udp4, "udp4", &[], Datagrams, false, udp::serve),
    spec(K::Udp6, "udp6", &[], Datagrams, true, udp::serve),
    spec(K::Tcp4, "tcp4", &[], Streams, false, tcp::serve),
    spec(K::Tcp6, "tcp6", &["tpc6"], Streams, true, tcp::serve),
    serial(K::Serial, "serial", true),
    serial(K::Multiserial, "multiserial", false),
    spec(
        K::Pseudoterminal,
        "pseudoterminal",
        &[],
        Pseudoterminal,
        false,
        pty::serve,
    ),
];

const fn spec(
    kind: TransportKind,
    name: &'static str,
    aliases: &'static [&'static str],
    medium: Medium,
    ipv6: bool,
    serve: Serve,
) -> TransportSpec {
    TransportSpec {
        kind,
        name,
        aliases,
        medium,
        ipv6,
        one_device: false,
        serve,
    }
}

const fn serial(kind: TransportKind, name: &'static str, one_device: bool) -> TransportSpec {
    TransportSpec {
        one_device,
        ..spec(kind, name, &[], SerialLines, false, multiserial::serve)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::ValueEnum;

    #[test]
    fn every_kind_has_its_line_in_order_and_its_name_parses() {
        let kinds = TransportKind::value_variants();
        assert_eq!(kinds.len(), TRANSPORTS.len());
        for k in kinds {
            assert_eq!(k.spec().kind, *k);
            let value = k.to_possible_value().expect("a command-line value");
            assert_eq!(value.get_name(), k.name(), "clap and the registry agree");
            assert_eq!(TransportKind::by_name(k.name()), Some(*k));
        }
        assert_eq!(TransportKind::by_name("tpc6"), Some(TransportKind::Tcp6));
        assert_eq!(TransportKind::by_name("can"), None);
    }
}
