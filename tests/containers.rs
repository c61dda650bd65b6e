//! The texture containers (`seamstress::container`) with real blocks (BC1,
//! BC3 and BC7 from intel_tex_2, of the Duck's texture): read back by this
//! crate; KTX2 files by ktx-parse (npm, under node), their levels inflated
//! with zstd and decoded by texture2ddecoder; BC7 DDS files by Pillow. And
//! damaged files, which must give errors naming the problem.

use std::path::{Path, PathBuf};
use std::process::Command;

use base64::Engine as _;
use needs::needs;
use seamstress::container::dds::{read_dds, write_dds, DdsHeader};
use seamstress::container::ktx2::{read_ktx2, write_ktx2};
use seamstress::container::{
    full_chain_len, mip_size, BlockFormat, ColorSpace, ContainerError, EncodedTexture,
};

// intel_tex_2's static library is C++ and needs the C++ runtime.
#[link(name = "stdc++")]
extern "C" {}

const COLOR_SPACES: [ColorSpace; 2] = [ColorSpace::Srgb, ColorSpace::Linear];
const ZSTD: [Option<i32>; 3] = [None, Some(3), Some(22)];

/// An RGBA8 image: width, height, texels.
#[derive(Clone)]
struct Rgba {
    w: u32,
    h: u32,
    px: Vec<u8>,
}

impl Rgba {
    fn at(&self, x: u32, y: u32) -> [u8; 4] {
        let i = ((y.min(self.h - 1) * self.w + x.min(self.w - 1)) * 4) as usize;
        self.px[i..i + 4].try_into().unwrap()
    }

    /// Halved by a 2×2 box (clamped at the edges), rounding down, at least 1.
    fn half(&self) -> Rgba {
        let (w, h) = ((self.w / 2).max(1), (self.h / 2).max(1));
        let mut px = Vec::with_capacity((w * h * 4) as usize);
        for y in 0..h {
            for x in 0..w {
                let t = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .map(|(dx, dy)| self.at(2 * x + dx, 2 * y + dy));
                for c in 0..4 {
                    px.push(((t.iter().map(|p| u32::from(p[c])).sum::<u32>() + 2) / 4) as u8);
                }
            }
        }
        Rgba { w, h, px }
    }

    /// Padded to whole blocks by repeating the last row and column, as the
    /// block encoders want.
    fn padded(&self) -> Rgba {
        let (w, h) = (self.w.next_multiple_of(4), self.h.next_multiple_of(4));
        let px = (0..h)
            .flat_map(|y| (0..w).flat_map(move |x| self.at(x, y)))
            .collect();
        Rgba { w, h, px }
    }
}

/// 211×97 texels of the Duck's texture (neither side a multiple of 4),
/// with an alpha ramp so that BC3's and BC7's alpha carry something.
fn duck() -> Rgba {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets/Duck/Duck.gltf");
    let gltf: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    let uri = gltf["images"][0]["uri"].as_str().unwrap();
    let png = base64::engine::general_purpose::STANDARD
        .decode(uri.split_once(',').unwrap().1)
        .unwrap();
    let full = image::load_from_memory(&png).unwrap().to_rgba8();
    let (w, h) = (211, 97);
    let mut px = Vec::with_capacity((w * h * 4) as usize);
    for y in 0..h {
        for x in 0..w {
            let p = full.get_pixel(150 + x, 200 + y).0;
            px.extend_from_slice(&[p[0], p[1], p[2], (40 + (x + 2 * y) % 216) as u8]);
        }
    }
    Rgba { w, h, px }
}

/// The image's mip chain: level 0 alone, or down to 1×1.
fn chain(img: &Rgba, mips: bool) -> Vec<Rgba> {
    let n = if mips {
        full_chain_len(img.w, img.h)
    } else {
        1
    };
    std::iter::successors(Some(img.clone()), |l| Some(l.half()))
        .take(n)
        .collect()
}

fn encode(level: &Rgba, format: BlockFormat) -> Vec<u8> {
    let p = level.padded();
    let surface = intel_tex_2::RgbaSurface {
        data: &p.px,
        width: p.w,
        height: p.h,
        stride: p.w * 4,
    };
    match format {
        BlockFormat::Bc1 => intel_tex_2::bc1::compress_blocks(&surface),
        BlockFormat::Bc3 => intel_tex_2::bc3::compress_blocks(&surface),
        BlockFormat::Bc7 => intel_tex_2::bc7::compress_blocks(
            &intel_tex_2::bc7::alpha_ultra_fast_settings(),
            &surface,
        ),
    }
}

