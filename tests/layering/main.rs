//! Layering checks that need no build of the crates: the Cargo dependency direction, read from
//! `cargo metadata`, and the import graph of every module folder, read from the sources as text.
//!
//! * **Dependency direction**: `seasonloc-core` depends on none of the service's machinery
//!   (axum, hyper, tower, tokio, sled, PostgreSQL, clap, serde_json); `seasonloc-app` knows no
//!   engine and no HTTP; `seasonloc-store` no HTTP; only `seasonloc-server` has axum; the
//!   workspace crates depend on each other only downwards (core <- app <- store <- server <-
//!   the binary).
//! * **No import cycle between the files of a module folder**, in any crate: every `super::`,
//!   `self::` and `crate::` path of a file is resolved to the module it names, and the graph of
//!   the folder's children (each child standing for itself and everything below it) must be
//!   acyclic. A folder's own `mod.rs` / `lib.rs` is left out (it declares every child and may
//!   hold the types they share, the way `solver/mod.rs` holds `Hypothesis`).
//! * `api`'s convention (the server crate): a resource is a directory (`<resource>/mod.rs` +
//!   `dto.rs`); the files directly in `api/` are shared machinery that never imports a
//!   resource, and only `mod.rs` imports the router.
//!
//! Comments and `#[cfg(test)]` modules are ignored: a doc link is not a dependency, and a test
//! may reach anywhere.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A crate's modules (by path below its `src/`, `[]` being `lib.rs` / `main.rs`) and the
/// modules each one names.
struct Graph {
    edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
    /// Modules that are directories (`<name>/mod.rs`, or `<name>.rs` beside `<name>/`).
    dirs: BTreeSet<Vec<String>>,
}

fn rs_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rs_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The module path of a file below a crate's `src/`.
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap();
    let mut parts: Vec<String> = rel
        .iter()
        .map(|c| c.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().unwrap();
    let stem = last.trim_end_matches(".rs");
    let root = parts.is_empty() && (stem == "lib" || stem == "main");
    if stem != "mod" && !root {
        parts.push(stem.to_string());
    }
    parts
}

/// The code of a file without comments and without its `#[cfg(test)]` tail.
fn code_of(text: &str) -> String {
    let mut out = String::new();
    for line in text.lines() {
        let trimmed = line.trim_start();
        if trimmed.starts_with("#[cfg(test)]") {
            break;
        }
        if trimmed.starts_with("//") {
            continue;
        }
        // Trailing comments (a `//` inside a string literal is rare in `use` lines and paths;
        // cutting there only loses text after it).
        let code = match line.find("//") {
            Some(k) if !line[..k].contains('"') => &line[..k],
            _ => line,
        };
        out.push_str(code);
        out.push('\n');
    }
    out
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// Every path that starts with `super`, `self` or `crate`, with `{...}` groups expanded, as
/// its segments.
fn paths_in(code: &str) -> Vec<Vec<String>> {
    let chars: Vec<char> = code.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        let at_word_start = i == 0 || !(is_ident(chars[i - 1]) || chars[i - 1] == ':');
        if at_word_start {
            for head in ["super", "self", "crate"] {
                let h: Vec<char> = head.chars().collect();
                let end = i + h.len();
                if chars.get(i..end) == Some(&h[..])
                    && chars.get(end..end + 2) == Some(&[':', ':'][..])
                {
                    let (paths, next) = parse_path(&chars, i);
                    out.extend(paths);
                    i = next;
                    break;
                }
            }
        }
        i += 1;
    }
    out
}

/// Parses the path starting at `start` (segments separated by `::`, possibly ending in a
/// `{a, b::c}` group); returns the expanded paths and the index after it.
fn parse_path(chars: &[char], start: usize) -> (Vec<Vec<String>>, usize) {
    let mut prefix = Vec::new();
    let mut i = start;
    loop {
        while i < chars.len() && chars[i].is_whitespace() {
            i += 1;
        }
        if chars.get(i) == Some(&'{') {
            // A group: split at top-level commas, parse each item as a path.
            let mut depth = 0;
            let mut j = i;
            let mut items = Vec::new();
            let mut item_start = i + 1;
            while j < chars.len() {
                match chars[j] {
                    '{' => depth += 1,
                    '}' => {
                        depth -= 1;
                        if depth == 0 {
                            items.push((item_start, j));
                            break;
                        }
                    }
                    ',' if depth == 1 => {
                        items.push((item_start, j));
                        item_start = j + 1;
                    }
                    _ => {}
                }
                j += 1;
            }
            let mut out = Vec::new();
            for (a, b) in items {
                let item: Vec<char> = chars[a..b].to_vec();
                let text: String = item.iter().collect();
                if text.trim().is_empty() {
                    continue;
                }
                let first = item.iter().position(|c| !c.is_whitespace()).unwrap_or(0);
                let (sub, _) = parse_path(&item, first);
                for s in sub {
                    let mut p = prefix.clone();
                    p.extend(s);
                    out.push(p);
                }
            }
            return (out, j + 1);
        }
        let seg_start = i;
        while i < chars.len() && is_ident(chars[i]) {
            i += 1;
        }
        if i == seg_start {
            return (vec![prefix], i);
        }
        prefix.push(chars[seg_start..i].iter().collect());
        if chars.get(i..i + 2) == Some(&[':', ':'][..]) {
            i += 2;
        } else {
            return (vec![prefix], i);
        }
    }
}

