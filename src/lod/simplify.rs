//! One primitive simplified to each ratio of its triangles by
//! meshoptimizer, under the seam test of [`super::seam_constraints`] (Liu
//! et al., "Seamless", ACM TOG 36(6), 2017, §5).
//!
//! meshoptimizer already collapses a seam vertex only along its seam, onto
//! a seam neighbour, with both wedges moving together. What it does not
//! know is the texture: that both sides must keep mapping the merged edge
//! the way the texture was erased for. Locks carry that test, and a lock
//! decided once on the full mesh holds for all time, though a seam vertex
//! that cannot go now may go once its neighbours have (or the other way
//! round). So the mesh is simplified in stages, each at most halving it,
//! the locks decided again before each stage on the seams as they are then
//! and against the original seam (so that deviations do not add up), and
//! each stage's result checked; the levels follow one another, each
//! starting from the one before.

use std::collections::HashMap;

use meshopt::SimplifyOptions;

use super::hausdorff::Reference;
use super::seam_constraints::{Budget, ChordRule, LockCounts, Topology};

/// Rounds of "simplify, check, lock what went wrong" per stage before the
/// level stops where it is. Each stage frees only seam vertices whose
/// chords were tested, so the check has nothing to find unless the
/// simplifier collapses along a seam in a way the flags did not foresee.
const MAX_ROUNDS: usize = 3;

/// Each stage aims at this fraction of its input's triangles: small enough
/// steps that seam vertices held in one stage (beside a neighbour that
/// went) are reconsidered before the simplifier has spent the collapses
/// elsewhere, few enough stages (seven down to 1%) to stay cheap.
const STAGE_SHRINK: f64 = 0.5;

/// Stages per level at most; a stage that removes nothing ends the level
/// earlier (the seams allow no more).
const MAX_STAGES: usize = 32;

/// A stage whose result strays further from the full mesh than this times
/// what meshoptimizer alone strays at the same triangle count is not
/// taken: past it the seams held cost more shape than the level is worth,
/// and the level stops (after a shorter step has been tried). The bound
/// each level is held to.
const MAX_ERROR_RATIO: f64 = 1.5;

/// Steps tried per stage: the full one, then each half the last.
const STEP_TRIES: usize = 3;

/// Triangles sampled per side when a stage's distance to the full mesh is
/// measured (for [`MAX_ERROR_RATIO`], on every stage, against meshoptimizer
/// at the same count; the last stage's are the report's figures): enough
/// to find a dent a few triangles wide, few enough to keep a
/// 100 000-triangle mesh's stages to tens of milliseconds each.
const STAGE_SAMPLED_TRIANGLES: usize = 4_000;

/// How much a normal's deviation counts against position error in the
/// simplifier's quadrics: the weight gltfpack gives normals.
const NORMAL_WEIGHT: f32 = 0.5;

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
#[derive(Clone, Copy)]
pub enum Constraints<'a> {
    /// The seam test: what a chord must satisfy to replace a stretch of
    /// seam.
    Seams(ChordRule<'a>),
    /// meshoptimizer alone (its own seam handling): what the seam test is
    /// measured against.
    Plain,
}

/// One simplified level of one primitive.
#[derive(Clone, Debug)]
pub struct Simplified {
    /// Into the same vertices as the input.
    pub indices: Vec<u32>,
    /// The simplifier's error, in the mesh's units: over stages, the sum of
    /// each stage's (a bound on the distance to the full mesh).
    pub error: f64,
    /// What the seam test holds on this level's seams.
    pub locks: LockCounts,
    /// Stages made from the full mesh.
    pub stages: usize,
    /// A stage's seams would not settle; the level stopped before it.
    pub unsettled: bool,
    /// Symmetric Hausdorff distance to the full mesh, in the mesh's units;
    /// and meshoptimizer's alone at the same triangle count.
    pub hausdorff: f64,
    pub hausdorff_plain: f64,
}

/// Simplifies `mesh` to about `ratio` of its triangles.
pub fn simplify(
    mesh: &Mesh<'_>,
    topo: &Topology,
    ratio: f64,
    constraints: Constraints<'_>,
) -> Simplified {
    simplify_levels(mesh, topo, &[ratio], constraints)
        .pop()
        .expect("one level per ratio")
}

