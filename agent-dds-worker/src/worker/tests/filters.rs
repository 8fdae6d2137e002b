//! Bounds on content filters: clauses, the evaluation budget, work per pass.

use super::*;

const NAMED_TYPE: &str = r#"<dds><types><struct name="Named">
    <member name="id" type="int32"/>
    <member name="name" type="string"/>
  </struct></types></dds>"#;
const NAMED_TYPES: ObjectId = ObjectId::new(2, object_kind::TYPE);

/// A `Named` sample, little endian.
fn named(id: i32, name: &str) -> Vec<u8> {
    let mut b = id.to_le_bytes().to_vec();
    b.extend((name.len() as u32 + 1).to_le_bytes());
    b.extend(name.as_bytes());
    b.push(0);
    b
}

fn filtered_reader_xml(topic: &str, expression: &str) -> String {
    format!(
        "<dds><data_reader><topic><kind>NO_KEY</kind><name>{topic}</name>\
         <dataType>Named</dataType></topic>\
         <content_filter><expression>{expression}</expression></content_filter>\
         </data_reader></dds>"
    )
}

/// A LIKE that takes |name|·|pattern| steps on a name of `a`s: over any budget.
const QUADRATIC: &str = "name LIKE '%aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaab'";

impl Harness {
    /// A participant (domain 3) whose client defines `Named`, with a subscriber.
    fn named_participant(&mut self, client: ClientKey) {
        self.participant(client);
        let types = variant(object_kind::TYPE, NAMED_TYPE, VariantExtra::None);
        self.create(client, NAMED_TYPES, &types).expect("types");
    }

    /// Injects `n` samples from outside the agent on `topic` (domain 3).
    fn inject(&self, topic: &str, n: usize, body: impl Fn(usize) -> Vec<u8>) {
        for i in 0..n {
            let b = body(i);
            self.bus.inject(3, topic, || backend::Taken {
                sample: Sample::cdr(true, &b),
                identity: backend::SampleIdentity {
                    writer: [0x77; 16],
                    sequence_number: i as i64 + 1,
                },
                related: None,
                disposed: false,
                unregistered: false,
            });
        }
    }

    fn dropped(&self, reason: &str) -> u64 {
        self.worker.dropped.get(reason).copied().unwrap_or(0)
    }
}

/// A filter of more clauses than MAX_CLAUSES is refused with STATUS_ERR_RESOURCES, on a
/// reader's XML and on a READ_DATA; one at the cap is accepted.
#[test]
fn a_filter_with_too_many_clauses_is_refused_for_resources() {
    let mut t = Harness::new(false);
    t.named_participant(CLIENT);
    let clauses = |n: usize| vec!["id = 1"; n].join(" OR ");
    let at_cap = clauses(crate::filter::MAX_CLAUSES);
    t.reader(CLIENT, READER, &filtered_reader_xml("F", &at_cap))
        .expect("at the cap");
    let over = clauses(crate::filter::MAX_CLAUSES + 1);
    let refused = t
        .reader(
            CLIENT,
            ObjectId::new(2, object_kind::DATAREADER),
            &filtered_reader_xml("F", &over),
        )
        .expect_err("over the cap");
    assert_eq!(refused.status(), status::ERR_RESOURCES, "{}", refused);
    assert!(refused.to_string().contains("clauses"), "{}", refused);
    assert_eq!(t.dropped("filters_refused"), 1);
    // On a READ_DATA of the accepted reader.
    let mut body = Vec::new();
    ReadSpecification {
        data_format: xrce_common::wire::data_format::DATA,
        content_filter_expression: Some(over),
        ..Default::default()
    }
    .encode(&mut CdrWriter::new(&mut body, true));
    let refused = t
        .worker
        .start_read((FE, CLIENT, READER), Default::default(), false, &body)
        .expect_err("over the cap");
    assert_eq!(refused.status(), status::ERR_RESOURCES);
    assert_eq!(t.dropped("filters_refused"), 2);
}

/// A sample whose evaluation runs out of the evaluation budget is treated as not matching:
/// not delivered, counted as `content_filter_over_budget`, and the samples after it are
/// judged on their own.
#[test]
fn a_sample_over_the_evaluation_budget_does_not_match_and_is_counted() {
    let mut t = Harness::new(false);
    t.named_participant(CLIENT);
    let expression = format!("id = 7 OR {QUADRATIC}");
    t.reader(CLIENT, READER, &filtered_reader_xml("F", &expression))
        .expect("reader");
    t.read(CLIENT, READER);
    let long = "a".repeat(4000);
    t.inject("F", 3, |i| match i {
        0 => named(1, &long),   // over budget
        1 => named(7, &long),   // matches by its first clause (OR short-cuts)
        _ => named(2, "short"), // no match, cheaply
    });
    t.worker.pump_readers().expect("pump");
    t.worker.flush();
    let got: Vec<Vec<u8>> = t.samples().into_iter().map(|(_, _, b)| b).collect();
    assert_eq!(got, vec![named(7, &long)]);
    assert_eq!(t.dropped("content_filter_over_budget"), 1);
    assert_eq!(t.dropped("content_filtered"), 1);
}

