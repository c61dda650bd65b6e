//! The README's worked example is what the code does: its command runs
//! here, and every line it shows, every figure of its report excerpt and
//! every figure its prose quotes must be what that run printed and wrote.
//! A change that moves a figure fails here until the README says so.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The README's `## Worked example` section.
fn worked_example() -> String {
    let readme = std::fs::read_to_string(repo().join("README.md")).unwrap();
    let start = readme
        .find("## Worked example\n")
        .expect("the README has a worked example");
    let rest = &readme[start + 3..];
    let end = rest.find("\n## ").map_or(rest.len(), |e| e + 1);
    rest[..end].to_string()
}

/// The fenced blocks of `text` with their language, and the prose between
/// them.
fn blocks(text: &str) -> (Vec<(String, String)>, String) {
    let (mut fenced, mut prose) = (Vec::new(), String::new());
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        if let Some(lang) = line.strip_prefix("```") {
            let body: Vec<&str> = lines.by_ref().take_while(|l| *l != "```").collect();
            fenced.push((lang.to_string(), body.join("\n")));
        } else {
            prose.push_str(line);
            prose.push('\n');
        }
    }
    (fenced, prose)
}

/// Every leaf of `excerpt` equals the same leaf of `full`.
fn assert_subset(excerpt: &Value, full: &Value, path: &str) {
    match excerpt {
        Value::Object(map) => {
            for (k, v) in map {
                let there = full
                    .get(k)
                    .unwrap_or_else(|| panic!("README shows {path}.{k}, the report has none"));
                assert_subset(v, there, &format!("{path}.{k}"));
            }
        }
        Value::Array(items) => {
            for (i, v) in items.iter().enumerate() {
                assert_subset(v, &full[i], &format!("{path}[{i}]"));
            }
        }
        leaf => assert_eq!(leaf, full, "README's {path} is not the report's"),
    }
}

/// Every number of a report, as it stands.
fn numbers(v: &Value, out: &mut Vec<f64>) {
    match v {
        Value::Number(n) => out.extend(n.as_f64()),
        Value::Object(map) => map.values().for_each(|v| numbers(v, out)),
        Value::Array(items) => items.iter().for_each(|v| numbers(v, out)),
        _ => {}
    }
}

/// The decimal figures of `prose` (`47.28`, `0.91`), as written.
fn decimals(prose: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut token = String::new();
    for c in prose.chars().chain(std::iter::once(' ')) {
        if c.is_ascii_digit() || (c == '.' && !token.is_empty()) {
            token.push(c);
            continue;
        }
        let t = token.trim_end_matches('.');
        if t.contains('.') {
            out.push(t.to_string());
        }
        token.clear();
    }
    out
}

#[test]
fn the_worked_example_is_what_its_command_prints_and_writes() {
    let section = worked_example();
    let (fenced, prose) = blocks(&section);
    let console = &fenced
        .iter()
        .find(|(lang, _)| lang == "console")
        .expect("a console block")
        .1;
    let mut lines = console.lines();
    let command = lines.next().unwrap();
    let args: Vec<&str> = command
        .strip_prefix("$ cargo run -- ")
        .unwrap_or_else(|| panic!("the example runs `cargo run -- …`: {command}"))
        .split_whitespace()
        .collect();
    let shown: Vec<&str> = lines.collect();

    // Run where the README's relative paths mean what they say: the
    // repository's examples, and an output folder of its own.
    let dir = std::env::temp_dir().join(format!("seamstress-readme-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::os::unix::fs::symlink(repo().join("examples"), dir.join("examples")).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(&args)
        .current_dir(&dir)
        .env_remove("SEAMSTRESS_LOG")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let printed = String::from_utf8(o.stdout).unwrap();
    assert_eq!(
        printed.lines().collect::<Vec<_>>(),
        shown,
        "the README shows other lines than the command prints"
    );

    let out = args
        .windows(2)
        .find(|w| w[0] == "-o" || w[0] == "--out")
        .map(|w| dir.join(w[1]))
        .expect("the command names its output folder");
    let report: Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let texture = &report["textures"][0];
    let excerpt = &fenced
        .iter()
        .find(|(lang, _)| lang == "json")
        .expect("a JSON block")
        .1;
    let excerpt: Value = serde_json::from_str(excerpt).expect("the README's excerpt is JSON");
    assert_subset(&excerpt, texture, "textures[0]");

    // The prose quotes the report's figures, and one difference of them.
    let mut figures = Vec::new();
    numbers(texture, &mut figures);
    let psnr_cost = texture["bc1"]["psnr"].as_f64().unwrap()
        - texture["bc1_seam_aware"]["psnr"].as_f64().unwrap();
    figures.push(psnr_cost);
    let quoted = decimals(&prose);
    assert!(quoted.len() >= 5, "the prose quotes figures: {quoted:?}");
    for q in &quoted {
        let places = q.len() - q.find('.').unwrap() - 1;
        assert!(
            figures.iter().any(|f| format!("{f:.places$}") == *q),
            "the README quotes {q}, which no figure of the report rounds to"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn decimals_are_found_as_written() {
    assert_eq!(
        decimals("from 36.21 to 0.27 levels. At 0.91, 48 levels, 3.5."),
        ["36.21", "0.27", "0.91", "3.5"]
    );
    assert!(Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("README.md")
        .is_file());
}
