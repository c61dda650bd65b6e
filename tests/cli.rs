//! The `seamstress` binary end to end: outputs, exit statuses, and agreement
//! with the independent evaluator in `../shared/tools/seam_eval.py`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex, OnceLock};

use serde_json::Value;

mod common;
use needs::needs;

fn shared() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared")
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-cli-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn seamstress(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(args)
        .output()
        .expect("seamstress runs")
}

/// Processed at the images' own sizes (`--resize none`): the evaluator
/// reads the outputs against the model's images.
fn process(model: &Path, out: &Path) -> Value {
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--resize",
        "none",
    ]);
    assert!(
        o.status.success(),
        "{}: {}",
        model.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    let report = std::fs::read(out.join("report.json")).expect("report.json written");
    serde_json::from_slice(&report).expect("report.json is JSON")
}

/// Where [`processed`] writes: one folder for the whole test process,
/// removed when it exits.
fn shared_outputs() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    extern "C" fn remove() {
        if let Some(dir) = DIR.get() {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
    DIR.get_or_init(|| {
        // SAFETY: `remove` is a plain function that only removes the folder.
        unsafe { libc::atexit(remove) };
        scratch("shared")
    })
}

/// [`process`] of the shared model at `rel` (under `assets`), run once per
/// test process: the tests that compare the same outputs with the
/// evaluator in different ways read one run, the first to ask waiting for
/// it, the others for it. Its output folder and report.
fn processed(rel: &str) -> (PathBuf, Value) {
    type Runs = BTreeMap<String, Arc<OnceLock<(PathBuf, Value)>>>;
    static RUNS: Mutex<Runs> = Mutex::new(BTreeMap::new());
    let run = RUNS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .entry(rel.to_string())
        .or_default()
        .clone();
    run.get_or_init(|| {
        let out = shared_outputs().join(rel.replace('/', "_"));
        let report = process(&shared().join("assets").join(rel), &out);
        (out, report)
    })
    .clone()
}

/// Runs the evaluator on texture `texture` (see [`common::seam_eval`]).
fn seam_eval(model: &Path, image: Option<&Path>, texture: usize) -> Value {
    common::seam_eval(model, image, &["--texture", &texture.to_string()])
}

fn close(ours: &Value, theirs: &Value, what: &str) {
    // A model without seams reports null; the evaluator reports 0.
    let a = ours.as_f64().unwrap_or(0.0);
    let b = theirs.as_f64().unwrap_or(0.0);
    assert!(
        (a - b).abs() <= 0.005 * b.abs().max(a.abs()) + 1e-3,
        "{what}: report {a} vs seam_eval {b}"
    );
}

#[needs(python)]
#[test]
fn reports_agree_with_the_independent_evaluator() {
    if !common::PYTHON.available() {
        return;
    }
    let models = [
        "cube/cube_gradient_128.glb",
        "cube/cube_gradient_1024.glb",
        "cube/cube_bad_background_100.glb",
        "Duck/Duck.gltf",
        "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
        "BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb",
        "BoxTextured/BoxTextured-glTF-Embedded/BoxTextured.gltf",
        "blub/blub.glb",
        "Fox/Fox.gltf",
    ];
    for rel in models {
        let model = shared().join("assets").join(rel);
        let (out, report) = processed(rel);
        for t in report["textures"].as_array().expect("textures") {
            let texture = t["image"].as_u64().unwrap() as usize;
            let png = out.join(t["files"]["erased"].as_str().unwrap());
            assert!(png.exists(), "{rel}: {} missing", png.display());
            let input = seam_eval(&model, None, texture);
            close(
                &t["input"]["seam_rms"],
                &input["seam_rms"],
                &format!("{rel} input seam_rms"),
            );
            let erased = seam_eval(&model, Some(&png), texture);
            close(
                &t["erased"]["seam_rms"],
                &erased["seam_rms"],
                &format!("{rel} erased seam_rms"),
            );
            close(
                &t["erased"]["psnr"],
                &erased["psnr"],
                &format!("{rel} erased psnr"),
            );
            assert_eq!(t["seam_edges"], input["seam_edges"], "{rel}: seam edges");
            // The DDS holds the seam-aware encoding; the evaluator decodes it independently.
            let dds = out.join(t["files"]["dds"].as_str().expect("a DDS by default"));
            let shipped = seam_eval(&model, Some(&dds), texture);
            let sa = &t["bc1_seam_aware"];
            close(
                &sa["seam_rms"],
                &shipped["seam_rms"],
                &format!("{rel} DDS seam_rms"),
            );
            close(&sa["psnr"], &shipped["psnr"], &format!("{rel} DDS psnr"));
        }
    }
}

/// The evaluator decodes the DDS with each GPU's palette rounding and
/// measures what the report says for that decoder.
#[needs(python)]
#[test]
fn per_decoder_figures_agree_with_the_independent_evaluator() {
    if !common::PYTHON.available() {
        return;
    }
    for rel in ["Duck/Duck.gltf", "cube/cube_gradient_1024.glb"] {
        let model = shared().join("assets").join(rel);
        let (out, report) = processed(rel);
        let t = &report["textures"][0];
        assert_eq!(t["bc1_target"], "robust");
        let dds = out.join(t["files"]["dds"].as_str().unwrap());
        for d in ["ideal", "nvidia", "amd"] {
            let theirs = common::seam_eval(&model, Some(&dds), &["--decoder", d]);
            let ours = &t["bc1_seam_aware"]["decoders"][d];
            close(
                &ours["seam_rms"],
                &theirs["seam_rms"],
                &format!("{rel} {d} seam_rms"),
            );
            close(&ours["psnr"], &theirs["psnr"], &format!("{rel} {d} psnr"));
        }
    }
}

/// The evaluator's own judgement of which seams should agree (sides within
/// 16 levels as their charts paint them) and its PSNR per UV chart confirm
/// what the report says: the agreeing seams close, no chart is repainted.
#[needs(python)]
#[test]
fn the_evaluator_confirms_that_charts_painted_apart_are_kept() {
    if !common::PYTHON.available() {
        return;
    }
    for (rel, floor) in [("Fox/Fox.gltf", 40.0), ("CesiumMan/CesiumMan.gltf", 30.0)] {
        let model = shared().join("assets").join(rel);
        let (out, report) = processed(rel);
        let t = &report["textures"][0];
        let png = out.join(t["files"]["erased"].as_str().unwrap());
        let theirs = common::seam_eval(&model, Some(&png), &["--agree", "16", "--charts"]);
        eprintln!("{rel}: seam_eval {theirs}");
        let agree = theirs["agree"]["seam_rms"].as_f64().unwrap();
        assert!(agree <= 0.3, "{rel}: agreeing seams at {agree}");
        let worst = theirs["charts"]["worst_psnr"].as_f64().unwrap();
        assert!(worst >= floor, "{rel}: worst chart {worst} dB");
        close(
            &t["erased"]["worst_chart_psnr"],
            &theirs["charts"]["worst_psnr"],
            &format!("{rel} worst chart psnr"),
        );
        assert_eq!(
            t["erased"]["charts_under_30db"], theirs["charts"]["under_30db"],
            "{rel}"
        );
    }
}

#[test]
fn every_negative_asset_is_bad_input_with_one_line() {
    let mut files = Vec::new();
    let mut stack = vec![shared().join("assets/negative")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).expect("negative assets") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                stack.push(p);
            } else if matches!(p.extension().and_then(|x| x.to_str()), Some("gltf" | "glb")) {
                files.push(p);
            }
        }
    }
    assert!(files.len() >= 10, "negative assets found: {files:?}");
    for f in files {
        let out = scratch("negative");
        let o = seamstress(&[
            "process",
            f.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{}: {err}", f.display());
        assert_eq!(err.trim_end().lines().count(), 1, "{}: {err}", f.display());
        let name = f.file_name().unwrap().to_str().unwrap();
        assert!(
            err.contains(name),
            "{}: error does not name the file: {err}",
            f.display()
        );
        assert!(
            !out.join("report.json").exists(),
            "{}: wrote a report",
            f.display()
        );
    }
}

#[test]
fn texture_above_the_pixel_limit_is_refused() {
    let model = shared().join("assets/cube/cube_gradient_128.glb");
    let out = scratch("limit");
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--max-texture-size",
        "64",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("cube_gradient_128.glb"), "{err}");
}

