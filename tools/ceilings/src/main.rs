//! `ceilings`: the structure checks that CI runs (`.ci/ceilings`; docs/architecture.md,
//! "Checked in CI"). It fails on
//!
//! - `ceiling`: a source file (src/**/*.rs, tests/**/*.rs, web/*.js, tests/**/*.mjs, and the
//!   Python of tests/, clients/ and bench/) over 700 lines whose first line is not
//!   `// ceiling: <reason>` (`# ceiling: <reason>` in Python);
//! - `status-literal`: a job-status word (the variants of `JobStatus` in src/domain/, as serde
//!   writes them) hand-written in a string literal (SQL included) in src/ outside src/domain/;
//! - `layer`: an import that runs up the layers, or an HTTP crate below http/, or sqlx below
//!   store/;
//! - `cycle`: an import cycle between files of the library;
//!
//! unless the exception is listed, with its reason, in `allow.rs`. Test code (`#[cfg(test)]`,
//! `#[test]`) is exempt from the last three rules.
//!
//!     ceilings [--root DIR]           exit 0: clean, 1: problems found, 2: could not check
//!     ceilings [--root DIR] --graph   print the import graph between top-level modules

mod allow;
mod graph;
mod source;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::Instant;

use graph::{cycle_through, strongly_connected, Graph};
use source::{Crate, Crates};

/// Lines a source file may have without a reason.
const CEILING_LINES: usize = 700;
/// The first line that gives a long file its reason (Python's comments start with `#`).
const MARKER: &str = "// ceiling:";
const PYTHON_MARKER: &str = "# ceiling:";

fn marker(rel: &str) -> &'static str {
    if rel.ends_with(".py") {
        PYTHON_MARKER
    } else {
        MARKER
    }
}
const ALLOW_FILE: &str = "tools/ceilings/src/allow.rs";

/// The layers of docs/architecture.md, top first. A module may import its own layer and the
/// layers below it.
const LAYERS: &[(&str, &[&str])] = &[
    ("entry points", &["server", "worker", "demo", "bench"]),
    (
        "the transports (HTTP, gRPC) and the service's settings",
        &["http", "grpc", "config", "logging"],
    ),
    ("serving and the job queue", &["serving", "jobs"]),
    ("storage", &["store"]),
    ("domain", &["domain"]),
    ("the core, below every service layer", &["algo", "data", "envs", "charts"]),
    ("leaf utilities", &["text", "lttb"]),
];
/// Crates that speak HTTP (gRPC's tonic too): only the layers from http/ up may use them.
const HTTP_CRATES: &[&str] = &[
    "axum",
    "hyper",
    "hyper_util",
    "tower",
    "tower_http",
    "utoipa_axum",
    "reqwest",
    "http",
    "tonic",
];
/// Crates that speak SQL: only the layers from store/ up may use them.
const SQL_CRATES: &[&str] = &["sqlx"];

struct Finding {
    file: String,
    line: usize,
    rule: &'static str,
    message: String,
}

#[derive(Default)]
struct Report {
    problems: Vec<Finding>,
    notes: Vec<Finding>,
}

impl Report {
    fn problem(&mut self, file: &str, line: usize, rule: &'static str, message: String) {
        self.problems.push(Finding { file: file.to_owned(), line, rule, message });
    }

    fn note(&mut self, file: &str, line: usize, rule: &'static str, message: String) {
        self.notes.push(Finding { file: file.to_owned(), line, rule, message });
    }
}

