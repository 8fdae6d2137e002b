//! Content filters: the SQL subset of DDS 1.4 Annex B ("Syntax for Queries and Filters"),
//! compiled against a type description and evaluated on serialized samples in the worker
//! (RustDDS has no content-filtered topics).
//!
//! Grammar: `Condition := Predicate | Condition AND|OR Condition | NOT Condition | (Condition)`;
//! `Predicate := Field RelOp Value | Value RelOp Field | Field RelOp Field | Field [NOT]
//! BETWEEN Value AND Value`; `RelOp := = | <> | != | < | <= | > | >= | LIKE`; values are
//! integers (decimal or 0x hex), floats, `'strings'`, TRUE/FALSE and enumerator names.
//! Parameters (`%n`) are refused: an XRCE read carries none.

use std::sync::Arc;

use crate::types::{read_fields, resolve_path, Seg, StructDef, Ty, Value};

/// Longest expression accepted (octets).
const MAX_EXPRESSION: usize = 4096;
/// Deepest nesting of conditions.
const MAX_NESTING: usize = 64;

/// A compiled filter.
#[derive(Debug, Clone)]
pub struct Filter {
    ty: Arc<StructDef>,
    paths: Vec<Vec<Seg>>,
    root: Cond,
    text: String,
}

#[derive(Debug, Clone)]
enum Cond {
    And(Box<Cond>, Box<Cond>),
    Or(Box<Cond>, Box<Cond>),
    Not(Box<Cond>),
    Cmp(Operand, Op, Operand),
    Between(usize, Operand, Operand, bool),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Op {
    Eq,
    Ne,
    Lt,
    Le,
    Gt,
    Ge,
    Like,
}

#[derive(Debug, Clone)]
enum Operand {
    /// Index into the filter's paths.
    Field(usize),
    Const(Value),
}

#[derive(Debug, Clone, PartialEq)]
enum Tok {
    Ident(String),
    Int(i128),
    Float(f64),
    Str(String),
    Op(Op),
    LParen,
    RParen,
    Param,
}

fn tokenize(s: &str) -> Result<Vec<Tok>, String> {
    let b = s.as_bytes();
    let mut i = 0;
    let mut out = Vec::new();
    while i < b.len() {
        let c = b[i];
        match c {
            b' ' | b'\t' | b'\r' | b'\n' => i += 1,
            b'(' => {
                out.push(Tok::LParen);
                i += 1;
            }
            b')' => {
                out.push(Tok::RParen);
                i += 1;
            }
            b'%' => {
                out.push(Tok::Param);
                i += 1;
            }
            b'=' => {
                out.push(Tok::Op(Op::Eq));
                i += if b.get(i + 1) == Some(&b'=') { 2 } else { 1 };
            }
            b'!' if b.get(i + 1) == Some(&b'=') => {
                out.push(Tok::Op(Op::Ne));
                i += 2;
            }
            b'<' => match b.get(i + 1) {
                Some(b'=') => {
                    out.push(Tok::Op(Op::Le));
                    i += 2;
                }
                Some(b'>') => {
                    out.push(Tok::Op(Op::Ne));
                    i += 2;
                }
                _ => {
                    out.push(Tok::Op(Op::Lt));
                    i += 1;
                }
            },
            b'>' => {
                if b.get(i + 1) == Some(&b'=') {
                    out.push(Tok::Op(Op::Ge));
                    i += 2;
                } else {
                    out.push(Tok::Op(Op::Gt));
                    i += 1;
                }
            }
            b'\'' | b'"' | b'`' => {
                // `text' is the spec's other quoting.
                let close = if c == b'`' { b'\'' } else { c };
                let start = i + 1;
                let end = b[start..]
                    .iter()
                    .position(|&x| x == close)
                    .ok_or("unterminated string")?;
                out.push(Tok::Str(s[start..start + end].to_string()));
                i = start + end + 1;
            }
            b'0'..=b'9' | b'-' | b'+' | b'.' => {
                let start = i;
                i += 1;
                while i < b.len()
                    && (b[i].is_ascii_alphanumeric()
                        || b[i] == b'.'
                        || ((b[i] == b'-' || b[i] == b'+') && matches!(b[i - 1], b'e' | b'E')))
                {
                    i += 1;
                }
                let t = &s[start..i];
                let (neg, digits) = match t.strip_prefix('-') {
                    Some(d) => (true, d),
                    None => (false, t.trim_start_matches('+')),
                };
                let tok = if let Some(h) = digits
                    .strip_prefix("0x")
                    .or_else(|| digits.strip_prefix("0X"))
                {
                    let v = i128::from_str_radix(h, 16).map_err(|_| format!("bad number {t}"))?;
                    Tok::Int(if neg { -v } else { v })
                } else if let Ok(v) = t.parse::<i128>() {
                    Tok::Int(v)
                } else {
                    Tok::Float(t.parse::<f64>().map_err(|_| format!("bad number {t}"))?)
                };
                out.push(tok);
            }
            c if c.is_ascii_alphabetic() || c == b'_' => {
                let start = i;
                while i < b.len()
                    && (b[i].is_ascii_alphanumeric() || matches!(b[i], b'_' | b'.' | b'[' | b']'))
                {
                    i += 1;
                }
                out.push(Tok::Ident(s[start..i].to_string()));
            }
            _ => return Err(format!("unexpected character {:?}", c as char)),
        }
    }
    Ok(out)
}

struct Parser<'t> {
    toks: &'t [Tok],
    pos: usize,
    ty: Arc<StructDef>,
    paths: Vec<Vec<Seg>>,
    types: Vec<Ty>,
    depth: usize,
}

