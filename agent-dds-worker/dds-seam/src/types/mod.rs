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

mod cdr;
mod fields;
mod keys;
mod parse;
#[cfg(test)]
mod tests;

pub use cdr::*;
pub use fields::*;
pub use keys::*;
use keys::{copy_key, KeyWriter};
use parse::*;
