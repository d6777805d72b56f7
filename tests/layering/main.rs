//! Module layering checks that need no build of the crate: they read `src/` as text.
//!
//! * `src/api` and `src/solver` have no import cycles between their modules (issue 10, stage
//!   D): every `super::`, `self::` and `crate::<layer>::` path of a file is resolved to the
//!   module it names, and the resulting graph must be acyclic. A file is a module
//!   (`maps/mod.rs` is `maps`, `maps/dto.rs` is `maps::dto`); the layer's own `mod.rs` is left
//!   out (it declares every child and may hold the types they share, the way `solver/mod.rs`
//!   holds `Hypothesis`).
//! * `src/api`'s convention: a resource is a directory (`<resource>/mod.rs` + `dto.rs`); the
//!   files directly in `api/` are shared machinery that never imports a resource, and only
//!   `mod.rs` imports the router.
//!
//! Comments and `#[cfg(test)]` modules are ignored: a doc link is not a dependency, and a test
//! may reach anywhere.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A layer's modules (by path below the layer, `[]` being its `mod.rs`) and the modules each
/// one names.
struct Graph {
    edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
    /// Modules that are directories (`<name>/mod.rs`), the root excluded.
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

/// The module path of a file below the layer's directory.
fn module_of(layer_dir: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(layer_dir).unwrap();
    let mut parts: Vec<String> = rel
        .iter()
        .map(|c| c.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().unwrap();
    let stem = last.trim_end_matches(".rs");
    if stem != "mod" {
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
/// outside the layer).
fn resolve(
    layer: &str,
    from: &[String],
    path: &[String],
    known: &BTreeSet<Vec<String>>,
) -> Option<Vec<String>> {
    let mut base: Vec<String>;
    let mut rest = path;
    match path.first().map(String::as_str) {
        Some("crate") => {
            if path.get(1).map(String::as_str) != Some(layer) {
                return None;
            }
            base = Vec::new();
            rest = &path[2..];
        }
        Some("self") => {
            base = from.to_vec();
            rest = &path[1..];
        }
        Some("super") => {
            base = from.to_vec();
            while rest.first().map(String::as_str) == Some("super") {
                // `super` of the layer's root leaves the layer.
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

fn graph(layer: &str) -> Graph {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let dir = root.join(layer);
    let mut files = Vec::new();
    rs_files(&dir, &mut files);
    let known: BTreeSet<Vec<String>> = files.iter().map(|f| module_of(&dir, f)).collect();
    let dirs = files
        .iter()
        .filter(|f| f.file_name().is_some_and(|n| n == "mod.rs"))
        .map(|f| module_of(&dir, f))
        .filter(|m| !m.is_empty())
        .collect();
    let mut edges = BTreeMap::new();
    for f in &files {
        let from = module_of(&dir, f);
        let code = code_of(&std::fs::read_to_string(f).unwrap());
        let mut to = BTreeSet::new();
        for p in paths_in(&code) {
            if let Some(m) = resolve(layer, &from, &p, &known) {
                if m != from && !m.is_empty() {
                    to.insert(m);
                }
            }
        }
        edges.insert(from, to);
    }
    Graph { edges, dirs }
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

fn assert_acyclic(layer: &str) {
    let g = graph(layer);
    assert!(g.edges.len() > 3, "found too few modules in src/{layer}");
    if let Some(cycle) = find_cycle(&g) {
        panic!(
            "src/{layer} has an import cycle: {} (move what they share down into a module \
             both can use)",
            cycle.join(" -> ")
        );
    }
}

#[test]
fn api_modules_import_each_other_without_cycles() {
    assert_acyclic("api");
}

#[test]
fn solver_modules_import_each_other_without_cycles() {
    assert_acyclic("solver");
}

#[test]
fn api_shared_files_never_import_a_resource_or_the_router() {
    let g = graph("api");
    let resources: BTreeSet<&String> = g
        .dirs
        .iter()
        .filter(|m| m.len() == 1)
        .map(|m| &m[0])
        .collect();
    assert!(resources.contains(&"maps".to_string()), "{resources:?}");
    for (from, to) in &g.edges {
        // Every directory is a resource with its handlers in mod.rs and its wire types in
        // dto.rs, nothing else.
        if from.len() == 2 {
            assert_eq!(from[1], "dto", "unexpected file api/{}.rs", from.join("/"));
        }
        let shared = from.len() == 1 && !resources.contains(&from[0]) && from[0] != "router";
        for m in to {
            assert!(
                m.first().map(String::as_str) != Some("router"),
                "api::{} imports the router",
                name(from)
            );
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
        "//! see crate::api::z\nuse crate::api::{a::Thing, b::dto::{X, Y}};\nfn f() { super::a::g(); }\n#[cfg(test)]\nmod tests { use crate::api::b; }\n",
    );
    let from = vec!["b".to_string(), "dto".to_string()];
    let targets: BTreeSet<Vec<String>> = paths_in(&code)
        .iter()
        .filter_map(|p| resolve("api", &from, p, &known))
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