fn keyword(t: Option<&Tok>, k: &str) -> bool {
    matches!(t, Some(Tok::Ident(s)) if s.eq_ignore_ascii_case(k))
}

impl Parser<'_> {
    fn peek(&self) -> Option<&Tok> {
        self.toks.get(self.pos)
    }
    fn next(&mut self) -> Option<Tok> {
        let t = self.toks.get(self.pos).cloned();
        self.pos += 1;
        t
    }

    fn or(&mut self) -> Result<Cond, String> {
        let mut l = self.and()?;
        while keyword(self.peek(), "OR") {
            self.pos += 1;
            l = Cond::Or(Box::new(l), Box::new(self.and()?));
        }
        Ok(l)
    }

    fn and(&mut self) -> Result<Cond, String> {
        let mut l = self.not()?;
        while keyword(self.peek(), "AND") {
            self.pos += 1;
            l = Cond::And(Box::new(l), Box::new(self.not()?));
        }
        Ok(l)
    }

    fn not(&mut self) -> Result<Cond, String> {
        self.depth += 1;
        if self.depth > MAX_NESTING {
            return Err("expression nested too deep".into());
        }
        let c = if keyword(self.peek(), "NOT") {
            self.pos += 1;
            Cond::Not(Box::new(self.not()?))
        } else if self.peek() == Some(&Tok::LParen) {
            self.pos += 1;
            let c = self.or()?;
            if self.next() != Some(Tok::RParen) {
                return Err("missing )".into());
            }
            c
        } else {
            self.predicate()?
        };
        self.depth -= 1;
        Ok(c)
    }

    fn field(&mut self, name: &str) -> Result<usize, String> {
        let (segs, ty) = resolve_path(&self.ty, name)?;
        if let Some(i) = self.paths.iter().position(|p| *p == segs) {
            return Ok(i);
        }
        self.paths.push(segs);
        self.types.push(ty);
        Ok(self.paths.len() - 1)
    }

    fn operand(&mut self) -> Result<Operand, String> {
        match self.next() {
            Some(Tok::Int(v)) => Ok(Operand::Const(Value::Int(v))),
            Some(Tok::Float(v)) => Ok(Operand::Const(Value::Float(v))),
            Some(Tok::Str(v)) => Ok(Operand::Const(Value::Str(v))),
            Some(Tok::Param) => {
                Err("parameters (%n) are not supported: a read carries none".into())
            }
            Some(Tok::Ident(s)) if s.eq_ignore_ascii_case("TRUE") => {
                Ok(Operand::Const(Value::Bool(true)))
            }
            Some(Tok::Ident(s)) if s.eq_ignore_ascii_case("FALSE") => {
                Ok(Operand::Const(Value::Bool(false)))
            }
            Some(Tok::Ident(s)) => match self.field(&s) {
                Ok(i) => Ok(Operand::Field(i)),
                // An enumerator name of some enum field.
                Err(e) => self
                    .types
                    .iter()
                    .chain(self.ty.members.iter().map(|m| &m.ty))
                    .find_map(|t| match t {
                        Ty::Enum(en) => en
                            .values
                            .iter()
                            .find(|(n, _)| *n == s)
                            .map(|(n, v)| Operand::Const(Value::Enum(*v, n.clone()))),
                        _ => None,
                    })
                    .ok_or(e),
            },
            Some(t) => Err(format!("unexpected {t:?}")),
            None => Err("unexpected end of expression".into()),
        }
    }

    fn predicate(&mut self) -> Result<Cond, String> {
        let l = self.operand()?;
        let negated = keyword(self.peek(), "NOT");
        if negated {
            self.pos += 1;
        }
        if keyword(self.peek(), "BETWEEN") {
            self.pos += 1;
            let Operand::Field(f) = l else {
                return Err("BETWEEN needs a field on its left".into());
            };
            let lo = self.operand()?;
            if !keyword(self.peek(), "AND") {
                return Err("BETWEEN without AND".into());
            }
            self.pos += 1;
            let hi = self.operand()?;
            return Ok(Cond::Between(f, lo, hi, negated));
        }
        if negated {
            return Err("NOT must be followed by BETWEEN here".into());
        }
        let op = match self.next() {
            Some(Tok::Op(op)) => op,
            Some(Tok::Ident(s)) if s.eq_ignore_ascii_case("LIKE") => Op::Like,
            other => return Err(format!("expected a comparison, found {other:?}")),
        };
        let r = self.operand()?;
        if !matches!((&l, &r), (Operand::Field(_), _) | (_, Operand::Field(_))) {
            return Err("a comparison needs at least one field".into());
        }
        Ok(Cond::Cmp(l, op, r))
    }
}

