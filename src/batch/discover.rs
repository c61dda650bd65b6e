//! From the command line's inputs to the models of a batch and their
//! output folders.
//!
//! A single model file writes into `--out` itself, as it always has. Any
//! other batch mirrors its inputs under `--out`: a model found in a folder
//! `F` (recursively) goes to `F`'s relative path without the extension
//! (`F/props/crate.glb` → `out/props/crate/`); a glob pattern's matches are
//! relative to the pattern's literal prefix; a file named on its own goes
//! to its stem (`out/crate/`).

use std::path::{Component, Path, PathBuf};

/// One model of a batch.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BatchModel {
    pub path: PathBuf,
    /// Where its outputs go, relative to `--out` (empty: `--out` itself).
    pub out: PathBuf,
}

#[derive(Debug, thiserror::Error)]
pub enum DiscoverError {
    #[error("{path}: no such file or folder")]
    NotFound { path: String },
    #[error("{path}: {message}")]
    Unreadable { path: String, message: String },
    #[error("{pattern}: not a valid glob pattern: {message}")]
    BadGlob { pattern: String, message: String },
    #[error("{path}: not a .glb or .gltf file")]
    NotAModel { path: String },
    #[error("{a} and {b} would both write into {out}")]
    Collision { a: String, b: String, out: String },
    #[error("no .glb or .gltf models in {inputs}")]
    Empty { inputs: String },
}

fn is_model(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("glb") || e.eq_ignore_ascii_case("gltf"))
}

fn has_glob_chars(s: &str) -> bool {
    s.contains(['*', '?', '['])
}

/// The models of `inputs` (files, folders, glob patterns), in a fixed
/// order, each with its output folder.
pub fn discover(inputs: &[PathBuf]) -> Result<Vec<BatchModel>, DiscoverError> {
    if let [one] = inputs {
        if one.is_file() {
            return Ok(vec![BatchModel {
                path: one.clone(),
                out: PathBuf::new(),
            }]);
        }
    }
    let mut models = Vec::new();
    for input in inputs {
        let shown = input.display().to_string();
        if input.is_dir() {
            let mut found = Vec::new();
            walk(input, &mut found)?;
            found.sort();
            models.extend(found.into_iter().map(|p| mirrored(p, input)));
        } else if input.is_file() {
            if !is_model(input) {
                return Err(DiscoverError::NotAModel { path: shown });
            }
            let stem = input.file_stem().map(PathBuf::from).unwrap_or_default();
            models.push(BatchModel {
                path: input.clone(),
                out: stem,
            });
        } else if has_glob_chars(&shown) {
            models.extend(expand(&shown)?);
        } else {
            return Err(DiscoverError::NotFound { path: shown });
        }
    }
    if models.is_empty() {
        let inputs = inputs
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ");
        return Err(DiscoverError::Empty { inputs });
    }
    let mut seen: Vec<(&PathBuf, &PathBuf)> = models.iter().map(|m| (&m.out, &m.path)).collect();
    seen.sort();
    for w in seen.windows(2) {
        if w[0].0 == w[1].0 {
            return Err(DiscoverError::Collision {
                a: w[0].1.display().to_string(),
                b: w[1].1.display().to_string(),
                out: w[0].0.display().to_string(),
            });
        }
    }
    Ok(models)
}

/// `path` found under `base`: its output folder is its relative path
/// without the extension.
fn mirrored(path: PathBuf, base: &Path) -> BatchModel {
    let rel = path.strip_prefix(base).unwrap_or(&path).with_extension("");
    BatchModel { path, out: rel }
}

fn walk(dir: &Path, found: &mut Vec<PathBuf>) -> Result<(), DiscoverError> {
    let unreadable = |e: std::io::Error| DiscoverError::Unreadable {
        path: dir.display().to_string(),
        message: e.to_string(),
    };
    for entry in std::fs::read_dir(dir).map_err(unreadable)? {
        let p = entry.map_err(unreadable)?.path();
        // Output folders of earlier runs and hidden folders are no inputs.
        if p.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with('.'))
        {
            continue;
        }
        if p.is_dir() {
            walk(&p, found)?;
        } else if is_model(&p) {
            found.push(p);
        }
    }
    Ok(())
}

/// The models a glob pattern matches, relative to its literal prefix.
fn expand(pattern: &str) -> Result<Vec<BatchModel>, DiscoverError> {
    let bad = |message: String| DiscoverError::BadGlob {
        pattern: pattern.to_string(),
        message,
    };
    let base: PathBuf = Path::new(pattern)
        .components()
        .take_while(|c| !matches!(c, Component::Normal(s) if has_glob_chars(&s.to_string_lossy())))
        .collect();
    let mut found = Vec::new();
    for entry in glob::glob(pattern).map_err(|e| bad(e.to_string()))? {
        let p = entry.map_err(|e| bad(e.to_string()))?;
        if p.is_file() && is_model(&p) {
            found.push(p);
        }
    }
    found.sort();
    Ok(found.into_iter().map(|p| mirrored(p, &base)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree() -> PathBuf {
        let dir = std::env::temp_dir().join(format!("seamstress-discover-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        for f in [
            "a/x.glb",
            "a/b/y.gltf",
            "a/b/y.bin",
            "a/.hidden/z.glb",
            "c/w.GLB",
        ] {
            let p = dir.join(f);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, b"").unwrap();
        }
        dir
    }

    #[test]
    fn folders_files_and_globs_mirror_into_the_output() {
        let dir = tree();
        let got = discover(&[dir.join("a"), dir.join("c/w.GLB")]).unwrap();
        let outs: Vec<_> = got.iter().map(|m| m.out.clone()).collect();
        assert_eq!(
            outs,
            [PathBuf::from("b/y"), PathBuf::from("x"), PathBuf::from("w")]
        );
        let pattern = format!("{}/a/**/*.gltf", dir.display());
        let got = discover(&[PathBuf::from(pattern)]).unwrap();
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].out, PathBuf::from("b/y"));
        // One file alone writes into --out itself.
        let one = discover(&[dir.join("a/x.glb")]).unwrap();
        assert_eq!(one[0].out, PathBuf::new());
        // Two inputs into one folder, a missing input, no models: errors.
        assert!(matches!(
            discover(&[dir.join("a/x.glb"), dir.join("a/x.glb")]),
            Err(DiscoverError::Collision { .. })
        ));
        assert!(matches!(
            discover(&[dir.join("nope")]),
            Err(DiscoverError::NotFound { .. })
        ));
        assert!(matches!(
            discover(&[dir.join("a/b/y.bin"), dir.join("c")]),
            Err(DiscoverError::NotAModel { .. })
        ));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
