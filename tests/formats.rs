//! BC7 and KTX2 through the whole job: the files hold what the report
//! measures, an independent decoder reads them, and the seam-aware BC7
//! keeps the erased seams closed.

use std::path::PathBuf;

use seamstress::container::dds::{read_dds, DdsHeader};
use seamstress::container::ktx2::read_ktx2;
use seamstress::container::{BlockFormat, ColorSpace, EncodedTexture};
use seamstress::model::{self, LoadOptions, Texture};
use seamstress::pipeline::{self, Container, Format, Output, ProcessOptions};

mod common;

const MODEL: &str = "examples/cube_gradient_128.glb";

fn run(opts: &ProcessOptions) -> Output {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(MODEL);
    let m = model::load(&path, &LoadOptions::default()).unwrap();
    pipeline::run(&m, MODEL, 0, opts).unwrap_or_else(|e| panic!("{MODEL}: {e}"))
}

fn file<'a>(out: &'a Output, name: &str) -> &'a [u8] {
    &out.files
        .iter()
        .find(|f| f.name == name)
        .unwrap_or_else(|| panic!("no output file {name}"))
        .bytes
}

fn bc7() -> ProcessOptions {
    ProcessOptions {
        format: Format::Bc7,
        ..ProcessOptions::default()
    }
}

/// texture2ddecoder's BC7 decoding of level 0, as RGB in 8 bits.
fn independent_rgb(t: &EncodedTexture) -> Vec<u8> {
    let (w, h) = (t.width as usize, t.height as usize);
    let mut px = vec![0u32; w * h];
    texture2ddecoder::decode_bc7(&t.levels[0], w, h, &mut px).unwrap();
    px.iter()
        .flat_map(|p| {
            let [b, g, r, _] = p.to_le_bytes();
            [r, g, b]
        })
        .collect()
}

fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum();
    10.0 * (255.0f64.powi(2) * a.len() as f64 / se).log10()
}

#[test]
fn a_bc7_dds_holds_every_level_and_decodes_as_the_report_says() {
    let out = run(&bc7());
    let t = &out.report.textures[0];
    assert!(t.bc1.is_none() && t.bc1_seam_aware.is_none());
    let (regular, aware) = (t.bc7.as_ref().unwrap(), t.bc7_seam_aware.as_ref().unwrap());
    eprintln!(
        "bc7 {regular:?}\nseam-aware {aware:?}\nerased {:?}",
        t.erased
    );
    let dds = read_dds(file(&out, t.files.dds.as_deref().unwrap())).unwrap();
    assert_eq!(dds.header, DdsHeader::Dx10);
    let tex = dds.texture;
    assert_eq!(tex.format, BlockFormat::Bc7);
    assert_eq!(tex.color_space, ColorSpace::Srgb);
    assert_eq!(tex.levels.len(), 8, "128² has 8 levels");

    // The file decodes, by a decoder that is not ours, to the erased
    // texture within BC7's error, and to the figure the report gives.
    let erased = Texture::decode(file(&out, &t.files.erased), u32::MAX).unwrap();
    let erased8: Vec<u8> = erased
        .data
        .chunks(erased.channels)
        .flat_map(|px| [px[0], px[1], px[2]].map(|v| (v * 255.0).round() as u8))
        .collect();
    let decoded = independent_rgb(&tex);
    let p = psnr(&erased8, &decoded);
    assert!(p >= 40.0, "BC7 against the erased texture: {p} dB");
    let blocks: Vec<seamstress::bc7::Block> = tex.levels[0]
        .chunks_exact(16)
        .map(|b| seamstress::bc7::Block(b.try_into().unwrap()))
        .collect();
    let ours = seamstress::bc7::decode_image(&blocks, 128, 128).unwrap();
    let ours_rgb: Vec<u8> = ours
        .chunks_exact(4)
        .flat_map(|px| [px[0], px[1], px[2]])
        .collect();
    assert_eq!(
        ours_rgb, decoded,
        "our decoder and texture2ddecoder's differ"
    );

    // Regular BC7 reopens the closed seams (0.27 → 0.88 levels here);
    // seam-aware BC7 keeps them as closed as erasure left them, at a cost
    // of hundredths of a dB.
    let erased_closed = t.erased.seam_rms_closed.unwrap();
    let (r, a) = (
        regular.seam_rms_closed.unwrap(),
        aware.seam_rms_closed.unwrap(),
    );
    assert!(r > 2.0 * erased_closed, "regular BC7 seams at {r}");
    assert!(
        a <= erased_closed + 0.05 && a <= 0.4 * r,
        "seam-aware BC7 seams at {a}, regular at {r}, erased at {erased_closed}"
    );
    assert!(aware.psnr.unwrap() >= regular.psnr.unwrap() - 0.1);
}

