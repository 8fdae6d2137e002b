//! The names of an instance's files: what an instance may be called, and the prefixes the
//! shared memory and the event sockets of its processes carry ([`crate::shm`] makes them,
//! [`crate::runtime_dir`] cleans them up). Plain functions of a name, below both.

/// Checks an instance name: 1–32 characters of `[A-Za-z0-9_-]`.
pub fn valid_instance(instance: &str) -> bool {
    !instance.is_empty()
        && instance.len() <= 32
        && instance
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// Suffix of iceoryx2's event sockets in its root (its default is `.event`): shorter, so
/// that the socket paths (108 bytes at most) fit under a private runtime directory.
pub const EVENT_SUFFIX: &str = ".ev";

/// The prefix of every file iceoryx2 makes for `instance`, in its root and in `/dev/shm`,
/// whatever its random part ([`node_prefix`]): what a clean-up looks for.
pub fn file_prefix(instance: &str) -> String {
    format!("xrce_{}_", short_instance(instance))
}

/// Longest part of an instance's name its file names carry.
const SHORT_INSTANCE: usize = 20;

/// The part of `instance`'s name its file names carry: the name itself up to
/// [`SHORT_INSTANCE`] characters, else its first 11 and a hash of the whole. iceoryx2's
/// event sockets (108 bytes at most, the root's path included) carry the prefix and the
/// random part of the names: a name of 32 characters would not fit with both.
fn short_instance(instance: &str) -> String {
    if instance.len() <= SHORT_INSTANCE {
        return instance.to_string();
    }
    const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);
    let head: String = instance.chars().take(SHORT_INSTANCE - 9).collect();
    format!("{head}.{:08x}", CRC.checksum(instance.as_bytes()))
}

/// The prefix of the files iceoryx2 makes for `instance` in this run: [`file_prefix`] and
/// the instance's random part ([`crate::runtime_dir::SHM_TOKEN`]).
pub fn node_prefix(instance: &str, token: &str) -> String {
    format!("{}{token}_", file_prefix(instance))
}
