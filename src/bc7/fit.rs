//! Fitting one subset's endpoints and indices: a principal-axis start,
//! least-squares endpoints for fixed indices (as in Castaño, "High Quality
//! DXT Compression using CUDA", 2007, and Intel's ISPC BC7 kernel), each
//! float fit quantised under every p-bit choice and scored by the exact
//! integer decode, and, at the highest effort, a ±1 search over the
//! quantised endpoint codes.
//!
//! A fit covers `N` channels that share one index set: RGB (modes 0–3),
//! RGBA (modes 6, 7), or, in modes 4 and 5, the three colour channels and
//! the one scalar channel apart. Values are 0–255, errors weighted squared
//! 8-bit differences. A channel of weight 0 does not matter to the caller:
//! it is kept at the top of its range so that it decodes to 255 where the
//! p-bits allow.

// Small fixed arrays indexed by channel, texel and value in step;
// iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

use super::modes::{expand, interpolate, weights, PBits};
use super::solid;

/// Subsets whose channels all span at most this many levels also try the
/// single-colour tables ([`solid`]): on the bench's Fox crop that lifted
/// `default` from 60.7 to 62.8 dB (mode 6 alone: 54.5 to 59.7), and Duck
/// from 59.6 to 62.1.
const SOLID_RANGE: f32 = 12.0;

/// What a subset's fit may use.
#[derive(Clone, Copy, Debug)]
pub struct Setup<const N: usize> {
    /// Stored bits per channel, p-bit excluded.
    pub bits: [u32; N],
    pub pbits: PBits,
    pub index_bits: u32,
    /// Error weight per channel.
    pub w: [f32; N],
}

/// How hard a fit tries.
#[derive(Clone, Copy, Debug)]
pub struct FitEffort {
    /// Least-squares refits after the principal-axis start.
    pub refine: usize,
    /// Score every p-bit choice by its decode (else take the choice that
    /// quantises the float endpoints most closely).
    pub pbit_search: bool,
    /// Rounds of ±1 moves over the quantised endpoint codes.
    pub code_search: usize,
}

/// A quantised fit: stored codes, p-bits, indices (in the order of the
/// texels given) and their weighted squared error.
#[derive(Clone, Copy, Debug)]
pub struct Fit<const N: usize> {
    pub codes: [[u8; N]; 2],
    pub pbits: [u8; 2],
    pub indices: [u8; 16],
    pub err: f32,
}

/// The p-bit pairs a mode allows.
fn pbit_choices(p: PBits) -> &'static [[u8; 2]] {
    match p {
        PBits::None => &[[0, 0]],
        PBits::Shared => &[[0, 0], [1, 1]],
        PBits::Unique => &[[0, 0], [0, 1], [1, 0], [1, 1]],
    }
}

/// The 8-bit value of stored code `q` with p-bit `p`.
#[inline]
fn decoded(q: u32, bits: u32, pbits: PBits, p: u8) -> u32 {
    match pbits {
        PBits::None => expand(q, bits),
        _ => expand((q << 1) | u32::from(p), bits + 1),
    }
}

/// The stored code whose decode lies nearest `v` (0–255).
#[inline]
pub fn quantise(v: f32, bits: u32, pbits: PBits, p: u8) -> u8 {
    let max = (1i32 << bits) - 1;
    let levels = if pbits == PBits::None {
        max as f32
    } else {
        (2 * max + 1) as f32
    };
    let x = v.clamp(0.0, 255.0) * levels / 255.0;
    let guess = if pbits == PBits::None {
        x.round() as i32
    } else {
        ((x - f32::from(p)) * 0.5).round() as i32
    };
    let mut best = (f32::MAX, 0);
    for q in (guess - 1).max(0)..=(guess + 1).min(max) {
        let d = (decoded(q as u32, bits, pbits, p) as f32 - v).abs();
        if d < best.0 {
            best = (d, q);
        }
    }
    best.1 as u8
}