fn main() {
    let mut root = String::from(".");
    let mut graph_only = false;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match (arg.as_str(), if arg == "--root" { args.next() } else { None }) {
            ("--root", Some(dir)) => root = dir,
            ("--graph", _) => graph_only = true,
            _ => {
                eprintln!("usage: ceilings [--root DIR] [--graph]");
                std::process::exit(2);
            }
        }
    }
    if graph_only {
        match print_graph(Path::new(&root)) {
            Ok(()) => return,
            Err(e) => {
                eprintln!("ceilings: could not read the crate: {e}");
                std::process::exit(2);
            }
        }
    }
    let started = Instant::now();
    let root = Path::new(&root);
    let mut report = Report::default();
    let checked = match run(root, &mut report) {
        Ok(checked) => checked,
        Err(e) => {
            eprintln!("ceilings: could not check: {e}");
            std::process::exit(2);
        }
    };
    let show = |prefix: &str, f: &Finding| {
        let at = if f.line > 0 { format!("{}:{}", f.file, f.line) } else { f.file.clone() };
        println!("{prefix}{at}: [{}] {}", f.rule, f.message);
    };
    report.notes.sort_by(|a, b| (&a.file, a.line).cmp(&(&b.file, b.line)));
    report.problems.sort_by(|a, b| (&a.file, a.line).cmp(&(&b.file, b.line)));
    for note in &report.notes {
        show("allowed: ", note);
    }
    for problem in &report.problems {
        show("", problem);
    }
    let ms = started.elapsed().as_millis();
    if report.problems.is_empty() {
        println!("ceilings: ok ({checked} files, {} allowed, {ms} ms)", report.notes.len());
    } else {
        println!(
            "ceilings: {} problem(s) in {checked} files ({ms} ms); the rules and how to allow an \
             exception: docs/architecture.md, \"Checked in CI\"",
            report.problems.len()
        );
        std::process::exit(1);
    }
}

fn run(root: &Path, report: &mut Report) -> Result<usize, String> {
    if !root.join("src/lib.rs").is_file() {
        return Err(format!(
            "{} has no src/lib.rs: pass the repository with --root",
            root.display()
        ));
    }
    let checked = ceilings(root, report)?;
    let crates = source::load(root)?;
    status_literals(root, &crates, report)?;
    let graph = Graph::new(&crates);
    layers(&crates, &graph, report);
    cycles(&crates, &graph, report);
    Ok(checked)
}

/// Which top-level module imports which (code that is not test code), with the layers.
fn print_graph(root: &Path) -> Result<(), String> {
    let crates = source::load(root)?;
    let graph = Graph::new(&crates);
    let mut edges: BTreeMap<(&str, &str), usize> = BTreeMap::new();
    for (&from, targets) in &graph.edges {
        for &to in targets.keys() {
            if let (Some(a), Some(b)) = (top_module(&crates, from), top_module(&crates, to)) {
                if a != b {
                    *edges.entry((a, b)).or_default() += 1;
                }
            }
        }
    }
    for ((from, to), count) in edges {
        let layer = |m: &str| layer_of(m).map_or("no layer", |l| LAYERS[l].0);
        println!("{from} ({}) -> {to} ({}): {count} file import(s)", layer(from), layer(to));
    }
    Ok(())
}

/// Every file under `folder` (relative to `root`) that `keep` accepts, sorted, relative and with
/// `/`; dependency and build folders are skipped.
pub fn walk(root: &Path, folder: &str, keep: &dyn Fn(&str) -> bool) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    let mut pending = vec![folder.to_owned()];
    while let Some(dir) = pending.pop() {
        let entries = match std::fs::read_dir(root.join(&dir)) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(format!("{dir}: {e}")),
        };
        for entry in entries {
            let entry = entry.map_err(|e| format!("{dir}: {e}"))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let rel = format!("{dir}/{name}");
            let kind = entry.file_type().map_err(|e| format!("{rel}: {e}"))?;
            if kind.is_dir() {
                // Not checked: installed packages, build outputs and Python's byte code.
                let generated = ["node_modules", "target", "build", "__pycache__"];
                if !name.starts_with('.') && !generated.contains(&name.as_str()) {
                    pending.push(rel);
                }
            } else if kind.is_file() && keep(&rel) {
                out.push(rel);
            }
        }
    }
    out.sort();
    Ok(out)
}

// --- ceiling ---------------------------------------------------------------------------------

