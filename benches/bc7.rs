//! BC7 benchmark: our three levels against intel_tex_2 (Intel's ISPC BC7
//! kernel) at its ultra_fast, very_fast, basic and slow settings (the
//! `alpha_*` ones for textures with alpha, else `opaque_*`).
//!
//! Every result is decoded by `seamstress::bc7` and scored by PSNR over the
//! RGB channels (RGBA for textures with alpha) against the 8-bit source.
//! Speed is source MPix/s on one thread (a 1-thread rayon pool; intel_tex_2
//! is single-threaded per call), the best of a few runs.
//!
//! Images: the shared models' base-colour textures (Fox, Duck, blub,
//! CesiumMan, WaterBottle), cropped to their central `BC7_BENCH_CROP`²
//! texels (default 512; 0 keeps the whole texture), and Duck-alpha: Duck's
//! crop with an alpha channel made from CesiumMan's.
//!
//! Then seam-aware BC7 on the models' erased textures (the engine's PNG
//! output): seam_rms (8-bit levels, over the seams of the first texture's
//! triangles along which the erased texture agrees to within a level:
//! those the erasure closed) and PSNR over the texels inside the UV charts, of
//! the regular encoding and of the seam-aware one, with the default
//! options of `bc1::seam_aware`.
//!
//! Knobs: `BC7_BENCH_ONLY=fox,duck` (image names), `BC7_BENCH_ENCODERS=
//! fast,default,best,ispc-ultra,ispc-veryfast,ispc-basic,ispc-slow`,
//! `BC7_BENCH_SEAMS=0` (skip the seam-aware rows), `SHARED_DIR` (default
//! `/work/shared`).
//!
//! Run: `cargo bench --bench bc7`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use base64::Engine as _;
use seamstress::bc7::{self, Block, EncodeOptions, Level};

// intel_tex_2's static library is C++ and needs the C++ runtime.
#[link(name = "stdc++")]
extern "C" {}

struct Image {
    name: String,
    width: usize,
    height: usize,
    rgba: Vec<u8>,
    alpha: bool,
}

fn glb_chunks(bytes: &[u8]) -> Option<(&[u8], Option<&[u8]>)> {
    if bytes.len() < 20 || &bytes[0..4] != b"glTF" {
        return None;
    }
    let u32_at = |o: usize| -> Option<usize> {
        Some(u32::from_le_bytes(bytes.get(o..o + 4)?.try_into().ok()?) as usize)
    };
    let jlen = u32_at(12)?;
    let json = bytes.get(20..20 + jlen)?;
    let bin = u32_at(20 + jlen).and_then(|blen| bytes.get(28 + jlen..28 + jlen + blen));
    Some((json, bin))
}

fn data_uri(uri: &str) -> Option<Vec<u8>> {
    let (_, b64) = uri.strip_prefix("data:")?.split_once(";base64,")?;
    base64::engine::general_purpose::STANDARD.decode(b64).ok()
}

/// The encoded bytes of `images[0]` of a .gltf (data URIs or files) or .glb.
fn gltf_image0(path: &Path) -> Result<Vec<u8>, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let (json, bin) = glb_chunks(&bytes).unwrap_or((&bytes[..], None));
    let doc: serde_json::Value = serde_json::from_slice(json).map_err(|e| e.to_string())?;
    let img = &doc["images"][0];
    if let Some(uri) = img["uri"].as_str() {
        if let Some(d) = data_uri(uri) {
            return Ok(d);
        }
        let p = path.parent().unwrap_or(Path::new(".")).join(uri);
        return std::fs::read(&p).map_err(|e| format!("{}: {e}", p.display()));
    }
    let bv = &doc["bufferViews"][img["bufferView"].as_u64().ok_or("image has no source")? as usize];
    let off = bv["byteOffset"].as_u64().unwrap_or(0) as usize;
    let len = bv["byteLength"]
        .as_u64()
        .ok_or("bufferView without length")? as usize;
    let buf = &doc["buffers"][bv["buffer"].as_u64().unwrap_or(0) as usize];
    let data = match buf["uri"].as_str() {
        Some(uri) => data_uri(uri).ok_or("external buffers not supported here")?,
        None => bin.ok_or("no BIN chunk")?.to_vec(),
    };
    data.get(off..off + len)
        .map(<[u8]>::to_vec)
        .ok_or_else(|| "bufferView out of range".to_string())
}

