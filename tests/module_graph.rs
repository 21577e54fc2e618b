//! No import circles between the modules of a server crate (issue 23): a module that needs
//! another's items and is needed by it back is one unit split in two, and a newcomer cannot
//! read either first. The graph is read from the sources: an edge `a → b` for every
//! `crate::b` path in the files of top-level module `a` (`src/a.rs` or `src/a/…`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The top-level module a file belongs to (`None` for the crate root files).
fn module_of(src: &Path, file: &Path) -> Option<String> {
    let rel = file.strip_prefix(src).ok()?;
    let first = rel
        .components()
        .next()?
        .as_os_str()
        .to_string_lossy()
        .into_owned();
    let name = first.trim_end_matches(".rs").to_owned();
    (!matches!(name.as_str(), "lib" | "main")).then_some(name)
}

/// Modules named by `crate::x` paths, including `use crate::{x, y::z}` groups.
fn crate_paths(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let code: String = text
        .lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n");
    let mut rest = code.as_str();
    while let Some(at) = rest.find("crate::") {
        let before = rest[..at].chars().last();
        rest = &rest[at + "crate::".len()..];
        // `voxlight_engine::crate::`-like suffixes do not occur; `$crate::` is a macro's.
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == '$') {
            continue;
        }
        if let Some(group) = rest.strip_prefix('{') {
            let end = group.find('}').unwrap_or(group.len());
            for part in group[..end].split(',') {
                let name: String = part
                    .trim()
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                out.insert(name);
            }
            continue;
        }
        let name: String = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        if rest[name.len()..].starts_with("::") {
            out.insert(name);
        }
    }
    out
}

fn graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let modules: BTreeSet<String> = files.iter().filter_map(|f| module_of(src, f)).collect();
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for file in &files {
        let Some(from) = module_of(src, file) else {
            continue;
        };
        let text = std::fs::read_to_string(file).expect("source file");
        for to in crate_paths(&text) {
            if to != from && modules.contains(&to) {
                edges.entry(from.clone()).or_default().insert(to);
            }
        }
    }
    edges
}

/// Every pair of modules that reach each other (members of one strongly connected component).
fn circles(edges: &BTreeMap<String, BTreeSet<String>>) -> Vec<(String, String)> {
    let reach = |from: &str| {
        let mut seen = BTreeSet::new();
        let mut stack = vec![from.to_owned()];
        while let Some(m) = stack.pop() {
            for n in edges.get(&m).into_iter().flatten() {
                if seen.insert(n.clone()) {
                    stack.push(n.clone());
                }
            }
        }
        seen
    };
    let mut out = Vec::new();
    for a in edges.keys() {
        for b in reach(a) {
            if a < &b && reach(&b).contains(a) {
                out.push((a.clone(), b));
            }
        }
    }
    out
}

fn server_crate(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(rel)
}

#[test]
fn the_graph_reader_finds_a_circle() {
    let text_a = "use crate::b::Thing;\nfn f() { crate::c::g(); }";
    assert_eq!(
        crate_paths(text_a),
        BTreeSet::from(["b".to_owned(), "c".to_owned()])
    );
    assert_eq!(
        crate_paths("use crate::{hub::X, reply};\n// crate::commented::out"),
        BTreeSet::from(["hub".to_owned(), "reply".to_owned()])
    );
    let edges = BTreeMap::from([
        ("a".to_owned(), BTreeSet::from(["b".to_owned()])),
        ("b".to_owned(), BTreeSet::from(["c".to_owned()])),
        ("c".to_owned(), BTreeSet::from(["a".to_owned()])),
        ("d".to_owned(), BTreeSet::from(["a".to_owned()])),
    ]);
    assert_eq!(circles(&edges).len(), 3);
}

/// Every server crate, and the least number of its modules the graph must have read.
const CRATES: [(&str, usize); 5] = [
    ("server/app/src", 5),
    ("server/engine/src", 8),
    ("server/volumes/src", 4),
    ("protocol/src", 0),
    ("bench/src", 3),
];

#[test]
fn no_import_circles_in_any_crate() {
    for (rel, least) in CRATES {
        let edges = graph(&server_crate(rel));
        println!("{rel}: {} modules import others", edges.len());
        assert!(edges.len() >= least, "read too little of {rel}: {edges:?}");
        let found = circles(&edges);
        assert!(
            found.is_empty(),
            "{rel}: modules that import each other: {found:?}"
        );
    }
}