/// The mesh as meshoptimizer is given it: one vertex per position and UVs.
///
/// meshoptimizer treats every vertex that shares its position with another
/// as a discontinuity, and moves it only along a seam of exactly two
/// wedges. A flat-shaded mesh has such splits of its normals everywhere:
/// left in, they would lock every vertex; crossed (its `Permissive` mode),
/// a collapse can join a triangle of one UV chart to the other chart's
/// wedge of a seam vertex, which samples the atlas across the gap. With
/// the vertices merged by position and UVs its seams are the UV seams
/// alone; each corner of the result then takes, among the vertices merged
/// into it, the one whose normal faces the simplified triangle best.
struct Wedged {
    indices: Vec<u32>,
    /// Per vertex, 3 floats: the normals averaged over each merged vertex.
    normals: Vec<f32>,
    weights: [f32; 3],
    /// Per merged vertex (by its first vertex), the vertices merged into
    /// it, when more than one.
    members: HashMap<u32, Vec<u32>>,
}

impl Wedged {
    fn new(mesh: &Mesh<'_>) -> Wedged {
        let n = mesh.positions.len();
        let indices: Vec<u32> = mesh
            .indices
            .iter()
            .map(|&i| mesh.uv_wedge[i as usize])
            .collect();
        let mut members: HashMap<u32, Vec<u32>> = HashMap::new();
        for &i in mesh.indices {
            let list = members.entry(mesh.uv_wedge[i as usize]).or_default();
            if !list.contains(&i) {
                list.push(i);
            }
        }
        members.retain(|_, list| list.len() > 1);
        let mut normals = vec![0.0f32; n * 3];
        if let Some(src) = mesh.normals {
            for (&w, list) in &members {
                let mut sum = [0.0f32; 3];
                for &v in list {
                    for k in 0..3 {
                        sum[k] += src[v as usize][k];
                    }
                }
                let len = (sum[0] * sum[0] + sum[1] * sum[1] + sum[2] * sum[2]).sqrt();
                if len > 0.0 {
                    for k in 0..3 {
                        normals[w as usize * 3 + k] = sum[k] / len;
                    }
                }
            }
            for &i in &indices {
                if !members.contains_key(&i) {
                    normals[i as usize * 3..i as usize * 3 + 3].copy_from_slice(&src[i as usize]);
                }
            }
        }
        let weights = [if mesh.normals.is_some() {
            NORMAL_WEIGHT
        } else {
            0.0
        }; 3];
        Wedged {
            indices,
            normals,
            weights,
            members,
        }
    }

    /// One meshoptimizer run from `indices` towards `target` indices, in
    /// the mesh's units.
    fn run(
        &self,
        mesh: &Mesh<'_>,
        indices: &[u32],
        lock: &[bool],
        options: SimplifyOptions,
        target: usize,
    ) -> (Vec<u32>, f64) {
        let mut error = 0.0f32;
        // Sparse: the vertices merged away are still in the buffer, and
        // meshoptimizer would count them among the wedges of their
        // position (and lock it) unless it looks at the indices' vertices
        // only. Absolute: the error stays in the mesh's units, not the
        // subset's extent.
        let options = options | SimplifyOptions::Sparse | SimplifyOptions::ErrorAbsolute;
        let out = meshopt::simplify_with_attributes_and_locks_decoder(
            indices,
            mesh.positions,
            &self.normals,
            &self.weights,
            3 * std::mem::size_of::<f32>(),
            lock,
            target,
            f32::MAX,
            options,
            Some(&mut error),
        );
        (out, f64::from(error))
    }

