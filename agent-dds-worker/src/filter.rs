//! Content filters: the SQL subset of DDS 1.4 Annex B ("Syntax for Queries and Filters"),
//! compiled against a type description and evaluated on serialized samples in the worker
//! (RustDDS has no content-filtered topics).
//!
//! Grammar: `Condition := Predicate | Condition AND|OR Condition | NOT Condition | (Condition)`;
//! `Predicate := Field RelOp Value | Value RelOp Field | Field RelOp Field | Field [NOT]
//! BETWEEN Value AND Value`; `RelOp := = | <> | != | < | <= | > | >= | LIKE`; values are
//! integers (decimal or 0x hex), floats, `'strings'`, TRUE/FALSE and enumerator names.
//! Parameters (`%n`) are refused: an XRCE read carries none.
//!
//! # Bounds
//!
//! A filter runs on the worker's loop for every sample of its reader, and its expression
//! comes from a client, so its cost is bounded three ways (a client could otherwise make one
//! pass of the loop take minutes: the watchdog would restart the worker, the replay would
//! re-create the filter, and so on):
//!
//! * **Clauses**: at most [`MAX_CLAUSES`] predicates (comparisons, `BETWEEN`s, `LIKE`s) per
//!   filter; more is refused at creation ([`FilterError::TooManyClauses`], which the worker
//!   answers with `STATUS_ERR_RESOURCES`).
//! * **Per evaluation**: one budget of [`EVAL_BUDGET`] steps for everything one sample's
//!   evaluation does, all clauses together: walking the sample to its fields (a step per
//!   element visited, and per [`STRING_OCTETS_PER_STEP`] string octets copied), a step per
//!   condition node, a step per `LIKE` iteration, and a step per
//!   [`STRING_OCTETS_PER_STEP`] octets of a string comparison. A sample whose evaluation
//!   runs out of budget is **treated as not matching** ([`Verdict::OverBudget`]): the worker
//!   drops it from that read as it drops filtered samples, and counts it
//!   (`content_filter_over_budget`). The outcome depends only on the sample and the filter,
//!   never on the load.
//! * **Per reader and per pass** (the worker's reads): a reader evaluates at most
//!   [`READER_PASS_BUDGET`] steps per pass of the worker's loop, and all readers together at
//!   most [`PASS_BUDGET`]; a reader takes its next sample only while a whole evaluation fits
//!   in what is left, so the rest of its samples wait in DDS for the next pass, and none is
//!   judged on a budget cut short.

use std::sync::Arc;

pub use crate::types::STRING_OCTETS_PER_STEP;
use crate::types::{read_fields_within, resolve_path, Seg, StructDef, Ty, Value, WalkError};

/// Longest expression accepted (octets).
const MAX_EXPRESSION: usize = 4096;
/// Deepest nesting of conditions.
const MAX_NESTING: usize = 64;

/// Most predicates one filter may have: real filters have a few; each one is work for every
/// sample of the reader.
pub const MAX_CLAUSES: usize = 32;

/// Steps one evaluation of one sample may take, all clauses and the walk to the fields
/// together (about a millisecond at worst; see [`Filter::evaluate`]).
pub const EVAL_BUDGET: u64 = 1 << 16;

/// Steps one reader's evaluations may take in one pass of the worker's loop (16 worst-case
/// evaluations; thousands of ordinary ones).
pub const READER_PASS_BUDGET: u64 = 1 << 20;

/// Steps all readers' evaluations may take together in one pass of the worker's loop: what
/// bounds the time filters add to a pass, whatever the number of readers.
pub const PASS_BUDGET: u64 = 1 << 22;

/// Why an expression was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FilterError {
    /// Longer than 4,096 octets.
    #[error("expression longer than {MAX_EXPRESSION} octets")]
    TooLong,
    /// More than [`MAX_CLAUSES`] predicates.
    #[error("more than {MAX_CLAUSES} clauses (comparisons, BETWEEN, LIKE) in one filter")]
    TooManyClauses,
    /// Conditions nested deeper than 64 levels.
    #[error("expression nested deeper than {MAX_NESTING}")]
    TooDeep,
    /// Not the grammar, or a field the type does not have.
    #[error("{0}")]
    Syntax(String),
}