/// Resolves a path written in module `from` to the longest known module it names (`None`
/// outside the crate).
fn resolve(from: &[String], path: &[String], known: &BTreeSet<Vec<String>>) -> Option<Vec<String>> {
    let mut base: Vec<String>;
    let mut rest = path;
    match path.first().map(String::as_str) {
        Some("crate") => {
            base = Vec::new();
            rest = &path[1..];
        }
        Some("self") => {
            base = from.to_vec();
            rest = &path[1..];
        }
        Some("super") => {
            base = from.to_vec();
            while rest.first().map(String::as_str) == Some("super") {
                // `super` of the crate's root leaves the crate.
                base.pop()?;
                rest = &rest[1..];
            }
        }
        _ => return None,
    }
    let mut best = base.clone();
    for seg in rest {
        base.push(seg.clone());
        if known.contains(&base) {
            best = base.clone();
        } else {
            break;
        }
    }
    Some(best)
}

/// The workspace root.
fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The `src/` folder of every crate of the workspace.
fn crate_sources() -> Vec<PathBuf> {
    let mut out = vec![root().join("src"), root().join("python/src")];
    for e in std::fs::read_dir(root().join("crates")).unwrap() {
        let src = e.unwrap().path().join("src");
        if src.is_dir() {
            out.push(src);
        }
    }
    out.sort();
    out
}

/// The import graph of the crate whose sources are in `src`.
fn graph(src: &Path) -> Graph {
    let mut files = Vec::new();
    rs_files(src, &mut files);
    let known: BTreeSet<Vec<String>> = files.iter().map(|f| module_of(src, f)).collect();
    let dirs = known
        .iter()
        .filter(|m| !m.is_empty() && known.iter().any(|k| k.len() > m.len() && k.starts_with(m)))
        .cloned()
        .collect();
    let mut edges = BTreeMap::new();
    for f in &files {
        let from = module_of(src, f);
        let code = code_of(&std::fs::read_to_string(f).unwrap());
        let mut to = BTreeSet::new();
        for p in paths_in(&code) {
            if let Some(m) = resolve(&from, &p, &known) {
                if m != from && !m.is_empty() {
                    to.insert(m);
                }
            }
        }
        edges.insert(from, to);
    }
    Graph { edges, dirs }
}

/// The graph between the children of folder `folder` (each child standing for itself and
/// everything below it); the folder's own file is left out.
fn folder_graph(g: &Graph, folder: &[String]) -> Graph {
    let child = |m: &Vec<String>| -> Option<Vec<String>> {
        (m.len() > folder.len() && m.starts_with(folder)).then(|| m[..=folder.len()].to_vec())
    };
    let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for (from, to) in &g.edges {
        let Some(a) = child(from) else { continue };
        let targets = edges.entry(a.clone()).or_default();
        for t in to {
            if let Some(b) = child(t) {
                if b != a {
                    targets.insert(b);
                }
            }
        }
    }
    Graph {
        edges,
        dirs: BTreeSet::new(),
    }
}

fn name(m: &[String]) -> String {
    m.join("::")
}

