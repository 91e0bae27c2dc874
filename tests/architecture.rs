//! The structure docs/architecture.md describes, kept by a test: the crates depend on each other
//! along the data flow only (core <- io, link <- daemon <- sim <- the binary), a flight build
//! leaves the simulator out; the pure core depends on no I/O, async or wall-clock crate (its whole
//! dependency tree, read from Cargo.lock) and uses none of std's; visnav-io is not async,
//! visnav-link reads no map or image; no crate's modules import each other in a circle; the
//! library crates return typed errors; no core function is over 120 lines.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Cargo.lock's packages: name -> the names it depends on.
fn lock_graph() -> BTreeMap<String, Vec<String>> {
    let text = std::fs::read_to_string(repo().join("Cargo.lock")).expect("Cargo.lock");
    let lock: toml::Value = toml::from_str(&text).expect("Cargo.lock is TOML");
    let mut g = BTreeMap::new();
    for p in lock["package"].as_array().expect("[[package]]") {
        let name = p["name"].as_str().expect("name").to_string();
        let deps: Vec<String> = p
            .get("dependencies")
            .and_then(|d| d.as_array())
            .map(|d| {
                d.iter()
                    .filter_map(|v| v.as_str())
                    // "name version" when several versions are locked.
                    .map(|s| s.split(' ').next().unwrap_or(s).to_string())
                    .collect()
            })
            .unwrap_or_default();
        g.entry(name).or_insert_with(Vec::new).extend(deps);
    }
    // The lock also lists a workspace crate's dev-dependencies (visnav-gpu's tests use
    // visnav-sim's fix bench): no build of a dependent has them, so a workspace crate's edges are
    // its manifest's `[dependencies]` (optional ones included).
    for krate in CRATES {
        g.insert(krate.to_string(), normal_dependencies(krate));
    }
    g
}

fn closure(g: &BTreeMap<String, Vec<String>>, root: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    let mut todo = vec![root.to_string()];
    while let Some(n) = todo.pop() {
        for d in g.get(&n).into_iter().flatten() {
            if seen.insert(d.clone()) {
                todo.push(d.clone());
            }
        }
    }
    seen
}

/// Cargo.lock also holds dev-dependencies; the crate's own `[dependencies]` are the roots here.
fn normal_dependencies(krate: &str) -> Vec<String> {
    let text = std::fs::read_to_string(repo().join("crates").join(krate).join("Cargo.toml"))
        .expect("crate manifest");
    let m: toml::Value = toml::from_str(&text).expect("TOML");
    m["dependencies"]
        .as_table()
        .expect("[dependencies]")
        .keys()
        .cloned()
        .collect()
}

/// The crate's whole dependency tree, its optional dependencies included.
fn tree(krate: &str) -> BTreeSet<String> {
    tree_without(krate, &[])
}

/// The same without the lock's edges `cut` (dependency, optional dependency of it).
fn tree_without(krate: &str, cut: &[(&str, &str)]) -> BTreeSet<String> {
    let mut g = lock_graph();
    for (from, to) in cut {
        if let Some(deps) = g.get_mut(*from) {
            deps.retain(|d| d != to);
        }
    }
    let mut all = BTreeSet::new();
    for d in normal_dependencies(krate) {
        all.insert(d.clone());
        all.extend(closure(&g, &d));
    }
    all
}

/// Cargo.lock records an optional dependency as soon as any package of the workspace enables it:
/// rand's OS entropy source (`getrandom`, then libc; rand's `sys_rng` / `thread_rng` features) is
/// there for proptest, a dev-dependency. The core reaches rand only through rand_distr, declared
/// without default features and with none added, and rand_distr 0.6 enables no entropy source
/// (`cargo tree -p visnav-core -e normal` shows no getrandom). The edge is cut only while that
/// holds: the core names neither rand nor getrandom itself.
fn core_tree() -> BTreeSet<String> {
    let root: toml::Value = toml::from_str(
        &std::fs::read_to_string(repo().join("Cargo.toml")).expect("workspace manifest"),
    )
    .expect("TOML");
    let distr = &root["workspace"]["dependencies"]["rand_distr"];
    assert_eq!(
        distr.get("default-features").and_then(|v| v.as_bool()),
        Some(false),
        "rand_distr with its default features: {distr:?}"
    );
    assert!(distr.get("features").is_none(), "{distr:?}");
    let direct = normal_dependencies("visnav-core");
    assert!(
        !direct.iter().any(|d| d == "rand" || d == "getrandom"),
        "{direct:?}"
    );
    tree_without("visnav-core", &[("rand", "getrandom")])
}

