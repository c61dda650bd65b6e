//! A build farm's folder: every shared model (the negative ones aside)
//! through `process --jobs 2`, through `submit` to a server on loopback,
//! and through one `process` per model in a loop, as a shell script would;
//! then once more from the cache. Prints models per minute for each.
//!
//! `cargo bench --bench farm`

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[path = "../tests/common/mod.rs"]
mod common;
use common::server;

fn models_below(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).expect("readable folder") {
            let p = e.expect("entry").path();
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if p.is_dir() && name != "negative" {
                dirs.push(p);
            } else if name.ends_with(".glb") || name.ends_with(".gltf") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

fn seamstress(args: &[&str], extra: &[&Path]) -> Duration {
    let t = Instant::now();
    let status = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(args)
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("seamstress runs");
    assert!(status.success(), "seamstress {args:?} failed: {status}");
    t.elapsed()
}

fn report(what: &str, models: usize, took: Duration) {
    println!(
        "{what:<36} {models} models in {:>6.2} s = {:>6.1} models/min",
        took.as_secs_f64(),
        models as f64 / took.as_secs_f64() * 60.0
    );
}

fn main() {
    let shared = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets");
    let models = models_below(&shared);
    let dir = std::env::temp_dir().join(format!("seamstress-bench-farm-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch folder");
    // The folders, not the files: folders mirror into distinct outputs.
    let mut folders: Vec<PathBuf> = std::fs::read_dir(&shared)
        .expect("the shared assets")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && !p.ends_with("negative"))
        .collect();
    folders.sort();
    let inputs: Vec<&Path> = folders.iter().map(PathBuf::as_path).collect();
    let n = models.len();
    println!(
        "{n} shared models, {} cores",
        std::thread::available_parallelism().map_or(1, |c| c.get())
    );

    let out = dir.join("process");
    let o = out.to_str().expect("UTF-8 path");
    report(
        "process --jobs 2",
        n,
        seamstress(&["process", "--out", o, "--jobs", "2"], &inputs),
    );
    report(
        "process --jobs 2, again (cache)",
        n,
        seamstress(&["process", "--out", o, "--jobs", "2"], &inputs),
    );

    let looped = Instant::now();
    for (i, m) in models.iter().enumerate() {
        let out = dir.join(format!("loop/{i}"));
        seamstress(&["process", "--out", out.to_str().expect("UTF-8")], &[m]);
    }
    report("one process per model, in a loop", n, looped.elapsed());

    let srv = server::Server::start(&dir.join("data"), &[]);
    let out = dir.join("submit");
    report(
        "submit --jobs 4 (server: 2 workers)",
        n,
        seamstress(
            &[
                "submit",
                "--out",
                out.to_str().expect("UTF-8"),
                "--jobs",
                "4",
                "--server",
                &srv.base,
            ],
            &inputs,
        ),
    );
    drop(srv);
    let _ = std::fs::remove_dir_all(&dir);
}
