//! Seam-aware levels of detail on the shared models: per model and level,
//! triangles, seam edges, the erased texture's and the DDS's seam RMS on
//! the level's mesh, the simplifier's error and the Hausdorff distance
//! (relative to the model's extent), with the seam test and with plain
//! meshoptimizer side by side (at the triangle counts the seam test
//! reached); the time per level (`ms`: simplifying, the Hausdorff distance
//! and measuring the seams, averaged over the levels); and a 100 000-triangle
//! mesh simplified with the seam test, timed.
//!
//! `cargo bench --bench lod` (models missing from ../shared are skipped).

use std::path::{Path, PathBuf};
use std::time::Instant;

use seamstress::budget::Limits;
use seamstress::lod::seam_constraints::{ChordRule, Topology};
use seamstress::lod::simplify::{simplify, Constraints, Mesh};
use seamstress::model::{DirResolver, LoadOptions};
use seamstress::pipeline::job::{run_job, JobInput, JobSettings};
use seamstress::pipeline::lod::{make_levels, Constrained};
use seamstress::pipeline::NoSink;
use seamstress::pipeline::ProcessOptions;

const RATIOS: [f64; 6] = [0.5, 0.25, 0.1, 0.05, 0.02, 0.01];

const MODELS: [(&str, &str); 6] = [
    ("blub", "shared:blub/blub.glb"),
    ("Fox", "shared:Fox/Fox.gltf"),
    ("CesiumMan", "shared:CesiumMan/CesiumMan.gltf"),
    ("blub_atlas_black", "shared:blub_atlas/blub_atlas_black.glb"),
    (
        "blub_atlas_dilated",
        "shared:blub_atlas/blub_atlas_dilated.glb",
    ),
    (
        "controller",
        "repo:tests/assets/oculus-touch-v3/oculus-touch-v3-left.glb",
    ),
];

fn resolve(spec: &str) -> PathBuf {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    match spec.split_once(':') {
        Some(("shared", rel)) => repo.join("../shared/assets").join(rel),
        Some(("repo", rel)) => repo.join(rel),
        _ => PathBuf::from(spec),
    }
}

fn f(v: Option<f64>) -> String {
    v.map_or("-".into(), |v| format!("{v:.3}"))
}

fn model(name: &str, path: &Path) {
    let main = std::fs::read(path).expect("model reads");
    let files = DirResolver::new(path.parent().unwrap()).expect("folder");
    let file_name = path.file_name().unwrap().to_str().unwrap();
    let input = JobInput {
        name: file_name,
        main: &main,
        files: &files,
    };
    let settings = JobSettings {
        process: ProcessOptions::default(),
        load: LoadOptions::default(),
        limits: Limits {
            max_memory: u64::MAX,
        },
    };
    let out = run_job(&input, &settings, &mut NoSink).expect("job runs");
    let Some(rewritten) = out.files.iter().find(|f| f.name == file_name) else {
        println!("{name}: no rewritten model");
        return;
    };
    println!("\n{name}");
    for t in &out.report.textures {
        println!(
            "  {}: seam_rms_closed on the full mesh, erased {} / DDS {} (as the job measured it)",
            t.name,
            f(t.erased.seam_rms_closed),
            f(t.bc1_seam_aware.as_ref().and_then(|m| m.seam_rms_closed)),
        );
    }
    println!(
        "{:>5} {:>6} | {:>6} {:>5} {:>7} {:>7} {:>6} {:>6} {:>7} {:>7} {:>5} | {:>6} {:>6} {:>6} {:>7} {:>7} | {:>5}",
        "level", "ratio", "tris", "seams", "rms_er", "rms_dds", "cl_er", "cl_dds", "err", "hausd", "ms",
        "p.tris", "p.cler", "p.cldd", "p.err", "p.haus", "h/p.h"
    );
    let t = Instant::now();
    let seams = make_levels(
        file_name,
        &rewritten.bytes,
        None,
        &out.report,
        &out.files,
        &files,
        &RATIOS,
        Constrained::Seams,
    )
    .expect("levels");
    let ms = t.elapsed().as_secs_f64() * 1e3 / (RATIOS.len() + 1) as f64;
    // Plain meshoptimizer at the triangle counts the seam test reached, so
    // that errors compare at the same count.
    let full = seams.levels[0].triangles.max(1) as f64;
    let reached: Vec<f64> = seams.levels[1..]
        .iter()
        .map(|l| l.triangles as f64 / full)
        .collect();
    let plain = make_levels(
        file_name,
        &rewritten.bytes,
        None,
        &out.report,
        &out.files,
        &files,
        &reached,
        Constrained::Plain,
    )
    .expect("levels");
    for (s, p) in seams.levels.iter().zip(&plain.levels) {
        // Against meshoptimizer alone with each primitive at the same
        // triangle count (the plain run above asks for the model's ratio).
        let ratio = if s.hausdorff_plain > 0.0 {
            format!("{:.2}", s.hausdorff / s.hausdorff_plain)
        } else {
            "-".into()
        };
        println!(
            "{:>5} {:>6} | {:>6} {:>5} {:>7} {:>7} {:>6} {:>6} {:>7.4} {:>7.4} {:>5.0} | {:>6} {:>6} {:>6} {:>7.4} {:>7.4} | {:>5}",
            s.level,
            s.ratio,
            s.triangles,
            s.seam_edges,
            f(s.seam_rms_erased),
            f(s.seam_rms_dds),
            f(s.seam_rms_closed_erased),
            f(s.seam_rms_closed_dds),
            s.simplifier_error,
            s.hausdorff,
            ms,
            p.triangles,
            f(p.seam_rms_closed_erased),
            f(p.seam_rms_closed_dds),
            p.simplifier_error,
            p.hausdorff,
            ratio,
        );
    }
    let held: Vec<String> = seams.levels[1..]
        .iter()
        .map(|l| format!("{}/{}", l.seam_vertices_locked, l.seam_vertices))
        .collect();
    println!(
        "  seam vertices held by the seam test / left, per level: {}",
        held.join(" ")
    );
}

