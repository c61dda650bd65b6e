//! The block encoder: shared tables and helpers, the single-block search of
//! the `best` level, and the dispatch between levels.
//!
//! All work happens on the 0..255 scale in f32, against the exact float
//! palette of SPEC §5, with squared RGB error (optionally weighted per
//! texel). Only four-colour blocks are produced.
//!
//! Two facts shape the design:
//! * The four palette entries are collinear and evenly spaced, so the best
//!   index for a texel is its projection onto the endpoint segment rounded to
//!   the nearest third: selection is exact and costs one dot product.
//! * With the indices fixed, the error separates by channel into a 2-D
//!   quadratic in (c0, c1) for that channel, so the best 565 endpoints for
//!   those indices can be found exactly by a short scan of the lattice near
//!   the least-squares solution, instead of rounding it.
//!
//! `fast` and `default` run in [`fast`], many blocks at a time. `best`
//! starts from the `default` result of each block and adds cluster fit over
//! every ordered partition along the principal axis (two passes), exact
//! fitting of the most promising partitions, and a long local search over
//! neighbouring endpoint pairs; the lowest error found wins, so `best` is
//! never worse than `default` on any block.

// Index loops over lanes and texels are the point here: they are what the
// compiler vectorises, and several arrays share each index.
#![allow(clippy::needless_range_loop)]

// Inlining: the AVX2 entry points compile only what is inlined into them
// with AVX2, so optimised builds force every helper in (without it `fast`
// runs at 0.6× and `default` at 0.55×). Forced everywhere, it also makes
// three functions of 50 000–60 000 lines of IR each, which at the dev
// profile's opt-level cost 150 s of a cold build for the library and again
// for its unit tests; so builds with debug assertions (tests) force only
// the one-line helpers.

use super::block::{pack565, Block, EXPAND5, EXPAND6};
use super::fast::{self, Group, GroupEffort, F, LANES};
use super::Level;

/// 5- and 6-bit levels as floats on the 0..255 scale.
const LEVELS5_C: [f32; 32] = {
    let mut t = [0.0f32; 32];
    let mut i = 0;
    while i < 32 {
        t[i] = EXPAND5[i] as f32;
        i += 1;
    }
    t
};
const LEVELS6_C: [f32; 64] = {
    let mut t = [0.0f32; 64];
    let mut i = 0;
    while i < 64 {
        t[i] = EXPAND6[i] as f32;
        i += 1;
    }
    t
};

static LEVELS5: [f32; 32] = LEVELS5_C;
static LEVELS6: [f32; 64] = LEVELS6_C;

#[inline(always)]
fn levels(ch: usize) -> &'static [f32] {
    if ch == 1 {
        &LEVELS6
    } else {
        &LEVELS5
    }
}

/// Adding and subtracting 1.5·2²³ rounds a small non-negative f32 to the
/// nearest integer (ties to even) with plain float ops, which vectorise
/// on every target, unlike `round()` or a saturating `as` cast.
pub(crate) const ROUND_MAGIC: f32 = 12_582_912.0;

const THIRD: f32 = 1.0 / 3.0;

#[inline(always)]
fn min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// Sum of 16 lanes in a fixed tree order, so results do not depend on how
/// the compiler vectorises.
#[cfg_attr(not(debug_assertions), inline(always))]
fn hsum(v: &[f32; 16]) -> f32 {
    let mut t8 = [0.0f32; 8];
    for i in 0..8 {
        t8[i] = v[i] + v[i + 8];
    }
    let mut t4 = [0.0f32; 4];
    for i in 0..4 {
        t4[i] = t8[i] + t8[i + 4];
    }
    (t4[0] + t4[2]) + (t4[1] + t4[3])
}

/// Minimum and maximum of 16 lanes, in a fixed tree order.
#[cfg_attr(not(debug_assertions), inline(always))]
fn hminmax(v: &[f32; 16], lo_in: &[f32; 16]) -> (f32, f32) {
    let mut lo8 = [0.0f32; 8];
    let mut hi8 = [0.0f32; 8];
    for i in 0..8 {
        lo8[i] = min(lo_in[i], lo_in[i + 8]);
        hi8[i] = max(v[i], v[i + 8]);
    }
    let mut lo4 = [0.0f32; 4];
    let mut hi4 = [0.0f32; 4];
    for i in 0..4 {
        lo4[i] = min(lo8[i], lo8[i + 4]);
        hi4[i] = max(hi8[i], hi8[i + 4]);
    }
    (
        min(min(lo4[0], lo4[2]), min(lo4[1], lo4[3])),
        max(max(hi4[0], hi4[2]), max(hi4[1], hi4[3])),
    )
}

/// A block's texels on the 0..255 scale, structure-of-arrays, with weights.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Texels {
    pub(crate) c: [[f32; 16]; 3],
    pub(crate) w: [f32; 16],
}

#[inline(always)]
fn sanitize01(v: f32) -> f32 {
    // NaN fails both comparisons and becomes 0.
    if v > 0.0 {
        if v < 1.0 {
            v
        } else {
            1.0
        }
    } else {
        0.0
    }
}

impl Texels {
    pub(crate) fn from_rgb(texels: &[[f32; 3]; 16], weights: &[f32; 16]) -> Texels {
        let mut t = Texels {
            c: [[0.0; 16]; 3],
            w: [0.0; 16],
        };
        for k in 0..16 {
            for ch in 0..3 {
                t.c[ch][k] = sanitize01(texels[k][ch]) * 255.0;
            }
            let w = weights[k];
            t.w[k] = if w > 0.0 && w.is_finite() { w } else { 0.0 };
        }
        t
    }