impl From<String> for FilterError {
    fn from(s: String) -> Self {
        FilterError::Syntax(s)
    }
}

impl From<&str> for FilterError {
    fn from(s: &str) -> Self {
        FilterError::Syntax(s.to_string())
    }
}

impl FilterError {
    /// Whether it is a bound on the work a filter may cause (the CREATE or READ is refused
    /// for resources) rather than an invalid expression.
    pub fn is_limit(&self) -> bool {
        matches!(self, FilterError::TooManyClauses)
    }
}

/// A step budget, spent by evaluations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Steps {
    left: u64,
    spent: u64,
}

impl Steps {
    /// A budget of `n` steps.
    pub fn new(n: u64) -> Self {
        Steps { left: n, spent: 0 }
    }

    /// Steps left.
    pub fn left(&self) -> u64 {
        self.left
    }

    /// Steps spent so far.
    pub fn spent(&self) -> u64 {
        self.spent
    }

    /// Spends `n` steps, or all that are left if fewer (work done elsewhere: a reader's
    /// pass budget pays for the evaluations of its samples).
    pub fn charge(&mut self, n: u64) {
        let n = n.min(self.left);
        self.left -= n;
        self.spent += n;
    }

    /// Spends `n` steps; `Err` (and nothing left) if fewer than `n` were left.
    fn spend(&mut self, n: u64) -> Result<(), OverBudget> {
        if n > self.left {
            self.spent += self.left;
            self.left = 0;
            return Err(OverBudget);
        }
        self.left -= n;
        self.spent += n;
        Ok(())
    }
}

/// An evaluation ran out of steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct OverBudget;