#[test]
fn the_core_depends_on_no_io_async_or_protocol_crate() {
    let all = core_tree();
    for banned in [
        "tokio",
        "mavlink",
        "tiff",
        "image",
        "memmap2",
        "libc",
        "tracing-subscriber",
    ] {
        assert!(
            !all.contains(banned),
            "visnav-core depends on {banned} (tree: {all:?})"
        );
    }
    // The check sees the tree: nalgebra's own dependencies are in it.
    assert!(
        all.contains("nalgebra") && all.contains("num-traits"),
        "{all:?}"
    );
}

#[test]
fn the_io_crate_is_neither_async_nor_a_protocol() {
    let all = tree("visnav-io");
    for banned in ["tokio", "mavlink", "tracing-subscriber"] {
        assert!(
            !all.contains(banned),
            "visnav-io depends on {banned} (tree: {all:?})"
        );
    }
    assert!(
        all.contains("visnav-core") && all.contains("tiff"),
        "{all:?}"
    );
}

#[test]
fn the_link_crate_knows_mavlink_not_maps_or_images() {
    let all = tree("visnav-link");
    for banned in ["visnav-io", "tiff", "image", "tracing-subscriber"] {
        assert!(
            !all.contains(banned),
            "visnav-link depends on {banned} (tree: {all:?})"
        );
    }
    assert!(
        all.contains("mavlink") && all.contains("visnav-core"),
        "{all:?}"
    );
}

/// Rust sources under `dir`, recursively.
fn sources(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).expect("read dir").flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(sources(&p));
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
    out
}

/// The code of a source file outside its test module and comments.
fn code_outside_tests(p: &Path) -> String {
    let s = std::fs::read_to_string(p).expect("read source");
    let body = s.split("#[cfg(test)]").next().unwrap_or("");
    body.lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn the_core_does_no_io_and_reads_no_clock() {
    for p in sources(&repo().join("crates/visnav-core/src")) {
        let code = code_outside_tests(&p);
        for banned in [
            "std::fs",
            "std::net",
            "File::",
            "Instant::now",
            "SystemTime",
            "std::thread::sleep",
        ] {
            assert!(!code.contains(banned), "{} uses {banned}", p.display());
        }
    }
}

/// The library crates, in the order of the data flow.
const CRATES: [&str; 7] = [
    "visnav-core",
    "visnav-metrics",
    "visnav-gpu",
    "visnav-io",
    "visnav-link",
    "visnav-daemon",
    "visnav-sim",
];

/// The workspace crates a crate may depend on: only those before it in the data flow.
fn allowed(krate: &str) -> &'static [&'static str] {
    match krate {
        "visnav-core" => &[],
        "visnav-metrics" | "visnav-gpu" | "visnav-io" => &["visnav-core"],
        "visnav-link" => &["visnav-core", "visnav-metrics"],
        "visnav-daemon" => &[
            "visnav-core",
            "visnav-metrics",
            "visnav-gpu",
            "visnav-io",
            "visnav-link",
        ],
        "visnav-sim" => &[
            "visnav-core",
            "visnav-metrics",
            "visnav-io",
            "visnav-link",
            "visnav-daemon",
        ],
        _ => &[],
    }
}

#[test]
fn the_crates_depend_on_each_other_along_the_data_flow() {
    for krate in CRATES {
        for d in normal_dependencies(krate) {
            if d.starts_with("visnav") {
                assert!(
                    allowed(krate).contains(&d.as_str()),
                    "{krate} depends on {d}: against the data flow (docs/architecture.md)"
                );
            }
        }
    }
    // The whole trees too: the daemon pulls no simulator in, by any path.
    assert!(!tree("visnav-daemon").contains("visnav-sim"));
    assert!(tree("visnav-sim").contains("visnav-daemon"));
}