    /// Reads texel (x0+i, y0+j) from an interleaved image, replicating the
    /// last column and row for texels past the edge.
    #[cfg_attr(not(debug_assertions), inline(always))]
    pub(crate) fn from_image(
        rgb: &[f32],
        width: usize,
        height: usize,
        stride: usize,
        bx: usize,
        by: usize,
    ) -> Texels {
        let mut t = Texels {
            c: [[0.0; 16]; 3],
            w: [1.0; 16],
        };
        if bx * 4 + 4 <= width && by * 4 + 4 <= height && (stride == 3 || stride == 4) {
            // Interior block, packed texels: sanitise whole rows at once
            // (vectorises), then split the channels.
            for j in 0..4 {
                let start = ((by * 4 + j) * width + bx * 4) * stride;
                let mut row = [0.0f32; 16];
                if stride == 3 {
                    row[..12].copy_from_slice(&rgb[start..start + 12]);
                } else {
                    row.copy_from_slice(&rgb[start..start + 16]);
                }
                for v in row.iter_mut() {
                    *v = sanitize01(*v) * 255.0;
                }
                for i in 0..4 {
                    for ch in 0..3 {
                        t.c[ch][j * 4 + i] = row[i * stride + ch];
                    }
                }
            }
            return t;
        }
        for j in 0..4 {
            let y = (by * 4 + j).min(height - 1);
            for i in 0..4 {
                let x = (bx * 4 + i).min(width - 1);
                let base = (y * width + x) * stride;
                let k = j * 4 + i;
                for ch in 0..3 {
                    t.c[ch][k] = sanitize01(rgb[base + ch]) * 255.0;
                }
            }
        }
        t
    }
}

/// Quantised endpoints as 5/6/5-bit channel values: `a` is the end at
/// palette position 0, `b` the end at position 3.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Ends {
    a: [u8; 3],
    b: [u8; 3],
}

impl Ends {
    #[cfg_attr(not(debug_assertions), inline(always))]
    fn values(&self) -> ([f32; 3], [f32; 3]) {
        (
            [
                LEVELS5[self.a[0] as usize],
                LEVELS6[self.a[1] as usize],
                LEVELS5[self.a[2] as usize],
            ],
            [
                LEVELS5[self.b[0] as usize],
                LEVELS6[self.b[1] as usize],
                LEVELS5[self.b[2] as usize],
            ],
        )
    }
}

/// A candidate encoding: endpoints, each texel's palette position (0..=3
/// along a→b, as f32), and its error.
#[derive(Clone, Copy, Debug)]
struct Candidate {
    ends: Ends,
    pos: [f32; 16],
    err: f32,
}

/// Best palette positions for endpoints `a`, `b` (0..255 scale) and the
/// resulting weighted squared error.
#[cfg_attr(not(debug_assertions), inline(always))]
fn select(t: &Texels, a: [f32; 3], b: [f32; 3]) -> (f32, [f32; 16]) {
    let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    let inv = if dd > 0.0 { 3.0 / dd } else { 0.0 };
    let mut pos = [0.0f32; 16];
    let mut e = [0.0f32; 16];
    for k in 0..16 {
        let x0 = t.c[0][k] - a[0];
        let x1 = t.c[1][k] - a[1];
        let x2 = t.c[2][k] - a[2];
        let s = (x0 * d[0] + x1 * d[1] + x2 * d[2]) * inv;
        let s = min(max(s, 0.0), 3.0);
        let q = (s + ROUND_MAGIC) - ROUND_MAGIC;
        pos[k] = q;
        let f = q * THIRD;
        let r0 = x0 - d[0] * f;
        let r1 = x1 - d[1] * f;
        let r2 = x2 - d[2] * f;
        e[k] = t.w[k] * (r0 * r0 + r1 * r1 + r2 * r2);
    }
    (hsum(&e), pos)
}

#[cfg_attr(not(debug_assertions), inline(always))]
fn eval(t: &Texels, ends: Ends) -> (f32, [f32; 16]) {
    let (a, b) = ends.values();
    select(t, a, b)
}

/// For each integer 0..=255, the largest level index q with level q ≤ it,
/// limited to `n - 2` so that q + 1 is always a level too. Levels are
/// integers, so this also answers for any real v through ⌊v⌋.
const fn floor_table<const N: usize>(tab: &[f32; N]) -> [u8; 256] {
    let mut out = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        let mut q = 0;
        while q + 2 < N && tab[q + 1] <= i as f32 {
            q += 1;
        }
        out[i] = q as u8;
        i += 1;
    }
    out
}

static FLOOR5: [u8; 256] = floor_table(&LEVELS5_C);
static FLOOR6: [u8; 256] = floor_table(&LEVELS6_C);

/// Largest level index q with `tab[q] <= v` (0 below the first level),
/// limited to `tab.len() - 2` so that `q + 1` is always a valid level too.
#[inline(always)]
fn floor_level(tab: &[f32], v: f32) -> usize {
    let i = min(max(v, 0.0), 255.0) as usize;
    let f = if tab.len() == 64 { &FLOOR6 } else { &FLOOR5 };
    f[i & 255] as usize
}

#[inline(always)]
fn nearest_level(tab: &[f32], v: f32) -> u8 {
    let q = floor_level(tab, v);
    if (v - tab[q]).abs() <= (tab[q + 1] - v).abs() {
        q as u8
    } else {
        (q + 1) as u8
    }
}

#[cfg_attr(not(debug_assertions), inline(always))]
fn quantize_nearest(a: [f32; 3], b: [f32; 3]) -> Ends {
    Ends {
        a: [
            nearest_level(&LEVELS5, a[0]),
            nearest_level(&LEVELS6, a[1]),
            nearest_level(&LEVELS5, a[2]),
        ],
        b: [
            nearest_level(&LEVELS5, b[0]),
            nearest_level(&LEVELS6, b[1]),
            nearest_level(&LEVELS5, b[2]),
        ],
    }
}

