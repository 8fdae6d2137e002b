//! The kernel's count of datagrams it dropped at a socket because its receive buffer was
//! full: `getsockopt(SO_MEMINFO)`, one system call, whatever else the host runs (the
//! `drops` of `/proc/net/udp` would walk every socket of the host).
//!
//! Invariant: the kernel writes at most `len` bytes into the buffer it is handed, `len` is
//! that buffer's size, and the buffer lives across the call.

#![allow(unsafe_code)]

use std::os::fd::{AsRawFd, BorrowedFd};

/// `SO_MEMINFO` (Linux's `asm-generic/socket.h`; SPARC numbers it apart).
#[cfg(not(any(target_arch = "sparc", target_arch = "sparc64")))]
const SO_MEMINFO: libc::c_int = 55;
#[cfg(any(target_arch = "sparc", target_arch = "sparc64"))]
const SO_MEMINFO: libc::c_int = 0x0039;

/// Entries of the kernel's answer this reads (`SK_MEMINFO_DROPS` is the last one needed;
/// newer kernels give more, and write only what fits).
const ENTRIES: usize = libc::SK_MEMINFO_DROPS as usize + 1;

/// How many datagrams the kernel dropped at `socket` since it was made (32 bits, wrapping);
/// `None` where the kernel does not say.
pub(crate) fn dropped_at(socket: BorrowedFd<'_>) -> Option<u32> {
    let mut info = [0u32; ENTRIES];
    let mut len = std::mem::size_of_val(&info) as libc::socklen_t;
    // SAFETY: `info` is writable for `len` bytes and outlives the call; the kernel writes at
    // most `len` bytes and says how many in `len` (invariant above).
    let rc = unsafe {
        libc::getsockopt(
            socket.as_raw_fd(),
            libc::SOL_SOCKET,
            SO_MEMINFO,
            info.as_mut_ptr().cast(),
            &mut len,
        )
    };
    (rc == 0 && len as usize >= std::mem::size_of_val(&info))
        .then(|| info[libc::SK_MEMINFO_DROPS as usize])
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::fd::AsFd;

    /// A socket flooded without being read: the kernel's count shows every datagram that
    /// did not fit.
    #[test]
    fn a_flooded_socket_shows_its_drops() {
        let server = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        socket2::SockRef::from(&server)
            .set_recv_buffer_size(4096)
            .expect("small buffer");
        server.set_nonblocking(true).expect("nonblocking");
        assert_eq!(dropped_at(server.as_fd()), Some(0));
        let client = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let to = server.local_addr().expect("addr");
        for _ in 0..200 {
            client.send_to(&[0u8; 512], to).expect("send");
        }
        let mut got = 0;
        let mut buf = [0u8; 1024];
        while server.recv(&mut buf).is_ok() {
            got += 1;
        }
        assert_eq!(dropped_at(server.as_fd()), Some(200 - got));
    }
}
