//! Seam-aware BC3 alpha: the alpha blocks under the seams re-encoded so
//! that the *decoded* alpha stays seam-free, as `seam_aware.rs` does for
//! colour (SPEC §6's energy, one channel).
//!
//! Over the blocks that hold a texel of any seam sample's bilinear
//! footprint, minimise E_c + α·E_s, the mean over the target's decoders:
//! E_c = Σ w_t (decoded_t − target_t)², E_s = Σ_points weight·(B₁ − B₂)².
//! An alpha block has 65 536 endpoint pairs and 8¹⁶ index sets, and one
//! channel, so a plain block coordinate descent serves: for each block,
//! endpoint pairs near its current ones in both modes (indices picked for
//! fidelity), then each texel's index in turn against the whole energy;
//! a change is kept only when it lowers the block's share of the energy.

use super::alpha::AlphaBlock;
use super::seam_aware::{SeamAwareOptions, SeamAwareStats};
use super::{block_dims, Decoder};
use crate::seam::quadrature::QuadPoint;

/// Endpoint steps tried either side of a block's current endpoints.
const ENDPOINT_RADIUS: i32 = 1;

/// The alpha channel and the seams it must agree along.
pub struct AlphaProblem<'a> {
    pub width: usize,
    pub height: usize,
    /// One alpha per texel, in \[0, 1\].
    pub target: &'a [f32],
    pub inside: &'a [bool],
    /// Seam differences at the Gauss points, weights in texel-length units.
    pub points: &'a [QuadPoint],
}

struct Search<'a> {
    p: &'a AlphaProblem<'a>,
    opts: &'a SeamAwareOptions,
    decoders: &'a [Decoder],
    bw: usize,
    /// Decoded alpha per decoder, per texel.
    dec: Vec<Vec<f32>>,
    /// The seam points that tap each footprint block.
    touches: Vec<Vec<u32>>,
}

impl Search<'_> {
    fn texel(&self, b: usize, k: usize) -> Option<usize> {
        crate::bc1::block_texel((self.p.width, self.p.height), self.bw, b, k)
    }

    fn set(&mut self, b: usize, block: &AlphaBlock) {
        for (d, dec) in self.decoders.iter().enumerate() {
            let v = block.decode_with(*dec);
            for (k, &a) in v.iter().enumerate() {
                if let Some(t) = self.texel(b, k) {
                    self.dec[d][t] = a;
                }
            }
        }
    }

    /// Σ w (decoded − target)² over block `b`'s texels, summed over the
    /// decoders.
    fn fidelity(&self, b: usize) -> f64 {
        let mut e = 0.0;
        for k in 0..16 {
            if let Some(t) = self.texel(b, k) {
                let w = if self.p.inside[t] {
                    1.0
                } else {
                    self.opts.outside_weight
                };
                for dec in &self.dec {
                    let v = f64::from(dec[t] - self.p.target[t]);
                    e += w * v * v;
                }
            }
        }
        e
    }

    /// α·weight·(B₁ − B₂)² of seam point `q`, summed over the decoders.
    fn seam(&self, q: u32) -> f64 {
        let q = &self.p.points[q as usize];
        self.dec
            .iter()
            .map(|dec| {
                let v: f64 = q
                    .taps
                    .iter()
                    .map(|&(t, w)| w * f64::from(dec[t as usize]))
                    .sum();
                self.opts.alpha * q.weight * v * v
            })
            .sum()
    }

    /// Block `b`'s share of the energy (mean over the decoders): its
    /// texels' fidelity and every seam point that taps it. Nothing else
    /// changes when the block does.
    fn energy(&self, b: usize, s: usize) -> f64 {
        let seams: f64 = self.touches[s].iter().map(|&q| self.seam(q)).sum();
        (self.fidelity(b) + seams) / self.dec.len() as f64
    }

    /// E_c + α·E_s over the footprint blocks, the mean over the decoders.
    fn total(&self, footprint: &[usize]) -> f64 {
        let fidelity: f64 = footprint.iter().map(|&b| self.fidelity(b)).sum();
        let seams: f64 = (0..self.p.points.len() as u32).map(|q| self.seam(q)).sum();
        (fidelity + seams) / self.dec.len() as f64
    }

    /// The block's target alphas, 0–255 (0 in the padding).
    fn values(&self, b: usize) -> [f32; 16] {
        std::array::from_fn(|k| self.texel(b, k).map_or(0.0, |t| self.p.target[t] * 255.0))
    }

    /// One block's turn: returns the block it settles on.
    fn improve(&mut self, b: usize, s: usize, current: AlphaBlock) -> AlphaBlock {
        let mut best = (current, self.energy(b, s));
        let values = self.values(b);
        let try_block = |this: &mut Self, cand: AlphaBlock, best: &mut (AlphaBlock, f64)| {
            this.set(b, &cand);
            let e = this.energy(b, s);
            if e < best.1 {
                *best = (cand, e);
            }
        };
        let (a0, a1) = (i32::from(current.a0), i32::from(current.a1));
        let r = ENDPOINT_RADIUS;
        for (x, y) in [(a0, a1), (a1, a0)] {
            for i in -r..=r {
                for j in -r..=r {
                    let (c0, c1) = (x + i, y + j);
                    if !(0..=255).contains(&c0) || !(0..=255).contains(&c1) {
                        continue;
                    }
                    let (c0, c1) = (c0 as u8, c1 as u8);
                    let pals: Vec<[f32; 8]> = self
                        .decoders
                        .iter()
                        .map(|d| d.alpha_palette(c0, c1))
                        .collect();
                    // Indices for fidelity; the per-texel pass below
                    // weighs the seams.
                    let idx: [u8; 16] = std::array::from_fn(|k| {
                        let err = |i: u8| -> f32 {
                            pals.iter()
                                .map(|p| (p[i as usize] - values[k]).powi(2))
                                .sum()
                        };
                        (0..8u8)
                            .min_by(|&m, &n| err(m).total_cmp(&err(n)))
                            .unwrap_or(0)
                    });
                    try_block(self, AlphaBlock::with_indices(c0, c1, &idx), &mut best);
                }
            }
        }
        // Each texel's index against the seams as well.
        for k in 0..16 {
            let base = best.0;
            let idx: [u8; 16] = std::array::from_fn(|m| base.index(m));
            for i in 0..8u8 {
                if i == idx[k] {
                    continue;
                }
                let mut cand = idx;
                cand[k] = i;
                try_block(
                    self,
                    AlphaBlock::with_indices(base.a0, base.a1, &cand),
                    &mut best,
                );
            }
        }
        self.set(b, &best.0);
        best.0
    }
}

