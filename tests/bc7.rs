//! BC7: our decoder against two independent ones (the `texture2ddecoder`
//! crate and Python's Pillow) on every block of real textures encoded by
//! our encoder and on random and crafted blocks covering every mode,
//! partition, rotation and index selection; the encoder's quality on real
//! textures; and its independence from the thread count.

use std::path::{Path, PathBuf};
use std::process::Command;

use base64::Engine as _;
use seamstress::bc7::{self, Block, EncodeOptions, Level, Params};

mod common;
use needs::needs;

fn asset(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel)
}

fn glb_chunks(bytes: &[u8]) -> Option<(&[u8], Option<&[u8]>)> {
    if bytes.len() < 20 || &bytes[0..4] != b"glTF" {
        return None;
    }
    let at = |o: usize| Some(u32::from_le_bytes(bytes.get(o..o + 4)?.try_into().ok()?) as usize);
    let jlen = at(12)?;
    let bin = at(20 + jlen).and_then(|n| bytes.get(28 + jlen..28 + jlen + n));
    Some((bytes.get(20..20 + jlen)?, bin))
}

fn data_uri(uri: &str) -> Option<Vec<u8>> {
    let (_, b64) = uri.strip_prefix("data:")?.split_once(";base64,")?;
    base64::engine::general_purpose::STANDARD.decode(b64).ok()
}

/// The encoded bytes of a model's first image.
fn image0(path: &Path) -> Vec<u8> {
    let bytes = std::fs::read(path).unwrap();
    let (json, bin) = glb_chunks(&bytes).unwrap_or((&bytes[..], None));
    let doc: serde_json::Value = serde_json::from_slice(json).unwrap();
    let img = &doc["images"][0];
    if let Some(uri) = img["uri"].as_str() {
        return data_uri(uri)
            .unwrap_or_else(|| std::fs::read(path.parent().unwrap().join(uri)).unwrap());
    }
    let bv = &doc["bufferViews"][img["bufferView"].as_u64().unwrap() as usize];
    let off = bv["byteOffset"].as_u64().unwrap_or(0) as usize;
    let len = bv["byteLength"].as_u64().unwrap() as usize;
    let buf = &doc["buffers"][bv["buffer"].as_u64().unwrap_or(0) as usize];
    let data = match buf["uri"].as_str() {
        Some(uri) => data_uri(uri).unwrap(),
        None => bin.unwrap().to_vec(),
    };
    data[off..off + len].to_vec()
}

/// An RGBA crop of `size`² texels of a model's first texture, its top-left
/// corner at (`fx`, `fy`) as fractions of the free range.
struct Texture {
    name: String,
    size: usize,
    rgba: Vec<u8>,
}

fn crop(model: &str, size: usize, fx: f32, fy: f32) -> Texture {
    let img = image::load_from_memory(&image0(&asset(model)))
        .unwrap()
        .to_rgba8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let x0 = ((w - size) as f32 * fx) as usize;
    let y0 = ((h - size) as f32 * fy) as usize;
    let mut rgba = Vec::with_capacity(size * size * 4);
    for y in y0..y0 + size {
        rgba.extend_from_slice(&img.as_raw()[(y * w + x0) * 4..(y * w + x0 + size) * 4]);
    }
    Texture {
        name: format!("{model}@{fx},{fy}"),
        size,
        rgba,
    }
}

/// Real art: the shared models' base colours, plus one with an alpha
/// channel made from another's red (cut-outs and soft edges alike).
fn textures() -> Vec<Texture> {
    let mut out = vec![
        crop("Fox/Fox.gltf", 64, 0.3, 0.4),
        crop("Duck/Duck.gltf", 64, 0.5, 0.5),
        crop("CesiumMan/CesiumMan.gltf", 64, 0.2, 0.7),
        crop("WaterBottle/WaterBottle.gltf", 64, 0.5, 0.5),
    ];
    let mut alpha = crop("Duck/Duck.gltf", 64, 0.2, 0.3);
    let source = crop("CesiumMan/CesiumMan.gltf", 64, 0.6, 0.4);
    for (t, s) in alpha
        .rgba
        .chunks_exact_mut(4)
        .zip(source.rgba.chunks_exact(4))
    {
        t[3] = if s[0] < 60 { 0 } else { s[0] };
    }
    alpha.name.push_str("+alpha");
    out.push(alpha);
    out
}

/// A small deterministic generator (xorshift64*).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: u64) -> u8 {
        (self.next() % n) as u8
    }
}

