//! Textures whose sides are not multiples of 4 (BoxTextured's 211²): padded
//! with the rewritten model's UVs scaled, or resampled where UVs tile.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

use seamstress::bc1;
use seamstress::bc1::dds::read_dds;
use seamstress::model::Wrap;

mod common;
use needs::needs;

fn box_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets/BoxTextured/BoxTextured-glTF")
}

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-resize-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// BoxTextured with each face's UVs moved into the first period (its faces
/// sit side by side along u from 0 to 6): a model that samples one period,
/// so padding is exact. Returns the model and the range its v coordinates
/// span.
fn box_in_one_period(dir: &Path) -> (PathBuf, [f64; 2]) {
    let src = box_dir();
    let mut g: Value =
        serde_json::from_slice(&std::fs::read(src.join("BoxTextured.gltf")).unwrap()).unwrap();
    let mut bin = std::fs::read(src.join("BoxTextured0.bin")).unwrap();
    let acc = g["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]
        .as_u64()
        .unwrap() as usize;
    let view = &g["bufferViews"][g["accessors"][acc]["bufferView"].as_u64().unwrap() as usize];
    let start = view["byteOffset"].as_u64().unwrap() as usize;
    let count = g["accessors"][acc]["count"].as_u64().unwrap() as usize;
    let u_at = |v: usize| start + 8 * v;
    let v_range = (0..count)
        .map(|k| {
            let o = u_at(k) + 4;
            f64::from(f32::from_le_bytes(bin[o..o + 4].try_into().unwrap()))
        })
        .fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], v| {
            [lo.min(v), hi.max(v)]
        });
    for face in 0..count / 4 {
        let us: Vec<f32> = (0..4)
            .map(|k| {
                let o = u_at(face * 4 + k);
                f32::from_le_bytes(bin[o..o + 4].try_into().unwrap())
            })
            .collect();
        let shift = us.iter().cloned().fold(f32::INFINITY, f32::min).floor();
        for (k, u) in us.iter().enumerate() {
            let o = u_at(face * 4 + k);
            bin[o..o + 4].copy_from_slice(&(u - shift).to_le_bytes());
        }
    }
    let a = g["accessors"][acc].as_object_mut().unwrap();
    a.insert("min".into(), serde_json::json!([0.0, 0.0]));
    a.insert("max".into(), serde_json::json!([1.0, 1.0]));
    std::fs::write(dir.join("BoxTextured0.bin"), bin).unwrap();
    std::fs::copy(
        src.join("CesiumLogoFlat.png"),
        dir.join("CesiumLogoFlat.png"),
    )
    .unwrap();
    let path = dir.join("box_one_period.gltf");
    std::fs::write(&path, serde_json::to_vec(&g).unwrap()).unwrap();
    (path, v_range)
}

fn process(model: &Path, out: &Path, extra: &[&str]) -> Value {
    common::process_report(model, out, extra)
}

/// BoxTextured's sampler: MIRRORED_REPEAT across, CLAMP_TO_EDGE down.
const WRAPS: [Wrap; 2] = [Wrap::MirroredRepeat, Wrap::ClampToEdge];

/// An RGB image in \[0, 255\], sampled bilinearly with BoxTextured's wraps,
/// as a GPU does.
struct Rgb {
    w: usize,
    h: usize,
    texels: Vec<f32>,
}

impl Rgb {
    fn png(path: &Path) -> Rgb {
        let img = image::open(path).unwrap().to_rgb8();
        Rgb {
            w: img.width() as usize,
            h: img.height() as usize,
            texels: img.into_raw().into_iter().map(f32::from).collect(),
        }
    }

    fn dds(path: &Path) -> Rgb {
        let dds = read_dds(&std::fs::read(path).unwrap()).unwrap();
        let l = &dds.levels[0];
        let (w, h) = (l.width as usize, l.height as usize);
        let texels = bc1::decode_image(&l.blocks, w, h).unwrap();
        Rgb {
            w,
            h,
            texels: texels.into_iter().map(|v| v * 255.0).collect(),
        }
    }

