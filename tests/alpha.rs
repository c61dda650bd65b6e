//! Alpha kept: Duck (whose texture has an alpha channel, all opaque) with
//! alpha painted in and its material made `MASK` or `BLEND`.

use std::path::{Path, PathBuf};
use std::process::Command;

use base64::Engine;
use serde_json::Value;

use seamstress::bc1::alpha::decode_alpha_image;
use seamstress::bc1::dds::read_dds;
use seamstress::bc1::punch::punch_alpha;
use seamstress::bc1::{decode_image_with, Decoder};

mod common;
use needs::needs;

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-alpha-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Duck with `alpha(x, y, rgb)` (0–255) painted into its texture, written
/// beside a copy of the model whose material has `mode` (and `cutoff`).
fn alpha_duck(
    dir: &Path,
    mode: &str,
    cutoff: Option<f64>,
    alpha: impl Fn(u32, u32, [u8; 3]) -> u8,
) -> PathBuf {
    let shared = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets");
    let mut g: Value =
        serde_json::from_slice(&std::fs::read(shared.join("Duck/Duck.gltf")).unwrap()).unwrap();
    let uri = g["images"][0]["uri"].as_str().unwrap().to_string();
    let png = base64::engine::general_purpose::STANDARD
        .decode(uri.split_once(',').unwrap().1)
        .unwrap();
    let mut img = image::load_from_memory(&png).unwrap().to_rgba8();
    for (x, y, px) in img.enumerate_pixels_mut() {
        px.0[3] = alpha(x, y, [px.0[0], px.0[1], px.0[2]]);
    }
    img.save(dir.join("duck_alpha.png")).unwrap();
    g["images"][0] = serde_json::json!({"uri": "duck_alpha.png"});
    g["materials"][0]["alphaMode"] = Value::from(mode);
    if let Some(c) = cutoff {
        g["materials"][0]["alphaCutoff"] = Value::from(c);
    }
    let path = dir.join(format!("duck_{}.gltf", mode.to_lowercase()));
    std::fs::write(&path, serde_json::to_vec(&g).unwrap()).unwrap();
    path
}

/// A scratch folder, and in it the output of the default run on
/// [`alpha_duck`]'s model.
fn processed_duck(
    tag: &str,
    mode: &str,
    cutoff: Option<f64>,
    alpha: impl Fn(u32, u32, [u8; 3]) -> u8,
) -> (PathBuf, PathBuf) {
    let dir = scratch(tag);
    let model = alpha_duck(&dir, mode, cutoff, alpha);
    let out = dir.join("out");
    process(&model, &out, &[]);
    (dir, out)
}

