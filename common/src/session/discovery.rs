//! Agent discovery (§7.8.1, eProsima's `-d`): a client multicasts a session-less GET_INFO
//! about the agent, and every agent that hears it answers with INFO naming the transport
//! locators where it accepts clients. Sans-IO: the front-end's discovery module owns the
//! socket and calls [`answer`] for each datagram.

use super::agent::agent_info_message;
use crate::wire::info::TransportLocator;
use crate::wire::{DecodeError, Dialect, MessageHeader, ObjectId, Payload, Submessages};

/// The multicast group discovery requests go to.
pub const DISCOVERY_GROUP: std::net::Ipv4Addr = std::net::Ipv4Addr::new(239, 255, 0, 2);
/// The reference agent's default discovery port (also DDS domain 0's discovery port).
pub const DEFAULT_DISCOVERY_PORT: u16 = 7400;

/// Why a discovery datagram gets no answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DiscoveryError {
    /// It is not an XRCE message.
    #[error("undecodable: {0}")]
    Decode(#[from] DecodeError),
    /// It is a message, but not a session-less GET_INFO about the agent.
    #[error("not a discovery request")]
    NotDiscovery,
}

impl DiscoveryError {
    /// A short stable name, used as a counter label.
    pub fn reason(&self) -> &'static str {
        match self {
            DiscoveryError::Decode(e) => e.reason(),
            DiscoveryError::NotDiscovery => "not_discovery",
        }
    }
}

/// The INFO answering one discovery request, listing `locators`, or why there is none.
pub fn answer(
    request: &[u8],
    vendor_id: [u8; 2],
    locators: &[TransportLocator],
) -> Result<Vec<u8>, DiscoveryError> {
    let (header, hlen) = MessageHeader::decode(request)?;
    if header.session_id != 0x00 && header.session_id != 0x80 {
        return Err(DiscoveryError::NotDiscovery);
    }
    for raw in Submessages::new(request, hlen) {
        if let Payload::GetInfo(g) = raw?.decode()? {
            if g.base.object_id == ObjectId::AGENT || g.base.object_id == ObjectId::CLIENT {
                return Ok(agent_info_message(
                    header,
                    g.base,
                    false,
                    Dialect::default(),
                    vendor_id,
                    locators.to_vec(),
                ));
            }
        }
    }
    Err(DiscoveryError::NotDiscovery)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::VENDOR_EPROSIMA;

    fn unhex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
            .collect()
    }

    /// wire-traces/discovery-multicast.txt: the reference agent, serving UDP port 2019 on
    /// 127.0.0.1 and 192.0.2.2, answers byte for byte like this.
    #[test]
    fn answers_like_the_reference_agent() {
        let request = unhex("80000000020108000009fffd03000000");
        let expected = unhex(
            "8000000006012c000009fffd0000010d585243450100010f00010d000100000002000000\
             017f00000100e30701c000020200e307",
        );
        let locators = [
            TransportLocator::Medium {
                address: [127, 0, 0, 1],
                port: 2019,
            },
            TransportLocator::Medium {
                address: [192, 0, 2, 2],
                port: 2019,
            },
        ];
        assert_eq!(
            answer(&request, VENDOR_EPROSIMA, &locators).expect("answered"),
            expected
        );
    }

    #[test]
    fn other_messages_get_no_answer() {
        // A CREATE_CLIENT, a session's GET_INFO, and noise.
        let create = unhex(
            "800000000001100058524345010001 0faaaabbbb810000"
                .replace(' ', "")
                .as_str(),
        );
        assert!(answer(&create, VENDOR_EPROSIMA, &[]).is_err());
        let in_session = unhex("81000000020108000009fffd03000000");
        assert_eq!(
            answer(&in_session, VENDOR_EPROSIMA, &[]),
            Err(DiscoveryError::NotDiscovery)
        );
        assert!(answer(&[1, 2, 3], VENDOR_EPROSIMA, &[]).is_err());
    }
}