impl Filter {
    /// Compiles `expression` against the structure `ty`.
    pub fn compile(expression: &str, ty: Arc<StructDef>) -> Result<Filter, String> {
        if expression.len() > MAX_EXPRESSION {
            return Err(format!("expression longer than {MAX_EXPRESSION} octets"));
        }
        let toks = tokenize(expression)?;
        let mut p = Parser {
            toks: &toks,
            pos: 0,
            ty: ty.clone(),
            paths: Vec::new(),
            types: Vec::new(),
            depth: 0,
        };
        let root = p.or()?;
        if p.pos != toks.len() {
            return Err(format!("unexpected {:?}", toks[p.pos]));
        }
        Ok(Filter {
            ty,
            paths: p.paths,
            root,
            text: expression.to_string(),
        })
    }

    /// The expression as given.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// Whether a sample passes; a sample that cannot be walked does not.
    pub fn matches(&self, body: &[u8], le: bool, xcdr2: bool) -> bool {
        match read_fields(&self.ty, &self.paths, body, le, xcdr2) {
            Ok(values) => eval(&self.root, &values),
            Err(_) => false,
        }
    }
}

fn value_of<'v>(o: &'v Operand, values: &'v [Option<Value>]) -> Option<&'v Value> {
    match o {
        Operand::Field(i) => values.get(*i)?.as_ref(),
        Operand::Const(v) => Some(v),
    }
}