/// Sums that define the fixed-index least-squares problem.
#[derive(Clone, Copy, Debug)]
struct LsSums {
    /// Σw(1−β)², Σw(1−β)β, Σwβ² with β = position/3.
    aa: f32,
    ab: f32,
    bb: f32,
    /// Σw(1−β)x and Σwβx per channel.
    sa: [f32; 3],
    sb: [f32; 3],
}

impl LsSums {
    #[inline(always)]
    fn det(&self) -> f32 {
        self.aa * self.bb - self.ab * self.ab
    }

    /// True when both endpoints are pinned down by the data.
    #[inline(always)]
    fn solvable(&self) -> bool {
        let scale = self.aa + self.bb + 2.0 * self.ab;
        self.det() > 1e-5 * scale * scale
    }

    #[cfg_attr(not(debug_assertions), inline(always))]
    fn solve(&self) -> ([f32; 3], [f32; 3]) {
        let inv = 1.0 / self.det();
        let mut a = [0.0f32; 3];
        let mut b = [0.0f32; 3];
        for ch in 0..3 {
            a[ch] = (self.bb * self.sa[ch] - self.ab * self.sb[ch]) * inv;
            b[ch] = (self.aa * self.sb[ch] - self.ab * self.sa[ch]) * inv;
        }
        (a, b)
    }
}

/// Whole-block sums that do not depend on the indices.
#[derive(Clone, Copy, Debug)]
struct Stats {
    /// Σw, Σwx per channel, Σw|x|².
    w: f32,
    sx: [f32; 3],
    sxx: f32,
    mean: [f32; 3],
    /// Weighted covariance: xx, xy, xz, yy, yz, zz.
    cov: [f32; 6],
    min: [f32; 3],
    max: [f32; 3],
}

#[cfg_attr(not(debug_assertions), inline(always))]
fn stats(t: &Texels) -> Stats {
    let w = hsum(&t.w);
    let mut tmp = [0.0f32; 16];
    let mut sx = [0.0f32; 3];
    for ch in 0..3 {
        for k in 0..16 {
            tmp[k] = t.w[k] * t.c[ch][k];
        }
        sx[ch] = hsum(&tmp);
    }
    let inv_w = if w > 0.0 { 1.0 / w } else { 0.0 };
    let mean = sx.map(|s| s * inv_w);
    let mut d = [[0.0f32; 16]; 3];
    for ch in 0..3 {
        for k in 0..16 {
            d[ch][k] = t.c[ch][k] - mean[ch];
        }
    }
    let pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
    let mut cov = [0.0f32; 6];
    for (n, &(p, q)) in pairs.iter().enumerate() {
        for k in 0..16 {
            tmp[k] = t.w[k] * d[p][k] * d[q][k];
        }
        cov[n] = hsum(&tmp);
    }
    for k in 0..16 {
        tmp[k] = t.w[k] * (t.c[0][k] * t.c[0][k] + t.c[1][k] * t.c[1][k] + t.c[2][k] * t.c[2][k]);
    }
    let sxx = hsum(&tmp);
    let mut mn = [0.0f32; 3];
    let mut mx = [0.0f32; 3];
    let mut lo_in = [0.0f32; 16];
    let mut hi_in = [0.0f32; 16];
    for ch in 0..3 {
        // Texels with no weight do not count towards the range.
        for k in 0..16 {
            let live = t.w[k] > 0.0;
            lo_in[k] = if live { t.c[ch][k] } else { 255.0 };
            hi_in[k] = if live { t.c[ch][k] } else { 0.0 };
        }
        (mn[ch], mx[ch]) = hminmax(&hi_in, &lo_in);
    }
    Stats {
        w,
        sx,
        sxx,
        mean,
        cov,
        min: mn,
        max: mx,
    }
}

/// Principal axis of the weighted covariance by power iteration (not
/// normalised; zero when the block has no spread).
#[cfg_attr(not(debug_assertions), inline(always))]
fn principal_axis(cov: &[f32; 6], iters: u32) -> [f32; 3] {
    let [xx, xy, xz, yy, yz, zz] = *cov;
    // Start from the covariance row of the widest channel: it is never
    // orthogonal to the principal axis unless that channel has no spread.
    let mut v = if xx >= yy && xx >= zz {
        [xx, xy, xz]
    } else if yy >= zz {
        [xy, yy, yz]
    } else {
        [xz, yz, zz]
    };
    for _ in 0..iters {
        let n = [
            xx * v[0] + xy * v[1] + xz * v[2],
            xy * v[0] + yy * v[1] + yz * v[2],
            xz * v[0] + yz * v[1] + zz * v[2],
        ];
        let m = max(max(n[0].abs(), n[1].abs()), n[2].abs());
        if m <= 0.0 {
            break;
        }
        let inv = 1.0 / m;
        v = [n[0] * inv, n[1] * inv, n[2] * inv];
    }
    v
}

/// Endpoints at the extremes of the texels' projections onto `axis`,
/// pulled in by 1/16 of the span (the extremes are rarely worth a palette
/// entry of their own).
#[cfg_attr(not(debug_assertions), inline(always))]
fn axis_endpoints(t: &Texels, s: &Stats, axis: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let nn = axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2];
    if nn <= 0.0 {
        return (s.min, s.max);
    }
    let mut lo_in = [0.0f32; 16];
    let mut hi_in = [0.0f32; 16];
    for k in 0..16 {
        let p = (t.c[0][k] - s.mean[0]) * axis[0]
            + (t.c[1][k] - s.mean[1]) * axis[1]
            + (t.c[2][k] - s.mean[2]) * axis[2];
        let live = t.w[k] > 0.0;
        lo_in[k] = if live { p } else { f32::MAX };
        hi_in[k] = if live { p } else { f32::MIN };
    }
    let (lo, hi) = hminmax(&hi_in, &lo_in);
    let inset = (hi - lo) / 16.0;
    let lo = (lo + inset) / nn;
    let hi = (hi - inset) / nn;
    let mut a = [0.0f32; 3];
    let mut b = [0.0f32; 3];
    for ch in 0..3 {
        a[ch] = min(max(s.mean[ch] + axis[ch] * lo, 0.0), 255.0);
        b[ch] = min(max(s.mean[ch] + axis[ch] * hi, 0.0), 255.0);
    }
    (a, b)
}

