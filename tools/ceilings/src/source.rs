//! Reading the crate with syn: the module tree (from `src/lib.rs` and `src/main.rs` through
//! their `mod` declarations), every path that names something of the crate or of a dependency,
//! every string literal, and which of them is test code (`#[cfg(test)]`, `#[test]`, or a file
//! whose `mod` declaration is `#[cfg(test)]`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use proc_macro2::{Delimiter, TokenStream, TokenTree};
use syn::punctuated::Punctuated;
use syn::visit::{self, Visit};
use syn::{Attribute, Expr, Item, Token, UseTree};

/// A module path inside one crate (`["algo", "safedice"]`; the crate root is `[]`).
pub type ModPath = Vec<String>;

/// Which crate of the package a file belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Crate {
    /// `src/lib.rs` and its modules: the layered library.
    Lib,
    /// `src/main.rs` and its modules: the CLI, which reaches the library as `safedice::`.
    Bin,
}

/// A path as written (`super::losses::scalar`, `crate::data::Dataset`, `sqlx::query`).
#[derive(Clone, Debug)]
pub struct PathSite {
    pub segments: Vec<String>,
    /// The module (inline modules included) the path is written in.
    pub module: ModPath,
    pub line: usize,
    pub test: bool,
    /// Written in a `use` declaration (a lone name there is a crate or a module, never a local).
    pub in_use: bool,
}

/// A string literal's value and where it is.
#[derive(Clone, Debug)]
pub struct LiteralSite {
    pub value: String,
    pub line: usize,
    pub test: bool,
}

/// One parsed source file.
#[derive(Debug)]
pub struct SourceFile {
    /// Relative to the root, with `/` (`src/algo/safedice.rs`).
    pub rel: String,
    pub krate: Crate,
    /// The module the file is (`None` for a file no `mod` declaration reaches).
    pub module: Option<ModPath>,
    pub paths: Vec<PathSite>,
    pub literals: Vec<LiteralSite>,
}

/// A module of the tree: the file it lives in, its child modules and the names its `use`
/// declarations bring in (followed when another module names an item through it).
#[derive(Debug, Default)]
pub struct Module {
    pub file: usize,
    pub children: BTreeSet<String>,
    /// Name brought in by a `use` of this module → the path it names, as written.
    pub imports: BTreeMap<String, Vec<String>>,
}

/// The whole package as the checks see it.
#[derive(Debug, Default)]
pub struct Crates {
    pub files: Vec<SourceFile>,
    pub modules: BTreeMap<(Crate, ModPath), Module>,
}

/// Parses `src/lib.rs`, `src/main.rs` and every module they declare, then every other `.rs`
/// file under `src/` on its own (as code no module reaches).
pub fn load(root: &Path) -> Result<Crates, String> {
    let mut crates = Crates::default();
    for (krate, root_file) in [(Crate::Lib, "src/lib.rs"), (Crate::Bin, "src/main.rs")] {
        if root.join(root_file).is_file() {
            load_module_file(root, &mut crates, krate, root_file.to_owned(), Vec::new(), false)?;
        }
    }
    let loaded: BTreeSet<String> = crates.files.iter().map(|f| f.rel.clone()).collect();
    for rel in crate::walk(root, "src", &|p| p.ends_with(".rs"))? {
        if !loaded.contains(&rel) {
            let (collector, _) = parse(root, &rel, Vec::new(), false)?;
            crates.files.push(SourceFile {
                rel,
                krate: Crate::Lib,
                module: None,
                paths: collector.paths,
                literals: collector.literals,
            });
        }
    }
    Ok(crates)
}

fn parse(
    root: &Path,
    rel: &str,
    module: ModPath,
    file_test: bool,
) -> Result<(Collector, syn::File), String> {
    let text = std::fs::read_to_string(root.join(rel)).map_err(|e| format!("{rel}: {e}"))?;
    let file = syn::parse_file(&text).map_err(|e| {
        let at = e.span().start();
        format!("{rel}:{}:{}: does not parse as Rust: {e}", at.line, at.column + 1)
    })?;
    let mut collector = Collector {
        module,
        test_depth: usize::from(file_test),
        paths: Vec::new(),
        literals: Vec::new(),
        mods: Vec::new(),
        imports: Vec::new(),
    };
    collector.visit_file(&file);
    Ok((collector, file))
}