fn ceilings(root: &Path, report: &mut Report) -> Result<usize, String> {
    let mut files = walk(root, "src", &|p| p.ends_with(".rs"))?;
    files.extend(walk(root, "tests", &|p| p.ends_with(".rs"))?);
    // web/*.js: the dashboard's own scripts, not web/vendor/.
    files.extend(walk(root, "web", &|p| p.ends_with(".js") && p.matches('/').count() == 1)?);
    // The browser tests, and the Python of the clients' tests, the Python client and benchmarks.
    files.extend(walk(root, "tests", &|p| p.ends_with(".mjs") || p.ends_with(".py"))?);
    for folder in ["clients", "bench"] {
        files.extend(walk(root, folder, &|p| p.ends_with(".py"))?);
    }
    for rel in &files {
        let text = std::fs::read_to_string(root.join(rel)).map_err(|e| format!("{rel}: {e}"))?;
        let lines = text.lines().count();
        let first = text.lines().next().unwrap_or("");
        let marker = marker(rel);
        let reason = first.strip_prefix(marker).map(str::trim);
        let allowed = allow::CEILING.iter().find(|(file, _)| file == rel);
        if lines > CEILING_LINES {
            match (reason, allowed) {
                (Some(reason), _) if !reason.is_empty() => {
                    report.note(rel, 1, "ceiling", format!("{lines} lines: {reason}"))
                }
                (_, Some((_, why))) => report.note(
                    rel,
                    0,
                    "ceiling",
                    format!("{lines} lines, on the allow-list in {ALLOW_FILE}: {why}"),
                ),
                (Some(_), None) => report.problem(
                    rel,
                    1,
                    "ceiling",
                    format!("{lines} lines and a `{marker}` line without a reason: say why"),
                ),
                (None, None) => report.problem(
                    rel,
                    0,
                    "ceiling",
                    format!(
                        "{lines} lines, over the ceiling of {CEILING_LINES}: split it, or make \
                         its first line `{marker} <why it is long>`"
                    ),
                ),
            }
        } else {
            if reason.is_some() {
                report.problem(
                    rel,
                    1,
                    "ceiling",
                    format!(
                        "{lines} lines, within the ceiling of {CEILING_LINES}: remove its \
                         `{marker}` line"
                    ),
                );
            }
            if allowed.is_some() {
                report.problem(
                    rel,
                    0,
                    "ceiling",
                    format!(
                        "{lines} lines, within the ceiling of {CEILING_LINES}: remove its entry \
                         from CEILING in {ALLOW_FILE}"
                    ),
                );
            }
        }
    }
    for (file, _) in allow::CEILING {
        if !files.iter().any(|f| f == file) {
            report.problem(
                file,
                0,
                "ceiling",
                format!("no such file: remove it from CEILING in {ALLOW_FILE}"),
            );
        }
    }
    Ok(files.len())
}

// --- status-literal --------------------------------------------------------------------------

