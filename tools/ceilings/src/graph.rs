//! The import graph of the library: which file names an item of which other file, through a
//! `use` or a qualified path, following `use` re-exports to the file that defines the item.

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use crate::source::{Crate, Crates, ModPath};

/// Who imports whom in the library, from code that is not test code: file → file → the first
/// line that does it.
pub struct Graph {
    pub edges: BTreeMap<usize, BTreeMap<usize, usize>>,
}

impl Graph {
    pub fn new(crates: &Crates) -> Graph {
        let mut edges: BTreeMap<usize, BTreeMap<usize, usize>> = BTreeMap::new();
        for (from, file) in crates.files.iter().enumerate() {
            if file.krate != Crate::Lib || file.module.is_none() {
                continue;
            }
            for site in file.paths.iter().filter(|s| !s.test) {
                let Some(abs) = absolute(crates, &site.module, &site.segments, 0) else { continue };
                let Some((to, _)) = target(crates, &abs, 0) else { continue };
                if to != from {
                    let first = edges.entry(from).or_default().entry(to).or_insert(site.line);
                    *first = (*first).min(site.line);
                }
            }
        }
        Graph { edges }
    }
}

/// A path as written in `module`, made absolute (from the crate root); `None` for a path that
/// does not start in this crate (a dependency, the prelude, a local name).
pub fn absolute(
    crates: &Crates,
    module: &ModPath,
    segments: &[String],
    depth: usize,
) -> Option<Vec<String>> {
    let (first, rest) = segments.split_first()?;
    let here = crates.modules.get(&(Crate::Lib, module.clone()));
    let mut base = match first.as_str() {
        "crate" => Vec::new(),
        "self" => module.clone(),
        "super" => {
            let mut base = module.clone();
            base.pop();
            let mut rest = rest;
            while rest.first().is_some_and(|s| s == "super") {
                base.pop();
                rest = &rest[1..];
            }
            base.extend(rest.iter().cloned());
            return Some(base);
        }
        name if here.is_some_and(|m| m.children.contains(name)) => {
            let mut base = module.clone();
            base.push(name.to_owned());
            base
        }
        name => {
            let import = here.and_then(|m| m.imports.get(name))?;
            if depth > 8 || import.first() == Some(first) {
                return None;
            }
            absolute(crates, module, import, depth + 1)?
        }
    };
    base.extend(rest.iter().cloned());
    Some(base)
}

/// The file that defines what an absolute path names: the deepest module on the path, or, when
/// the next segment is a name that module only imports (a re-export), the file it comes from.
pub fn target(crates: &Crates, abs: &[String], depth: usize) -> Option<(usize, ModPath)> {
    let mut k = abs.len();
    while k > 0 && !crates.modules.contains_key(&(Crate::Lib, abs[..k].to_vec())) {
        k -= 1;
    }
    let module = abs[..k].to_vec();
    let info = crates.modules.get(&(Crate::Lib, module.clone()))?;
    if let Some(name) = abs.get(k) {
        if let Some(import) = info.imports.get(name) {
            if depth > 8 {
                return None;
            }
            let mut next = absolute(crates, &module, import, depth + 1)?;
            next.extend(abs[k + 1..].iter().cloned());
            return target(crates, &next, depth + 1);
        }
    }
    Some((info.file, module))
}

/// Tarjan's strongly connected components.
pub fn strongly_connected(adjacency: &BTreeMap<usize, Vec<usize>>) -> Vec<Vec<usize>> {
    struct State<'a> {
        adjacency: &'a BTreeMap<usize, Vec<usize>>,
        index: BTreeMap<usize, usize>,
        low: BTreeMap<usize, usize>,
        stack: Vec<usize>,
        on_stack: BTreeSet<usize>,
        out: Vec<Vec<usize>>,
    }
    fn visit(s: &mut State, v: usize) {
        let i = s.index.len();
        s.index.insert(v, i);
        s.low.insert(v, i);
        s.stack.push(v);
        s.on_stack.insert(v);
        for &w in s.adjacency.get(&v).into_iter().flatten() {
            if !s.index.contains_key(&w) {
                visit(s, w);
                let low = s.low[&v].min(s.low[&w]);
                s.low.insert(v, low);
            } else if s.on_stack.contains(&w) {
                let low = s.low[&v].min(s.index[&w]);
                s.low.insert(v, low);
            }
        }
        if s.low[&v] == s.index[&v] {
            let mut component = Vec::new();
            while let Some(w) = s.stack.pop() {
                s.on_stack.remove(&w);
                component.push(w);
                if w == v {
                    break;
                }
            }
            component.sort();
            s.out.push(component);
        }
    }
    let mut state = State {
        adjacency,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for &v in adjacency.keys() {
        if !state.index.contains_key(&v) {
            visit(&mut state, v);
        }
    }
    state.out
}

/// A shortest cycle from the component's first file back to it, within the component.
pub fn cycle_through(adjacency: &BTreeMap<usize, Vec<usize>>, component: &[usize]) -> Vec<usize> {
    let start = component[0];
    let inside: BTreeSet<usize> = component.iter().copied().collect();
    let mut previous: BTreeMap<usize, usize> = BTreeMap::new();
    let mut queue = VecDeque::from([start]);
    while let Some(v) = queue.pop_front() {
        for &w in adjacency.get(&v).into_iter().flatten() {
            if w == start {
                let mut path = vec![v];
                let mut at = v;
                while at != start {
                    at = previous[&at];
                    path.push(at);
                }
                path.reverse();
                path.push(start);
                return path;
            }
            if inside.contains(&w) && w != start && !previous.contains_key(&w) {
                previous.insert(w, v);
                queue.push_back(w);
            }
        }
    }
    vec![start, start]
}
