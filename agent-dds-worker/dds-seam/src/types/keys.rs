//! A sample's key fields: the KeyHash bytes (XTypes rules) and the key-only payload of a
//! dispose or unregister.

use super::*;

/// A serialized key: the bytes of the KeyHash rule and the key-only payload.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyBytes {
    /// The KeyHash (XTypes 1.3 §7.6.8: the key fields as big-endian XCDR2, zero-padded to
    /// 16 octets when the key's maximum size fits, otherwise their MD5).
    pub hash: [u8; 16],
    /// The key fields alone, XCDR1 in the sample's byte order (a dispose's payload).
    pub payload: Vec<u8>,
}

/// Writes primitives with alignment from the start of the output.
pub(super) struct KeyWriter {
    pub(super) out: Vec<u8>,
    pub(super) le: bool,
    pub(super) xcdr2: bool,
}

impl KeyWriter {
    pub(super) fn align(&mut self, a: usize) {
        while self.out.len() % a != 0 {
            self.out.push(0);
        }
    }
    /// Writes `bytes` (a primitive in `from_le` order) in this writer's order.
    pub(super) fn prim(&mut self, p: Prim, bytes: &[u8], from_le: bool) {
        self.align(p.align(self.xcdr2));
        if from_le == self.le {
            self.out.extend_from_slice(bytes);
        } else {
            self.out.extend(bytes.iter().rev());
        }
    }
    pub(super) fn u32(&mut self, v: u32) {
        self.align(4);
        self.out.extend_from_slice(&if self.le {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        });
    }
}

/// The key of a keyed structure: where its key fields are and how large they can be.
#[derive(Debug, Clone)]
pub struct KeyDescriptor {
    ty: Arc<StructDef>,
    /// The key holder: the key fields only, nested as in the type.
    holder: Ty,
    /// The key's maximum XCDR2 size exceeds 16 octets (then the hash is an MD5).
    pub(super) md5: bool,
}

