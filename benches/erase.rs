//! Per-stage timings and peak memory of the seam engine on the 2048² models.
//!
//! `cargo bench --bench erase` prints one row per (model, mode, seams): the
//! seams judged (those painted apart left, the default) or all closed
//! (`--erase-all`). Each row runs
//! in a child process of its own, so "peak MB" (the kernel's high-water mark
//! of resident memory, VmHWM) belongs to that run alone. Each row is the
//! median of [`RUNS`] runs by erase time.
//!
//! A second table runs the default job through the binary (`seamstress
//! process`) on every shared model, a few times each, and prints the
//! budget's estimate of its peak memory beside the measured peaks, with the
//! quantities the estimate is made of: the budget must be honest, within 20%.

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use seamstress::model::{self, LoadOptions};
use seamstress::pipeline::{self, Format, Method, ProcessOptions};
use seamstress::seam::erase::Mode;

mod common;

const MODELS: [&str; 3] = ["blub/blub.glb", "Fox/Fox.gltf", "CesiumMan/CesiumMan.gltf"];
/// Runs per row; the row shows the median one (this machine's speed varies by
/// 10–20% from one run to the next).
const RUNS: usize = 5;

fn asset(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel)
}

/// Runs one model in this process and prints one tab-separated line.
fn child(rel: &str, mode: Mode, erase_all: bool) {
    let t = Instant::now();
    let m = match model::load(&asset(rel), &LoadOptions::default()) {
        Ok(m) => m,
        Err(e) => {
            println!("ERR\t{e}");
            return;
        }
    };
    let load_ms = t.elapsed().as_millis() as u64;
    let opts = ProcessOptions {
        mode,
        method: Method::Erase,
        format: Format::Png,
        erase_all,
        ..ProcessOptions::default()
    };
    let t = Instant::now();
    let out = match pipeline::run(&m, rel, load_ms, &opts) {
        Ok(o) => o,
        Err(e) => {
            println!("ERR\t{e}");
            return;
        }
    };
    let total_ms = t.elapsed().as_millis();
    let r = &out.report.textures[0];
    println!(
        "OK\t{}\t{}\t{}\t{}\t{}\t{:.1}\t{}\t{:.3}\t{:.3}\t{:.2}\t{:.3}\t{:.3}\t{:.1}",
        r.timings_ms.load,
        r.timings_ms.seams,
        r.timings_ms.erase,
        total_ms,
        r.solver.unknowns,
        seamstress::heap::peak_resident_mb() as f64,
        r.solver.band_radius.map_or("-".into(), |b| b.to_string()),
        r.input.seam_rms.unwrap_or(f64::NAN),
        r.erased.seam_rms.unwrap_or(f64::NAN),
        r.erased.psnr.unwrap_or(f64::NAN),
        r.seams.closed.length_share,
        r.erased.seam_rms_closed.unwrap_or(f64::NAN),
        r.erased.worst_chart_psnr.unwrap_or(f64::NAN),
    );
}

/// Every shared model, for the budget table.
const JOB_MODELS: [&str; 9] = [
    "blub/blub.glb",
    "Fox/Fox.gltf",
    "CesiumMan/CesiumMan.gltf",
    "Duck/Duck.gltf",
    "BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb",
    "cube/cube_gradient_1024.glb",
    "cube/cube_gradient_128.glb",
    "WaterBottle/WaterBottle.gltf",
    "TextureTransformTest/TextureTransformTest.gltf",
];

/// Runs of `seamstress process` per model in the budget table: the peak of
/// one model still varies by a few percent from run to run.
const BUDGET_RUNS: usize = 3;

/// The budget's estimate for the default job on one model, with the
/// quantities it is linear in (`budget::Terms`).
fn estimate(rel: &str) -> Result<(seamstress::budget::Need, seamstress::budget::Terms), String> {
    let plan = model::plan(&asset(rel), &LoadOptions::default()).map_err(|e| e.to_string())?;
    Ok(seamstress::budget::need_and_terms(
        &plan,
        &ProcessOptions::default(),
    ))
}

