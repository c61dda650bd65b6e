//! `#[needs(tool, ...)]` for the tests that need a tool from outside the
//! project (Python modules, node, Chromium, PostgreSQL, ...): where one is
//! missing, the test is marked `#[ignore = "needs ..."]`, so that `cargo
//! test` counts it as ignored and names what to install. The build script
//! looked for the tools; under `SEAMSTRESS_REQUIRE_TOOLS` it takes them all
//! as found, so that nothing is ignored and a missing tool fails its test.
//!
//! The tests keep their own check when they run (`tests/common`), which
//! skips with a notice, or fails under `SEAMSTRESS_REQUIRE_TOOLS`, should a
//! tool found at build time be gone.

use proc_macro::{Delimiter, TokenStream, TokenTree};

mod probe;

include!(concat!(env!("OUT_DIR"), "/found.rs"));

/// Marks the test ignored, with what to install, unless every tool named
/// is here. Put it above `#[test]` (or `#[tokio::test]`), which reads the
/// mark. The tools are those of `probe::TOOLS`, by key: `python`,
/// `texture2ddecoder`, `schemathesis`, `gltf_validator`, `ktx_parse`, `chromium`,
/// `postgres`, `seaweedfs`, `tmpfs`.
#[proc_macro_attribute]
pub fn needs(args: TokenStream, item: TokenStream) -> TokenStream {
    match missing(args) {
        Err(e) => e,
        Ok(missing) if missing.is_empty() => item,
        Ok(missing) => {
            let mut out: TokenStream = format!("#[ignore = {:?}]", reason(&missing))
                .parse()
                .unwrap();
            out.extend(item);
            out
        }
    }
}

/// `module! { #[needs(tool, ...)] #[path = "FILE.rs"] mod NAME; }` in a
/// file of `tests/`: the module as written where every tool named is here;
/// elsewhere, in its place, one ignored test per test of `tests/FILE.rs`,
/// under the same names. For a test file that is another's suite again
/// on servers the tools start, all of whose tests need them.
#[proc_macro]
pub fn module(input: TokenStream) -> TokenStream {
    let mut tokens = input.into_iter();
    let (Some(TokenTree::Punct(hash)), Some(TokenTree::Group(attr))) =
        (tokens.next(), tokens.next())
    else {
        return error("module! starts with #[needs(...)]");
    };
    let mut attr = attr.stream().into_iter();
    let (true, Some(TokenTree::Ident(name)), Some(TokenTree::Group(args)), None) =
        (hash.as_char() == '#', attr.next(), attr.next(), attr.next())
    else {
        return error("module! starts with #[needs(...)]");
    };
    if name.to_string() != "needs" || args.delimiter() != Delimiter::Parenthesis {
        return error("module! starts with #[needs(...)]");
    }
    let missing = match missing(args.stream()) {
        Err(e) => return e,
        Ok(m) => m,
    };
    let rest: TokenStream = tokens.collect();
    if missing.is_empty() {
        return rest;
    }
    let (Some(file), Some(module)) = path_and_module(&rest) else {
        return error("module! takes #[path = \"FILE.rs\"] mod NAME;");
    };
    let dir = std::env::var("CARGO_MANIFEST_DIR").unwrap_or_default();
    let text = match std::fs::read_to_string(format!("{dir}/tests/{file}")) {
        Ok(t) => t,
        Err(e) => return error(&format!("tests/{file}: {e}")),
    };
    let names = test_names(&text);
    if names.is_empty() {
        return error(&format!("tests/{file} has no test"));
    }
    let reason = reason(&missing);
    // The include makes the file a dependency, so that the names follow
    // its changes.
    let mut code = format!("mod {module} {{ const _: &str = include_str!({file:?});\n");
    for n in names {
        code += &format!("#[test] #[ignore = {reason:?}] fn {n}() {{}}\n");
    }
    code += "}";
    code.parse().unwrap()
}

/// What the build script found, by key, for `tests/tools.rs`:
/// `[(&str, bool); N]`.
#[proc_macro]
pub fn found_at_build(_: TokenStream) -> TokenStream {
    let pairs: Vec<String> = probe::TOOLS
        .iter()
        .zip(FOUND)
        .map(|(t, f)| format!("({:?}, {f})", t.key))
        .collect();
    format!("[{}]", pairs.join(", ")).parse().unwrap()
}

/// The tools named in `args` that the build script did not find, or a
/// compile error naming a key that is not a tool.
fn missing(args: TokenStream) -> Result<Vec<&'static probe::Tool>, TokenStream> {
    let mut missing = Vec::new();
    let mut named = 0;
    for t in args {
        match t {
            TokenTree::Punct(p) if p.as_char() == ',' => {}
            TokenTree::Ident(i) => {
                let key = i.to_string();
                let Some(n) = probe::TOOLS.iter().position(|t| t.key == key) else {
                    let keys: Vec<_> = probe::TOOLS.iter().map(|t| t.key).collect();
                    return Err(error(&format!(
                        "no tool `{key}`; the tools are {}",
                        keys.join(", ")
                    )));
                };
                named += 1;
                if !FOUND[n] {
                    missing.push(&probe::TOOLS[n]);
                }
            }
            other => return Err(error(&format!("expected a tool's name, not `{other}`"))),
        }
    }
    if named == 0 {
        return Err(error("#[needs(...)] names at least one tool"));
    }
    Ok(missing)
}

fn reason(missing: &[&probe::Tool]) -> String {
    let each: Vec<String> = missing
        .iter()
        .map(|t| format!("{}: {}", t.what, t.install))
        .collect();
    format!("needs {}", each.join("; and "))
}

/// The `#[path = "..."]` and the name of `mod NAME;` in `tokens`.
fn path_and_module(tokens: &TokenStream) -> (Option<String>, Option<String>) {
    let (mut path, mut module) = (None, None);
    let mut after_mod = false;
    for t in tokens.clone() {
        match t {
            TokenTree::Group(g) if g.delimiter() == Delimiter::Bracket => {
                let inner: Vec<TokenTree> = g.stream().into_iter().collect();
                if let [TokenTree::Ident(i), TokenTree::Punct(eq), TokenTree::Literal(l)] =
                    inner.as_slice()
                {
                    if i.to_string() == "path" && eq.as_char() == '=' {
                        path = l
                            .to_string()
                            .strip_prefix('"')
                            .and_then(|s| s.strip_suffix('"'))
                            .map(str::to_string);
                    }
                }
            }
            TokenTree::Ident(i) if after_mod => {
                module = Some(i.to_string());
                after_mod = false;
            }
            TokenTree::Ident(i) if i.to_string() == "mod" => after_mod = true,
            _ => {}
        }
    }
    (path, module)
}

/// The names of the functions marked `#[test]` or `#[tokio::test(...)]` in
/// a test file's source.
fn test_names(text: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut marked = false;
    for line in text.lines().map(str::trim) {
        if line.starts_with("#[test]") || line.starts_with("#[tokio::test") {
            marked = true;
        } else if marked && !line.starts_with("#[") && !line.starts_with("//") {
            let name = line
                .split_once("fn ")
                .map(|(_, rest)| rest)
                .and_then(|rest| {
                    rest.split(|c: char| !c.is_alphanumeric() && c != '_')
                        .next()
                })
                .filter(|n| !n.is_empty());
            names.extend(name.map(str::to_string));
            marked = false;
        }
    }
    names
}

fn error(message: &str) -> TokenStream {
    format!("compile_error!({message:?});").parse().unwrap()
}
