//! Seam erasure (SPEC §4, after Liu et al., "Seamless").
//!
//! Minimises, over texel values p (all channels share one matrix),
//!
//!   w_seam·pᵀMp + w_change·E_change + w_grad·E_grad + w_c1·E_C1
//!
//! with M the exact quadratic form of Dtotal. The energy is a sum of weighted
//! squares of texel functionals, assembled into one sparse SPD system.
//!
//! # The band
//! Away from the seams only E_change (weight c = w_change/|T| per texel) and
//! E_grad (weight 1 per neighbour pair) act, so the correction δ = p − p0 obeys
//! the screened Poisson equation (c − Δ)δ = 0 there. Along a line, its decaying
//! solution shrinks by r = 1 + c/2 − sqrt(c + c²/4) per texel, and by the
//! maximum principle no solution in 2D decays slower than the 1D one from the
//! same boundary values. So we solve only for texels within `R` texels
//! (Chebyshev distance) of a seam texel, holding the rest at p0, and check the
//! answer: if the largest |δ| on the band's outer ring, times r, exceeds the
//! tolerance (1e-3 levels by default), the true solution may differ outside
//! the band by that much, so R grows by the number of decay steps still needed
//! and the system is solved again.

use std::collections::VecDeque;

use super::grid::TexelGrid;
use super::quadrature::{seam_derivative_points, seam_difference_points, QuadPoint, Segment};
use super::system::{SolveError, SpdSystem};
use super::texels::TexelClasses;
use super::twolevel::Prolongation;
use crate::model::SeamSet;
use faer::sparse::Triplet;

/// How far the erasure may spread (SPEC §4): `local` keeps changes near the
/// seams; `global` lets a colour offset between the two sides spread out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    #[default]
    Local,
    Global,
}

#[derive(Clone, Copy, Debug)]
pub struct EraseWeights {
    pub seam: f64,
    pub change: f64,
    pub grad: f64,
    pub c1: f64,
}

impl EraseWeights {
    pub fn for_mode(mode: Mode) -> Self {
        EraseWeights {
            seam: 1e10,
            change: match mode {
                Mode::Local => 1e4,
                Mode::Global => 1e2,
            },
            grad: 1.0,
            c1: 1e2,
        }
    }
}

#[derive(Clone, Copy, Debug)]
pub struct EraseOptions {
    pub weights: EraseWeights,
    /// Largest change (8-bit levels) that fixing the texels outside the band may cause.
    pub band_tolerance_levels: f64,
    /// Solve for every inside or free texel instead of a band (for tests and comparisons).
    pub full: bool,
    pub solver: Solver,
}

/// How the band's linear system is solved.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Solver {
    /// Direct up to [`DIRECT_LIMIT`] unknowns, iterative above.
    #[default]
    Auto,
    Direct,
    Iterative,
}

impl EraseOptions {
    pub fn new(mode: Mode) -> Self {
        EraseOptions {
            weights: EraseWeights::for_mode(mode),
            band_tolerance_levels: 1e-3,
            full: false,
            solver: Solver::Auto,
        }
    }
}