/// Blocks that cover the format: random bytes (every mode, the reserved
/// one included, and anchor bits set where the format leaves them out),
/// and for every mode each partition, rotation and index selection with
/// random endpoints, p-bits and indices, extreme codes among them.
fn crafted_blocks() -> Vec<Block> {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let mut out = Vec::new();
    for _ in 0..2048 {
        let mut b = [0u8; 16];
        for v in &mut b {
            *v = rng.below(256);
        }
        out.push(Block(b));
    }
    for first in 0..=255u8 {
        let mut b = [0xa5u8; 16];
        b[0] = first;
        out.push(Block(b));
    }
    for mode in 0..8u8 {
        let (partitions, rotations, selections) = match mode {
            0 => (16, 1, 1),
            1 | 2 | 3 | 7 => (64, 1, 1),
            4 => (1, 4, 2),
            5 => (1, 4, 1),
            _ => (1, 1, 1),
        };
        for partition in 0..partitions {
            for rotation in 0..rotations {
                for index_selection in 0..selections {
                    for extreme in 0..3 {
                        let mut p = Params {
                            mode,
                            partition,
                            rotation,
                            index_selection,
                            ..Params::default()
                        };
                        for s in 0..3 {
                            for e in 0..2 {
                                for c in 0..4 {
                                    p.ends[s][e][c] = match extreme {
                                        0 => 0,
                                        1 => 255,
                                        _ => rng.below(256),
                                    };
                                }
                                p.pbits[s][e] = rng.below(2);
                            }
                            if mode == 1 {
                                p.pbits[s][1] = p.pbits[s][0];
                            }
                        }
                        let bits = [
                            [3, 0],
                            [3, 0],
                            [2, 0],
                            [2, 0],
                            [2, 3],
                            [2, 2],
                            [4, 0],
                            [2, 0],
                        ];
                        for (set, &n) in bits[usize::from(mode)].iter().enumerate() {
                            for i in p.indices[set].iter_mut() {
                                *i = if n == 0 { 0 } else { rng.below(1 << n) };
                            }
                        }
                        // Codes wider than their fields are masked by the
                        // writer: keep them in range so that they round-trip.
                        let m = [
                            (4, 0),
                            (6, 0),
                            (5, 0),
                            (7, 0),
                            (5, 6),
                            (7, 8),
                            (7, 7),
                            (5, 5),
                        ][usize::from(mode)];
                        for s in 0..3 {
                            for e in 0..2 {
                                for c in 0..4 {
                                    let width = if c < 3 { m.0 } else { m.1 };
                                    p.ends[s][e][c] &= ((1u16 << width) - 1) as u8;
                                }
                            }
                        }
                        let block = Block::from_params(&p);
                        assert_eq!(block.mode(), Some(mode));
                        assert_eq!(block.decode(), p.decode(), "anchor fix-up changed {p:?}");
                        out.push(block);
                    }
                }
            }
        }
    }
    out
}

fn bytes_of(blocks: &[Block]) -> Vec<u8> {
    blocks.iter().flat_map(|b| b.0).collect()
}

/// Blocks laid out as an image `bw` blocks wide, decoded by us.
fn ours(blocks: &[Block], bw: usize) -> Vec<u8> {
    let bh = blocks.len() / bw;
    bc7::decode_image(blocks, bw * 4, bh * 4).unwrap()
}

fn texture2d(blocks: &[Block], bw: usize) -> Vec<u8> {
    let (w, h) = (bw * 4, blocks.len() / bw * 4);
    let mut px = vec![0u32; w * h];
    texture2ddecoder::decode_bc7(&bytes_of(blocks), w, h, &mut px).unwrap();
    px.iter()
        .flat_map(|p| {
            let [b, g, r, a] = p.to_le_bytes();
            [r, g, b, a]
        })
        .collect()
}

/// The first texel where two decodes differ, with the block's bytes.
fn first_difference(blocks: &[Block], bw: usize, a: &[u8], b: &[u8]) -> Option<String> {
    let w = bw * 4;
    let t = a
        .chunks_exact(4)
        .zip(b.chunks_exact(4))
        .position(|(x, y)| x != y)?;
    let (x, y) = (t % w, t / w);
    let block = blocks[(y / 4) * bw + x / 4];
    Some(format!(
        "texel ({x}, {y}): {:?} vs {:?}; block {:02x?} = {:?}",
        &a[t * 4..t * 4 + 4],
        &b[t * 4..t * 4 + 4],
        block.0,
        block.params()
    ))
}

fn encoded_textures() -> Vec<(String, Vec<Block>)> {
    let mut out = Vec::new();
    for t in textures() {
        for level in [Level::Fast, Level::Default] {
            let opts = EncodeOptions::for_image(level, &t.rgba);
            let blocks = bc7::encode_image(&t.rgba, t.size, t.size, &opts).unwrap();
            out.push((format!("{} {level}", t.name), blocks));
        }
    }
    out.push(("crafted".into(), crafted_blocks()));
    out
}

