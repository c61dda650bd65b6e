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
//!
//! GPUs do not decode with the float palette that the float solve assumes:
//! they round the interpolated entries with integer formulas of their own
//! ([`Decoder`]), and a seam tuned under one decoder opens by whole levels
//! under another. The float solve stays on the ideal palette (it only
//! starts the search); the integer search scores every candidate with the
//! exact palettes of the decoders it targets ([`Target`]) and minimises
//! their mean energy. `robust`, the default, targets all three, so one DDS
//! keeps its seams closed on any GPU: a candidate that one decoder rounds
//! away from the seam costs under that decoder, and the search moves on to
//! one that holds under all. With indices fixed, a channel's energy under
//! a decoder is Σᵢⱼ pᵢpⱼSᵢⱼ − 2Σᵢ pᵢRᵢ over the four palette values p, with
//! S and R summed once from the block's quadratic form, so an endpoint
//! candidate still costs O(1) per decoder.

// The kernels below index small fixed matrices by channel and slot in
// step; iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use crate::bc1::{pack565, unpack565, Block, Decoder, Target};
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
/// Integer endpoint candidates span this many steps either side of the
/// float optimum. Measured under `robust` (`cargo bench --bench
/// seam_aware`): at 2, blub's seams under AMD decoding stayed at 0.50× the
/// regular encoding's (0.021 levels against 0.043), and 3 changed nothing;
/// at 4 they close to 0.30× (0.013), with every other model and decoder
/// within 0.01 of its figure at 2, and 5 changes nothing more. The price is
/// the search's time: Fox 744 → 1028 ms, cube_gradient_1024 75 → 131,
/// blub 325 → 445.
const ENDPOINT_RADIUS: i32 = 4;
/// Candidates for one endpoint with the other fixed.
const CANDIDATES_PER_ROW: usize = 2 * ENDPOINT_RADIUS as usize + 1;

/// α of seam-aware BC1 unless told otherwise, from the trade-off curve of
/// `cargo bench --bench seam_aware`, with the cost measured against the
/// erased texture (the one BC1 compresses; against the input, erasure's own
/// change hides it). Under `robust`, α = 48 cuts the regular encoding's
/// seam_rms to 0.20–0.32× under every decoder on Fox, blub, Duck, CesiumMan
/// and cube_gradient_1024 at a cost of 0–0.13 dB; 256 bought only 5–10% more
/// seam agreement for 0.2–0.28 dB.
pub const DEFAULT_ALPHA: f64 = 48.0;

#[derive(Clone, Copy, Debug)]
pub struct SeamAwareOptions {
    /// α: weight of seam agreement against fidelity.
    pub alpha: f64,
    /// The decoders the seams must stay closed under.
    pub target: Target,
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
            target: Target::default(),
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

impl SeamAwareStats {
    /// One debug line with the figures, for the encoding named `what`.
    pub fn log(&self, what: &'static str) {
        tracing::debug!(
            what,
            blocks = self.blocks,
            sweeps = self.sweeps,
            energy_regular = self.energy_regular,
            energy_final = self.energy_final,
            "seam-aware encoding"
        );
    }
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

/// Per-block state during the integer search: endpoints per channel,
/// indices, and the four-colour palette each decoder makes of the endpoints
/// (\[0, 1\]; [`Decoder::ALL`] order).
#[derive(Clone, Copy)]
struct State {
    q: [[i32; 3]; 2],
    idx: [u8; 16],
    pal: [[[f64; 4]; 3]; 3],
}

impl State {
    fn new(q: [[i32; 3]; 2], idx: [u8; 16]) -> Self {
        let mut st = State {
            q,
            idx,
            pal: [[[0.0; 4]; 3]; 3],
        };
        st.refresh();
        st
    }

    fn from_block(b: &Block) -> Self {
        let (r0, g0, b0) = unpack565(b.c0);
        let (r1, g1, b1) = unpack565(b.c1);
        State::new(
            [
                [i32::from(r0), i32::from(g0), i32::from(b0)],
                [i32::from(r1), i32::from(g1), i32::from(b1)],
            ],
            std::array::from_fn(|k| b.index(k)),
        )
    }