    /// `indices` (merged vertices) back into the mesh's own vertices.
    fn restore(&self, mesh: &Mesh<'_>, indices: &[u32]) -> Vec<u32> {
        let mut out = Vec::with_capacity(indices.len());
        for t in indices.chunks_exact(3) {
            let t = [t[0], t[1], t[2]];
            let p = t.map(|i| mesh.positions[i as usize].map(f64::from));
            let (d1, d2) = (sub(p[1], p[0]), sub(p[2], p[0]));
            let face = [
                d1[1] * d2[2] - d1[2] * d2[1],
                d1[2] * d2[0] - d1[0] * d2[2],
                d1[0] * d2[1] - d1[1] * d2[0],
            ];
            for i in t {
                let pick = match (self.members.get(&i), mesh.normals) {
                    (Some(list), Some(normals)) => *list
                        .iter()
                        .max_by(|&&a, &&b| {
                            let dot = |v: u32| {
                                let m = normals[v as usize].map(f64::from);
                                m[0] * face[0] + m[1] * face[1] + m[2] * face[2]
                            };
                            dot(a).total_cmp(&dot(b)).then(b.cmp(&a))
                        })
                        .expect("members are never empty"),
                    (Some(list), None) => list[0],
                    (None, _) => i,
                };
                out.push(pick);
            }
        }
        out
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Simplifies `mesh` to about each of `ratios` (decreasing) of its
/// triangles, one level each.
pub fn simplify_levels(
    mesh: &Mesh<'_>,
    topo: &Topology,
    ratios: &[f64],
    constraints: Constraints<'_>,
) -> Vec<Simplified> {
    let triangles = mesh.indices.len() / 3;
    let target_of = |ratio: f64| ((triangles as f64 * ratio).round() as usize).max(1);
    let wedged = Wedged::new(mesh);
    let reference = Reference::new(mesh.positions, mesh.indices, STAGE_SAMPLED_TRIANGLES);
    let distance = |indices: &[u32]| reference.symmetric(mesh.positions, indices);
    let none = vec![false; mesh.positions.len()];
    let plain_with_error = |triangles: usize| {
        wedged.run(
            mesh,
            &wedged.indices,
            &none,
            SimplifyOptions::None,
            triangles * 3,
        )
    };
    let plain_run = |triangles: usize| plain_with_error(triangles).0;
    let Constraints::Seams(rule) = constraints else {
        return ratios
            .iter()
            .map(|&r| {
                let (indices, error) = plain_with_error(target_of(r));
                let h = distance(&indices);
                Simplified {
                    indices: wedged.restore(mesh, &indices),
                    error,
                    locks: LockCounts::default(),
                    stages: 1,
                    unsettled: false,
                    hausdorff: h,
                    hausdorff_plain: h,
                }
            })
            .collect();
    };
    let mut current = wedged.indices.clone();
    let mut budget = topo.budget(mesh, &rule);
    let mut error = 0.0;
    let mut stages = 0;
    let mut unsettled = false;
    let mut floor = false;
    let mut distances = (0.0, 0.0);
    let mut out = Vec::with_capacity(ratios.len());
    // One stage from `current` towards `target` triangles: the result, its
    // error and the chords planned; `None` where the seams would not
    // settle.
    let stage = |current: &[u32], target: usize, budget: Option<&Budget>| {
        let flags = topo.stage_flags(mesh, current, &rule, budget);
        let mut lock = flags.lock;
        for round in 1..=MAX_ROUNDS {
            let (indices, e) = wedged.run(
                mesh,
                current,
                &lock,
                SimplifyOptions::LockBorder,
                target * 3,
            );
            let bad = topo.violations(mesh, current, &indices, &rule);
            if bad.is_empty() {
                return Some((indices, e, flags.planned));
            }
            tracing::debug!(
                round,
                violations = bad.len(),
                "seam edges re-mapped; locking them"
            );
            for (v, l) in lock.iter_mut().enumerate() {
                if bad.binary_search(&topo.weld[v]).is_ok() {
                    *l = true;
                }
            }
        }
        None
    };
    for &ratio in ratios {
        let target = target_of(ratio);
        let mut level_stages = 0;
        while !unsettled && !floor && current.len() / 3 > target && level_stages < MAX_STAGES {
            let now = current.len() / 3;
            let mut step = target.max((now as f64 * STAGE_SHRINK).ceil() as usize);
            let mut taken = None;
            for _ in 0..STEP_TRIES {
                let Some((indices, e, planned)) = stage(&current, step, budget.as_ref()) else {
                    tracing::warn!(ratio, "seams would not settle; the level stops here");
                    unsettled = true;
                    break;
                };
                let reached = indices.len() / 3;
                if reached >= now {
                    // Nothing more can go: the seams hold the rest.
                    break;
                }
                let ours = distance(&indices);
                let plain = distance(&plain_run(reached));
                if ours <= MAX_ERROR_RATIO * plain {
                    taken = Some((indices, e, planned, (ours, plain)));
                    break;
                }
                // The seams held cost too much shape this far: a shorter
                // step, or the floor.
                step = now - (now - reached) / 2;
                if step >= now {
                    break;
                }
            }
            let Some((indices, e, planned, d)) = taken else {
                floor = true;
                break;
            };
            level_stages += 1;
            if let Some(b) = budget.as_mut() {
                b.spend(&planned, &topo.present(&indices));
            }
            current = indices;
            error += e;
            distances = d;
        }
        stages += level_stages;
        out.push(Simplified {
            indices: wedged.restore(mesh, &current),
            error,
            locks: topo
                .stage_flags(mesh, &current, &rule, budget.as_ref())
                .counts,
            stages,
            unsettled,
            hausdorff: distances.0,
            hausdorff_plain: distances.1,
        });
    }
    out
}