/// Re-encodes the alpha blocks under the seams of `p`; `blocks` holds the
/// regular encoding on entry and the seam-aware one on return.
pub fn optimise_alpha(
    p: &AlphaProblem,
    blocks: &mut [AlphaBlock],
    opts: &SeamAwareOptions,
) -> SeamAwareStats {
    let bw = block_dims(p.width, p.height).0;
    let block_of = |t: u32| ((t as usize / p.width) / 4) * bw + (t as usize % p.width) / 4;
    let mut footprint: Vec<usize> = p
        .points
        .iter()
        .flat_map(|q| q.taps.iter().map(|&(t, _)| block_of(t)))
        .collect();
    footprint.sort_unstable();
    footprint.dedup();
    let mut touches: Vec<Vec<u32>> = vec![Vec::new(); footprint.len()];
    for (qi, q) in p.points.iter().enumerate() {
        let mut seen: Vec<usize> = q.taps.iter().map(|&(t, _)| block_of(t)).collect();
        seen.sort_unstable();
        seen.dedup();
        for b in seen {
            if let Ok(s) = footprint.binary_search(&b) {
                touches[s].push(qi as u32);
            }
        }
    }
    let decoders = opts.target.decoders();
    let mut search = Search {
        p,
        opts,
        decoders,
        bw,
        dec: vec![vec![0.0; p.width * p.height]; decoders.len()],
        touches,
    };
    for (b, block) in blocks.iter().enumerate() {
        search.set(b, block);
    }
    let mut stats = SeamAwareStats {
        blocks: footprint.len(),
        energy_regular: search.total(&footprint),
        ..SeamAwareStats::default()
    };
    let mut energy = stats.energy_regular;
    for _ in 0..opts.max_sweeps {
        stats.sweeps += 1;
        for (s, &b) in footprint.iter().enumerate() {
            blocks[b] = search.improve(b, s, blocks[b]);
        }
        let e = search.total(&footprint);
        let fell = energy - e;
        energy = e;
        if fell <= 1e-9 * energy.max(1e-300) {
            break;
        }
    }
    stats.energy_final = energy;
    stats
}