    fn sample(&self, u: f64, v: f64) -> [f32; 3] {
        let (x, y) = (u * self.w as f64 - 0.5, v * self.h as f64 - 0.5);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let (xa, xb) = (WRAPS[0].index(x0, self.w), WRAPS[0].index(x0 + 1, self.w));
        let (ya, yb) = (WRAPS[1].index(y0, self.h), WRAPS[1].index(y0 + 1, self.h));
        let at = |x: usize, y: usize, c: usize| self.texels[(y * self.w + x) * 3 + c];
        std::array::from_fn(|c| {
            let top = at(xa, ya, c) * (1.0 - fx) + at(xb, ya, c) * fx;
            let bottom = at(xa, yb, c) * (1.0 - fx) + at(xb, yb, c) * fx;
            top * (1.0 - fy) + bottom * fy
        })
    }
}

/// Mean absolute difference (levels) between `a` at (u, v) and `b` at
/// (u·s₀, v·s₁), over a grid of UVs covering u ∈ [0, 1] and `v`, edges
/// included.
fn sampled_difference(a: &Rgb, b: &Rgb, s: [f64; 2], v: [f64; 2]) -> f64 {
    let n = 97;
    let mut sum = 0.0;
    for i in 0..=n {
        for j in 0..=n {
            let t = j as f64 / n as f64;
            let (u, v) = (i as f64 / n as f64, v[0] + (v[1] - v[0]) * t);
            let (p, q) = (a.sample(u, v), b.sample(u * s[0], v * s[1]));
            sum += p
                .iter()
                .zip(&q)
                .map(|(x, y)| f64::from((x - y).abs()))
                .sum::<f64>();
        }
    }
    sum / ((n + 1) * (n + 1) * 3) as f64
}

