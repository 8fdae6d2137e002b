//! Primitive XCDR reading and writing with per-submessage endianness.
//!
//! Alignment is measured from the start of the buffer given to the reader or writer. Every
//! XRCE submessage payload starts on a 4-byte boundary of the message and no XRCE type needs
//! more than 4-byte alignment under XCDR2, so payload-relative alignment gives the same bytes
//! as message-relative alignment.

use super::DecodeError;

/// Reads primitives from a payload.
#[derive(Debug, Clone)]
pub struct CdrReader<'a> {
    buf: &'a [u8],
    pos: usize,
    little_endian: bool,
}

impl<'a> CdrReader<'a> {
    /// Whether multi-byte values are read little endian.
    pub fn is_little_endian(&self) -> bool {
        self.little_endian
    }

    /// A reader over `buf` whose multi-byte values are little endian when `little_endian`.
    pub fn new(buf: &'a [u8], little_endian: bool) -> Self {
        Self {
            buf,
            pos: 0,
            little_endian,
        }
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// Current offset from the start of the buffer.
    pub fn position(&self) -> usize {
        self.pos
    }

    /// Skips padding so the next read starts on a multiple of `n`.
    pub fn align(&mut self, n: usize) -> Result<(), DecodeError> {
        let pad = (n - self.pos % n) % n;
        self.take(pad).map(|_| ())
    }

    /// Takes `n` raw bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        if self.remaining() < n {
            return Err(DecodeError::Truncated);
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    /// Takes everything that is left.
    pub fn rest(&mut self) -> &'a [u8] {
        let s = &self.buf[self.pos..];
        self.pos = self.buf.len();
        s
    }

    /// Takes a fixed-size array of octets.
    pub fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    /// Reads an octet.
    pub fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.take(1)?[0])
    }

    /// Reads a boolean, rejecting values other than 0 and 1.
    pub fn bool(&mut self) -> Result<bool, DecodeError> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            _ => Err(DecodeError::InvalidValue("boolean")),
        }
    }

    /// Reads an aligned unsigned short.
    pub fn u16(&mut self) -> Result<u16, DecodeError> {
        self.align(2)?;
        let b = self.array::<2>()?;
        Ok(if self.little_endian {
            u16::from_le_bytes(b)
        } else {
            u16::from_be_bytes(b)
        })
    }

    /// Reads an aligned short.
    pub fn i16(&mut self) -> Result<i16, DecodeError> {
        self.u16().map(|v| v as i16)
    }

    /// Reads an aligned unsigned long.
    pub fn u32(&mut self) -> Result<u32, DecodeError> {
        self.align(4)?;
        let b = self.array::<4>()?;
        Ok(if self.little_endian {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    /// Reads an aligned long.
    pub fn i32(&mut self) -> Result<i32, DecodeError> {
        self.u32().map(|v| v as i32)
    }

    /// Reads an unsigned long long aligned to `align` (8 for Micro-CDR, 4 for XCDR2).
    pub fn u64_aligned(&mut self, align: usize) -> Result<u64, DecodeError> {
        self.align(align)?;
        let a = u64::from(self.u32()?);
        let b = u64::from(self.u32()?);
        Ok(if self.little_endian {
            a | b << 32
        } else {
            a << 32 | b
        })
    }

    /// Reads a string (length including NUL, bytes, NUL) of at most `max` characters.
    pub fn string(&mut self, max: usize) -> Result<String, DecodeError> {
        let len = self.u32()? as usize;
        if len == 0 {
            // Tolerated: some writers encode the empty string as length 0.
            return Ok(String::new());
        }
        if len - 1 > max {
            return Err(DecodeError::TooLong("string"));
        }
        let bytes = self.take(len)?;
        let (body, nul) = bytes.split_at(len - 1);
        if nul != [0] {
            return Err(DecodeError::InvalidValue("string terminator"));
        }
        String::from_utf8(body.to_vec()).map_err(|_| DecodeError::InvalidValue("string utf-8"))
    }

    /// Reads a `sequence<octet>` of at most `max` bytes.
    pub fn octet_seq(&mut self, max: usize) -> Result<&'a [u8], DecodeError> {
        let len = self.u32()? as usize;
        if len > max {
            return Err(DecodeError::TooLong("sequence"));
        }
        self.take(len)
    }
}

/// Appends primitives to a buffer.
#[derive(Debug)]
pub struct CdrWriter<'a> {
    buf: &'a mut Vec<u8>,
    origin: usize,
    little_endian: bool,
}

impl<'a> CdrWriter<'a> {
    /// Whether multi-byte values are written little endian.
    pub fn is_little_endian(&self) -> bool {
        self.little_endian
    }

    /// A writer appending to `buf`; alignment is measured from the current end of `buf`.
    pub fn new(buf: &'a mut Vec<u8>, little_endian: bool) -> Self {
        let origin = buf.len();
        Self {
            buf,
            origin,
            little_endian,
        }
    }

    /// Bytes written so far.
    pub fn len(&self) -> usize {
        self.buf.len() - self.origin
    }

    /// Whether nothing was written yet.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Pads with zeros to a multiple of `n`.
    pub fn align(&mut self, n: usize) {
        let pad = (n - self.len() % n) % n;
        self.buf.extend(std::iter::repeat_n(0u8, pad));
    }

    /// Appends raw bytes.
    pub fn bytes(&mut self, b: &[u8]) {
        self.buf.extend_from_slice(b);
    }

    /// Appends an octet.
    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    /// Appends a boolean.
    pub fn bool(&mut self, v: bool) {
        self.buf.push(v as u8);
    }

    /// Appends an aligned unsigned short.
    pub fn u16(&mut self, v: u16) {
        self.align(2);
        let b = if self.little_endian {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        };
        self.bytes(&b);
    }

    /// Appends an aligned short.
    pub fn i16(&mut self, v: i16) {
        self.u16(v as u16);
    }

    /// Appends an aligned unsigned long.
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        let b = if self.little_endian {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        };
        self.bytes(&b);
    }

    /// Appends an aligned long.
    pub fn i32(&mut self, v: i32) {
        self.u32(v as u32);
    }

    /// Appends an unsigned long long aligned to `align` (8 for Micro-CDR, 4 for XCDR2).
    pub fn u64_aligned(&mut self, v: u64, align: usize) {
        self.align(align);
        let (lo, hi) = (v as u32, (v >> 32) as u32);
        if self.little_endian {
            self.u32(lo);
            self.u32(hi);
        } else {
            self.u32(hi);
            self.u32(lo);
        }
    }

    /// Appends a string with its NUL terminator.
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.bytes(s.as_bytes());
        self.u8(0);
    }

    /// Appends a `sequence<octet>`.
    pub fn octet_seq(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.bytes(b);
    }
}