fn load_module_file(
    root: &Path,
    crates: &mut Crates,
    krate: Crate,
    rel: String,
    module: ModPath,
    file_test: bool,
) -> Result<(), String> {
    let (collector, _) = parse(root, &rel, module.clone(), file_test)?;
    let index = crates.files.len();
    crates.modules.entry((krate, module.clone())).or_default().file = index;
    for decl in collector.mods.iter().filter(|d| d.inline) {
        let mut path = decl.parent.clone();
        path.push(decl.name.clone());
        crates.modules.entry((krate, path)).or_default().file = index;
    }
    for decl in &collector.mods {
        crates
            .modules
            .entry((krate, decl.parent.clone()))
            .or_default()
            .children
            .insert(decl.name.clone());
    }
    for (at, name, target) in &collector.imports {
        crates
            .modules
            .entry((krate, at.clone()))
            .or_default()
            .imports
            .insert(name.clone(), target.clone());
    }
    crates.files.push(SourceFile {
        rel: rel.clone(),
        krate,
        module: Some(module.clone()),
        paths: collector.paths,
        literals: collector.literals,
    });

    // Where the file's child modules live: beside it for lib.rs, main.rs and mod.rs, in a folder
    // of its name otherwise; inline modules add a folder each; `#[path]` is relative to the
    // file's folder.
    let file_path = Path::new(&rel);
    let folder = file_path.parent().unwrap_or(Path::new(""));
    let mod_rs = matches!(
        file_path.file_name().and_then(|n| n.to_str()),
        Some("lib.rs" | "main.rs" | "mod.rs")
    );
    for decl in collector.mods.iter().filter(|d| !d.inline) {
        let mut base = folder.to_path_buf();
        if !mod_rs {
            base.push(file_path.file_stem().unwrap_or_default());
        }
        for inline in &decl.parent[module.len()..] {
            base.push(inline);
        }
        let candidates = match &decl.path_attr {
            Some(p) => vec![folder.join(p)],
            None => {
                vec![base.join(format!("{}.rs", decl.name)), base.join(&decl.name).join("mod.rs")]
            }
        };
        let Some(child) = candidates.iter().find(|c| root.join(c).is_file()) else {
            continue; // cargo reports a missing module file; nothing here to check
        };
        let mut path = decl.parent.clone();
        path.push(decl.name.clone());
        let child_rel = child.to_string_lossy().replace('\\', "/");
        load_module_file(root, crates, krate, child_rel, path, decl.test)?;
    }
    Ok(())
}

struct ModDecl {
    parent: ModPath,
    name: String,
    inline: bool,
    test: bool,
    path_attr: Option<String>,
}

struct Collector {
    module: ModPath,
    test_depth: usize,
    paths: Vec<PathSite>,
    literals: Vec<LiteralSite>,
    mods: Vec<ModDecl>,
    /// (module, name, path as written) for each name a `use` brings in (globs excluded).
    imports: Vec<(ModPath, String, Vec<String>)>,
}

impl Collector {
    fn in_test(&self) -> bool {
        self.test_depth > 0
    }

    fn push_path(&mut self, segments: Vec<String>, line: usize, in_use: bool) {
        if !segments.is_empty() {
            let (module, test) = (self.module.clone(), self.in_test());
            self.paths.push(PathSite { segments, module, line, test, in_use });
        }
    }

    fn push_literal(&mut self, value: String, line: usize) {
        self.literals.push(LiteralSite { value, line, test: self.in_test() });
    }

    /// Every leaf of a `use` tree as a full path; `self` in a group names the group's module,
    /// a glob names the module it reads from.
    fn use_tree(&mut self, prefix: &mut Vec<String>, tree: &UseTree, line: usize) {
        match tree {
            UseTree::Path(p) => {
                let line = line.max(p.ident.span().start().line);
                prefix.push(p.ident.to_string());
                self.use_tree(prefix, &p.tree, line);
                prefix.pop();
            }
            UseTree::Name(n) => {
                let name = n.ident.to_string();
                self.use_leaf(prefix, &name, &name, n.ident.span().start().line);
            }
            UseTree::Rename(r) => {
                self.use_leaf(
                    prefix,
                    &r.ident.to_string(),
                    &r.rename.to_string(),
                    r.ident.span().start().line,
                );
            }
            UseTree::Glob(g) => {
                self.push_path(prefix.clone(), g.star_token.span.start().line, true);
            }
            UseTree::Group(g) => {
                for tree in &g.items {
                    self.use_tree(prefix, tree, line);
                }
            }
        }
    }

    fn use_leaf(&mut self, prefix: &[String], ident: &str, name: &str, line: usize) {
        let mut full = prefix.to_vec();
        if ident != "self" {
            full.push(ident.to_owned());
        }
        let name = if name == "self" {
            prefix.last().cloned().unwrap_or_default()
        } else {
            name.to_owned()
        };
        if name != "_" && !self.in_test() {
            self.imports.push((self.module.clone(), name, full.clone()));
        }
        self.push_path(full, line, true);
    }

