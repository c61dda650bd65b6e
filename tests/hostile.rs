//! Hostile and unlucky inputs through the `seamstress` binary: models that
//! ask for unbounded memory or time are refused before the work, with the
//! quantity, its value and the limit named, and exit status 2.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;

fn shared() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets")
}

fn scratch(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("seamstress-hostile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn seamstress(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(args)
        .output()
        .expect("seamstress runs")
}

/// BoxTextured with its PNG replaced by one whose header announces
/// `side`×`side` texels, followed by 64 KiB of image data that is not a
/// valid zlib stream: the header is all a budget may read.
fn box_announcing(side: u32, dir: &Path) -> PathBuf {
    let src = shared().join("BoxTextured/BoxTextured-glTF");
    for f in ["BoxTextured.gltf", "BoxTextured0.bin"] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend(side.to_be_bytes());
    ihdr.extend(side.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]); // 8-bit RGB
    let mut idat = b"IDAT".to_vec();
    idat.extend(vec![0u8; 64 << 10]);
    for chunk in [&ihdr, &idat, &b"IEND".to_vec()] {
        png.extend((chunk.len() as u32 - 4).to_be_bytes());
        png.extend(chunk.iter());
        png.extend(common::crc32(chunk).to_be_bytes());
    }
    std::fs::write(dir.join("CesiumLogoFlat.png"), png).unwrap();
    dir.join("BoxTextured.gltf")
}

fn refused(o: &std::process::Output, quantity: &str, file: &Path) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains(quantity), "{err}");
    assert!(err.contains("over the limit of"), "{err}");
    assert!(
        err.contains(file.file_name().unwrap().to_str().unwrap()),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
}

#[test]
fn uvs_spanning_many_periods_are_refused_at_once() {
    let dir = scratch("tiled");
    let model = common::tiled_duck(1000.0, &dir);
    let t = Instant::now();
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    refused(&o, "texels covered by triangles", &model);
    assert!(t.elapsed() < Duration::from_secs(20), "{:?}", t.elapsed());
    assert!(!dir.join("out/report.json").exists());
}

#[test]
fn a_modest_tiling_still_runs() {
    let dir = scratch("tiled2");
    let model = common::tiled_duck(2.0, &dir);
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: Value =
        serde_json::from_slice(&std::fs::read(dir.join("out/report.json")).unwrap()).unwrap();
    let t = &report["textures"][0];
    assert!(
        t["erased"]["seam_rms_closed"].as_f64().unwrap()
            < 0.5 * t["input"]["seam_rms_closed"].as_f64().unwrap()
    );
}

#[test]
fn an_image_announcing_more_than_the_memory_limit_is_refused_before_decoding() {
    let dir = scratch("announce");
    let model = box_announcing(8192, &dir);
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
        "--max-memory",
        "1G",
    ]);
    refused(&o, "estimated memory", &model);
    assert!(String::from_utf8_lossy(&o.stderr).contains("1.0 GiB"));
}