fn eval(c: &Cond, values: &[Option<Value>]) -> bool {
    match c {
        Cond::And(a, b) => eval(a, values) && eval(b, values),
        Cond::Or(a, b) => eval(a, values) || eval(b, values),
        Cond::Not(a) => !eval(a, values),
        Cond::Cmp(l, op, r) => {
            let (Some(l), Some(r)) = (value_of(l, values), value_of(r, values)) else {
                return false;
            };
            if *op == Op::Like {
                return match (l, r) {
                    (Value::Str(s), Value::Str(p)) => like(s.as_bytes(), p.as_bytes()),
                    _ => false,
                };
            }
            match compare(l, r) {
                Some(o) => match op {
                    Op::Eq => o.is_eq(),
                    Op::Ne => o.is_ne(),
                    Op::Lt => o.is_lt(),
                    Op::Le => o.is_le(),
                    Op::Gt => o.is_gt(),
                    Op::Ge => o.is_ge(),
                    Op::Like => false,
                },
                None => false,
            }
        }
        Cond::Between(f, lo, hi, negated) => {
            let (Some(v), Some(lo), Some(hi)) = (
                values.get(*f).and_then(Option::as_ref),
                value_of(lo, values),
                value_of(hi, values),
            ) else {
                return false;
            };
            let inside = compare(v, lo).is_some_and(|o| o.is_ge())
                && compare(v, hi).is_some_and(|o| o.is_le());
            inside != *negated
        }
    }
}

fn compare(a: &Value, b: &Value) -> Option<std::cmp::Ordering> {
    use Value::*;
    match (a, b) {
        (Int(x), Int(y)) => Some(x.cmp(y)),
        (Int(x), Float(y)) => (*x as f64).partial_cmp(y),
        (Float(x), Int(y)) => x.partial_cmp(&(*y as f64)),
        (Float(x), Float(y)) => x.partial_cmp(y),
        (Bool(x), Bool(y)) => Some(x.cmp(y)),
        (Str(x), Str(y)) => Some(x.cmp(y)),
        (Enum(x, _), Enum(y, _)) => Some(x.cmp(y)),
        (Enum(x, _), Int(y)) => Some(i128::from(*x).cmp(y)),
        (Int(x), Enum(y, _)) => Some(x.cmp(&i128::from(*y))),
        (Enum(_, n), Str(s)) | (Str(s), Enum(_, n)) => Some(n.cmp(s)),
        // A one-character string against a char field.
        (Int(x), Str(s)) if s.len() == 1 => Some(x.cmp(&i128::from(s.as_bytes()[0]))),
        (Str(s), Int(x)) if s.len() == 1 => Some(i128::from(s.as_bytes()[0]).cmp(x)),
        _ => None,
    }
}

/// Most steps one LIKE may take: the greedy matcher is O(|s|·|p|), and a client can send a
/// long pattern against a long string; beyond this the sample does not match.
const LIKE_MAX_STEPS: usize = 1 << 20;

