//! The type model, its reading and the sample walks, against hand-built samples.

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