    /// Recomputes the palettes after the endpoints changed. Four-colour
    /// mode throughout: [`State::to_block`] keeps it, and swapping the
    /// endpoints with entries 2 and 3 leaves every decoder's palette as is.
    fn refresh(&mut self) {
        for (d, dec) in Decoder::ALL.iter().enumerate() {
            for ch in 0..3 {
                self.pal[d][ch] = channel_palette(*dec, ch, self.q[0][ch], self.q[1][ch]);
            }
        }
    }

    /// Value of slot `k`, channel `ch`, under decoder number `d`.
    #[inline]
    fn decoded(&self, d: usize, k: usize, ch: usize) -> f64 {
        self.pal[d][ch][self.idx[k] as usize]
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

    /// Same endpoints and indices (the palettes follow from them).
    fn same(&self, other: &State) -> bool {
        self.q == other.q && self.idx == other.idx
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

/// One channel's four-colour palette under `dec`, in \[0, 1\].
#[inline]
fn channel_palette(dec: Decoder, ch: usize, q0: i32, q1: i32) -> [f64; 4] {
    dec.four_colour_palette_unit(ch, q0 as u8, q1 as u8)
}

/// The places in [`Decoder::ALL`] of a target's decoders, held inline: a
/// block's visit takes microseconds, and a vector per visit a good part of
/// them.
#[derive(Clone, Copy)]
struct Slots {
    len: usize,
    slot: [usize; MAX_DECODERS],
}

impl Slots {
    fn of(target: Target) -> Self {
        let mut out = Slots {
            len: 0,
            slot: [0; MAX_DECODERS],
        };
        for d in target.decoders() {
            out.slot[out.len] = Decoder::ALL.iter().position(|a| a == d).unwrap_or(0);
            out.len += 1;
        }
        out
    }

    fn len(&self) -> usize {
        self.len
    }

    fn iter(&self) -> impl Iterator<Item = usize> + '_ {
        self.slot[..self.len].iter().copied()
    }
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
    local: Reach,
}

/// A seam point's texel slots in one block and their coefficients, in the
/// order its taps first reach them. Held inline: a point has eight taps, and
/// on a 2048² atlas the hundreds of thousands of touches, each with a vector
/// of its own, cost more to allocate and free than the search spends on them.
#[derive(Clone, Copy)]
struct Reach {
    len: u8,
    slot: [u8; 8],
    coefficient: [f64; 8],
}

impl Reach {
    fn new() -> Self {
        Reach {
            len: 0,
            slot: [0; 8],
            coefficient: [0.0; 8],
        }
    }

    /// Adds `w` to slot `k`'s coefficient, taking a new place for a new slot.
    fn add(&mut self, k: u8, w: f64) {
        let n = usize::from(self.len);
        match self.slot[..n].iter().position(|&s| s == k) {
            Some(i) => self.coefficient[i] += w,
            None => {
                self.slot[n] = k;
                self.coefficient[n] = w;
                self.len += 1;
            }
        }
    }

    fn iter(&self) -> impl Iterator<Item = (u8, f64)> + '_ {
        let n = usize::from(self.len);
        self.slot[..n]
            .iter()
            .copied()
            .zip(self.coefficient[..n].iter().copied())
    }
}

struct Layout {
    bw: usize,
    /// Footprint blocks, ascending, and each block's slot in that list.
    blocks: Vec<usize>,
    slot: Vec<u32>,
    touches: Vec<Vec<Touch>>,
    /// Per seam point, where each of its taps lies: (block slot, texel
    /// slot in the block), in the order of the point's taps.
    at: Vec<[(u32, u8); 8]>,
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
            // The blocks the point's taps reach, in the order they first do.
            let mut per = [(0usize, Reach::new()); 8];
            let mut reached = 0;
            for &(t, w) in &q.taps {
                let (b, k) = block_of(t);
                let s = slot[b] as usize;
                let i = match per[..reached].iter().position(|e| e.0 == s) {
                    Some(i) => i,
                    None => {
                        per[reached].0 = s;
                        reached += 1;
                        reached - 1
                    }
                };
                per[i].1.add(k, w);
            }
            for &(s, local) in &per[..reached] {
                touches[s].push(Touch {
                    point: qi as u32,
                    local,
                });
            }
        }
        let at = p
            .points
            .iter()
            .map(|q| {
                q.taps.map(|(t, _)| {
                    let (b, k) = block_of(t);
                    (slot[b], k)
                })
            })
            .collect();
        Layout {
            bw,
            blocks,
            slot,
            touches,
            at,
        }
    }

