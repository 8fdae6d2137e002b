//! A file's bytes mapped into the front-end's memory, written without a system call: the
//! session store's state records ([`crate::session_store`]) change with almost every client
//! message, and a `pwrite` each cost more than the rest of the message's handling.
//!
//! The pages belong to the file (a tmpfs file under `/dev/shm`), not to the process: what was
//! copied into them is in the file the moment the copy ends, and stays there when the process
//! is killed. A kill can cut a copy short, which the store's records detect (two slots,
//! each with a checksum over all of it).
//!
//! Invariants that make [`MappedFile::open`] sound (a mapped file changed or shrunk behind the
//! process's back is undefined behaviour, or a SIGBUS):
//!
//! * only this process writes the file while it maps it, and nobody shrinks it: the store
//!   creates each file under a temporary name, sizes it, and renames it into place, so a
//!   file a predecessor still mapped is replaced, never truncated; a successor maps a file
//!   only after its predecessor stopped, and only grows a short one;
//! * the mapping is only written through `&mut self`, never handed out, so no Rust reference
//!   to its bytes outlives a call.

#![allow(unsafe_code)]

use std::fs::File;

/// A writable shared mapping of a whole file of a fixed length.
#[derive(Debug)]
pub struct MappedFile {
    map: memmap2::MmapMut,
}

impl MappedFile {
    /// Maps `file`, which must be open for reading and writing, first growing it to `len`
    /// bytes if it is shorter (never shrinking it). See the module's invariants.
    pub fn open(file: &File, len: u64) -> std::io::Result<Self> {
        if file.metadata()?.len() < len {
            file.set_len(len)?;
        }
        // SAFETY: the module's invariants: nobody else writes or shrinks the file while it
        // is mapped here, and its length is at least `len` (grown above).
        let map = unsafe {
            memmap2::MmapOptions::new()
                .len(len as usize)
                .map_mut(file)?
        };
        Ok(MappedFile { map })
    }

    /// Copies `bytes` into the file at `offset`; false (nothing written) if they do not fit.
    pub fn write_at(&mut self, offset: usize, bytes: &[u8]) -> bool {
        let Some(dst) = offset
            .checked_add(bytes.len())
            .and_then(|end| self.map.get_mut(offset..end))
        else {
            return false;
        };
        dst.copy_from_slice(bytes);
        true
    }
}
