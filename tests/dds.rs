//! DDS files written by `seamstress process`, read back by this crate, by
//! the `ddsfile` crate and by Python's Pillow.

use std::path::{Path, PathBuf};
use std::process::Command;

use seamstress::bc1::dds::{read_dds, DdsHeaderKind};
use seamstress::bc1::{self, Block};

mod common;

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
    // 211² is not a multiple of 4: every level is padded by edge replication.
    let (out, report) = process(
        "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
        "mips",
        &["--mips", "--dx10"],
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
    let (out, report) = process("cube/cube_gradient_128.glb", "legacy", &[]);
    let bytes = std::fs::read(dds_path(&out, &report)).unwrap();
    let dds = ddsfile::Dds::read(&mut &bytes[..]).expect("ddsfile reads it");
    assert_eq!(dds.get_d3d_format(), Some(ddsfile::D3DFormat::DXT1));
    assert_eq!(dds.get_num_mipmap_levels(), 1);
    assert_eq!(dds.data.len(), 32 * 32 * 8);
    // Without the seam-aware pass, the DDS differs and its seams are worse.
    let (out2, report2) = process("cube/cube_gradient_128.glb", "plain", &["--no-seam-aware"]);
    let plain = std::fs::read(dds_path(&out2, &report2)).unwrap();
    assert_ne!(plain, bytes);
    let t = &report["textures"][0];
    assert!(report2["textures"][0]["bc1_seam_aware"].is_null());
    assert!(
        t["bc1_seam_aware"]["seam_rms"].as_f64().unwrap() < t["bc1"]["seam_rms"].as_f64().unwrap()
    );
}

/// Pillow decodes the 1/3 mixes to integers; our decoder keeps them exact,
/// so the two agree to within one level.
#[test]
fn pillow_decodes_what_we_encoded() {
    if !common::PYTHON.available() {
        return;
    }
    let (out, report) = process("Duck/Duck.gltf", "pillow", &[]);
    let path = dds_path(&out, &report);
    let script = "import sys\nfrom PIL import Image\nim = Image.open(sys.argv[1]).convert('RGB')\nsys.stdout.buffer.write(im.tobytes())";
    let o = Command::new("python3")
        .args(["-c", script, path.to_str().unwrap()])
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "Pillow failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let ours = read_dds(&std::fs::read(&path).unwrap()).unwrap();
    let l = &ours.levels[0];
    let decoded = bc1::decode_image(&l.blocks, l.width as usize, l.height as usize).unwrap();
    assert_eq!(o.stdout.len(), decoded.len());
    let worst = o
        .stdout
        .iter()
        .zip(&decoded)
        .map(|(&p, &d)| (f32::from(p) - d * 255.0).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst <= 1.0,
        "Pillow and our decoder differ by {worst} levels"
    );
}