#[test]
fn the_default_limit_follows_the_address_space_limit() {
    let dir = scratch("rlimit");
    let model = box_announcing(8192, &dir);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_seamstress"));
    cmd.args([
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    common::limit_address_space(&mut cmd, 2 << 30);
    let o = cmd.output().expect("seamstress runs");
    refused(&o, "estimated memory", &model);
}

#[test]
fn bad_memory_limits_are_usage_errors() {
    for bad in ["lots", "0", "4X"] {
        let o = seamstress(&["process", "x.glb", "--out", "o", "--max-memory", bad]);
        assert_eq!(o.status.code(), Some(2), "{bad}");
    }
}

/// BoxTextured (.gltf and its files, copied into `dir`) with `edit` applied
/// to its JSON.
fn box_edited(dir: &Path, edit: impl FnOnce(&mut Value)) -> PathBuf {
    let src = shared().join("BoxTextured/BoxTextured-glTF");
    for f in ["BoxTextured0.bin", "CesiumLogoFlat.png"] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    let mut g: Value =
        serde_json::from_slice(&std::fs::read(src.join("BoxTextured.gltf")).unwrap()).unwrap();
    edit(&mut g);
    let path = dir.join("BoxTextured.gltf");
    std::fs::write(&path, serde_json::to_vec(&g).unwrap()).unwrap();
    path
}

#[test]
fn texcoords_reading_the_normals_are_refused_with_the_texture_named() {
    let dir = scratch("uv-normals");
    // TEXCOORD_0 reads the first two components of every normal: UVs the
    // loader accepts, on which the seam system is singular.
    let model = box_edited(&dir, |g| {
        let attributes = g["meshes"][0]["primitives"][0]["attributes"].clone();
        let normals = attributes["NORMAL"].as_u64().unwrap() as usize;
        let uv = attributes["TEXCOORD_0"].as_u64().unwrap() as usize;
        let from = g["accessors"][normals].clone();
        let to = g["accessors"][uv].as_object_mut().unwrap();
        to.insert("bufferView".into(), from["bufferView"].clone());
        to.insert("byteOffset".into(), from["byteOffset"].clone());
        to.remove("min");
        to.remove("max");
    });
    let out = dir.join("out");
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    // Its only texture cannot be processed: the model is at fault, and the
    // error names the file, the texture and why.
    assert_eq!(o.status.code(), Some(2), "{err}");
    let line = err
        .lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_else(|| panic!("no error line: {err}"));
    assert!(line.contains("BoxTextured.gltf"), "{line}");
    assert!(line.contains("no texture can be processed"), "{line}");
    assert!(line.contains("texture CesiumLogoFlat: skipped"), "{line}");
    assert!(line.contains("solver"), "{line}");
    assert!(!out.join("CesiumLogoFlat.dds").exists());
}

#[test]
fn a_texture_transform_tiling_ten_thousand_times_is_refused_at_once() {
    let dir = scratch("transform");
    let model = box_edited(&dir, |g| {
        g["extensionsUsed"] = serde_json::json!(["KHR_texture_transform"]);
        g["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["extensions"] = serde_json::json!({
            "KHR_texture_transform": { "scale": [1e4, 1e4] }
        });
    });
    let t = Instant::now();
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    refused(&o, "over the limit", &model);
    assert!(t.elapsed() < Duration::from_secs(20), "{:?}", t.elapsed());
}

#[test]
fn a_very_long_uri_is_bad_input_and_cut_in_the_message() {
    let dir = scratch("longuri");
    let long = format!("{}.png", "a".repeat(100_000));
    let model = box_edited(&dir, |g| g["images"][0]["uri"] = Value::String(long));
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{}", &err[..err.len().min(500)]);
    assert!(err.len() < 1000, "{} bytes of message", err.len());
    assert_eq!(err.trim().lines().count(), 1);
}

#[test]
fn a_buffer_file_far_longer_than_declared_is_refused_unread() {
    let dir = scratch("longbuffer");
    let model = box_edited(&dir, |_| {});
    let mut bin = std::fs::read(dir.join("BoxTextured0.bin")).unwrap();
    bin.resize(bin.len() + (1 << 20), 0);
    std::fs::write(dir.join("BoxTextured0.bin"), bin).unwrap();
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("buffer 0") && err.contains("more than"),
        "{err}"
    );
}

#[test]
fn concurrent_runs_into_one_out_neither_fail_nor_mix() {
    let dir = scratch("concurrent");
    let model = shared().join("cube/cube_gradient_128.glb");
    let out = dir.join("out");
    let run = || {
        Command::new(env!("CARGO_BIN_EXE_seamstress"))
            .args([
                "process",
                model.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ])
            .output()
            .unwrap()
    };
    let reference = run();
    assert!(reference.status.success());
    let dds = std::fs::read(out.join("cube_gradient_128.dds")).unwrap();
    for _ in 0..4 {
        let (a, b) = std::thread::scope(|s| {
            let a = s.spawn(run);
            let b = s.spawn(run);
            (a.join().unwrap(), b.join().unwrap())
        });
        for o in [a, b] {
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        }
        assert_eq!(
            std::fs::read(out.join("cube_gradient_128.dds")).unwrap(),
            dds
        );
    }
    // Only the outputs remain: no staging folders or temporary files.
    for e in std::fs::read_dir(&out).unwrap() {
        let name = e.unwrap().file_name().into_string().unwrap();
        assert!(!name.starts_with('.'), "{name} left in --out");
    }
}

#[test]
fn an_out_that_cannot_be_written_is_bad_input() {
    // No one, root included, can make a folder in /proc.
    let model = shared().join("cube/cube_gradient_128.glb");
    let o = seamstress(&[
        "process",
        model.to_str().unwrap(),
        "--out",
        "/proc/seamstress-out",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("/proc/seamstress-out"), "{err}");
}