    /// String literals and `a::b` paths inside tokens that syn leaves unparsed (macro bodies,
    /// attribute arguments such as `derive(sqlx::FromRow)`), doc attributes excepted.
    fn scan_tokens(&mut self, tokens: &TokenStream) {
        let trees: Vec<TokenTree> = tokens.clone().into_iter().collect();
        let mut i = 0;
        while i < trees.len() {
            match &trees[i] {
                TokenTree::Literal(literal) => {
                    let line = literal.span().start().line;
                    if let syn::Lit::Str(s) = syn::Lit::new(literal.clone()) {
                        self.push_literal(s.value(), line);
                    }
                }
                TokenTree::Group(group) => {
                    let doc = group.delimiter() == Delimiter::Bracket
                        && matches!(group.stream().into_iter().next(), Some(TokenTree::Ident(i)) if i == "doc");
                    if !doc {
                        self.scan_tokens(&group.stream());
                    }
                }
                TokenTree::Ident(first) => {
                    let after_colons =
                        i > 0 && matches!(&trees[i - 1], TokenTree::Punct(p) if p.as_char() == ':');
                    let mut segments = vec![first.to_string()];
                    while let (
                        Some(TokenTree::Punct(a)),
                        Some(TokenTree::Punct(b)),
                        Some(TokenTree::Ident(next)),
                    ) = (trees.get(i + 1), trees.get(i + 2), trees.get(i + 3))
                    {
                        if a.as_char() != ':' || b.as_char() != ':' {
                            break;
                        }
                        segments.push(next.to_string());
                        i += 3;
                    }
                    if segments.len() > 1 && !after_colons {
                        self.push_path(segments, first.span().start().line, false);
                    }
                }
                TokenTree::Punct(_) => {}
            }
            i += 1;
        }
    }
}

/// `#[cfg(test)]`, `#[cfg(all(test, …))]` or `#[test]`.
fn is_test(attrs: &[Attribute]) -> bool {
    attrs.iter().any(|attr| {
        if attr.path().is_ident("test") {
            return true;
        }
        if !attr.path().is_ident("cfg") {
            return false;
        }
        match attr.parse_args::<syn::Meta>() {
            Ok(syn::Meta::Path(p)) => p.is_ident("test"),
            Ok(syn::Meta::List(list)) if list.path.is_ident("all") => list
                .tokens
                .clone()
                .into_iter()
                .any(|t| matches!(t, TokenTree::Ident(i) if i == "test")),
            _ => false,
        }
    })
}

fn item_attrs(item: &Item) -> &[Attribute] {
    match item {
        Item::Const(i) => &i.attrs,
        Item::Enum(i) => &i.attrs,
        Item::ExternCrate(i) => &i.attrs,
        Item::Fn(i) => &i.attrs,
        Item::ForeignMod(i) => &i.attrs,
        Item::Impl(i) => &i.attrs,
        Item::Macro(i) => &i.attrs,
        Item::Mod(i) => &i.attrs,
        Item::Static(i) => &i.attrs,
        Item::Struct(i) => &i.attrs,
        Item::Trait(i) => &i.attrs,
        Item::TraitAlias(i) => &i.attrs,
        Item::Type(i) => &i.attrs,
        Item::Union(i) => &i.attrs,
        Item::Use(i) => &i.attrs,
        _ => &[],
    }
}

impl<'ast> Visit<'ast> for Collector {
    fn visit_item(&mut self, item: &'ast Item) {
        let test = is_test(item_attrs(item));
        self.test_depth += usize::from(test);
        visit::visit_item(self, item);
        self.test_depth -= usize::from(test);
    }

    fn visit_impl_item_fn(&mut self, f: &'ast syn::ImplItemFn) {
        let test = is_test(&f.attrs);
        self.test_depth += usize::from(test);
        visit::visit_impl_item_fn(self, f);
        self.test_depth -= usize::from(test);
    }

