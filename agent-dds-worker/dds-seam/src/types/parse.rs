//! Reading `<types>`: definitions collected by scope, then references resolved into
//! [`Ty`]s (bounded in depth, array dimensions and work).

use super::*;

/// A definition before references are resolved.
#[derive(Debug, Clone)]
pub(super) enum Def {
    Struct {
        base: Option<String>,
        members: Vec<RawMember>,
    },
    Enum(Vec<(String, i64)>),
    Typedef(RawMember),
    Const(String),
}

#[derive(Debug, Clone)]
pub(super) struct RawMember {
    pub(super) name: String,
    pub(super) type_name: String,
    pub(super) key: bool,
    pub(super) string_bound: Option<String>,
    pub(super) array_dims: Option<String>,
    pub(super) seq_bound: Option<String>,
    pub(super) scope: String,
}

#[derive(Debug, Default)]
pub(super) struct Defs {
    pub(super) items: HashMap<String, Def>,
    pub(super) order: Vec<String>,
}

pub(super) fn qualify(scope: &str, name: &str) -> String {
    if scope.is_empty() {
        name.to_string()
    } else {
        format!("{scope}::{name}")
    }
}

pub(super) fn collect(
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

pub(super) fn raw_member(
    m: Node<'_, '_>,
    scope: &str,
    owner: &str,
) -> Result<RawMember, TypeError> {
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
pub(super) fn lookup<'d>(defs: &'d Defs, scope: &str, name: &str) -> Option<(String, &'d Def)> {
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

pub(super) fn number(
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

pub(super) fn resolve_struct(
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

pub(super) fn resolve_named(
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

pub(super) fn resolve_member(
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