#[test]
fn out_that_is_a_file_is_refused_and_left_alone() {
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/cube_gradient_128.glb");
    let file = scratch("out-file");
    std::fs::write(&file, b"keep me").unwrap();
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        file.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.contains(file.to_str().unwrap()), "{err}");
    assert!(err.contains("not a folder"), "{err}");
    assert_eq!(std::fs::read(&file).unwrap(), b"keep me");
    let _ = std::fs::remove_file(&file);
}

#[test]
fn repeated_runs_write_identical_files() {
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/cube_gradient_128.glb");
    let (a, b) = (scratch("det-a"), scratch("det-b"));
    let ra = process(&model, &a);
    process(&model, &b);
    let png = ra["textures"][0]["files"]["erased"].as_str().unwrap();
    assert_eq!(
        std::fs::read(a.join(png)).unwrap(),
        std::fs::read(b.join(png)).unwrap()
    );
}

/// Every file of `dir`, by name; `report.json` without its timings, the one
/// thing that may differ between runs.
fn outputs_without_timings(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            let mut bytes = std::fs::read(&p).unwrap();
            if name == "report.json" {
                let mut report: Value = serde_json::from_slice(&bytes).unwrap();
                for t in report["textures"].as_array_mut().unwrap() {
                    t.as_object_mut().unwrap().remove("timings_ms");
                }
                report.as_object_mut().unwrap().remove("timings_ms");
                bytes = serde_json::to_vec(&report).unwrap();
            }
            (name, bytes)
        })
        .collect();
    files.sort();
    files
}