/// Least-squares sums for the given positions.
#[cfg_attr(not(debug_assertions), inline(always))]
fn ls_sums(t: &Texels, s: &Stats, pos: &[f32; 16]) -> LsSums {
    let mut wb = [0.0f32; 16];
    let mut wbb = [0.0f32; 16];
    for k in 0..16 {
        let beta = pos[k] * THIRD;
        wb[k] = t.w[k] * beta;
        wbb[k] = wb[k] * beta;
    }
    let sum_b = hsum(&wb);
    let sum_bb = hsum(&wbb);
    let mut tmp = [0.0f32; 16];
    let mut sb = [0.0f32; 3];
    for ch in 0..3 {
        for k in 0..16 {
            tmp[k] = wb[k] * t.c[ch][k];
        }
        sb[ch] = hsum(&tmp);
    }
    LsSums {
        aa: s.w - 2.0 * sum_b + sum_bb,
        ab: sum_b - sum_bb,
        bb: sum_bb,
        sa: [s.sx[0] - sb[0], s.sx[1] - sb[1], s.sx[2] - sb[2]],
        sb,
    }
}

/// Half the widest gap between neighbouring levels, per table.
const HALF_STEP5: f32 = 4.5;
const HALF_STEP6: f32 = 2.5;

/// The best level pair (a, b) for one channel with fixed positions: the
/// minimum of aa·a² + 2ab·ab + bb·b² − 2sa·a − 2sb·b over the lattice.
///
/// Scans one endpoint over every level that can hold the optimum (bounded
/// by `max_radius` levels either side of the continuous solution) and takes
/// the best level of the other endpoint for each. Returns the pair and the
/// quadratic's value (without the constant Σwx²).
#[cfg_attr(not(debug_assertions), inline(always))]
fn best_pair(ch: usize, ls: &LsSums, cont: (f32, f32), max_radius: usize) -> (u8, u8, f32) {
    let tab = levels(ch);
    let half = if ch == 1 { HALF_STEP6 } else { HALF_STEP5 };
    let det = ls.det();
    let (sa, sb) = (ls.sa[ch], ls.sb[ch]);
    // The continuous minimum over the other endpoint, as a function of the
    // scanned one, rises as det/bb·(a−a*)²; the lattice can lower it by at
    // most bb·half² below that curve, which bounds the scan.
    // reach² ∝ 1 + bb²/det for scanning a, 1 + aa²/det for scanning b.
    let scan_a = ls.bb <= ls.aa;
    let reach = if max_radius > 1 {
        let c = if scan_a { ls.bb } else { ls.aa };
        (half * half * (1.0 + c * c / det)).sqrt()
    } else {
        0.0
    };
    // Written for scanning `u` (coefficient uu, linear su) and fitting `v`.
    let (uu, vv, su, sv, u_star) = if scan_a {
        (ls.aa, ls.bb, sa, sb, cont.0)
    } else {
        (ls.bb, ls.aa, sb, sa, cont.1)
    };
    let uv = ls.ab;
    let step = 2.0 * half;
    let r = ((reach / step) as usize + 1).min(max_radius.max(1));
    let q0 = floor_level(tab, u_star);
    let lo = q0.saturating_sub(r - 1);
    let hi = (q0 + r).min(tab.len() - 1);
    let inv_vv = 1.0 / vv;
    let mut best = (0u8, 0u8, f32::MAX);
    for qu in lo..=hi {
        let u = tab[qu];
        let v_star = (sv - uv * u) * inv_vv;
        let qv = floor_level(tab, v_star);
        let base = uu * u * u - 2.0 * su * u;
        for qv in [qv, qv + 1] {
            let v = tab[qv];
            let e = base + vv * v * v + 2.0 * uv * u * v - 2.0 * sv * v;
            if e < best.2 {
                best = (qu as u8, qv as u8, e);
            }
        }
    }
    if scan_a {
        best
    } else {
        (best.1, best.0, best.2)
    }
}

/// Best 565 endpoints for fixed positions (exact up to `max_radius`).
#[cfg_attr(not(debug_assertions), inline(always))]
fn quantize_for_positions(ls: &LsSums, max_radius: usize) -> Ends {
    let (a, b) = ls.solve();
    let mut ends = Ends {
        a: [0; 3],
        b: [0; 3],
    };
    for ch in 0..3 {
        let (qa, qb, _) = best_pair(ch, ls, (a[ch], b[ch]), max_radius);
        ends.a[ch] = qa;
        ends.b[ch] = qb;
    }
    ends
}

/// Alternates exact endpoint fitting for fixed positions with exact
/// re-selection of positions until neither improves the error.
#[cfg_attr(not(debug_assertions), inline(always))]
fn refine(t: &Texels, s: &Stats, cand: &mut Candidate, iters: u32, radius: usize) {
    for _ in 0..iters {
        let ls = ls_sums(t, s, &cand.pos);
        if !ls.solvable() {
            return;
        }
        let ends = quantize_for_positions(&ls, radius);
        if ends == cand.ends {
            return;
        }
        let (err, pos) = eval(t, ends);
        if err < cand.err {
            *cand = Candidate { ends, pos, err };
        } else {
            return;
        }
    }
}

/// Steps per level of the solid-colour tables.
const SOLID_RES: f32 = 4.0;
const SOLID_LEN: usize = 255 * 4 + 1;

