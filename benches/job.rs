//! Whole-job wall time and peak memory of `seamstress process`, as a build
//! farm runs it: one process per model, load to last byte written.
//!
//! `cargo bench --bench job` runs each model of [`JOBS`] with its mip chain
//! (the default) and with `--no-mips` [`RUNS`] times (`SEAMSTRESS_BENCH_RUNS`
//! overrides), in rounds that run every row once, and prints per row the
//! median wall time, the CPU time and peak resident memory of that run, its
//! stages from `report.json` (summed over the textures), how much of the wall
//! time the report's stages cover, and, where Debian's `libnvtt-bin` is
//! installed, `nvcompress -bc1` on the same erased images (no erasure, no
//! metrics) as the ratio to beat. A goal that compares two rows takes the
//! median over the rounds of their ratio within each round. Fox's texture
//! scaled to 4096² and 8192² is made by the bench in a temporary folder.
//!
//! Arguments filter the rows: `cargo bench --bench job -- Fox` runs the rows
//! whose name contains "Fox".

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use base64::Engine as _;
use serde_json::Value;

mod common;
use common::{measure, Run};

/// Runs per row; the row shows the median by wall time.
const RUNS: usize = 5;

/// Shared models (relative to `../shared/assets`) and the repository's own
/// (relative to the repository), with the options they run with.
const JOBS: [(&str, &str, &[&str]); 6] = [
    ("Fox", "shared:Fox/Fox.gltf", &[]),
    ("CesiumMan", "shared:CesiumMan/CesiumMan.gltf", &[]),
    ("WaterBottle", "shared:WaterBottle/WaterBottle.gltf", &[]),
    (
        "blub_atlas_black",
        "shared:blub_atlas/blub_atlas_black.glb",
        &[],
    ),
    (
        "blub_atlas_dilated",
        "shared:blub_atlas/blub_atlas_dilated.glb",
        &[],
    ),
    (
        "controller",
        "repo:tests/assets/oculus-touch-v3/oculus-touch-v3-left.glb",
        &[],
    ),
];

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn resolve(spec: &str) -> PathBuf {
    match spec.split_once(':') {
        Some(("shared", rel)) => repo().join("../shared/assets").join(rel),
        Some(("repo", rel)) => repo().join(rel),
        _ => PathBuf::from(spec),
    }
}

/// One run of a job, and its report.
fn one_job(model: &Path, extra: &[&str], out: &Path) -> Result<(Run, Value), String> {
    let _ = std::fs::remove_dir_all(out);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
    cmd.arg("process")
        .arg(model)
        .arg("--out")
        .arg(out)
        .args(extra);
    let run = measure(cmd)?;
    let report: Value = std::fs::read(out.join("report.json"))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .ok_or("no report.json")?;
    Ok((run, report))
}

/// The median of `values`.
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// `nvcompress -bc1` on every erased PNG of `out` (the median of `runs`
/// passes over all of them), in seconds; `None` without nvcompress.
fn nvcompress(out: &Path, mips: bool, runs: usize) -> Option<f64> {
    let pngs: Vec<PathBuf> = std::fs::read_dir(out)
        .ok()?
        .filter_map(|e| Some(e.ok()?.path()))
        .filter(|p| p.to_string_lossy().ends_with(".erased.png"))
        .collect();
    let mut times = Vec::new();
    for _ in 0..runs {
        let mut total = 0.0;
        for png in &pngs {
            let mut cmd = Command::new("nvcompress");
            cmd.args(["-bc1", "-nocuda", "-silent"]);
            if !mips {
                cmd.arg("-nomips");
            }
            cmd.arg(png).arg(png.with_extension("nv.dds"));
            total += measure(cmd).ok()?.wall;
        }
        times.push(total);
    }
    times.sort_by(f64::total_cmp);
    Some(times[runs / 2])
}

