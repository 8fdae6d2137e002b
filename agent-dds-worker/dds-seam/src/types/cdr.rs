//! Walking a serialized sample with its type: where it ends, its values, and a copy
//! re-based to another alignment origin (bounded in steps).

use super::*;

/// Why a sample could not be walked.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum WalkError {
    /// The sample ends before the type does.
    #[error("sample shorter than its type")]
    Truncated,
    /// A length beyond what the sample holds, or a bound.
    #[error("sample with an invalid length")]
    BadLength,
    /// More elements than the walk allows.
    #[error("sample too complex to walk")]
    TooComplex,
}

/// A field value, for content filters.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// Any integer (and chars, octets).
    Int(i128),
    /// float32 / float64.
    Float(f64),
    /// boolean.
    Bool(bool),
    /// string.
    Str(String),
    /// An enumerator: its value and name.
    Enum(i64, String),
}

/// A cursor over a serialized sample body.
#[derive(Debug, Clone)]
pub struct Cursor<'a> {
    pub(super) buf: &'a [u8],
    pub(super) pos: usize,
    /// Alignment origin (offset of the body start in the CDR stream).
    pub(super) origin: usize,
    pub(super) le: bool,
    pub(super) xcdr2: bool,
    pub(super) steps: usize,
    /// Most steps the walk may take ([`MAX_STEPS`] unless a caller gave less).
    pub(super) limit: usize,
}

impl<'a> Cursor<'a> {
    /// A cursor at the start of `buf`, whose first byte is at `origin` in the stream.
    pub fn new(buf: &'a [u8], origin: usize, le: bool, xcdr2: bool) -> Self {
        Cursor {
            buf,
            pos: 0,
            origin,
            le,
            xcdr2,
            steps: 0,
            limit: MAX_STEPS,
        }
    }

    /// Steps taken so far (elements visited, and string octets copied at one step per
    /// [`STRING_OCTETS_PER_STEP`]).
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Counts `n` steps of work at once; `TooComplex` beyond the limit.
    pub(super) fn charge(&mut self, n: usize) -> Result<(), WalkError> {
        self.steps = self.steps.saturating_add(n);
        if self.steps > self.limit {
            return Err(WalkError::TooComplex);
        }
        Ok(())
    }

    /// Octets consumed so far.
    pub fn position(&self) -> usize {
        self.pos
    }

    pub(super) fn align(&mut self, a: usize) -> Result<(), WalkError> {
        let off = self.origin + self.pos;
        let pad = (a - off % a) % a;
        self.take(pad).map(drop)
    }