/// A cycle of the graph without the layer's root, if there is one.
fn find_cycle(g: &Graph) -> Option<Vec<String>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        Open,
        Done,
    }
    let nodes: Vec<&Vec<String>> = g.edges.keys().filter(|m| !m.is_empty()).collect();
    let mut mark: BTreeMap<&Vec<String>, Mark> = nodes.iter().map(|&m| (m, Mark::New)).collect();
    fn visit<'a>(
        g: &'a Graph,
        m: &'a Vec<String>,
        mark: &mut BTreeMap<&'a Vec<String>, Mark>,
        stack: &mut Vec<&'a Vec<String>>,
    ) -> Option<Vec<String>> {
        mark.insert(m, Mark::Open);
        stack.push(m);
        for next in g.edges.get(m).into_iter().flatten() {
            match mark.get(next).copied() {
                Some(Mark::Open) => {
                    let k = stack.iter().position(|s| *s == next).unwrap_or(0);
                    let mut cycle: Vec<String> = stack[k..].iter().map(|s| name(s)).collect();
                    cycle.push(name(next));
                    return Some(cycle);
                }
                Some(Mark::New) => {
                    if let Some(c) = visit(g, next, mark, stack) {
                        return Some(c);
                    }
                }
                Some(Mark::Done) | None => {}
            }
        }
        stack.pop();
        mark.insert(m, Mark::Done);
        None
    }
    for m in nodes {
        if mark[m] == Mark::New {
            if let Some(c) = visit(g, m, &mut mark, &mut Vec::new()) {
                return Some(c);
            }
        }
    }
    None
}

/// Every folder of every crate: no cycle between its children.
#[test]
fn no_module_folder_has_an_import_cycle() {
    let mut folders_seen = 0;
    for src in crate_sources() {
        let g = graph(&src);
        let mut folders: Vec<Vec<String>> = g.dirs.iter().cloned().collect();
        folders.push(Vec::new());
        for folder in folders {
            folders_seen += 1;
            let sub = folder_graph(&g, &folder);
            if let Some(cycle) = find_cycle(&sub) {
                panic!(
                    "{}: the files of folder `{}` import each other in a cycle: {} (move what \
                     they share down into a module both can use)",
                    src.display(),
                    name(&folder),
                    cycle.join(" -> ")
                );
            }
        }
    }
    // The workspace has dozens of module folders; finding few means the reader is broken.
    assert!(
        folders_seen > 30,
        "found only {folders_seen} module folders"
    );
}

#[test]
fn api_shared_files_never_import_a_resource_or_the_router() {
    let g = graph(&root().join("crates/server/src"));
    let api: Vec<String> = vec!["api".into()];
    let resources: BTreeSet<String> = g
        .dirs
        .iter()
        .filter(|m| m.len() == 2 && m.starts_with(&api))
        .map(|m| m[1].clone())
        .collect();
    assert!(resources.contains("maps"), "{resources:?}");
    for (from, to) in &g.edges {
        if !from.starts_with(&api) || from.len() < 2 {
            continue;
        }
        let from = &from[1..];
        // Every directory is a resource with its handlers in mod.rs and its wire types in
        // dto.rs, nothing else.
        if from.len() == 2 {
            assert_eq!(from[1], "dto", "unexpected file api/{}.rs", from.join("/"));
        }
        let shared = from.len() == 1 && !resources.contains(&from[0]) && from[0] != "router";
        for m in to.iter().filter(|m| m.starts_with(&api) && m.len() >= 2) {
            let m = &m[1..];
            assert!(m[0] != "router", "api::{} imports the router", name(from));
            if shared {
                assert!(
                    !resources.contains(&m[0]),
                    "shared api::{} imports the resource api::{}",
                    name(from),
                    name(m)
                );
            }
        }
    }
}

/// The checker itself: a cycle written the ways the code writes imports is found.
#[test]
fn the_checker_sees_grouped_relative_and_absolute_paths() {
    let known: BTreeSet<Vec<String>> = [
        vec![],
        vec!["a".to_string()],
        vec!["b".to_string()],
        vec!["b".to_string(), "dto".to_string()],
    ]
    .into_iter()
    .collect();
    let code = code_of(
        "//! see crate::z\nuse crate::{a::Thing, b::dto::{X, Y}};\nfn f() { super::a::g(); }\n#[cfg(test)]\nmod tests { use crate::b; }\n",
    );
    let from = vec!["b".to_string(), "dto".to_string()];
    let targets: BTreeSet<Vec<String>> = paths_in(&code)
        .iter()
        .filter_map(|p| resolve(&from, p, &known))
        .collect();
    let expected: BTreeSet<Vec<String>> = [
        vec!["a".to_string()],
        vec!["b".to_string(), "dto".to_string()],
        vec!["b".to_string()],
    ]
    .into_iter()
    .collect();
    // `super::a` from `b::dto` is `b::a`, unknown, so it resolves to `b`.
    assert_eq!(targets, expected);
    let mut edges = BTreeMap::new();
    edges.insert(vec!["a".to_string()], [vec!["b".to_string()]].into());
    edges.insert(vec!["b".to_string()], [vec!["a".to_string()]].into());
    let cycle = find_cycle(&Graph {
        edges,
        dirs: BTreeSet::new(),
    })
    .unwrap();
    assert_eq!(cycle.len(), 3, "{cycle:?}");
}