/// The stages run side by side on as many threads as there are; the bytes
/// must not depend on how many. The controller has many seams, alpha and
/// a chain of mip levels, each encoded beside the erasure of the next.
#[test]
fn outputs_are_identical_on_one_and_two_threads() {
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/assets/oculus-touch-v3/oculus-touch-v3-left.glb");
    let run = |threads: &str| {
        let out = scratch(&format!("threads-{threads}"));
        let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .env("RAYON_NUM_THREADS", threads)
            .args(["process", model.to_str().unwrap(), "--pictures", "--out"])
            .arg(&out)
            .output()
            .expect("seamstress runs");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let files = outputs_without_timings(&out);
        let _ = std::fs::remove_dir_all(&out);
        files
    };
    let (one, two) = (run("1"), run("2"));
    assert!(
        one.iter().any(|(n, _)| n.ends_with(".dds")),
        "a DDS is written"
    );
    assert_eq!(
        one.iter().map(|f| &f.0).collect::<Vec<_>>(),
        two.iter().map(|f| &f.0).collect::<Vec<_>>()
    );
    for ((name, a), (_, b)) in one.iter().zip(&two) {
        assert!(a == b, "{name} differs between one and two threads");
    }
}

/// No validator error in a rewritten model but those its source has
/// already (CesiumMan's skin weights do not sum to 1, say): the rewriting
/// adds none.
fn no_new_errors(verdict: &Value, source: &Path, what: &str) {
    if verdict["errors"] == 0 {
        return;
    }
    let before = common::gltf_validate(source);
    for (code, n) in verdict["error_codes"].as_object().unwrap() {
        let had = before["error_codes"][code].as_u64().unwrap_or(0);
        assert!(
            n.as_u64().unwrap() <= had,
            "{what}: {code} ×{n}, the source has {had}: {verdict}"
        );
    }
}

#[needs(gltf_validator)]
#[test]
fn rewritten_models_pass_the_khronos_validator() {
    if !common::GLTF_VALIDATOR.available() {
        return;
    }
    let assets = shared().join("assets");
    let mut models = Vec::new();
    let mut dirs = vec![assets.clone()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() && p.file_name().is_some_and(|n| n != "negative") {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "gltf" || x == "glb") {
                models.push(p);
            }
        }
    }
    models.sort();
    assert!(models.len() >= 12, "{models:?}");
    for model in &models {
        let name = model.file_name().unwrap().to_str().unwrap();
        let rel = model.strip_prefix(&assets).unwrap().display().to_string();
        let out = scratch(&format!("validate-{}", rel.replace('/', "-")));
        // Default options but for the encoders' effort and the mip
        // chains: the model's structure is what is checked (a rewritten
        // .gltf is the same with mips or without; a .glb's binary chunk
        // holds a shorter DDS). BoxTextured's 211² texture is resized,
        // TextureTransformTest's transforms composed.
        let o = seamstress(&[
            "process",
            model.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--bc1-level",
            "fast",
            "--no-seam-aware",
            "--no-mips",
        ]);
        assert!(
            o.status.success(),
            "{rel}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let rewritten = out.join(name);
        assert!(rewritten.exists(), "{rel}: no rewritten model");
        let verdict = common::gltf_validate(&rewritten);
        no_new_errors(&verdict, model, &rel);
        if name.ends_with(".glb") {
            // One file out for one file in: nothing but the model is needed.
            let alone = scratch(&format!("validate-alone-{}", rel.replace('/', "-")));
            std::fs::create_dir_all(&alone).unwrap();
            std::fs::copy(&rewritten, alone.join(name)).unwrap();
            let verdict = common::gltf_validate(&alone.join(name));
            no_new_errors(&verdict, model, &format!("{rel} on its own"));
            let _ = std::fs::remove_dir_all(&alone);
        }
        let _ = std::fs::remove_dir_all(&out);
    }
}

#[test]
fn logs_are_plain_when_piped_and_all_json_when_asked() {
    let missing = "/nonexistent/model.glb";
    let o = seamstress(&["--log-format", "json", "process", missing, "--out", "o"]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.trim().is_empty());
    for line in err.lines() {
        let v: Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}"));
        assert!(
            v["fields"]["error"].as_str().unwrap().contains(missing),
            "{line}"
        );
    }
    // A model whose erasure repaints a chart logs a warning: no colour codes
    // into a pipe. (The warning comes from erasing level 0; the rest of the
    // job is left out.)
    let out = scratch("plain-logs");
    let o = seamstress(&[
        "process",
        shared().join("assets/Fox/Fox.gltf").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--erase-all",
        "--no-mips",
        "--no-seam-aware",
        "--bc1-level",
        "fast",
    ]);
    assert!(o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("WARN"), "{err}");
    assert!(!err.contains('\u{1b}'), "{err}");
    let help = seamstress(&["--help"]);
    assert!(String::from_utf8_lossy(&help.stdout).contains("SEAMSTRESS_LOG"));
}