fn decode(name: &str, bytes: &[u8], crop: usize) -> Result<Image, String> {
    let img = image::load_from_memory(bytes)
        .map_err(|e| format!("{name}: {e}"))?
        .to_rgba8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (cw, ch) = if crop == 0 {
        (w, h)
    } else {
        (crop.min(w), crop.min(h))
    };
    let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
    let mut rgba = Vec::with_capacity(cw * ch * 4);
    for y in y0..y0 + ch {
        rgba.extend_from_slice(&img.as_raw()[(y * w + x0) * 4..(y * w + x0 + cw) * 4]);
    }
    let alpha = bc7::has_alpha(&rgba);
    Ok(Image {
        name: name.to_string(),
        width: cw,
        height: ch,
        rgba,
        alpha,
    })
}

fn load_images() -> Vec<Image> {
    let shared =
        PathBuf::from(std::env::var("SHARED_DIR").unwrap_or_else(|_| "/work/shared".into()));
    let crop = std::env::var("BC7_BENCH_CROP")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(512);
    let mut images = Vec::new();
    for (name, rel) in [
        ("Fox", "assets/Fox/Fox.gltf"),
        ("Duck", "assets/Duck/Duck.gltf"),
        ("blub", "assets/blub/blub.glb"),
        ("CesiumMan", "assets/CesiumMan/CesiumMan.gltf"),
        ("WaterBottle", "assets/WaterBottle/WaterBottle.gltf"),
    ] {
        let path = shared.join(rel);
        match gltf_image0(&path).and_then(|b| decode(name, &b, crop)) {
            Ok(img) => images.push(img),
            Err(e) => println!("skipping {name}: {e}"),
        }
    }
    // No shared base colour has alpha: Duck's takes CesiumMan's red as
    // alpha, cut to 0 below 60 (hard cut-out edges beside soft ramps).
    let duck = images.iter().find(|i| i.name == "Duck");
    let cesium = images.iter().find(|i| i.name == "CesiumMan");
    if let (Some(d), Some(c)) = (duck, cesium) {
        if (d.width, d.height) == (c.width, c.height) {
            let mut rgba = d.rgba.clone();
            for (t, s) in rgba.chunks_exact_mut(4).zip(c.rgba.chunks_exact(4)) {
                t[3] = if s[0] < 60 { 0 } else { s[0] };
            }
            images.push(Image {
                name: "Duck-alpha".into(),
                width: d.width,
                height: d.height,
                alpha: bc7::has_alpha(&rgba),
                rgba,
            });
        }
    }
    if let Ok(only) = std::env::var("BC7_BENCH_ONLY") {
        let keep: Vec<String> = only.split(',').map(|s| s.trim().to_lowercase()).collect();
        images.retain(|i| keep.contains(&i.name.to_lowercase()));
    }
    images
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Encoder {
    Ours(Level),
    Ispc(&'static str),
}

impl Encoder {
    const ALL: [Encoder; 7] = [
        Encoder::Ours(Level::Fast),
        Encoder::Ours(Level::Default),
        Encoder::Ours(Level::Best),
        Encoder::Ispc("ultra"),
        Encoder::Ispc("veryfast"),
        Encoder::Ispc("basic"),
        Encoder::Ispc("slow"),
    ];

    fn key(self) -> String {
        match self {
            Encoder::Ours(l) => l.name().into(),
            Encoder::Ispc(s) => format!("ispc-{s}"),
        }
    }

    fn label(self) -> String {
        match self {
            Encoder::Ours(l) => format!("seamstress {l}"),
            Encoder::Ispc(s) => format!("intel_tex_2 {s}"),
        }
    }
}

fn ispc_settings(name: &str, alpha: bool) -> intel_tex_2::bc7::EncodeSettings {
    use intel_tex_2::bc7::*;
    match (name, alpha) {
        ("ultra", false) => opaque_ultra_fast_settings(),
        ("ultra", true) => alpha_ultra_fast_settings(),
        ("veryfast", false) => opaque_very_fast_settings(),
        ("veryfast", true) => alpha_very_fast_settings(),
        ("basic", false) => opaque_basic_settings(),
        ("basic", true) => alpha_basic_settings(),
        (_, false) => opaque_slow_settings(),
        (_, true) => alpha_slow_settings(),
    }
}

/// Pads to whole blocks by edge replication, for intel_tex_2.
fn padded(img: &Image) -> (usize, usize, Vec<u8>) {
    let (pw, ph) = (img.width.div_ceil(4) * 4, img.height.div_ceil(4) * 4);
    let mut out = vec![0u8; pw * ph * 4];
    for y in 0..ph {
        for x in 0..pw {
            let s = (y.min(img.height - 1) * img.width + x.min(img.width - 1)) * 4;
            out[(y * pw + x) * 4..(y * pw + x) * 4 + 4].copy_from_slice(&img.rgba[s..s + 4]);
        }
    }
    (pw, ph, out)
}

fn encode(enc: Encoder, img: &Image) -> Vec<Block> {
    match enc {
        Encoder::Ours(level) => {
            let opts = EncodeOptions::for_image(level, &img.rgba);
            bc7::encode_image(&img.rgba, img.width, img.height, &opts).expect("valid image")
        }
        Encoder::Ispc(name) => {
            let (pw, ph, data) = padded(img);
            let surface = intel_tex_2::RgbaSurface {
                data: &data,
                width: pw as u32,
                height: ph as u32,
                stride: (pw * 4) as u32,
            };
            intel_tex_2::bc7::compress_blocks(&ispc_settings(name, img.alpha), &surface)
                .chunks_exact(16)
                .map(|c| Block(c.try_into().expect("16 bytes")))
                .collect()
        }
    }
}

/// The engine's erased PNG of the model's first texture.
fn erased_png(path: &Path) -> Result<Vec<u8>, String> {
    use seamstress::model::{self, LoadOptions};
    use seamstress::pipeline::{self, Format, ProcessOptions};
    let m = model::load(path, &LoadOptions::default()).map_err(|e| e.to_string())?;
    let opts = ProcessOptions {
        format: Format::Png,
        ..ProcessOptions::default()
    };
    let out = pipeline::run(&m, "model", 0, &opts).map_err(|e| e.to_string())?;
    out.files
        .into_iter()
        .find(|f| f.name.ends_with(".erased.png"))
        .map(|f| f.bytes)
        .ok_or_else(|| "no erased texture".to_string())
}

/// seam_rms in 8-bit levels: the root of the seam energy per unit of seam
/// weight and channel.
fn seam_rms(
    dec: &[u8],
    points: &[seamstress::seam::quadrature::QuadPoint],
    channels: usize,
) -> f64 {
    let (mut e, mut w) = (0.0, 0.0);
    for q in points {
        for c in 0..channels {
            let v: f64 = q
                .taps
                .iter()
                .map(|&(t, cw)| cw * f64::from(dec[t as usize * 4 + c]))
                .sum();
            e += q.weight * v * v;
        }
        w += q.weight * channels as f64;
    }
    if w > 0.0 {
        (e / w).sqrt()
    } else {
        0.0
    }
}

/// PSNR over the RGB(A) of the texels inside the charts.
fn psnr_inside(a: &[u8], b: &[u8], inside: &[bool], channels: usize) -> f64 {
    let (mut se, mut n) = (0.0, 0usize);
    for (t, _) in inside.iter().enumerate().filter(|(_, i)| **i) {
        for c in 0..channels {
            let d = f64::from(a[t * 4 + c]) - f64::from(b[t * 4 + c]);
            se += d * d;
            n += 1;
        }
    }
    10.0 * (255.0 * 255.0 * n as f64 / se.max(1e-12)).log10()
}

fn seam_rows(shared: &Path) {
    use seamstress::bc7::seam_aware::{optimise, Problem, SeamAwareOptions};
    use seamstress::model::{self, seams::find_seams, LoadOptions};
    use seamstress::seam::{
        grid::TexelGrid, metric::seam_points_texel_length, texels::inside_mask,
    };
    println!(
        "\nseam-aware BC7 on the erased textures (seam_rms in 8-bit levels over the closed seams)"
    );
    println!(
        "{:<12} {:>9} {:<8} {:>7} {:>8} {:>9} {:>9} {:>9} {:>8} {:>7}",
        "model", "size", "level", "blocks", "rms", "rms_sa", "dB", "dB_sa", "sa ms", "sweeps"
    );
    let only = std::env::var("BC7_BENCH_ONLY")
        .ok()
        .map(|v| v.to_lowercase());
    for (name, rel) in [
        ("Fox", "assets/Fox/Fox.gltf"),
        ("Duck", "assets/Duck/Duck.gltf"),
        ("blub", "assets/blub/blub.glb"),
        ("CesiumMan", "assets/CesiumMan/CesiumMan.gltf"),
    ] {
        if only
            .as_ref()
            .is_some_and(|o| !o.split(',').any(|n| n.trim() == name.to_lowercase()))
        {
            continue;
        }
        let path = shared.join(rel);
        let loaded = model::load(&path, &LoadOptions::default()).map_err(|e| e.to_string());
        let img = erased_png(&path).and_then(|png| decode(name, &png, 0));
        let (m, img) = match (loaded, img) {
            (Ok(m), Ok(img)) => (m, img),
            (Err(e), _) | (_, Err(e)) => {
                println!("skipping {name}: {e}");
                continue;
            }
        };
        let Some(b) = m.bindings.first() else {
            continue;
        };
        let (w, h) = (img.width, img.height);
        let grid = TexelGrid {
            width: w,
            height: h,
            wrap_s: b.wrap_s,
            wrap_t: b.wrap_t,
        };
        // The seams the erasure closed: those along which the erased
        // texture agrees to within a level (the rest it left open, as
        // painted apart).
        let all = seam_points_texel_length(&grid, &find_seams(&b.triangles, w, h));
        let points: Vec<_> = all
            .into_iter()
            .filter(|q| {
                (0..3).all(|c| {
                    let v: f64 = q
                        .taps
                        .iter()
                        .map(|&(t, cw)| cw * f64::from(img.rgba[t as usize * 4 + c]))
                        .sum();
                    v.abs() <= 1.0
                })
            })
            .collect();
        let inside = inside_mask(&grid, &b.triangles);
        let rgb: Vec<f32> = img
            .rgba
            .chunks_exact(4)
            .flat_map(|t| [t[0], t[1], t[2]].map(|v| f32::from(v) / 255.0))
            .collect();
        let alpha: Vec<f32> = img
            .rgba
            .chunks_exact(4)
            .map(|t| f32::from(t[3]) / 255.0)
            .collect();
        let channels = if img.alpha { 4 } else { 3 };
        for level in [Level::Fast, Level::Default] {
            let opts = EncodeOptions::for_image(level, &img.rgba);
            let regular = bc7::encode_image(&img.rgba, w, h, &opts).expect("valid image");
            let problem = Problem {
                width: w,
                height: h,
                rgb: &rgb,
                alpha: img.alpha.then_some(&alpha[..]),
                inside: &inside,
                points: &points,
                alpha_points: None,
                level,
            };
            let mut blocks = regular.clone();
            let t = Instant::now();
            let stats = optimise(&problem, &mut blocks, &SeamAwareOptions::default())
                .expect("seam-aware BC7 runs");
            let ms = t.elapsed().as_secs_f64() * 1e3;
            let d0 = bc7::decode_image(&regular, w, h).expect("block count");
            let d1 = bc7::decode_image(&blocks, w, h).expect("block count");
            println!(
                "{:<12} {:>9} {:<8} {:>7} {:>8.3} {:>9.3} {:>9.2} {:>9.2} {:>8.0} {:>7}",
                name,
                format!("{w}x{h}"),
                level.name(),
                stats.blocks,
                seam_rms(&d0, &points, channels),
                seam_rms(&d1, &points, channels),
                psnr_inside(&img.rgba, &d0, &inside, channels),
                psnr_inside(&img.rgba, &d1, &inside, channels),
                ms,
                stats.sweeps
            );
        }
    }
}

fn main() {
    let images = load_images();
    let wanted: Vec<Encoder> = match std::env::var("BC7_BENCH_ENCODERS") {
        Ok(list) => {
            let keys: Vec<String> = list.split(',').map(|s| s.trim().to_lowercase()).collect();
            Encoder::ALL
                .into_iter()
                .filter(|e| keys.contains(&e.key()))
                .collect()
        }
        Err(_) => Encoder::ALL.to_vec(),
    };
    let pool1 = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a 1-thread pool");
    println!(
        "{:<14} {:>9} {:<22} {:>9} {:>11}  modes 0-7 (% of blocks)",
        "image", "size", "encoder", "PSNR dB", "MPix/s/thr"
    );
    for img in &images {
        let channels = if img.alpha { 0..4 } else { 0..3 };
        for &enc in &wanted {
            let mut best = f64::MAX;
            let mut blocks = Vec::new();
            let start = Instant::now();
            while blocks.is_empty() || (start.elapsed().as_secs_f64() < 1.0 && best < 0.3) {
                let t = Instant::now();
                blocks = pool1.install(|| encode(enc, img));
                best = best.min(t.elapsed().as_secs_f64());
            }
            let dec = bc7::decode_image(&blocks, img.width, img.height).expect("block count");
            let psnr = bc7::psnr(&img.rgba, &dec, channels.clone()).expect("same size");
            let mpix = (img.width * img.height) as f64 / best / 1e6;
            let mut modes = [0usize; 8];
            for b in &blocks {
                if let Some(m) = b.mode() {
                    modes[usize::from(m)] += 1;
                }
            }
            let share: Vec<String> = modes
                .iter()
                .map(|&n| format!("{:>3.0}", 100.0 * n as f64 / blocks.len() as f64))
                .collect();
            println!(
                "{:<14} {:>9} {:<22} {:>9.3} {:>11.3}  {}",
                img.name,
                format!("{}x{}", img.width, img.height),
                enc.label(),
                psnr,
                mpix,
                share.join(" ")
            );
        }
    }
    if std::env::var("BC7_BENCH_SEAMS").as_deref() != Ok("0") {
        let shared =
            PathBuf::from(std::env::var("SHARED_DIR").unwrap_or_else(|_| "/work/shared".into()));
        seam_rows(&shared);
    }
}
