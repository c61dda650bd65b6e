//! The `fast` and `default` levels, sixteen blocks at a time.
//!
//! Each lane of an [`F`] holds one block's value of a variable, so every
//! step of the per-block algorithm is one element-wise operation across
//! the group: the compiler turns those into SIMD instructions, and no step
//! ever mixes lanes. A block's result therefore does not depend on the
//! blocks that share its group, and [`encode_group`] with one block copied
//! into every lane is how a single block is encoded.
//!
//! Per block (`fast`): principal axis by power iteration, endpoints at the
//! extreme projections with a 1/16 inset, rounded to the nearest 565
//! levels; indices by projection (exact for the float palette); one
//! least-squares refit of the endpoints whose 565 levels are chosen
//! exactly for the fixed indices; the solid-mix candidate for blocks of low
//! spread. `default` then tries single texels moved across each palette
//! boundary and every texel shifted one position (each with a refit), and
//! a short local search over neighbouring 565 endpoint pairs. At every step
//! a lane keeps the lower-error candidate.

// Index loops over lanes and texels are the point here: they are what the
// compiler vectorises, and several arrays share each index.
#![allow(clippy::needless_range_loop)]

// Inlining as in `encode`: forced in optimised builds, for the one-line
// lane operations only in builds with debug assertions.

use std::ops::{Add, Div, Mul, Sub};

use super::block::Block;
use super::encode::{solid_pair, ROUND_MAGIC};

pub(crate) const LANES: usize = 16;

#[derive(Clone, Copy, Debug)]
pub(crate) struct F(pub(crate) [f32; LANES]);