/// Palettes of this many entries or fewer are searched in full; larger
/// ones (4-bit indices) only around each texel's projection on the
/// endpoint axis, which finds the nearest entry for all but texels far off
/// the axis, where the next entry is within a fraction of a level.
const FULL_SEARCH: usize = 8;

/// The best palette entry for each texel (see [`FULL_SEARCH`]); the
/// weighted squared error, or `f32::MAX` once it passes `stop_above`.
#[inline]
fn assign<const N: usize>(
    px: &[[f32; N]],
    palette: &[[f32; N]],
    w: &[f32; N],
    indices: &mut [u8; 16],
    stop_above: f32,
) -> f32 {
    let last = palette.len() - 1;
    let dist = |t: &[f32; N], e: &[f32; N]| {
        let mut d = 0.0;
        for c in 0..N {
            let x = e[c] - t[c];
            d += w[c] * x * x;
        }
        d
    };
    let axis: [f32; N] = std::array::from_fn(|c| (palette[last][c] - palette[0][c]) * w[c]);
    let len2: f32 = (0..N)
        .map(|c| axis[c] * (palette[last][c] - palette[0][c]))
        .sum();
    let project = palette.len() > FULL_SEARCH && len2 > 0.0;
    let mut total = 0.0;
    for (k, t) in px.iter().enumerate() {
        let range = if project {
            let along: f32 = (0..N)
                .map(|c| (t[c] - palette[0][c]) * axis[c])
                .sum::<f32>()
                / len2;
            let i = (along * last as f32).round().clamp(0.0, last as f32) as usize;
            i.saturating_sub(1)..=(i + 1).min(last)
        } else {
            0..=last
        };
        let mut best = (f32::MAX, 0u8);
        for i in range {
            let d = dist(t, &palette[i]);
            if d < best.0 {
                best = (d, i as u8);
            }
        }
        indices[k] = best.1;
        total += best.0;
        if total > stop_above {
            return f32::MAX;
        }
    }
    total
}

/// Scores stored codes and p-bits: the best indices and their error.
fn score<const N: usize>(
    px: &[[f32; N]],
    setup: &Setup<N>,
    codes: &[[u8; N]; 2],
    pbits: [u8; 2],
    stop_above: f32,
) -> ([u8; 16], f32) {
    let mut ends = [[0u32; N]; 2];
    for e in 0..2 {
        for c in 0..N {
            ends[e][c] = decoded(u32::from(codes[e][c]), setup.bits[c], setup.pbits, pbits[e]);
        }
    }
    let ws = weights(setup.index_bits);
    let mut palette = [[0f32; N]; 16];
    for (i, &f) in ws.iter().enumerate() {
        for c in 0..N {
            palette[i][c] = interpolate(ends[0][c], ends[1][c], f) as f32;
        }
    }
    let mut indices = [0u8; 16];
    let err = assign(px, &palette[..ws.len()], &setup.w, &mut indices, stop_above);
    (indices, err)
}