/// SQL LIKE: `%` any run, `_` any one character (iterative, bounded).
fn like(s: &[u8], p: &[u8]) -> bool {
    let (mut si, mut pi) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    let mut steps = 0usize;
    while si < s.len() {
        steps += 1;
        if steps > LIKE_MAX_STEPS {
            return false;
        }
        if pi < p.len() && p[pi] == b'%' {
            star = Some((pi, si));
            pi += 1;
        } else if pi < p.len() && (p[pi] == b'_' || p[pi] == s[si]) {
            si += 1;
            pi += 1;
        } else if let Some((sp, ss)) = star {
            pi = sp + 1;
            si = ss + 1;
            star = Some((sp, ss + 1));
        } else {
            return false;
        }
    }
    p[pi..].iter().all(|&c| c == b'%')
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::TypeSet;

    fn ty() -> Arc<StructDef> {
        let xml = r#"<types>
          <enum name="Color"><enumerator name="RED"/><enumerator name="GREEN"/></enum>
          <struct name="P"><member name="x" type="int32"/><member name="y" type="float64"/></struct>
          <struct name="S"><member name="id" type="uint32"/><member name="name" type="string"/>
            <member name="p" type="nonBasic" nonBasicTypeName="P"/>
            <member name="c" type="nonBasic" nonBasicTypeName="Color"/>
            <member name="ok" type="boolean"/></struct></types>"#;
        TypeSet::parse(xml)
            .expect("test value")
            .get("S")
            .expect("test value")
    }

    fn sample(id: u32, name: &str, x: i32, y: f64, color: u32, ok: bool) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend(id.to_le_bytes());
        b.extend((name.len() as u32 + 1).to_le_bytes());
        b.extend(name.as_bytes());
        b.push(0);
        while b.len() % 4 != 0 {
            b.push(0);
        }
        b.extend(x.to_le_bytes());
        while b.len() % 8 != 0 {
            b.push(0);
        }
        b.extend(y.to_le_bytes());
        b.extend(color.to_le_bytes());
        b.push(ok as u8);
        b
    }

    fn check(expr: &str, s: &[u8]) -> bool {
        Filter::compile(expr, ty())
            .expect("test value")
            .matches(s, true, false)
    }

    #[test]
    fn comparisons_logic_between_like_and_enums() {
        let s = sample(7, "robot_arm", -3, 2.5, 1, true);
        assert!(check("id = 7", &s));
        assert!(check("id > 5 AND id < 10", &s));
        assert!(!check("id <> 7", &s));
        assert!(check("id != 8 or name = 'x'", &s));
        assert!(check("NOT (id >= 8)", &s));
        assert!(check("p.x < 0 AND p.y BETWEEN 2 AND 3", &s));
        assert!(check("p.y NOT BETWEEN 3.0 AND 4.0", &s));
        assert!(check("name LIKE 'robot%'", &s));
        assert!(check("name LIKE '_obot_a%m'", &s));
        assert!(!check("name LIKE 'arm%'", &s));
        assert!(check("c = GREEN", &s));
        assert!(check("c = 'GREEN'", &s));
        assert!(!check("c = RED", &s));
        assert!(check("ok = TRUE", &s));
        assert!(check("10 > id", &s));
        assert!(check("id = 0x7", &s));
        assert!(check("p.x = -3", &s));
    }

    #[test]
    fn bad_expressions_are_refused_with_a_reason() {
        for bad in [
            "",
            "id =",
            "nope > 3",
            "id > %0",
            "(id > 3",
            "3 > 4",
            "p > 3",
            "id BETWEEN 1",
            "name = 'open",
            "id > 3 extra",
        ] {
            assert!(Filter::compile(bad, ty()).is_err(), "{bad}");
        }
        let deep = "(".repeat(200) + "id = 1" + &")".repeat(200);
        assert!(Filter::compile(&deep, ty()).is_err());
    }

    #[test]
    fn a_truncated_sample_does_not_pass() {
        let s = sample(7, "a", 0, 0.0, 0, false);
        assert!(!check("id = 7 AND ok = FALSE", &s[..10]));
        assert!(check("id = 7 AND ok = FALSE", &s));
    }

    #[test]
    fn like_patterns() {
        assert!(like(b"", b"%"));
        assert!(like(b"abc", b"a%c"));
        assert!(!like(b"abc", b"a%d"));
        assert!(like(b"aaa", b"%a%a%a%"));
        assert!(!like(&[b'a'; 40], b"%a%a%a%a%a%a%b"));
        assert!(like(b"%x", b"%"), "a literal % in the string");
        assert!(like(b"a%c", b"a%c"));
        let long = vec![b'a'; 1 << 20];
        assert!(!like(
            &long,
            &[b"%".as_slice(), &[b'a'; 2000], b"b"].concat()
        ));
    }
}
