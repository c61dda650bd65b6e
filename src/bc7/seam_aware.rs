//! Seam-aware BC7: re-encode the blocks under the seams so that the
//! *decoded* texture keeps its seams closed (SPEC §6's energy, as
//! `crate::bc1::seam_aware` minimises it for BC1).
//!
//! Over the blocks that hold a texel of any seam sample's bilinear
//! footprint, minimise E_c + α·E_s, texel values in \[0, 1\]:
//! * E_c = Σ w_t |decoded_t − target_t|², w_t = 1 inside the UV charts and
//!   `outside_weight` outside; alpha counts only where the texture's alpha
//!   matters;
//! * E_s = Σ_points weight·(Σ taps·decoded)² per channel: the colour
//!   channels along `points`, alpha along its own `alpha_points`.
//!
//! A block coordinate descent over the footprint blocks in ascending order
//! (the same on any number of threads), sweep after sweep until no block
//! changes or `max_sweeps`: each block in turn, with its neighbours fixed,
//! takes the best candidate of `seam_block.rs`. After the first
//! sweep, a block is visited again only when a block it shares a seam
//! point with has changed (nothing else enters its energy). Every accepted change
//! lowers the energy, so the result is never worse than the regular
//! encoding; a final check keeps the regular blocks if rounding said
//! otherwise.

// Small fixed arrays indexed by channel, texel and value in step;
// iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

use super::encode::{self, Effort};
use super::params::Params;
use super::seam_block::{values, BlockSearch, Local};
use super::{block_dims, Block, Level};
pub use crate::bc1::seam_aware::{SeamAwareOptions, SeamAwareStats};
use crate::seam::quadrature::QuadPoint;

/// The texture, its charts and its seams.
pub struct Problem<'a> {
    pub width: usize,
    pub height: usize,
    /// The texture the blocks should reproduce: RGB in \[0, 1\], 3 per texel.
    pub rgb: &'a [f32],
    /// Alpha in \[0, 1\], 1 per texel, when alpha matters.
    pub alpha: Option<&'a [f32]>,
    pub inside: &'a [bool],
    /// Colour seam differences at the Gauss points, weights in
    /// texel-length units.
    pub points: &'a [QuadPoint],
    /// Alpha's own seams (those closed for alpha), when alpha matters;
    /// `None`: alpha follows `points`.
    pub alpha_points: Option<&'a [QuadPoint]>,
    /// The regular encoder's level, for the blocks re-encoded towards the
    /// seams' optimum.
    pub level: Level,
}

/// Why the search could not run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SeamAwareError {
    #[error("{what} holds {got} values, a {width}x{height} texture needs {need}")]
    Size {
        what: &'static str,
        width: usize,
        height: usize,
        need: usize,
        got: usize,
    },
    #[error("{got} blocks given, a {width}x{height} texture needs {need}")]
    BlockCount {
        width: usize,
        height: usize,
        need: usize,
        got: usize,
    },
    #[error("a seam point taps texel {texel}, past the {width}x{height} texture")]
    Tap {
        texel: u32,
        width: usize,
        height: usize,
    },
}

impl Problem<'_> {
    fn check(&self, blocks: usize) -> Result<(), SeamAwareError> {
        let (w, h) = (self.width, self.height);
        let n = w.saturating_mul(h);
        let size = |what, need: usize, got: usize| {
            if got < need || (what == "inside" && got != need) {
                Err(SeamAwareError::Size {
                    what,
                    width: w,
                    height: h,
                    need,
                    got,
                })
            } else {
                Ok(())
            }
        };
        size("rgb", n.saturating_mul(3), self.rgb.len())?;
        size("inside", n, self.inside.len())?;
        if let Some(a) = self.alpha {
            size("alpha", n, a.len())?;
        }
        let (bw, bh) = block_dims(w, h);
        if w == 0 || h == 0 || blocks != bw * bh {
            return Err(SeamAwareError::BlockCount {
                width: w,
                height: h,
                need: bw * bh,
                got: blocks,
            });
        }
        let all = self.points.iter().chain(self.alpha_points.unwrap_or(&[]));
        for q in all {
            for &(t, _) in &q.taps {
                if t as usize >= n {
                    return Err(SeamAwareError::Tap {
                        texel: t,
                        width: w,
                        height: h,
                    });
                }
            }
        }
        Ok(())
    }

    fn alpha_seams(&self) -> &[QuadPoint] {
        match self.alpha {
            None => &[],
            Some(_) => self.alpha_points.unwrap_or(self.points),
        }
    }
}

