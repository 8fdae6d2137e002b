//! Type descriptions (DDS-XML / Fast DDS `<types>`) and what the worker needs them for:
//! finding where one serialized sample ends, extracting its key fields (for the KeyHash and
//! the dispose payload), and reading field values for content filters.
//!
//! Samples are XCDR version 1 (CDR_LE / CDR_BE, primitives aligned to their size) or XCDR
//! version 2 of final types (XCDR2_LE / XCDR2_BE, alignment capped at 4). Appendable and
//! mutable XCDR2 types (with DHEADERs) are not walked: every XRCE client serializes XCDR1.

use std::collections::HashMap;
use std::sync::Arc;

use roxmltree::Node;

/// Why a `<types>` document was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TypeError {
    /// Not well-formed XML.
    #[error("types XML: {0}")]
    Xml(String),
    /// Something the worker does not model (unions, maps, bitsets...).
    #[error("type {0}: {1} is not supported")]
    Unsupported(String, String),
    /// A reference to a type that is not defined.
    #[error("type {0}: unknown type {1:?}")]
    Unknown(String, String),
    /// A malformed attribute.
    #[error("type {0}: invalid {1} {2:?}")]
    Invalid(String, &'static str, String),
    /// A type that contains itself, or nests too deep.
    #[error("type {0}: recursive or nested deeper than {MAX_DEPTH}")]
    TooDeep(String),
}

/// Deepest nesting of types the worker accepts.
pub const MAX_DEPTH: usize = 32;
/// Most dimensions of one array member.
const MAX_ARRAY_DIMENSIONS: usize = 8;
/// Most nodes a key holder or a size computation visits.
const MAX_TYPE_WORK: usize = 1 << 16;
/// Most elements a single walk visits (bounds the work one sample can cause).
const MAX_STEPS: usize = 1 << 20;
/// String octets copied (or compared, by content filters) per step of a walk's work.
pub const STRING_OCTETS_PER_STEP: usize = 16;

/// A primitive type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prim {
    /// `boolean`, one octet.
    Bool,
    /// `char8`.
    Char8,
    /// `char16` / `wchar`.
    Char16,
    /// `byte` / `octet`.
    Octet,
    /// `int8`.
    I8,
    /// `uint8`.
    U8,
    /// `int16`.
    I16,
    /// `uint16`.
    U16,
    /// `int32`.
    I32,
    /// `uint32`.
    U32,
    /// `int64`.
    I64,
    /// `uint64`.
    U64,
    /// `float32`.
    F32,
    /// `float64`.
    F64,
    /// `float128` (carried, never interpreted).
    F128,
}

impl Prim {
    /// Serialized size in octets.
    pub fn size(self) -> usize {
        match self {
            Prim::Bool | Prim::Char8 | Prim::Octet | Prim::I8 | Prim::U8 => 1,
            Prim::Char16 | Prim::I16 | Prim::U16 => 2,
            Prim::I32 | Prim::U32 | Prim::F32 => 4,
            Prim::I64 | Prim::U64 | Prim::F64 => 8,
            Prim::F128 => 16,
        }
    }

    fn align(self, xcdr2: bool) -> usize {
        let a = self.size().min(8);
        if xcdr2 {
            a.min(4)
        } else {
            a
        }
    }

    fn from_name(name: &str) -> Option<Prim> {
        Some(match name {
            "boolean" | "bool" => Prim::Bool,
            "char8" | "char" => Prim::Char8,
            "char16" | "wchar" => Prim::Char16,
            "byte" | "octet" => Prim::Octet,
            "int8" => Prim::I8,
            "uint8" => Prim::U8,
            "int16" | "short" => Prim::I16,
            "uint16" | "unsignedshort" => Prim::U16,
            "int32" | "long" => Prim::I32,
            "uint32" | "unsignedlong" => Prim::U32,
            "int64" | "longlong" => Prim::I64,
            "uint64" | "unsignedlonglong" => Prim::U64,
            "float32" | "float" => Prim::F32,
            "float64" | "double" => Prim::F64,
            "float128" | "longdouble" => Prim::F128,
            _ => return None,
        })
    }
}

/// A type, with every reference resolved.
#[derive(Debug, Clone, PartialEq)]
pub enum Ty {
    /// A primitive.
    Prim(Prim),
    /// `string` (`wide` = `wstring`), with its bound if any.
    Str {
        /// Most characters (None = unbounded).
        bound: Option<u32>,
        /// wstring.
        wide: bool,
    },
    /// An enumeration (a 32-bit value on the wire).
    Enum(Arc<EnumDef>),
    /// A structure.
    Struct(Arc<StructDef>),
    /// `sequence<T, bound>`.
    Seq(Box<Ty>, Option<u32>),
    /// `T[n]` (multi-dimensional arrays nest).
    Array(Box<Ty>, u32),
}

