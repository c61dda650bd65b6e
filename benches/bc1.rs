//! BC1 comparison benchmark: our three levels against intel_tex_2 (Intel's
//! ISPC encoder), texpresso (libsquish's cluster fit) and quicktex (an
//! rgbcx-derived encoder, levels 10 and 18, through
//! `benches/bc1_quicktex.py`).
//!
//! Every encoder gets the same edge-replicated padded image; every result is
//! decoded by `seamstress::bc1` (exact float palette) and scored by RGB PSNR
//! over the unpadded texels against the 8-bit source. Speed is source
//! MPix/s, the best of several runs, on one thread (a 1-thread rayon pool)
//! and on all threads (the global pool). Slow encoders are timed on one
//! thread over an evenly spread subset of block rows.
//!
//! Images: the shared models' textures (Fox, blub, Duck), the photo
//! `skimage/data/astronaut.png` from the PyPI package scikit-image (skipped
//! when the package is not installed; `BC1_BENCH_PHOTO=path.png` overrides),
//! the engine's erased texture of `cube_gradient_1024.glb` (a smooth baked
//! atlas), and any PNGs listed in `BC1_BENCH_EXTRA` (comma-separated).
//!
//! Other knobs: `BC1_BENCH_ONLY=fox,duck` (image names), `BC1_BENCH_ENCODERS=
//! fast,default,best,ispc,texpresso,quicktex10,quicktex18`, `SHARED_DIR`
//! (default `/work/shared`), `PYTHON` (default `python3`).
//!
//! Run: `cargo bench --bench bc1`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use base64::Engine as _;
use rayon::prelude::*;
use seamstress::bc1::{self, Block, Level};

// intel_tex_2's static library is C++ and needs the C++ runtime.
#[link(name = "stdc++")]
extern "C" {}

struct Image {
    name: String,
    origin: String,
    width: usize,
    height: usize,
    /// Unpadded RGB in [0,1].
    rgb: Vec<f32>,
    /// Padded to multiples of 4 by edge replication.
    pw: usize,
    ph: usize,
    rgba8: Vec<u8>,
    rgbf: Vec<f32>,
}

impl Image {
    fn from_rgb8(name: &str, origin: String, width: usize, height: usize, px: &[u8]) -> Image {
        let rgb: Vec<f32> = px.iter().map(|&v| f32::from(v) / 255.0).collect();
        let (pw, ph) = (width.div_ceil(4) * 4, height.div_ceil(4) * 4);
        let mut rgba8 = vec![255u8; pw * ph * 4];
        let mut rgbf = vec![0f32; pw * ph * 3];
        for y in 0..ph {
            for x in 0..pw {
                let s = (y.min(height - 1) * width + x.min(width - 1)) * 3;
                let d = y * pw + x;
                rgba8[d * 4..d * 4 + 3].copy_from_slice(&px[s..s + 3]);
                rgbf[d * 3..d * 3 + 3].copy_from_slice(&rgb[s..s + 3]);
            }
        }
        Image {
            name: name.to_string(),
            origin,
            width,
            height,
            rgb,
            pw,
            ph,
            rgba8,
            rgbf,
        }
    }

    fn from_png(name: &str, origin: String, png: &[u8]) -> Result<Image, String> {
        let img = image::load_from_memory_with_format(png, image::ImageFormat::Png)
            .map_err(|e| format!("{name}: {e}"))?
            .to_rgb8();
        let (w, h) = (img.width() as usize, img.height() as usize);
        Ok(Image::from_rgb8(name, origin, w, h, img.as_raw()))
    }