    pub(super) fn take(&mut self, n: usize) -> Result<&'a [u8], WalkError> {
        let end = self.pos.checked_add(n).ok_or(WalkError::BadLength)?;
        let s = self.buf.get(self.pos..end).ok_or(WalkError::Truncated)?;
        self.pos = end;
        Ok(s)
    }

    pub(super) fn step(&mut self) -> Result<(), WalkError> {
        self.charge(1)
    }

    pub(super) fn prim(&mut self, p: Prim) -> Result<&'a [u8], WalkError> {
        self.align(p.align(self.xcdr2))?;
        self.take(p.size())
    }

    pub(super) fn uint(&mut self, bytes: &[u8]) -> u128 {
        let mut v: u128 = 0;
        if self.le {
            for b in bytes.iter().rev() {
                v = (v << 8) | u128::from(*b);
            }
        } else {
            for b in bytes {
                v = (v << 8) | u128::from(*b);
            }
        }
        v
    }

    pub(super) fn u32(&mut self) -> Result<u32, WalkError> {
        let b = self.prim(Prim::U32)?;
        Ok(self.uint(b) as u32)
    }

    /// Reads a string's length and returns its bytes (without the NUL).
    pub(super) fn string(&mut self, bound: Option<u32>, wide: bool) -> Result<&'a [u8], WalkError> {
        let n = self.u32()? as usize;
        if bound.is_some_and(|b| n > b as usize + 1) {
            return Err(WalkError::BadLength);
        }
        if wide {
            // XCDR1 wstring: the length counts 2-octet characters (no terminator).
            return self.take(n.checked_mul(2).ok_or(WalkError::BadLength)?);
        }
        let s = self.take(n)?;
        Ok(s.strip_suffix(&[0]).unwrap_or(s))
    }

    pub(super) fn count(&mut self, bound: Option<u32>) -> Result<usize, WalkError> {
        let n = self.u32()? as usize;
        if bound.is_some_and(|b| n > b as usize)
            || n > self.buf.len().saturating_sub(self.pos) + MAX_STEPS
        {
            return Err(WalkError::BadLength);
        }
        Ok(n)
    }

    /// XCDR2 puts a DHEADER before a sequence or array of non-primitive elements.
    pub(super) fn collection_header(&mut self, elem: &Ty) -> Result<(), WalkError> {
        if self.xcdr2 && !matches!(elem, Ty::Prim(_) | Ty::Enum(_)) {
            self.u32()?;
        }
        Ok(())
    }

    /// Skips one value of `ty`.
    pub fn skip(&mut self, ty: &Ty) -> Result<(), WalkError> {
        self.step()?;
        match ty {
            Ty::Prim(p) => self.prim(*p).map(drop),
            Ty::Str { bound, wide } => self.string(*bound, *wide).map(drop),
            Ty::Enum(_) => self.u32().map(drop),
            Ty::Struct(s) => s.members.iter().try_for_each(|m| self.skip(&m.ty)),
            Ty::Seq(t, bound) => {
                self.collection_header(t)?;
                let n = self.count(*bound)?;
                self.skip_n(t, n)
            }
            Ty::Array(t, n) => {
                self.collection_header(t)?;
                self.skip_n(t, *n as usize)
            }
        }
    }

    pub(super) fn skip_n(&mut self, ty: &Ty, n: usize) -> Result<(), WalkError> {
        if let Ty::Prim(p) = ty {
            // Contiguous: one alignment, then n elements.
            if n > 0 {
                self.align(p.align(self.xcdr2))?;
                self.take(p.size().checked_mul(n).ok_or(WalkError::BadLength)?)?;
            }
            return Ok(());
        }
        (0..n).try_for_each(|_| self.skip(ty))
    }

    /// Reads a value of a primitive, string or enum type.
    pub fn value(&mut self, ty: &Ty) -> Result<Option<Value>, WalkError> {
        self.step()?;
        Ok(Some(match ty {
            Ty::Prim(p) => {
                let b = self.prim(*p)?;
                let u = self.uint(b);
                match p {
                    Prim::Bool => Value::Bool(u != 0),
                    Prim::I8 => Value::Int(i128::from(u as u8 as i8)),
                    Prim::I16 => Value::Int(i128::from(u as u16 as i16)),
                    Prim::I32 => Value::Int(i128::from(u as u32 as i32)),
                    Prim::I64 => Value::Int(i128::from(u as u64 as i64)),
                    Prim::F32 => Value::Float(f64::from(f32::from_bits(u as u32))),
                    Prim::F64 => Value::Float(f64::from_bits(u as u64)),
                    Prim::F128 => return Ok(None),
                    _ => Value::Int(u as i128),
                }
            }
            Ty::Str { bound, wide: false } => {
                let octets = self.string(*bound, false)?;
                // Charged before the copy, which is the work.
                self.charge(octets.len() / STRING_OCTETS_PER_STEP)?;
                Value::Str(String::from_utf8_lossy(octets).into_owned())
            }
            Ty::Enum(e) => {
                let v = i64::from(self.u32()? as i32);
                let name = e
                    .values
                    .iter()
                    .find(|(_, x)| *x == v)
                    .map(|(n, _)| n.clone())
                    .unwrap_or_default();
                Value::Enum(v, name)
            }
            other => {
                self.skip(other)?;
                return Ok(None);
            }
        }))
    }
}

/// The serialized length of one sample of `ty` at the start of `buf` (which is at `origin`
/// in its CDR stream): the sizer that splits a WRITE_DATA sequence.
pub fn sample_len(ty: &Ty, buf: &[u8], origin: usize, le: bool) -> Option<usize> {
    let mut c = Cursor::new(buf, origin, le, false);
    c.skip(ty).ok()?;
    Some(c.position())
}

/// Re-serializes one sample of `ty` that sits at `origin` in its CDR stream (XCDR1, byte
/// order `le`) so that it aligns from its own start, as DDS expects: a sample split out of a
/// WRITE_DATA sequence at an offset that is not a multiple of 8.
pub fn rebase(ty: &Ty, buf: &[u8], origin: usize, le: bool) -> Result<Vec<u8>, WalkError> {
    let mut c = Cursor::new(buf, origin, le, false);
    let mut ignored = KeyWriter {
        out: Vec::new(),
        le,
        xcdr2: true,
    };
    let mut out = KeyWriter {
        out: Vec::with_capacity(buf.len()),
        le,
        xcdr2: false,
    };
    copy_key(ty, &mut c, &mut ignored, &mut out, false)?;
    Ok(out.out)
}