fn texture(levels: &[Rgba], format: BlockFormat, color_space: ColorSpace) -> EncodedTexture {
    EncodedTexture {
        format,
        color_space,
        width: levels[0].w,
        height: levels[0].h,
        levels: levels.iter().map(|l| encode(l, format)).collect(),
    }
}

/// Every combination of format, colour space and chain.
fn textures() -> Vec<(EncodedTexture, Vec<Rgba>)> {
    let img = duck();
    let mut out = Vec::new();
    for mips in [false, true] {
        let levels = chain(&img, mips);
        for format in BlockFormat::ALL {
            for cs in COLOR_SPACES {
                out.push((texture(&levels, format, cs), levels.clone()));
            }
        }
    }
    out
}

/// texture2ddecoder's decoding of one level's blocks, as RGBA8.
fn decode(format: BlockFormat, punch_through: bool, blocks: &[u8], w: u32, h: u32) -> Vec<u8> {
    let (w, h) = (w as usize, h as usize);
    let mut out = vec![0u32; w * h];
    match (format, punch_through) {
        (BlockFormat::Bc1, false) => texture2ddecoder::decode_bc1(blocks, w, h, &mut out),
        (BlockFormat::Bc1, true) => texture2ddecoder::decode_bc1a(blocks, w, h, &mut out),
        (BlockFormat::Bc3, _) => texture2ddecoder::decode_bc3(blocks, w, h, &mut out),
        (BlockFormat::Bc7, _) => texture2ddecoder::decode_bc7(blocks, w, h, &mut out),
    }
    .unwrap();
    // Each texel is B, G, R, A in memory order.
    out.iter()
        .flat_map(|p| {
            let [b, g, r, a] = p.to_le_bytes();
            [r, g, b, a]
        })
        .collect()
}

/// PSNR over the channels the format carries (BC1: RGB).
fn psnr(format: BlockFormat, a: &[u8], b: &[u8]) -> f64 {
    let channels = if format == BlockFormat::Bc1 { 3 } else { 4 };
    let (mut se, mut n) = (0f64, 0usize);
    for (p, q) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
        for c in 0..channels {
            se += (f64::from(p[c]) - f64::from(q[c])).powi(2);
            n += 1;
        }
    }
    10.0 * (255f64.powi(2) / (se / n as f64).max(1e-9)).log10()
}

fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "seamstress-containers-{}-{tag}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn every_format_colour_space_chain_and_zstd_round_trips() {
    for (tex, levels) in textures() {
        // The test's blocks are real encodings of their levels.
        for (k, l) in levels.iter().enumerate() {
            let got = decode(tex.format, false, &tex.levels[k], l.w, l.h);
            let db = psnr(tex.format, &got, &l.px);
            assert!(db > 28.0, "{} level {k}: {db:.1} dB", tex.format);
        }
        for zstd in ZSTD {
            let bytes = write_ktx2(&tex, zstd).unwrap();
            assert_eq!(read_ktx2(&bytes).unwrap(), tex, "{:?} {zstd:?}", tex.format);
            assert_eq!(bytes, write_ktx2(&tex, zstd).unwrap(), "deterministic");
        }
        let dds = read_dds(&write_dds(&tex, DdsHeader::Dx10).unwrap()).unwrap();
        assert_eq!((dds.header, &dds.texture), (DdsHeader::Dx10, &tex));
        if tex.format != BlockFormat::Bc7 {
            let legacy = read_dds(&write_dds(&tex, DdsHeader::Legacy).unwrap()).unwrap();
            assert_eq!(legacy.texture.levels, tex.levels);
        }
    }
}