/// One seam point's reach into one block: texel slots and coefficients.
struct Touch {
    point: u32,
    local: Vec<(u8, f64)>,
}

/// The footprint blocks and, for each, the seam points that tap it.
struct Footprint {
    bw: usize,
    blocks: Vec<usize>,
    /// Per footprint block: colour touches, alpha touches.
    touches: Vec<[Vec<Touch>; 2]>,
}

impl Footprint {
    fn new(p: &Problem) -> Footprint {
        let (bw, bh) = block_dims(p.width, p.height);
        let block_of = |t: u32| {
            let (x, y) = (t as usize % p.width, t as usize / p.width);
            ((y / 4) * bw + x / 4, ((y % 4) * 4 + x % 4) as u8)
        };
        let seams = [p.points, p.alpha_seams()];
        let mut slot = vec![u32::MAX; bw * bh];
        let mut blocks = Vec::new();
        for q in seams.iter().flat_map(|s| s.iter()) {
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
        let mut touches: Vec<[Vec<Touch>; 2]> = (0..blocks.len())
            .map(|_| [Vec::new(), Vec::new()])
            .collect();
        for (g, points) in seams.iter().enumerate() {
            for (qi, q) in points.iter().enumerate() {
                let mut per: Vec<(usize, Vec<(u8, f64)>)> = Vec::new();
                for &(t, w) in &q.taps {
                    if w == 0.0 {
                        continue;
                    }
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
                    touches[s][g].push(Touch {
                        point: qi as u32,
                        local,
                    });
                }
            }
        }
        Footprint {
            bw,
            blocks,
            touches,
        }
    }

    /// For each footprint block, the others that share a seam point with
    /// it: those whose energy it enters.
    fn neighbours(&self) -> Vec<Vec<u32>> {
        let mut at_point: [std::collections::BTreeMap<u32, Vec<u32>>; 2] = Default::default();
        for (s, groups) in self.touches.iter().enumerate() {
            for (g, touches) in groups.iter().enumerate() {
                for t in touches {
                    at_point[g].entry(t.point).or_default().push(s as u32);
                }
            }
        }
        let mut out: Vec<Vec<u32>> = vec![Vec::new(); self.blocks.len()];
        for blocks in at_point.iter().flat_map(|m| m.values()) {
            for &a in blocks {
                out[a as usize].extend(blocks.iter().copied().filter(|&b| b != a));
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

struct Search<'a> {
    p: &'a Problem<'a>,
    opts: &'a SeamAwareOptions,
    fp: Footprint,
    /// The decoded texture, RGBA in \[0, 1\].
    dec: Vec<[f64; 4]>,
}

impl Search<'_> {
    fn weight(&self, t: usize) -> f64 {
        if self.p.inside[t] {
            1.0
        } else {
            self.opts.outside_weight
        }
    }

    fn target(&self, t: usize) -> [f64; 4] {
        let rgb = &self.p.rgb[t * 3..t * 3 + 3];
        let a = self.p.alpha.map_or(1.0, |a| f64::from(a[t]));
        [f64::from(rgb[0]), f64::from(rgb[1]), f64::from(rgb[2]), a]
    }

    fn set(&mut self, b: usize, params: &Params) {
        let v = values(params);
        for (k, val) in v.iter().enumerate() {
            if let Some(t) = self.fp.texel(self.p, b, k) {
                self.dec[t] = *val;
            }
        }
    }

    /// Channels of a seam group: RGB for colour, A for alpha.
    fn channels(g: usize) -> std::ops::Range<usize> {
        if g == 0 {
            0..3
        } else {
            3..4
        }
    }

    fn points(&self, g: usize) -> &[QuadPoint] {
        if g == 0 {
            self.p.points
        } else {
            self.p.alpha_seams()
        }
    }

    /// Block `s`'s quadratic with its neighbours at their current values.
    fn local(&self, s: usize) -> Local {
        let b = self.fp.blocks[s];
        let mut local = Local {
            m: [[[0.0; 16]; 16]; 2],
            r: [[0.0; 16]; 4],
        };
        let alpha = self.p.alpha.is_some();
        for k in 0..16 {
            if let Some(t) = self.fp.texel(self.p, b, k) {
                let w = self.weight(t);
                let target = self.target(t);
                local.m[0][k][k] += w;
                if alpha {
                    local.m[1][k][k] += w;
                }
                for c in 0..4 {
                    if c < 3 || alpha {
                        local.r[c][k] += w * target[c];
                    }
                }
            }
        }
        for g in 0..2 {
            let points = self.points(g);
            for touch in &self.fp.touches[s][g] {
                let q = &points[touch.point as usize];
                let w = self.opts.alpha * q.weight;
                for &(k, ck) in &touch.local {
                    for &(l, cl) in &touch.local {
                        local.m[g][usize::from(k)][usize::from(l)] += w * ck * cl;
                    }
                }
                for c in Self::channels(g) {
                    // The taps outside this block, at their current values.
                    let rest: f64 = q
                        .taps
                        .iter()
                        .filter(|&&(t, _)| self.block_of(t) != b)
                        .map(|&(t, cw)| cw * self.dec[t as usize][c])
                        .sum();
                    for &(k, ck) in &touch.local {
                        local.r[c][usize::from(k)] -= w * ck * rest;
                    }
                }
            }
        }
        local
    }

    fn block_of(&self, t: u32) -> usize {
        let (x, y) = (t as usize % self.p.width, t as usize / self.p.width);
        (y / 4) * self.fp.bw + x / 4
    }

    /// E_c + α·E_s over the footprint, at the current decoded values.
    fn total(&self) -> f64 {
        let mut e = 0.0;
        let alpha = self.p.alpha.is_some();
        for &b in &self.fp.blocks {
            for k in 0..16 {
                if let Some(t) = self.fp.texel(self.p, b, k) {
                    let w = self.weight(t);
                    let target = self.target(t);
                    for c in 0..4 {
                        if c < 3 || alpha {
                            let d = self.dec[t][c] - target[c];
                            e += w * d * d;
                        }
                    }
                }
            }
        }
        for g in 0..2 {
            for q in self.points(g) {
                for c in Self::channels(g) {
                    let v: f64 = q
                        .taps
                        .iter()
                        .map(|&(t, w)| w * self.dec[t as usize][c])
                        .sum();
                    e += self.opts.alpha * q.weight * v * v;
                }
            }
        }
        e
    }
}

/// Re-encodes the blocks under the seams of `p`; `blocks` holds the regular
/// encoding on entry and the seam-aware one on return.
pub fn optimise(
    p: &Problem,
    blocks: &mut [Block],
    opts: &SeamAwareOptions,
) -> Result<SeamAwareStats, SeamAwareError> {
    p.check(blocks.len())?;
    let fp = Footprint::new(p);
    let mut stats = SeamAwareStats {
        blocks: fp.blocks.len(),
        ..SeamAwareStats::default()
    };
    if fp.blocks.is_empty() {
        return Ok(stats);
    }
    let mut search = Search {
        p,
        opts,
        fp,
        dec: vec![[0.0; 4]; p.width * p.height],
    };
    // Blocks of the reserved mode are re-encoded like any other: their
    // fields start as mode 6's, all zero.
    let mut params: Vec<Params> = search
        .fp
        .blocks
        .iter()
        .map(|&b| {
            blocks[b].params().unwrap_or(Params {
                mode: 6,
                ..Params::default()
            })
        })
        .collect();
    for &b in &search.fp.blocks.clone() {
        let v = values_of(&blocks[b]);
        for (k, val) in v.iter().enumerate() {
            if let Some(t) = search.fp.texel(p, b, k) {
                search.dec[t] = *val;
            }
        }
    }
    // Texels outside the footprint that seams tap are in footprint blocks
    // by construction; the rest of `dec` is never read.
    stats.energy_regular = search.total();
    let effort: Effort = encode::effort(p.level);
    let block_search = BlockSearch {
        effort: &effort,
        weights: [1.0, 1.0, 1.0, if p.alpha.is_some() { 1.0 } else { 0.0 }],
        alpha: p.alpha.is_some(),
    };
    let neighbours = search.fp.neighbours();
    let mut dirty = vec![true; search.fp.blocks.len()];
    let mut changed_any = false;
    for sweep in 0..opts.max_sweeps {
        stats.sweeps = sweep + 1;
        let mut changed = false;
        for s in 0..search.fp.blocks.len() {
            if !std::mem::take(&mut dirty[s]) {
                continue;
            }
            let local = search.local(s);
            let current = local.energy(&values(&params[s]));
            let (best, e) = block_search.improve(&local, params[s], sweep == 0);
            if e < current - 1e-12 * current.abs().max(1e-12) && best != params[s] {
                params[s] = best;
                let b = search.fp.blocks[s];
                search.set(b, &best);
                changed = true;
                for &n in &neighbours[s] {
                    dirty[n as usize] = true;
                }
            }
        }
        changed_any |= changed;
        if !changed {
            break;
        }
    }
    stats.energy_final = search.total();
    if !changed_any || stats.energy_final > stats.energy_regular {
        stats.energy_final = stats.energy_final.min(stats.energy_regular);
        return Ok(stats);
    }
    for (s, &b) in search.fp.blocks.iter().enumerate() {
        blocks[b] = Block::from_params(&params[s]);
    }
    Ok(stats)
}

/// A block's decoded texels in \[0, 1\], the reserved mode included.
fn values_of(b: &Block) -> [[f64; 4]; 16] {
    b.decode().map(|t| t.map(|v| f64::from(v) / 255.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bc7::{decode_image, encode_image, EncodeOptions};

    const W: usize = 32;

    /// A noisy texture whose column 25 repeats column 6, and the seam
    /// points that say so: the two columns must decode alike.
    fn seam_texture(alpha: bool) -> (Vec<u8>, Vec<QuadPoint>) {
        let mut state = 0x2545_f491_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % 256) as u8
        };
        let mut rgba = vec![0u8; W * W * 4];
        for y in 0..W {
            for x in 0..W {
                let o = (y * W + x) * 4;
                let base = [(x * 6) as u8, (y * 7) as u8, 128, (x * 3 + y * 4) as u8];
                for c in 0..4 {
                    let n = next() / 8;
                    rgba[o + c] = base[c].saturating_add(n);
                }
                if !alpha {
                    rgba[o + 3] = 255;
                }
            }
        }
        let mut points = Vec::new();
        for y in 0..W {
            let (a, b) = (y * W + 6, y * W + 25);
            let copy: [u8; 4] = rgba[a * 4..a * 4 + 4].try_into().unwrap();
            rgba[b * 4..b * 4 + 4].copy_from_slice(&copy);
            let mut taps = [(a as u32, 0.0); 8];
            taps[0] = (a as u32, 1.0);
            taps[1] = (b as u32, -1.0);
            points.push(QuadPoint { weight: 1.0, taps });
        }
        (rgba, points)
    }

    fn seam_energy(dec: &[u8], points: &[QuadPoint], channels: std::ops::Range<usize>) -> f64 {
        points
            .iter()
            .map(|q| {
                channels
                    .clone()
                    .map(|c| {
                        let v: f64 = q
                            .taps
                            .iter()
                            .map(|&(t, w)| w * f64::from(dec[t as usize * 4 + c]) / 255.0)
                            .sum();
                        q.weight * v * v
                    })
                    .sum::<f64>()
            })
            .sum()
    }

    fn run(alpha: bool, level: Level) -> (Vec<Block>, Vec<Block>, SeamAwareStats) {
        let (rgba, points) = seam_texture(alpha);
        let rgb: Vec<f32> = rgba
            .chunks_exact(4)
            .flat_map(|t| [t[0], t[1], t[2]].map(|v| f32::from(v) / 255.0))
            .collect();
        let a: Vec<f32> = rgba
            .chunks_exact(4)
            .map(|t| f32::from(t[3]) / 255.0)
            .collect();
        let inside = vec![true; W * W];
        let opts = EncodeOptions::new(level, alpha);
        let regular = encode_image(&rgba, W, W, &opts).unwrap();
        let p = Problem {
            width: W,
            height: W,
            rgb: &rgb,
            alpha: alpha.then_some(&a[..]),
            inside: &inside,
            points: &points,
            alpha_points: None,
            level,
        };
        let mut blocks = regular.clone();
        let sa = SeamAwareOptions::default();
        let stats = optimise(&p, &mut blocks, &sa).unwrap();
        (regular, blocks, stats)
    }

    #[test]
    fn seams_close_and_fidelity_holds() {
        for (alpha, level) in [(false, Level::Fast), (true, Level::Fast)] {
            let (rgba, points) = seam_texture(alpha);
            let (regular, seam, stats) = run(alpha, level);
            let channels = if alpha { 0..4 } else { 0..3 };
            let d0 = decode_image(&regular, W, W).unwrap();
            let d1 = decode_image(&seam, W, W).unwrap();
            let (e0, e1) = (
                seam_energy(&d0, &points, channels.clone()),
                seam_energy(&d1, &points, channels.clone()),
            );
            let p0 = crate::bc7::psnr(&rgba, &d0, channels.clone()).unwrap();
            let p1 = crate::bc7::psnr(&rgba, &d1, channels.clone()).unwrap();
            eprintln!(
                "alpha {alpha}: seam energy {e0:.5} -> {e1:.5}, PSNR {p0:.2} -> {p1:.2}, {stats:?}"
            );
            assert!(stats.energy_final < stats.energy_regular, "{stats:?}");
            assert!(e1 < 0.2 * e0, "alpha {alpha}: seam energy {e0} -> {e1}");
            assert!(p1 > p0 - 1.0, "alpha {alpha}: PSNR {p0} -> {p1}");
            // Blocks away from the seams are untouched.
            for (n, (a, b)) in regular.iter().zip(&seam).enumerate() {
                if n % 8 != 1 && n % 8 != 6 {
                    assert_eq!(a, b, "block {n}");
                }
            }
        }
    }

    #[test]
    fn same_result_on_any_thread_count() {
        let on = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| run(true, Level::Fast).1)
        };
        assert_eq!(on(1), on(2));
    }

    #[test]
    fn bad_problems_are_errors() {
        let rgb = vec![0.5f32; 4 * 4 * 3];
        let inside = vec![true; 16];
        let mut taps = [(0u32, 0.0); 8];
        taps[0] = (99, 1.0);
        let points = [QuadPoint { weight: 1.0, taps }];
        let p = Problem {
            width: 4,
            height: 4,
            rgb: &rgb,
            alpha: None,
            inside: &inside,
            points: &points,
            alpha_points: None,
            level: Level::Fast,
        };
        let mut blocks = vec![Block::default(); 1];
        let opts = SeamAwareOptions::default();
        assert!(matches!(
            optimise(&p, &mut blocks, &opts),
            Err(SeamAwareError::Tap { .. })
        ));
        assert!(matches!(
            optimise(&p, &mut [], &opts),
            Err(SeamAwareError::BlockCount { .. })
        ));
        let short = Problem {
            rgb: &rgb[..10],
            ..p
        };
        assert!(matches!(
            optimise(&short, &mut blocks, &opts),
            Err(SeamAwareError::Size { .. })
        ));
    }
}
