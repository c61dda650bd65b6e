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
//! texels (default 512; 0 keeps the whole texture).
//!
//! Knobs: `BC7_BENCH_ONLY=fox,duck` (image names), `BC7_BENCH_ENCODERS=
//! fast,default,best,ispc-ultra,ispc-veryfast,ispc-basic,ispc-slow`,
//! `SHARED_DIR` (default `/work/shared`).
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
                format!("{}{}", img.name, if img.alpha { "+a" } else { "" }),
                format!("{}x{}", img.width, img.height),
                enc.label(),
                psnr,
                mpix,
                share.join(" ")
            );
        }
    }
}