    /// The sweep's schedule: block slots grouped into waves, each wave after
    /// every neighbour of lower slot and before every neighbour of higher
    /// slot. A sweep in slot order reads, for each block, its lower
    /// neighbours as already updated and its higher ones as not yet: so does
    /// a sweep wave by wave, whatever order the blocks of one wave take
    /// (no two of them are neighbours). The result is the same on any
    /// number of threads.
    fn waves(neighbours: &[Vec<u32>]) -> Vec<Vec<u32>> {
        let mut wave_of = vec![0usize; neighbours.len()];
        let mut waves: Vec<Vec<u32>> = Vec::new();
        for (s, near) in neighbours.iter().enumerate() {
            let w = near
                .iter()
                .filter(|&&n| (n as usize) < s)
                .map(|&n| wave_of[n as usize] + 1)
                .max()
                .unwrap_or(0);
            wave_of[s] = w;
            if waves.len() <= w {
                waves.resize_with(w + 1, Vec::new);
            }
            waves[w].push(s as u32);
        }
        waves
    }

    /// For each footprint block, the others that share a seam point with
    /// it: those whose local energy it enters.
    fn neighbours(&self) -> Vec<Vec<u32>> {
        let mut out: Vec<Vec<u32>> = vec![Vec::new(); self.blocks.len()];
        for taps in &self.at {
            // The blocks this point's taps lie in, each once.
            let mut blocks = [0u32; 8];
            let mut n = 0;
            for &(s, _) in taps {
                if !blocks[..n].contains(&s) {
                    blocks[n] = s;
                    n += 1;
                }
            }
            for &a in &blocks[..n] {
                out[a as usize].extend(blocks[..n].iter().copied().filter(|&b| b != a));
            }
        }
        for n in &mut out {
            n.sort_unstable();
            n.dedup();
        }
        out
    }