/// For every value v on a quarter-level grid, the level pair (a, b) whose
/// 1/3 mix (2a+b)/3 lies closest to v, with a near v and b within 8 levels
/// of a. Pairs further apart rarely come closer, and with the exact palette
/// of SPEC §5 the gain over a single level is large on smooth textures.
const fn solid_table<const N: usize>(tab: &[f32; N]) -> [[u8; 2]; SOLID_LEN] {
    let mut out = [[0u8; 2]; SOLID_LEN];
    let mut key = 0;
    while key < SOLID_LEN {
        let v = key as f32 / SOLID_RES;
        // Nearest level by linear search: this runs at compile time.
        let mut q = 0;
        let mut n = 1;
        while n < N {
            if (tab[n] - v).abs() < (tab[q] - v).abs() {
                q = n;
            }
            n += 1;
        }
        let mut best = [q as u8, q as u8];
        let mut best_e = (tab[q] - v).abs();
        let lo_a = q.saturating_sub(2);
        let hi_a = if q + 2 < N { q + 2 } else { N - 1 };
        let mut qa = lo_a;
        while qa <= hi_a {
            let lo_b = qa.saturating_sub(8);
            let hi_b = if qa + 8 < N { qa + 8 } else { N - 1 };
            let mut qb = lo_b;
            while qb <= hi_b {
                let m = (2.0 * tab[qa] + tab[qb]) / 3.0;
                let e = (m - v).abs();
                if e < best_e {
                    best_e = e;
                    best = [qa as u8, qb as u8];
                }
                qb += 1;
            }
            qa += 1;
        }
        out[key] = best;
        key += 1;
    }
    out
}

static SOLID5: [[u8; 2]; SOLID_LEN] = solid_table(&LEVELS5_C);
static SOLID6: [[u8; 2]; SOLID_LEN] = solid_table(&LEVELS6_C);

/// The table entry for channel `ch` at value `v` (0..255 scale).
#[cfg_attr(not(debug_assertions), inline(always))]
pub(crate) fn solid_pair(ch: usize, v: f32) -> [u8; 2] {
    let key = min(max(v * SOLID_RES + 0.5, 0.0), (SOLID_LEN - 1) as f32) as usize;
    if ch == 1 {
        SOLID6[key]
    } else {
        SOLID5[key]
    }
}

/// Candidate that paints every texel with one palette entry near the
/// colour `c` (0..255 scale): the 1/3 mix of a level pair per channel, or a
/// level itself when that is closer.
#[cfg_attr(not(debug_assertions), inline(always))]
fn solid_candidate(t: &Texels, c: [f32; 3]) -> Candidate {
    let mut ends = Ends {
        a: [0; 3],
        b: [0; 3],
    };
    for ch in 0..3 {
        let [qa, qb] = solid_pair(ch, c[ch]);
        ends.a[ch] = qa;
        ends.b[ch] = qb;
    }
    let (err, pos) = eval(t, ends);
    Candidate { ends, pos, err }
}

/// Indices of the texels sorted by their projection onto `axis`, with the
/// prefix sums cluster fit needs.
struct Ordering {
    order: [u8; 16],
    /// Prefix sums over the sorted texels: Σw and Σwx per channel.
    pw: [f32; 17],
    px: [[f32; 17]; 3],
}

#[cfg_attr(not(debug_assertions), inline(always))]
fn ordering(t: &Texels, axis: [f32; 3]) -> Ordering {
    let mut key = [0.0f32; 16];
    for k in 0..16 {
        key[k] = t.c[0][k] * axis[0] + t.c[1][k] * axis[1] + t.c[2][k] * axis[2];
    }
    let mut order = [0u8, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15];
    // Insertion sort: 16 items, stable, deterministic.
    for i in 1..16 {
        let cur = order[i];
        let kc = key[cur as usize];
        let mut j = i;
        while j > 0 && key[order[j - 1] as usize] > kc {
            order[j] = order[j - 1];
            j -= 1;
        }
        order[j] = cur;
    }
    let mut pw = [0.0f32; 17];
    let mut px = [[0.0f32; 17]; 3];
    for i in 0..16 {
        let k = order[i] as usize;
        let w = t.w[k];
        pw[i + 1] = pw[i] + w;
        for ch in 0..3 {
            px[ch][i + 1] = px[ch][i] + w * t.c[ch][k];
        }
    }
    Ordering { order, pw, px }
}

/// One ordered partition of the sorted texels into the four palette
/// positions: texels [0,i) at 0, [i,j) at 1, [j,k) at 2, [k,16) at 3.
#[derive(Clone, Copy, Debug)]
struct Partition {
    i: u8,
    j: u8,
    k: u8,
    err: f32,
}

impl Partition {
    #[cfg_attr(not(debug_assertions), inline(always))]
    fn positions(&self, ord: &Ordering) -> [f32; 16] {
        let mut pos = [0.0f32; 16];
        for n in 0..16 {
            let p = if n < self.i as usize {
                0.0
            } else if n < self.j as usize {
                1.0
            } else if n < self.k as usize {
                2.0
            } else {
                3.0
            };
            pos[ord.order[n] as usize] = p;
        }
        pos
    }
}

/// Keeps the `N` lowest-error partitions seen, sorted ascending.
struct TopN<const N: usize> {
    items: [Partition; N],
    len: usize,
}

impl<const N: usize> TopN<N> {
    fn new() -> Self {
        TopN {
            items: [Partition {
                i: 0,
                j: 0,
                k: 0,
                err: f32::MAX,
            }; N],
            len: 0,
        }
    }

    #[cfg_attr(not(debug_assertions), inline(always))]
    fn worst(&self) -> f32 {
        if self.len < N {
            f32::MAX
        } else {
            self.items[N - 1].err
        }
    }

    #[cfg_attr(not(debug_assertions), inline(always))]
    fn push(&mut self, p: Partition) {
        if p.err >= self.worst() {
            return;
        }
        let mut n = self.len.min(N - 1);
        while n > 0 && self.items[n - 1].err > p.err {
            self.items[n] = self.items[n - 1];
            n -= 1;
        }
        self.items[n] = p;
        self.len = (self.len + 1).min(N);
    }

