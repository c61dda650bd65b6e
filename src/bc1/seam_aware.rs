//! Seam-aware BC1 (SPEC §6): re-encode the blocks under the seams so that
//! the *decoded* texture stays seam-free.
//!
//! Over the blocks that hold a texel of any seam sample's bilinear footprint,
//! minimise E_c + α·E_s:
//! * E_c = Σ w_t |decoded_t − target_t|², w_t = 1 inside the UV charts and
//!   far less outside (outside texels matter only through the seams);
//! * E_s = Σ_seams len·∫|B₁ − B₂|² dγ of the decoded texture, exactly (the
//!   Gauss points of [`crate::seam::quadrature`]), in texel-length units.
//!
//! 1. With the regular encoding's indices fixed, decoded values are linear in
//!    the float endpoints, so one sparse least-squares solve gives float
//!    endpoints for every block at once (the seed paper's method).
//! 2. Rounding those to 565 throws most of the gain away, so a block
//!    coordinate descent follows, on integer endpoints and indices against
//!    the same energy. With its neighbours fixed, a block's energy is a
//!    quadratic vᵀMv − 2vᵀr in its 16 texels (M = W + αQ, Q precomputed
//!    once from the seam points that touch it); with indices fixed, that is
//!    a 2×2 quadratic in each channel's two endpoints, so every integer
//!    endpoint candidate costs O(1), and every index candidate O(1) given Mv.

// The kernels below index small fixed matrices by channel and slot in
// step; iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

use crate::bc1::{pack565, unpack565, Block};
use crate::seam::quadrature::QuadPoint;
use crate::seam::system::{SolveError, SpdSystem};

/// Interpolation weights (of c0, c1) of the four-colour palette entries.
const MIX: [[f64; 2]; 4] = [
    [1.0, 0.0],
    [0.0, 1.0],
    [2.0 / 3.0, 1.0 / 3.0],
    [1.0 / 3.0, 2.0 / 3.0],
];
/// Bits per channel in RGB565.
const BITS: [u32; 3] = [5, 6, 5];
/// Pulls under-determined float endpoints towards the regular encoding.
const REGULARISER: f64 = 1e-6;
/// Integer endpoint candidates span this many steps either side of the float optimum.
const ENDPOINT_RADIUS: i32 = 2;

/// α of seam-aware BC1 unless told otherwise, from the trade-off curve of
/// `cargo bench --bench seam_aware`: the smallest α that cuts the regular
/// encoding's seam_rms 3× or more on the cube, blub and Fox atlases while
/// costing under 0.1 dB; larger α buys little more seam agreement.
pub const DEFAULT_ALPHA: f64 = 256.0;

#[derive(Clone, Copy, Debug)]
pub struct SeamAwareOptions {
    /// α: weight of seam agreement against fidelity.
    pub alpha: f64,
    /// Weight of a texel outside the UV charts in E_c (inside: 1).
    pub outside_weight: f64,
    /// Search integer endpoints and indices after the float solve (else round once, as the seed does).
    pub integer_search: bool,
    pub max_sweeps: usize,
}