/// What the solve did, for reports and benchmarks.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct EraseStats {
    pub unknowns: usize,
    /// Band radius in texels (`None`: every texel that may change was solved for).
    pub band_radius: Option<usize>,
    pub solves: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum EraseError {
    #[error(transparent)]
    Solve(#[from] SolveError),
}

/// The quadratic energy's pieces that do not depend on the band.
struct SeamTerms {
    points: Vec<QuadPoint>,
}

impl SeamTerms {
    fn new(grid: &TexelGrid, seams: &SeamSet, w: &EraseWeights) -> Self {
        let total = seams.total_length();
        let mut points = Vec::new();
        if total <= 0.0 {
            return SeamTerms { points };
        }
        for s in &seams.seams {
            let e1 = Segment::from_uv(grid, s.a);
            let e2 = Segment::from_uv(grid, s.b);
            let scale = s.length / total;
            seam_difference_points(grid, e1, e2, w.seam * scale, &mut points);
            let n1 = e1.inward_normal(grid.to_texel(s.a_opposite));
            let n2 = e2.inward_normal(grid.to_texel(s.b_opposite));
            // A half-edge collapsed to a point has no normal; its C1 term is undefined.
            if let (Some(n1), Some(n2)) = (n1, n2) {
                seam_derivative_points(grid, e1, e2, n1, n2, w.c1 * scale, &mut points);
            }
        }
        SeamTerms { points }
    }
}

/// Erases the seams of `input` (interleaved, `channels` per texel).
pub fn erase(
    grid: &TexelGrid,
    input: &[f32],
    channels: usize,
    seams: &SeamSet,
    classes: &TexelClasses,
    opts: &EraseOptions,
) -> Result<(Vec<f32>, EraseStats), EraseError> {
    let w = &opts.weights;
    let terms = SeamTerms::new(grid, seams, w);
    if terms.points.is_empty() {
        return Ok((input.to_vec(), EraseStats::default()));
    }
    let t_count = classes.free.iter().filter(|f| !**f).count().max(1);
    let change = w.change / t_count as f64;
    let movable: Vec<bool> = classes
        .inside
        .iter()
        .zip(&classes.free)
        .map(|(&i, &f)| i || f)
        .collect();

    let max_radius = grid.width.max(grid.height);
    let dist = distance_from(grid, &classes.seam, max_radius);
    // `start`: the texel values an iterative solve starts from.
    let solve = |band: &[bool], start: &[f32]| {
        solve_band(
            grid,
            input,
            channels,
            classes,
            &terms,
            band,
            &dist,
            change,
            w,
            opts.solver,
            start,
        )
    };
    if opts.full {
        let x = solve(&movable, input)?;
        let stats = EraseStats {
            unknowns: x.1,
            band_radius: None,
            solves: 1,
        };
        return Ok((x.0, stats));
    }

    let ratio = decay_per_texel(change / w.grad);
    let decay_len = -1.0 / ratio.ln();
    let tol = opts.band_tolerance_levels / 255.0;
    let mut radius = ((4.0 * decay_len).ceil() as usize).max(4).min(max_radius);
    let mut solves = 0;
    // A wider band starts from the narrower band's solution, which is already
    // right near the seams.
    let mut last: Option<Vec<f32>> = None;
    loop {
        let band: Vec<bool> = dist
            .iter()
            .zip(&movable)
            .map(|(&d, &m)| m && (d as usize) <= radius)
            .collect();
        let (out, unknowns) = solve(&band, last.as_deref().unwrap_or(input))?;
        solves += 1;
        let edge = max_change_at(&out, input, channels, &dist, &band, radius);
        let leak = edge * ratio;
        tracing::debug!(
            radius,
            unknowns,
            edge_change = edge * 255.0,
            "erase band solved"
        );
        if leak <= tol || radius >= max_radius || solves >= 4 {
            let stats = EraseStats {
                unknowns,
                band_radius: Some(radius),
                solves,
            };
            return Ok((out, stats));
        }
        let more = ((leak / tol).ln() * decay_len).ceil() as usize + 1;
        radius = (radius + more).min(max_radius);
        last = Some(out);
    }
}

/// Per-texel decay ratio of the 1D screened Poisson equation c·δ = δ'' (discrete).
fn decay_per_texel(c: f64) -> f64 {
    1.0 + 0.5 * c - (c + 0.25 * c * c).sqrt()
}

/// Chebyshev distance (in texels, capped at `cap`) to the nearest `source` texel.
fn distance_from(grid: &TexelGrid, source: &[bool], cap: usize) -> Vec<u32> {
    let (w, h) = (grid.width, grid.height);
    let mut dist = vec![u32::MAX; w * h];
    let mut queue = VecDeque::new();
    for (i, _) in source.iter().enumerate().filter(|(_, s)| **s) {
        dist[i] = 0;
        queue.push_back(i);
    }
    while let Some(i) = queue.pop_front() {
        let d = dist[i];
        if d as usize >= cap {
            continue;
        }
        let (x, y) = ((i % w) as i64, (i / w) as i64);
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (nx, ny) = (x + dx, y + dy);
                if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                    continue;
                }
                let j = ny as usize * w + nx as usize;
                if dist[j] == u32::MAX {
                    dist[j] = d + 1;
                    queue.push_back(j);
                }
            }
        }
    }
    dist
}