    fn as_slice(&self) -> &[Partition] {
        &self.items[..self.len]
    }
}

/// Cluster fit: every ordered partition of the sorted texels into the four
/// palette positions, scored by its continuous least-squares error; the
/// best `N` are returned.
#[cfg_attr(not(debug_assertions), inline(always))]
fn cluster_fit<const N: usize>(s: &Stats, ord: &Ordering) -> TopN<N> {
    let mut top = TopN::<N>::new();
    let pw = &ord.pw;
    let px = &ord.px;
    let wt = pw[16];
    let xt = [px[0][16], px[1][16], px[2][16]];
    const F49: f32 = 4.0 / 9.0;
    const F19: f32 = 1.0 / 9.0;
    const F29: f32 = 2.0 / 9.0;
    for i in 0..=16usize {
        for j in i..=16usize {
            for k in j..=16usize {
                let w0 = pw[i];
                let w1 = pw[j] - pw[i];
                let w2 = pw[k] - pw[j];
                let w3 = wt - pw[k];
                let aa = w0 + F49 * w1 + F19 * w2;
                let bb = F19 * w1 + F49 * w2 + w3;
                let ab = F29 * (w1 + w2);
                let det = aa * bb - ab * ab;
                let scale = aa + bb + 2.0 * ab;
                if det <= 1e-5 * scale * scale {
                    continue;
                }
                let inv = 1.0 / det;
                let mut gain = 0.0f32;
                for ch in 0..3 {
                    let sb = xt[ch] - (px[ch][i] + px[ch][j] + px[ch][k]) * THIRD;
                    let sa = xt[ch] - sb;
                    let a = (bb * sa - ab * sb) * inv;
                    let b = (aa * sb - ab * sa) * inv;
                    gain += a * sa + b * sb;
                }
                let err = s.sxx - gain;
                if err < top.worst() {
                    top.push(Partition {
                        i: i as u8,
                        j: j as u8,
                        k: k as u8,
                        err,
                    });
                }
            }
        }
    }
    top
}

/// Moves tried by the local search: (channel, Δa, Δb) in level steps.
const MOVES: [(usize, i8, i8); 24] = {
    let deltas: [(i8, i8); 8] = [
        (1, 0),
        (-1, 0),
        (0, 1),
        (0, -1),
        (1, 1),
        (-1, -1),
        (1, -1),
        (-1, 1),
    ];
    let mut m = [(0usize, 0i8, 0i8); 24];
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

#[inline(always)]
fn step_level(q: u8, d: i8, top: u8) -> Option<u8> {
    let v = i16::from(q) + i16::from(d);
    if v < 0 || v > i16::from(top) {
        None
    } else {
        Some(v as u8)
    }
}

/// Steepest-descent search over neighbouring 565 endpoint pairs, with full
/// re-selection of indices for every pair tried and an exact refit after
/// every step taken.
#[cfg_attr(not(debug_assertions), inline(always))]
fn local_search(t: &Texels, s: &Stats, cand: &mut Candidate, rounds: u32, radius: usize) {
    for _ in 0..rounds {
        if cand.err <= 0.0 {
            return;
        }
        let mut best: Option<Candidate> = None;
        for &(ch, da, db) in MOVES.iter() {
            let top = if ch == 1 { 63 } else { 31 };
            let (Some(qa), Some(qb)) = (
                step_level(cand.ends.a[ch], da, top),
                step_level(cand.ends.b[ch], db, top),
            ) else {
                continue;
            };
            let mut ends = cand.ends;
            ends.a[ch] = qa;
            ends.b[ch] = qb;
            let (err, pos) = eval(t, ends);
            let bar = best.as_ref().map_or(cand.err, |b| b.err);
            if err < bar {
                best = Some(Candidate { ends, pos, err });
            }
        }
        match best {
            Some(b) => {
                *cand = b;
                refine(t, s, cand, 4, radius);
            }
            None => return,
        }
    }
}

/// How hard the single-block search of the `best` level works.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Search {
    power_iters: u32,
    /// Least-squares/re-selection alternations after each start.
    refine_iters: u32,
    /// Lattice reach (levels either side) of the exact endpoint fit.
    radius: usize,
    /// Cluster-fit passes; each pass after the first re-sorts along the
    /// best endpoints found so far.
    cf_passes: u32,
    /// Partitions per cluster-fit pass taken on to exact fitting.
    cf_keep: usize,
    /// Rounds of local search over neighbouring endpoint pairs.
    search_rounds: u32,
}

/// How hard a level works.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Effort {
    /// Many blocks at a time (see [`fast`]).
    Group(GroupEffort),
    /// The `Default` level's result per block, then a wider search.
    Search(Search),
}

/// Principal axis and one exact refit.
const FAST: GroupEffort = GroupEffort {
    refits: 1,
    boundary_rounds: 0,
    search_rounds: 0,
};

/// Adds moves of single texels across palette boundaries and whole-block
/// shifts, each with a refit, and a short local endpoint search.
const DEFAULT: GroupEffort = GroupEffort {
    refits: 1,
    boundary_rounds: 1,
    search_rounds: 2,
};

/// Cluster fit over every ordered partition, two passes, and a long local
/// search, starting from the `Default` result.
const BEST: Search = Search {
    power_iters: 8,
    refine_iters: 8,
    radius: 4,
    cf_passes: 2,
    cf_keep: 16,
    search_rounds: 32,
};

pub(crate) fn effort(level: Level) -> Effort {
    match level {
        Level::Fast => Effort::Group(FAST),
        Level::Default => Effort::Group(DEFAULT),
        Level::Best => Effort::Search(BEST),
    }
}

