//! DDS files written by `seamstress process`, read back by this crate, by
//! the `ddsfile` crate and by Python's Pillow.

use std::path::{Path, PathBuf};
use std::process::Command;

use seamstress::bc1::dds::{read_dds, write_dds, DdsHeaderKind, MipLevel};
use seamstress::bc1::{self, Block};

mod common;
use needs::needs;

fn asset(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel)
}

fn process(rel: &str, tag: &str, extra: &[&str]) -> (PathBuf, serde_json::Value) {
    let out = std::env::temp_dir().join(format!("seamstress-dds-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let model = asset(rel);
    let mut args = vec![
        "process",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(&args)
        .output()
        .expect("seamstress runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    (out, report)
}

fn dds_path(out: &Path, report: &serde_json::Value) -> PathBuf {
    out.join(
        report["textures"][0]["files"]["dds"]
            .as_str()
            .expect("dds file"),
    )
}

#[test]
fn full_mip_chain_with_dx10_header_reads_back() {
    // 211² is not a multiple of 4, and left so: every level's last blocks
    // are padded by edge replication. The chain is the default.
    let (out, report) = process(
        "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
        "mips",
        &["--dx10", "--resize", "none"],
    );
    let bytes = std::fs::read(dds_path(&out, &report)).unwrap();
    let ours = read_dds(&bytes).expect("our reader");
    assert_eq!(ours.header, DdsHeaderKind::Dx10 { srgb: true });
    let sizes: Vec<(u32, u32)> = ours.levels.iter().map(|l| (l.width, l.height)).collect();
    assert_eq!(
        sizes,
        vec![
            (211, 211),
            (105, 105),
            (52, 52),
            (26, 26),
            (13, 13),
            (6, 6),
            (3, 3),
            (1, 1)
        ]
    );
    for l in &ours.levels {
        let (bw, bh) = bc1::block_dims(l.width as usize, l.height as usize);
        assert_eq!(l.blocks.len(), bw * bh);
        assert!(l
            .blocks
            .iter()
            .all(|b| b.c0 > b.c1 || (b.c0 == b.c1 && b.indices == 0)));
    }

    let dds = ddsfile::Dds::read(&mut &bytes[..]).expect("ddsfile reads it");
    assert_eq!(dds.get_num_mipmap_levels(), 8);
    assert_eq!(
        dds.get_dxgi_format(),
        Some(ddsfile::DxgiFormat::BC1_UNorm_sRGB)
    );
    let blocks: Vec<u8> = ours
        .levels
        .iter()
        .flat_map(|l| l.blocks.iter().flat_map(Block::to_bytes))
        .collect();
    assert_eq!(dds.data, blocks, "ddsfile sees the bytes we wrote");
}

#[test]
fn legacy_header_holds_the_seam_aware_encoding() {
    let (out, report) = process("cube/cube_gradient_128.glb", "legacy", &["--no-mips"]);
    let bytes = std::fs::read(dds_path(&out, &report)).unwrap();
    let dds = ddsfile::Dds::read(&mut &bytes[..]).expect("ddsfile reads it");
    assert_eq!(dds.get_d3d_format(), Some(ddsfile::D3DFormat::DXT1));
    assert_eq!(dds.get_num_mipmap_levels(), 1);
    assert_eq!(dds.data.len(), 32 * 32 * 8);
    // Without the seam-aware pass, the DDS differs and its seams are worse.
    let (out2, report2) = process(
        "cube/cube_gradient_128.glb",
        "plain",
        &["--no-mips", "--no-seam-aware"],
    );
    let plain = std::fs::read(dds_path(&out2, &report2)).unwrap();
    assert_ne!(plain, bytes);
    let t = &report["textures"][0];
    assert!(report2["textures"][0]["bc1_seam_aware"].is_null());
    assert!(
        t["bc1_seam_aware"]["seam_rms"].as_f64().unwrap() < t["bc1"]["seam_rms"].as_f64().unwrap()
    );
}

/// Pillow's reading of a DDS file, as 8-bit RGB: (width, height, texels).
fn pillow_rgb(path: &Path) -> (u32, u32, Vec<u8>) {
    let script = "import sys\nfrom PIL import Image\nim = Image.open(sys.argv[1]).convert('RGB')\nsys.stdout.write(f'{im.size[0]} {im.size[1]}\\n')\nsys.stdout.flush()\nsys.stdout.buffer.write(im.tobytes())";
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
    let nl = o
        .stdout
        .iter()
        .position(|&c| c == b'\n')
        .expect("a size line");
    let size = std::str::from_utf8(&o.stdout[..nl]).expect("an ASCII size line");
    let (w, h) = size.split_once(' ').expect("width and height");
    (
        w.parse().expect("a width"),
        h.parse().expect("a height"),
        o.stdout[nl + 1..].to_vec(),
    )
}

/// The largest difference, in 8-bit levels, between Pillow's texels and our
/// decoder's. Pillow rounds the palette's 1/3 mixes to integers; ours keeps
/// them exact, so the two agree to within one level.
fn worst_difference(pillow: &[u8], ours: &[f32]) -> f32 {
    assert_eq!(pillow.len(), ours.len());
    pillow
        .iter()
        .zip(ours)
        .map(|(&p, &d)| (f32::from(p) - d * 255.0).abs())
        .fold(0.0f32, f32::max)
}

#[needs(python)]
#[test]
fn pillow_decodes_what_we_encoded() {
    if !common::PYTHON.available() {
        return;
    }
    let (out, report) = process("Duck/Duck.gltf", "pillow", &[]);
    let path = dds_path(&out, &report);
    let (w, h, pillow) = pillow_rgb(&path);
    let ours = read_dds(&std::fs::read(&path).unwrap()).unwrap();
    let l = &ours.levels[0];
    assert_eq!((w, h), (l.width, l.height));
    let decoded = bc1::decode_image(&l.blocks, l.width as usize, l.height as usize).unwrap();
    let worst = worst_difference(&pillow, &decoded);
    assert!(
        worst <= 1.0,
        "Pillow and our decoder differ by {worst} levels"
    );
}

/// A size that is not a multiple of 4 (padded blocks), under both headers
/// Pillow reads. (It does not read BC1_UNORM_SRGB, which differs from
/// BC1_UNORM only in the format code.)
#[needs(python)]
#[test]
fn pillow_reads_padded_blocks_under_both_headers() {
    if !common::PYTHON.available() {
        return;
    }
    let (w, h) = (37usize, 21usize);
    let img: Vec<f32> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = (i % w, i / w);
            [
                ((x * 3 + y) % 97) as f32 / 96.0,
                (y % 31) as f32 / 30.0,
                ((x ^ y) % 256) as f32 / 255.0,
            ]
        })
        .collect();
    let blocks = bc1::encode_image(&img, w, h, 3, bc1::Level::Default).unwrap();
    let ours = bc1::decode_image(&blocks, w, h).unwrap();
    let dir = std::env::temp_dir().join(format!("seamstress-dds-{}-odd", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (n, kind) in [DdsHeaderKind::Legacy, DdsHeaderKind::Dx10 { srgb: false }]
        .into_iter()
        .enumerate()
    {
        let levels = [MipLevel {
            width: w as u32,
            height: h as u32,
            blocks: blocks.clone(),
            alpha: Vec::new(),
        }];
        let path = dir.join(format!("t{n}.dds"));
        std::fs::write(&path, write_dds(&levels, kind).unwrap()).unwrap();
        let (pw, ph, pillow) = pillow_rgb(&path);
        assert_eq!((pw as usize, ph as usize), (w, h), "{kind:?}");
        let worst = worst_difference(&pillow, &ours);
        assert!(worst <= 1.0, "{kind:?}: Pillow differs by {worst} levels");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