/// An enumeration.
#[derive(Debug, Clone, PartialEq)]
pub struct EnumDef {
    /// Fully qualified name.
    pub name: String,
    /// Enumerators and their values.
    pub values: Vec<(String, i64)>,
}

/// A structure; a base type's members come first.
#[derive(Debug, Clone, PartialEq)]
pub struct StructDef {
    /// Fully qualified name (`Module::Type`).
    pub name: String,
    /// Members in serialization order.
    pub members: Vec<Member>,
    /// Nesting depth (1 + the deepest member's), at most [`MAX_DEPTH`].
    pub depth: usize,
}

impl StructDef {
    /// A structure of these members.
    pub fn new(name: String, members: Vec<Member>) -> Self {
        let depth = 1 + members.iter().map(|m| ty_depth(&m.ty)).max().unwrap_or(0);
        StructDef {
            name,
            members,
            depth,
        }
    }
}

/// How deep a type nests (structures count their stored depth, so this is shallow).
fn ty_depth(ty: &Ty) -> usize {
    match ty {
        Ty::Prim(_) | Ty::Str { .. } | Ty::Enum(_) => 0,
        Ty::Struct(s) => s.depth,
        Ty::Seq(t, _) | Ty::Array(t, _) => 1 + ty_depth(t),
    }
}

/// A member of a structure.
#[derive(Debug, Clone, PartialEq)]
pub struct Member {
    /// Name.
    pub name: String,
    /// Type.
    pub ty: Ty,
    /// Part of the key.
    pub key: bool,
}

impl StructDef {
    /// Whether any member is a key.
    pub fn is_keyed(&self) -> bool {
        self.members.iter().any(|m| m.key)
    }
}

/// The types one `<types>` document defines, by fully qualified name.
#[derive(Debug, Clone, Default)]
pub struct TypeSet {
    structs: HashMap<String, Arc<StructDef>>,
    /// The type a TYPE object creates: the one no other type of the document uses.
    main: Option<String>,
}

impl TypeSet {
    /// Parses every `<types>` element of a document (a TYPE object's XML, or a references
    /// file); an empty set if there is none.
    pub fn parse(xml: &str) -> Result<TypeSet, TypeError> {
        let doc = roxmltree::Document::parse(xml).map_err(|e| TypeError::Xml(e.to_string()))?;
        let mut defs = Defs::default();
        for types in doc
            .descendants()
            .filter(|n| n.is_element() && n.tag_name().name() == "types")
        {
            collect(types, "", &mut defs, 0)?;
        }
        let mut resolved = HashMap::new();
        let mut used = std::collections::HashSet::new();
        for name in defs.order.clone() {
            if let Some(Def::Typedef(_)) = defs.items.get(&name) {
                // An alias is resolved so it can be found; if it names a structure, that
                // structure is what the alias gives.
                let t = resolve_named(&name, &defs, &mut resolved, 0)?;
                if !matches!(t, Ty::Struct(_)) {
                    mark_used(&t, &mut used);
                }
            }
            if let Some(Def::Struct { base, .. }) = defs.items.get(&name) {
                if let Some((b, _)) = base.as_deref().and_then(|b| {
                    let scope = name.rsplit_once("::").map(|(a, _)| a).unwrap_or_default();
                    lookup(&defs, scope, b)
                }) {
                    used.insert(b);
                }
                let s = resolve_struct(&name, &defs, &mut resolved, 0)?;
                for m in &s.members {
                    mark_used(&m.ty, &mut used);
                }
            }
        }
        let mut structs = HashMap::new();
        for (name, ty) in resolved {
            if let Ty::Struct(s) = ty {
                structs.insert(name, s);
            }
        }
        // Typedef aliases of a structure are found by name but are not types of their own.
        let mut top: Vec<&String> = defs
            .order
            .iter()
            .filter(|n| structs.get(*n).is_some_and(|s| s.name == **n) && !used.contains(*n))
            .collect();
        let main = (top.len() == 1).then(|| top.remove(0).clone());
        Ok(TypeSet { structs, main })
    }

    /// A set holding one structure (a type registered by reference).
    pub fn single(s: Arc<StructDef>) -> TypeSet {
        let name = s.name.clone();
        TypeSet {
            structs: HashMap::from([(name.clone(), s)]),
            main: Some(name),
        }
    }

    /// A structure by name: fully qualified, or its last component if that is unique.
    pub fn get(&self, name: &str) -> Option<Arc<StructDef>> {
        let name = name.trim_start_matches("::");
        if let Some(s) = self.structs.get(name) {
            return Some(s.clone());
        }
        let mut hits = self
            .structs
            .iter()
            .filter(|(k, _)| k.rsplit("::").next() == Some(name));
        match (hits.next(), hits.next()) {
            (Some((_, s)), None) => Some(s.clone()),
            _ => None,
        }
    }