macro_rules! lanewise {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for F {
            type Output = F;
            #[inline(always)]
            fn $f(self, o: F) -> F {
                let mut r = [0.0f32; LANES];
                for l in 0..LANES {
                    r[l] = self.0[l] $op o.0[l];
                }
                F(r)
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

impl F {
    #[inline(always)]
    fn splat(v: f32) -> F {
        F([v; LANES])
    }

    #[inline(always)]
    fn min(self, o: F) -> F {
        let mut r = [0.0f32; LANES];
        for l in 0..LANES {
            r[l] = if self.0[l] < o.0[l] {
                self.0[l]
            } else {
                o.0[l]
            };
        }
        F(r)
    }

    #[inline(always)]
    fn max(self, o: F) -> F {
        let mut r = [0.0f32; LANES];
        for l in 0..LANES {
            r[l] = if self.0[l] > o.0[l] {
                self.0[l]
            } else {
                o.0[l]
            };
        }
        F(r)
    }

    #[inline(always)]
    fn abs(self) -> F {
        let mut r = [0.0f32; LANES];
        for l in 0..LANES {
            r[l] = self.0[l].abs();
        }
        F(r)
    }

    /// Lane-wise `if a < b { x } else { y }`.
    #[inline(always)]
    fn lt_select(a: F, b: F, x: F, y: F) -> F {
        let mut r = [0.0f32; LANES];
        for l in 0..LANES {
            r[l] = if a.0[l] < b.0[l] { x.0[l] } else { y.0[l] };
        }
        F(r)
    }

    /// Lane-wise `if a <= b { x } else { y }`.
    #[inline(always)]
    fn le_select(a: F, b: F, x: F, y: F) -> F {
        let mut r = [0.0f32; LANES];
        for l in 0..LANES {
            r[l] = if a.0[l] <= b.0[l] { x.0[l] } else { y.0[l] };
        }
        F(r)
    }

    /// Round to nearest (ties to even) for values in 0..2²².
    #[inline(always)]
    fn round(self) -> F {
        (self + F::splat(ROUND_MAGIC)) - F::splat(ROUND_MAGIC)
    }

    /// Round to nearest for values of either sign below 2²².
    #[inline(always)]
    fn round_any(self) -> F {
        // Adding and removing 1.5·2²³ rounds both signs alike.
        (self + F::splat(ROUND_MAGIC)) - F::splat(ROUND_MAGIC)
    }

    #[inline(always)]
    fn clamp(self, lo: f32, hi: f32) -> F {
        self.max(F::splat(lo)).min(F::splat(hi))
    }

    #[inline(always)]
    fn any_lt(self, v: f32) -> bool {
        self.0.iter().any(|&x| x < v)
    }
}

/// One channel's 565 quantiser: `top` = 31 or 63 levels above 0.
#[derive(Clone, Copy)]
struct Chan {
    top: f32,
    /// Level spacing as a fraction of 255: top/255.
    scale: f32,
}

const CH5: Chan = Chan {
    top: 31.0,
    scale: 31.0 / 255.0,
};
const CH6: Chan = Chan {
    top: 63.0,
    scale: 63.0 / 255.0,
};

#[inline(always)]
fn chan(ch: usize) -> Chan {
    if ch == 1 {
        CH6
    } else {
        CH5
    }
}

impl Chan {
    /// The 8-bit value of level q (bit replication), for integral q, in
    /// float arithmetic: 5 bits: 8q + ⌊q/4⌋; 6 bits: 4q + ⌊q/16⌋. The
    /// floors are roundings of q/4 − 3/8 and q/16 − 15/32, whose fractional
    /// parts stay within ±1/2.
    #[inline(always)]
    fn expand(self, q: F) -> F {
        if self.top > 31.0 {
            q * F::splat(4.0) + (q * F::splat(1.0 / 16.0) - F::splat(15.0 / 32.0)).round_any()
        } else {
            q * F::splat(8.0) + (q * F::splat(0.25) - F::splat(3.0 / 8.0)).round_any()
        }
    }

    /// Nearest level to v (0..255).
    #[inline(always)]
    fn nearest(self, v: F) -> F {
        let q = (v.clamp(0.0, 255.0) * F::splat(self.scale)).round();
        let lo = (q - F::splat(1.0)).max(F::splat(0.0));
        let hi = (q + F::splat(1.0)).min(F::splat(self.top));
        let dq = (self.expand(q) - v).abs();
        let dlo = (self.expand(lo) - v).abs();
        let dhi = (self.expand(hi) - v).abs();
        let (best, d) = (F::lt_select(dlo, dq, lo, q), dlo.min(dq));
        F::lt_select(dhi, d, hi, best)
    }

    /// Largest level q ≤ top−1 whose value is ≤ v (0 below the first).
    #[inline(always)]
    fn floor(self, v: F) -> F {
        let v = v.clamp(0.0, 255.0);
        let q = (v * F::splat(self.scale) - F::splat(0.5))
            .round()
            .clamp(0.0, self.top - 1.0);
        // The estimate is within one level; correct it either way.
        let up = (q + F::splat(1.0)).min(F::splat(self.top - 1.0));
        let q = F::le_select(self.expand(up), v, up, q);
        let down = (q - F::splat(1.0)).max(F::splat(0.0));
        F::lt_select(v, self.expand(q), down, q)
    }
}

/// Eight blocks' texels on the 0..255 scale: `c[ch][k]` is channel `ch` of
/// texel `k` in every lane.
#[derive(Clone, Copy)]
pub(crate) struct Group {
    pub(crate) c: [[F; 16]; 3],
    pub(crate) w: [F; 16],
}

#[derive(Clone, Copy)]
struct Ends {
    a: [F; 3],
    b: [F; 3],
}

impl Group {
    /// Raw values in, clamped to \[0, 1\] (NaN to 0) and scaled to 0..255.
    #[cfg_attr(not(debug_assertions), inline(always))]
    pub(crate) fn sanitize(&mut self) {
        for ch in 0..3 {
            for k in 0..16 {
                // `max` keeps its second operand when the first is NaN.
                let v = self.c[ch][k].max(F::splat(0.0)).min(F::splat(1.0));
                self.c[ch][k] = v * F::splat(255.0);
            }
        }
    }

    /// Loads the blocks `bx0..bx0+8` of block row `by` (raw values, see
    /// [`Group::sanitize`]); lanes past the row's last block repeat it, and
    /// texels past the image's edge repeat its last row and column.
    #[cfg_attr(not(debug_assertions), inline(always))]
    pub(crate) fn load(
        rgb: &[f32],
        width: usize,
        height: usize,
        stride: usize,
        bx0: usize,
        by: usize,
    ) -> Group {
        let mut g = Group {
            c: [[F([0.0; LANES]); 16]; 3],
            w: [F([1.0; LANES]); 16],
        };
        let bw = width.div_ceil(4);
        let interior = (bx0 + LANES) * 4 <= width && by * 4 + 4 <= height;
        if interior && stride == 3 {
            g.load_interior::<3>(rgb, width, bx0, by);
        } else if interior && stride == 4 {
            g.load_interior::<4>(rgb, width, bx0, by);
        } else {
            for l in 0..LANES {
                let bx = (bx0 + l).min(bw - 1);
                for j in 0..4 {
                    let y = (by * 4 + j).min(height - 1);
                    for i in 0..4 {
                        let x = (bx * 4 + i).min(width - 1);
                        let base = (y * width + x) * stride;
                        for ch in 0..3 {
                            g.c[ch][j * 4 + i].0[l] = rgb[base + ch];
                        }
                    }
                }
            }
        }
        g
    }

    #[cfg_attr(not(debug_assertions), inline(always))]
    fn load_interior<const S: usize>(&mut self, rgb: &[f32], width: usize, bx0: usize, by: usize) {
        for j in 0..4 {
            let start = ((by * 4 + j) * width + bx0 * 4) * S;
            let row = &rgb[start..start + LANES * 4 * S];
            for l in 0..LANES {
                for i in 0..4 {
                    for ch in 0..3 {
                        self.c[ch][j * 4 + i].0[l] = row[(l * 4 + i) * S + ch];
                    }
                }
            }
        }
    }
}

impl Ends {
    #[cfg_attr(not(debug_assertions), inline(always))]
    fn values(&self) -> ([F; 3], [F; 3]) {
        let mut a = [F::splat(0.0); 3];
        let mut b = [F::splat(0.0); 3];
        for ch in 0..3 {
            a[ch] = chan(ch).expand(self.a[ch]);
            b[ch] = chan(ch).expand(self.b[ch]);
        }
        (a, b)
    }
}

/// Positions (0..=3 along a→b) and weighted squared error for endpoints
/// with values `a`, `b`.
#[cfg_attr(not(debug_assertions), inline(always))]
fn select<const W: bool>(g: &Group, a: &[F; 3], b: &[F; 3]) -> (F, [F; 16]) {
    let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    let inv = F::lt_select(F::splat(0.0), dd, F::splat(3.0) / dd, F::splat(0.0));
    let mut pos = [F::splat(0.0); 16];
    let mut err = F::splat(0.0);
    for k in 0..16 {
        let x0 = g.c[0][k] - a[0];
        let x1 = g.c[1][k] - a[1];
        let x2 = g.c[2][k] - a[2];
        let s = ((x0 * d[0] + x1 * d[1] + x2 * d[2]) * inv).clamp(0.0, 3.0);
        let q = s.round();
        pos[k] = q;
        let f = q * F::splat(1.0 / 3.0);
        let r0 = x0 - d[0] * f;
        let r1 = x1 - d[1] * f;
        let r2 = x2 - d[2] * f;
        let e = r0 * r0 + r1 * r1 + r2 * r2;
        err = err + if W { g.w[k] * e } else { e };
    }
    (err, pos)
}

/// How hard [`encode_group`] works beyond the fast level's single refit.
#[derive(Clone, Copy, Debug)]
pub(crate) struct GroupEffort {
    /// Least-squares refits in a row (at least one is always made).
    pub(crate) refits: u32,
    /// Rounds of single-texel moves across palette boundaries.
    pub(crate) boundary_rounds: u32,
    /// Rounds of local search over neighbouring 565 endpoint pairs.
    pub(crate) search_rounds: u32,
}

type Best = (Ends, F, [F; 16]);

/// Least-squares endpoints for the given positions, their 565 levels
/// chosen exactly for those positions, then re-selected positions and the
/// error. Lanes whose positions do not pin both endpoints get error MAX.
#[cfg_attr(not(debug_assertions), inline(always))]
fn fit<const W: bool>(g: &Group, wsum: F, sx: &[F; 3], pos: &[F; 16]) -> Option<Best> {
    let zero = F::splat(0.0);
    let one = F::splat(1.0);
    let mut sum_b = zero;
    let mut sum_bb = zero;
    let mut sb = [zero; 3];
    for k in 0..16 {
        let beta = pos[k] * F::splat(1.0 / 3.0);
        let wb = if W { g.w[k] * beta } else { beta };
        sum_b = sum_b + wb;
        sum_bb = sum_bb + wb * beta;
        for ch in 0..3 {
            sb[ch] = sb[ch] + wb * g.c[ch][k];
        }
    }
    let aa = wsum - F::splat(2.0) * sum_b + sum_bb;
    let ab = sum_b - sum_bb;
    let bb = sum_bb;
    let det = aa * bb - ab * ab;
    let scale = aa + bb + F::splat(2.0) * ab;
    let limit = F::splat(1e-5) * scale * scale;
    let mut solvable = [false; LANES];
    for l in 0..LANES {
        solvable[l] = det.0[l] > limit.0[l];
    }
    if !solvable.iter().any(|&s| s) {
        return None;
    }
    let inv_det = F::lt_select(limit, det, one / det, zero);
    let mut ends = Ends {
        a: [zero; 3],
        b: [zero; 3],
    };
    for ch in 0..3 {
        let sa = sx[ch] - sb[ch];
        let a_star = (bb * sa - ab * sb[ch]) * inv_det;
        let b_star = (aa * sb[ch] - ab * sa) * inv_det;
        let (qa, qb) = pair(chan(ch), aa, ab, bb, sa, sb[ch], a_star, b_star);
        ends.a[ch] = qa;
        ends.b[ch] = qb;
    }
    let (av, bv) = ends.values();
    let (mut err, pos) = select::<W>(g, &av, &bv);
    for l in 0..LANES {
        if !solvable[l] {
            err.0[l] = f32::MAX;
        }
    }
    Some((ends, err, pos))
}

/// Refits the endpoints to the best candidate's positions and keeps the
/// result where it is better. Returns whether any lane improved.
#[cfg_attr(not(debug_assertions), inline(always))]
fn refit<const W: bool>(g: &Group, wsum: F, sx: &[F; 3], best: &mut Best) -> bool {
    let Some((ends, err, pos)) = fit::<W>(g, wsum, sx, &best.2) else {
        return false;
    };
    let improved = (0..LANES).any(|l| err.0[l] < best.1 .0[l]);
    keep_better(best, ends, err, pos);
    improved
}

/// Moves single texels across the boundaries between neighbouring palette
/// positions (the one closest to each boundary, from either side), refitting
/// the endpoints for each move: a cheap stand-in for cluster fit around the
/// current indices. Returns whether any lane improved.
#[cfg_attr(not(debug_assertions), inline(always))]
fn boundary_round<const W: bool>(g: &Group, wsum: F, sx: &[F; 3], best: &mut Best) -> bool {
    let (av, bv) = best.0.values();
    let d = [bv[0] - av[0], bv[1] - av[1], bv[2] - av[2]];
    let mut proj = [F::splat(0.0); 16];
    for k in 0..16 {
        proj[k] =
            (g.c[0][k] - av[0]) * d[0] + (g.c[1][k] - av[1]) * d[1] + (g.c[2][k] - av[2]) * d[2];
    }
    let start = best.2;
    let mut improved = false;
    for p in 0..3 {
        let (lo_p, hi_p) = (F::splat(p as f32), F::splat(p as f32 + 1.0));
        // Highest projection at position p, lowest at p + 1.
        let mut up = (F::splat(f32::MIN), F::splat(-1.0));
        let mut down = (F::splat(f32::MAX), F::splat(-1.0));
        let half = F::splat(0.5);
        for k in 0..16 {
            let kf = F::splat(k as f32);
            // Positions are integers: |pos − p| < 1/2 means pos = p.
            let cand_up = F::lt_select((start[k] - lo_p).abs(), half, proj[k], F::splat(f32::MIN));
            let cand_dn = F::lt_select((start[k] - hi_p).abs(), half, proj[k], F::splat(f32::MAX));
            up.1 = F::lt_select(up.0, cand_up, kf, up.1);
            up.0 = up.0.max(cand_up);
            down.1 = F::lt_select(cand_dn, down.0, kf, down.1);
            down.0 = down.0.min(cand_dn);
        }
        for (which, to) in [(up.1, hi_p), (down.1, lo_p)] {
            let mut pos = start;
            for k in 0..16 {
                let kf = F::splat(k as f32);
                pos[k] = F::lt_select((which - kf).abs(), half, to, pos[k]);
            }
            if let Some((ends, err, pos)) = fit::<W>(g, wsum, sx, &pos) {
                improved |= (0..LANES).any(|l| err.0[l] < best.1 .0[l]);
                keep_better(best, ends, err, pos);
            }
        }
    }
    // Shift every texel one position down (emptying the top position) or
    // up: the endpoints then extrapolate past the data, which suits blocks
    // of a flat colour with a few outliers.
    for shift in [-1.0f32, 1.0] {
        let mut pos = start;
        for p in pos.iter_mut() {
            *p = (*p + F::splat(shift)).clamp(0.0, 3.0);
        }
        if let Some((ends, err, pos)) = fit::<W>(g, wsum, sx, &pos) {
            improved |= (0..LANES).any(|l| err.0[l] < best.1 .0[l]);
            keep_better(best, ends, err, pos);
        }
    }
    improved
}

/// Moves tried by the local search: (channel, Δa, Δb) in level steps.
const MOVES: [(usize, f32, f32); 24] = {
    let deltas: [(f32, f32); 8] = [
        (1.0, 0.0),
        (-1.0, 0.0),
        (0.0, 1.0),
        (0.0, -1.0),
        (1.0, 1.0),
        (-1.0, -1.0),
        (1.0, -1.0),
        (-1.0, 1.0),
    ];
    let mut m = [(0usize, 0.0f32, 0.0f32); 24];
    let mut ch = 0;
    while ch < 3 {
        let mut d = 0;
        while d < 8 {
            m[ch * 8 + d] = (ch, deltas[d].0, deltas[d].1);
            d += 1;
        }
        ch += 1;
    }
    m
};

/// One round of steepest descent over neighbouring 565 endpoint pairs, with
/// full re-selection for every pair tried. Returns whether any lane moved.
#[cfg_attr(not(debug_assertions), inline(always))]
fn search_round<const W: bool>(g: &Group, best: &mut Best) -> bool {
    let start = best.0;
    let mut step = start;
    let mut step_err = best.1;
    for &(ch, da, db) in MOVES.iter() {
        let c = chan(ch);
        let qa = start.a[ch] + F::splat(da);
        let qb = start.b[ch] + F::splat(db);
        // Steps off the lattice are clamped back onto it: they repeat a
        // candidate already seen and need no special case.
        let mut ends = start;
        ends.a[ch] = qa.clamp(0.0, c.top);
        ends.b[ch] = qb.clamp(0.0, c.top);
        let (av, bv) = ends.values();
        let (mut err, _) = select::<W>(g, &av, &bv);
        for ch2 in 0..3 {
            step.a[ch2] = F::lt_select(err, step_err, ends.a[ch2], step.a[ch2]);
            step.b[ch2] = F::lt_select(err, step_err, ends.b[ch2], step.b[ch2]);
        }
        err = err.min(step_err);
        step_err = err;
    }
    let moved = (0..LANES).any(|l| step_err.0[l] < best.1 .0[l]);
    if moved {
        let (av, bv) = step.values();
        let (err, pos) = select::<W>(g, &av, &bv);
        keep_better(best, step, err, pos);
    }
    moved
}

/// Keeps, lane by lane, whichever of two candidates has the lower error.
#[cfg_attr(not(debug_assertions), inline(always))]
fn keep_better(best: &mut (Ends, F, [F; 16]), ends: Ends, err: F, pos: [F; 16]) {
    let cur = best.1;
    for ch in 0..3 {
        best.0.a[ch] = F::lt_select(err, cur, ends.a[ch], best.0.a[ch]);
        best.0.b[ch] = F::lt_select(err, cur, ends.b[ch], best.0.b[ch]);
    }
    for k in 0..16 {
        best.2[k] = F::lt_select(err, cur, pos[k], best.2[k]);
    }
    best.1 = err.min(cur);
}

/// The best level pair for one channel with fixed positions, scanning two
/// levels of one end and fitting the other (see `encode::best_pair`).
#[cfg_attr(not(debug_assertions), inline(always))]
#[allow(clippy::too_many_arguments)]
fn pair(c: Chan, aa: F, ab: F, bb: F, sa: F, sb: F, a_star: F, b_star: F) -> (F, F) {
    // Scan the end whose reach is shorter (bb ≤ aa: scan a).
    let mut uu = [0.0f32; LANES];
    let mut vv = [0.0f32; LANES];
    let mut su = [0.0f32; LANES];
    let mut sv = [0.0f32; LANES];
    let mut us = [0.0f32; LANES];
    let mut scan_a = [false; LANES];
    for l in 0..LANES {
        let sa_ = bb.0[l] <= aa.0[l];
        scan_a[l] = sa_;
        uu[l] = if sa_ { aa.0[l] } else { bb.0[l] };
        vv[l] = if sa_ { bb.0[l] } else { aa.0[l] };
        su[l] = if sa_ { sa.0[l] } else { sb.0[l] };
        sv[l] = if sa_ { sb.0[l] } else { sa.0[l] };
        us[l] = if sa_ { a_star.0[l] } else { b_star.0[l] };
    }
    let (uu, vv, su, sv) = (F(uu), F(vv), F(su), F(sv));
    let inv_vv = F::splat(1.0) / vv;
    let q0 = c.floor(F(us));
    let mut best_u = q0;
    let mut best_v = q0;
    let mut best_e = F::splat(f32::MAX);
    for du in [0.0f32, 1.0] {
        let qu = q0 + F::splat(du);
        let u = c.expand(qu);
        let v_star = (sv - ab * u) * inv_vv;
        let qv0 = c.floor(v_star);
        let base = uu * u * u - F::splat(2.0) * su * u;
        for dv in [0.0f32, 1.0] {
            let qv = qv0 + F::splat(dv);
            let v = c.expand(qv);
            let e = base + vv * v * v + F::splat(2.0) * ab * u * v - F::splat(2.0) * sv * v;
            best_u = F::lt_select(e, best_e, qu, best_u);
            best_v = F::lt_select(e, best_e, qv, best_v);
            best_e = e.min(best_e);
        }
    }
    let mut qa = [0.0f32; LANES];
    let mut qb = [0.0f32; LANES];
    for l in 0..LANES {
        qa[l] = if scan_a[l] { best_u.0[l] } else { best_v.0[l] };
        qb[l] = if scan_a[l] { best_v.0[l] } else { best_u.0[l] };
    }
    (F(qa), F(qb))
}

/// Encodes a group of blocks. With `W` false the weights are taken as 1.
#[cfg_attr(not(debug_assertions), inline(always))]
pub(crate) fn encode_group<const W: bool>(g: &Group, effort: &GroupEffort) -> [Block; LANES] {
    let one = F::splat(1.0);
    let zero = F::splat(0.0);
    // Weighted sums.
    let mut wsum = zero;
    let mut sx = [zero; 3];
    for k in 0..16 {
        let w = if W { g.w[k] } else { one };
        wsum = wsum + w;
        for ch in 0..3 {
            sx[ch] = sx[ch] + w * g.c[ch][k];
        }
    }
    // A group never has zero total weight in a lane: callers replace such
    // blocks' weights by ones.
    let inv_w = one / wsum;
    let mean = [sx[0] * inv_w, sx[1] * inv_w, sx[2] * inv_w];
    let mut cov = [zero; 6];
    let mut lo = [F::splat(255.0); 3];
    let mut hi = [zero; 3];
    for k in 0..16 {
        let w = if W { g.w[k] } else { one };
        let d = [
            g.c[0][k] - mean[0],
            g.c[1][k] - mean[1],
            g.c[2][k] - mean[2],
        ];
        let wd = [w * d[0], w * d[1], w * d[2]];
        cov[0] = cov[0] + wd[0] * d[0];
        cov[1] = cov[1] + wd[0] * d[1];
        cov[2] = cov[2] + wd[0] * d[2];
        cov[3] = cov[3] + wd[1] * d[1];
        cov[4] = cov[4] + wd[1] * d[2];
        cov[5] = cov[5] + wd[2] * d[2];
        for ch in 0..3 {
            // Zero-weight texels do not widen the range.
            let v = g.c[ch][k];
            let (l_in, h_in) = if W {
                (
                    F::lt_select(zero, w, v, F::splat(255.0)),
                    F::lt_select(zero, w, v, zero),
                )
            } else {
                (v, v)
            };
            lo[ch] = lo[ch].min(l_in);
            hi[ch] = hi[ch].max(h_in);
        }
    }
    let spread = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(hi[2] - lo[2]);

    // Principal axis: power iteration from the widest channel's row.
    let [xx, xy, xz, yy, yz, zz] = cov;
    let mut v = [zero; 3];
    for l in 0..LANES {
        let (a, b, c) = (xx.0[l], yy.0[l], zz.0[l]);
        let row = if a >= b && a >= c {
            [a, xy.0[l], xz.0[l]]
        } else if b >= c {
            [xy.0[l], b, yz.0[l]]
        } else {
            [xz.0[l], yz.0[l], c]
        };
        for ch in 0..3 {
            v[ch].0[l] = row[ch];
        }
    }
    for _ in 0..3 {
        let n = [
            xx * v[0] + xy * v[1] + xz * v[2],
            xy * v[0] + yy * v[1] + yz * v[2],
            xz * v[0] + yz * v[1] + zz * v[2],
        ];
        let m = n[0].abs().max(n[1].abs()).max(n[2].abs());
        // Lanes with no spread keep their (zero) axis.
        let inv = F::lt_select(zero, m, one / m, zero);
        v = [n[0] * inv, n[1] * inv, n[2] * inv];
    }
    let nn = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];

    // Extreme projections, inset by 1/16 of the span.
    let mut plo = F::splat(f32::MAX);
    let mut phi = F::splat(f32::MIN);
    for k in 0..16 {
        let p = (g.c[0][k] - mean[0]) * v[0]
            + (g.c[1][k] - mean[1]) * v[1]
            + (g.c[2][k] - mean[2]) * v[2];
        let (l_in, h_in) = if W {
            (
                F::lt_select(zero, g.w[k], p, F::splat(f32::MAX)),
                F::lt_select(zero, g.w[k], p, F::splat(f32::MIN)),
            )
        } else {
            (p, p)
        };
        plo = plo.min(l_in);
        phi = phi.max(h_in);
    }
    let inset = (phi - plo) * F::splat(1.0 / 16.0);
    let inv_nn = F::lt_select(zero, nn, one / nn, zero);
    let tlo = (plo + inset) * inv_nn;
    let thi = (phi - inset) * inv_nn;
    let mut ends = Ends {
        a: [zero; 3],
        b: [zero; 3],
    };
    for ch in 0..3 {
        // Lanes without an axis fall back to the bounding box.
        let a = F::lt_select(zero, nn, mean[ch] + v[ch] * tlo, lo[ch]);
        let b = F::lt_select(zero, nn, mean[ch] + v[ch] * thi, hi[ch]);
        ends.a[ch] = chan(ch).nearest(a);
        ends.b[ch] = chan(ch).nearest(b);
    }
    let (av, bv) = ends.values();
    let (err, pos) = select::<W>(g, &av, &bv);
    let mut best = (ends, err, pos);

    refit::<W>(g, wsum, &sx, &mut best);

    // Blocks within a few levels: one palette entry between the 565 levels
    // often beats any spread of four.
    if spread.any_lt(24.0) {
        let mut solid = Ends {
            a: [zero; 3],
            b: [zero; 3],
        };
        for ch in 0..3 {
            for l in 0..LANES {
                let [qa, qb] = solid_pair(ch, mean[ch].0[l]);
                solid.a[ch].0[l] = f32::from(qa);
                solid.b[ch].0[l] = f32::from(qb);
            }
        }
        let (av, bv) = solid.values();
        let (err, pos) = select::<W>(g, &av, &bv);
        keep_better(&mut best, solid, err, pos);
    }

    for _ in 1..effort.refits {
        if !refit::<W>(g, wsum, &sx, &mut best) {
            break;
        }
    }
    for _ in 0..effort.boundary_rounds {
        if !boundary_round::<W>(g, wsum, &sx, &mut best) {
            break;
        }
    }
    for _ in 0..effort.search_rounds {
        if !search_round::<W>(g, &mut best) {
            break;
        }
        refit::<W>(g, wsum, &sx, &mut best);
    }

    // Pack: position p along a→b is index [0, 2, 3, 1][p] when a is c0;
    // when b packs larger, b becomes c0 and p is reversed. Index bits are
    // summed in floats, eight texels (16 bits, exact) per half.
    let mut ca = zero;
    let mut cb = zero;
    for (ch, m) in [2048.0f32, 32.0, 1.0].into_iter().enumerate() {
        ca = ca + best.0.a[ch] * F::splat(m);
        cb = cb + best.0.b[ch] * F::splat(m);
    }
    let mut half = [zero; 2];
    let mut weight = one;
    for (k, &p) in best.2.iter().enumerate() {
        if k == 8 {
            weight = one;
        }
        let p = F::lt_select(ca, cb, F::splat(3.0) - p, p);
        let idx = F::lt_select(
            p,
            F::splat(0.5),
            zero,
            F::lt_select(p, F::splat(2.5), p + one, one),
        );
        half[k / 8] = half[k / 8] + idx * weight;
        weight = weight * F::splat(4.0);
    }
    let mut out = [Block::default(); LANES];
    for l in 0..LANES {
        let (a, b) = (ca.0[l] as u16, cb.0[l] as u16);
        out[l] = if a == b {
            Block::solid(a)
        } else {
            Block {
                c0: a.max(b),
                c1: a.min(b),
                indices: half[0].0[l] as u32 | ((half[1].0[l] as u32) << 16),
            }
        };
    }
    out
}
