//! The front-end's only `unsafe` code, each part with its invariants written down:
//!
//! * [`owned_fd`]: taking ownership of descriptors that arrive as bare numbers;
//! * [`mapped_file`]: a file mapped into memory, written without a system call;
//! * [`socket_drops`]: the kernel's count of what it dropped at a socket.

pub(crate) mod mapped_file;
pub(crate) mod owned_fd;
pub(crate) mod socket_drops;