#[test]
fn ktx2_holds_the_blocks_the_dds_holds_with_or_without_zstd() {
    let dds = run(&bc7());
    let t = &dds.report.textures[0];
    let from_dds = read_dds(file(&dds, t.files.dds.as_deref().unwrap()))
        .unwrap()
        .texture;
    for zstd in [0, 19] {
        let out = run(&ProcessOptions {
            container: Container::Ktx2,
            zstd,
            ..bc7()
        });
        let t = &out.report.textures[0];
        assert_eq!(t.files.dds, None);
        let name = t.files.ktx2.as_deref().unwrap();
        assert_eq!(name, "cube_gradient_128.ktx2");
        let bytes = file(&out, name);
        let from_ktx2 = read_ktx2(bytes).unwrap();
        assert_eq!(from_ktx2, from_dds, "zstd {zstd}");
        eprintln!("KTX2, zstd {zstd}: {} bytes", bytes.len());
    }
    // BC1 goes into KTX2 as well.
    let out = run(&ProcessOptions {
        container: Container::Ktx2,
        ..ProcessOptions::default()
    });
    let t = &out.report.textures[0];
    let k = read_ktx2(file(&out, t.files.ktx2.as_deref().unwrap())).unwrap();
    assert_eq!((k.format, k.levels.len()), (BlockFormat::Bc1, 8));
    assert!(t.bc1_seam_aware.is_some() && t.bc7.is_none());
}

#[test]
fn bc7_options_that_cannot_hold_are_refused() {
    let patch = |json: &str| {
        pipeline::OptionPatch::from_json(json.as_bytes())
            .and_then(|p| p.resolve(&ProcessOptions::default()))
    };
    assert!(patch(r#"{"format": "bc7", "alpha": "bc3"}"#).is_err());
    assert!(patch(r#"{"zstd": 3}"#).is_err());
    assert!(patch(r#"{"container": "ktx2", "zstd": 23}"#).is_err());
    let ok = patch(r#"{"format": "bc7", "container": "ktx2", "zstd": 22, "bc7_level": "fast"}"#)
        .unwrap();
    assert_eq!(
        (ok.format, ok.container, ok.zstd),
        (Format::Bc7, Container::Ktx2, 22)
    );
    // Jobs stored before BC7 said "dds" for BC1.
    assert_eq!(patch(r#"{"format": "dds"}"#).unwrap().format, Format::Bc1);
}

/// From the command line: the rewritten model refers to a BC7 DDS through
/// `MSFT_texture_dds`, and with KTX2 files to the erased PNG alone.
#[test]
fn the_rewritten_model_refers_to_dds_files_only() {
    let dir = std::env::temp_dir().join(format!("seamstress-formats-{}", std::process::id()));
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(MODEL);
    for (flags, dds) in [
        (&["--format", "bc7", "--no-mips"][..], true),
        (
            &[
                "--format",
                "bc7",
                "--no-mips",
                "--container",
                "ktx2",
                "--zstd",
                "3",
            ][..],
            false,
        ),
    ] {
        let out = dir.join(if dds { "dds" } else { "ktx2" });
        let report = common::process_report(&model, &out, flags);
        let files = &report["textures"][0]["files"];
        assert_eq!(files["dds"].is_string(), dds, "{files}");
        assert_eq!(files["ktx2"].is_string(), !dds, "{files}");
        let glb = std::fs::read(out.join("cube_gradient_128.glb")).unwrap();
        let text = String::from_utf8_lossy(&glb);
        assert_eq!(text.contains("MSFT_texture_dds"), dds, "{flags:?}");
        assert!(text.contains("image/png"));
    }
    let _ = std::fs::remove_dir_all(&dir);
}