impl KeyDescriptor {
    /// The key of `ty`, or None if it has no key member.
    pub fn new(ty: Arc<StructDef>) -> Option<Self> {
        if !ty.is_keyed() {
            return None;
        }
        let Some(holder) = key_holder(&Ty::Struct(ty.clone()), &mut MAX_TYPE_WORK.clone()) else {
            tracing::warn!(r#type = %ty.name, "key too complex to describe; carried without key");
            return None;
        };
        let md5 = max_size(&holder, 0, 16, &mut MAX_TYPE_WORK.clone()).is_none();
        Some(KeyDescriptor { ty, holder, md5 })
    }

    /// The structure the key belongs to.
    pub fn ty(&self) -> &Arc<StructDef> {
        &self.ty
    }

    /// The key of a whole sample.
    /// Its payload is in the sample's byte order.
    pub fn of_sample(&self, body: &[u8], le: bool, xcdr2: bool) -> Result<KeyBytes, WalkError> {
        self.extract(&Ty::Struct(self.ty.clone()), body, le, xcdr2, true, le)
    }

    /// The key of a key-only payload (a dispose's), in the payload's byte order.
    pub fn of_key_payload(
        &self,
        body: &[u8],
        le: bool,
        xcdr2: bool,
    ) -> Result<KeyBytes, WalkError> {
        self.extract(&self.holder.clone(), body, le, xcdr2, false, le)
    }

    /// The key of a received sample (`key_only`: a dispose's key payload), with the payload
    /// as little-endian XCDR1 whatever the input's encoding.
    pub fn of_received(
        &self,
        body: &[u8],
        le: bool,
        xcdr2: bool,
        key_only: bool,
    ) -> Result<KeyBytes, WalkError> {
        if key_only {
            self.extract(&self.holder.clone(), body, le, xcdr2, false, true)
        } else {
            self.extract(&Ty::Struct(self.ty.clone()), body, le, xcdr2, true, true)
        }
    }

    pub(super) fn extract(
        &self,
        ty: &Ty,
        body: &[u8],
        le: bool,
        xcdr2: bool,
        full: bool,
        out_le: bool,
    ) -> Result<KeyBytes, WalkError> {
        let mut c = Cursor::new(body, 0, le, xcdr2);
        let mut hash = KeyWriter {
            out: Vec::new(),
            le: false,
            xcdr2: true,
        };
        let mut payload = KeyWriter {
            out: Vec::new(),
            le: out_le,
            xcdr2: false,
        };
        copy_key(ty, &mut c, &mut hash, &mut payload, full)?;
        let mut h = [0u8; 16];
        if self.md5 {
            h = md5::compute(&hash.out).0;
        } else {
            let n = hash.out.len().min(16);
            h[..n].copy_from_slice(&hash.out[..n]);
        }
        Ok(KeyBytes {
            hash: h,
            payload: payload.out,
        })
    }
}

/// The key holder of a type: for a structure, its key members (their own key holders), or
/// all members when none is a key (XTypes: a key member of a keyless struct type keys on
/// the whole value). None when building it takes more than `budget` nodes.
pub(super) fn key_holder(ty: &Ty, budget: &mut usize) -> Option<Ty> {
    *budget = budget.checked_sub(1)?;
    Some(match ty {
        Ty::Struct(s) => {
            let keyed = s.is_keyed();
            let members = s
                .members
                .iter()
                .filter(|m| !keyed || m.key)
                .map(|m| {
                    Some(Member {
                        name: m.name.clone(),
                        ty: key_holder(&m.ty, budget)?,
                        key: true,
                    })
                })
                .collect::<Option<Vec<_>>>()?;
            Ty::Struct(Arc::new(StructDef::new(s.name.clone(), members)))
        }
        Ty::Array(t, n) => Ty::Array(Box::new(key_holder(t, budget)?), *n),
        Ty::Seq(t, b) => Ty::Seq(Box::new(key_holder(t, budget)?), *b),
        other => other.clone(),
    })
}

/// The largest XCDR2 size of `ty` starting at `off`, if it is at most `limit` (None =
/// larger, unbounded, or more than `budget` nodes to visit). Every later alignment only
/// grows with the offset, so the largest lengths give the largest size.
pub(super) fn max_size(ty: &Ty, off: usize, limit: usize, budget: &mut usize) -> Option<usize> {
    *budget = budget.checked_sub(1)?;
    let align = |off: usize, a: usize| off.div_ceil(a) * a;
    let size = match ty {
        Ty::Prim(p) => align(off, p.align(true)) + p.size() - off,
        Ty::Enum(_) => align(off, 4) + 4 - off,
        Ty::Str { bound, wide } => {
            let b = (*bound)? as usize;
            align(off, 4) + 4 + if *wide { 2 * b } else { b + 1 } - off
        }
        Ty::Struct(s) => {
            let mut o = off;
            for m in &s.members {
                o += max_size(&m.ty, o, limit.checked_sub(o - off)?, budget)?;
            }
            o - off
        }
        Ty::Array(t, n) => {
            let mut o = off;
            for _ in 0..*n {
                o += max_size(t, o, limit.checked_sub(o - off)?, budget)?;
            }
            o - off
        }
        Ty::Seq(t, b) => {
            let mut o = align(off, 4) + 4;
            for _ in 0..(*b)? {
                o += max_size(t, o, limit.checked_sub(o - off)?, budget)?;
            }
            o - off
        }
    };
    (size <= limit).then_some(size)
}

/// Walks a value of `ty` from `c`, copying its key fields (all of it when `in_key`) to both
/// key writers. `full` = the input is a whole sample (non-key members are skipped); otherwise
/// it is a key holder.
pub(super) fn copy_key(
    ty: &Ty,
    c: &mut Cursor<'_>,
    hash: &mut KeyWriter,
    payload: &mut KeyWriter,
    full: bool,
) -> Result<(), WalkError> {
    c.step()?;
    match ty {
        Ty::Prim(p) => {
            let b = c.prim(*p)?;
            hash.prim(*p, b, c.le);
            payload.prim(*p, b, c.le);
        }
        Ty::Enum(_) => {
            let v = c.u32()?;
            hash.u32(v);
            payload.u32(v);
        }
        Ty::Str { bound, wide } => {
            let s = c.string(*bound, *wide)?;
            let n = if *wide { s.len() / 2 } else { s.len() + 1 } as u32;
            for w in [&mut *hash, &mut *payload] {
                w.u32(n);
                w.out.extend_from_slice(s);
                if !*wide {
                    w.out.push(0);
                }
            }
        }
        Ty::Struct(s) => {
            let keyed = s.is_keyed();
            for m in &s.members {
                // At the top a keyed struct contributes its key members only; a nested
                // struct used as a key contributes its key members, or all if it has none.
                if full && keyed && !m.key {
                    c.skip(&m.ty)?;
                } else {
                    copy_key(&m.ty, c, hash, payload, full)?;
                }
            }
        }
        Ty::Array(t, n) => {
            c.collection_header(t)?;
            for _ in 0..*n {
                copy_key(t, c, hash, payload, full)?;
            }
        }
        Ty::Seq(t, bound) => {
            c.collection_header(t)?;
            let n = c.count(*bound)?;
            hash.u32(n as u32);
            payload.u32(n as u32);
            for _ in 0..n {
                copy_key(t, c, hash, payload, full)?;
            }
        }
    }
    Ok(())
}