    /// The structure the document creates (see [`TypeSet::parse`]), if it is unambiguous.
    pub fn main(&self) -> Option<&str> {
        self.main.as_deref()
    }

    /// Every structure defined (aliases included).
    pub fn structs(&self) -> impl Iterator<Item = &Arc<StructDef>> {
        self.structs.values()
    }

    /// Whether no type was defined.
    pub fn is_empty(&self) -> bool {
        self.structs.is_empty()
    }
}

fn mark_used(ty: &Ty, used: &mut std::collections::HashSet<String>) {
    match ty {
        Ty::Struct(s) => {
            used.insert(s.name.clone());
        }
        Ty::Seq(t, _) | Ty::Array(t, _) => mark_used(t, used),
        _ => {}
    }
}

/// A definition before references are resolved.
#[derive(Debug, Clone)]
enum Def {
    Struct {
        base: Option<String>,
        members: Vec<RawMember>,
    },
    Enum(Vec<(String, i64)>),
    Typedef(RawMember),
    Const(String),
}

#[derive(Debug, Clone)]
struct RawMember {
    name: String,
    type_name: String,
    key: bool,
    string_bound: Option<String>,
    array_dims: Option<String>,
    seq_bound: Option<String>,
    scope: String,
}

#[derive(Debug, Default)]
struct Defs {
    items: HashMap<String, Def>,
    order: Vec<String>,
}

fn qualify(scope: &str, name: &str) -> String {
    if scope.is_empty() {
        name.to_string()
    } else {
        format!("{scope}::{name}")
    }
}

fn collect(
    node: Node<'_, '_>,
    scope: &str,
    defs: &mut Defs,
    depth: usize,
) -> Result<(), TypeError> {
    if depth > MAX_DEPTH {
        return Err(TypeError::TooDeep(scope.to_string()));
    }
    for n in node.children().filter(|n| n.is_element()) {
        let tag = n.tag_name().name();
        let name = n.attribute("name").unwrap_or_default();
        let full = qualify(scope, name);
        let def = match tag {
            // Fast DDS wraps each definition in <type>.
            "type" => {
                collect(n, scope, defs, depth + 1)?;
                continue;
            }
            "module" => {
                collect(n, &full, defs, depth + 1)?;
                continue;
            }
            "struct" => Def::Struct {
                base: n.attribute("baseType").map(str::to_string),
                members: n
                    .children()
                    .filter(|m| m.is_element() && m.tag_name().name() == "member")
                    .map(|m| raw_member(m, scope, &full))
                    .collect::<Result<_, _>>()?,
            },
            "enum" => {
                let mut next = 0i64;
                let mut values = Vec::new();
                for e in n
                    .children()
                    .filter(|e| e.is_element() && e.tag_name().name() == "enumerator")
                {
                    if let Some(v) = e.attribute("value") {
                        next = v.trim().parse().map_err(|_| {
                            TypeError::Invalid(full.clone(), "enumerator value", v.into())
                        })?;
                    }
                    values.push((e.attribute("name").unwrap_or_default().to_string(), next));
                    next = next.checked_add(1).ok_or_else(|| {
                        TypeError::Invalid(full.clone(), "enumerator value", next.to_string())
                    })?;
                }
                Def::Enum(values)
            }
            "typedef" => Def::Typedef(raw_member(n, scope, &full)?),
            "const" => Def::Const(n.attribute("value").unwrap_or_default().to_string()),
            "union" | "bitset" | "bitmask" => {
                return Err(TypeError::Unsupported(full, tag.to_string()))
            }
            _ => continue,
        };
        if name.is_empty() {
            return Err(TypeError::Invalid(full, "name", String::new()));
        }
        if defs.items.insert(full.clone(), def).is_none() {
            defs.order.push(full);
        }
    }
    Ok(())
}

fn raw_member(m: Node<'_, '_>, scope: &str, owner: &str) -> Result<RawMember, TypeError> {
    let attr = |a: &str| m.attribute(a).map(str::to_string);
    let type_name = match attr("type").as_deref() {
        Some("nonBasic") | None => attr("nonBasicTypeName").unwrap_or_default(),
        Some(t) => t.to_string(),
    };
    if attr("mapMaxLength").is_some() || attr("key_type").is_some() {
        return Err(TypeError::Unsupported(owner.into(), "a map member".into()));
    }
    let key = attr("key")
        .or_else(|| attr("isKey"))
        .is_some_and(|v| v.eq_ignore_ascii_case("true") || v == "1");
    Ok(RawMember {
        name: attr("name").unwrap_or_default(),
        type_name,
        key,
        string_bound: attr("stringMaxLength"),
        array_dims: attr("arrayDimensions"),
        seq_bound: attr("sequenceMaxLength"),
        scope: scope.to_string(),
    })
}