/// What ktx-parse makes of each file, as JSON: header, DFD, key/values,
/// the stored bytes of each level (base64), and whether its writer, given
/// what it read, lays out the very same file.
fn ktx_parse(files: &[PathBuf]) -> Vec<serde_json::Value> {
    let script = r#"
const { pathToFileURL } = require('url');
import(pathToFileURL(require.resolve('ktx-parse')).href).then(({ read, write }) => {
  const fs = require('fs');
  const out = process.argv.slice(1).map((f) => {
    const bytes = fs.readFileSync(f);
    const c = read(new Uint8Array(bytes));
    const again = Buffer.from(write(c, { keepWriter: true }));
    return {
      rewritesIdentically: Buffer.compare(again, bytes) === 0,
      vkFormat: c.vkFormat, typeSize: c.typeSize, pixelWidth: c.pixelWidth,
      pixelHeight: c.pixelHeight, pixelDepth: c.pixelDepth, layerCount: c.layerCount,
      faceCount: c.faceCount, levelCount: c.levelCount,
      supercompressionScheme: c.supercompressionScheme,
      dfd: c.dataFormatDescriptor, keyValue: c.keyValue,
      levels: c.levels.map((l) => ({
        data: Buffer.from(l.levelData).toString('base64'),
        uncompressedByteLength: l.uncompressedByteLength,
      })),
    };
  });
  process.stdout.write(JSON.stringify(out));
});
"#;
    let o = Command::new("node")
        .arg("-e")
        .arg(script)
        .args(files)
        .output()
        .expect("node runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn format_of_vk(vk: u64) -> (BlockFormat, ColorSpace, bool) {
    match vk {
        131 => (BlockFormat::Bc1, ColorSpace::Linear, false),
        132 => (BlockFormat::Bc1, ColorSpace::Srgb, false),
        133 => (BlockFormat::Bc1, ColorSpace::Linear, true),
        134 => (BlockFormat::Bc1, ColorSpace::Srgb, true),
        137 => (BlockFormat::Bc3, ColorSpace::Linear, false),
        138 => (BlockFormat::Bc3, ColorSpace::Srgb, false),
        145 => (BlockFormat::Bc7, ColorSpace::Linear, false),
        146 => (BlockFormat::Bc7, ColorSpace::Srgb, false),
        _ => panic!("vkFormat {vk}"),
    }
}

#[needs(ktx_parse)]
#[test]
fn ktx_parse_reads_our_ktx2_files() {
    let dir = scratch("ktx-parse");
    let all = textures();
    let mut cases = Vec::new();
    for (tex, levels) in &all {
        for zstd in ZSTD {
            cases.push((tex.clone(), levels.clone(), zstd, false));
        }
    }
    // BC1 with punch-through alpha: one level-0 block fully transparent
    // (three-colour mode, every index 3).
    let (mut punched, levels) = all
        .into_iter()
        .find(|(t, _)| t.format == BlockFormat::Bc1 && t.levels.len() > 1)
        .unwrap();
    punched.levels[0][..8].copy_from_slice(&[0, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF]);
    cases.push((punched.clone(), levels.clone(), None, true));
    cases.push((punched, levels, Some(9), true));

    let files: Vec<PathBuf> = cases
        .iter()
        .enumerate()
        .map(|(i, (tex, _, zstd, _))| {
            let path = dir.join(format!("{i}.ktx2"));
            std::fs::write(&path, write_ktx2(tex, *zstd).unwrap()).unwrap();
            path
        })
        .collect();
    let parsed = ktx_parse(&files);
    assert_eq!(parsed.len(), cases.len());
    let n = |v: &serde_json::Value| v.as_u64().unwrap();
    for ((tex, levels, zstd, punched), c) in cases.iter().zip(&parsed) {
        let what = format!(
            "{:?} {:?} {} levels, zstd {zstd:?}",
            tex.format,
            tex.color_space,
            tex.levels.len()
        );
        let (format, cs, alpha) = format_of_vk(n(&c["vkFormat"]));
        assert_eq!(
            (format, cs, alpha),
            (tex.format, tex.color_space, *punched),
            "{what}"
        );
        assert_eq!(c["rewritesIdentically"], true, "{what}");
        assert_eq!(n(&c["typeSize"]), 1);
        assert_eq!((n(&c["pixelWidth"]), n(&c["pixelHeight"])), (211, 97));
        assert_eq!(
            (n(&c["pixelDepth"]), n(&c["layerCount"]), n(&c["faceCount"])),
            (0, 0, 1)
        );
        assert_eq!(n(&c["levelCount"]) as usize, tex.levels.len());
        assert_eq!(
            n(&c["supercompressionScheme"]),
            if zstd.is_some() { 2 } else { 0 }
        );

        let dfd = &c["dfd"][0];
        let model = match format {
            BlockFormat::Bc1 => 128,
            BlockFormat::Bc3 => 130,
            BlockFormat::Bc7 => 134,
        };
        assert_eq!(n(&dfd["colorModel"]), model, "{what}");
        assert_eq!(n(&dfd["colorPrimaries"]), 1, "BT709");
        let transfer = if cs == ColorSpace::Srgb { 2 } else { 1 };
        assert_eq!(n(&dfd["transferFunction"]), transfer, "{what}");
        assert_eq!(dfd["texelBlockDimension"], serde_json::json!([3, 3, 0, 0]));
        let bytes = format.block_bytes() as u64;
        assert_eq!(
            dfd["bytesPlane"],
            serde_json::json!([bytes, 0, 0, 0, 0, 0, 0, 0])
        );
        let samples: Vec<(u64, u64, u64)> = dfd["samples"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| {
                assert_eq!(s["samplePosition"], serde_json::json!([0, 0, 0, 0]));
                assert_eq!(
                    (n(&s["sampleLower"]), n(&s["sampleUpper"])),
                    (0, u32::MAX as u64)
                );
                (n(&s["bitOffset"]), n(&s["bitLength"]), n(&s["channelType"]))
            })
            .collect();
        let alpha_type = if cs == ColorSpace::Srgb { 0x1F } else { 15 };
        let want: Vec<(u64, u64, u64)> = match (format, alpha) {
            (BlockFormat::Bc1, false) => vec![(0, 63, 0)],
            (BlockFormat::Bc1, true) => vec![(0, 63, 1)],
            (BlockFormat::Bc3, _) => vec![(0, 63, alpha_type), (64, 63, 0)],
            (BlockFormat::Bc7, _) => vec![(0, 127, 0)],
        };
        assert_eq!(samples, want, "{what}");

        assert_eq!(c["keyValue"]["KTXorientation"], "rd");
        assert_eq!(
            c["keyValue"]["KTXwriter"],
            format!("Seamstress {}", env!("CARGO_PKG_VERSION"))
        );
        match zstd {
            Some(l) => assert_eq!(c["keyValue"]["KTXwriterScParams"], format!("--zstd {l}")),
            None => assert!(c["keyValue"].get("KTXwriterScParams").is_none()),
        }

        let stored = c["levels"].as_array().unwrap();
        assert_eq!(stored.len(), tex.levels.len());
        for (k, l) in stored.iter().enumerate() {
            let data = base64::engine::general_purpose::STANDARD
                .decode(l["data"].as_str().unwrap())
                .unwrap();
            let raw = match zstd {
                Some(_) => zstd::stream::decode_all(&data[..]).unwrap(),
                None => data,
            };
            assert_eq!(
                n(&l["uncompressedByteLength"]) as usize,
                raw.len(),
                "{what} level {k}"
            );
            assert_eq!(raw, tex.levels[k], "{what} level {k}");
            // Decoded as the file says it should be, the blocks give the
            // level they were made from.
            let (w, h) = mip_size(211, 97, k);
            let got = decode(format, alpha, &raw, w, h);
            assert_eq!(got, decode(tex.format, alpha, &tex.levels[k], w, h));
            if *punched && k == 0 {
                assert!((0..4).all(|y| (0..4).all(|x| got[(y * w as usize + x) * 4 + 3] == 0)));
            } else {
                let db = psnr(format, &got, &levels[k].px);
                assert!(db > 28.0, "{what} level {k}: {db:.1} dB");
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pillow's reading of a DDS file's level 0, as RGBA8.
fn pillow_rgba(path: &Path) -> (u32, u32, Vec<u8>) {
    let script = "import sys\nfrom PIL import Image\nim = Image.open(sys.argv[1]).convert('RGBA')\nsys.stdout.write(f'{im.size[0]} {im.size[1]}\\n')\nsys.stdout.flush()\nsys.stdout.buffer.write(im.tobytes())";
    let o = Command::new("python3")
        .args(["-c", script])
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "Pillow failed on {}: {}",
        path.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    let nl = o.stdout.iter().position(|&b| b == b'\n').unwrap();
    let head = String::from_utf8(o.stdout[..nl].to_vec()).unwrap();
    let (w, h) = head.split_once(' ').unwrap();
    (
        w.parse().unwrap(),
        h.parse().unwrap(),
        o.stdout[nl + 1..].to_vec(),
    )
}

#[needs(python)]
#[test]
fn pillow_reads_bc7_dds_as_texture2ddecoder_decodes_it() {
    let dir = scratch("pillow");
    let levels = chain(&duck(), true);
    for cs in COLOR_SPACES {
        let tex = texture(&levels, BlockFormat::Bc7, cs);
        let path = dir.join(format!("bc7_{cs:?}.dds"));
        std::fs::write(&path, write_dds(&tex, DdsHeader::Dx10).unwrap()).unwrap();
        let (w, h, px) = pillow_rgba(&path);
        assert_eq!((w, h), (211, 97));
        assert_eq!(
            px,
            decode(BlockFormat::Bc7, false, &tex.levels[0], w, h),
            "{cs:?}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn put_u32(b: &mut [u8], off: usize, v: u32) {
    b[off..off + 4].copy_from_slice(&v.to_le_bytes());
}

fn put_u64(b: &mut [u8], off: usize, v: u64) {
    b[off..off + 8].copy_from_slice(&v.to_le_bytes());
}

#[test]
fn damaged_files_give_errors_that_name_the_problem() {
    let levels = chain(&duck().half().half(), true);
    let tex = texture(&levels, BlockFormat::Bc7, ColorSpace::Srgb);
    for zstd in [None, Some(5)] {
        let good = write_ktx2(&tex, zstd).unwrap();
        for cut in 0..good.len() {
            assert!(read_ktx2(&good[..cut]).is_err(), "cut at {cut}");
        }
        // Flips anywhere in the metadata or the first level: an error or
        // a texture, never a panic.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..4000 {
            let mut b = good.clone();
            for _ in 0..3 {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let at = (state % 400) as usize % b.len();
                b[at] = (state >> 32) as u8;
            }
            let _ = read_ktx2(&b);
        }
        let msg = |b: &[u8]| read_ktx2(b).unwrap_err().to_string();

        let mut b = good.clone();
        b[1] = b'X';
        assert_eq!(read_ktx2(&b), Err(ContainerError::Ktx2Identifier));
        assert!(
            msg(&good[..40]).contains("KTX2 header"),
            "{}",
            msg(&good[..40])
        );

        // Level 2's data said to lie past the end.
        let mut b = good.clone();
        put_u64(&mut b, 80 + 2 * 24, good.len() as u64 - 16);
        let m = msg(&b);
        assert!(m.contains("level 2") && m.contains("past the end"), "{m}");
        // An uncompressed length that is not the level's.
        let mut b = good.clone();
        put_u64(&mut b, 80 + 24 + 16, u64::MAX);
        let m = msg(&b);
        assert!(
            m.contains("level 1") && m.contains("uncompressedByteLength"),
            "{m}"
        );
        // Huge dimensions, and more levels than they allow.
        let mut b = good.clone();
        put_u32(&mut b, 20, u32::MAX);
        put_u32(&mut b, 24, u32::MAX);
        assert!(matches!(
            read_ktx2(&b),
            Err(ContainerError::Dimensions { .. })
        ));
        let mut b = good.clone();
        put_u32(&mut b, 40, 40);
        assert!(matches!(
            read_ktx2(&b),
            Err(ContainerError::TooManyLevels { .. })
        ));
        // Not BC1, BC3 or BC7; a scheme not read.
        let mut b = good.clone();
        put_u32(&mut b, 12, 37);
        assert_eq!(read_ktx2(&b), Err(ContainerError::VkFormat(37)));
        let mut b = good.clone();
        put_u32(&mut b, 44, 1);
        assert_eq!(read_ktx2(&b), Err(ContainerError::Supercompression(1)));
        // A DFD that contradicts the vkFormat.
        let mut b = good.clone();
        put_u32(&mut b, 12, 138);
        assert!(msg(&b).contains("colorModel 134"), "{}", msg(&b));
        let mut b = good.clone();
        put_u32(&mut b, 12, 145);
        assert!(msg(&b).contains("transferFunction"), "{}", msg(&b));
    }
    // Level 0's zstd frame without its magic number.
    let mut b = write_ktx2(&tex, Some(5)).unwrap();
    let off = u64::from_le_bytes(b[80..88].try_into().unwrap()) as usize;
    b[off] ^= 0x5A;
    let e = read_ktx2(&b).unwrap_err();
    assert!(matches!(e, ContainerError::Zstd(_)), "{e}");
    assert!(e.to_string().contains("level 0"), "{e}");
    // Levels off their 16-byte alignment.
    let mut b = write_ktx2(&tex, None).unwrap();
    let off = u64::from_le_bytes(b[80..88].try_into().unwrap());
    put_u64(&mut b, 80, off - 1);
    assert!(read_ktx2(&b)
        .unwrap_err()
        .to_string()
        .contains("not a multiple of 16"));

    // DDS: truncated, huge, and a BC7 DDS cut short.
    let dds = write_dds(&tex, DdsHeader::Dx10).unwrap();
    for cut in 0..dds.len() {
        assert!(read_dds(&dds[..cut]).is_err(), "cut at {cut}");
    }
    let mut b = dds.clone();
    put_u32(&mut b, 16, u32::MAX);
    assert!(matches!(
        read_dds(&b),
        Err(ContainerError::Dimensions { .. })
    ));
    assert!(matches!(
        read_dds(b"DDS "),
        Err(ContainerError::Truncated { .. })
    ));
}
