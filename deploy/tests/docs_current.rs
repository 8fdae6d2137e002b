//! The references under docs/ are generated from the code (`xrce-agent generate reference`,
//! `xrce-agent generate gateway-reference`); this test fails when a committed one is not what
//! the code generates now. `XRCE_WRITE_DOCS=1 cargo test -p xrce-agent --test docs_current`
//! rewrites them.

use std::path::PathBuf;

fn check(file: &str, generated: String) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../docs")
        .join(file);
    if std::env::var_os("XRCE_WRITE_DOCS").is_some() {
        std::fs::write(&path, &generated).expect("write the reference");
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == generated,
        "docs/{file} is not what the code generates: run \
         `XRCE_WRITE_DOCS=1 cargo test -p xrce-agent --test docs_current` and commit it"
    );
}

#[test]
fn the_command_line_reference_is_current() {
    check("cli.md", xrce_agent::docs::reference());
}

#[test]
fn the_gateway_file_reference_is_current() {
    check("gateway.md", xrce_agent::gateway::reference());
}