/// Quantises float endpoints under the allowed p-bits; the best result.
fn quantise_fit<const N: usize>(
    px: &[[f32; N]],
    setup: &Setup<N>,
    ends: &[[f32; N]; 2],
    effort: &FitEffort,
) -> Fit<N> {
    let choices = pbit_choices(setup.pbits);
    let codes_for = |p: [u8; 2]| {
        let mut codes = [[0u8; N]; 2];
        for e in 0..2 {
            for c in 0..N {
                let v = if setup.w[c] > 0.0 { ends[e][c] } else { 255.0 };
                codes[e][c] = quantise(v, setup.bits[c], setup.pbits, p[e]);
            }
        }
        codes
    };
    let candidates: &[[u8; 2]] = if effort.pbit_search || choices.len() == 1 {
        choices
    } else {
        let closest = choices
            .iter()
            .map(|&p| {
                let codes = codes_for(p);
                let mut d = 0.0;
                for e in 0..2 {
                    for c in 0..N {
                        let q = decoded(u32::from(codes[e][c]), setup.bits[c], setup.pbits, p[e]);
                        let x = q as f32 - if setup.w[c] > 0.0 { ends[e][c] } else { 255.0 };
                        d += setup.w[c] * x * x;
                    }
                }
                (d, p)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or([0, 0], |c| c.1);
        return finish(px, setup, codes_for(closest), closest);
    };
    let mut best: Option<Fit<N>> = None;
    for &p in candidates {
        let codes = codes_for(p);
        let bound = best.map_or(f32::MAX, |b| b.err);
        let (indices, err) = score(px, setup, &codes, p, bound);
        if best.is_none_or(|b| err < b.err) {
            best = Some(Fit {
                codes,
                pbits: p,
                indices,
                err,
            });
        }
    }
    best.unwrap_or_else(|| finish(px, setup, codes_for([0, 0]), [0, 0]))
}

fn finish<const N: usize>(
    px: &[[f32; N]],
    setup: &Setup<N>,
    codes: [[u8; N]; 2],
    pbits: [u8; 2],
) -> Fit<N> {
    let (indices, err) = score(px, setup, &codes, pbits, f32::MAX);
    Fit {
        codes,
        pbits,
        indices,
        err,
    }
}

/// Float endpoints along the weighted principal axis, spanning the texels'
/// projections.
pub fn principal_ends<const N: usize>(px: &[[f32; N]], w: &[f32; N]) -> [[f32; N]; 2] {
    let n = px.len().max(1) as f32;
    let mut mean = [0f32; N];
    for t in px {
        for c in 0..N {
            mean[c] += t[c];
        }
    }
    mean.iter_mut().for_each(|m| *m /= n);
    let sw: [f32; N] = std::array::from_fn(|c| w[c].max(0.0).sqrt());
    let mut cov = [[0f32; N]; N];
    for t in px {
        let d: [f32; N] = std::array::from_fn(|c| (t[c] - mean[c]) * sw[c]);
        for a in 0..N {
            for b in a..N {
                cov[a][b] += d[a] * d[b];
            }
        }
    }
    for a in 0..N {
        for b in 0..a {
            cov[a][b] = cov[b][a];
        }
    }
    let axis = principal_axis(&cov);
    let (mut lo, mut hi) = (f32::MAX, f32::MIN);
    for t in px {
        let p: f32 = (0..N).map(|c| (t[c] - mean[c]) * sw[c] * axis[c]).sum();
        lo = lo.min(p);
        hi = hi.max(p);
    }
    if lo > hi {
        (lo, hi) = (0.0, 0.0);
    }
    let mut ends = [mean; 2];
    for c in 0..N {
        if sw[c] > 0.0 {
            ends[0][c] = (mean[c] + lo * axis[c] / sw[c]).clamp(0.0, 255.0);
            ends[1][c] = (mean[c] + hi * axis[c] / sw[c]).clamp(0.0, 255.0);
        }
    }
    ends
}

/// Power iterations from the covariance's largest column: enough for
/// an endpoint start, which least squares then refines.
fn principal_axis<const N: usize>(cov: &[[f32; N]; N]) -> [f32; N] {
    let start = (0..N)
        .max_by(|&a, &b| cov[a][a].total_cmp(&cov[b][b]))
        .unwrap_or(0);
    let mut v: [f32; N] = std::array::from_fn(|c| cov[c][start]);
    for _ in 0..POWER_ITERATIONS {
        let next: [f32; N] = std::array::from_fn(|a| (0..N).map(|b| cov[a][b] * v[b]).sum());
        let norm = next.iter().map(|x| x * x).sum::<f32>().sqrt();
        if norm < 1e-12 {
            break;
        }
        v = next.map(|x| x / norm);
    }
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if norm < 1e-12 {
        let mut u = [0f32; N];
        u[0] = 1.0;
        u
    } else {
        v.map(|x| x / norm)
    }
}

/// Power iterations per axis. Four leave the axis within a degree for the
/// blocks that matter (a dominant direction); the refits do the rest.
const POWER_ITERATIONS: usize = 4;

/// Float endpoints minimising the squared error for fixed indices, or
/// `None` when every texel takes the same weight.
fn least_squares<const N: usize>(
    px: &[[f32; N]],
    indices: &[u8; 16],
    index_bits: u32,
) -> Option<[[f32; N]; 2]> {
    let ws = weights(index_bits);
    let (mut aa, mut ab, mut bb) = (0f32, 0f32, 0f32);
    let mut ra = [0f32; N];
    let mut rb = [0f32; N];
    for (k, t) in px.iter().enumerate() {
        let f = ws[usize::from(indices[k])] as f32 / 64.0;
        let g = 1.0 - f;
        aa += g * g;
        ab += g * f;
        bb += f * f;
        for c in 0..N {
            ra[c] += g * t[c];
            rb[c] += f * t[c];
        }
    }
    let det = aa * bb - ab * ab;
    if det.abs() < 1e-6 {
        return None;
    }
    let mut ends = [[0f32; N]; 2];
    for c in 0..N {
        ends[0][c] = ((bb * ra[c] - ab * rb[c]) / det).clamp(0.0, 255.0);
        ends[1][c] = ((aa * rb[c] - ab * ra[c]) / det).clamp(0.0, 255.0);
    }
    Some(ends)
}

/// The mean of the texels as both endpoints: a flat subset's start.
fn mean_ends<const N: usize>(px: &[[f32; N]]) -> [[f32; N]; 2] {
    let n = px.len().max(1) as f32;
    let mut mean = [0f32; N];
    for t in px {
        for c in 0..N {
            mean[c] += t[c] / n;
        }
    }
    [mean; 2]
}

/// The best fit found for the texels `px` from the float endpoints `start`.
pub fn fit_from<const N: usize>(
    px: &[[f32; N]],
    setup: &Setup<N>,
    start: &[[f32; N]; 2],
    effort: &FitEffort,
) -> Fit<N> {
    let mut best = quantise_fit(px, setup, start, effort);
    for _ in 0..effort.refine {
        if best.err <= 0.0 {
            break;
        }
        let ends =
            least_squares(px, &best.indices, setup.index_bits).unwrap_or_else(|| mean_ends(px));
        let next = quantise_fit(px, setup, &ends, effort);
        if next.err < best.err {
            best = next;
        } else {
            break;
        }
    }
    if best.err > 0.0 && spread(px, &setup.w) <= SOLID_RANGE {
        let s = solid_fit(px, setup, best.err);
        if s.err < best.err {
            best = s;
        }
    }
    for _ in 0..effort.code_search {
        if best.err <= 0.0 || !search_codes(px, setup, &mut best) {
            break;
        }
    }
    best
}

/// The largest range of a weighted channel over the texels.
fn spread<const N: usize>(px: &[[f32; N]], w: &[f32; N]) -> f32 {
    let mut out = 0f32;
    for c in (0..N).filter(|&c| w[c] > 0.0) {
        let (lo, hi) = px.iter().fold((f32::MAX, f32::MIN), |(lo, hi), t| {
            (lo.min(t[c]), hi.max(t[c]))
        });
        out = out.max(hi - lo);
    }
    out
}

/// The single-colour fit to the texels' mean: per p-bit pair and index
/// weight, the table codes that land nearest the mean in each channel.
fn solid_fit<const N: usize>(px: &[[f32; N]], setup: &Setup<N>, stop_above: f32) -> Fit<N> {
    let n = px.len().max(1) as f32;
    let mean: [usize; N] = std::array::from_fn(|c| {
        if setup.w[c] > 0.0 {
            (px.iter().map(|t| t[c]).sum::<f32>() / n)
                .round()
                .clamp(0.0, 255.0) as usize
        } else {
            255
        }
    });
    let levels = weights(setup.index_bits).len();
    let mut best = (f32::MAX, [[0u8; N]; 2], [0u8; 2]);
    for &p in pbit_choices(setup.pbits) {
        for index in 0..levels {
            let mut err = 0.0;
            let mut codes = [[0u8; N]; 2];
            for c in 0..N {
                let t = solid::table(setup.bits[c], setup.pbits, p, setup.index_bits, index);
                let (q0, q1, e) = t[mean[c]];
                codes[0][c] = q0;
                codes[1][c] = q1;
                err += setup.w[c] * f32::from(e) * f32::from(e);
            }
            if err < best.0 {
                best = (err, codes, p);
            }
        }
    }
    let (indices, err) = score(px, setup, &best.1, best.2, stop_above);
    Fit {
        codes: best.1,
        pbits: best.2,
        indices,
        err,
    }
}

/// The best fit found for the texels `px`.
pub fn fit<const N: usize>(px: &[[f32; N]], setup: &Setup<N>, effort: &FitEffort) -> Fit<N> {
    let start = principal_ends(px, &setup.w);
    fit_from(px, setup, &start, effort)
}

/// One round of ±1 moves on each stored code (and of flipping each p-bit),
/// keeping those that lower the error. True when one did.
fn search_codes<const N: usize>(px: &[[f32; N]], setup: &Setup<N>, best: &mut Fit<N>) -> bool {
    let mut improved = false;
    for e in 0..2 {
        for c in 0..N {
            if setup.w[c] <= 0.0 {
                continue;
            }
            let max = (1i32 << setup.bits[c]) - 1;
            for step in [-1i32, 1] {
                let q = i32::from(best.codes[e][c]) + step;
                if !(0..=max).contains(&q) {
                    continue;
                }
                let mut codes = best.codes;
                codes[e][c] = q as u8;
                let (indices, err) = score(px, setup, &codes, best.pbits, best.err);
                if err < best.err {
                    *best = Fit {
                        codes,
                        pbits: best.pbits,
                        indices,
                        err,
                    };
                    improved = true;
                }
            }
        }
    }
    improved
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantise_picks_the_nearest_decode() {
        // Every layout a mode has: p-bits only below 8 stored bits.
        for bits in 4..=8 {
            for pb in [PBits::None, PBits::Unique] {
                if bits == 8 && pb != PBits::None {
                    continue;
                }
                for p in 0..=u8::from(pb != PBits::None) {
                    for v in 0..=255 {
                        let q = quantise(v as f32, bits, pb, p);
                        let d = (decoded(u32::from(q), bits, pb, p) as i32 - v).abs();
                        let max = (1 << bits) - 1;
                        for other in 0..=max {
                            let o = (decoded(other, bits, pb, p) as i32 - v).abs();
                            assert!(d <= o, "{bits} {pb:?} {p} {v}: {q} vs {other}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn two_colours_fit_exactly_when_representable() {
        let setup = Setup::<3> {
            bits: [7, 7, 7],
            pbits: PBits::None,
            index_bits: 2,
            w: [1.0; 3],
        };
        let a = [
            expand(10, 7) as f32,
            expand(100, 7) as f32,
            expand(3, 7) as f32,
        ];
        let b = [
            expand(90, 7) as f32,
            expand(20, 7) as f32,
            expand(127, 7) as f32,
        ];
        let px: Vec<[f32; 3]> = (0..16).map(|k| if k % 3 == 0 { a } else { b }).collect();
        let effort = FitEffort {
            refine: 2,
            pbit_search: true,
            code_search: 0,
        };
        assert_eq!(fit(&px, &setup, &effort).err, 0.0);
    }
}