#[test]
fn decoder_agrees_with_texture2ddecoder() {
    let mut modes = [0usize; 9];
    for (name, blocks) in encoded_textures() {
        // 16 blocks across (crafted sets are padded to a whole row).
        let mut blocks = blocks;
        while blocks.len() % 16 != 0 {
            blocks.push(Block([0x40; 16]));
        }
        for b in &blocks {
            modes[b.mode().map_or(8, usize::from)] += 1;
        }
        let a = ours(&blocks, 16);
        let b = texture2d(&blocks, 16);
        if let Some(d) = first_difference(&blocks, 16, &a, &b) {
            panic!("{name}: {d}");
        }
    }
    // Every mode was encoded or crafted many times, the reserved one too.
    assert!(modes[..8].iter().all(|&n| n >= 100), "{modes:?}");
    assert!(modes[8] >= 8, "{modes:?}");
}

/// A DDS file with the DX10 header, one BC7_UNORM (DXGI 98) level.
fn bc7_dds(blocks: &[Block], w: usize, h: usize) -> Vec<u8> {
    let mut d = Vec::with_capacity(148 + blocks.len() * 16);
    let u32s = |d: &mut Vec<u8>, v: &[u32]| v.iter().for_each(|x| d.extend(x.to_le_bytes()));
    d.extend(b"DDS ");
    // size, flags (caps, height, width, pixel format, linear size), height,
    // width, linear size, depth, mip count, 11 reserved.
    u32s(
        &mut d,
        &[
            124,
            0x0008_1007,
            h as u32,
            w as u32,
            (blocks.len() * 16) as u32,
            0,
            1,
        ],
    );
    u32s(&mut d, &[0; 11]);
    // Pixel format: size, FOURCC, "DX10", bit count and masks unused.
    u32s(&mut d, &[32, 4]);
    d.extend(b"DX10");
    u32s(&mut d, &[0; 5]);
    // Caps (texture), caps2-4, reserved.
    u32s(&mut d, &[0x1000, 0, 0, 0, 0]);
    // DX10: format, 2D texture, misc, array size, misc2.
    u32s(&mut d, &[98, 3, 0, 1, 0]);
    assert_eq!(d.len(), 148);
    d.extend(bytes_of(blocks));
    d
}

#[test]
#[needs(python)]
fn decoder_agrees_with_pillow() {
    if !common::PYTHON.available() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("seamstress-bc7-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (n, (name, mut blocks)) in encoded_textures().into_iter().enumerate() {
        while blocks.len() % 16 != 0 {
            blocks.push(Block([0x40; 16]));
        }
        let (w, h) = (64, blocks.len() / 16 * 4);
        let path = dir.join(format!("{n}.dds"));
        std::fs::write(&path, bc7_dds(&blocks, w, h)).unwrap();
        let o = Command::new("python3")
            .args([
                "-c",
                "import sys; from PIL import Image; \
                 sys.stdout.buffer.write(Image.open(sys.argv[1]).convert('RGBA').tobytes())",
                path.to_str().unwrap(),
            ])
            .output()
            .expect("python3 runs");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let mut a = ours(&blocks, 16);
        // Pillow decodes the reserved mode to opaque black, not to the
        // transparent black of Direct3D (and of texture2ddecoder).
        for (t, px) in a.chunks_exact_mut(4).enumerate() {
            let (x, y) = (t % w, t / w);
            if blocks[(y / 4) * 16 + x / 4].mode().is_none() {
                px[3] = 255;
            }
        }
        if let Some(d) = first_difference(&blocks, 16, &a, &o.stdout) {
            panic!("{name}: {d}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Encode → decode quality on real art, at figures a little under those
/// measured (in this profile), so that a regression fails.
#[test]
fn encoded_textures_keep_their_quality() {
    // (texture index, level, minimum PSNR in dB) over RGB, or RGBA for the
    // texture with alpha.
    let floors = [
        (Level::Fast, [48.0, 46.0, 40.0, 44.0, 40.0]),
        (Level::Default, [50.0, 49.0, 42.0, 46.0, 42.0]),
    ];
    let textures = textures();
    for (level, floor) in floors {
        for (t, min) in textures.iter().zip(floor) {
            let opts = EncodeOptions::for_image(level, &t.rgba);
            let blocks = bc7::encode_image(&t.rgba, t.size, t.size, &opts).unwrap();
            let dec = bc7::decode_image(&blocks, t.size, t.size).unwrap();
            let ch = if bc7::has_alpha(&t.rgba) { 0..4 } else { 0..3 };
            let p = bc7::psnr(&t.rgba, &dec, ch).unwrap();
            eprintln!("{} {level}: {p:.2} dB", t.name);
            assert!(p >= min, "{} {level}: {p:.2} dB < {min}", t.name);
            if !bc7::has_alpha(&t.rgba) {
                assert!(dec.chunks_exact(4).all(|t| t[3] >= 251), "{}", t.name);
            }
        }
    }
}

#[test]
fn output_is_independent_of_thread_count() {
    let t = crop("Fox/Fox.gltf", 32, 0.5, 0.5);
    for level in [Level::Fast, Level::Default] {
        let opts = EncodeOptions::for_image(level, &t.rgba);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| bc7::encode_image(&t.rgba, t.size, t.size, &opts).unwrap())
        };
        assert_eq!(run(1), run(2), "{level}");
    }
}
