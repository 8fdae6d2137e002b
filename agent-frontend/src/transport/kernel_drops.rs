//! Datagrams the kernel dropped because a socket's receive buffer was full: a flood, or a
//! loop that stalled. The agent never sees them, so it reads the kernel's count of them
//! (the `drops` column of `/proc/net/udp` and `/proc/net/udp6`, found by the socket's inode)
//! and counts what it adds.

use std::os::fd::AsFd;

/// The kernel's count of datagrams dropped at the socket `fd` since it was made, if the
/// tables can be read and list it.
pub(crate) fn dropped_by_kernel(fd: impl AsFd) -> Option<u64> {
    let inode = nix::sys::stat::fstat(fd).ok()?.st_ino;
    ["/proc/net/udp", "/proc/net/udp6"]
        .into_iter()
        .filter_map(|table| std::fs::read_to_string(table).ok())
        .find_map(|text| drops_in(&text, inode))
}

/// The `drops` of the socket with `inode` in the text of a `/proc/net/udp` table.
fn drops_in(table: &str, inode: u64) -> Option<u64> {
    table.lines().skip(1).find_map(|line| {
        let fields: Vec<&str> = line.split_whitespace().collect();
        // sl local rem st tx:rx tr:when retrnsmt uid timeout inode ref pointer drops
        let line_inode = fields.get(9)?.parse::<u64>().ok()?;
        (line_inode == inode)
            .then(|| fields.get(12)?.parse::<u64>().ok())
            .flatten()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_drops_of_the_socket_with_the_inode() {
        let table = "   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode ref pointer drops\n\
  1: 0100007F:22B8 00000000:0000 07 00000000:00000000 00:00000000 00000000     0        0 4242 2 0000000000000000 0\n\
  2: 0100007F:22B9 00000000:0000 07 00000000:00040000 00:00000000 00000000     0        0 4343 2 0000000000000000 117\n";
        assert_eq!(drops_in(table, 4343), Some(117));
        assert_eq!(drops_in(table, 4242), Some(0));
        assert_eq!(drops_in(table, 99), None);
        assert_eq!(drops_in("header only\n", 4242), None);
        assert_eq!(drops_in("h\n 1: a b c d e f g h 4242 x\n", 4242), None);
    }

    /// A socket flooded without being read: the kernel's drops show.
    #[test]
    fn a_flooded_socket_shows_its_drops() {
        let server = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        socket2::SockRef::from(&server)
            .set_recv_buffer_size(4096)
            .expect("small buffer");
        assert_eq!(dropped_by_kernel(&server), Some(0));
        let client = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let to = server.local_addr().expect("addr");
        for _ in 0..200 {
            client.send_to(&[0u8; 512], to).expect("send");
        }
        assert!(dropped_by_kernel(&server).is_some_and(|d| d > 0));
    }
}