fn max_change_at(
    out: &[f32],
    input: &[f32],
    channels: usize,
    dist: &[u32],
    band: &[bool],
    radius: usize,
) -> f64 {
    let mut m = 0.0f64;
    for (t, _) in band.iter().enumerate().filter(|(_, b)| **b) {
        if dist[t] as usize == radius {
            for c in 0..channels {
                let k = t * channels + c;
                m = m.max(f64::from((out[k] - input[k]).abs()));
            }
        }
    }
    m
}

/// Above this many unknowns, two-level CG beats a direct factorisation.
pub const DIRECT_LIMIT: usize = 1_500_000;
/// Texels this close to a seam texel are their own coarse unknowns.
const COARSE_EXACT_RADIUS: u32 = 3;
/// Lattice spacing of the coarse space elsewhere.
const COARSE_SPACING: usize = 4;

/// The coarse space of [`super::twolevel`]: identity near the seams, bilinear
/// hat functions on a `COARSE_SPACING` lattice elsewhere.
fn coarse_space(grid: &TexelGrid, unknown: &[u32], dist: &[u32]) -> Prolongation {
    let h = COARSE_SPACING;
    let lw = grid.width / h + 2;
    let mut node = vec![u32::MAX; lw * (grid.height / h + 2)];
    let mut count = 0u32;
    let mut entries = Vec::new();
    let mut lattice = Vec::new();
    let mut id = |slot: usize, count: &mut u32, lattice: &mut Vec<bool>| {
        if node[slot] == u32::MAX {
            node[slot] = *count;
            *count += 1;
            lattice.push(true);
        }
        node[slot]
    };
    for (t, &u) in unknown.iter().enumerate() {
        if u == u32::MAX {
            continue;
        }
        if dist[t] <= COARSE_EXACT_RADIUS {
            let c = count;
            count += 1;
            lattice.push(false);
            entries.push(Triplet::new(u, c, 1.0));
            continue;
        }
        let (x, y) = (t % grid.width, t / grid.width);
        let (cx, cy) = (x / h, y / h);
        let fx = (x - cx * h) as f64 / h as f64;
        let fy = (y - cy * h) as f64 / h as f64;
        for (dx, dy, w) in [
            (0, 0, (1.0 - fx) * (1.0 - fy)),
            (1, 0, fx * (1.0 - fy)),
            (0, 1, (1.0 - fx) * fy),
            (1, 1, fx * fy),
        ] {
            if w > 0.0 {
                let c = id((cy + dy) * lw + cx + dx, &mut count, &mut lattice);
                entries.push(Triplet::new(u, c, w));
            }
        }
    }
    Prolongation {
        coarse: count as usize,
        lattice,
        entries,
    }
}

