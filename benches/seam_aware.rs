//! Seam-aware BC1 on the shared models: what it buys over a regular encoder,
//! what it costs, and how the seed paper's method (float solve, one
//! rounding) compares with the integer search.
//!
//! `cargo bench --bench seam_aware` prints, per model, seam_rms of the input,
//! the erased texture, the regular BC1 encoding and the seam-aware one, their
//! PSNR and the seam-aware stage's milliseconds; then the trade-off curve
//! (seam_rms against PSNR) over α.

use std::path::PathBuf;
use std::time::Instant;

use seamstress::bc1::seam_aware::{optimise, Problem, SeamAwareOptions};
use seamstress::bc1::{self, Level};
use seamstress::model::{self, find_seams, LoadOptions};
use seamstress::seam::erase::{erase, EraseOptions, Mode};
use seamstress::seam::metric::seam_points_texel_length;
use seamstress::seam::{colour_channels, psnr, SeamMetric, TexelClasses, TexelGrid};

const MODELS: [&str; 4] = [
    "cube/cube_gradient_1024.glb",
    "blub/blub.glb",
    "Fox/Fox.gltf",
    "Duck/Duck.gltf",
];
const ALPHAS: [f64; 6] = [4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0];

struct Case {
    name: String,
    width: usize,
    height: usize,
    input_rgb: Vec<f32>,
    target: Vec<f32>,
    inside: Vec<bool>,
    metric: SeamMetric,
    points: Vec<seamstress::seam::quadrature::QuadPoint>,
    compared: usize,
    input_rms: f64,
    erased_rms: f64,
}

fn quantise_rgb(data: &[f32], ch: usize) -> Vec<f32> {
    data.chunks(ch)
        .flat_map(|c| {
            if ch < 3 {
                [c[0]; 3]
            } else {
                [c[0], c[1], c[2]]
            }
        })
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() / 255.0)
        .collect()
}

fn prepare(rel: &str) -> Case {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel);
    let m = model::load(&path, &LoadOptions::default()).expect("model loads");
    let b = &m.bindings[0];
    let t = &b.texture;
    let grid = TexelGrid::of(b);
    let seams = find_seams(&b.triangles, t.width, t.height);
    let classes = TexelClasses::new(&grid, &b.triangles, &seams);
    let (erased, _) = erase(
        &grid,
        &t.data,
        t.channels,
        &seams,
        &classes,
        &EraseOptions::new(Mode::Local),
    )
    .expect("erasure");
    let metric = SeamMetric::new(&grid, &seams);
    let compared = colour_channels(t.channels);
    let target = quantise_rgb(&erased, t.channels);
    let input_rgb = quantise_rgb(&t.data, t.channels);
    Case {
        name: rel.rsplit('/').next().unwrap_or(rel).to_string(),
        width: t.width,
        height: t.height,
        input_rms: metric.seam_rms(&input_rgb, 3, compared).unwrap_or(0.0),
        erased_rms: metric.seam_rms(&target, 3, compared).unwrap_or(0.0),
        points: seam_points_texel_length(&grid, &seams),
        inside: classes.inside,
        metric,
        compared,
        input_rgb,
        target,
    }
}

/// (seam_rms, psnr) of decoded blocks.
fn measure(c: &Case, blocks: &[bc1::Block]) -> (f64, f64) {
    let d = bc1::decode_image(blocks, c.width, c.height).expect("decodes");
    (
        c.metric.seam_rms(&d, 3, c.compared).unwrap_or(0.0),
        psnr(&d, &c.input_rgb, 3, c.compared, &c.inside).unwrap_or(f64::INFINITY),
    )
}

fn seam_aware(c: &Case, regular: &[bc1::Block], opts: &SeamAwareOptions) -> (f64, f64, u128) {
    let mut blocks = regular.to_vec();
    let p = Problem {
        width: c.width,
        height: c.height,
        target: &c.target,
        channels: 3,
        inside: &c.inside,
        points: &c.points,
    };
    let t = Instant::now();
    optimise(&p, &mut blocks, opts).expect("seam-aware encoding");
    let ms = t.elapsed().as_millis();
    let (r, q) = measure(c, &blocks);
    (r, q, ms)
}

fn main() {
    let default_alpha = seamstress::pipeline::DEFAULT_SEAM_WEIGHT;
    let cases: Vec<Case> = MODELS.iter().map(|m| prepare(m)).collect();
    let regular: Vec<Vec<bc1::Block>> = cases
        .iter()
        .map(|c| {
            bc1::encode_image(&c.target, c.width, c.height, 3, Level::Default).expect("encodes")
        })
        .collect();

    println!("seam_rms in 8-bit levels; PSNR in dB over inside texels against the input; α = {default_alpha}\n");
    println!(
        "{:<22} {:>8} {:>8} {:>8} {:>9} {:>8} {:>9} {:>9} {:>7} {:>9} {:>9}",
        "model",
        "input",
        "erased",
        "bc1",
        "bc1_sa",
        "gain",
        "bc1 dB",
        "sa dB",
        "ΔdB",
        "sa ms",
        "seed rms"
    );
    for (c, reg) in cases.iter().zip(&regular) {
        let (br, bp) = measure(c, reg);
        let (sr, sp, ms) = seam_aware(
            c,
            reg,
            &SeamAwareOptions {
                alpha: default_alpha,
                ..Default::default()
            },
        );
        let seed = SeamAwareOptions {
            alpha: default_alpha,
            integer_search: false,
            ..Default::default()
        };
        let (seed_r, seed_p, _) = seam_aware(c, reg, &seed);
        println!(
            "{:<22} {:>8.3} {:>8.3} {:>8.3} {:>9.3} {:>7.2}× {:>9.2} {:>9.2} {:>7.3} {:>9} {:>9.3}",
            c.name,
            c.input_rms,
            c.erased_rms,
            br,
            sr,
            br / sr,
            bp,
            sp,
            sp - bp,
            ms,
            seed_r
        );
        let _ = seed_p;
    }

    println!("\nTrade-off over α (seam_rms / ΔPSNR against the regular encoding):");
    print!("{:<22}", "model");
    for a in ALPHAS {
        print!(" {:>16}", format!("α={a}"));
    }
    println!();
    for (c, reg) in cases.iter().zip(&regular) {
        let (_, bp) = measure(c, reg);
        print!("{:<22}", c.name);
        for a in ALPHAS {
            let (r, p, _) = seam_aware(
                c,
                reg,
                &SeamAwareOptions {
                    alpha: a,
                    ..Default::default()
                },
            );
            print!(" {:>16}", format!("{r:.3} / {:+.3}", p - bp));
        }
        println!();
    }

    println!("\nSeed method (float solve, one rounding) against the integer search, α = {default_alpha}:");
    println!(
        "{:<22} {:>10} {:>10} {:>10} {:>10}",
        "model", "bc1 rms", "seed rms", "seed ΔdB", "ours rms"
    );
    for (c, reg) in cases.iter().zip(&regular) {
        let (br, bp) = measure(c, reg);
        let seed = SeamAwareOptions {
            alpha: default_alpha,
            integer_search: false,
            ..Default::default()
        };
        let (sr, sp, _) = seam_aware(c, reg, &seed);
        let (or, _, _) = seam_aware(
            c,
            reg,
            &SeamAwareOptions {
                alpha: default_alpha,
                ..Default::default()
            },
        );
        println!(
            "{:<22} {:>10.3} {:>10.3} {:>10.3} {:>10.3}",
            c.name,
            br,
            sr,
            sp - bp,
            or
        );
    }
}