/// A `n`×`n` quad grid over a bumpy sheet, its UVs cut along the middle
/// column into two charts placed apart, straight along the cut.
fn grid(n: usize) -> (Vec<[f32; 3]>, Vec<[f32; 2]>, Vec<u32>) {
    let mut positions = Vec::new();
    let mut uvs = Vec::new();
    let half = n / 2;
    let mut index = vec![[0u32; 2]; (n + 1) * (n + 1)];
    for y in 0..=n {
        for x in 0..=n {
            let (fx, fy) = (x as f32 / n as f32, y as f32 / n as f32);
            let p = [fx, fy, 0.05 * (fx * 12.0).sin() * (fy * 9.0).cos()];
            let copies = if x == half { 2 } else { 1 };
            for c in 0..copies {
                let chart = usize::from(x > half || (x == half && c == 1));
                let u = 0.45 * fx + 0.1 * chart as f32;
                index[y * (n + 1) + x][c] = positions.len() as u32;
                if copies == 1 {
                    index[y * (n + 1) + x][1] = positions.len() as u32;
                }
                positions.push(p);
                uvs.push([u, fy]);
            }
        }
    }
    let mut indices = Vec::new();
    for y in 0..n {
        for x in 0..n {
            let side = usize::from(x >= half);
            let v = |xx: usize, yy: usize| index[yy * (n + 1) + xx][side];
            indices.extend([v(x, y), v(x + 1, y), v(x, y + 1)]);
            indices.extend([v(x + 1, y), v(x + 1, y + 1), v(x, y + 1)]);
        }
    }
    (positions, uvs, indices)
}

fn large_mesh() {
    let (positions, uvs, indices) = grid(224);
    let sets = [uvs];
    let uv_wedge: Vec<u32> = (0..positions.len() as u32).collect();
    let mesh = Mesh {
        positions: &positions,
        normals: None,
        uv_sets: &sets,
        indices: &indices,
        uv_wedge: &uv_wedge,
    };
    let t = Instant::now();
    let topo = Topology::new(&mesh);
    let rule = ChordRule::geometric(1e-5);
    let s = simplify(&mesh, &topo, 0.1, Constraints::Seams(rule));
    println!(
        "\n{} triangles to {} with the seam test: {:.0} ms ({} stages)",
        indices.len() / 3,
        s.indices.len() / 3,
        t.elapsed().as_secs_f64() * 1e3,
        s.stages
    );
}

fn main() {
    large_mesh();
    for (name, spec) in MODELS {
        let path = resolve(spec);
        if path.exists() {
            model(name, &path);
        } else {
            println!("{name}: {} missing, skipped", path.display());
        }
    }
}