/// Finds a name from `scope` outwards (IDL scoping).
fn lookup<'d>(defs: &'d Defs, scope: &str, name: &str) -> Option<(String, &'d Def)> {
    let name = name.trim_start_matches("::");
    let mut s = scope.to_string();
    loop {
        let full = qualify(&s, name);
        if let Some(d) = defs.items.get(&full) {
            return Some((full, d));
        }
        if s.is_empty() {
            return None;
        }
        s = s
            .rsplit_once("::")
            .map(|(a, _)| a.to_string())
            .unwrap_or_default();
    }
}

fn number(
    defs: &Defs,
    scope: &str,
    owner: &str,
    what: &'static str,
    v: &str,
) -> Result<u32, TypeError> {
    let v = v.trim();
    if let Ok(n) = v.parse::<u32>() {
        return Ok(n);
    }
    match lookup(defs, scope, v) {
        Some((_, Def::Const(c))) => c
            .trim()
            .parse()
            .map_err(|_| TypeError::Invalid(owner.into(), what, v.into())),
        _ => Err(TypeError::Invalid(owner.into(), what, v.into())),
    }
}

fn resolve_struct(
    name: &str,
    defs: &Defs,
    done: &mut HashMap<String, Ty>,
    depth: usize,
) -> Result<Arc<StructDef>, TypeError> {
    match resolve_named(name, defs, done, depth)? {
        Ty::Struct(s) => Ok(s),
        _ => Err(TypeError::Unknown(name.into(), name.into())),
    }
}

fn resolve_named(
    full: &str,
    defs: &Defs,
    done: &mut HashMap<String, Ty>,
    depth: usize,
) -> Result<Ty, TypeError> {
    if let Some(t) = done.get(full) {
        return Ok(t.clone());
    }
    if depth > MAX_DEPTH {
        return Err(TypeError::TooDeep(full.into()));
    }
    let scope = full.rsplit_once("::").map(|(a, _)| a).unwrap_or_default();
    let ty = match defs.items.get(full) {
        Some(Def::Struct { base, members }) => {
            let mut all = Vec::new();
            if let Some(b) = base {
                let (bfull, _) = lookup(defs, scope, b)
                    .ok_or_else(|| TypeError::Unknown(full.into(), b.clone()))?;
                all.extend(
                    resolve_struct(&bfull, defs, done, depth + 1)?
                        .members
                        .iter()
                        .cloned(),
                );
            }
            for m in members {
                all.push(Member {
                    name: m.name.clone(),
                    ty: resolve_member(m, full, defs, done, depth + 1)?,
                    key: m.key,
                });
            }
            Ty::Struct(Arc::new(StructDef::new(full.to_string(), all)))
        }
        Some(Def::Enum(values)) => Ty::Enum(Arc::new(EnumDef {
            name: full.to_string(),
            values: values.clone(),
        })),
        Some(Def::Typedef(m)) => resolve_member(m, full, defs, done, depth + 1)?,
        Some(Def::Const(_)) | None => return Err(TypeError::Unknown(full.into(), full.into())),
    };
    // Types defined in dependency order resolve one level at a time, so the depth check
    // above alone would not bound them.
    if ty_depth(&ty) > MAX_DEPTH {
        return Err(TypeError::TooDeep(full.into()));
    }
    done.insert(full.to_string(), ty.clone());
    Ok(ty)
}

