//! Seam-aware levels of detail: decimated meshes that reuse the one erased
//! texture with its seams still closed.
//!
//! After Liu, Ferguson, Jacobson and Gingold, "Seamless: Seam erasure and
//! seam-aware decoupling of shape from mesh resolution", ACM Transactions
//! on Graphics 36(6), 2017, §5–6 (seam-aware decimation): an edge collapse
//! that moves a seam vertex along one side of a seam but not the other, or
//! off the straight line the seam's texels were erased along, reopens the
//! seam, because the texture was erased for edges that no longer exist.
//! Collapses along a seam are allowed only where both sides stay
//! consistent ([`seam_constraints`]): on the textures the primitive
//! samples, each chord that would replace a stretch of seam is measured on
//! the erased texture and the DDS and must keep the level's seam RMS
//! within a budget ([`seam_texture`]); meshoptimizer does the rest
//! ([`simplify`]), a stage at a time, each held to 1.5 times plain
//! meshoptimizer's distance to the full mesh. The levels are written into the model with `MSFT_lod`
//! ([`gltf_lod`]) and measured with a sampled Hausdorff distance
//! ([`hausdorff`]) besides the simplifier's own error.

pub mod closed;
pub mod gltf_lod;
pub mod hausdorff;
pub mod ratios;
pub mod seam_constraints;
pub mod seam_texture;
pub mod simplify;

use rayon::prelude::*;
use serde::Serialize;

pub use gltf_lod::{LevelIndices, MeshSource, Primitive};
pub use ratios::{LodRatios, RatiosError, MAX_LODS};
pub use simplify::Constraints;

use std::collections::HashMap;

use seam_constraints::{ChordJudge, ChordRule, Topology};
use seam_texture::TextureJudge;

/// Where no processed texture judges a seam (the primitive samples none):
/// how far (in texels of the largest texture the model samples) a seam
/// vertex may sit off the chord that replaces it, and how far apart its
/// two sides may put it along that chord, and still collapse.
/// A twentieth of a texel moves a bilinear sample by at most 5% of one
/// texel's difference: far below a level of 8-bit colour on erased seams.
pub const SEAM_TOLERANCE_TEXELS: f64 = 0.05;

/// How far (in texels of the largest texture) a chord may stray from the
/// seam it replaces where the texture itself judges it. The judge measures
/// the chord, so a farther one is not wrong; but it spends on one stretch
/// the allowance the level has for all of them: blub reaches 1% of its
/// triangles with 2 or 4 texels and stops at 2% with 8 or none; Fox,
/// CesiumMan, both blub_atlas models and the controller stop within 10%
/// of the same triangle counts with 2, 4, 8 or none (their floors come
/// from the geometric bound, `MAX_ERROR_RATIO` in [`simplify`]).
pub const JUDGED_CHORD_TEXELS: f64 = 4.0;

/// What a level may add to the full mesh's seam RMS (8-bit levels) on
/// the erased texture and on the DDS: four fifths of the bounds each level
/// is held to (0.05 and 0.1), the rest left for the level's seams being
/// weighted by their chords' lengths rather than the seams' they replace.
pub const LEVEL_MARGIN_ERASED: f64 = 0.04;
pub const LEVEL_MARGIN_DDS: f64 = 0.08;

/// Texture size assumed where the model samples no processed texture.
pub const DEFAULT_TEXTURE_SIZE: f64 = 1024.0;