/// Turns a candidate into a block with c0 > c1 (or c0 = c1, indices 0).
#[cfg_attr(not(debug_assertions), inline(always))]
fn finish(cand: &Candidate) -> Block {
    let ca = pack565(cand.ends.a[0], cand.ends.a[1], cand.ends.a[2]);
    let cb = pack565(cand.ends.b[0], cand.ends.b[1], cand.ends.b[2]);
    if ca == cb {
        return Block::solid(ca);
    }
    // Position p along a→b maps to index [0, 2, 3, 1][p] when a is c0 (that
    // is, bit 1 = p is 1 or 2, bit 0 = p ≥ 2); swapping the ends reverses p.
    let swap = ca < cb;
    let flip = if swap { 3 } else { 0 };
    let mut indices = 0u32;
    for k in 0..16 {
        let p = ((cand.pos[k] as u32) & 3) ^ flip;
        let idx = (((p ^ (p >> 1)) & 1) << 1) | (p >> 1);
        indices |= idx << (2 * k);
    }
    let (c0, c1) = if swap { (cb, ca) } else { (ca, cb) };
    Block { c0, c1, indices }
}

/// A block's endpoints as a candidate, with positions re-selected (which
/// never raises its error).
fn candidate_from_block(t: &Texels, b: &Block) -> Candidate {
    let (a, b) = (super::block::unpack565(b.c0), super::block::unpack565(b.c1));
    let ends = Ends {
        a: [a.0, a.1, a.2],
        b: [b.0, b.1, b.2],
    };
    let (err, pos) = eval(t, ends);
    Candidate { ends, pos, err }
}

/// Encodes one block of texels (0..255 scale) with the given effort,
/// starting from `start` when given.
#[cfg_attr(not(debug_assertions), inline(always))]
pub(crate) fn encode_texels(t: &Texels, e: &Search, start: Option<Block>) -> Block {
    let mut s = stats(t);
    let unweighted;
    let t = if s.w <= 0.0 {
        // No texel matters: encode them all equally so the block is sensible.
        unweighted = Texels {
            c: t.c,
            w: [1.0; 16],
        };
        s = stats(&unweighted);
        &unweighted
    } else {
        t
    };
    let spread = (s.max[0] - s.min[0])
        .max(s.max[1] - s.min[1])
        .max(s.max[2] - s.min[2]);
    if spread <= 0.0 {
        return finish(&solid_candidate(t, s.mean));
    }

    let axis = principal_axis(&s.cov, e.power_iters);
    let (a, b) = axis_endpoints(t, &s, axis);
    let ends = quantize_nearest(a, b);
    let (err, pos) = eval(t, ends);
    let mut best = Candidate { ends, pos, err };
    refine(t, &s, &mut best, e.refine_iters, e.radius);
    if let Some(b) = start {
        let c = candidate_from_block(t, &b);
        if c.err < best.err {
            best = c;
        }
    }

    // A block whose texels all sit within a few levels is often best served
    // by one palette entry placed between the 565 levels.
    if spread < 24.0 {
        let c = solid_candidate(t, s.mean);
        if c.err < best.err {
            best = c;
        }
    }

    let mut axis = axis;
    for pass in 0..e.cf_passes {
        if best.err <= 0.0 {
            break;
        }
        // Later passes sort along the best endpoints so far, whose indices
        // are then one of the ordered partitions.
        if pass > 0 {
            let (a, b) = best.ends.values();
            let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            if d == [0.0; 3] || d == axis {
                break;
            }
            axis = d;
        }
        let ord = ordering(t, axis);
        let top = cluster_fit::<32>(&s, &ord);
        for p in top.as_slice().iter().take(e.cf_keep) {
            let pos = p.positions(&ord);
            let ls = ls_sums(t, &s, &pos);
            if !ls.solvable() {
                continue;
            }
            let ends = quantize_for_positions(&ls, e.radius);
            let (err, pos) = eval(t, ends);
            let mut c = Candidate { ends, pos, err };
            refine(t, &s, &mut c, e.refine_iters, e.radius);
            if c.err < best.err {
                best = c;
            }
        }
    }

    if e.search_rounds > 0 {
        local_search(t, &s, &mut best, e.search_rounds, e.radius);
    }
    finish(&best)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AVX2 build of the row encoder must give the same blocks as the
    /// portable one.
    #[test]
    fn simd_paths_agree() {
        let (w, h) = (70usize, 12usize);
        let mut rng = crate::bc1::block::tests::Rng::new(17);
        let img: Vec<f32> = (0..w * h * 4)
            .map(|i| {
                let smooth = ((i / 4) % w) as f32 / w as f32;
                if rng.next_u64().is_multiple_of(3) {
                    (rng.next_u64() % 256) as f32 / 255.0
                } else {
                    smooth
                }
            })
            .collect();
        let bw = w.div_ceil(4);
        for level in Level::ALL {
            let e = effort(level);
            for by in 0..h / 4 {
                let mut a = vec![Block::default(); bw];
                let mut b = vec![Block::default(); bw];
                encode_row(&img, w, h, 4, by, &mut a, &e);
                encode_row_generic(&img, w, h, 4, by, &mut b, &e);
                assert_eq!(a, b, "{level} row {by}");
            }
        }
    }

    #[test]
    fn floor_and_nearest_levels() {
        for tab in [&LEVELS5[..], &LEVELS6[..]] {
            for i in 0..=2550 {
                let v = i as f32 / 10.0;
                let q = floor_level(tab, v);
                assert!(q + 1 < tab.len());
                assert!(tab[q] <= v || q == 0, "v={v} q={q}");
                assert!(tab[q + 1] > v || q + 2 == tab.len(), "v={v} q={q}");
                let n = nearest_level(tab, v) as usize;
                let best = (0..tab.len())
                    .map(|k| (tab[k] - v).abs())
                    .fold(f32::MAX, f32::min);
                assert_eq!((tab[n] - v).abs(), best, "v={v}");
            }
        }
    }

    /// The lattice fit for fixed positions must match brute force.
    #[test]
    fn best_pair_is_exact() {
        let mut rng = crate::bc1::block::tests::Rng::new(3);
        for _ in 0..300 {
            let mut t = Texels {
                c: [[0.0; 16]; 3],
                w: [1.0; 16],
            };
            let mut pos = [0.0f32; 16];
            for k in 0..16 {
                for ch in 0..3 {
                    t.c[ch][k] = (rng.next_u64() % 256) as f32;
                }
                pos[k] = (rng.next_u64() % 4) as f32;
            }
            let s = stats(&t);
            let ls = ls_sums(&t, &s, &pos);
            if !ls.solvable() {
                continue;
            }
            let (a, b) = ls.solve();
            for ch in 0..3 {
                let (_, _, e) = best_pair(ch, &ls, (a[ch], b[ch]), 64);
                let tab = levels(ch);
                let mut brute = f32::MAX;
                for &u in tab {
                    for &v in tab {
                        let q = ls.aa * u * u + 2.0 * ls.ab * u * v + ls.bb * v * v
                            - 2.0 * ls.sa[ch] * u
                            - 2.0 * ls.sb[ch] * v;
                        brute = brute.min(q);
                    }
                }
                assert!(e <= brute + 1e-3 * brute.abs().max(1.0), "{e} vs {brute}");
            }
        }
    }

    #[test]
    fn selection_is_nearest_palette_entry() {
        let mut rng = crate::bc1::block::tests::Rng::new(5);
        for _ in 0..200 {
            let mut t = Texels {
                c: [[0.0; 16]; 3],
                w: [1.0; 16],
            };
            for k in 0..16 {
                for ch in 0..3 {
                    t.c[ch][k] = (rng.next_u64() % 256) as f32;
                }
            }
            let ends = Ends {
                a: [(rng.next_u64() % 32) as u8, (rng.next_u64() % 64) as u8, 3],
                b: [(rng.next_u64() % 32) as u8, 60, (rng.next_u64() % 32) as u8],
            };
            let (err, _) = eval(&t, ends);
            let (a, b) = ends.values();
            let pal: [[f32; 3]; 4] = std::array::from_fn(|p| {
                std::array::from_fn(|ch| a[ch] + (b[ch] - a[ch]) * p as f32 / 3.0)
            });
            let mut brute = 0.0f32;
            for k in 0..16 {
                brute += pal
                    .iter()
                    .map(|c| (0..3).map(|ch| (c[ch] - t.c[ch][k]).powi(2)).sum::<f32>())
                    .fold(f32::MAX, f32::min);
            }
            assert!(
                (err - brute).abs() <= 1e-3 * brute.max(1.0),
                "{err} vs {brute}"
            );
        }
    }
}

