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
//! same boundary values. Holding the texels beyond distance R at p0 truncates
//! the decaying a·r^d to a·(r^d − r^(2R+2−d)): the band's edge texels keep only
//! (1 − r²) of their true change, and the first texels outside miss
//! a·r^(R+1) = edge·r/(1 − r²), about ten times the edge change in local mode.
//! The first band holds every texel where an estimate of the change
//! ([`FarField`]: the responses to half the input's jump at each seam texel,
//! what each side takes, summed in the plane) reaches a quarter of the
//! tolerance (a sixteenth on smaller mip levels, [`MIP_BAND_MARGIN`]), a
//! thousandth of an 8-bit level (SPEC §4; see [`EraseOptions`]).
//! On Fox that is 1.82 M unknowns, where the largest 1D decay from any one
//! seam texel took 1.97 M; neither needs a second solve. After the solve,
//! wherever the changes of a texel's band neighbours imply a miss above the
//! tolerance at a texel just outside (summed, where the band surrounds it
//! on several sides), the band widens around that texel by the decay steps
//! still needed, and the system is solved again from the previous solution.

use rayon::prelude::*;

use super::assemble::{assemble, SeamBlocks, Weights};
use super::far_field::FarField;
use super::grid::TexelGrid;
use super::multigrid::{self, Node};
use super::quadrature::{seam_derivative_points, seam_difference_points, QuadPoint, Segment};
use super::sparse::Rows;
use super::system::{Cholesky, SolveError};
use super::texels::TexelClasses;
use crate::model::SeamSet;

/// How far the erasure may spread (SPEC §4): `local` keeps changes near the
/// seams; `global` lets a colour offset between the two sides spread out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Change only texels near the seams
    #[default]
    Local,
    /// Let changes spread over the charts, for sides painted with a colour offset
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
    /// Largest change, in 8-bit levels, that fixing the texels outside the
    /// band may cause: SPEC §4 allows a thousandth. (A hundredth would take
    /// Fox from 1.97 M unknowns to 1.56 M and move one stored value in 12.6
    /// million by a level, but the SPEC does not allow it.)
    pub band_tolerance_levels: f64,
    /// How far below the tolerance the first band's estimate reaches
    /// ([`BAND_MARGIN`] or [`MIP_BAND_MARGIN`]).
    pub band_margin: f64,
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
            band_margin: BAND_MARGIN,
            full: false,
            solver: Solver::Auto,
        }
    }
}