    /// Every `step`-th block row, stitched into a smaller padded image.
    fn rows_subset(&self, step: usize) -> Image {
        let bh = self.ph / 4;
        let rows: Vec<usize> = (0..bh).step_by(step.max(1)).collect();
        let ph = rows.len() * 4;
        let mut rgba8 = Vec::with_capacity(self.pw * ph * 4);
        let mut rgbf = Vec::with_capacity(self.pw * ph * 3);
        for &r in &rows {
            let y0 = r * 4;
            rgba8.extend_from_slice(&self.rgba8[y0 * self.pw * 4..(y0 + 4) * self.pw * 4]);
            rgbf.extend_from_slice(&self.rgbf[y0 * self.pw * 3..(y0 + 4) * self.pw * 3]);
        }
        Image {
            name: self.name.clone(),
            origin: self.origin.clone(),
            width: self.pw,
            height: ph,
            rgb: Vec::new(),
            pw: self.pw,
            ph,
            rgba8,
            rgbf,
        }
    }
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

/// The PNG bytes of `images[0]` of a .gltf (data URIs) or .glb.
fn gltf_image0(path: &Path) -> Result<Vec<u8>, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let (json, bin) = match glb_chunks(&bytes) {
        Some((j, b)) => (j, b),
        None => (&bytes[..], None),
    };
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

fn python() -> String {
    std::env::var("PYTHON").unwrap_or_else(|_| "python3".into())
}

/// scikit-image ships a few sample photos inside its wheel; locate one
/// without importing the package.
fn skimage_photo() -> Option<(PathBuf, String)> {
    let script = "import importlib.util, importlib.metadata, os\n\
        s = importlib.util.find_spec('skimage')\n\
        print(os.path.join(list(s.submodule_search_locations)[0], 'data', 'astronaut.png'))\n\
        print(importlib.metadata.version('scikit-image'))\n";
    let out = Command::new(python()).args(["-c", script]).output().ok()?;
    if !out.status.success() {
        return None;
    }
    let text = String::from_utf8(out.stdout).ok()?;
    let mut lines = text.lines();
    let path = PathBuf::from(lines.next()?);
    let version = lines.next().unwrap_or("?").to_string();
    path.exists().then_some((path, version))
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

fn load_images() -> Vec<Image> {
    let shared =
        PathBuf::from(std::env::var("SHARED_DIR").unwrap_or_else(|_| "/work/shared".into()));
    let mut images = Vec::new();
    for (name, rel) in [
        ("Fox", "assets/Fox/Fox.gltf"),
        ("blub", "assets/blub/blub.glb"),
        ("Duck", "assets/Duck/Duck.gltf"),
    ] {
        let path = shared.join(rel);
        match gltf_image0(&path)
            .and_then(|png| Image::from_png(name, format!("{} images[0]", path.display()), &png))
        {
            Ok(img) => images.push(img),
            Err(e) => println!("skipping {name}: {e}"),
        }
    }
    // A smooth baked atlas as the engine leaves it: the erased texture of
    // cube_gradient_1024 (where encoders differ most).
    let cube = shared.join("assets/cube/cube_gradient_1024.glb");
    match erased_png(&cube).and_then(|png| {
        Image::from_png(
            "cube-erased",
            format!("{} erased (local mode)", cube.display()),
            &png,
        )
    }) {
        Ok(img) => images.push(img),
        Err(e) => println!("skipping the erased cube: {e}"),
    }
    let photo = match std::env::var("BC1_BENCH_PHOTO") {
        Ok(p) => Some((PathBuf::from(&p), format!("{p} (BC1_BENCH_PHOTO)"))),
        Err(_) => skimage_photo().map(|(p, v)| {
            let origin = format!(
                "PyPI scikit-image {v}: skimage/data/astronaut.png ({})",
                p.display()
            );
            (p, origin)
        }),
    };
    match photo {
        Some((path, origin)) => match std::fs::read(&path)
            .map_err(|e| e.to_string())
            .and_then(|png| Image::from_png("astronaut", origin, &png))
        {
            Ok(img) => images.push(img),
            Err(e) => println!("skipping photo: {e}"),
        },
        None => println!(
            "skipping photo: scikit-image not installed (pip install scikit-image) and BC1_BENCH_PHOTO unset"
        ),
    }
    if let Ok(extra) = std::env::var("BC1_BENCH_EXTRA") {
        for p in extra.split(',').filter(|s| !s.is_empty()) {
            let path = PathBuf::from(p);
            let name = path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| p.to_string());
            match std::fs::read(&path)
                .map_err(|e| e.to_string())
                .and_then(|png| Image::from_png(&name, format!("{p} (BC1_BENCH_EXTRA)"), &png))
            {
                Ok(img) => images.push(img),
                Err(e) => println!("skipping {p}: {e}"),
            }
        }
    }
    if let Ok(only) = std::env::var("BC1_BENCH_ONLY") {
        let keep: Vec<String> = only.split(',').map(|s| s.trim().to_lowercase()).collect();
        images.retain(|i| keep.contains(&i.name.to_lowercase()));
    }
    images
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Encoder {
    Ours(Level),
    Ispc,
    Texpresso,
    Quicktex(u32),
}

impl Encoder {
    fn label(self) -> String {
        match self {
            Encoder::Ours(l) => format!("seamstress {l}"),
            Encoder::Ispc => "intel_tex_2 (ISPC)".into(),
            Encoder::Texpresso => "texpresso cluster fit".into(),
            Encoder::Quicktex(l) => format!("quicktex {l}"),
        }
    }

    fn key(self) -> String {
        match self {
            Encoder::Ours(l) => l.name().into(),
            Encoder::Ispc => "ispc".into(),
            Encoder::Texpresso => "texpresso".into(),
            Encoder::Quicktex(l) => format!("quicktex{l}"),
        }
    }
}

/// Encodes a padded image in-process; returns the block bytes, row-major.
fn encode_padded(enc: Encoder, img: &Image) -> Vec<u8> {
    let (pw, ph) = (img.pw, img.ph);
    let bw = pw / 4;
    match enc {
        Encoder::Ours(level) => bc1::encode_image(&img.rgbf, pw, ph, 3, level)
            .expect("valid image")
            .iter()
            .flat_map(Block::to_bytes)
            .collect(),
        Encoder::Ispc => {
            let mut out = vec![0u8; bw * (ph / 4) * 8];
            out.par_chunks_mut(bw * 8)
                .enumerate()
                .for_each(|(by, row)| {
                    let strip = &img.rgba8[by * 4 * pw * 4..(by + 1) * 4 * pw * 4];
                    let surface = intel_tex_2::RgbaSurface {
                        data: strip,
                        width: pw as u32,
                        height: 4,
                        stride: (pw * 4) as u32,
                    };
                    intel_tex_2::bc1::compress_blocks_into(&surface, row);
                });
            out
        }
        Encoder::Texpresso => {
            let fmt = texpresso::Format::Bc1;
            let mut out = vec![0u8; fmt.compressed_size(pw, ph)];
            let params = texpresso::Params {
                algorithm: texpresso::Algorithm::ClusterFit,
                weights: texpresso::COLOUR_WEIGHTS_UNIFORM,
                weigh_colour_by_alpha: false,
            };
            fmt.compress(&img.rgba8, pw, ph, params, &mut out);
            out
        }
        Encoder::Quicktex(_) => unreachable!("quicktex runs out of process"),
    }
}

fn psnr_of(img: &Image, bytes: &[u8]) -> f64 {
    let blocks: Vec<Block> = bytes
        .chunks_exact(8)
        .map(|c| Block::from_bytes(c.try_into().expect("8 bytes")))
        .collect();
    let dec = bc1::decode_image(&blocks, img.pw, img.ph).expect("block count");
    let mut cropped = Vec::with_capacity(img.width * img.height * 3);
    for y in 0..img.height {
        cropped.extend_from_slice(&dec[y * img.pw * 3..(y * img.pw + img.width) * 3]);
    }
    bc1::psnr(&img.rgb, &cropped).expect("same size")
}

/// Best-of timing: runs at least once, then until `min_secs` have passed or
/// `max_runs` runs were made.
fn time_best<T>(min_secs: f64, max_runs: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let start = Instant::now();
    let mut best = f64::MAX;
    let mut out;
    let mut runs = 0;
    loop {
        let t = Instant::now();
        out = f();
        best = best.min(t.elapsed().as_secs_f64());
        runs += 1;
        if runs >= max_runs || start.elapsed().as_secs_f64() >= min_secs {
            break;
        }
    }
    (best, out)
}

struct Row {
    image: String,
    enc: Encoder,
    psnr: f64,
    mpix1: f64,
    mpix_all: Option<f64>,
    note: String,
}

fn run_in_process(enc: Encoder, img: &Image, pool1: &rayon::ThreadPool) -> Row {
    let pixels = (img.width * img.height) as f64;
    // All threads, full image: PSNR and throughput.
    let (t_all, bytes) = time_best(0.5, 10, || encode_padded(enc, img));
    let psnr = psnr_of(img, &bytes);
    // Our own full-image path (with its internal padding) must agree with
    // the padded run.
    if let Encoder::Ours(level) = enc {
        let direct = bc1::encode_image(&img.rgb, img.width, img.height, 3, level).expect("valid");
        let direct: Vec<u8> = direct.iter().flat_map(Block::to_bytes).collect();
        assert_eq!(
            direct, bytes,
            "padding differs from explicit edge replication"
        );
    }
    // One thread: the whole image when that is quick, else a row subset.
    let threads = rayon::current_num_threads() as f64;
    let est_one = t_all * threads;
    let budget = 2.0;
    let (sub, note) = if est_one <= budget {
        (None, String::new())
    } else {
        let step = (est_one / budget).ceil() as usize;
        let s = img.rows_subset(step);
        let note = format!("1T timed on 1 block row in {step}");
        (Some(s), note)
    };
    let timed = sub.as_ref().unwrap_or(img);
    let (t1, _) = pool1.install(|| time_best(0.5, 5, || encode_padded(enc, timed)));
    let timed_pixels = if sub.is_some() {
        (timed.pw * timed.ph) as f64
    } else {
        pixels
    };
    Row {
        image: img.name.clone(),
        enc,
        psnr,
        mpix1: timed_pixels / t1 / 1e6,
        mpix_all: Some(pixels / t_all / 1e6),
        note,
    }
}

fn run_quicktex(levels: &[u32], img: &Image, dir: &Path) -> Vec<Row> {
    // Beside this file, whichever package compiles it.
    let script = [
        PathBuf::from(file!()).with_file_name("bc1_quicktex.py"),
        Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/bc1_quicktex.py"),
    ]
    .into_iter()
    .find(|p| p.exists())
    .unwrap_or_else(|| PathBuf::from("benches/bc1_quicktex.py"));
    let raw = dir.join(format!("{}.rgba", img.name));
    if let Err(e) = std::fs::write(&raw, &img.rgba8) {
        println!("quicktex skipped for {}: {e}", img.name);
        return Vec::new();
    }
    let lv: Vec<String> = levels.iter().map(u32::to_string).collect();
    let out = Command::new(python())
        .arg(&script)
        .arg("--raw")
        .arg(&raw)
        .args([
            "--width",
            &img.pw.to_string(),
            "--height",
            &img.ph.to_string(),
        ])
        .args(["--levels", &lv.join(",")])
        .arg("--out-dir")
        .arg(dir)
        .output();
    let out = match out {
        Ok(o) if o.status.success() => o,
        Ok(o) => {
            println!(
                "quicktex skipped for {}: {}{}",
                img.name,
                String::from_utf8_lossy(&o.stdout).trim(),
                String::from_utf8_lossy(&o.stderr).trim()
            );
            return Vec::new();
        }
        Err(e) => {
            println!("quicktex skipped ({}: {e})", python());
            return Vec::new();
        }
    };
    let pixels = (img.width * img.height) as f64;
    let mut rows = Vec::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        let (Some(level), Some(secs)) = (v["level"].as_u64(), v["seconds"].as_f64()) else {
            continue;
        };
        let Ok(bytes) = std::fs::read(dir.join(format!("quicktex-{level}.bc1"))) else {
            continue;
        };
        if bytes.len() != img.pw * img.ph / 2 {
            println!("quicktex {level}: unexpected output size {}", bytes.len());
            continue;
        }
        rows.push(Row {
            image: img.name.clone(),
            enc: Encoder::Quicktex(level as u32),
            psnr: psnr_of(img, &bytes),
            mpix1: pixels / secs / 1e6,
            mpix_all: None,
            note: "encodes on one thread".into(),
        });
    }
    rows
}

fn main() {
    // `cargo bench` passes `--bench`; nothing else is understood.
    let images = load_images();
    if images.is_empty() {
        println!("no images found");
        return;
    }
    let all = [
        Encoder::Ours(Level::Fast),
        Encoder::Ours(Level::Default),
        Encoder::Ours(Level::Best),
        Encoder::Ispc,
        Encoder::Texpresso,
        Encoder::Quicktex(10),
        Encoder::Quicktex(18),
    ];
    let wanted: Vec<Encoder> = match std::env::var("BC1_BENCH_ENCODERS") {
        Ok(list) => {
            let keys: Vec<String> = list.split(',').map(|s| s.trim().to_lowercase()).collect();
            all.into_iter()
                .filter(|e| keys.contains(&e.key()))
                .collect()
        }
        Err(_) => all.to_vec(),
    };
    let pool1 = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("thread pool");
    let dir = std::env::temp_dir().join(format!("seamstress-bc1-bench-{}", std::process::id()));
    if let Err(e) = std::fs::create_dir_all(&dir) {
        println!("cannot create {}: {e}", dir.display());
    }
    println!(
        "BC1 benchmark: {} threads for 'all', PSNR over RGB in [0,1] against the 8-bit source",
        rayon::current_num_threads()
    );
    for img in &images {
        println!(
            "  {:<12} {}x{}  {}",
            img.name, img.width, img.height, img.origin
        );
    }
    println!(
        "Peers: intel_tex_2 BC1 (ISPC kernel); texpresso ClusterFit with uniform RGB weights; \
         quicktex BC1Encoder(level) with its default FourColor mode. \
         MPix/s counts source texels; every result is decoded by seamstress::bc1."
    );
    println!();
    println!(
        "{:<12} {:<24} {:>9} {:>10} {:>10}  note",
        "image", "encoder", "PSNR dB", "MPix/s 1T", "MPix/s all"
    );
    let mut rows: Vec<Row> = Vec::new();
    let started = Instant::now();
    for img in &images {
        for &enc in &wanted {
            if matches!(enc, Encoder::Quicktex(_)) {
                continue;
            }
            let row = run_in_process(enc, img, &pool1);
            print_row(&row);
            rows.push(row);
        }
        let qt: Vec<u32> = wanted
            .iter()
            .filter_map(|e| match e {
                Encoder::Quicktex(l) => Some(*l),
                _ => None,
            })
            .collect();
        if !qt.is_empty() {
            for row in run_quicktex(&qt, img, &dir) {
                print_row(&row);
                rows.push(row);
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    println!("\n(total {:.0} s)", started.elapsed().as_secs_f64());
    report_goals(&images, &rows);
}

fn print_row(r: &Row) {
    let all = r
        .mpix_all
        .map_or_else(|| "-".to_string(), |v| format!("{v:.2}"));
    println!(
        "{:<12} {:<24} {:>9.3} {:>10.2} {:>10}  {}",
        r.image,
        r.enc.label(),
        r.psnr,
        r.mpix1,
        all,
        r.note
    );
}

fn report_goals(images: &[Image], rows: &[Row]) {
    let find = |img: &str, e: Encoder| rows.iter().find(|r| r.image == img && r.enc == e);
    println!("\nGoals:");
    let mut all_met = true;
    let mut checked = 0;
    for img in images {
        let n = &img.name;
        let ours = |l| find(n, Encoder::Ours(l));
        let mut line = |text: String, ok: bool| {
            checked += 1;
            all_met &= ok;
            println!("  {:<4} {n:<12} {text}", if ok { "met" } else { "MISS" });
        };
        if let (Some(b), Some(q)) = (ours(Level::Best), find(n, Encoder::Quicktex(18))) {
            line(
                format!("best {:.3} >= quicktex18 {:.3} - 0.05", b.psnr, q.psnr),
                b.psnr >= q.psnr - 0.05,
            );
        }
        if let (Some(d), Some(q)) = (ours(Level::Default), find(n, Encoder::Quicktex(10))) {
            line(
                format!("default {:.3} >= quicktex10 {:.3}", d.psnr, q.psnr),
                d.psnr >= q.psnr,
            );
        }
        if let Some(d) = ours(Level::Default) {
            line(
                format!("default {:.1} MPix/s 1T >= 10", d.mpix1),
                d.mpix1 >= 10.0,
            );
        }
        if let (Some(f), Some(i)) = (ours(Level::Fast), find(n, Encoder::Ispc)) {
            line(
                format!("fast {:.3} >= intel_tex_2 {:.3}", f.psnr, i.psnr),
                f.psnr >= i.psnr,
            );
        }
        if let Some(f) = ours(Level::Fast) {
            line(
                format!("fast {:.1} MPix/s 1T >= 100", f.mpix1),
                f.mpix1 >= 100.0,
            );
        }
    }
    println!(
        "{}",
        if checked == 0 {
            "  (no goal could be checked: peers missing)"
        } else if all_met {
            "  all checked goals met"
        } else {
            "  some goals missed"
        }
    );
}
