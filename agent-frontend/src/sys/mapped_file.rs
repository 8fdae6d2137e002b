//! A file's bytes mapped into the front-end's memory, written without a system call: the
//! session store's state records ([`crate::session_store`]) change with almost every client
//! message, and a `pwrite` each cost more than the rest of the message's handling.
//!
//! The pages belong to the file (a tmpfs file in the agent's runtime directory), not to the
//! process: what was copied into them is in the file the moment the copy ends, and stays
//! there when the process is killed. A kill can cut a copy short, which the store's records detect (two slots,
//! each with a checksum over all of it).
//!
//! Invariants that make [`MappedFile`] sound (a mapped file changed or shrunk behind the
//! process's back is undefined behaviour, or a SIGBUS):
//!
//! * only this process writes the file while it maps it, and nobody shrinks it: the store
//!   creates each file under a temporary name, sizes it, and renames it into place, so a
//!   file a predecessor still mapped is replaced, never truncated; a successor maps a file
//!   only after its predecessor stopped, and only grows a short one;
//! * no page is written through the mapping before the file system allocated it
//!   (`posix_fallocate`, once per page): the file is sparse, and a first write to a hole
//!   of a full tmpfs would be a SIGBUS instead of the error a `pwrite` returns;
//! * the mapping is only written through `&mut self`, never handed out, so no Rust reference
//!   to its bytes outlives a call.

#![allow(unsafe_code)]

use std::fs::File;

/// Pages are allocated this many bytes at a time.
const PAGE: usize = 4096;

/// A writable shared mapping of a whole file of a fixed length.
#[derive(Debug)]
pub(crate) struct MappedFile {
    map: memmap2::MmapMut,
    /// Kept to allocate pages before their first write.
    file: File,
    /// Which pages are known to be allocated.
    allocated: Vec<bool>,
}

impl MappedFile {
    /// Maps `file`, which must be open for reading and writing, first growing it to `len`
    /// bytes if it is shorter (never shrinking it). See the module's invariants.
    pub(crate) fn open(file: File, len: u64) -> std::io::Result<Self> {
        if file.metadata()?.len() < len {
            file.set_len(len)?;
        }
        // SAFETY: the module's invariants: nobody else writes or shrinks the file while it
        // is mapped here, its length is at least `len` (grown above), and `write_at`
        // allocates every page before writing it.
        let map = unsafe {
            memmap2::MmapOptions::new()
                .len(len as usize)
                .map_mut(&file)?
        };
        let pages = map.len().div_ceil(PAGE);
        Ok(MappedFile {
            map,
            file,
            allocated: vec![false; pages],
        })
    }

    /// Bytes mapped (the file's length when it was mapped).
    pub(crate) fn mapped_len(&self) -> usize {
        self.map.len()
    }

    /// Copies `bytes` into the file at `offset`. Fails, writing nothing, if they do not fit
    /// or the file system cannot allocate the pages they go to (a full tmpfs).
    pub(crate) fn write_at(&mut self, offset: usize, bytes: &[u8]) -> std::io::Result<()> {
        let end = offset
            .checked_add(bytes.len())
            .filter(|end| *end <= self.map.len())
            .ok_or_else(|| std::io::Error::other("write beyond the mapped file"))?;
        if bytes.is_empty() {
            return Ok(());
        }
        let pages = offset / PAGE..end.div_ceil(PAGE);
        if let Some(first) = pages.clone().find(|p| !self.allocated[*p]) {
            let start = first * PAGE;
            let len = (pages.end * PAGE).min(self.map.len()) - start;
            nix::fcntl::posix_fallocate(&self.file, start as i64, len as i64)
                .map_err(std::io::Error::from)?;
            self.allocated[first..pages.end].fill(true);
        }
        self.map[offset..end].copy_from_slice(bytes);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::MetadataExt;

    #[test]
    fn writes_land_in_the_file_and_only_their_pages_are_allocated() {
        let path = std::env::temp_dir().join(format!("xrce-mapped-{}", std::process::id()));
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(true)
            .read(true)
            .write(true)
            .open(&path)
            .expect("create");
        let len = 64 * PAGE;
        let mut m = MappedFile::open(file, len as u64).expect("map");
        let sparse = std::fs::metadata(&path).expect("meta").blocks();
        m.write_at(10, b"hello").expect("write");
        m.write_at(40 * PAGE - 2, b"across")
            .expect("write across two pages");
        let bytes = std::fs::read(&path).expect("read");
        assert_eq!(bytes.len(), len);
        assert_eq!(&bytes[10..15], b"hello");
        assert_eq!(&bytes[40 * PAGE - 2..40 * PAGE + 4], b"across");
        // Three pages allocated (st_blocks counts 512-byte blocks), not the whole file.
        let blocks = std::fs::metadata(&path).expect("meta").blocks() - sparse;
        assert!(
            (3 * 8..16 * 8).contains(&blocks),
            "{blocks} blocks allocated"
        );
        assert!(m.write_at(len - 2, b"abc").is_err(), "beyond the end");
        assert!(m.write_at(usize::MAX, b"a").is_err(), "offset overflow");
        let _ = std::fs::remove_file(path);
    }
}