/// Stage milliseconds summed over the textures, and the texture total.
fn stages(report: &Value) -> (Vec<(&'static str, u64)>, u64, usize) {
    const KEYS: [&str; 9] = [
        "seams",
        "erase",
        "waited",
        "encode",
        "seam_aware",
        "beside_wait",
        "metrics",
        "pictures",
        "dds",
    ];
    let textures = report["textures"].as_array().cloned().unwrap_or_default();
    let sum = |key: &str| {
        textures
            .iter()
            .map(|t| t["timings_ms"][key].as_u64().unwrap_or(0))
            .sum::<u64>()
    };
    let list = KEYS.iter().map(|k| (*k, sum(k))).collect();
    (list, sum("total"), textures.len())
}

/// WaterBottle with its base colour alone (the emissive texture dropped
/// from its material), in `dir`: the largest texture of the default job,
/// processed alone.
fn water_bottle_base_colour(dir: &Path) -> Result<PathBuf, String> {
    let source = resolve("shared:WaterBottle/WaterBottle.gltf");
    let folder = source.parent().ok_or("no folder")?;
    let mut gltf: Value =
        serde_json::from_slice(&std::fs::read(&source).map_err(|e| e.to_string())?)
            .map_err(|e| e.to_string())?;
    for m in gltf["materials"].as_array_mut().ok_or("no materials")? {
        if let Some(m) = m.as_object_mut() {
            m.remove("emissiveTexture");
        }
    }
    std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    for e in std::fs::read_dir(folder).map_err(|e| e.to_string())? {
        let p = e.map_err(|e| e.to_string())?.path();
        if p.extension().is_some_and(|x| x == "bin" || x == "png") {
            std::fs::copy(&p, dir.join(p.file_name().ok_or("no name")?))
                .map_err(|e| e.to_string())?;
        }
    }
    let model = dir.join("WaterBottle_baseColor_alone.gltf");
    std::fs::write(
        &model,
        serde_json::to_vec(&gltf).map_err(|e| e.to_string())?,
    )
    .map_err(|e| e.to_string())?;
    Ok(model)
}

/// Fox's model with its texture scaled to `side`², in `dir`.
fn scaled_fox(side: u32, dir: &Path) -> Result<PathBuf, String> {
    let source = resolve("shared:Fox/Fox.gltf");
    let mut gltf: Value =
        serde_json::from_slice(&std::fs::read(&source).map_err(|e| e.to_string())?)
            .map_err(|e| e.to_string())?;
    let uri = gltf["images"][0]["uri"]
        .as_str()
        .ok_or("Fox has no image URI")?;
    let data = uri.split_once(',').ok_or("not a data URI")?.1;
    let png = base64::engine::general_purpose::STANDARD
        .decode(data)
        .map_err(|e| e.to_string())?;
    let image = image::load_from_memory(&png).map_err(|e| e.to_string())?;
    let scaled = image.resize_exact(side, side, image::imageops::FilterType::Triangle);
    std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    let name = format!("Fox_{side}.png");
    scaled.save(dir.join(&name)).map_err(|e| e.to_string())?;
    gltf["images"][0] = serde_json::json!({ "uri": name });
    let model = dir.join(format!("Fox_{side}.gltf"));
    std::fs::write(
        &model,
        serde_json::to_vec(&gltf).map_err(|e| e.to_string())?,
    )
    .map_err(|e| e.to_string())?;
    Ok(model)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let [_, flag, side, dir] = &args[..] {
        if flag == "--make-fox" {
            match side
                .parse()
                .map_err(|_| "bad side".to_string())
                .and_then(|side| scaled_fox(side, Path::new(dir)))
            {
                Ok(model) => println!("{}", model.display()),
                Err(e) => {
                    println!("{e}");
                    std::process::exit(1);
                }
            }
            return;
        }
    }
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let runs = std::env::var("SEAMSTRESS_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(RUNS)
        .max(1);
    let scratch = std::env::temp_dir().join(format!("seamstress-bench-job-{}", std::process::id()));
    let mut rows: Vec<(String, PathBuf, Vec<&str>)> = Vec::new();
    for (name, spec, extra) in JOBS {
        for mips in [false, true] {
            let mut args = extra.to_vec();
            let mut label = name.to_string();
            if !mips {
                args.push("--no-mips");
                label.push_str(" --no-mips");
            }
            rows.push((label, resolve(spec), args));
        }
    }
    let label = "WaterBottle baseColor alone".to_string();
    if filters.is_empty() || filters.iter().any(|f| label.contains(f.as_str())) {
        match water_bottle_base_colour(&scratch.join("bottle")) {
            Ok(model) => rows.insert(6, (label, model, vec!["--no-mips"])),
            Err(e) => println!("{label}: cannot make the model: {e}"),
        }
    }
    for side in [4096, 8192] {
        let label = format!("Fox {side}²");
        if filters.is_empty() || filters.iter().any(|f| label.contains(f.as_str())) {
            // Made by a child process: an 8192² image held here would be
            // counted in the peak of every job forked after it.
            let dir = scratch.join("models");
            let made = std::env::current_exe()
                .map_err(|e| e.to_string())
                .and_then(|exe| {
                    Command::new(exe)
                        .args(["--make-fox", &side.to_string()])
                        .arg(&dir)
                        .output()
                        .map_err(|e| e.to_string())
                })
                .and_then(|o| {
                    let text = String::from_utf8_lossy(&o.stdout).trim().to_string();
                    if o.status.success() {
                        Ok(PathBuf::from(text))
                    } else {
                        Err(format!("{text} {}", String::from_utf8_lossy(&o.stderr)))
                    }
                });
            match made {
                Ok(model) => rows.push((label, model, vec!["--no-mips"])),
                Err(e) => println!("{label}: cannot make the model: {e}"),
            }
        }
    }
    let has_nv = Command::new("nvcompress")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok();

    println!(
        "{:<26} {:>3} {:>7} {:>7} {:>8} {:>7} {:>8} {:>6}  stages ms (summed over textures)",
        "job", "tex", "wall s", "cpu s", "peak MiB", "cover", "nv s", "× nv"
    );
    let rows: Vec<_> = rows
        .into_iter()
        .filter(|(label, ..)| {
            filters.is_empty() || filters.iter().any(|f| label.contains(f.as_str()))
        })
        .collect();
    // Rounds of every row in turn, not each row's runs back to back: this
    // kind of machine's speed drifts by a third within the hour, and the
    // goals compare rows with each other (see `ratio`).
    let outs: Vec<PathBuf> = (0..rows.len())
        .map(|i| scratch.join(format!("out{i}")))
        .collect();
    let mut done: Vec<Vec<(Run, Value)>> = rows.iter().map(|_| Vec::new()).collect();
    let mut failed: Vec<Option<String>> = vec![None; rows.len()];
    for _ in 0..runs {
        for (i, (_, model, args)) in rows.iter().enumerate() {
            if failed[i].is_some() {
                continue;
            }
            match one_job(model, args, &outs[i]) {
                Ok(r) => done[i].push(r),
                Err(e) => failed[i] = Some(e),
            }
        }
    }
    let mut figures = std::collections::BTreeMap::new();
    for (i, (label, _, args)) in rows.iter().enumerate() {
        if let Some(e) = &failed[i] {
            println!("{label:<26} failed: {e}");
            continue;
        }
        let walls: Vec<f64> = done[i].iter().map(|(r, _)| r.wall).collect();
        let mut runs_of_row = std::mem::take(&mut done[i]);
        runs_of_row.sort_by(|a, b| a.0.wall.total_cmp(&b.0.wall));
        let (run, report) = runs_of_row.swap_remove(runs / 2);
        let (list, textures_ms, count) = stages(&report);
        let load = report["textures"][0]["timings_ms"]["load"]
            .as_u64()
            .unwrap_or(0);
        // Textures overlap (each one's erase beside the last one's
        // encoding): their stages cover the wall time of one texture only.
        let cover = (count == 1).then(|| (load + textures_ms) as f64 / 1000.0 / run.wall);
        let nv = if has_nv {
            nvcompress(&outs[i], !args.contains(&"--no-mips"), runs)
        } else {
            None
        };
        let breakdown: Vec<String> = std::iter::once(format!("load {load}"))
            .chain(
                list.iter()
                    .filter(|(_, v)| *v > 0)
                    .map(|(k, v)| format!("{k} {v}")),
            )
            .collect();
        println!(
            "{label:<26} {count:>3} {:>7.2} {:>7.2} {:>8.0} {:>7} {:>8} {:>6}  {}",
            run.wall,
            run.cpu,
            run.peak_mb,
            cover.map_or("-".into(), |c| format!("{:.0}%", c * 100.0)),
            nv.map_or("-".into(), |s| format!("{s:.2}")),
            nv.map_or("-".into(), |s| format!("{:.1}", run.wall / s)),
            breakdown.join(", ")
        );
        figures.insert(label.clone(), (walls, run.peak_mb));
        let _ = std::fs::remove_dir_all(&outs[i]);
    }
    let _ = std::fs::remove_dir_all(&scratch);

    println!("\nwall: median of {runs} whole-process runs; cpu and peak (ru_maxrss) of that run;");
    println!("cover (one texture): load + the texture's stages over the wall time (the rest is");
    println!(
        "process start, the report, the rewritten model and writing files); nv: nvcompress -bc1"
    );
    println!("-nocuda on the same erased PNGs (with mips when the row has them).");
    let wall = |k: &str| figures.get(k).map(|f| median(f.0.clone()));
    let peak = |k: &str| figures.get(k).map(|f| f.1);
    // Two rows' ratio: the median over the rounds of the ratio within each,
    // whose runs ran minutes apart at most.
    let ratio = |a: &str, b: &str| {
        let (a, b) = (&figures.get(a)?.0, &figures.get(b)?.0);
        Some(median(a.iter().zip(b).map(|(a, b)| a / b).collect()))
    };
    let goal = |what: &str, value: Option<f64>, limit: f64, unit: &str| {
        if let Some(v) = value {
            let verdict = if v <= limit { "met" } else { "not met" };
            println!("  {what:<44} {v:>8.2} {unit} (goal ≤ {limit}) {verdict}");
        }
    };
    println!("\nGoals (a ratio is the median of its rounds' ratios):");
    goal("Fox wall", wall("Fox"), 1.5, "s");
    goal("Fox --no-mips wall", wall("Fox --no-mips"), 1.0, "s");
    for mips in [" --no-mips", ""] {
        for atlas in ["blub_atlas_black", "blub_atlas_dilated"] {
            goal(
                &format!("{atlas}{mips} / Fox{mips}"),
                ratio(&format!("{atlas}{mips}"), &format!("Fox{mips}")),
                2.0,
                "×",
            );
        }
    }
    goal("Fox 8192² wall", wall("Fox 8192²"), 15.0, "s");
    goal(
        "Fox 8192² peak",
        peak("Fox 8192²").map(|p| p * 1048576.0 / 1e9),
        3.0,
        "GB",
    );
    goal(
        "WaterBottle / its base colour alone",
        ratio("WaterBottle --no-mips", "WaterBottle baseColor alone"),
        1.3,
        "×",
    );
}