#[test]
fn a_flight_build_leaves_the_simulator_out() {
    let text = std::fs::read_to_string(repo().join("Cargo.toml")).expect("Cargo.toml");
    let m: toml::Value = toml::from_str(&text).expect("TOML");
    let sim = &m["dependencies"]["visnav-sim"];
    assert_eq!(sim.get("optional").and_then(|o| o.as_bool()), Some(true));
    let features = m["features"].as_table().expect("[features]");
    let default: Vec<&str> = features["default"]
        .as_array()
        .expect("default")
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    assert_eq!(default, ["sim"]);
    // Only the `sim` feature turns the simulator on.
    for (name, list) in features {
        let on = list
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|v| v.as_str())
            .any(|f| f == "dep:visnav-sim" || f.starts_with("visnav-sim/"));
        assert_eq!(on, name == "sim", "feature {name}");
    }
    // The library re-exports the simulator only behind the feature (the cli modules that use it
    // are gated in cli/mod.rs, which `cargo clippy --no-default-features` in CI compiles).
    let lib = std::fs::read_to_string(repo().join("src/lib.rs")).expect("src/lib.rs");
    let lines: Vec<&str> = lib.lines().collect();
    let mut seen = 0;
    for (i, l) in lines.iter().enumerate() {
        if l.contains("visnav_sim") && !l.trim_start().starts_with("//") {
            seen += 1;
            assert!(
                i > 0 && lines[i - 1].contains("#[cfg(feature = \"sim\")]"),
                "src/lib.rs:{}: visnav-sim named without the `sim` gate",
                i + 1
            );
        }
    }
    assert!(seen > 0, "src/lib.rs re-exports the simulator as `sitl`");
}