/// What the solve did, for reports and benchmarks.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct EraseStats {
    pub unknowns: usize,
    /// The largest Chebyshev distance from a seam texel of any texel solved
    /// for (`None`: every texel that may change was solved for).
    pub band_radius: Option<usize>,
    pub solves: usize,
    /// Unknowns of the solves that moved only the texels around a widening
    /// (see `local_patch`), summed; 0 where none did.
    pub patched: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum EraseError {
    #[error(transparent)]
    Solve(#[from] SolveError),
}

/// The quadratic energy's pieces that do not depend on the band.
struct SeamTerms {
    points: Vec<QuadPoint>,
    /// The input's largest jump across a seam (any channel) at the texels of
    /// each seam cell: what the erasure must remove there.
    jumps: Vec<(u32, f64)>,
}

impl SeamTerms {
    fn new(
        grid: &TexelGrid,
        seams: &SeamSet,
        w: &EraseWeights,
        input: &[f32],
        channels: usize,
    ) -> Self {
        let total = seams.total_length();
        let mut points = Vec::new();
        let mut jumps = Vec::new();
        if total <= 0.0 {
            return SeamTerms { points, jumps };
        }
        for s in &seams.seams {
            let e1 = Segment::from_uv(grid, s.a);
            let e2 = Segment::from_uv(grid, s.b);
            let scale = s.length / total;
            let first = points.len();
            seam_difference_points(grid, e1, e2, w.seam * scale, &mut points);
            for q in &points[first..] {
                let jump = (0..channels)
                    .map(|c| q.apply(input, channels, c).abs())
                    .fold(0.0, f64::max);
                jumps.extend(q.taps.iter().map(|&(t, _)| (t, jump)));
            }
            let n1 = e1.inward_normal(grid.to_texel(s.a_opposite));
            let n2 = e2.inward_normal(grid.to_texel(s.b_opposite));
            // A half-edge collapsed to a point has no normal; its C1 term is undefined.
            if let (Some(n1), Some(n2)) = (n1, n2) {
                seam_derivative_points(grid, e1, e2, n1, n2, w.c1 * scale, &mut points);
            }
        }
        SeamTerms { points, jumps }
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
    erase_within(grid, input, channels, seams, classes, opts, None).map(|e| (e.data, e.stats))
}

/// What [`erase_within`] made.
pub struct Erased {
    pub data: Vec<f32>,
    pub stats: EraseStats,
    /// The band solved for last (`None` where every texel that may change
    /// was): what a solve of nearly the same seams can start from.
    pub band: Option<Vec<bool>>,
}

/// [`erase`], its first band widened to `prior` (a band a solve of nearly
/// the same seams ended with). Where some of the seams of a first solve
/// are spared and the texture solved again, the band the first solve had
/// to grow to is what the second needs too; starting from it saves the
/// second growing solve (the controller's level 0: four solves to three).
pub fn erase_within(
    grid: &TexelGrid,
    input: &[f32],
    channels: usize,
    seams: &SeamSet,
    classes: &TexelClasses,
    opts: &EraseOptions,
    prior: Option<&[bool]>,
) -> Result<Erased, EraseError> {
    let w = &opts.weights;
    let t0 = std::time::Instant::now();
    let max_radius = grid.width.max(grid.height);
    // Both run on one thread each: side by side they take the time of one.
    let (mut terms, dist) = rayon::join(
        || SeamTerms::new(grid, seams, w, input, channels),
        || distance_from(grid, &classes.seam, max_radius),
    );
    let jumps = std::mem::take(&mut terms.jumps);
    if terms.points.is_empty() {
        return Ok(Erased {
            data: input.to_vec(),
            stats: EraseStats::default(),
            band: None,
        });
    }
    let t_count = classes.free.iter().filter(|f| !**f).count().max(1);
    let change = w.change / t_count as f64;
    let movable: Vec<bool> = classes
        .inside
        .par_iter()
        .zip(&classes.free)
        .map(|(&i, &f)| i || f)
        .collect();

    tracing::debug!(
        rss_mb = crate::heap::resident_mb(),
        elapsed_ms = t0.elapsed().as_millis() as u64,
        "seam terms and distances"
    );
    // `start`: the texel values an iterative solve starts from; `held`:
    // those of the texels outside `band`.
    let solve = |band: &[bool], (start, held): (&[f32], &[f32]), seam: &SeamBlocks| {
        solve_band(
            grid,
            (input, held),
            channels,
            classes,
            seam,
            band,
            &dist,
            change,
            w,
            opts.solver,
            start,
        )
    };
    let seam_blocks = || SeamBlocks::new(&terms.points, &movable, input, channels);
    if opts.full {
        let x = solve(&movable, (input, input), &seam_blocks())?;
        let stats = EraseStats {
            unknowns: x.1,
            band_radius: None,
            solves: 1,
            patched: 0,
        };
        return Ok(Erased {
            data: x.0,
            stats,
            band: None,
        });
    }

    let ratio = decay_per_texel(change / w.grad);
    let tol = opts.band_tolerance_levels / 255.0;
    // The first band is found on one thread, the seam blocks summed on the
    // other: neither needs the other.
    let (mut band, seam) = rayon::join(
        || {
            let mut band = first_band(grid, &jumps, &dist, &movable, ratio, tol / opts.band_margin);
            if let Some(prior) = prior.filter(|p| p.len() == band.len()) {
                band.par_iter_mut()
                    .zip(prior)
                    .zip(&movable)
                    .for_each(|((b, &p), &m)| *b |= p && m);
            }
            band
        },
        seam_blocks,
    );
    // The points live on in the blocks. Freed now, their pages (over 20 MB on
    // Fox) serve the band's system instead of fresh ones.
    drop((jumps, terms));
    tracing::debug!(
        rss_mb = crate::heap::resident_mb(),
        elapsed_ms = t0.elapsed().as_millis() as u64,
        "first band chosen"
    );
    let mut solves = 0;
    let mut patched = 0;
    // A wider band starts from the narrower band's solution, which is already
    // right near the seams; where it can, it solves only around the widening
    // (`patch`, see `local_patch`).
    let mut last: Option<Vec<f32>> = None;
    let mut patch: Option<Vec<bool>> = None;
    let no_seam = SeamBlocks::new(&[], &movable, input, channels);
    loop {
        let (out, solved) = match (&patch, &last) {
            (Some(patch), Some(last)) => solve(patch, (last, last), &no_seam)?,
            _ => solve(&band, (last.as_deref().unwrap_or(input), input), &seam)?,
        };
        solves += 1;
        let growth = grow_band(grid, &band, &movable, &out, input, channels, ratio, tol);
        let unknowns = if patch.is_some() {
            patched += solved;
            band.par_iter().filter(|&&b| b).count()
        } else {
            solved
        };
        tracing::debug!(
            rss_mb = crate::heap::resident_mb(),
            elapsed_ms = t0.elapsed().as_millis() as u64,
            unknowns,
            solved,
            leaks = growth.leaks,
            "erase band solved"
        );
        let Some(wider) = growth.band.filter(|_| solves < 4) else {
            let reach = band
                .par_iter()
                .zip(&dist)
                .filter(|(b, _)| **b)
                .map(|(_, &d)| d as usize)
                .max();
            let stats = EraseStats {
                unknowns,
                band_radius: reach,
                solves,
                patched,
            };
            return Ok(Erased {
                data: out,
                stats,
                band: Some(band),
            });
        };
        patch = local_patch(
            grid,
            &band,
            &wider,
            &dist,
            growth.reach + reach_beyond(ratio),
        );
        band = wider;
        last = Some(out);
    }
}

/// How much farther than a widening's own reach (in texels) a local
/// re-solve reaches into the band it widens: [`MIN_BAND`] decay lengths, so
/// that the correction, which dies out from the widening inwards as the
/// change does outwards, is far below the tolerance where it is cut off.
fn reach_beyond(ratio: f64) -> i32 {
    (-MIN_BAND / ratio.ln()).ceil() as i32
}

/// The texels a widened band's solve must move, where the band before it
/// was solved already: the widening, and every texel of `wider` within
/// `reach` (Chebyshev) of it. The energy is quadratic, so the solution on
/// `wider` is the one on `band` plus a correction that satisfies the same
/// system with a right-hand side on the widening alone, and dies out away
/// from it; solving for the correction only within `reach`, the rest held
/// at the last solution, is the whole solve up to what lies beyond.
/// `None` where that reaches a seam's texels (their seam terms are the
/// band's own), or half the band (no saving): the whole band is solved
/// again then.
fn local_patch(
    grid: &TexelGrid,
    band: &[bool],
    wider: &[bool],
    dist: &[u32],
    reach: i32,
) -> Option<Vec<bool>> {
    let mut spread: Vec<i32> = band
        .par_iter()
        .zip(wider)
        .map(|(&b, &w)| if w && !b { reach } else { -1 })
        .collect();
    spread_down(&mut spread, grid.width, grid.height);
    let patch: Vec<bool> = spread
        .par_iter()
        .zip(wider)
        .map(|(&r, &w)| w && r >= 0)
        .collect();
    let touches_seam = patch.par_iter().zip(dist).any(|(&p, &d)| p && d == 0);
    let size = patch.par_iter().filter(|&&p| p).count();
    let whole = wider.par_iter().filter(|&&w| w).count();
    (!touches_seam && 2 * size < whole).then_some(patch)
}

/// The first band: every movable texel where the far-field estimate
/// ([`FarField`]) reaches `level`, and every one within [`MIN_BAND`] decay
/// lengths of a seam (near the seams the C1 term and the bilinear taps
/// shape the change in ways the estimate ignores).
fn first_band(
    grid: &TexelGrid,
    jumps: &[(u32, f64)],
    dist: &[u32],
    movable: &[bool],
    ratio: f64,
    level: f64,
) -> Vec<bool> {
    let field = FarField::new(grid.width, grid.height, jumps, ratio, level);
    let base = (-MIN_BAND / ratio.ln()).ceil() as u32;
    let w = grid.width;
    let mut band = crate::heap::filled(grid.len(), false);
    band.par_chunks_mut(w)
        .zip(dist.par_chunks(w).zip(movable.par_chunks(w)))
        .enumerate()
        .for_each(|(y, (band, (dist, movable)))| {
            let estimate = field.row(y);
            for (x, b) in band.iter_mut().enumerate() {
                *b = movable[x] && (dist[x] <= base || estimate(x) >= level);
            }
        });
    band
}

/// How far below the tolerance the first band's estimate reaches. A leak
/// costs a second solve: on Fox (local mode) margins of 1.5 and 2 leave one
/// (1.69 M and 1.73 M unknowns first, 1.81 M and 1.82 M in the end), 3 and
/// more none (1.78 M at 3, 1.82 M at 4). Fox's texture scaled up to 8192²
/// leaves two leaks at 4 (27.96 M unknowns), each widening then solved only
/// around itself (`local_patch`: 2.1 M, 1.4 M and 1.4 M unknowns, about
/// 2 s each, against 7 s for the whole band again). blub and
/// cube_gradient_1024 have none from 1.5 on;
/// cube_gradient_128, whose change dies out within a dozen texels, has some
/// at every margin tried (six at 3).
pub const BAND_MARGIN: f64 = 4.0;

/// [`BAND_MARGIN`] for a smaller mip level, filtered from an erased one:
/// its sides already agree in value, so what still moves it is mostly the
/// C1 term, which the estimate (made from the jumps) does not see, and its
/// change decays within a few texels, where the coarse estimate is rough.
/// At 4 every level of Fox below the first leaks (level 1 at 386 k unknowns,
/// then a second solve at 415 k, nearly as long as the first), as do the
/// controller's; at 16 none of Fox's levels 1–4 and none of the
/// controller's levels 1–2 does (Fox level 1: 437 k unknowns, one solve).
pub const MIP_BAND_MARGIN: f64 = 16.0;

/// The narrowest band, in decay lengths.
const MIN_BAND: f64 = 2.0;

/// How much a widening may raise the change at the band's edge (see `grow_band`).
const GROWTH_MARGIN: f64 = 10.0;

struct Growth {
    /// The widened band (`None` without leaks).
    band: Option<Vec<bool>>,
    /// Texels just outside the band that may miss more than the tolerance.
    leaks: usize,
    /// The widest widening around a leak, in texels.
    reach: i32,
}

/// Texels per parallel task of [`grow_band`].
const GROW_CHUNK: usize = 1 << 14;

/// Widens the band around each texel just outside it whose implied miss (see
/// the module docs) exceeds `tol`: by as many texels as the decay needs to
/// bring it below, and only there.
#[allow(clippy::too_many_arguments)]
fn grow_band(
    grid: &TexelGrid,
    band: &[bool],
    movable: &[bool],
    out: &[f32],
    input: &[f32],
    ch: usize,
    ratio: f64,
    tol: f64,
) -> Growth {
    let (w, h) = (grid.width, grid.height);
    let decay_len = -1.0 / ratio.ln();
    // The implied miss at each texel just outside the band (0 elsewhere). The
    // fixed texel s sees its band neighbours' changes as a source, which
    // reaches s itself multiplied by the line factor r/(1 − r²) along a
    // straight edge; where the band surrounds s on several sides, each of
    // them pushes, so their changes add (taking one neighbour alone let a
    // notch in the band miss more than the tolerance).
    let leak = |s: usize| {
        if band[s] || !movable[s] {
            return 0.0;
        }
        let (x, y) = (s % w, s / w);
        let mut source = [0.0f64; 4];
        let neighbours = [
            (x > 0).then(|| s - 1),
            (x + 1 < w).then(|| s + 1),
            (y > 0).then(|| s - w),
            (y + 1 < h).then(|| s + w),
        ];
        for t in neighbours.into_iter().flatten().filter(|&t| band[t]) {
            for (c, sc) in source.iter_mut().enumerate().take(ch) {
                *sc += f64::from((out[t * ch + c] - input[t * ch + c]).abs());
            }
        }
        source.into_iter().fold(0.0, f64::max) * ratio / (1.0 - ratio * ratio)
    };
    // Usually there is none: then no texel needs marking.
    let leaks = (0..w * h)
        .into_par_iter()
        .with_min_len(GROW_CHUNK)
        .filter(|&t| leak(t) > tol)
        .count();
    if leaks == 0 {
        return Growth {
            band: None,
            leaks,
            reach: 0,
        };
    }
    // reach[t] ≥ 0: texel t lies within the needed widening of some leak.
    let mut reach = crate::heap::filled(w * h, -1i32);
    reach
        .par_chunks_mut(GROW_CHUNK)
        .enumerate()
        .for_each(|(k, reach)| {
            for (i, r) in reach.iter_mut().enumerate() {
                // Widening next to a leak raises its neighbours' change too:
                // widen those close to the tolerance as well, with a margin.
                let leak = leak(k * GROW_CHUNK + i);
                if leak * GROWTH_MARGIN > tol {
                    *r = ((leak * GROWTH_MARGIN / tol).ln() * decay_len).ceil() as i32 + 1;
                }
            }
        });
    let widest = reach.par_iter().copied().max().unwrap_or(0);
    spread_down(&mut reach, w, h);
    let band = band
        .par_iter()
        .zip(&reach)
        .zip(movable)
        .map(|((&b, &r), &m)| b || (m && r >= 0))
        .collect();
    Growth {
        band: Some(band),
        leaks,
        reach: widest,
    }
}

/// `reach[i] = max over j of reach[j] − chebyshev(i, j)`: two raster passes.
///
/// Each pass takes a row at a time: first what the finished row before it
/// gives (three neighbours each, no dependence along the row, so the loop
/// vectorises), then the one running maximum along the row.
fn spread_down(reach: &mut [i32], w: usize, h: usize) {
    if w == 0 {
        return;
    }
    let from_row = |row: &mut [i32], prev: &[i32]| {
        for (x, r) in row.iter_mut().enumerate() {
            let left = prev[x.saturating_sub(1)];
            let right = prev[(x + 1).min(w - 1)];
            *r = (*r).max(left.max(prev[x]).max(right) - 1);
        }
    };
    for y in 0..h {
        let (before, rest) = reach.split_at_mut(y * w);
        let row = &mut rest[..w];
        if y > 0 {
            from_row(row, &before[(y - 1) * w..]);
        }
        for x in 1..w {
            row[x] = row[x].max(row[x - 1] - 1);
        }
    }
    for y in (0..h).rev() {
        let (head, after) = reach.split_at_mut((y + 1) * w);
        let row = &mut head[y * w..];
        if y + 1 < h {
            from_row(row, &after[..w]);
        }
        for x in (0..w - 1).rev() {
            row[x] = row[x].max(row[x + 1] - 1);
        }
    }
}

/// Per-texel decay ratio of the 1D screened Poisson equation c·δ = δ'' (discrete).
fn decay_per_texel(c: f64) -> f64 {
    1.0 + 0.5 * c - (c + 0.25 * c * c).sqrt()
}

/// Chebyshev distance (in texels, capped at `cap`) to the nearest `source`
/// texel: `cap` less how far a reach of `cap` from every source spreads.
fn distance_from(grid: &TexelGrid, source: &[bool], cap: usize) -> Vec<u32> {
    let cap = cap.min(i32::MAX as usize / 2) as i32;
    // Far below any reach, and far enough above i32::MIN to step down from.
    let none = i32::MIN / 2;
    let mut reach: Vec<i32> = source
        .par_iter()
        .map(|&s| if s { cap } else { none })
        .collect();
    spread_down(&mut reach, grid.width, grid.height);
    reach.par_iter().map(|&r| (cap - r.max(0)) as u32).collect()
}

/// Above this many unknowns, multigrid CG beats a direct factorisation.
pub const DIRECT_LIMIT: usize = 100_000;
/// Texels this close to a seam texel stay unknowns of their own on every
/// multigrid level (see [`super::multigrid`]).
const EXACT_RADIUS: u32 = 1;

/// Assembles and solves the energy with the texels in `band` as unknowns,
/// the others held at `held`.
#[allow(clippy::too_many_arguments)]
fn solve_band(
    grid: &TexelGrid,
    (input, held): (&[f32], &[f32]),
    channels: usize,
    classes: &TexelClasses,
    seam: &SeamBlocks,
    band: &[bool],
    dist: &[u32],
    change: f64,
    w: &EraseWeights,
    solver: Solver,
    start: &[f32],
) -> Result<(Vec<f32>, usize), EraseError> {
    let t0 = std::time::Instant::now();
    let (unknown, n) = number_band(band);
    let weights = Weights {
        change,
        free_anchor: change * 1e-6,
        grad: w.grad,
    };
    let direct = match solver {
        Solver::Auto => n <= DIRECT_LIMIT,
        Solver::Direct => true,
        Solver::Iterative => false,
    };
    let ch = channels;
    // The seam entries are summed on one thread; the multigrid's node
    // placement, which needs only the band, takes the other.
    let (assembled, placed) = rayon::join(
        || {
            assemble(
                grid, input, held, channels, classes, seam, &unknown, n, &weights,
            )
        },
        || (!direct).then(|| place_nodes(grid.width, &unknown, n, dist, start, ch)),
    );
    let (a, b) = assembled?;
    tracing::debug!(
        rss_mb = crate::heap::resident_mb(),
        elapsed_ms = t0.elapsed().as_millis() as u64,
        "band assembled"
    );
    let x = match placed {
        None => Cholesky::new(&a.to_csr()?.into_faer())?.solve_interleaved(&b, ch),
        Some((nodes, x0)) => {
            let (x, iterations) = multigrid::solve(a, nodes, b, ch, x0, weights.floor())?;
            tracing::debug!(
                rss_mb = crate::heap::resident_mb(),
                elapsed_ms = t0.elapsed().as_millis() as u64,
                unknowns = n,
                iterations,
                "multigrid solve"
            );
            x
        }
    };
    let mut out = crate::heap::copied(held);
    out.par_chunks_mut(ch)
        .zip(unknown.par_iter())
        .filter(|(_, &u)| u != u32::MAX)
        .for_each(|(o, &u)| {
            for (c, v) in o.iter_mut().enumerate() {
                *v = x[u as usize * ch + c] as f32;
            }
        });
    Ok((out, n))
}

/// Texels per parallel task of [`number_band`].
const NUMBER_CHUNK: usize = 1 << 16;

/// Numbers the band's texels in texel order (`u32::MAX` outside it): each
/// chunk counts its texels, then numbers them from the sum before it.
fn number_band(band: &[bool]) -> (Vec<u32>, usize) {
    let counts: Vec<u32> = band
        .par_chunks(NUMBER_CHUNK)
        .map(|b| b.iter().filter(|&&b| b).count() as u32)
        .collect();
    let firsts: Vec<u32> = counts
        .iter()
        .scan(0u32, |sum, &c| {
            let first = *sum;
            *sum += c;
            Some(first)
        })
        .collect();
    let mut unknown = crate::heap::filled(band.len(), u32::MAX);
    unknown
        .par_chunks_mut(NUMBER_CHUNK)
        .zip(band.par_chunks(NUMBER_CHUNK))
        .zip(firsts)
        .for_each(|((u, b), mut next)| {
            for (u, _) in u.iter_mut().zip(b).filter(|(_, &inside)| inside) {
                *u = next;
                next += 1;
            }
        });
    (unknown, counts.iter().map(|&c| c as usize).sum())
}

/// Texel rows per parallel task of [`place_nodes`].
const PLACE_ROWS: usize = 16;

/// The band's unknowns' places in the hierarchy (exact within
/// [`EXACT_RADIUS`] of a seam texel) and the starting guess, in unknown order.
///
/// Unknowns are numbered in texel order, so each run of texel rows fills a
/// contiguous run of both outputs: the runs are counted, then filled in parallel.
fn place_nodes(
    width: usize,
    unknown: &[u32],
    n: usize,
    dist: &[u32],
    start: &[f32],
    ch: usize,
) -> (Vec<Node>, Vec<f64>) {
    let run = PLACE_ROWS * width;
    let counts: Vec<usize> = unknown
        .par_chunks(run)
        .map(|u| u.iter().filter(|&&u| u != u32::MAX).count())
        .collect();
    let mut nodes = crate::heap::filled(n, Node::Exact);
    let mut x0 = crate::heap::filled(n * ch, 0.0f64);
    let mut parts = Vec::with_capacity(counts.len());
    let (mut rest_n, mut rest_x) = (&mut nodes[..], &mut x0[..]);
    for &c in &counts {
        let (a, b) = std::mem::take(&mut rest_n).split_at_mut(c);
        let (xa, xb) = std::mem::take(&mut rest_x).split_at_mut(c * ch);
        parts.push((a, xa));
        (rest_n, rest_x) = (b, xb);
    }
    parts
        .into_par_iter()
        .enumerate()
        .for_each(|(r, (nodes, x0))| {
            let first = r * run;
            let texels =
                (first..(first + run).min(unknown.len())).filter(|&t| unknown[t] != u32::MAX);
            for ((t, node), x) in texels.zip(nodes.iter_mut()).zip(x0.chunks_exact_mut(ch)) {
                if dist[t] > EXACT_RADIUS {
                    *node = Node::Lattice((t % width) as u32, (t / width) as u32);
                }
                for (xc, &v) in x.iter_mut().zip(&start[t * ch..(t + 1) * ch]) {
                    *xc = f64::from(v);
                }
            }
        });
    (nodes, x0)
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
    fn distance_is_the_capped_chebyshev_distance() {
        let grid = TexelGrid {
            width: 13,
            height: 9,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        };
        let sources = [(2usize, 1usize), (10, 7), (5, 5)];
        let mut source = vec![false; grid.len()];
        for &(x, y) in &sources {
            source[y * 13 + x] = true;
        }
        for cap in [3, 100] {
            let d = distance_from(&grid, &source, cap);
            for y in 0..9usize {
                for x in 0..13usize {
                    let brute = sources
                        .iter()
                        .map(|&(sx, sy)| x.abs_diff(sx).max(y.abs_diff(sy)))
                        .min()
                        .unwrap_or(usize::MAX)
                        .min(cap);
                    assert_eq!(d[y * 13 + x] as usize, brute, "({x},{y}) cap {cap}");
                }
            }
        }
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