fn process(model: &Path, out: &Path, extra: &[&str]) -> Value {
    common::process_report(model, out, extra)
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

/// Colour seams close as far as Duck's opaque texture's do: over the seams
/// closed, the seam-aware DDS at most 0.4× the regular encoding's seam_rms
/// under every decoder.
fn colour_seams_closed(t: &Value) {
    for d in ["ideal", "nvidia", "amd"] {
        let regular = f(&t["bc1"]["decoders"][d]["seam_rms_closed"]);
        let aware = f(&t["bc1_seam_aware"]["decoders"][d]["seam_rms_closed"]);
        assert!(aware <= 0.4 * regular, "{d}: {aware} vs regular {regular}");
    }
}

/// Holes: round cut-outs on a grid, with soft (anti-aliased) rims.
fn holes(x: u32, y: u32) -> u8 {
    let (cx, cy) = ((x % 64) as f64 - 32.0, (y % 64) as f64 - 32.0);
    let r = (cx * cx + cy * cy).sqrt();
    ((r - 10.0) * 64.0).clamp(0.0, 255.0) as u8
}

#[test]
fn a_mask_keeps_every_texels_opacity_in_one_bit_alpha() {
    let dir = scratch("mask");
    let model = alpha_duck(&dir, "MASK", Some(0.5), |x, y, _| holes(x, y));
    let out = dir.join("out");
    let report = process(&model, &out, &[]);
    let t = &report["textures"][0];
    let a = &t["alpha"];
    assert_eq!(a["format"], "bc1a", "{a}");
    assert_eq!(a["material"]["mode"], "mask");
    assert_eq!(a["erased_seams"], false);
    // Erasure leaves a mask's alpha as painted.
    assert_eq!(a["erased"]["psnr"], Value::Null, "{a}");
    for d in ["ideal", "nvidia", "amd"] {
        assert_eq!(a["dds"][d]["opacity_changes"], 0, "{d}: {a}");
    }
    colour_seams_closed(t);

    // The DDS's transparent texels are exactly the input's under the cutoff.
    let dds = read_dds(&std::fs::read(out.join("duck_alpha.dds")).unwrap()).unwrap();
    let l = &dds.levels[0];
    assert!(l.alpha.is_empty(), "BC1, not BC3");
    let (w, h) = (l.width as usize, l.height as usize);
    let ours = punch_alpha(&l.blocks, w, h);
    let clear = (0..w * h)
        .filter(|&t| (holes((t % w) as u32, (t / w) as u32) as f32) < 0.5 * 255.0)
        .count();
    assert!(clear > w * h / 20, "the holes cover {clear} texels");
    for (t, &v) in ours.iter().enumerate() {
        let want = if (holes((t % w) as u32, (t / w) as u32) as f32) < 0.5 * 255.0 {
            0.0
        } else {
            1.0
        };
        assert_eq!(v, want, "texel {t}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pillow and texture2ddecoder read the `MASK` DDS (BC1 with one-bit
/// alpha) as our decoders do.
#[needs(texture2ddecoder)]
#[test]
fn outside_readers_read_a_mask_dds_as_we_do() {
    let (dir, out) = processed_duck("mask-readers", "MASK", Some(0.5), |x, y, _| holes(x, y));
    let dds = read_dds(&std::fs::read(out.join("duck_alpha.dds")).unwrap()).unwrap();
    let l = &dds.levels[0];
    let (w, h) = (l.width as usize, l.height as usize);
    let ours = punch_alpha(&l.blocks, w, h);
    readers_agree(&out.join("duck_alpha.dds"), &dir, |d| {
        let rgb = decode_image_with(&l.blocks, w, h, d).unwrap();
        (rgb, ours.clone())
    });
    let _ = std::fs::remove_dir_all(&dir);
}

/// Soft alpha painted as the colour is (so it agrees across the seams as
/// far as the colour does): from the texel's luminance.
fn from_luminance(rgb: [u8; 3]) -> u8 {
    let l = 0.3 * f64::from(rgb[0]) + 0.59 * f64::from(rgb[1]) + 0.11 * f64::from(rgb[2]);
    (64.0 + 0.7 * l).round() as u8
}

/// A decal's transparency painted as a smooth field over texture space, so
/// that the two sides of a seam read alpha up to 200 levels apart while
/// the colour agrees.
fn alpha_apart(x: u32, _: u32, _: [u8; 3]) -> u8 {
    let phase = std::f64::consts::TAU * 3.0 * f64::from(x) / 512.0;
    (128.0 + 100.0 * phase.sin()).round() as u8
}

/// Alpha painted apart across the seams, colour agreeing: seams are judged
/// per channel group, so the colour seams close as on the opaque Duck while
/// the alpha seams painted apart keep their alpha, and nothing is
/// repainted.
#[test]
fn alpha_painted_apart_stays_as_painted_while_the_colour_closes() {
    let dir = scratch("alpha-apart");
    let model = alpha_duck(&dir, "BLEND", None, alpha_apart);
    let out = dir.join("out");
    let report = process(&model, &out, &[]);
    let t = &report["textures"][0];
    let a = &t["alpha"];
    eprintln!("seams {}\nalpha {a}", t["seams"]);
    assert_eq!(a["format"], "bc3", "{a}");
    let alpha_seams = &t["seams"]["alpha"];
    assert!(
        alpha_seams["left"]["edges"].as_u64().unwrap() > 0,
        "{}",
        t["seams"]
    );
    assert!(
        alpha_seams["left"]["edges"].as_u64() > t["seams"]["left"]["edges"].as_u64(),
        "alpha leaves the seams its sides are painted apart on: {}",
        t["seams"]
    );
    let psnr = f(&a["erased"]["psnr"]);
    assert!(psnr >= 40.0, "alpha repainted to {psnr} dB");
    // No chart's alpha falls under 30 dB either.
    assert_eq!(a["erased"]["charts_under_30db"], 0, "{a}");
    assert!(f(&a["erased"]["worst_chart_psnr"]) >= 30.0, "{a}");
    for d in ["ideal", "nvidia", "amd"] {
        assert!(f(&a["dds"][d]["psnr"]) >= 40.0, "{d}: {a}");
    }
    let colour = f(&t["erased"]["seam_rms_closed"]);
    assert!(colour <= 0.3, "colour seams closed to {colour}");
    colour_seams_closed(t);
    assert!(
        report["warnings"].as_array().unwrap().is_empty(),
        "{}",
        report["warnings"]
    );

    // --erase-all forces the alpha together too: said, with the figure.
    let all = process(&model, &dir.join("all"), &["--erase-all"]);
    let t = &all["textures"][0];
    let psnr = f(&t["alpha"]["erased"]["psnr"]);
    assert!(
        psnr < 40.0,
        "alpha kept at {psnr} dB with every seam closed"
    );
    let name = t["name"].as_str().unwrap();
    let warnings: Vec<&str> = all["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| w.as_str().unwrap())
        .collect();
    assert!(
        warnings.iter().any(|w| w.contains(name)
            && w.contains("its alpha")
            && w.contains(&format!("{psnr:.1} dB"))),
        "{warnings:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_blend_gets_bc3_with_its_alpha_seams_closed() {
    let dir = scratch("blend");
    let model = alpha_duck(&dir, "BLEND", None, |_, _, rgb| from_luminance(rgb));
    let out = dir.join("out");
    let report = process(&model, &out, &[]);
    let t = &report["textures"][0];
    let a = &t["alpha"];
    eprintln!("seams {}\nalpha {a}", t["seams"]);
    assert_eq!(a["format"], "bc3", "{a}");
    assert_eq!(a["erased_seams"], true);
    // Painted as the colour is, alpha agrees where the colour does: at most
    // 0.3 levels apart over the seams it closes once erased.
    assert!(f(&a["erased"]["seam_rms_closed"]) <= 0.3, "{a}");
    // Over the seams closed (those whose colours are painted apart are left,
    // alpha with them).
    let input = f(&a["input"]["seam_rms_closed"]);
    let erased = f(&a["erased"]["seam_rms_closed"]);
    assert!(
        erased < 0.2 * input,
        "alpha seams: input {input}, erased {erased}"
    );
    for d in ["ideal", "nvidia", "amd"] {
        let regular = f(&a["regular"][d]["seam_rms_closed"]);
        let aware = f(&a["dds"][d]["seam_rms_closed"]);
        assert!(
            aware <= 0.6 * regular,
            "{d}: alpha seam_rms {aware} vs regular {regular}"
        );
        assert!(f(&a["dds"][d]["psnr"]) >= 40.0, "{d}: {a}");
        assert!(f(&a["dds"][d]["encoding_psnr"]) >= 40.0, "{d}: {a}");
    }
    colour_seams_closed(t);
    let dds = read_dds(&std::fs::read(out.join("duck_alpha.dds")).unwrap()).unwrap();
    let l = &dds.levels[0];
    assert_eq!(l.alpha.len(), l.blocks.len(), "BC3");
    // Opaque materials keep the image's alpha, unerased; --alpha drop drops it.
    let dropped = process(&model, &dir.join("drop"), &["--alpha", "drop"]);
    assert_eq!(dropped["textures"][0]["alpha"]["format"], "dropped");
    assert!(dropped["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .any(|w| w.as_str().unwrap().contains("alpha")));
    let _ = std::fs::remove_dir_all(&dir);
}

/// BC7 keeps a blended alpha in its own blocks, closed along alpha's own
/// seams as BC3's is, and exactly as every GPU decodes it.
#[test]
fn a_blend_in_bc7_keeps_its_alpha_seams_closed() {
    let dir = scratch("blend-bc7");
    let model = alpha_duck(&dir, "BLEND", None, |_, _, rgb| from_luminance(rgb));
    let report = process(&model, &dir.join("out"), &["--format", "bc7", "--no-mips"]);
    let t = &report["textures"][0];
    let a = &t["alpha"];
    eprintln!("alpha {a}");
    assert_eq!(a["format"], "bc7", "{a}");
    let regular = f(&a["regular"]["exact"]["seam_rms_closed"]);
    let aware = f(&a["dds"]["exact"]["seam_rms_closed"]);
    assert!(
        aware <= 0.6 * regular,
        "alpha seam_rms {aware} vs regular {regular}"
    );
    assert!(f(&a["dds"]["exact"]["psnr"]) >= 40.0, "{a}");
    let colour = f(&t["bc7_seam_aware"]["seam_rms_closed"]);
    assert!(colour <= 0.3, "colour seams at {colour} in the BC7 file");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pillow and texture2ddecoder read the `BLEND` DDS (BC3) as our decoders
/// do.
#[needs(texture2ddecoder)]
#[test]
fn outside_readers_read_a_blend_dds_as_we_do() {
    let (dir, out) = processed_duck("blend-readers", "BLEND", None, |_, _, rgb| {
        from_luminance(rgb)
    });
    let dds = read_dds(&std::fs::read(out.join("duck_alpha.dds")).unwrap()).unwrap();
    let l = &dds.levels[0];
    let (w, h) = (l.width as usize, l.height as usize);
    readers_agree(&out.join("duck_alpha.dds"), &dir, |d| {
        let rgb = decode_image_with(&l.blocks, w, h, d).unwrap();
        (rgb, decode_alpha_image(&l.alpha, w, h, d))
    });
    let _ = std::fs::remove_dir_all(&dir);
}

/// The `BLEND` model rewritten passes the Khronos validator.
#[needs(gltf_validator)]
#[test]
fn a_blend_model_rewritten_passes_the_khronos_validator() {
    let (dir, out) = processed_duck("blend-validator", "BLEND", None, |_, _, rgb| {
        from_luminance(rgb)
    });
    let verdict = common::gltf_validate(&out.join("duck_blend.gltf"));
    assert_eq!(verdict["errors"], 0, "{verdict}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pillow and texture2ddecoder decode the DDS to the texels our decoder
/// gives (`ours(decoder)`: RGB and alpha in [0, 1]) under some decoder.
fn readers_agree(dds: &Path, dir: &Path, ours: impl Fn(Decoder) -> (Vec<f32>, Vec<f32>)) {
    if !common::TEXTURE2DDECODER.available() {
        return;
    }
    let script = r#"
import sys, texture2ddecoder
from PIL import Image
data = open(sys.argv[1], 'rb').read()
h = int.from_bytes(data[12:16], 'little'); w = int.from_bytes(data[16:20], 'little')
four = data[84:88]
blocks = data[128:]
n = ((w + 3) // 4) * ((h + 3) // 4) * (16 if four == b'DXT5' else 8)
dec = texture2ddecoder.decode_bc3 if four == b'DXT5' else texture2ddecoder.decode_bc1
bgra = dec(blocks[:n], w, h)
img = Image.frombytes('RGBA', (w, h), bgra, 'raw', 'BGRA')
open(sys.argv[2], 'wb').write(img.tobytes())
pil = Image.open(sys.argv[1]).convert('RGBA')
open(sys.argv[3], 'wb').write(pil.tobytes())
"#;
    let (t2d, pil) = (dir.join("t2d.rgba"), dir.join("pil.rgba"));
    let o = Command::new("python3")
        .args(["-c", script])
        .arg(dds)
        .arg(&t2d)
        .arg(&pil)
        .output()
        .expect("python3 runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bc1 = std::fs::read(dds).unwrap()[84..88] == *b"DXT1";
    for (reader, path) in [("texture2ddecoder", &t2d), ("Pillow", &pil)] {
        let theirs = std::fs::read(path).unwrap();
        // texture2ddecoder decodes BC1's transparent index as opaque black.
        let alpha_known = !(bc1 && reader == "texture2ddecoder");
        // Readers round the interpolated entries one way or another: the
        // best-matching of our decoders must agree within a level.
        let best = Decoder::ALL
            .into_iter()
            .map(|d| {
                let (rgb, alpha) = ours(d);
                let n = alpha.len();
                let mut worst = 0.0f32;
                for t in 0..n {
                    let px = &theirs[t * 4..t * 4 + 4];
                    let a = alpha[t] * 255.0;
                    if alpha_known {
                        worst = worst.max((f32::from(px[3]) - a).abs());
                    }
                    if a > 0.0 {
                        for c in 0..3 {
                            worst = worst.max((f32::from(px[c]) - rgb[t * 3 + c] * 255.0).abs());
                        }
                    }
                }
                (d, worst)
            })
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(
            best.1 <= 1.0,
            "{reader}: off by {} levels at best ({:?})",
            best.1,
            best.0
        );
    }
}