impl Default for SeamAwareOptions {
    fn default() -> Self {
        SeamAwareOptions {
            alpha: DEFAULT_ALPHA,
            outside_weight: 1e-2,
            integer_search: true,
            max_sweeps: 8,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct SeamAwareStats {
    /// Blocks re-encoded (those under a seam footprint).
    pub blocks: usize,
    pub sweeps: usize,
    /// E_c + α·E_s of the regular encoding, and of the result.
    pub energy_regular: f64,
    pub energy_final: f64,
}

/// The texel layout and the energy's fixed parts.
pub struct Problem<'a> {
    pub width: usize,
    pub height: usize,
    /// The texture the blocks should reproduce: RGB in \[0, 1\], `channels` per texel.
    pub target: &'a [f32],
    pub channels: usize,
    pub inside: &'a [bool],
    /// Seam differences at the Gauss points, weights in texel-length units.
    pub points: &'a [QuadPoint],
}

/// Per-block state during the integer search: endpoints per channel, indices.
#[derive(Clone, Copy)]
struct State {
    q: [[i32; 3]; 2],
    idx: [u8; 16],
}

impl State {
    fn from_block(b: &Block) -> Self {
        let (r0, g0, b0) = unpack565(b.c0);
        let (r1, g1, b1) = unpack565(b.c1);
        State {
            q: [
                [i32::from(r0), i32::from(g0), i32::from(b0)],
                [i32::from(r1), i32::from(g1), i32::from(b1)],
            ],
            idx: std::array::from_fn(|k| b.index(k)),
        }
    }

    fn to_block(self) -> Block {
        let pack = |q: [i32; 3]| pack565(q[0] as u8, q[1] as u8, q[2] as u8);
        let (mut c0, mut c1) = (pack(self.q[0]), pack(self.q[1]));
        let mut idx = self.idx;
        if c0 < c1 {
            // Same palette, other order: keep the four-colour mode (c0 > c1).
            std::mem::swap(&mut c0, &mut c1);
            for i in &mut idx {
                *i = [1, 0, 3, 2][*i as usize];
            }
        }
        let indices = idx
            .iter()
            .enumerate()
            .fold(0u32, |acc, (k, &i)| acc | (u32::from(i) << (2 * k)));
        Block { c0, c1, indices }
    }

    /// Endpoint value of channel `ch` in \[0, 1\].
    #[inline]
    fn end(&self, e: usize, ch: usize) -> f64 {
        expand(self.q[e][ch], ch)
    }

    #[inline]
    fn value(&self, k: usize, ch: usize) -> f64 {
        let m = MIX[self.idx[k] as usize];
        m[0] * self.end(0, ch) + m[1] * self.end(1, ch)
    }

    /// Four-colour mode needs distinct packed endpoints.
    fn valid(&self) -> bool {
        self.q[0] != self.q[1]
    }
}

#[inline]
fn expand(q: i32, ch: usize) -> f64 {
    let v = match BITS[ch] {
        5 => (q << 3) | (q >> 2),
        _ => (q << 2) | (q >> 4),
    };
    f64::from(v) / 255.0
}

/// The nearest 565 level to `v` in \[0, 1\] for channel `ch`.
fn nearest_level(v: f64, ch: usize) -> i32 {
    let max = (1 << BITS[ch]) - 1;
    let guess = (v.clamp(0.0, 1.0) * f64::from(max)).round() as i32;
    (guess - 1..=guess + 1)
        .filter(|q| (0..=max).contains(q))
        .min_by(|&a, &b| {
            (expand(a, ch) - v)
                .abs()
                .total_cmp(&(expand(b, ch) - v).abs())
        })
        .unwrap_or(guess.clamp(0, max))
}

/// One seam point's reach into one block: texel slots and coefficients.
struct Touch {
    point: u32,
    local: Vec<(u8, f64)>,
}

struct Layout {
    bw: usize,
    /// Footprint blocks, ascending, and each block's slot in that list.
    blocks: Vec<usize>,
    slot: Vec<u32>,
    touches: Vec<Vec<Touch>>,
}

impl Layout {
    fn new(p: &Problem) -> Self {
        let bw = p.width.div_ceil(4);
        let bh = p.height.div_ceil(4);
        let block_of = |t: u32| {
            let (x, y) = (t as usize % p.width, t as usize / p.width);
            ((y / 4) * bw + x / 4, ((y % 4) * 4 + x % 4) as u8)
        };
        let mut slot = vec![u32::MAX; bw * bh];
        let mut blocks = Vec::new();
        for q in p.points {
            for &(t, _) in &q.taps {
                let b = block_of(t).0;
                if slot[b] == u32::MAX {
                    slot[b] = 0;
                    blocks.push(b);
                }
            }
        }
        blocks.sort_unstable();
        for (i, &b) in blocks.iter().enumerate() {
            slot[b] = i as u32;
        }
        let mut touches: Vec<Vec<Touch>> = (0..blocks.len()).map(|_| Vec::new()).collect();
        for (qi, q) in p.points.iter().enumerate() {
            let mut per: Vec<(usize, Vec<(u8, f64)>)> = Vec::new();
            for &(t, w) in &q.taps {
                let (b, k) = block_of(t);
                let s = slot[b] as usize;
                match per.iter_mut().find(|e| e.0 == s) {
                    Some(e) => match e.1.iter_mut().find(|l| l.0 == k) {
                        Some(l) => l.1 += w,
                        None => e.1.push((k, w)),
                    },
                    None => per.push((s, vec![(k, w)])),
                }
            }
            for (s, local) in per {
                touches[s].push(Touch {
                    point: qi as u32,
                    local,
                });
            }
        }
        Layout {
            bw,
            blocks,
            slot,
            touches,
        }
    }

    /// Texel index of slot `k` of block `b`, or `None` in the padding.
    fn texel(&self, p: &Problem, b: usize, k: usize) -> Option<usize> {
        let (x, y) = ((b % self.bw) * 4 + k % 4, (b / self.bw) * 4 + k / 4);
        (x < p.width && y < p.height).then(|| y * p.width + x)
    }
}

/// Re-encodes the blocks under the seams of `p`; `blocks` holds the regular
/// encoding on entry and the seam-aware one on return.
pub fn optimise(
    p: &Problem,
    blocks: &mut [Block],
    opts: &SeamAwareOptions,
) -> Result<SeamAwareStats, SolveError> {
    let layout = Layout::new(p);
    let mut stats = SeamAwareStats {
        blocks: layout.blocks.len(),
        ..SeamAwareStats::default()
    };
    if layout.blocks.is_empty() {
        return Ok(stats);
    }
    let mut states: Vec<State> = layout
        .blocks
        .iter()
        .map(|&b| State::from_block(&blocks[b]))
        .collect();
    stats.energy_regular = total_energy(p, &layout, &states, opts);

    float_solve(p, &layout, &mut states, opts)?;
    if opts.integer_search {
        let mut energy = total_energy(p, &layout, &states, opts);
        for _ in 0..opts.max_sweeps {
            stats.sweeps += 1;
            for s in 0..states.len() {
                improve_block(p, &layout, &mut states, s, opts);
            }
            let e = total_energy(p, &layout, &states, opts);
            let fell = energy - e;
            energy = e;
            if fell <= 1e-9 * energy.max(1e-300) {
                break;
            }
        }
    }
    stats.energy_final = total_energy(p, &layout, &states, opts);
    // Never worse than where we started; the seed's method is left as it is,
    // so that it can be measured.
    if opts.integer_search && stats.energy_final > stats.energy_regular {
        stats.energy_final = stats.energy_regular;
        return Ok(stats);
    }
    for (s, &b) in layout.blocks.iter().enumerate() {
        blocks[b] = states[s].to_block();
    }
    Ok(stats)
}

fn weight(p: &Problem, t: usize, opts: &SeamAwareOptions) -> f64 {
    if p.inside[t] {
        1.0
    } else {
        opts.outside_weight
    }
}

fn decoded(p: &Problem, layout: &Layout, states: &[State], t: u32, ch: usize) -> f64 {
    let (x, y) = (t as usize % p.width, t as usize / p.width);
    let b = (y / 4) * layout.bw + x / 4;
    states[layout.slot[b] as usize].value((y % 4) * 4 + x % 4, ch)
}

fn total_energy(p: &Problem, layout: &Layout, states: &[State], opts: &SeamAwareOptions) -> f64 {
    let mut e = 0.0;
    for (s, &b) in layout.blocks.iter().enumerate() {
        for k in 0..16 {
            if let Some(t) = layout.texel(p, b, k) {
                let w = weight(p, t, opts);
                for ch in 0..3 {
                    let d = states[s].value(k, ch) - f64::from(p.target[t * p.channels + ch]);
                    e += w * d * d;
                }
            }
        }
    }
    for q in p.points {
        for ch in 0..3 {
            let v: f64 = q
                .taps
                .iter()
                .map(|&(t, w)| w * decoded(p, layout, states, t, ch))
                .sum();
            e += opts.alpha * q.weight * v * v;
        }
    }
    e
}

/// Step 1: float endpoints for all blocks at once, indices fixed, then
/// rounded to the nearest 565 levels.
fn float_solve(
    p: &Problem,
    layout: &Layout,
    states: &mut [State],
    opts: &SeamAwareOptions,
) -> Result<(), SolveError> {
    let n = states.len() * 2;
    let identity: Vec<u32> = (0..n as u32).collect();
    let mut sys = SpdSystem::new(&identity, n, 3);
    let none: [f32; 0] = [];
    for (s, &b) in layout.blocks.iter().enumerate() {
        let st = &states[s];
        for k in 0..16 {
            if let Some(t) = layout.texel(p, b, k) {
                let m = MIX[st.idx[k] as usize];
                let target: Vec<f64> = (0..3)
                    .map(|ch| f64::from(p.target[t * p.channels + ch]))
                    .collect();
                let taps = [(2 * s as u32, m[0]), (2 * s as u32 + 1, m[1])];
                sys.add_square(weight(p, t, opts), &taps, &target, &none);
            }
        }
        for e in 0..2 {
            let reg: Vec<f64> = (0..3).map(|ch| st.end(e, ch)).collect();
            sys.add_anchor(REGULARISER, (2 * s + e) as u32, &reg);
        }
    }
    let zero = [0.0f64; 3];
    let mut taps = Vec::with_capacity(16);
    for q in p.points {
        taps.clear();
        for &(t, w) in &q.taps {
            let (x, y) = (t as usize % p.width, t as usize / p.width);
            let s = layout.slot[(y / 4) * layout.bw + x / 4] as usize;
            let m = MIX[states[s].idx[(y % 4) * 4 + x % 4] as usize];
            taps.push((2 * s as u32, w * m[0]));
            taps.push((2 * s as u32 + 1, w * m[1]));
        }
        sys.add_square(opts.alpha * q.weight, &taps, &zero, &none);
    }
    let x = sys.solve()?;
    for (s, st) in states.iter_mut().enumerate() {
        let before = *st;
        for e in 0..2 {
            for ch in 0..3 {
                st.q[e][ch] = nearest_level(x[(2 * s + e) * 3 + ch], ch);
            }
        }
        if !st.valid() {
            *st = before;
        }
    }
    Ok(())
}

/// One block's share of the energy with its neighbours fixed: vᵀMv − 2vᵀr
/// per channel, over the block's 16 slots.
struct Local {
    m: [[f64; 16]; 16],
    r: [[f64; 16]; 3],
}

fn local_energy(
    p: &Problem,
    layout: &Layout,
    states: &[State],
    s: usize,
    opts: &SeamAwareOptions,
) -> Local {
    let b = layout.blocks[s];
    let mut m = [[0.0; 16]; 16];
    let mut r = [[0.0; 16]; 3];
    for k in 0..16 {
        if let Some(t) = layout.texel(p, b, k) {
            let w = weight(p, t, opts);
            m[k][k] += w;
            for ch in 0..3 {
                r[ch][k] += w * f64::from(p.target[t * p.channels + ch]);
            }
        }
    }
    for touch in &layout.touches[s] {
        let q = &p.points[touch.point as usize];
        let w = opts.alpha * q.weight;
        // Contribution of texels outside this block, at their current values.
        let mut rest = [0.0f64; 3];
        for &(t, c) in &q.taps {
            let (x, y) = (t as usize % p.width, t as usize / p.width);
            if (y / 4) * layout.bw + x / 4 != b {
                for (ch, v) in rest.iter_mut().enumerate() {
                    *v += c * decoded(p, layout, states, t, ch);
                }
            }
        }
        for &(k, ck) in &touch.local {
            for &(l, cl) in &touch.local {
                m[k as usize][l as usize] += w * ck * cl;
            }
            for ch in 0..3 {
                r[ch][k as usize] -= w * ck * rest[ch];
            }
        }
    }
    Local { m, r }
}

/// Step 2 for one block: alternate the best integer endpoints for the
/// current indices with single-texel index changes, while the energy falls.
fn improve_block(
    p: &Problem,
    layout: &Layout,
    states: &mut [State],
    s: usize,
    opts: &SeamAwareOptions,
) {
    let local = local_energy(p, layout, states, s, opts);
    // v: the block's decoded texels; mv = M·v; energy = Σ v·(Mv − 2r).
    let prepare = |st: &State| {
        let v: [[f64; 16]; 3] = std::array::from_fn(|ch| std::array::from_fn(|k| st.value(k, ch)));
        let mut mv = [[0.0f64; 16]; 3];
        let mut e = 0.0;
        for ch in 0..3 {
            for k in 0..16 {
                mv[ch][k] = (0..16).map(|l| local.m[k][l] * v[ch][l]).sum();
                e += v[ch][k] * (mv[ch][k] - 2.0 * local.r[ch][k]);
            }
        }
        (v, mv, e)
    };
    let mut best = states[s];
    let (mut v, mut mv, mut best_e) = prepare(&best);
    for _ in 0..4 {
        let mut changed = false;
        if let Some(cand) = best_endpoints(&local, &best) {
            let (cv, cmv, e) = prepare(&cand);
            if e < best_e - 1e-15 {
                (best, v, mv, best_e) = (cand, cv, cmv, e);
                changed = true;
            }
        }
        for k in 0..16 {
            for i in 0..4u8 {
                if i == best.idx[k] {
                    continue;
                }
                let m = MIX[i as usize];
                let delta: [f64; 3] = std::array::from_fn(|ch| {
                    m[0] * best.end(0, ch) + m[1] * best.end(1, ch) - v[ch][k]
                });
                let de: f64 = (0..3)
                    .map(|ch| {
                        delta[ch] * delta[ch] * local.m[k][k]
                            + 2.0 * delta[ch] * (mv[ch][k] - local.r[ch][k])
                    })
                    .sum();
                if de < -1e-15 {
                    best.idx[k] = i;
                    best_e += de;
                    for ch in 0..3 {
                        v[ch][k] += delta[ch];
                        for l in 0..16 {
                            mv[ch][l] += local.m[l][k] * delta[ch];
                        }
                    }
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    states[s] = best;
}

/// With indices fixed, each channel's energy is a 2×2 quadratic in its two
/// endpoint values: minimise it over integer levels near its float optimum.
fn best_endpoints(local: &Local, st: &State) -> Option<State> {
    let a: [[f64; 2]; 16] = std::array::from_fn(|k| MIX[st.idx[k] as usize]);
    // H = Aᵀ M A (shared by channels), f = Aᵀ r (per channel).
    let mut h = [[0.0f64; 2]; 2];
    for k in 0..16 {
        for l in 0..16 {
            let mkl = local.m[k][l];
            if mkl == 0.0 {
                continue;
            }
            for i in 0..2 {
                for j in 0..2 {
                    h[i][j] += a[k][i] * mkl * a[l][j];
                }
            }
        }
    }
    let mut out = *st;
    for ch in 0..3 {
        let mut f = [0.0f64; 2];
        for k in 0..16 {
            f[0] += a[k][0] * local.r[ch][k];
            f[1] += a[k][1] * local.r[ch][k];
        }
        let det = h[0][0] * h[1][1] - h[0][1] * h[1][0];
        let centre = if det.abs() > 1e-12 * (h[0][0] * h[1][1]).abs().max(1e-300) {
            [
                (h[1][1] * f[0] - h[0][1] * f[1]) / det,
                (h[0][0] * f[1] - h[1][0] * f[0]) / det,
            ]
        } else {
            [st.end(0, ch), st.end(1, ch)]
        };
        let cost = |c0: f64, c1: f64| {
            h[0][0] * c0 * c0 + 2.0 * h[0][1] * c0 * c1 + h[1][1] * c1 * c1
                - 2.0 * (f[0] * c0 + f[1] * c1)
        };
        let max = (1 << BITS[ch]) - 1;
        let (g0, g1) = (nearest_level(centre[0], ch), nearest_level(centre[1], ch));
        let mut best = (st.q[0][ch], st.q[1][ch]);
        let mut best_c = cost(st.end(0, ch), st.end(1, ch));
        for d0 in -ENDPOINT_RADIUS..=ENDPOINT_RADIUS {
            for d1 in -ENDPOINT_RADIUS..=ENDPOINT_RADIUS {
                let (q0, q1) = (g0 + d0, g1 + d1);
                if !(0..=max).contains(&q0) || !(0..=max).contains(&q1) {
                    continue;
                }
                let c = cost(expand(q0, ch), expand(q1, ch));
                if c < best_c {
                    best = (q0, q1);
                    best_c = c;
                }
            }
        }
        out.q[0][ch] = best.0;
        out.q[1][ch] = best.1;
    }
    out.valid().then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bc1::expand565;

    #[test]
    fn state_round_trips_and_keeps_four_colour_mode() {
        let b = Block {
            c0: pack565(20, 40, 10),
            c1: pack565(3, 9, 30),
            indices: 0b11_10_01_00_11_10_01_00_11_10_01_00_11_10_01_00,
        };
        assert_eq!(State::from_block(&b).to_block(), b);
        // Swapped endpoints come back in four-colour order, same texels.
        let mut s = State::from_block(&b);
        s.q.swap(0, 1);
        for i in &mut s.idx {
            *i = [1, 0, 3, 2][*i as usize];
        }
        let back = s.to_block();
        assert!(back.c0 > back.c1);
        assert_eq!(back.decode(), b.decode());
    }

    #[test]
    fn state_values_match_the_decoder() {
        let b = Block {
            c0: pack565(31, 17, 2),
            c1: pack565(0, 63, 29),
            indices: 0x1b1b_e4e4,
        };
        let s = State::from_block(&b);
        let d = b.decode();
        for k in 0..16 {
            for ch in 0..3 {
                assert!((s.value(k, ch) - f64::from(d[k][ch])).abs() < 1e-6);
            }
        }
        assert_eq!(expand(31, 0), 1.0);
        assert_eq!(
            expand565(pack565(16, 32, 16))[1] as f64 / 255.0,
            expand(32, 1)
        );
    }

    #[test]
    fn nearest_level_picks_the_closer_expanded_value() {
        for ch in 0..3 {
            let max = (1 << BITS[ch]) - 1;
            for q in 0..=max {
                assert_eq!(nearest_level(expand(q, ch), ch), q);
            }
        }
    }
}