    fn visit_item_mod(&mut self, m: &'ast syn::ItemMod) {
        let path_attr =
            m.attrs.iter().find(|a| a.path().is_ident("path")).and_then(|a| match &a.meta {
                syn::Meta::NameValue(nv) => match &nv.value {
                    Expr::Lit(syn::ExprLit { lit: syn::Lit::Str(s), .. }) => Some(s.value()),
                    _ => None,
                },
                _ => None,
            });
        self.mods.push(ModDecl {
            parent: self.module.clone(),
            name: m.ident.to_string(),
            inline: m.content.is_some(),
            test: self.in_test(),
            path_attr,
        });
        if let Some((_, items)) = &m.content {
            self.module.push(m.ident.to_string());
            for attr in &m.attrs {
                self.visit_attribute(attr);
            }
            for item in items {
                self.visit_item(item);
            }
            self.module.pop();
        }
    }

    fn visit_item_use(&mut self, u: &'ast syn::ItemUse) {
        let line = u.use_token.span.start().line;
        self.use_tree(&mut Vec::new(), &u.tree, line);
    }

    fn visit_path(&mut self, path: &'ast syn::Path) {
        let segments: Vec<String> = path.segments.iter().map(|s| s.ident.to_string()).collect();
        let line = path.segments.first().map(|s| s.ident.span().start().line).unwrap_or(0);
        self.push_path(segments, line, false);
        visit::visit_path(self, path);
    }

    /// `pub(in crate::x)` restricts visibility; it imports nothing.
    fn visit_vis_restricted(&mut self, _: &'ast syn::VisRestricted) {}

    fn visit_attribute(&mut self, attr: &'ast Attribute) {
        if attr.path().is_ident("doc") {
            return;
        }
        if let syn::Meta::List(list) = &attr.meta {
            self.scan_tokens(&list.tokens);
        }
        visit::visit_attribute(self, attr);
    }

    /// Macro bodies that are comma-separated expressions (`format!`, `bail!`, `matches!`,
    /// `assert_eq!`, `vec!`) are visited as code; any other body is scanned for literals.
    fn visit_macro(&mut self, mac: &'ast syn::Macro) {
        self.visit_path(&mac.path);
        let parser = Punctuated::<Expr, Token![,]>::parse_terminated;
        match syn::parse::Parser::parse2(parser, mac.tokens.clone()) {
            Ok(exprs) => {
                for expr in &exprs {
                    self.visit_expr(expr);
                }
            }
            Err(_) => self.scan_tokens(&mac.tokens),
        }
    }

    fn visit_lit_str(&mut self, lit: &'ast syn::LitStr) {
        self.push_literal(lit.value(), lit.span().start().line);
    }
}

/// The words a `#[serde(rename_all = …)]` enum's variants serialize to.
pub fn enum_words(
    root: &Path,
    folder: &str,
    name: &str,
) -> Result<Option<(String, Vec<String>)>, String> {
    for rel in crate::walk(root, folder, &|p| p.ends_with(".rs"))? {
        let text = std::fs::read_to_string(root.join(&rel)).map_err(|e| format!("{rel}: {e}"))?;
        let file =
            syn::parse_file(&text).map_err(|e| format!("{rel}: does not parse as Rust: {e}"))?;
        for item in &file.items {
            let Item::Enum(e) = item else { continue };
            if e.ident != name {
                continue;
            }
            let rename_all = serde_value(&e.attrs, "rename_all");
            let words = e
                .variants
                .iter()
                .map(|v| {
                    serde_value(&v.attrs, "rename").unwrap_or_else(|| {
                        let ident = v.ident.to_string();
                        match rename_all.as_deref() {
                            Some("lowercase") => ident.to_lowercase(),
                            Some("UPPERCASE") => ident.to_uppercase(),
                            Some("snake_case") => snake_case(&ident),
                            Some("SCREAMING_SNAKE_CASE") => snake_case(&ident).to_uppercase(),
                            Some("kebab-case") => snake_case(&ident).replace('_', "-"),
                            _ => ident,
                        }
                    })
                })
                .collect();
            return Ok(Some((rel, words)));
        }
    }
    Ok(None)
}

/// `key = "value"` inside a `#[serde(…)]` attribute.
fn serde_value(attrs: &[Attribute], key: &str) -> Option<String> {
    let mut found = None;
    for attr in attrs.iter().filter(|a| a.path().is_ident("serde")) {
        let _ = attr.parse_nested_meta(|meta| {
            if meta.path.is_ident(key) {
                found = Some(meta.value()?.parse::<syn::LitStr>()?.value());
            } else if meta.input.peek(Token![=]) {
                meta.value()?.parse::<Expr>()?;
            }
            Ok(())
        });
    }
    found
}

fn snake_case(ident: &str) -> String {
    let mut out = String::new();
    for (i, c) in ident.chars().enumerate() {
        if c.is_uppercase() && i > 0 {
            out.push('_');
        }
        out.extend(c.to_lowercase());
    }
    out
}