/// What an evaluation found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// The sample passes.
    Match,
    /// It does not (or it cannot be walked: a malformed sample does not pass).
    NoMatch,
    /// Its evaluation needed more steps than the budget: treated as not matching, and
    /// counted by the caller.
    OverBudget,
}

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
    /// Predicates parsed so far.
    clauses: usize,
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

    fn or(&mut self) -> Result<Cond, FilterError> {
        let mut l = self.and()?;
        while keyword(self.peek(), "OR") {
            self.pos += 1;
            l = Cond::Or(Box::new(l), Box::new(self.and()?));
        }
        Ok(l)
    }

    fn and(&mut self) -> Result<Cond, FilterError> {
        let mut l = self.not()?;
        while keyword(self.peek(), "AND") {
            self.pos += 1;
            l = Cond::And(Box::new(l), Box::new(self.not()?));
        }
        Ok(l)
    }

    fn not(&mut self) -> Result<Cond, FilterError> {
        self.depth += 1;
        if self.depth > MAX_NESTING {
            return Err(FilterError::TooDeep);
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

    fn operand(&mut self) -> Result<Operand, FilterError> {
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
                    .ok_or(FilterError::Syntax(e)),
            },
            Some(t) => Err(format!("unexpected {t:?}").into()),
            None => Err("unexpected end of expression".into()),
        }
    }

    fn predicate(&mut self) -> Result<Cond, FilterError> {
        self.clauses += 1;
        if self.clauses > MAX_CLAUSES {
            return Err(FilterError::TooManyClauses);
        }
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
            other => return Err(format!("expected a comparison, found {other:?}").into()),
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
    pub fn compile(expression: &str, ty: Arc<StructDef>) -> Result<Filter, FilterError> {
        if expression.len() > MAX_EXPRESSION {
            return Err(FilterError::TooLong);
        }
        let toks = tokenize(expression)?;
        let mut p = Parser {
            toks: &toks,
            pos: 0,
            ty: ty.clone(),
            paths: Vec::new(),
            types: Vec::new(),
            depth: 0,
            clauses: 0,
        };
        let root = p.or()?;
        if let Some(t) = toks.get(p.pos) {
            return Err(format!("unexpected {t:?}").into());
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

    /// Whether a sample passes within one evaluation's budget ([`EVAL_BUDGET`]); a sample
    /// that cannot be walked, or needs more steps, does not.
    pub fn matches(&self, body: &[u8], le: bool, xcdr2: bool) -> bool {
        self.evaluate(body, le, xcdr2, &mut Steps::new(EVAL_BUDGET)) == Verdict::Match
    }

    /// Evaluates the filter on a sample, spending from `steps` (see the module's "Bounds"):
    /// [`Verdict::OverBudget`] as soon as they run out, whatever is left to do.
    pub fn evaluate(&self, body: &[u8], le: bool, xcdr2: bool, steps: &mut Steps) -> Verdict {
        let limit = usize::try_from(steps.left()).unwrap_or(usize::MAX);
        let values = match read_fields_within(&self.ty, &self.paths, body, le, xcdr2, limit) {
            Ok((values, walked)) => {
                if steps.spend(walked as u64).is_err() {
                    return Verdict::OverBudget;
                }
                values
            }
            // The walk stopped at the budget (or at its own bound, which is larger than any
            // budget a caller has).
            Err(WalkError::TooComplex) => {
                let _ = steps.spend(steps.left().saturating_add(1));
                return Verdict::OverBudget;
            }
            Err(_) => {
                let _ = steps.spend(1);
                return Verdict::NoMatch;
            }
        };
        match eval(&self.root, &values, steps) {
            Ok(true) => Verdict::Match,
            Ok(false) => Verdict::NoMatch,
            Err(OverBudget) => Verdict::OverBudget,
        }
    }
}

fn value_of<'v>(o: &'v Operand, values: &'v [Option<Value>]) -> Option<&'v Value> {
    match o {
        Operand::Field(i) => values.get(*i)?.as_ref(),
        Operand::Const(v) => Some(v),
    }
}

/// Steps a comparison of `a` and `b` costs: one, and the octets of the shorter string.
fn compare_cost(a: &Value, b: &Value) -> u64 {
    let len = |v: &Value| match v {
        Value::Str(s) | Value::Enum(_, s) => s.len(),
        _ => 0,
    };
    1 + (len(a).min(len(b)) / STRING_OCTETS_PER_STEP) as u64
}

fn eval(c: &Cond, values: &[Option<Value>], steps: &mut Steps) -> Result<bool, OverBudget> {
    steps.spend(1)?;
    Ok(match c {
        Cond::And(a, b) => eval(a, values, steps)? && eval(b, values, steps)?,
        Cond::Or(a, b) => eval(a, values, steps)? || eval(b, values, steps)?,
        Cond::Not(a) => !eval(a, values, steps)?,
        Cond::Cmp(l, op, r) => {
            let (Some(l), Some(r)) = (value_of(l, values), value_of(r, values)) else {
                return Ok(false);
            };
            if *op == Op::Like {
                return match (l, r) {
                    (Value::Str(s), Value::Str(p)) => like(s.as_bytes(), p.as_bytes(), steps),
                    _ => Ok(false),
                };
            }
            steps.spend(compare_cost(l, r))?;
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
                return Ok(false);
            };
            steps.spend(compare_cost(v, lo) + compare_cost(v, hi))?;
            let inside = compare(v, lo).is_some_and(|o| o.is_ge())
                && compare(v, hi).is_some_and(|o| o.is_le());
            inside != *negated
        }
    })
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

/// SQL LIKE: `%` any run, `_` any one character (iterative). The greedy matcher is
/// O(|s|·|p|) and a client chooses the pattern and may choose the string: every iteration
/// is a step of the evaluation's budget.
fn like(s: &[u8], p: &[u8], steps: &mut Steps) -> Result<bool, OverBudget> {
    let (mut si, mut pi) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    // Spent in rounds rather than per iteration (the loop is a few instructions).
    const ROUND: u64 = 64;
    let mut round = 0;
    while si < s.len() {
        if round == 0 {
            steps.spend(ROUND)?;
            round = ROUND;
        }
        round -= 1;
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
            return Ok(false);
        }
    }
    steps.spend(1 + (p.len().saturating_sub(pi) / STRING_OCTETS_PER_STEP) as u64)?;
    Ok(p[pi..].iter().all(|&c| c == b'%'))
}

#[cfg(test)]
mod tests;