fn resolve_member(
    m: &RawMember,
    owner: &str,
    defs: &Defs,
    done: &mut HashMap<String, Ty>,
    depth: usize,
) -> Result<Ty, TypeError> {
    let bound = |v: &Option<String>, what| -> Result<Option<u32>, TypeError> {
        match v.as_deref().map(str::trim) {
            None | Some("") | Some("-1") => Ok(None),
            Some(v) => number(defs, &m.scope, owner, what, v).map(Some),
        }
    };
    let tname = m.type_name.as_str();
    let mut ty = if let Some(p) = Prim::from_name(tname) {
        Ty::Prim(p)
    } else if tname == "string" || tname == "wstring" {
        Ty::Str {
            bound: bound(&m.string_bound, "stringMaxLength")?,
            wide: tname == "wstring",
        }
    } else {
        let (full, _) = lookup(defs, &m.scope, tname)
            .ok_or_else(|| TypeError::Unknown(owner.into(), tname.into()))?;
        resolve_named(&full, defs, done, depth + 1)?
    };
    if let Some(b) = m.seq_bound.as_deref() {
        ty = Ty::Seq(
            Box::new(ty),
            bound(&Some(b.to_string()), "sequenceMaxLength")?,
        );
    }
    if let Some(dims) = m.array_dims.as_deref().filter(|d| !d.trim().is_empty()) {
        let dims: Vec<u32> = dims
            .split(',')
            .map(|d| number(defs, &m.scope, owner, "arrayDimensions", d))
            .collect::<Result<_, _>>()?;
        if dims.len() > MAX_ARRAY_DIMENSIONS {
            return Err(TypeError::Invalid(
                owner.into(),
                "arrayDimensions",
                format!("{} dimensions", dims.len()),
            ));
        }
        for d in dims.into_iter().rev() {
            ty = Ty::Array(Box::new(ty), d);
        }
    }
    Ok(ty)
}

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
    buf: &'a [u8],
    pos: usize,
    /// Alignment origin (offset of the body start in the CDR stream).
    origin: usize,
    le: bool,
    xcdr2: bool,
    steps: usize,
    /// Most steps the walk may take ([`MAX_STEPS`] unless a caller gave less).
    limit: usize,
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
    fn charge(&mut self, n: usize) -> Result<(), WalkError> {
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

    fn align(&mut self, a: usize) -> Result<(), WalkError> {
        let off = self.origin + self.pos;
        let pad = (a - off % a) % a;
        self.take(pad).map(drop)
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], WalkError> {
        let end = self.pos.checked_add(n).ok_or(WalkError::BadLength)?;
        let s = self.buf.get(self.pos..end).ok_or(WalkError::Truncated)?;
        self.pos = end;
        Ok(s)
    }

    fn step(&mut self) -> Result<(), WalkError> {
        self.charge(1)
    }

    fn prim(&mut self, p: Prim) -> Result<&'a [u8], WalkError> {
        self.align(p.align(self.xcdr2))?;
        self.take(p.size())
    }

    fn uint(&mut self, bytes: &[u8]) -> u128 {
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

    fn u32(&mut self) -> Result<u32, WalkError> {
        let b = self.prim(Prim::U32)?;
        Ok(self.uint(b) as u32)
    }

    /// Reads a string's length and returns its bytes (without the NUL).
    fn string(&mut self, bound: Option<u32>, wide: bool) -> Result<&'a [u8], WalkError> {
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

    fn count(&mut self, bound: Option<u32>) -> Result<usize, WalkError> {
        let n = self.u32()? as usize;
        if bound.is_some_and(|b| n > b as usize)
            || n > self.buf.len().saturating_sub(self.pos) + MAX_STEPS
        {
            return Err(WalkError::BadLength);
        }
        Ok(n)
    }

    /// XCDR2 puts a DHEADER before a sequence or array of non-primitive elements.
    fn collection_header(&mut self, elem: &Ty) -> Result<(), WalkError> {
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

    fn skip_n(&mut self, ty: &Ty, n: usize) -> Result<(), WalkError> {
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
struct KeyWriter {
    out: Vec<u8>,
    le: bool,
    xcdr2: bool,
}

impl KeyWriter {
    fn align(&mut self, a: usize) {
        while self.out.len() % a != 0 {
            self.out.push(0);
        }
    }
    /// Writes `bytes` (a primitive in `from_le` order) in this writer's order.
    fn prim(&mut self, p: Prim, bytes: &[u8], from_le: bool) {
        self.align(p.align(self.xcdr2));
        if from_le == self.le {
            self.out.extend_from_slice(bytes);
        } else {
            self.out.extend(bytes.iter().rev());
        }
    }
    fn u32(&mut self, v: u32) {
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
    md5: bool,
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

    fn extract(
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
fn key_holder(ty: &Ty, budget: &mut usize) -> Option<Ty> {
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
fn max_size(ty: &Ty, off: usize, limit: usize, budget: &mut usize) -> Option<usize> {
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
fn copy_key(
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
fn by_index<'p>(wanted: &[Wanted<'p>], member: bool) -> Vec<(usize, Vec<Wanted<'p>>)> {
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

fn read_into(
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
fn read_elements(
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

#[cfg(test)]
mod tests {
    use super::*;

    const SHAPES: &str = r#"<dds><types>
        <module name="ShapesDemoTypes">
          <const name="MAX_COLOR_LEN" type="int32" value="128"/>
          <struct name="ShapeType">
            <member name="color" key="true" type="string" stringMaxLength="MAX_COLOR_LEN"/>
            <member name="x" type="int32"/>
            <member name="y" type="int32"/>
            <member name="shapesize" type="int32"/>
          </struct>
        </module></types></dds>"#;

    fn shape(color: &str, x: i32, le: bool) -> Vec<u8> {
        let mut b = Vec::new();
        let n = color.len() as u32 + 1;
        b.extend(if le { n.to_le_bytes() } else { n.to_be_bytes() });
        b.extend(color.as_bytes());
        b.push(0);
        while b.len() % 4 != 0 {
            b.push(0);
        }
        for v in [x, 2, 30] {
            b.extend(if le { v.to_le_bytes() } else { v.to_be_bytes() });
        }
        b
    }

    #[test]
    fn dds_xml_types_with_modules_and_consts() {
        let t = TypeSet::parse(SHAPES).expect("test value");
        assert_eq!(t.main(), Some("ShapesDemoTypes::ShapeType"));
        let s = t.get("ShapeType").expect("test value");
        assert_eq!(s.name, "ShapesDemoTypes::ShapeType");
        assert_eq!(
            s.members[0].ty,
            Ty::Str {
                bound: Some(128),
                wide: false
            }
        );
        assert!(s.members[0].key && !s.members[1].key);
    }

    #[test]
    fn fast_dds_types_with_nested_arrays_sequences_enums_and_inheritance() {
        let xml = r#"<types>
          <type><enum name="Mode"><enumerator name="OFF"/><enumerator name="ON" value="5"/></enum></type>
          <type><struct name="Inner"><member name="a" type="uint16"/><member name="b" type="float64"/></struct></type>
          <type><struct name="Base"><member name="id" type="uint64" key="true"/></struct></type>
          <type><struct name="Outer" baseType="Base">
            <member name="mode" type="nonBasic" nonBasicTypeName="Mode"/>
            <member name="inner" type="nonBasic" nonBasicTypeName="Inner" arrayDimensions="2,3"/>
            <member name="vals" type="int32" sequenceMaxLength="10"/>
            <member name="tag" type="char8"/>
          </struct></type></types>"#;
        let t = TypeSet::parse(xml).expect("test value");
        assert_eq!(t.main(), Some("Outer"));
        let s = t.get("Outer").expect("test value");
        assert_eq!(s.members.len(), 5);
        assert_eq!(s.members[0].name, "id");
        assert!(s.members[0].key);
        match &s.members[2].ty {
            Ty::Array(inner, 2) => assert!(matches!(&**inner, Ty::Array(_, 3))),
            other => panic!("{other:?}"),
        }
        match &s.members[1].ty {
            Ty::Enum(e) => assert_eq!(e.values, vec![("OFF".into(), 0), ("ON".into(), 5)]),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn unknown_recursive_and_unsupported_types_are_refused() {
        let unknown = r#"<types><struct name="A"><member name="x" type="nonBasic" nonBasicTypeName="Nope"/></struct></types>"#;
        assert!(matches!(
            TypeSet::parse(unknown),
            Err(TypeError::Unknown(..))
        ));
        let rec = r#"<types><struct name="A"><member name="x" type="nonBasic" nonBasicTypeName="A"/></struct></types>"#;
        assert!(matches!(TypeSet::parse(rec), Err(TypeError::TooDeep(_))));
        let union = r#"<types><union name="U"/></types>"#;
        assert!(matches!(
            TypeSet::parse(union),
            Err(TypeError::Unsupported(..))
        ));
        let map = r#"<types><struct name="A"><member name="m" type="int32" key_type="int32" mapMaxLength="3"/></struct></types>"#;
        assert!(matches!(
            TypeSet::parse(map),
            Err(TypeError::Unsupported(..))
        ));
    }

    #[test]
    fn key_of_a_string_key_is_md5_of_its_big_endian_form_in_either_byte_order() {
        let t = TypeSet::parse(SHAPES).expect("test value");
        let k = KeyDescriptor::new(t.get("ShapeType").expect("test value")).expect("test value");
        let le = k
            .of_sample(&shape("RED", 7, true), true, false)
            .expect("test value");
        let be = k
            .of_sample(&shape("RED", 9, false), false, false)
            .expect("test value");
        assert_eq!(
            le.hash, be.hash,
            "the hash is independent of byte order and non-key fields"
        );
        // string<128> can exceed 16 octets: MD5 of 00 00 00 04 'R' 'E' 'D' 00.
        assert_eq!(le.hash, md5::compute([0, 0, 0, 4, b'R', b'E', b'D', 0]).0);
        assert_eq!(le.payload, vec![4, 0, 0, 0, b'R', b'E', b'D', 0]);
        assert_eq!(be.payload, vec![0, 0, 0, 4, b'R', b'E', b'D', 0]);
        // The dispose payload gives the same key back.
        assert_eq!(
            k.of_key_payload(&le.payload, true, false)
                .expect("test value"),
            le
        );
        let other = k
            .of_sample(&shape("BLUE", 7, true), true, false)
            .expect("test value");
        assert_ne!(other.hash, le.hash);
    }

    #[test]
    fn small_keys_are_zero_padded_big_endian() {
        let xml = r#"<types><struct name="Sensor">
            <member name="id" type="uint8" key="true" arrayDimensions="4"/>
            <member name="value" type="int16"/>
            <member name="unit" type="uint32" key="true"/></struct></types>"#;
        let t = TypeSet::parse(xml).expect("test value");
        let k = KeyDescriptor::new(t.get("Sensor").expect("test value")).expect("test value");
        let body = [1, 2, 3, 4, 0x10, 0x00, 0, 0, 0x78, 0x56, 0x34, 0x12];
        let key = k.of_sample(&body, true, false).expect("test value");
        let mut want = [0u8; 16];
        want[..8].copy_from_slice(&[1, 2, 3, 4, 0x12, 0x34, 0x56, 0x78]);
        assert_eq!(key.hash, want);
        assert_eq!(key.payload, vec![1, 2, 3, 4, 0x78, 0x56, 0x34, 0x12]);
    }

    #[test]
    fn eight_byte_members_align_to_8_in_xcdr1_and_4_in_the_xcdr2_hash() {
        let xml = r#"<types><struct name="K"><member name="a" type="uint8" key="true"/>
            <member name="b" type="int64" key="true"/></struct></types>"#;
        let t = TypeSet::parse(xml).expect("test value");
        let k = KeyDescriptor::new(t.get("K").expect("test value")).expect("test value");
        let mut body = vec![9, 0, 0, 0, 0, 0, 0, 0];
        body.extend(5i64.to_le_bytes());
        let key = k.of_sample(&body, true, false).expect("test value");
        let mut want = [0u8; 16];
        want[0] = 9;
        want[4..12].copy_from_slice(&5i64.to_be_bytes());
        assert_eq!(key.hash, want);
        assert_eq!(key.payload, body);
        assert_eq!(
            sample_len(&Ty::Struct(t.get("K").expect("test value")), &body, 0, true),
            Some(16)
        );
    }

    #[test]
    fn truncated_and_oversized_samples_are_errors_not_panics() {
        let t = TypeSet::parse(SHAPES).expect("test value");
        let k = KeyDescriptor::new(t.get("ShapeType").expect("test value")).expect("test value");
        let s = shape("RED", 1, true);
        for n in 0..s.len() {
            assert!(k.of_sample(&s[..n], true, false).is_err() || n >= 8);
        }
        // A string length beyond the bound.
        let mut bad = s.clone();
        bad[..4].copy_from_slice(&500u32.to_le_bytes());
        assert_eq!(k.of_sample(&bad, true, false), Err(WalkError::BadLength));
        // A huge sequence count of empty elements.
        let xml = r#"<types><struct name="E"/><struct name="S"><member name="v" type="nonBasic" nonBasicTypeName="E" sequenceMaxLength="-1"/></struct></types>"#;
        let t = TypeSet::parse(xml).expect("test value");
        let ty = Ty::Struct(t.get("S").expect("test value"));
        assert_eq!(sample_len(&ty, &u32::MAX.to_le_bytes(), 0, true), None);
    }

    #[test]
    fn hostile_type_documents_are_refused_or_bounded() {
        // Structures defined in dependency order, each containing the previous one.
        let mut chain =
            String::from("<types><struct name=\"S0\"><member name=\"v\" type=\"int8\"/></struct>");
        for i in 1..200 {
            chain += &format!(
                "<struct name=\"S{i}\"><member name=\"v\" type=\"nonBasic\" nonBasicTypeName=\"S{}\"/></struct>",
                i - 1
            );
        }
        chain += "</types>";
        assert!(matches!(TypeSet::parse(&chain), Err(TypeError::TooDeep(_))));
        // The same with typedefs of arrays.
        let mut defs =
            String::from("<types><typedef name=\"T0\" type=\"int8\" arrayDimensions=\"2\"/>");
        for i in 1..200 {
            defs += &format!(
                "<typedef name=\"T{i}\" type=\"nonBasic\" nonBasicTypeName=\"T{}\" arrayDimensions=\"2\"/>",
                i - 1
            );
        }
        defs += "<struct name=\"U\"><member name=\"v\" type=\"nonBasic\" nonBasicTypeName=\"T199\"/></struct></types>";
        assert!(matches!(TypeSet::parse(&defs), Err(TypeError::TooDeep(_))));
        // Deeply nested modules.
        let deep = "<module name=\"m\">".repeat(500) + &"</module>".repeat(500);
        assert!(TypeSet::parse(&format!("<types>{deep}</types>")).is_err());
        // Too many array dimensions; an enumerator counting past i64::MAX.
        let dims = format!(
            "<types><struct name=\"A\"><member name=\"v\" type=\"int8\" arrayDimensions=\"{}\"/></struct></types>",
            vec!["1"; 50].join(",")
        );
        assert!(TypeSet::parse(&dims).is_err());
        let en = r#"<types><enum name="E"><enumerator name="A" value="9223372036854775807"/><enumerator name="B"/></enum></types>"#;
        assert!(matches!(TypeSet::parse(en), Err(TypeError::Invalid(..))));
        // A huge key array: its size is settled without visiting every element.
        let big = r#"<types><struct name="K"><member name="k" type="int8" key="true" arrayDimensions="4096,4096,4096"/></struct></types>"#;
        let t = TypeSet::parse(big).expect("valid");
        // Without the work budget this would visit 4096^3 elements.
        let k = KeyDescriptor::new(t.get("K").expect("K")).expect("keyed");
        assert!(k.md5);
    }

    #[test]
    fn a_typedef_alias_of_a_struct_is_not_a_second_main_type() {
        let xml = r#"<types><struct name="P"><member name="x" type="int32"/></struct>
            <typedef name="Alias" type="nonBasic" nonBasicTypeName="P"/></types>"#;
        let t = TypeSet::parse(xml).expect("valid");
        assert_eq!(t.main(), Some("P"));
        assert_eq!(t.get("Alias").map(|s| s.name.clone()), Some("P".into()));
    }

    #[test]
    fn rebase_realigns_a_sample_split_at_an_offset() {
        let xml = r#"<types><struct name="D"><member name="a" type="uint32"/><member name="b" type="float64"/></struct></types>"#;
        let t = TypeSet::parse(xml).expect("valid");
        let ty = Ty::Struct(t.get("D").expect("D"));
        // At stream offset 4: a (4 bytes) then b aligned to 8 in the stream (no padding).
        let mut at4 = 7u32.to_le_bytes().to_vec();
        at4.extend(2.5f64.to_le_bytes());
        assert_eq!(sample_len(&ty, &at4, 4, true), Some(12));
        let rebased = rebase(&ty, &at4, 4, true).expect("rebase");
        let mut want = 7u32.to_le_bytes().to_vec();
        want.extend([0; 4]);
        want.extend(2.5f64.to_le_bytes());
        assert_eq!(rebased, want);
    }

    #[test]
    fn xcdr2_sequences_of_strings_have_a_dheader() {
        let xml = r#"<types><struct name="N"><member name="names" type="string" sequenceMaxLength="-1"/>
            <member name="id" type="uint16" key="true"/></struct></types>"#;
        let t = TypeSet::parse(xml).expect("valid");
        let n = t.get("N").expect("N");
        let mut b = Vec::new();
        b.extend(10u32.to_le_bytes()); // DHEADER: the 10 bytes that follow
        b.extend(1u32.to_le_bytes());
        b.extend(2u32.to_le_bytes());
        b.extend(b"a\0");
        b.extend(9u16.to_le_bytes());
        let (path, _) = resolve_path(&n, "id").expect("id");
        let v = read_fields(&n, &[path], &b, true, true).expect("XCDR2");
        assert_eq!(v, vec![Some(Value::Int(9))]);
    }

    #[test]
    fn fields_are_read_by_path() {
        let xml = r#"<types><struct name="P"><member name="x" type="float32"/><member name="y" type="float32"/></struct>
            <struct name="M"><member name="name" type="string"/><member name="pos" type="nonBasic" nonBasicTypeName="P"/>
            <member name="hist" type="int16" sequenceMaxLength="-1"/></struct></types>"#;
        let t = TypeSet::parse(xml).expect("test value");
        let m = t.get("M").expect("test value");
        let mut b = Vec::new();
        b.extend(3u32.to_le_bytes());
        b.extend(b"ab\0\0");
        b.extend(1.5f32.to_le_bytes());
        b.extend((-2.0f32).to_le_bytes());
        b.extend(2u32.to_le_bytes());
        b.extend(7i16.to_le_bytes());
        b.extend((-8i16).to_le_bytes());
        let paths: Vec<Vec<Seg>> = ["pos.y", "name", "hist[1]", "hist[5]"]
            .iter()
            .map(|p| resolve_path(&m, p).expect("test value").0)
            .collect();
        let v = read_fields(&m, &paths, &b, true, false).expect("test value");
        assert_eq!(
            v,
            vec![
                Some(Value::Float(-2.0)),
                Some(Value::Str("ab".into())),
                Some(Value::Int(-8)),
                None
            ]
        );
        assert!(resolve_path(&m, "pos").is_err());
        assert!(resolve_path(&m, "nope").is_err());
    }
}
