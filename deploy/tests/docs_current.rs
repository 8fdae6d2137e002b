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

/// Every path of the repository under the workspace root (files and directories, `/`
/// separated), but build outputs and git's own.
fn repository_paths() -> Vec<String> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut out = Vec::new();
    let mut todo = vec![(root.clone(), String::new())];
    while let Some((dir, rel)) = todo.pop() {
        for e in std::fs::read_dir(&dir)
            .expect("read the repository")
            .flatten()
        {
            let name = e.file_name().to_string_lossy().into_owned();
            if rel.is_empty() && (name == "target" || name == ".git") {
                continue;
            }
            let path = format!("{rel}{name}");
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                out.push(format!("{path}/"));
                todo.push((e.path(), format!("{path}/")));
            } else {
                out.push(path);
            }
        }
    }
    out
}

/// The map of the code names only what exists: each path it writes in backticks (a file
/// with an extension, or a directory of two levels or more; relative ones may start at any
/// directory, as the map names modules inside their crate) is a path of the repository, and
/// each link goes to a file.
#[test]
fn every_path_the_design_map_names_exists() {
    let docs = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docs");
    let text = std::fs::read_to_string(docs.join("design.md")).expect("docs/design.md");
    let paths = repository_paths();
    let exists = |p: &str| {
        let p = p.trim_start_matches("./");
        paths
            .iter()
            .any(|have| have == p || have.ends_with(&format!("/{p}")))
    };
    let mut missing = Vec::new();
    for (i, token) in text.split('`').enumerate() {
        if i % 2 == 0 || token.contains(char::is_whitespace) || token.starts_with(['<', '/']) {
            continue;
        }
        let file = [".rs", ".md", ".toml", ".sh", ".py", ".txt", ".tsv"]
            .iter()
            .any(|x| token.ends_with(x));
        let deep_dir = token.ends_with('/') && token.trim_end_matches('/').contains('/');
        if (file || deep_dir) && (token.starts_with("../") || !exists(token)) {
            missing.push(token.to_string());
        }
    }
    for link in text.split("](").skip(1) {
        let target = link.split(')').next().unwrap_or_default();
        let target = target.split('#').next().unwrap_or_default();
        if target.is_empty() || target.contains("://") {
            continue;
        }
        if !docs.join(target).exists() {
            missing.push(format!("link {target}"));
        }
    }
    assert!(
        missing.is_empty(),
        "docs/design.md names what the repository does not have: {missing:?}"
    );
}