/// The worst case of the walk to a field (filter.rs measures it with the others): a field
/// behind a sequence of one-octet structures, each two steps to skip.
const WALK_TYPE: &str = r#"<dds><types><struct name="E"><member name="x" type="int8"/></struct>
    <struct name="Walk"><member name="items" type="nonBasic" nonBasicTypeName="E"
      sequenceMaxLength="-1"/><member name="id" type="int32"/></struct></types></dds>"#;

/// A `Walk` sample of `n` elements and id 1.
fn walk(n: u32) -> Vec<u8> {
    let mut b = n.to_le_bytes().to_vec();
    b.resize(4 + n as usize, 7);
    while b.len() % 4 != 0 {
        b.push(0);
    }
    b.extend(1i32.to_le_bytes());
    b
}

/// A reader whose evaluations spend its budget for the pass takes the rest of its samples
/// next pass (nothing is lost, nothing judged on a budget cut short), and all readers
/// together stop at the pass's budget: those left go first next pass. With the worst
/// filters within the caps (a quadratic LIKE, the walk to a field), each sample costing a
/// whole evaluation's budget; the passes' times are printed (not asserted: release mode
/// and `--nocapture` for numbers worth reading).
#[test]
fn filter_work_per_reader_and_per_pass_is_bounded_and_the_rest_waits() {
    let long = "a".repeat(4000);
    bounded_passes("LIKE", "Named", QUADRATIC, &|_| named(1, &long));
    bounded_passes("walk", "Walk", "id = 1 AND id = 1", &|_| walk(40_000));
}

fn bounded_passes(what: &str, ty: &str, expression: &str, sample: &dyn Fn(usize) -> Vec<u8>) {
    use crate::filter::{EVAL_BUDGET, PASS_BUDGET, READER_PASS_BUDGET};
    let per_reader = READER_PASS_BUDGET / EVAL_BUDGET;
    let readers_per_pass = (PASS_BUDGET / READER_PASS_BUDGET) as usize;
    let mut t = Harness::new(false);
    t.named_participant(CLIENT);
    let types = variant(object_kind::TYPE, WALK_TYPE, VariantExtra::None);
    t.create(CLIENT, ObjectId::new(3, object_kind::TYPE), &types)
        .expect("types");
    let n_readers = readers_per_pass + 1;
    let ids: Vec<ObjectId> = (0..n_readers)
        .map(|i| ObjectId::new(10 + i as u16, object_kind::DATAREADER))
        .collect();
    let xml = filtered_reader_xml("W", expression).replace("Named", ty);
    for id in &ids {
        t.reader(CLIENT, *id, &xml).expect("reader");
        t.read(CLIENT, *id);
    }
    // Each sample costs a whole evaluation budget (and does not match).
    let samples = 2 * per_reader as usize + 3;
    t.inject("W", samples, sample);

    let start = Instant::now();
    t.worker.pump_readers().expect("pump");
    let took = start.elapsed();
    let first = per_reader * readers_per_pass as u64;
    assert_eq!(
        t.dropped("content_filter_over_budget"),
        first,
        "{what}: {per_reader} evaluations per reader, {readers_per_pass} readers per pass"
    );
    eprintln!(
        "{what}: a pass of {readers_per_pass} readers full of the worst samples took {:.1} ms \
         ({:.2} ms per reader, {:.3} ms per evaluation)",
        took.as_secs_f64() * 1e3,
        took.as_secs_f64() * 1e3 / readers_per_pass as f64,
        took.as_secs_f64() * 1e3 / first as f64
    );
    let last = (FE, CLIENT, ids[n_readers - 1]);
    assert!(
        t.worker.readers.over_budget.contains(&last),
        "{what}: the reader without a turn goes first next pass"
    );
    assert_eq!(
        t.dropped("filter_budget_deferrals"),
        readers_per_pass as u64
    );

    t.worker.pump_readers().expect("pump");
    // The reader left out went first and got its full share.
    let second = t.dropped("content_filter_over_budget") - first;
    assert_eq!(second, per_reader * readers_per_pass as u64);
    for _ in 0..8 {
        t.worker.pump_readers().expect("pump");
    }
    assert_eq!(
        t.dropped("content_filter_over_budget"),
        (samples * n_readers) as u64,
        "{what}: every sample was evaluated once, none lost or skipped"
    );
    assert!(t.worker.readers.over_budget.is_empty() && t.worker.readers.pump_again.is_empty());
}
