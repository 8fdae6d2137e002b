//! Entry point shared by the representation fuzz target (`fuzz/`) and its corpus replay test:
//! arbitrary bytes as an XML string, a binary body and a references file, through every
//! parser the worker applies to client input. Nothing may panic; errors are the normal result.

use xrce_common::wire::{object_kind, Representation};

use crate::references::References;
use crate::representation::{check_plain, describe_endpoint, describe_topic};

/// Feeds `data` to every representation parser.
pub fn representations(data: &[u8]) {
    let refs = References::parse(&String::from_utf8_lossy(data), "fuzz").unwrap_or_default();
    let mut reprs = vec![Representation::Binary(data.to_vec())];
    if let Ok(s) = std::str::from_utf8(data) {
        reprs.push(Representation::Xml(s.to_string()));
        reprs.push(Representation::Reference(s.to_string()));
    }
    for (repr, le) in reprs.iter().flat_map(|r| [(r, true), (r, false)]) {
        for kind in [
            object_kind::PARTICIPANT,
            object_kind::TOPIC,
            object_kind::PUBLISHER,
            object_kind::SUBSCRIBER,
            object_kind::DATAWRITER,
            object_kind::DATAREADER,
        ] {
            let _ = check_plain(repr, kind, &refs, le);
        }
        let _ = describe_topic(repr, &refs, le);
        let _ = describe_endpoint(repr, true, &refs, le);
        let _ = describe_endpoint(repr, false, &refs, le);
    }
    types_and_filters(data);
}

/// Type documents, keys and content filters: `data` as a `<types>` document, then as a
/// sample of each type it defines and as a filter expression over it.
fn types_and_filters(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(set) = crate::types::TypeSet::parse(text) else {
        return;
    };
    for ty in set.structs().take(8) {
        if let Some(k) = crate::types::KeyDescriptor::new(ty.clone()) {
            for (le, xcdr2) in [(true, false), (false, true)] {
                let _ = k.of_sample(data, le, xcdr2);
                let _ = k.of_key_payload(data, le, xcdr2);
            }
        }
        let t = crate::types::Ty::Struct(ty.clone());
        let _ = crate::types::sample_len(&t, data, 4, true);
        let _ = crate::types::rebase(&t, data, 4, false);
        if let Ok(f) = crate::filter::Filter::compile(text, ty.clone()) {
            let _ = f.matches(data, true, false);
        }
    }
}