#[derive(Debug, thiserror::Error)]
pub enum LodError {
    #[error("{0}")]
    Model(String),
    /// A level's seams picture could not be drawn.
    #[error("lod seams picture: {0}")]
    Picture(#[from] crate::picture::PictureError),
}

/// One level's geometry over the whole model.
#[derive(Clone, Debug)]
pub struct LevelGeometry {
    pub indices: LevelIndices,
    /// Triangles of the simplified meshes in this level.
    pub triangles: usize,
    /// The simplifier's error, the largest over primitives, relative to the
    /// model's extent (its bounding box's longest side).
    pub error: f64,
    /// Symmetric Hausdorff distance to the full mesh, the largest over
    /// primitives, relative to the model's extent.
    pub hausdorff: f64,
    /// The same of meshoptimizer alone, each primitive simplified to the
    /// same triangle count.
    pub hausdorff_plain: f64,
    /// Welded seam vertices, and those the seam test locked.
    pub seam_vertices: usize,
    pub seam_locked: usize,
    /// Primitives stopped short because a stage's seams would not settle.
    pub unsettled: usize,
}

/// Per-level figures in the report.
#[derive(Clone, Debug, Serialize)]
pub struct LodLevel {
    /// 0 is the full mesh, measured the same way for comparison.
    pub level: usize,
    pub ratio: f64,
    pub triangles: usize,
    /// Seam edges over every processed texture.
    pub seam_edges: usize,
    /// The erased texture's seam RMS on this level's mesh (8-bit levels;
    /// the largest over textures).
    pub seam_rms_erased: Option<f64>,
    /// The seam-aware DDS's (BC1), the same way.
    pub seam_rms_dds: Option<f64>,
    /// The same two over the level's seam edges that run along closed
    /// seams only: the seams left as painted disagree by tens of levels
    /// and would drown what a level does to the closed ones.
    pub seam_rms_closed_erased: Option<f64>,
    pub seam_rms_closed_dds: Option<f64>,
    /// The simplifier's own error relative to the model's extent.
    pub simplifier_error: f64,
    /// Symmetric Hausdorff distance to the full mesh, sampled on both
    /// surfaces, relative to the model's extent.
    pub hausdorff: f64,
    /// The same for meshoptimizer alone (no seam test), each primitive
    /// simplified to the same triangle count as here: what the seam test
    /// costs in shape (at most 1.5 times as far; see `lod` in the README).
    pub hausdorff_plain: f64,
    pub seam_vertices: usize,
    pub seam_vertices_locked: usize,
    /// `<name>.lodN.glb`, with `lod_files`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
    pub textures: Vec<LodTexture>,
}

/// One texture's seam figures on one level's mesh.
#[derive(Clone, Debug, Serialize)]
pub struct LodTexture {
    pub image: usize,
    pub seam_edges: usize,
    pub seam_rms_erased: Option<f64>,
    pub seam_rms_dds: Option<f64>,
    pub seam_rms_closed_erased: Option<f64>,
    pub seam_rms_closed_dds: Option<f64>,
    /// `<name>.lodN.seams.png`, with `pictures` (below level 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seams_picture: Option<String>,
}

struct PrimitiveLevels {
    mesh: usize,
    primitive: usize,
    levels: Vec<simplify::Simplified>,
}

/// The bounding box's longest side over every simplified primitive.
pub fn model_extent(meshes: &[MeshSource]) -> f64 {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for m in meshes {
        for p in &m.primitives {
            if let Primitive::Simplify(d) = p {
                for v in &d.positions {
                    for k in 0..3 {
                        lo[k] = lo[k].min(f64::from(v[k]));
                        hi[k] = hi[k].max(f64::from(v[k]));
                    }
                }
            }
        }
    }
    (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max)
}

/// How the seams constrain the simplifier over a whole model.
pub enum ModelConstraints<'a> {
    /// meshoptimizer alone, for comparison.
    Plain,
    /// The seam test: on the texture each primitive samples (`judges`, by
    /// mesh and primitive, asked about chords up to `most` off the seam),
    /// else geometric within `tolerance` (both in UV).
    Seams {
        tolerance: f64,
        most: f64,
        judges: &'a HashMap<(usize, usize), TextureJudge<'a>>,
    },
}

/// Every simplifiable mesh simplified to each ratio under `constraints`.
/// Primitives run in parallel; the result does not depend on how.
pub fn simplify_model(
    meshes: &[MeshSource],
    ratios: &[f64],
    constraints: &ModelConstraints<'_>,
) -> Vec<LevelGeometry> {
    let work: Vec<(usize, usize, &gltf_lod::PrimitiveData)> = meshes
        .iter()
        .enumerate()
        .filter(|(_, m)| m.kept_whole.is_none())
        .flat_map(|(mi, m)| {
            m.primitives
                .iter()
                .enumerate()
                .filter_map(move |(pi, p)| match p {
                    Primitive::Simplify(d) => Some((mi, pi, d)),
                    Primitive::Keep => None,
                })
        })
        .collect();
    let of_primitive = |mesh: usize, primitive: usize| match constraints {
        ModelConstraints::Plain => Constraints::Plain,
        ModelConstraints::Seams {
            tolerance,
            most,
            judges,
        } => Constraints::Seams(ChordRule {
            tolerance: *tolerance,
            judge: judges
                .get(&(mesh, primitive))
                .map(|j| (j as &dyn ChordJudge, *most)),
        }),
    };
    let done: Vec<PrimitiveLevels> = work
        .par_iter()
        .map(|&(mesh, primitive, data)| {
            let m = data.mesh();
            let topo = Topology::new(&m);
            let levels =
                simplify::simplify_levels(&m, &topo, ratios, of_primitive(mesh, primitive));
            PrimitiveLevels {
                mesh,
                primitive,
                levels,
            }
        })
        .collect();

    let extent = model_extent(meshes).max(f64::MIN_POSITIVE);
    let mut out = Vec::with_capacity(ratios.len());
    for k in 0..ratios.len() {
        let mut level = LevelGeometry {
            indices: LevelIndices::new(),
            triangles: 0,
            error: 0.0,
            hausdorff: 0.0,
            hausdorff_plain: 0.0,
            seam_vertices: 0,
            seam_locked: 0,
            unsettled: 0,
        };
        for (mi, m) in meshes.iter().enumerate() {
            if m.kept_whole.is_none() {
                level.indices.insert(mi, vec![None; m.primitives.len()]);
            }
        }
        for p in &done {
            let s = &p.levels[k];
            level.triangles += s.indices.len() / 3;
            level.error = level.error.max(s.error / extent);
            level.hausdorff = level.hausdorff.max(s.hausdorff / extent);
            level.hausdorff_plain = level.hausdorff_plain.max(s.hausdorff_plain / extent);
            level.seam_vertices += s.locks.seam;
            level.seam_locked += s.locks.seam_locked;
            level.unsettled += usize::from(s.unsettled);
            if let Some(prims) = level.indices.get_mut(&p.mesh) {
                prims[p.primitive] = Some(s.indices.clone());
            }
        }
        out.push(level);
    }
    out
}

/// Triangles of the simplifiable meshes at full detail.
pub fn full_triangles(meshes: &[MeshSource]) -> usize {
    meshes
        .iter()
        .filter(|m| m.kept_whole.is_none())
        .flat_map(|m| &m.primitives)
        .map(|p| match p {
            Primitive::Simplify(d) => d.indices.len() / 3,
            Primitive::Keep => 0,
        })
        .sum()
}