/// User text never shows Rust's debug formatting (`Some(3)`, `[1.0, 2.0]`, `Utm { zone: 10 }`):
/// no `{:?}` / `{name:?}` outside the tests of the crates and the binary, except where a line
/// says why (`// debug form: ...`, e.g. a float's shortest round-trip text as a TOML literal).
#[test]
fn user_text_has_no_debug_formatting() {
    let mut dirs: Vec<PathBuf> = CRATES
        .iter()
        .map(|k| repo().join("crates").join(k).join("src"))
        .collect();
    dirs.push(repo().join("src"));
    let mut found = Vec::new();
    for dir in dirs {
        for p in sources(&dir) {
            if p.components().any(|c| c.as_os_str() == "tests") || p.ends_with("tests.rs") {
                continue;
            }
            for (n, line) in code_outside_tests(&p).lines().enumerate() {
                let debug = line.contains(":?}");
                if debug && !line.contains("// debug form:") {
                    found.push(format!(
                        "{}: {} (line {} of the code)",
                        p.display(),
                        line.trim(),
                        n + 1
                    ));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "debug formatting in user text:\n{}",
        found.join("\n")
    );
}

#[test]
fn the_library_crates_return_typed_errors() {
    for krate in CRATES {
        for p in sources(&repo().join("crates").join(krate).join("src")) {
            let code = code_outside_tests(&p);
            for (n, line) in code.lines().enumerate() {
                let t = line.trim();
                let string_error = t.contains("Result<") && t.contains(", String>");
                assert!(
                    !string_error,
                    "{}: `{t}` (line {} of the code)",
                    p.display(),
                    n + 1
                );
            }
        }
    }
}

/// A library crate uses the others' items by their own paths and re-exports none of them, so
/// each type has one path in the crates (the binary's src/lib.rs joins them under one name for
/// users; that is the only place that mixes crates).
#[test]
fn no_library_crate_re_exports_another() {
    for krate in CRATES {
        for p in sources(&repo().join("crates").join(krate).join("src")) {
            let code = code_outside_tests(&p);
            for line in code.lines() {
                let t = line.trim_start();
                let re_export = t.starts_with("pub use ") && t.contains("visnav_");
                assert!(!re_export, "{}: `{t}`", p.display());
            }
        }
    }
}

/// Functions of rustfmt-formatted `code` longer than `max` lines: `(line, name, lines)`. A
/// function starts at its `fn` line and ends at the first `}` line at the same indentation.
fn long_functions(code: &str, max: usize) -> Vec<(usize, String, usize)> {
    let lines: Vec<&str> = code.lines().collect();
    let mut out = Vec::new();
    for (i, l) in lines.iter().enumerate() {
        let t = l.trim_start();
        let decl = [
            "fn ",
            "pub fn ",
            "pub(crate) fn ",
            "pub(super) fn ",
            "const fn ",
            "pub const fn ",
            "async fn ",
            "pub async fn ",
            "pub(crate) async fn ",
            "pub(super) async fn ",
        ]
        .iter()
        .find_map(|p| t.strip_prefix(p));
        let Some(rest) = decl else { continue };
        if t.ends_with(';') {
            continue; // a declaration without a body
        }
        let indent = l.len() - t.len();
        let end = format!("{}}}", " ".repeat(indent));
        if let Some(n) = lines[i + 1..].iter().position(|e| *e == end) {
            let name: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if n + 2 > max {
                out.push((i + 1, name, n + 2));
            }
        }
    }
    out
}

#[test]
fn no_core_function_is_over_120_lines() {
    for p in sources(&repo().join("crates/visnav-core/src")) {
        let text = std::fs::read_to_string(&p).expect("read source");
        let code = text.split("#[cfg(test)]").next().unwrap_or("");
        let long = long_functions(code, 120);
        assert!(long.is_empty(), "{}: {long:?}", p.display());
    }
    // The measure sees a function's length.
    let f = format!("fn f() {{\n{}}}\n", "    x();\n".repeat(130));
    assert_eq!(long_functions(&f, 120).len(), 1);
}

/// The functions outside the core still over 120 lines (file under `crates/`, name). The list
/// can only shrink: a function not on it may not grow past 120 lines, and one on it that is no
/// longer long must leave it.
const LONG_FUNCTIONS: &[(&str, &str)] = &[("visnav-sim/src/closed_loop.rs", "run_until_stopped")];

#[test]
fn no_other_library_function_grows_over_120_lines() {
    let mut found = BTreeSet::new();
    for krate in CRATES.iter().filter(|k| **k != "visnav-core") {
        let src = repo().join("crates").join(krate).join("src");
        for p in sources(&src) {
            let text = std::fs::read_to_string(&p).expect("read source");
            let code = text.split("#[cfg(test)]").next().unwrap_or("");
            let rel = p
                .strip_prefix(repo().join("crates"))
                .expect("under crates")
                .to_string_lossy()
                .replace('\\', "/");
            for (line, name, n) in long_functions(code, 120) {
                let listed = LONG_FUNCTIONS.iter().any(|(f, m)| *f == rel && *m == name);
                assert!(
                    listed,
                    "{rel}:{line}: `{name}` is {n} lines (at most 120 outside the allow-list)"
                );
                found.insert((rel.clone(), name));
            }
        }
    }
    for (f, m) in LONG_FUNCTIONS {
        assert!(
            found.contains(&(f.to_string(), m.to_string())),
            "{f}: `{m}` is no longer over 120 lines: take it off LONG_FUNCTIONS"
        );
    }
}

/// The modules under `src` (`<name>.rs` or `<name>/`) and which of them each names with one of
/// `prefixes` outside its tests. A top-level module's `super::` is the crate root as `crate::`
/// is; a name the crate root re-exports (`pub use module::{Name}` in lib.rs) counts as its
/// module, so an import through the root is seen.
fn modules_under(src: &Path, prefixes: &[&str]) -> BTreeMap<String, BTreeSet<String>> {
    let top_of = |p: &Path| {
        p.strip_prefix(src)
            .expect("under src")
            .components()
            .next()
            .and_then(|c| c.as_os_str().to_str())
            .unwrap_or("")
            .trim_end_matches(".rs")
            .to_string()
    };
    let files = sources(src);
    let modules: BTreeSet<String> = files.iter().map(|p| top_of(p)).collect();
    let exports = root_exports(&src.join("lib.rs"));
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for p in files {
        let top = top_of(&p);
        if ["lib", "main", "mod"].contains(&top.as_str()) {
            continue;
        }
        let top_level = p.parent() == Some(src);
        let code = code_outside_tests(&p);
        let uses = g.entry(top.clone()).or_default();
        let root_prefixes: &[&str] = if top_level && prefixes.contains(&"crate::") {
            &["super::"]
        } else {
            &[]
        };
        for prefix in prefixes.iter().chain(root_prefixes) {
            for (i, _) in code.match_indices(prefix) {
                let before = code[..i].chars().next_back();
                if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                    continue;
                }
                let rest = &code[i + prefix.len()..];
                // `crate::{a, b::C}`: each name in the braces.
                let names: Vec<String> = match rest.strip_prefix('{') {
                    Some(list) => list
                        .split('}')
                        .next()
                        .unwrap_or("")
                        .split(',')
                        .map(|n| ident(n.trim()))
                        .collect(),
                    None => vec![ident(rest)],
                };
                for name in names {
                    let module = if modules.contains(&name) {
                        Some(name)
                    } else {
                        exports.get(&name).cloned()
                    };
                    if let Some(m) = module.filter(|m| *m != top && !m.is_empty()) {
                        uses.insert(m);
                    }
                }
            }
        }
    }
    g
}

/// The identifier at the start of `s`.
fn ident(s: &str) -> String {
    s.chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
        .collect()
}

/// The names a crate root re-exports, each with the module it comes from (`pub use m::{A, b}`
/// and `pub use m::A`); empty without a lib.rs.
fn root_exports(lib: &Path) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let Ok(text) = std::fs::read_to_string(lib) else {
        return out;
    };
    for stmt in text.split("pub use ").skip(1) {
        let stmt = stmt.split(';').next().unwrap_or("");
        let Some((module, rest)) = stmt.split_once("::") else {
            continue;
        };
        let rest = rest.trim().trim_start_matches('{').trim_end_matches('}');
        for name in rest.split(',') {
            let name = ident(name.trim().rsplit("::").next().unwrap_or(""));
            if !name.is_empty() {
                out.insert(name, ident(module.trim()));
            }
        }
    }
    out
}

/// A circle through `start` in `g`, if any (depth-first).
fn circle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        g: &BTreeMap<String, BTreeSet<String>>,
        n: &str,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(i) = path.iter().position(|p| p == n) {
            let mut c = path[i..].to_vec();
            c.push(n.to_string());
            return Some(c);
        }
        if done.contains(n) {
            return None;
        }
        path.push(n.to_string());
        for m in g.get(n).into_iter().flatten() {
            if let Some(c) = visit(g, m, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(n.to_string());
        None
    }
    let mut done = BTreeSet::new();
    for n in g.keys() {
        if let Some(c) = visit(g, n, &mut Vec::new(), &mut done) {
            return Some(c);
        }
    }
    None
}

#[test]
fn the_crates_modules_import_each_other_without_a_circle() {
    for krate in CRATES {
        let g = modules_under(&repo().join("crates").join(krate).join("src"), &["crate::"]);
        assert_eq!(circle(&g), None, "{krate}: import circle; the graph: {g:?}");
    }
    // The graph sees `super::` in a top-level module and names re-exported at the root.
    let daemon = modules_under(&repo().join("crates/visnav-daemon/src"), &["crate::"]);
    assert!(daemon["wiring"].contains("fixer"), "{daemon:?}");
    assert!(daemon["wiring"].contains("config"), "{daemon:?}");
    let exports = root_exports(&repo().join("crates/visnav-daemon/src/lib.rs"));
    assert_eq!(
        exports.get("DaemonConfig").map(String::as_str),
        Some("config"),
        "{exports:?}"
    );
    // Inside io's geo: the GeoTIFF reader, its info and the window reader.
    let geo = repo().join("crates/visnav-io/src/geo");
    let g = modules_under(&geo, &["super::"]);
    assert!(g["window"].contains("geotiff_info"), "{g:?}");
    assert_eq!(circle(&g), None, "io geo: import circle; the graph: {g:?}");
}

/// The daemon's crate root is only modules and re-exports: the service lives in `daemon`, the
/// navigation task in `nav_task`, the frame path's view of the engine in `fixer`.
#[test]
fn the_daemons_crate_root_is_only_modules_and_re_exports() {
    let lib = code_outside_tests(&repo().join("crates/visnav-daemon/src/lib.rs"));
    let code: String = lib
        .lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join(" ");
    for stmt in code.split(';').map(str::trim).filter(|s| !s.is_empty()) {
        // Crate-level lint attributes (`#![warn(missing_docs)]`) come before the first item.
        let mut stmt = stmt;
        while let Some(rest) = stmt.strip_prefix("#![") {
            stmt = rest.split_once(']').map_or("", |(_, r)| r).trim_start();
        }
        assert!(
            ["pub mod ", "mod ", "pub use "]
                .iter()
                .any(|k| stmt.starts_with(k)),
            "visnav-daemon/src/lib.rs: {stmt}"
        );
    }
}

#[test]
fn the_binarys_commands_import_each_other_without_a_circle() {
    let g = modules_under(&repo().join("src/cli"), &["super::"]);
    // The graph is read: `bench fix` is a bench mode.
    assert!(g["bench"].contains("bench_fix"), "{g:?}");
    assert_eq!(circle(&g), None, "cli: import circle; the graph: {g:?}");
    // The circle finder finds one.
    let mut bad = g.clone();
    bad.entry("bench_fix".into())
        .or_default()
        .insert("bench".into());
    assert!(circle(&bad).is_some());
}
