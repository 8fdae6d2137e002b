//! Field paths for content filters: a path resolved against a type, and the values at
//! resolved paths read from a sample.

use super::*;

/// A field path into a structure: member indexes and element indexes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Seg {
    /// The n-th member of a structure.
    Member(usize),
    /// The n-th element of an array or sequence.
    Index(usize),
}

/// Resolves `a.b[2].c` against a structure; the path and the type it ends at.
pub fn resolve_path(ty: &Arc<StructDef>, path: &str) -> Result<(Vec<Seg>, Ty), String> {
    let mut cur = Ty::Struct(ty.clone());
    let mut segs = Vec::new();
    for part in path.split('.') {
        let (name, mut rest) = match part.find('[') {
            Some(i) => (&part[..i], &part[i..]),
            None => (part, ""),
        };
        let Ty::Struct(s) = &cur else {
            return Err(format!("{path}: {name} is not a member of a structure"));
        };
        let (i, m) = s
            .members
            .iter()
            .enumerate()
            .find(|(_, m)| m.name == name)
            .ok_or_else(|| format!("{path}: {} has no member {name}", s.name))?;
        segs.push(Seg::Member(i));
        cur = m.ty.clone();
        while let Some(r) = rest.strip_prefix('[') {
            let end = r.find(']').ok_or_else(|| format!("{path}: unclosed ["))?;
            let idx: usize = r[..end]
                .trim()
                .parse()
                .map_err(|_| format!("{path}: invalid index"))?;
            cur = match cur {
                Ty::Array(t, n) if idx < n as usize => *t,
                Ty::Seq(t, _) => *t,
                _ => return Err(format!("{path}: index {idx} out of range")),
            };
            segs.push(Seg::Index(idx));
            rest = &r[end + 1..];
        }
        if !rest.is_empty() {
            return Err(format!("{path}: unexpected {rest}"));
        }
    }
    if matches!(cur, Ty::Struct(_) | Ty::Seq(..) | Ty::Array(..)) {
        return Err(format!("{path}: not a primitive, string or enum field"));
    }
    Ok((segs, cur))
}

/// Reads the values at `paths` from one sample (None for an element beyond a sequence's
/// length).
pub fn read_fields(
    ty: &Arc<StructDef>,
    paths: &[Vec<Seg>],
    body: &[u8],
    le: bool,
    xcdr2: bool,
) -> Result<Vec<Option<Value>>, WalkError> {
    read_fields_within(ty, paths, body, le, xcdr2, MAX_STEPS).map(|(v, _)| v)
}

/// [`read_fields`] in at most `max_steps` steps of work (elements visited, string octets
/// copied; never more than the walk's own bound): the values and the steps taken, or
/// `TooComplex` when the sample needs more. Content filters walk samples within their
/// evaluation budget with it.
pub fn read_fields_within(
    ty: &Arc<StructDef>,
    paths: &[Vec<Seg>],
    body: &[u8],
    le: bool,
    xcdr2: bool,
    max_steps: usize,
) -> Result<(Vec<Option<Value>>, usize), WalkError> {
    let mut out = vec![None; paths.len()];
    let wanted: Vec<(usize, &[Seg])> = paths.iter().enumerate().map(|(i, p)| (i, &p[..])).collect();
    let mut c = Cursor::new(body, 0, le, xcdr2);
    c.limit = max_steps.min(MAX_STEPS);
    read_into(&Ty::Struct(ty.clone()), &mut c, &wanted, &mut out)?;
    Ok((out, c.steps))
}

/// A wanted field: its index among the filter's paths, and the rest of its path.
type Wanted<'p> = (usize, &'p [Seg]);

/// The wanted paths that go on through member or element `index` of the value at hand,
/// grouped by that index, in increasing order (each path looked at once, however many
/// members or elements the value has).
pub(super) fn by_index<'p>(wanted: &[Wanted<'p>], member: bool) -> Vec<(usize, Vec<Wanted<'p>>)> {
    let mut groups: Vec<(usize, Vec<Wanted<'p>>)> = Vec::new();
    for (j, p) in wanted {
        let index = match (p.first(), member) {
            (Some(Seg::Member(k)), true) | (Some(Seg::Index(k)), false) => *k,
            _ => continue,
        };
        match groups.iter_mut().find(|(k, _)| *k == index) {
            Some((_, g)) => g.push((*j, &p[1..])),
            None => groups.push((index, vec![(*j, &p[1..])])),
        }
    }
    groups.sort_by_key(|(k, _)| *k);
    groups
}

pub(super) fn read_into(
    ty: &Ty,
    c: &mut Cursor<'_>,
    wanted: &[(usize, &[Seg])],
    out: &mut [Option<Value>],
) -> Result<(), WalkError> {
    if wanted.is_empty() {
        return c.skip(ty);
    }
    if wanted.iter().any(|(_, p)| p.is_empty()) {
        let v = c.value(ty)?;
        for (j, p) in wanted {
            if p.is_empty() {
                out[*j] = v.clone();
            }
        }
        return Ok(());
    }
    match ty {
        Ty::Struct(s) => {
            let groups = by_index(wanted, true);
            let mut next = groups.iter().peekable();
            for (k, m) in s.members.iter().enumerate() {
                match next.next_if(|(i, _)| *i == k) {
                    Some((_, w)) => read_into(&m.ty, c, w, out)?,
                    None => c.skip(&m.ty)?,
                }
            }
        }
        Ty::Array(t, n) => {
            c.collection_header(t)?;
            read_elements(t, *n as usize, c, wanted, out)?;
        }
        Ty::Seq(t, bound) => {
            c.collection_header(t)?;
            let n = c.count(*bound)?;
            read_elements(t, n, c, wanted, out)?;
        }
        other => c.skip(other)?,
    }
    Ok(())
}

/// The `n` elements of an array or sequence: the wanted ones read, the runs between them
/// skipped (a run of primitives in one step).
pub(super) fn read_elements(
    t: &Ty,
    n: usize,
    c: &mut Cursor<'_>,
    wanted: &[(usize, &[Seg])],
    out: &mut [Option<Value>],
) -> Result<(), WalkError> {
    let mut at = 0;
    for (k, w) in by_index(wanted, false) {
        if k >= n {
            break;
        }
        c.skip_n(t, k - at)?;
        read_into(t, c, &w, out)?;
        at = k + 1;
    }
    c.skip_n(t, n - at)
}
