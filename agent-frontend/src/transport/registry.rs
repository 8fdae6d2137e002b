//! Every transport a front-end serves, one line each: its names and how it reaches clients.
//! The front-end's start-up (`crate::start`, which opens each medium's transport), the
//! supervisor's plans and the gateway file's names all read this table; a new transport is
//! its module, its line here, its [`TransportKind`] variant (which the command line's value
//! list is derived from) and its arm in the start-up's `open_and_serve`.

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

/// The transports a front-end serves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TransportKind {
    /// UDP over IPv4.
    Udp4,
    /// UDP over IPv6.
    Udp6,
    /// TCP over IPv4.
    Tcp4,
    /// TCP over IPv6.
    Tcp6,
    /// One serial device.
    Serial,
    /// Several serial devices.
    Multiserial,
    /// A pseudoterminal.
    Pseudoterminal,
}

impl TransportKind {
    /// What the front-end knows of it ([`self`] module's table).
    pub fn spec(self) -> &'static TransportSpec {
        // The registry lists the kinds in declaration order (checked by its tests).
        &TRANSPORTS[self as usize]
    }

    /// The name used on the command line and in gateway files.
    pub fn name(self) -> &'static str {
        self.spec().name
    }

    /// The kind of that name (or of one of its aliases).
    pub fn by_name(name: &str) -> Option<Self> {
        TRANSPORTS
            .iter()
            .find(|t| t.name == name || t.aliases.contains(&name))
            .map(|t| t.kind)
    }

    /// How it reaches clients.
    pub fn medium(self) -> Medium {
        self.spec().medium
    }

    /// Whether it serves an IP port.
    pub fn is_ip(self) -> bool {
        matches!(self.medium(), Medium::Datagrams | Medium::Streams)
    }

    /// Whether it serves IPv6.
    pub fn is_ipv6(self) -> bool {
        self.spec().ipv6
    }
}

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
}

use Medium::*;
use TransportKind as K;

/// The transports, in [`TransportKind`]'s declaration order.
pub const TRANSPORTS: [TransportSpec; 7] = [
    spec(K::Udp4, "udp4", &[], Datagrams, false),
    spec(K::Udp6, "udp6", &[], Datagrams, true),
    spec(K::Tcp4, "tcp4", &[], Streams, false),
    spec(K::Tcp6, "tcp6", &["tpc6"], Streams, true),
    serial(K::Serial, "serial", true),
    serial(K::Multiserial, "multiserial", false),
    spec(
        K::Pseudoterminal,
        "pseudoterminal",
        &[],
        Pseudoterminal,
        false,
    ),
];

const fn spec(
    kind: TransportKind,
    name: &'static str,
    aliases: &'static [&'static str],
    medium: Medium,
    ipv6: bool,
) -> TransportSpec {
    TransportSpec {
        kind,
        name,
        aliases,
        medium,
        ipv6,
        one_device: false,
    }
}

const fn serial(kind: TransportKind, name: &'static str, one_device: bool) -> TransportSpec {
    TransportSpec {
        one_device,
        ..spec(kind, name, &[], SerialLines, false)
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