fn uv_scale(rewritten: &Path) -> [f64; 2] {
    let g: Value = serde_json::from_slice(&std::fs::read(rewritten).unwrap()).unwrap();
    let t = &g["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["extensions"]
        ["KHR_texture_transform"];
    assert!(g["extensionsUsed"]
        .as_array()
        .unwrap()
        .iter()
        .any(|e| e == "KHR_texture_transform"));
    [
        t["scale"][0].as_f64().unwrap(),
        t["scale"][1].as_f64().unwrap(),
    ]
}

#[test]
fn a_padded_texture_samples_as_the_original_through_the_rewritten_model() {
    let dir = scratch("padded");
    let (model, v_range) = box_in_one_period(&dir);
    let out = dir.join("out");
    let report = process(&model, &out, &[]);
    let t = &report["textures"][0];
    assert_eq!(t["resize"]["method"], "padded", "{t}");
    // u reaches both edges under MIRRORED_REPEAT: two added texels at
    // least, one for each side of the wrap. v clamps: one added row, a copy
    // of the last, will do.
    assert_eq!(t["resize"]["to"], serde_json::json!([216, 212]));
    assert_eq!(
        (t["width"].as_u64(), t["height"].as_u64()),
        (Some(216), Some(212))
    );

    let scale = uv_scale(&out.join("box_one_period.gltf"));
    assert!((scale[0] - 211.0 / 216.0).abs() < 1e-12, "{scale:?}");
    assert!((scale[1] - 211.0 / 212.0).abs() < 1e-12, "{scale:?}");
    let original = Rgb::png(&box_dir().join("CesiumLogoFlat.png"));
    let dds = Rgb::dds(&out.join(t["files"]["dds"].as_str().unwrap()));
    assert_eq!((dds.w, dds.h), (216, 212));
    // BC1 and the erasure's few texels: a few levels on average; without
    // the scale, the logo is sampled up to 5 texels off.
    let through = sampled_difference(&original, &dds, scale, v_range);
    let without = sampled_difference(&original, &dds, [1.0, 1.0], v_range);
    assert!(through < 3.0, "mean difference {through} levels");
    assert!(without > 2.0 * through, "{without} vs {through}");
    // The fallback PNG is padded the same way.
    let fallback = Rgb::png(&out.join(t["files"]["erased"].as_str().unwrap()));
    assert_eq!((fallback.w, fallback.h), (216, 212));
    assert!(sampled_difference(&original, &fallback, scale, v_range) < 1.0);

    let _ = std::fs::remove_dir_all(&dir);
}

/// The padded model passes the Khronos validator.
#[needs(gltf_validator)]
#[test]
fn a_padded_model_passes_the_khronos_validator() {
    let dir = scratch("padded-validator");
    let (model, _) = box_in_one_period(&dir);
    let out = dir.join("out");
    process(&model, &out, &[]);
    let verdict = common::gltf_validate(&out.join("box_one_period.gltf"));
    assert_eq!(verdict["errors"], 0, "{verdict}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pillow decodes the padded DDS to the input, within BC1 error: the
/// input's texels where they were, the padding beyond.
#[needs(python)]
#[test]
fn pillow_reads_the_padded_dds_as_the_input() {
    let dir = scratch("padded-pillow");
    let (model, _) = box_in_one_period(&dir);
    let out = dir.join("out");
    let report = process(&model, &out, &[]);
    let t = &report["textures"][0];
    let original = Rgb::png(&box_dir().join("CesiumLogoFlat.png"));
    let png = dir.join("pillow.png");
    let o = Command::new("python3")
            .args([
                "-c",
                "import sys\nfrom PIL import Image\nImage.open(sys.argv[1]).convert('RGB').save(sys.argv[2])",
            ])
            .arg(out.join(t["files"]["dds"].as_str().unwrap()))
            .arg(&png)
            .output()
            .expect("python3 runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let pillow = Rgb::png(&png);
    assert_eq!((pillow.w, pillow.h), (216, 212));
    let mut sum = 0.0;
    for y in 0..original.h {
        for x in 0..original.w {
            for c in 0..3 {
                let a = original.texels[(y * original.w + x) * 3 + c];
                let b = pillow.texels[(y * pillow.w + x) * 3 + c];
                sum += f64::from((a - b).abs());
            }
        }
    }
    let mean = sum / (original.w * original.h * 3) as f64;
    assert!(
        mean < 3.0,
        "Pillow's decode is {mean} levels off the input on average"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_tiled_texture_is_resampled_and_its_uvs_kept() {
    let dir = scratch("tiled");
    let out = dir.join("out");
    let report = process(&box_dir().join("BoxTextured.gltf"), &out, &[]);
    let t = &report["textures"][0];
    assert_eq!(t["resize"]["method"], "resampled", "{t}");
    assert_eq!(t["resize"]["to"], serde_json::json!([212, 212]));
    assert!(t["resize"].get("uv_scale").is_none());
    let g: Value =
        serde_json::from_slice(&std::fs::read(out.join("BoxTextured.gltf")).unwrap()).unwrap();
    assert!(
        g["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]
            .get("extensions")
            .is_none()
    );
    let original = Rgb::png(&box_dir().join("CesiumLogoFlat.png"));
    let dds = Rgb::dds(&out.join(t["files"]["dds"].as_str().unwrap()));
    assert!(sampled_difference(&original, &dds, [1.0, 1.0], [0.0, 1.0]) < 4.0);

    let none = dir.join("none");
    let report = process(
        &box_dir().join("BoxTextured.gltf"),
        &none,
        &["--resize", "none"],
    );
    assert!(report["textures"][0].get("resize").is_none());
    assert_eq!(report["textures"][0]["width"], 211);
    let pow2 = dir.join("pow2");
    let report = process(
        &box_dir().join("BoxTextured.gltf"),
        &pow2,
        &["--resize", "pow2"],
    );
    assert_eq!(
        report["textures"][0]["resize"]["to"],
        serde_json::json!([256, 256])
    );
    let _ = std::fs::remove_dir_all(&dir);
}
