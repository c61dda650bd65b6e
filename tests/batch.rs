//! `process` over many models: a folder of every shared model with a bad
//! one mixed in, the mirrored output tree, the summary, exit statuses, and
//! a second run served from the cache.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

mod common;
use common::{farm_folder, report_without_timings};

fn shared() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets")
}

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-batch-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn process(args: &[&Path], extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("process")
        .args(args)
        .args(extra)
        .output()
        .expect("seamstress runs")
}

fn summary(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn statuses(s: &Value) -> Vec<(String, String)> {
    s["outcomes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| {
            let model = o["model"].as_str().unwrap().to_string();
            (model, o["status"].as_str().unwrap().to_string())
        })
        .collect()
}

/// The farm folder once more, kept going past its bad model: the summary.
fn again(input: &Path, out: &Path, sum: &Path) -> Value {
    let o = process(
        &[input],
        &[
            "--out",
            out.to_str().unwrap(),
            "--keep-going",
            "--summary",
            sum.to_str().unwrap(),
        ],
    );
    assert_eq!(o.status.code(), Some(2));
    summary(sum)
}

#[test]
fn a_folder_of_every_shared_model_with_a_bad_one_then_from_the_cache() {
    let dir = scratch("farm");
    let (input, models) = farm_folder(&dir);
    let out = dir.join("out");
    let sum = dir.join("summary.json");
    let sum_s = sum.to_str().unwrap();
    let o = process(
        &[&input],
        &[
            "--out",
            out.to_str().unwrap(),
            "--jobs",
            "2",
            "--keep-going",
            "--summary",
            sum_s,
        ],
    );
    // Some inputs bad: exit 2, the others all done.
    assert_eq!(
        o.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let s = summary(&sum);
    assert_eq!(s["models"], models);
    assert_eq!(s["processed"], models - 1, "{s}");
    assert_eq!(s["bad_input"], 1);
    let bad: Vec<_> = statuses(&s)
        .into_iter()
        .filter(|(_, st)| st != "processed")
        .collect();
    assert_eq!(bad.len(), 1);
    assert!(bad[0].0.ends_with("draco.glb"), "{bad:?}");
    let closed = |k: &str| s[k].as_f64().unwrap();
    assert!(
        closed("seam_rms_closed_after") < closed("seam_rms_closed_before"),
        "{s}"
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("KHR_draco_mesh_compression"), "{err}");

    // The tree mirrors the inputs; each folder is what `process` writes for
    // that model alone.
    let duck = out.join("Duck/Duck");
    for f in ["report.json", "Duck.gltf"] {
        assert!(duck.join(f).is_file(), "{f} missing in {}", duck.display());
    }
    assert!(out
        .join("cube/cube_gradient_128/cube_gradient_128.glb")
        .is_file());
    let alone = dir.join("alone");
    let o = process(
        &[&input.join("Duck/Duck.gltf")],
        &["--out", alone.to_str().unwrap()],
    );
    assert!(o.status.success());
    for e in std::fs::read_dir(&alone).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_str().unwrap().to_string();
        let ours = std::fs::read(duck.join(&name)).unwrap();
        if name == "report.json" {
            assert_eq!(
                report_without_timings(&ours),
                report_without_timings(&std::fs::read(&p).unwrap())
            );
        } else {
            assert_eq!(ours, std::fs::read(&p).unwrap(), "{name}");
        }
    }

    // Again, unchanged: everything from the cache.
    let s = again(&input, &out, &sum);
    assert_eq!(s["cached"], models - 1, "{s}");
    assert_eq!(s["processed"], 0);

    // A changed image redoes its model only; --force redoes them all.
    let png = input.join("BoxTextured/BoxTextured-glTF/CesiumLogoFlat.png");
    let mut img = image::open(&png).unwrap().to_rgb8();
    img.get_pixel_mut(5, 5).0 = [255, 0, 0];
    img.save(&png).unwrap();
    let s = again(&input, &out, &sum);
    assert_eq!(s["cached"], models - 2, "{s}");
    let redone: Vec<_> = statuses(&s)
        .into_iter()
        .filter(|(_, st)| st == "processed")
        .map(|(m, _)| m)
        .collect();
    assert_eq!(redone.len(), 1, "{s}");
    assert!(
        redone[0].ends_with("BoxTextured-glTF/BoxTextured.gltf"),
        "{redone:?}"
    );
    let cubes = dir.join("cubes");
    for force in [false, true] {
        let mut extra = vec!["--out", cubes.to_str().unwrap(), "--summary", sum_s];
        if force {
            extra.push("--force");
        }
        let o = process(&[&input.join("cube")], &extra);
        assert!(o.status.success());
        assert_eq!(summary(&sum)["processed"], 3);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn without_keep_going_a_batch_stops_at_the_first_failure() {
    let dir = scratch("stop");
    let bad = dir.join("draco.glb");
    std::fs::copy(shared().join("negative/BoxTextured_draco.glb"), &bad).unwrap();
    let out = dir.join("out");
    let sum = dir.join("summary.json");
    let o = process(
        &[&bad, &shared().join("cube")],
        &[
            "--out",
            out.to_str().unwrap(),
            "--summary",
            sum.to_str().unwrap(),
        ],
    );
    assert_eq!(o.status.code(), Some(2));
    let s = summary(&sum);
    assert_eq!(s["bad_input"], 1);
    assert_eq!(s["not_run"], 3, "{s}");
    // Glob patterns expand relative to their literal prefix.
    let pattern = format!("{}/*_128.glb", shared().join("cube").display());
    let o = process(
        &[Path::new(&pattern)],
        &[
            "--out",
            out.to_str().unwrap(),
            "--summary",
            sum.to_str().unwrap(),
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("cube_gradient_128/report.json").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

/// The mean over a report's textures of `pick`, as the summary takes it.
fn mean_over_textures(report: &Value, pick: impl Fn(&Value) -> Option<f64>) -> f64 {
    let textures = report["textures"].as_array().unwrap();
    let v: Vec<f64> = textures.iter().filter_map(pick).collect();
    assert!(!v.is_empty(), "no texture has the figure");
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn the_summary_headlines_the_closed_seams_as_the_report_has_them() {
    let dir = scratch("headline");
    let out = dir.join("out");
    let sum = dir.join("summary.json");
    let o = process(
        &[&shared().join("CesiumMan")],
        &[
            "--out",
            out.to_str().unwrap(),
            "--summary",
            sum.to_str().unwrap(),
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let s = summary(&sum);
    let outcome = &s["outcomes"][0];
    let report: Value = serde_json::from_slice(
        &std::fs::read(Path::new(outcome["out"].as_str().unwrap()).join("report.json")).unwrap(),
    )
    .unwrap();
    let before = mean_over_textures(&report, |t| t["input"]["seam_rms_closed"].as_f64());
    let after = mean_over_textures(&report, |t| t["bc1_seam_aware"]["seam_rms_closed"].as_f64());
    let edges = |which: &str| {
        report["textures"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t["seams"][which]["edges"].as_u64().unwrap())
            .sum::<u64>()
    };
    assert!(edges("left") > 0, "CesiumMan leaves seams as painted");
    for figures in [&s, outcome] {
        assert_eq!(
            figures["seam_rms_closed_before"].as_f64(),
            Some(before),
            "{s}"
        );
        assert_eq!(
            figures["seam_rms_closed_after"].as_f64(),
            Some(after),
            "{s}"
        );
        assert_eq!(
            figures["seams_closed"].as_u64(),
            Some(edges("closed")),
            "{s}"
        );
        assert_eq!(figures["seams_left"].as_u64(), Some(edges("left")), "{s}");
        assert!(figures["seam_rms_all_seams_before"].is_f64(), "{s}");
        assert!(figures["seam_rms_all_seams_after"].is_f64(), "{s}");
        for old in ["seam_rms_before", "seam_rms_after"] {
            assert!(figures.get(old).is_none(), "{old} is still written: {s}");
        }
    }
    assert!(after < before, "{before} → {after}");

    // Printed: the counts, then the closed seams first, with the report's
    // figures, then those over all seams under their own name.
    let textures = report["textures"].as_array().unwrap().len();
    let lines: Vec<&str> = err.lines().collect();
    let counts = lines
        .iter()
        .position(|l| l.starts_with("1 model: 1 processed"))
        .unwrap_or_else(|| panic!("no counts line: {err}"));
    let texture_count = if textures == 1 {
        "1 texture,".to_string()
    } else {
        format!("{textures} textures,")
    };
    assert!(lines[counts].contains(&texture_count), "{err}");
    let headline = format!(
        "seam_rms over the closed seams: {before:.3} → {after:.3} (1 model; {} seams closed, {} left as painted)",
        edges("closed"),
        edges("left")
    );
    assert_eq!(lines.get(counts + 1), Some(&headline.as_str()), "{err}");
    let all = lines.get(counts + 2).copied().unwrap_or_default();
    assert!(
        all.starts_with("seam_rms over all seams, those left as painted included: "),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