/// Runs `seamstress process` on one model, as a user would, and returns its
/// peak resident memory in MiB (the kernel's `ru_maxrss` of that child).
fn binary_peak_mb(rel: &str) -> Result<f64, String> {
    let out = std::env::temp_dir().join(format!("seamstress-budget-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
    cmd.arg("process").arg(asset(rel)).arg("--out").arg(&out);
    let run = common::measure(cmd);
    let _ = std::fs::remove_dir_all(&out);
    Ok(run?.peak_mb)
}

fn budget_table() {
    println!("\nThe budget: estimated against the peak memory of `seamstress process`");
    println!(
        "{:<28} {:>8} {:>15} {:>11} {:>10} {:>10} {:>8}",
        "model", "est. MB", "peak MB", "est/peak", "held ch·tx", "work tx", "points"
    );
    let mut outside = 0;
    for rel in JOB_MODELS {
        let name = rel.rsplit('/').next().unwrap_or(rel);
        let measured = estimate(rel).and_then(|e| {
            let peaks: Vec<f64> = (0..BUDGET_RUNS)
                .map(|_| binary_peak_mb(rel))
                .collect::<Result<_, _>>()?;
            Ok((e, peaks))
        });
        let ((need, terms), peaks) = match measured {
            Ok(m) => m,
            Err(e) => {
                println!("{name:<28} failed: {e}");
                outside += BUDGET_RUNS;
                continue;
            }
        };
        let est = need.memory_bytes as f64 / 1048576.0;
        let lo = peaks.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = peaks.iter().copied().fold(0.0, f64::max);
        let within = |p: f64| (est / p) >= 1.0 / 1.2 && (est / p) <= 1.25;
        outside += peaks.iter().filter(|&&p| !within(p)).count();
        println!(
            "{name:<28} {est:>8.1} {:>15} {:>11} {:>10} {:>10} {:>8}",
            format!("{lo:.1}–{hi:.1}"),
            format!("{:.2}–{:.2}", est / hi, est / lo),
            terms.held_channel_texels,
            terms.work_texels,
            terms.work_points,
        );
    }
    println!("peak: the lowest and highest of {BUDGET_RUNS} runs; est/peak must lie in 0.83–1.25");
    println!("(|peak − est| ≤ 20% of est): {outside} runs outside.");
}

// As the binary does.
#[global_allocator]
static ALLOC: seamstress::heap::HugePageAlloc = seamstress::heap::HugePageAlloc;

fn main() {
    // As the binary does.
    seamstress::heap::retain_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--child") {
        let mode = if args[i + 2] == "global" {
            Mode::Global
        } else {
            Mode::Local
        };
        child(&args[i + 1], mode, args[i + 3] == "all");
        return;
    }
    let exe = std::env::current_exe().expect("own path");
    // `cargo bench --bench erase -- budget`: the budget table alone.
    if args.iter().any(|a| a == "budget") {
        budget_table();
        return;
    }
    println!(
        "{:<16} {:<6} {:<6} {:>7} {:>8} {:>9} {:>9} {:>10} {:>7} {:>8} {:>9} {:>10} {:>8} {:>7} {:>10} {:>9}",
        "model",
        "mode",
        "seams",
        "load ms",
        "seams ms",
        "erase ms",
        "total ms",
        "unknowns",
        "band",
        "peak MB",
        "input rms",
        "erased rms",
        "psnr dB",
        "closed",
        "closed rms",
        "worst dB"
    );
    for rel in MODELS {
        for (mode, seams) in [
            ("local", "judged"),
            ("local", "all"),
            ("global", "judged"),
            ("global", "all"),
        ] {
            let name = rel.rsplit('/').next().unwrap_or(rel);
            let mut runs = Vec::new();
            for _ in 0..RUNS {
                let out = Command::new(&exe)
                    .args(["--child", rel, mode, seams])
                    .output()
                    .expect("child runs");
                let text = String::from_utf8_lossy(&out.stdout);
                let line = text
                    .lines()
                    .find(|l| l.starts_with("OK") || l.starts_with("ERR"))
                    .map(|l| l.split('\t').map(str::to_string).collect::<Vec<_>>());
                match line {
                    Some(f) if f[0] == "OK" && f.len() == 14 => runs.push(f),
                    other => {
                        println!("{name:<16} {mode:<6} {seams:<6} failed: {other:?}");
                        break;
                    }
                }
            }
            if runs.len() < RUNS {
                continue;
            }
            // The run with the median erase time; this machine's speed varies.
            runs.sort_by_key(|f| f[3].parse::<u64>().unwrap_or(u64::MAX));
            let f = &runs[RUNS / 2];
            println!(
                "{:<16} {:<6} {:<6} {:>7} {:>8} {:>9} {:>9} {:>10} {:>7} {:>8} {:>9} {:>10} {:>8} {:>7} {:>10} {:>9}",
                name, mode, seams, f[1], f[2], f[3], f[4], f[5], f[7], f[6], f[8], f[9], f[10], f[11], f[12], f[13]
            );
        }
    }
    println!("\nerase: seam erasure incl. the solve; the run with the median erase of {RUNS};");
    println!("peak MB: VmHWM of that run's child process. seams: judged (painted apart left)");
    println!("or all closed; closed: their share of the seam length; closed rms: erased");
    println!("seam_rms over them; worst dB: the lowest PSNR of any UV chart.");
    println!("Goals (local mode, 2048²): erase < 1000 ms, peak < 1024 MB.");
    budget_table();
}
