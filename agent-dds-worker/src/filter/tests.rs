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

/// LIKE with a whole evaluation's budget.
fn like_ok(s: &[u8], p: &[u8]) -> bool {
    like(s, p, &mut Steps::new(EVAL_BUDGET)) == Ok(true)
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
    assert!(like_ok(b"", b"%"));
    assert!(like_ok(b"abc", b"a%c"));
    assert!(!like_ok(b"abc", b"a%d"));
    assert!(like_ok(b"aaa", b"%a%a%a%"));
    assert!(!like_ok(&[b'a'; 40], b"%a%a%a%a%a%a%b"));
    assert!(like_ok(b"%x", b"%"), "a literal % in the string");
    assert!(like_ok(b"a%c", b"a%c"));
    let long = vec![b'a'; 1 << 20];
    let mut steps = Steps::new(EVAL_BUDGET);
    assert_eq!(
        like(
            &long,
            &[b"%".as_slice(), &[b'a'; 2000], b"b"].concat(),
            &mut steps
        ),
        Err(OverBudget),
        "a quadratic match stops at the budget"
    );
    assert_eq!(steps.left(), 0);
}

/// The worst filters a client can build within the caps, each with the sample that
/// makes it work hardest: (what, expression, type XML, type name, sample, verdict).
type Case = (&'static str, String, String, &'static str, Vec<u8>, Verdict);

fn worst_cases() -> Vec<Case> {
    let cdr_string = |b: &mut Vec<u8>, s: &str| {
        while b.len() % 4 != 0 {
            b.push(0);
        }
        b.extend((s.len() as u32 + 1).to_le_bytes());
        b.extend(s.as_bytes());
        b.push(0);
    };
    let mut out = Vec::new();
    // 1. LIKE: quadratic patterns against a long string, as many clauses as allowed
    //    (the first one spends the whole budget).
    let named = r#"<types><struct name="N"><member name="id" type="int32"/>
            <member name="name" type="string"/></struct></types>"#;
    let pattern = format!("%{}b", "a".repeat(100));
    let like_all = vec![format!("name LIKE '{pattern}'"); MAX_CLAUSES].join(" OR ");
    assert!(like_all.len() <= MAX_EXPRESSION);
    let mut sample = 1i32.to_le_bytes().to_vec();
    cdr_string(&mut sample, &"a".repeat(60_000));
    out.push((
        "LIKE",
        like_all,
        named.to_string(),
        "N",
        sample,
        Verdict::OverBudget,
    ));
    // 2. The walk: a field behind a long sequence of elements to skip, each a struct
    //    (empty, of one octet, of one string).
    for (what, elem, per) in [
        ("walk (empty structs)", r#"<struct name="E"/>"#, 0usize),
        (
            "walk (one-octet structs)",
            r#"<struct name="E"><member name="x" type="int8"/></struct>"#,
            1,
        ),
        (
            "walk (one-string structs)",
            r#"<struct name="E"><member name="s" type="string"/></struct>"#,
            5,
        ),
    ] {
        let xml = format!(
            r#"<types>{elem}<struct name="W"><member name="items" type="nonBasic"
                   nonBasicTypeName="E" sequenceMaxLength="-1"/>
                   <member name="id" type="int32"/></struct></types>"#
        );
        let n = 200_000u32;
        let mut sample = n.to_le_bytes().to_vec();
        for _ in 0..n {
            match per {
                0 => {}
                1 => sample.push(7),
                _ => cdr_string(&mut sample, ""),
            }
        }
        while sample.len() % 4 != 0 {
            sample.push(0);
        }
        sample.extend(1i32.to_le_bytes());
        let filter = vec!["id = 1"; MAX_CLAUSES].join(" AND ");
        out.push((what, filter, xml, "W", sample, Verdict::OverBudget));
    }
    // 3. Condition nodes: the longest chains of NOT the expression allows around
    //    cheap comparisons (the nesting cap is per chain).
    let chain = |i: usize| format!("{}id <> {}", "NOT ".repeat(30), 1000 + i);
    let nodes = (0..MAX_CLAUSES)
        .map(chain)
        .take_while({
            let mut len = 0;
            move |c| {
                len += c.len() + 4;
                len <= MAX_EXPRESSION
            }
        })
        .collect::<Vec<_>>()
        .join(" AND ");
    let mut sample = 1i32.to_le_bytes().to_vec();
    cdr_string(&mut sample, "x");
    out.push((
        "nodes",
        nodes,
        named.to_string(),
        "N",
        sample,
        Verdict::Match,
    ));
    // 4. Fields: 32 comparisons of 64 long string fields with each other.
    let members: String = (0..2 * MAX_CLAUSES)
        .map(|i| format!(r#"<member name="s{i}" type="string"/>"#))
        .collect();
    let xml = format!(r#"<types><struct name="F">{members}</struct></types>"#);
    let filter = (0..MAX_CLAUSES)
        .map(|i| format!("s{} = s{}", 2 * i, 2 * i + 1))
        .collect::<Vec<_>>()
        .join(" AND ");
    let mut sample = Vec::new();
    let long = "q".repeat(1_000);
    for _ in 0..2 * MAX_CLAUSES {
        cdr_string(&mut sample, &long);
    }
    out.push(("fields", filter, xml, "F", sample, Verdict::Match));
    out
}

/// Each worst case stays within one evaluation's budget and has the outcome the module
/// documents (out of budget: not matching). Run it in release mode with `--nocapture`
/// for the times (printed, not asserted): the worst evaluation, the worst reader's
/// share of a pass, and the worst pass.
#[test]
fn the_worst_filters_within_the_caps_stay_within_their_budgets() {
    let mut worst = std::time::Duration::ZERO;
    for (what, expression, xml, name, sample, expected) in worst_cases() {
        let ty = TypeSet::parse(&xml)
            .expect("type")
            .get(name)
            .expect("struct");
        let f = Filter::compile(&expression, ty).expect("within the caps");
        let mut steps = Steps::new(EVAL_BUDGET);
        assert_eq!(
            f.evaluate(&sample, true, false, &mut steps),
            expected,
            "{what}"
        );
        assert!(steps.spent() <= EVAL_BUDGET, "{what}: {}", steps.spent());
        if expected == Verdict::OverBudget {
            assert_eq!(steps.left(), 0, "{what}");
        }
        // Timed: as many evaluations as a pass allows (each at least one step).
        let evaluations = (PASS_BUDGET / steps.spent().max(1)).clamp(1, 4096);
        let start = std::time::Instant::now();
        for _ in 0..evaluations {
            let mut steps = Steps::new(EVAL_BUDGET);
            let _ = f.evaluate(&sample, true, false, &mut steps);
        }
        let each = start.elapsed() / evaluations as u32;
        worst = worst.max(each);
        eprintln!(
            "filter worst case {what:28}: {:6} steps, {:8.1} µs per evaluation \
                 ({:.0} ns per step)",
            steps.spent(),
            each.as_secs_f64() * 1e6,
            each.as_secs_f64() * 1e9 / steps.spent().max(1) as f64
        );
    }
    let reader = worst * (READER_PASS_BUDGET / EVAL_BUDGET) as u32;
    let pass = worst * (PASS_BUDGET / EVAL_BUDGET) as u32;
    eprintln!(
        "filter bounds: worst evaluation {:.2} ms, a reader's share of a pass {:.1} ms, \
             a pass {:.1} ms (evaluations alone)",
        worst.as_secs_f64() * 1e3,
        reader.as_secs_f64() * 1e3,
        pass.as_secs_f64() * 1e3
    );
}
