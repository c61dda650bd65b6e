//! What `seamstress process` prints: a summary for a person by default,
//! the report with `--json`, nothing with `-q`; counts in good English;
//! files of other formats named for what they are.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

fn shared_asset(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel)
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-output-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn seamstress(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(args)
        .env_remove("SEAMSTRESS_LOG")
        .output()
        .expect("seamstress runs")
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn report(out: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
}

/// CesiumMan leaves some seams as painted: the summary names the closed
/// ones' share and their seam_rms before and after, as the report has them.
#[test]
fn one_model_prints_its_summary() {
    let dir = scratch("cesium");
    let out = dir.join("out");
    let model = shared_asset("CesiumMan/CesiumMan.gltf");
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let stdout = text(&o.stdout);
    println!("{stdout}");
    let r = report(&out);
    let t = &r["textures"][0];
    let before = t["input"]["seam_rms_closed"].as_f64().unwrap();
    let after = t["bc1_seam_aware"]["seam_rms_closed"].as_f64().unwrap();
    assert!(after < before / 4.0, "{before} → {after}");
    let closed = t["seams"]["closed"]["edges"].as_u64().unwrap();
    let left = t["seams"]["left"]["edges"].as_u64().unwrap();
    assert!(closed > 0 && left > 0, "{t}");
    let share = t["seams"]["closed"]["length_share"].as_f64().unwrap() * 100.0;
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 3, "{stdout}");
    let warnings = match r["warnings"].as_array().unwrap().len() {
        0 => String::new(),
        1 => ", 1 warning (in report.json)".to_string(),
        n => format!(", {n} warnings (in report.json)"),
    };
    assert_eq!(lines[0], format!("CesiumMan.gltf: 1 texture{warnings}"));
    let expected = format!(
        "  CesiumMan 1024×1024: {closed} of {} seams closed ({share:.0}% of the seam length), \
         {left} left as painted ({:.0}%); seam_rms over the closed seams {before:.2} → {after:.2} \
         in the DDS",
        closed + left,
        100.0 - share
    );
    assert_eq!(lines[1], expected);
    let files = std::fs::read_dir(&out).unwrap().count();
    assert!(
        lines[2].starts_with(&format!("wrote {files} files to {}: ", out.display())),
        "{stdout}"
    );
    assert!(lines[2].contains("CesiumMan.dds"), "{stdout}");
    // A summary is no report.
    assert!(serde_json::from_str::<Value>(&stdout).is_err());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn json_prints_the_report_and_quiet_prints_nothing() {
    let dir = scratch("modes");
    let model = shared_asset("cube/cube_gradient_128.glb");
    let model = model.to_str().unwrap();
    let json_out = dir.join("json");
    let o = seamstress(&[
        "process",
        model,
        "--out",
        json_out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let printed: Value = serde_json::from_slice(&o.stdout).expect("--json prints JSON");
    assert_eq!(printed, report(&json_out));

    let quiet_out = dir.join("quiet");
    let o = seamstress(&["process", model, "-q", "-o", quiet_out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert_eq!(text(&o.stdout), "");
    assert_eq!(text(&o.stderr), "");
    assert!(quiet_out.join("report.json").is_file());

    // -v logs what the default level keeps quiet; -q and --json exclude
    // each other.
    let o = seamstress(&[
        "process",
        model,
        "-v",
        "-o",
        dir.join("v").to_str().unwrap(),
    ]);
    assert!(o.status.success());
    assert!(
        text(&o.stderr).contains("model loaded"),
        "{}",
        text(&o.stderr)
    );
    let o = seamstress(&["process", model, "-q", "--json", "-o", "x"]);
    assert_eq!(o.status.code(), Some(2));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_batch_of_one_says_one_model() {
    let dir = scratch("one");
    let input = dir.join("in");
    std::fs::create_dir_all(&input).unwrap();
    std::fs::copy(
        shared_asset("cube/cube_gradient_128.glb"),
        input.join("cube.glb"),
    )
    .unwrap();
    let out = dir.join("out");
    let o = seamstress(&[
        "process",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-mips",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let err = text(&o.stderr);
    assert!(err.contains("1 model: 1 processed"), "{err}");
    assert!(err.contains("— 1 texture,"), "{err}");
    assert!(
        !err.contains("1 models") && !err.contains("1 textures"),
        "{err}"
    );
    // --json: the batch's summary on standard output.
    let o = seamstress(&[
        "process",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-mips",
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let summary: Value = serde_json::from_slice(&o.stdout).expect("a JSON summary");
    assert_eq!(summary["models"], 1);
    assert_eq!(summary["cached"], 1);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn other_formats_are_named() {
    let dir = scratch("foreign");
    let cases: [(&str, &[u8], &str); 3] = [
        (
            "tiny.obj",
            b"# a triangle\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n",
            "tiny.obj: a Wavefront OBJ file, not glTF; convert it to glTF (.gltf or .glb) first",
        ),
        (
            "scene.fbx",
            b"Kaydara FBX Binary  \0\x1a\0\xe8\x1c\0\0",
            "scene.fbx: an FBX file, not glTF",
        ),
        (
            "texture.gltf",
            b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR",
            "texture.gltf: a PNG image, not a model",
        ),
    ];
    for (name, bytes, message) in cases {
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        let o = seamstress(&[
            "process",
            path.to_str().unwrap(),
            "--out",
            dir.join("out").to_str().unwrap(),
        ]);
        let err = text(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{name}: {err}");
        assert_eq!(err.lines().count(), 1, "{name}: {err}");
        assert!(err.contains(message), "{name}: {err}");
        assert!(o.stdout.is_empty(), "{name}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