/// Encodes block row `by` of an image into `row`.
///
/// On x86-64 CPUs with AVX2 the same code is compiled a second time with
/// AVX2 enabled and picked at run time. FMA stays off, and every reduction
/// has a fixed order, so both versions give bit-identical blocks.
pub(crate) fn encode_row(
    rgb: &[f32],
    width: usize,
    height: usize,
    stride: usize,
    by: usize,
    row: &mut [Block],
    e: &Effort,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            unsafe { encode_row_avx2(rgb, width, height, stride, by, row, e) };
            return;
        }
    }
    encode_row_generic(rgb, width, height, stride, by, row, e);
}

#[cfg_attr(not(debug_assertions), inline(always))]
fn encode_row_generic(
    rgb: &[f32],
    width: usize,
    height: usize,
    stride: usize,
    by: usize,
    row: &mut [Block],
    e: &Effort,
) {
    let ge = match e {
        Effort::Group(g) => *g,
        Effort::Search(_) => DEFAULT,
    };
    for (n, chunk) in row.chunks_mut(LANES).enumerate() {
        let mut g = Group::load(rgb, width, height, stride, n * LANES, by);
        g.sanitize();
        let blocks = fast::encode_group::<false>(&g, &ge);
        chunk.copy_from_slice(&blocks[..chunk.len()]);
    }
    if let Effort::Search(search) = e {
        for (bx, out) in row.iter_mut().enumerate() {
            let t = Texels::from_image(rgb, width, height, stride, bx, by);
            *out = encode_texels(&t, search, Some(*out));
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn encode_row_avx2(
    rgb: &[f32],
    width: usize,
    height: usize,
    stride: usize,
    by: usize,
    row: &mut [Block],
    e: &Effort,
) {
    encode_row_generic(rgb, width, height, stride, by, row, e);
}

/// Encodes one block, with the same run-time choice as [`encode_row`].
pub(crate) fn encode_one(t: &Texels, e: &Effort) -> Block {
    let search = match e {
        Effort::Group(g) => return encode_one_group(t, g),
        Effort::Search(search) => search,
    };
    let start = encode_one_group(t, &DEFAULT);
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            return unsafe { encode_one_avx2(t, search, start) };
        }
    }
    encode_texels(t, search, Some(start))
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn encode_one_avx2(t: &Texels, e: &Search, start: Block) -> Block {
    encode_texels(t, e, Some(start))
}

/// A fast-level block on its own: copied into every lane of a group.
fn encode_one_group(t: &Texels, ge: &GroupEffort) -> Block {
    let mut g = Group {
        c: [[F([0.0; LANES]); 16]; 3],
        w: [F([1.0; LANES]); 16],
    };
    let live = t.w.iter().any(|&w| w > 0.0);
    for k in 0..16 {
        for ch in 0..3 {
            g.c[ch][k] = F([t.c[ch][k]; LANES]);
        }
        // All-zero weights: weigh every texel equally instead.
        g.w[k] = F([if live { t.w[k] } else { 1.0 }; LANES]);
    }
    fast::encode_group::<true>(&g, ge)[0]
}
