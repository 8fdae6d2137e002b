//! The contract between front-ends and the DDS worker (version [`IPC_VERSION`]), and the
//! process plumbing both sides share: the iceoryx2 link ([`shm`]), the agent's private runtime
//! directory ([`runtime_dir`]), the status reports each process writes ([`status`]) and how
//! a supervisor hands its processes their settings ([`settings`]).
//! Feature `shm` (default) brings the plumbing; without it, only the messages and their codec.
//!
//! The messages are types ([`Request`] and [`Reply`] with their [`Route`]) with one codec in
//! [`message`]; object descriptions and read specifications travel in their XRCE encoding
//! (little endian), so there is one codec for them too. Service names live under
//! `xrce/<instance>/`.
//!
//! Flow: front-ends publish operations on [`request_service`] (many publishers, one worker);
//! the worker answers each front-end on its own [`reply_service`], and announces each new
//! worker generation on [`announce_service`]. Every data service has an event service of the
//! same name plus `.ev` so receivers block instead of polling.

#![deny(unsafe_code)]
// What is `pub` is the crate's API, documented; an item only the crate uses says so (`pub(crate)`).
#![warn(unreachable_pub, missing_docs)]

mod codec;
pub mod fuzzing;
pub mod message;
#[cfg(feature = "shm")]
pub mod names;
#[cfg(feature = "shm")]
pub mod runtime_dir;
#[cfg(feature = "shm")]
pub mod settings;
#[cfg(feature = "shm")]
pub mod shm;
#[cfg(feature = "shm")]
pub mod status;
#[cfg(feature = "shm")]
#[allow(unsafe_code)]
mod sys;

pub use codec::IpcError;
pub use message::{
    Encode, Reply, ReplyMessage, Request, RequestMessage, Route, Sample, SampleIdentity,
    SampleOrigin, WriteOrigin, HEADER_LEN, REPLAY_REFUSED,
};

/// Version of this contract; both sides drop (and log) messages of another version.
pub const IPC_VERSION: u16 = 10;
/// Magic at the start of every message.
pub const IPC_MAGIC: [u8; 4] = *b"XRIP";

/// Largest message body carried (a sample of up to 1 MiB, the largest message the session
/// core reassembles, plus slack); bigger samples are refused.
pub const MAX_BODY: usize = (1 << 20) + 512;
/// Body size the shared-memory segments are first laid out for; larger bodies grow them.
pub const INITIAL_BODY: usize = 65_536 + 512;
/// Buffer of each publisher→subscriber connection in messages.
pub const CHANNEL_DEPTH: usize = 256;
/// Operations a front-end may have sent and not seen processed; below [`CHANNEL_DEPTH`] so the
/// worker's queue never overflows (an overflow would silently lose operations).
pub const IN_FLIGHT_WINDOW: u64 = 192;

/// Operations from all front-ends to the worker.
pub fn request_service(instance: &str) -> String {
    format!("xrce/{instance}/requests")
}

/// Replies and samples from the worker to one front-end.
pub fn reply_service(instance: &str, frontend_id: u32) -> String {
    format!("xrce/{instance}/replies/{frontend_id}")
}

/// Worker generation announcements.
pub fn announce_service(instance: &str) -> String {
    format!("xrce/{instance}/announce")
}

/// The instance name an agent takes when none is given: `<label>-<8 hex digits>`, the digits
/// a CRC-32 of what the agent serves (`identity`: its transport's address and port, or its
/// devices) and of the network namespace it runs in (its inode, as `/proc/self/ns/net`
/// shows it). The same command line in the same namespace finds the same instance, and so
/// the sessions its predecessor stored, after a restart of the whole agent; two agents that
/// serve different things (one port on two addresses, one command line in two network
/// namespaces) never share one. Stays within the 32 characters an instance may have.
pub fn derived_instance(label: &str, identity: &str) -> String {
    let netns = std::fs::read_link("/proc/self/ns/net")
        .map(|p| p.display().to_string())
        .unwrap_or_default();
    derived_instance_in(label, identity, &netns)
}

/// [`derived_instance`] for a given network namespace.
pub fn derived_instance_in(label: &str, identity: &str, netns: &str) -> String {
    const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);
    let mut digest = CRC.digest();
    for part in [label, identity, netns] {
        digest.update(part.as_bytes());
        digest.update(&[0]);
    }
    let label: String = label
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .take(32 - 9)
        .collect();
    format!("{label}-{:08x}", digest.finalize())
}

/// The event service paired with a data service.
pub fn event_service(data_service: &str) -> String {
    format!("{data_service}.ev")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_instances_are_stable_and_tell_agents_apart() {
        let a = derived_instance_in("udp4-8888", "0.0.0.0:8888", "net:[4026531840]");
        assert_eq!(
            a,
            derived_instance_in("udp4-8888", "0.0.0.0:8888", "net:[4026531840]")
        );
        assert!(a.starts_with("udp4-8888-") && a.len() == 18, "{a}");
        assert_ne!(
            a,
            derived_instance_in("udp4-8888", "10.0.0.1:8888", "net:[4026531840]")
        );
        assert_ne!(
            a,
            derived_instance_in("udp4-8888", "0.0.0.0:8888", "net:[4026532000]")
        );
        let long = derived_instance_in(&"x".repeat(40), "", "");
        assert!(long.len() <= 32, "{long}");
        assert_eq!(derived_instance_in("a.b", "", "").chars().nth(1), Some('_'));
    }
}
