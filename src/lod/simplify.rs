//! One primitive simplified to one ratio of its triangles by meshoptimizer,
//! under the seam test of [`super::seam_constraints`].
//!
//! meshoptimizer already collapses a seam vertex only along its seam, onto
//! a seam neighbour, with both wedges moving together. What it does not
//! know is the texture: it does not check that each side stays collinear
//! in UV with matching length ratios. Locks carry that test, and since the
//! test is made on the full mesh's neighbours while collapses chain, every
//! surviving seam edge is checked afterwards against the seam it replaced;
//! vertices it got wrong are locked and the level made again.

use meshopt::{SimplifyOptions, SimplifyVertex};

use super::seam_constraints::{LockCounts, Topology};

/// Rounds of "simplify, check, lock what went wrong" before giving up and
/// locking every seam vertex (which always passes: no seam edge changes).
/// On the shared models one extra round settles it, where any is needed.
const MAX_ROUNDS: usize = 4;

/// How much a normal's deviation counts against position error in the
/// simplifier's quadrics: the weight gltfpack gives normals.
const NORMAL_WEIGHT: f32 = 0.5;

/// The simplifier's error (relative to the mesh's extent) a level may
/// reach. Where the seam test locks most seams, the last collapses towards
/// a low target stretch triangles from the locked seams across the shape
/// (errors of 10–30% on the atlas models); past a few percent a level is
/// another shape, so it stops there, short of its ratio, and says so.
pub const MAX_RELATIVE_ERROR: f32 = 0.025;

/// No error limit: the comparison runs reach their triangle target.
const NO_ERROR_LIMIT: f32 = f32::MAX;

/// A triangle list over one vertex buffer, as the simplifier reads it.
pub struct Mesh<'a> {
    pub positions: &'a [[f32; 3]],
    pub normals: Option<&'a [[f32; 3]]>,
    /// Every TEXCOORD set, in UV as stored (floats, never quantised).
    pub uv_sets: &'a [Vec<[f32; 2]>],
    pub indices: &'a [u32],
    /// Per vertex, the first vertex with its position and UVs: vertices
    /// that differ only in other attributes (a flat-shaded normal) are one
    /// wedge for the seam test, which is about the texture.
    pub uv_wedge: &'a [u32],
}

/// Whether the seam test constrains the simplifier.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Constraints {
    /// The seam test, with its UV tolerance.
    Seams { tolerance: f64 },
    /// meshoptimizer alone (its own seam handling): what the seam test is
    /// measured against.
    Plain,
}

/// One simplified level of one primitive.
#[derive(Clone, Debug)]
pub struct Simplified {
    /// Into the same vertices as the input.
    pub indices: Vec<u32>,
    /// The simplifier's error, in the mesh's units.
    pub error: f64,
    /// Seam vertices (welded) locked in the last round.
    pub locks: LockCounts,
    /// Rounds made (the last is the one kept).
    pub rounds: usize,
    /// Every seam vertex had to be locked.
    pub seams_frozen: bool,
}

/// Simplifies `mesh` to about `ratio` of its triangles.
pub fn simplify(
    mesh: &Mesh<'_>,
    topo: &Topology,
    ratio: f64,
    constraints: Constraints,
) -> Simplified {
    let triangles = mesh.indices.len() / 3;
    let target = ((triangles as f64 * ratio).round() as usize).max(1) * 3;
    let vertices = mesh.positions.len();
    let normals: Vec<f32> = match mesh.normals {
        Some(n) => n.iter().flatten().copied().collect(),
        None => vec![0.0; vertices * 3],
    };
    let weights = [if mesh.normals.is_some() {
        NORMAL_WEIGHT
    } else {
        0.0
    }; 3];
    let scale = f64::from(meshopt::simplify_scale_decoder(mesh.positions));
    // Permissive: collapses may cross discontinuities of the other
    // attributes (flat-shaded normals would otherwise lock every vertex),
    // while UV seam vertices are protected, so that meshoptimizer moves
    // them only along their seam with both sides together.
    let run = |locks: &[bool], protect: &[bool]| -> (Vec<u32>, f64) {
        let flags: Vec<SimplifyVertex> = locks
            .iter()
            .zip(protect)
            .map(|(&l, &p)| {
                if l {
                    SimplifyVertex::Lock
                } else if p {
                    SimplifyVertex::Protect
                } else {
                    SimplifyVertex::None
                }
            })
            .collect();
        let mut error = 0.0f32;
        let options = match constraints {
            Constraints::Seams { .. } => SimplifyOptions::LockBorder | SimplifyOptions::Permissive,
            Constraints::Plain => SimplifyOptions::Permissive,
        };
        let limit = match constraints {
            Constraints::Seams { .. } => MAX_RELATIVE_ERROR,
            Constraints::Plain => NO_ERROR_LIMIT,
        };
        let indices = meshopt::simplify_with_attributes_and_locks_decoder(
            mesh.indices,
            mesh.positions,
            &normals,
            &weights,
            3 * std::mem::size_of::<f32>(),
            &flags,
            target,
            limit,
            options,
            Some(&mut error),
        );
        (indices, f64::from(error) * scale)
    };

    let Constraints::Seams { tolerance } = constraints else {
        let (indices, error) = run(&vec![false; vertices], &topo.on_seam());
        return Simplified {
            indices,
            error,
            locks: LockCounts::default(),
            rounds: 1,
            seams_frozen: false,
        };
    };
    let (mut locks, protect, mut counts) = topo.seam_locks(mesh, tolerance);
    for round in 1..=MAX_ROUNDS {
        let (indices, error) = run(&locks, &protect);
        let bad = topo.violations(mesh, &indices, tolerance);
        if bad.is_empty() {
            return Simplified {
                indices,
                error,
                locks: counts,
                rounds: round,
                seams_frozen: false,
            };
        }
        tracing::debug!(
            round,
            violations = bad.len(),
            "seam edges re-mapped; locking them"
        );
        for (v, lock) in locks.iter_mut().enumerate() {
            if bad.binary_search(&topo.weld[v]).is_ok() {
                *lock = true;
            }
        }
        counts.seam_locked += bad.len();
    }
    // Never reached on the shared models; kept so that no level ever
    // reopens a seam: with every seam vertex locked no seam edge changes.
    let (frozen, protect, counts) = topo.seam_locks(mesh, -1.0);
    let (indices, error) = run(&frozen, &protect);
    tracing::warn!(ratio, "seams would not settle; every seam vertex locked");
    Simplified {
        indices,
        error,
        locks: counts,
        rounds: MAX_ROUNDS + 1,
        seams_frozen: true,
    }
}