/// The workspace's dependency graph from `cargo metadata`: for each package name, the names
/// of the packages it depends on for its normal (not dev, not build) targets, directly.
fn normal_dependencies() -> BTreeMap<String, BTreeSet<String>> {
    // Only this machine's platform: the dependencies of other targets are not downloaded.
    let rustc = std::process::Command::new("rustc")
        .arg("-vV")
        .output()
        .expect("rustc runs");
    let host = String::from_utf8_lossy(&rustc.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: ").map(str::to_string))
        .expect("rustc -vV names the host");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args([
            "metadata",
            "--format-version",
            "1",
            "--offline",
            "--filter-platform",
            &host,
        ])
        .current_dir(root())
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let name_of: BTreeMap<String, String> = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            (
                p["id"].as_str().unwrap().to_string(),
                p["name"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let mut deps = BTreeMap::new();
    for node in meta["resolve"]["nodes"].as_array().unwrap() {
        let normal: BTreeSet<String> = node["deps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| {
                d["dep_kinds"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|k| k["kind"].is_null())
            })
            .map(|d| name_of[d["pkg"].as_str().unwrap()].clone())
            .collect();
        deps.insert(name_of[node["id"].as_str().unwrap()].clone(), normal);
    }
    deps
}

/// Everything `package` pulls in for its normal targets, itself excluded.
fn closure(deps: &BTreeMap<String, BTreeSet<String>>, package: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    let mut todo = vec![package.to_string()];
    while let Some(p) = todo.pop() {
        for d in deps.get(&p).into_iter().flatten() {
            if seen.insert(d.clone()) {
                todo.push(d.clone());
            }
        }
    }
    seen
}

/// Cargo enforces what ARCHITECTURE.md promises: the algorithms know no service machinery,
/// the application no engine and no HTTP, the engines no HTTP, and only the server knows axum.
#[test]
fn crates_depend_on_each_other_only_downwards() {
    let deps = normal_dependencies();
    let forbidden_in_core = [
        "axum",
        "hyper",
        "tower",
        "tokio",
        "sled",
        "tokio-postgres",
        "deadpool-postgres",
        "clap",
    ];
    // JSON exists only at the edges: the core's own code never uses serde_json (tract, behind
    // the core's `cnn` feature, reads its NNEF format with it).
    assert!(
        !deps["seasonloc-core"].contains("serde_json"),
        "seasonloc-core depends on serde_json"
    );
    let rules: [(&str, &[&str]); 5] = [
        ("seasonloc-core", &forbidden_in_core),
        (
            "seasonloc-app",
            &[
                "axum",
                "hyper",
                "tower",
                "sled",
                "tokio-postgres",
                "deadpool-postgres",
                "clap",
                "seasonloc-store",
                "seasonloc-server",
            ],
        ),
        (
            "seasonloc-store",
            &["axum", "hyper", "tower", "clap", "seasonloc-server"],
        ),
        (
            "seasonloc-test-support",
            &["seasonloc-core", "seasonloc-app", "tokio"],
        ),
        // The Python package is a thin binding over the algorithms: no use case, store or
        // service below it.
        (
            "seasonloc-py",
            &[
                "seasonloc-app",
                "seasonloc-store",
                "seasonloc-server",
                "tokio",
                "axum",
            ],
        ),
    ];
    for (package, banned) in rules {
        let all = closure(&deps, package);
        assert!(deps.contains_key(package), "no package {package}");
        for b in banned {
            assert!(
                !all.contains(*b),
                "{package} depends on {b} (directly or through another crate)"
            );
        }
    }
    let with_axum: Vec<&String> = deps
        .iter()
        .filter(|(p, d)| p.starts_with("seasonloc") && d.contains("axum"))
        .map(|(p, _)| p)
        .collect();
    assert_eq!(
        with_axum,
        ["seasonloc-server"],
        "only the server crate may use axum"
    );
    // The workspace crates in their order: each may use only those before it.
    let order = [
        "seasonloc-core",
        "seasonloc-app",
        "seasonloc-store",
        "seasonloc-server",
        "seasonloc",
    ];
    for (k, p) in order.iter().enumerate() {
        for later in &order[k + 1..] {
            assert!(
                !deps[*p].contains(*later),
                "{p} depends on {later}, a crate above it"
            );
        }
    }
}