fn status_literals(root: &Path, crates: &Crates, report: &mut Report) -> Result<(), String> {
    let Some((enum_file, words)) = source::enum_words(root, "src/domain", "JobStatus")? else {
        report.problem(
            "src/domain",
            0,
            "status-literal",
            "no `enum JobStatus` found: the rule reads the job statuses from it".to_owned(),
        );
        return Ok(());
    };
    let mut seen = BTreeSet::new();
    for file in crates
        .files
        .iter()
        .filter(|f| f.rel.starts_with("src/") && !f.rel.starts_with("src/domain/"))
    {
        let mut found = Vec::new();
        for literal in file.literals.iter().filter(|l| !l.test) {
            for word in &words {
                let hits = if literal.value == *word {
                    1
                } else {
                    literal.value.matches(&format!("'{word}'")).count()
                        + literal.value.matches(&format!("\"{word}\"")).count()
                };
                for _ in 0..hits {
                    found.push((literal.line, word.clone(), snippet(&literal.value)));
                }
            }
        }
        let allowed = allow::STATUS_LITERALS.iter().find(|(f, _, _)| *f == file.rel);
        seen.insert(file.rel.clone());
        match allowed {
            Some((_, count, why)) if found.len() == *count => report.note(
                &file.rel,
                0,
                "status-literal",
                format!("{count} job-status literal(s), on the allow-list in {ALLOW_FILE}: {why}"),
            ),
            Some((_, count, _)) if found.len() < *count => report.problem(
                &file.rel,
                0,
                "status-literal",
                format!(
                    "{} job-status literal(s) where STATUS_LITERALS in {ALLOW_FILE} allows {count}: \
                     lower the entry to {} (remove it at 0)",
                    found.len(),
                    found.len()
                ),
            ),
            _ => {
                let over = match allowed {
                    Some((_, count, _)) => format!(" ({} here, {count} allowed in {ALLOW_FILE})", found.len()),
                    None => String::new(),
                };
                for (line, word, text) in found {
                    report.problem(
                        &file.rel,
                        line,
                        "status-literal",
                        format!(
                            "job-status '{word}' written by hand in {text}: use the enum of \
                             {enum_file} (`.as_str()` bound as a parameter, or `.sql()` in SQL text){over}"
                        ),
                    );
                }
            }
        }
    }
    for (file, _, _) in allow::STATUS_LITERALS {
        if !seen.contains(*file) {
            report.problem(
                file,
                0,
                "status-literal",
                format!("no such file: remove it from STATUS_LITERALS in {ALLOW_FILE}"),
            );
        }
    }
    Ok(())
}

/// A literal as quoted in a message: one line, at most 70 characters.
fn snippet(value: &str) -> String {
    let flat = value.split_whitespace().collect::<Vec<_>>().join(" ");
    if flat.chars().count() > 70 {
        format!("\"{}…\"", flat.chars().take(69).collect::<String>())
    } else {
        format!("\"{flat}\"")
    }
}

fn top_module(crates: &Crates, file: usize) -> Option<&str> {
    crates.files[file].module.as_ref()?.first().map(String::as_str)
}

fn layer_of(module: &str) -> Option<usize> {
    LAYERS.iter().position(|(_, modules)| modules.contains(&module))
}

// --- layer -----------------------------------------------------------------------------------

fn layers(crates: &Crates, graph: &Graph, report: &mut Report) {
    let mut unplaced = BTreeSet::new();
    let mut used_allowances = BTreeSet::new();
    for (index, file) in crates.files.iter().enumerate() {
        if file.krate != Crate::Lib {
            continue;
        }
        let Some(from) = top_module(crates, index) else { continue };
        let Some(from_layer) = layer_of(from) else {
            if unplaced.insert(from.to_owned()) {
                report.problem(
                    &file.rel,
                    0,
                    "layer",
                    format!(
                        "module `{from}` is in no layer: place it in LAYERS of \
                         tools/ceilings/src/main.rs and in docs/architecture.md"
                    ),
                );
            }
            continue;
        };
        for (&to_file, &line) in graph.edges.get(&index).into_iter().flatten() {
            let Some(to) = top_module(crates, to_file) else { continue };
            let Some(to_layer) = layer_of(to) else { continue };
            if to_layer >= from_layer {
                continue;
            }
            if let Some(entry) = allow::LAYERS.iter().find(|(f, m, _)| *f == file.rel && *m == to) {
                used_allowances.insert((entry.0, entry.1));
                report.note(
                    &file.rel,
                    line,
                    "layer",
                    format!("imports `{to}`, a higher layer: {}", entry.2),
                );
                continue;
            }
            report.problem(
                &file.rel,
                line,
                "layer",
                format!(
                    "`{from}` ({}) imports {} of `{to}`, a higher layer ({}): imports go down \
                     the layers only",
                    LAYERS[from_layer].0, crates.files[to_file].rel, LAYERS[to_layer].0
                ),
            );
        }
        let http = layer_of("http").unwrap_or(0);
        let store = layer_of("store").unwrap_or(0);
        let here = |site: &source::PathSite| crates.modules.get(&(Crate::Lib, site.module.clone()));
        let mut reported = BTreeSet::new();
        for site in file.paths.iter().filter(|s| !s.test) {
            // A lone name outside `use` is a local (`let http = …`), not the crate.
            if site.segments.len() < 2 && !site.in_use {
                continue;
            }
            let first = site.segments[0].as_str();
            // A child module or an imported name that shadows the crate's name is not the crate.
            if here(site).is_some_and(|m| {
                m.children.contains(first) || m.imports.get(first).is_some_and(|i| i[0] != first)
            }) {
                continue;
            }
            let what = if HTTP_CRATES.contains(&first) && from_layer > http {
                "HTTP"
            } else if SQL_CRATES.contains(&first) && from_layer > store {
                "SQL"
            } else {
                continue;
            };
            if reported.insert((site.line, first)) {
                report.problem(
                    &file.rel,
                    site.line,
                    "layer",
                    format!(
                        "`{from}` ({}) uses the {what} crate `{first}`: nothing below {} knows \
                         about {what}",
                        LAYERS[from_layer].0,
                        if what == "HTTP" { "http/" } else { "store/" }
                    ),
                );
            }
        }
    }
    for (file, module, _) in allow::LAYERS {
        if !used_allowances.contains(&(*file, *module)) {
            report.problem(
                file,
                0,
                "layer",
                format!(
                    "imports no `{module}` any more: remove its entry from LAYERS in {ALLOW_FILE}"
                ),
            );
        }
    }
}