    /// Texel index of slot `k` of block `b`, or `None` in the padding.
    fn texel(&self, p: &Problem, b: usize, k: usize) -> Option<usize> {
        crate::bc1::block_texel((p.width, p.height), self.bw, b, k)
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
        let neighbours = layout.neighbours();
        // A block whose last search ended at a fixed point, none of whose
        // neighbours has moved since, would find the same state again: its
        // energy depends on nothing else. Later sweeps touch only the
        // blocks around those that still move.
        let waves = Layout::waves(&neighbours);
        tracing::debug!(
            blocks = states.len(),
            waves = waves.len(),
            "seam-aware schedule"
        );
        let mut settled = vec![false; states.len()];
        let mut energy = total_energy(p, &layout, &states, opts);
        let decoders = opts.target.decoders().len() as f64;
        for _ in 0..opts.max_sweeps {
            stats.sweeps += 1;
            // What the sweep takes off the energy: the blocks of a wave are
            // not neighbours, so their local falls add up to the total's,
            // which then needs no new sum over every seam point per sweep
            // (and no difference of two large sums).
            let mut fell = 0.0;
            let mut visited = 0usize;
            for wave in &waves {
                let due: Vec<u32> = wave
                    .iter()
                    .copied()
                    .filter(|&s| !settled[s as usize])
                    .collect();
                visited += due.len();
                let improve = |&s: &u32| improve_block(p, &layout, &states, s as usize, opts);
                let found: Vec<Improved> = if due.len() >= MIN_PARALLEL_WAVE {
                    due.par_iter().map(improve).collect()
                } else {
                    due.iter().map(improve).collect()
                };
                for (&s, found) in due.iter().zip(found) {
                    let (s, state) = (s as usize, found.state);
                    settled[s] = found.fixed;
                    fell += found.fell;
                    if !state.same(&states[s]) {
                        states[s] = state;
                        for &n in &neighbours[s] {
                            settled[n as usize] = false;
                        }
                    }
                }
            }
            let fell = fell / decoders;
            energy -= fell;
            tracing::trace!(
                sweep = stats.sweeps,
                visited,
                fell,
                energy,
                "seam-aware sweep"
            );
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

/// The decoded value of a seam point's tap at `(slot, k)` ([`Layout::at`]).
#[inline]
fn decoded_at(states: &[State], (slot, k): (u32, u8), d: usize, ch: usize) -> f64 {
    states[slot as usize].decoded(d, k as usize, ch)
}

/// E_c + α·E_s of the current states, the mean over the target's decoders.
fn total_energy(p: &Problem, layout: &Layout, states: &[State], opts: &SeamAwareOptions) -> f64 {
    let slots = Slots::of(opts.target);
    let mut e = 0.0;
    for d in slots.iter() {
        for (s, &b) in layout.blocks.iter().enumerate() {
            for k in 0..16 {
                if let Some(t) = layout.texel(p, b, k) {
                    let w = weight(p, t, opts);
                    for ch in 0..3 {
                        let v =
                            states[s].decoded(d, k, ch) - f64::from(p.target[t * p.channels + ch]);
                        e += w * v * v;
                    }
                }
            }
        }
        for (q, at) in p.points.iter().zip(&layout.at) {
            for ch in 0..3 {
                let v: f64 = q
                    .taps
                    .iter()
                    .zip(at)
                    .map(|(&(_, w), &place)| w * decoded_at(states, place, d, ch))
                    .sum();
                e += opts.alpha * q.weight * v * v;
            }
        }
    }
    e / slots.len() as f64
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
                let target: [f64; 3] =
                    std::array::from_fn(|ch| f64::from(p.target[t * p.channels + ch]));
                let taps = [(2 * s as u32, m[0]), (2 * s as u32 + 1, m[1])];
                sys.add_square(weight(p, t, opts), &taps, &target, &none);
            }
        }
        for e in 0..2 {
            let reg: [f64; 3] = std::array::from_fn(|ch| st.end(e, ch));
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
        st.refresh();
        if !st.valid() {
            *st = before;
        }
    }
    Ok(())
}

/// One block's share of the energy with its neighbours fixed: vᵀMv − 2vᵀr
/// per channel and decoder, over the block's 16 slots. M does not depend on
/// the decoder; r does, through the neighbours' decoded values.
struct Local {
    m: [[f64; 16]; 16],
    /// Per targeted decoder (in the order of [`Slots`]; the first
    /// `slots.len()`), per channel.
    r: [[[f64; 16]; 3]; MAX_DECODERS],
    slots: Slots,
}

fn local_energy(
    p: &Problem,
    layout: &Layout,
    states: &[State],
    s: usize,
    opts: &SeamAwareOptions,
) -> Local {
    let b = layout.blocks[s];
    let slots = Slots::of(opts.target);
    let mut m = [[0.0; 16]; 16];
    let mut r0 = [[0.0; 16]; 3];
    for k in 0..16 {
        if let Some(t) = layout.texel(p, b, k) {
            let w = weight(p, t, opts);
            m[k][k] += w;
            for ch in 0..3 {
                r0[ch][k] += w * f64::from(p.target[t * p.channels + ch]);
            }
        }
    }
    let mut r = [r0; MAX_DECODERS];
    for touch in &layout.touches[s] {
        let q = &p.points[touch.point as usize];
        let w = opts.alpha * q.weight;
        for (k, ck) in touch.local.iter() {
            for (l, cl) in touch.local.iter() {
                m[k as usize][l as usize] += w * ck * cl;
            }
        }
        for (di, d) in slots.iter().enumerate() {
            // Contribution of texels outside this block, at their current values.
            let mut rest = [0.0f64; 3];
            for (&(_, c), &place) in q.taps.iter().zip(&layout.at[touch.point as usize]) {
                if place.0 as usize != s {
                    for (ch, v) in rest.iter_mut().enumerate() {
                        *v += c * decoded_at(states, place, d, ch);
                    }
                }
            }
            for (k, ck) in touch.local.iter() {
                for ch in 0..3 {
                    r[di][ch][k as usize] -= w * ck * rest[ch];
                }
            }
        }
    }
    Local { m, r, slots }
}

/// A block's decoded values under each targeted decoder, M·v, and the
/// energy Σ v·(Mv − 2r) summed over the decoders.
struct Evaluated {
    v: [[[f64; 16]; 3]; MAX_DECODERS],
    mv: [[[f64; 16]; 3]; MAX_DECODERS],
    energy: f64,
}

/// The most decoders a target has: the searches' per-decoder values live
/// in arrays of this size, not in vectors allocated per candidate.
const MAX_DECODERS: usize = Decoder::ALL.len();

fn evaluate(local: &Local, st: &State) -> Evaluated {
    let mut out = Evaluated {
        v: [[[0.0; 16]; 3]; MAX_DECODERS],
        mv: [[[0.0; 16]; 3]; MAX_DECODERS],
        energy: 0.0,
    };
    for (di, d) in local.slots.iter().enumerate() {
        for ch in 0..3 {
            for k in 0..16 {
                out.v[di][ch][k] = st.decoded(d, k, ch);
            }
            for k in 0..16 {
                let mv: f64 = (0..16).map(|l| local.m[k][l] * out.v[di][ch][l]).sum();
                out.mv[di][ch][k] = mv;
                out.energy += out.v[di][ch][k] * (mv - 2.0 * local.r[di][ch][k]);
            }
        }
    }
    out
}

/// Waves with fewer blocks due than this run on the calling thread: a
/// block's search takes tens of microseconds, about what handing work to
/// another thread costs.
const MIN_PARALLEL_WAVE: usize = 4;

/// Rounds of [`improve_block`]'s alternation per visit: most blocks settle
/// in one or two; the rest continue in the next sweep.
const ROUNDS_PER_VISIT: usize = 4;

/// Step 2 for one block: alternate the best integer endpoints for the
/// current indices with single-texel index changes, while the energy falls.
fn improve_block(
    p: &Problem,
    layout: &Layout,
    states: &[State],
    s: usize,
    opts: &SeamAwareOptions,
) -> Improved {
    let local = local_energy(p, layout, states, s, opts);
    let mut best = states[s];
    let mut ev = evaluate(&local, &best);
    let start = ev.energy;
    let mut fixed = false;
    for _ in 0..ROUNDS_PER_VISIT {
        let mut changed = false;
        if let Some(cand) = best_endpoints(&local, &best) {
            let cev = evaluate(&local, &cand);
            if cev.energy < ev.energy - 1e-15 {
                (best, ev) = (cand, cev);
                changed = true;
            }
        }
        for k in 0..16 {
            for i in 0..4u8 {
                if i != best.idx[k] && try_index(&local, &mut best, &mut ev, k, i) {
                    changed = true;
                }
            }
        }
        if !changed {
            fixed = true;
            break;
        }
    }
    Improved {
        state: best,
        fixed,
        fell: start - ev.energy,
    }
}

/// What [`improve_block`] found for a block.
struct Improved {
    state: State,
    /// It stopped at a fixed point (a round changed nothing), not at the
    /// round limit.
    fixed: bool,
    /// How much its local energy, summed over the decoders, fell.
    fell: f64,
}

/// Moves slot `k` to palette entry `i` if that lowers the energy summed over
/// the decoders; keeps `ev` up to date.
fn try_index(local: &Local, st: &mut State, ev: &mut Evaluated, k: usize, i: u8) -> bool {
    let mut de = 0.0;
    let mut deltas = [[0.0f64; 3]; MAX_DECODERS];
    for (di, d) in local.slots.iter().enumerate() {
        for ch in 0..3 {
            let delta = st.pal[d][ch][i as usize] - ev.v[di][ch][k];
            deltas[di][ch] = delta;
            de += delta * delta * local.m[k][k]
                + 2.0 * delta * (ev.mv[di][ch][k] - local.r[di][ch][k]);
        }
    }
    if de >= -1e-15 {
        return false;
    }
    st.idx[k] = i;
    ev.energy += de;
    for (di, delta) in deltas.iter().take(local.slots.len()).enumerate() {
        for ch in 0..3 {
            ev.v[di][ch][k] += delta[ch];
            for l in 0..16 {
                ev.mv[di][ch][l] += local.m[l][k] * delta[ch];
            }
        }
    }
    true
}

/// With indices fixed, each channel's energy under one decoder is
/// Σᵢⱼ pᵢpⱼSᵢⱼ − 2Σᵢ pᵢRᵢ over its four palette values. The ideal palette
/// makes that a 2×2 quadratic in the two endpoint values, whose float
/// optimum centres the search; every integer candidate near it is then
/// scored exactly under each targeted decoder.
fn best_endpoints(local: &Local, st: &State) -> Option<State> {
    // S: M summed by the palette entries of both slots (shared by channels).
    let mut sm = [[0.0f64; 4]; 4];
    for k in 0..16 {
        for l in 0..16 {
            sm[st.idx[k] as usize][st.idx[l] as usize] += local.m[k][l];
        }
    }
    // H = Aᵀ M A for the ideal mix weights A.
    let mut h = [[0.0f64; 2]; 2];
    for i in 0..4 {
        for j in 0..4 {
            for a in 0..2 {
                for b in 0..2 {
                    h[a][b] += MIX[i][a] * sm[i][j] * MIX[j][b];
                }
            }
        }
    }
    // pᵀSp over S's upper triangle, the entries off the diagonal doubled
    // (S is symmetric but for rounding): ten products a candidate, not 16.
    let upper: [[f64; 4]; 4] = std::array::from_fn(|i| {
        std::array::from_fn(|j| match j.cmp(&i) {
            std::cmp::Ordering::Less => 0.0,
            std::cmp::Ordering::Equal => sm[i][i],
            std::cmp::Ordering::Greater => sm[i][j] + sm[j][i],
        })
    });
    let mut out = *st;
    for ch in 0..3 {
        // R per decoder: r summed by palette entry.
        let mut rs = [[0.0f64; 4]; MAX_DECODERS];
        for (acc, r) in rs.iter_mut().zip(&local.r).take(local.slots.len()) {
            for k in 0..16 {
                acc[st.idx[k] as usize] += r[ch][k];
            }
        }
        let rs = &rs[..local.slots.len()];
        let centre = ideal_optimum(&h, rs, st, ch);
        let mut tables = [Decoder::four_colour_unit_table(0, ch); MAX_DECODERS];
        for (t, d) in tables.iter_mut().zip(local.slots.iter()) {
            *t = Decoder::four_colour_unit_table(d, ch);
        }
        let cost = |q0: i32, q1: i32| {
            let mut c = 0.0;
            for (table, r) in tables.iter().zip(rs) {
                let p = table.at(q0 as usize, q1 as usize);
                for i in 0..4 {
                    let mut sp = upper[i][i] * p[i];
                    for j in i + 1..4 {
                        sp += upper[i][j] * p[j];
                    }
                    c += p[i] * (sp - 2.0 * r[i]);
                }
            }
            c
        };
        let max = (1 << BITS[ch]) - 1;
        let (g0, g1) = (nearest_level(centre[0], ch), nearest_level(centre[1], ch));
        let mut best = (st.q[0][ch], st.q[1][ch]);
        let mut best_c = cost(best.0, best.1);
        // A row of candidates is scored before any is compared: the
        // scores do not depend on each other, so the processor overlaps
        // them, where scoring and comparing in turn waits on each sum.
        let (lo, hi) = (
            (g1 - ENDPOINT_RADIUS).max(0),
            (g1 + ENDPOINT_RADIUS).min(max),
        );
        let mut row = [0.0f64; CANDIDATES_PER_ROW];
        for q0 in (g0 - ENDPOINT_RADIUS).max(0)..=(g0 + ENDPOINT_RADIUS).min(max) {
            for (c, q1) in row.iter_mut().zip(lo..=hi) {
                *c = cost(q0, q1);
            }
            for (&c, q1) in row.iter().zip(lo..=hi) {
                if c < best_c {
                    best = (q0, q1);
                    best_c = c;
                }
            }
        }
        out.q[0][ch] = best.0;
        out.q[1][ch] = best.1;
    }
    out.refresh();
    out.valid().then_some(out)
}

/// The float endpoints that minimise the ideal palette's energy for channel
/// `ch` (with R averaged over the decoders), or the current ones when that
/// quadratic is singular.
fn ideal_optimum(h: &[[f64; 2]; 2], rs: &[[f64; 4]], st: &State, ch: usize) -> [f64; 2] {
    let mut f = [0.0f64; 2];
    for r in rs {
        for i in 0..4 {
            f[0] += MIX[i][0] * r[i] / rs.len() as f64;
            f[1] += MIX[i][1] * r[i] / rs.len() as f64;
        }
    }
    let det = h[0][0] * h[1][1] - h[0][1] * h[1][0];
    if det.abs() > 1e-12 * (h[0][0] * h[1][1]).abs().max(1e-300) {
        [
            (h[1][1] * f[0] - h[0][1] * f[1]) / det,
            (h[0][0] * f[1] - h[1][0] * f[0]) / det,
        ]
    } else {
        [st.end(0, ch), st.end(1, ch)]
    }
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
        for (n, dec) in Decoder::ALL.iter().enumerate() {
            let d = b.decode_with(*dec);
            for k in 0..16 {
                for ch in 0..3 {
                    assert!((s.decoded(n, k, ch) - f64::from(d[k][ch])).abs() < 1e-6);
                }
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