/// Assembles and solves the energy with the texels in `band` as unknowns.
#[allow(clippy::too_many_arguments)]
fn solve_band(
    grid: &TexelGrid,
    input: &[f32],
    channels: usize,
    classes: &TexelClasses,
    terms: &SeamTerms,
    band: &[bool],
    dist: &[u32],
    change: f64,
    w: &EraseWeights,
    solver: Solver,
    start: &[f32],
) -> Result<(Vec<f32>, usize), EraseError> {
    let mut unknown = vec![u32::MAX; grid.len()];
    let mut n = 0u32;
    for (t, _) in band.iter().enumerate().filter(|(_, b)| **b) {
        unknown[t] = n;
        n += 1;
    }
    let mut sys = SpdSystem::new(&unknown, n as usize, channels);
    let zero = [0.0f64; 4];
    let p0 = |t: usize| -> [f64; 4] {
        let mut v = [0.0; 4];
        for c in 0..channels {
            v[c] = f64::from(input[t * channels + c]);
        }
        v
    };

    for q in &terms.points {
        sys.add_square(q.weight, &q.taps, &zero, input);
    }
    // Free texels are outside T; a vanishing anchor keeps a free cluster with
    // no path to an inside texel from leaving the system singular.
    let free_anchor = change * 1e-6;
    let (wd, ht) = (grid.width, grid.height);
    for (t, _) in band.iter().enumerate().filter(|(_, b)| **b) {
        let weight = if classes.free[t] { free_anchor } else { change };
        sys.add_anchor(weight, t as u32, &p0(t));
        let (x, y) = (t % wd, t / wd);
        let movable = |s: usize| classes.inside[s] || classes.free[s];
        // Each pair once: from the unknown with the smaller index, or from the
        // only unknown when its neighbour is held fixed.
        for (nx, ny) in [
            (x.wrapping_sub(1), y),
            (x + 1, y),
            (x, y.wrapping_sub(1)),
            (x, y + 1),
        ] {
            if nx >= wd || ny >= ht {
                continue;
            }
            let s = ny * wd + nx;
            if !movable(s) || (band[s] && s < t) {
                continue;
            }
            let both_inside = classes.inside[t] && classes.inside[s];
            let (a, b) = (p0(t), p0(s));
            let mut target = [0.0; 4];
            if both_inside {
                for c in 0..channels {
                    target[c] = a[c] - b[c];
                }
            }
            sys.add_square(w.grad, &[(t as u32, 1.0), (s as u32, -1.0)], &target, input);
        }
    }

    let unknowns = sys.unknowns();
    let direct = match solver {
        Solver::Auto => unknowns <= DIRECT_LIMIT,
        Solver::Direct => true,
        Solver::Iterative => false,
    };
    let x = if direct {
        sys.solve()?
    } else {
        let coarse = coarse_space(grid, &unknown, dist);
        let mut x0 = vec![0.0; unknowns * channels];
        for (t, &u) in unknown.iter().enumerate() {
            if u != u32::MAX {
                for c in 0..channels {
                    x0[u as usize * channels + c] = f64::from(start[t * channels + c]);
                }
            }
        }
        sys.solve_iterative(&coarse, &x0)?.0
    };
    let mut out = input.to_vec();
    for (t, &u) in unknown.iter().enumerate() {
        if u != u32::MAX {
            for c in 0..channels {
                out[t * channels + c] = x[u as usize * channels + c] as f32;
            }
        }
    }
    Ok((out, unknowns))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{find_seams, UvTriangle, Wrap};

    /// Two triangles of a square, cut apart in UV along their diagonal and
    /// placed in different spots of an 16×16 texture.
    fn setup() -> (TexelGrid, Vec<UvTriangle>, Vec<f32>) {
        let p = [[0.0f32, 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 0.]];
        let tris = vec![
            UvTriangle {
                group: 0,
                positions: [p[0], p[1], p[2]],
                uvs: [[0.1, 0.1], [0.45, 0.12], [0.12, 0.47]],
            },
            UvTriangle {
                group: 0,
                positions: [p[1], p[3], p[2]],
                uvs: [[0.9, 0.55], [0.88, 0.9], [0.55, 0.85]],
            },
        ];
        let grid = TexelGrid {
            width: 16,
            height: 16,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        };
        let data = (0..256)
            .flat_map(|i| {
                let (x, y) = ((i % 16) as f32, (i / 16) as f32);
                [0.3 + 0.02 * x, 0.6 - 0.015 * y]
            })
            .collect();
        (grid, tris, data)
    }

    /// SPEC §4's energy from its definition: seam and C1 integrals by dense
    /// midpoint sampling, the grid terms by plain loops.
    fn energy(
        grid: &TexelGrid,
        seams: &SeamSet,
        cl: &TexelClasses,
        p0: &[f32],
        p: &[f32],
        w: &EraseWeights,
    ) -> f64 {
        let ch = 2;
        let total = seams.total_length();
        let n = 20_000;
        let mut seam = 0.0;
        let mut c1 = 0.0;
        for s in &seams.seams {
            let (e1, e2) = (Segment::from_uv(grid, s.a), Segment::from_uv(grid, s.b));
            let n1 = e1.inward_normal(grid.to_texel(s.a_opposite)).unwrap();
            let n2 = e2.inward_normal(grid.to_texel(s.b_opposite)).unwrap();
            let h = 1e-5;
            let deriv = |q: [f64; 2], nn: [f64; 2], c: usize| {
                (grid.sample(p, ch, c, [q[0] + h * nn[0], q[1] + h * nn[1]])
                    - grid.sample(p, ch, c, [q[0] - h * nn[0], q[1] - h * nn[1]]))
                    / (2.0 * h)
            };
            for k in 0..n {
                let g = (k as f64 + 0.5) / n as f64;
                for c in 0..ch {
                    let d = grid.sample(p, ch, c, e1.at(g)) - grid.sample(p, ch, c, e2.at(g));
                    seam += s.length / total * d * d / n as f64;
                    let dd = deriv(e1.at(g), n1, c) + deriv(e2.at(g), n2, c);
                    c1 += s.length / total * dd * dd / n as f64;
                }
            }
        }
        let t_count = cl.free.iter().filter(|f| !**f).count() as f64;
        let mut change = 0.0;
        let mut grad = 0.0;
        for t in 0..grid.len() {
            for c in 0..ch {
                let k = t * ch + c;
                if !cl.free[t] {
                    change += f64::from(p[k] - p0[k]).powi(2) / t_count;
                }
            }
            let (x, y) = (t % 16, t / 16);
            let movable = |s: usize| cl.inside[s] || cl.free[s];
            for s in [(x + 1 < 16).then(|| t + 1), (y + 1 < 16).then(|| t + 16)]
                .into_iter()
                .flatten()
            {
                if movable(t) && movable(s) {
                    let scale = if cl.inside[t] && cl.inside[s] {
                        1.0
                    } else {
                        0.0
                    };
                    for c in 0..ch {
                        let d = f64::from(p[t * ch + c] - p[s * ch + c])
                            - scale * f64::from(p0[t * ch + c] - p0[s * ch + c]);
                        grad += d * d;
                    }
                }
            }
        }
        w.seam * seam + w.change * change + w.grad * grad + w.c1 * c1
    }

    #[test]
    fn solution_is_a_stationary_point_of_the_energy() {
        let (grid, tris, p0) = setup();
        let seams = find_seams(&tris, 16, 16);
        assert_eq!(seams.seams.len(), 1);
        let cl = TexelClasses::new(&grid, &tris, &seams);
        let mut opts = EraseOptions::new(Mode::Local);
        // Moderate weights keep the finite differences well conditioned.
        opts.weights.seam = 1e4;
        opts.full = true;
        let (x, _) = erase(&grid, &p0, 2, &seams, &cl, &opts).unwrap();
        let w = opts.weights;
        let e0 = energy(&grid, &seams, &cl, &p0, &x, &w);
        let movable: Vec<usize> = (0..grid.len())
            .filter(|&t| cl.inside[t] || cl.free[t])
            .collect();
        // Along any direction over the unknowns, E(x ± εd) − E(x) is second order.
        let mut rng = 0x9e37_79b9u32;
        for _ in 0..5 {
            let mut d = vec![0.0f32; x.len()];
            for &t in &movable {
                for c in 0..2 {
                    rng ^= rng << 13;
                    rng ^= rng >> 17;
                    rng ^= rng << 5;
                    d[t * 2 + c] = (rng % 2001) as f32 / 1000.0 - 1.0;
                }
            }
            let eps = 1e-3f32;
            let shifted =
                |s: f32| -> Vec<f32> { x.iter().zip(&d).map(|(a, b)| a + s * b).collect() };
            let up = energy(&grid, &seams, &cl, &p0, &shifted(eps), &w);
            let down = energy(&grid, &seams, &cl, &p0, &shifted(-eps), &w);
            let slope = (up - down) / (2.0 * f64::from(eps));
            let curvature = (up + down - 2.0 * e0) / f64::from(eps).powi(2);
            assert!(curvature > 0.0, "energy must curve upwards");
            // The slope at a minimum vanishes relative to the curvature scale.
            assert!(
                slope.abs() < 1e-3 * curvature.sqrt().max(1.0),
                "slope {slope} (curvature {curvature}, e0 {e0})"
            );
        }
        // And the solution beats the input by a wide margin.
        assert!(e0 < energy(&grid, &seams, &cl, &p0, &p0, &w));
    }
}