// --- cycle -----------------------------------------------------------------------------------

/// Import cycles between files of the library. A file's use of its own ancestors (`super::`,
/// the items of the `mod.rs` that declares it) is the module tree, not an import, and is left
/// out; what a `mod.rs` re-exports counts as imported from the file that defines it.
fn cycles(crates: &Crates, graph: &Graph, report: &mut Report) {
    let ancestor = |from: usize, to: usize| {
        let (Some(a), Some(b)) = (&crates.files[from].module, &crates.files[to].module) else {
            return false;
        };
        b.len() < a.len() && a.starts_with(b)
    };
    let mut adjacency: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (&from, targets) in &graph.edges {
        for &to in targets.keys() {
            if !ancestor(from, to) {
                adjacency.entry(from).or_default().push(to);
            }
        }
    }
    let mut matched = BTreeSet::new();
    for component in strongly_connected(&adjacency) {
        if component.len() < 2 {
            continue;
        }
        let names: BTreeSet<&str> =
            component.iter().map(|&f| crates.files[f].rel.as_str()).collect();
        let path = cycle_through(&adjacency, &component);
        let steps: Vec<String> = path
            .windows(2)
            .map(|w| {
                format!(
                    "{}:{} imports {}",
                    crates.files[w[0]].rel, graph.edges[&w[0]][&w[1]], crates.files[w[1]].rel
                )
            })
            .collect();
        let first = &crates.files[path[0]];
        let line = graph.edges[&path[0]][&path[1]];
        let message = format!(
            "import cycle between {}: {}",
            names.iter().cloned().collect::<Vec<_>>().join(", "),
            steps.join("; ")
        );
        match allow::CYCLES
            .iter()
            .position(|(files, _)| files.iter().copied().collect::<BTreeSet<_>>() == names)
        {
            Some(i) => {
                matched.insert(i);
                report.note(
                    &first.rel,
                    line,
                    "cycle",
                    format!("{message} (on the allow-list: {})", allow::CYCLES[i].1),
                );
            }
            None => report.problem(
                &first.rel,
                line,
                "cycle",
                format!("{message}: break it (move what both need below both)"),
            ),
        }
    }
    for (i, (files, _)) in allow::CYCLES.iter().enumerate() {
        if !matched.contains(&i) {
            report.problem(
                files[0],
                0,
                "cycle",
                format!(
                    "the allowed cycle between {} is gone or changed: remove or update its entry \
                     in CYCLES of {ALLOW_FILE}",
                    files.join(", ")
                ),
            );
        }
    }
}
