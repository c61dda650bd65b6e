//! Seam-aware BC1 on the shared models, under every GPU decoder: what it
//! buys over a regular encoder, what it costs, what `robust` gives up
//! against a single-decoder target, and the α trade-off.
//!
//! `cargo bench --bench seam_aware` runs the whole pipeline (seams judged,
//! erased, encoded) and prints, from its reports:
//! 1. per model × decoder: seam_rms over the seams closed for the regular
//!    and the seam-aware (`robust`) encodings, their ratio, and PSNR against
//!    the erased texture (the one BC1 compresses) with the cost;
//! 2. per model and target (`ideal`, `nvidia`, `amd`, `robust`): the regular
//!    encoder's milliseconds and PSNR under each decoder (it fits its blocks
//!    to the target's palettes), and the seam-aware stage's milliseconds and
//!    seam_rms under each decoder;
//! 3. the α curve under `robust`: the worst ratio and worst cost over the
//!    three decoders.

use std::path::PathBuf;

use seamstress::model::{self, LoadOptions, Model};
use seamstress::pipeline::{self, DecoderMetrics, Metrics, ProcessOptions, Target};

const MODELS: [&str; 5] = [
    "cube/cube_gradient_1024.glb",
    "blub/blub.glb",
    "Fox/Fox.gltf",
    "Duck/Duck.gltf",
    "CesiumMan/CesiumMan.gltf",
];
const DECODERS: [&str; 3] = ["ideal", "nvidia", "amd"];
const TARGETS: [Target; 4] = [Target::Ideal, Target::Nvidia, Target::Amd, Target::Robust];
const ALPHAS: [f64; 6] = [8.0, 16.0, 32.0, 48.0, 128.0, 256.0];

fn load(rel: &str) -> Model {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel);
    model::load(&path, &LoadOptions::default()).expect("model loads")
}

struct Run {
    regular: Metrics,
    shipped: Metrics,
    encode_ms: u64,
    seam_aware_ms: u64,
}

fn run(m: &Model, rel: &str, target: Target, alpha: f64) -> Run {
    let opts = ProcessOptions {
        decoder: target,
        seam_weight: alpha,
        // Level 0 is what the table compares; the chain would only add time.
        mips: false,
        ..ProcessOptions::default()
    };
    let out = pipeline::run(m, rel, 0, &opts).expect("pipeline runs");
    let t = out.report.textures.into_iter().next().expect("a texture");
    Run {
        regular: t.bc1.expect("regular BC1"),
        shipped: t.bc1_seam_aware.expect("seam-aware BC1"),
        encode_ms: t.timings_ms.encode,
        seam_aware_ms: t.timings_ms.seam_aware,
    }
}

fn under<'a>(m: &'a Metrics, d: &str) -> &'a DecoderMetrics {
    &m.decoders.as_ref().expect("per decoder")[d]
}

fn name(rel: &str) -> &str {
    rel.rsplit('/').next().unwrap_or(rel)
}

fn main() {
    let alpha = seamstress::pipeline::DEFAULT_SEAM_WEIGHT;
    let models: Vec<(&str, Model)> = MODELS.iter().map(|r| (*r, load(r))).collect();

    println!("seam_rms over the seams closed, 8-bit levels; PSNR (dB) over inside texels");
    println!("against the erased texture; target robust, α = {alpha}\n");
    println!(
        "{:<24} {:<7} {:>9} {:>9} {:>7} {:>9} {:>9} {:>8}",
        "model", "decoder", "bc1", "bc1_sa", "ratio", "bc1 dB", "sa dB", "cost dB"
    );
    for (rel, m) in &models {
        let r = run(m, rel, Target::Robust, alpha);
        for d in DECODERS {
            let (b, s) = (under(&r.regular, d), under(&r.shipped, d));
            let (br, sr) = (
                b.seam_rms_closed.unwrap_or(0.0),
                s.seam_rms_closed.unwrap_or(0.0),
            );
            let (bp, sp) = (
                b.encoding_psnr.unwrap_or(0.0),
                s.encoding_psnr.unwrap_or(0.0),
            );
            println!(
                "{:<24} {:<7} {:>9.3} {:>9.3} {:>7.2} {:>9.2} {:>9.2} {:>8.3}",
                name(rel),
                d,
                br,
                sr,
                sr / br,
                bp,
                sp,
                bp - sp
            );
        }
    }

    let runs: Vec<Vec<Run>> = models
        .iter()
        .map(|(rel, m)| TARGETS.iter().map(|t| run(m, rel, *t, alpha)).collect())
        .collect();
    let per_target = |title: &str, cell: &dyn Fn(&Run) -> String| {
        println!("\n{title}");
        print!("{:<24}", "model");
        for t in TARGETS {
            print!(" {:>28}", t.name());
        }
        println!();
        for ((rel, _), rs) in models.iter().zip(&runs) {
            print!("{:<24}", name(rel));
            for r in rs {
                print!(" {:>28}", cell(r));
            }
            println!();
        }
    };
    let joined = |m: &Metrics, f: &dyn Fn(&DecoderMetrics) -> f64, digits: usize| {
        DECODERS
            .iter()
            .map(|d| format!("{:.digits$}", f(under(m, d))))
            .collect::<Vec<_>>()
            .join("/")
    };
    per_target(
        "Each target, the regular encoder: encode ms, and PSNR (dB) against the erased texture under ideal / nvidia / amd:",
        &|r| {
            let psnr = joined(&r.regular, &|d| d.encoding_psnr.unwrap_or(0.0), 2);
            format!("{} ms {psnr}", r.encode_ms)
        },
    );
    per_target(
        "Each target, seam-aware: ms, and seam_rms (closed) under ideal / nvidia / amd:",
        &|r| {
            let rms = joined(&r.shipped, &|d| d.seam_rms_closed.unwrap_or(0.0), 3);
            format!("{} ms {rms}", r.seam_aware_ms)
        },
    );

    println!("\nα under robust: worst ratio to the regular encoding / worst cost (dB) over the decoders:");
    print!("{:<24}", "model");
    for a in ALPHAS {
        print!(" {:>16}", format!("α={a}"));
    }
    println!();
    for (rel, m) in &models {
        print!("{:<24}", name(rel));
        for a in ALPHAS {
            let r = run(m, rel, Target::Robust, a);
            let (mut ratio, mut cost) = (0.0f64, f64::NEG_INFINITY);
            for d in DECODERS {
                let (b, s) = (under(&r.regular, d), under(&r.shipped, d));
                ratio =
                    ratio.max(s.seam_rms_closed.unwrap_or(0.0) / b.seam_rms_closed.unwrap_or(1.0));
                cost = cost.max(b.encoding_psnr.unwrap_or(0.0) - s.encoding_psnr.unwrap_or(0.0));
            }
            print!(" {:>16}", format!("{ratio:.2} / {cost:.3}"));
        }
        println!();
    }
}
