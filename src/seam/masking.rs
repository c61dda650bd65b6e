//! Least-squares seam masking (seeds 000/003): the sampled baseline.
//!
//! Each seam is sampled every ≤ 0.1 texel; the energy is E_c + α·E_s with
//! E_s the length-weighted squared difference of the two sides at the sample
//! points (texel-length units) and E_c the squared change of the texels the
//! samples read. Texels outside the UV charts carry no reliable colour, so
//! they are tied only weakly, to a guess dilated from the nearest inside texels.

use std::collections::VecDeque;

use super::grid::TexelGrid;
use super::quadrature::{difference_taps, Segment};
use super::system::{SolveError, SpdSystem};
use super::texels::TexelClasses;
use crate::model::SeamSet;

/// Longest step between seam samples, in texels.
const SAMPLE_STEP: f64 = 0.1;
/// Weight of an outside texel's tie to its dilated guess, relative to an inside texel's.
const OUTSIDE_WEIGHT: f64 = 1e-3;

#[derive(Clone, Copy, Debug)]
pub struct MaskingOptions {
    /// α: seam agreement against colour change.
    pub alpha: f64,
}

impl Default for MaskingOptions {
    fn default() -> Self {
        MaskingOptions { alpha: 2.0 }
    }
}

/// Masks the seams of `input` (interleaved, `channels` per texel).
pub fn mask(
    grid: &TexelGrid,
    input: &[f32],
    channels: usize,
    seams: &SeamSet,
    classes: &TexelClasses,
    opts: &MaskingOptions,
) -> Result<Vec<f32>, SolveError> {
    let mut unknown = vec![u32::MAX; grid.len()];
    let mut n = 0u32;
    for (t, _) in classes.seam.iter().enumerate().filter(|(_, s)| **s) {
        unknown[t] = n;
        n += 1;
    }
    if n == 0 {
        return Ok(input.to_vec());
    }
    let guess = dilate(grid, input, channels, &classes.inside);
    let mut sys = SpdSystem::new(&unknown, n as usize, channels);
    let zero = [0.0f64; 4];
    for s in &seams.seams {
        let e1 = Segment::from_uv(grid, s.a);
        let e2 = Segment::from_uv(grid, s.b);
        let len = 0.5 * (e1.length() + e2.length());
        let count = ((len / SAMPLE_STEP).ceil() as usize).max(1);
        let weight = opts.alpha * len / count as f64;
        for k in 0..count {
            let g = (k as f64 + 0.5) / count as f64;
            let (p1, p2) = (e1.at(g), e2.at(g));
            let a = grid.bilinear_taps([p1[0].floor() as i64, p1[1].floor() as i64], p1);
            let b = grid.bilinear_taps([p2[0].floor() as i64, p2[1].floor() as i64], p2);
            sys.add_square(weight, &difference_taps(a, b), &zero, input);
        }
    }
    for (t, _) in classes.seam.iter().enumerate().filter(|(_, s)| **s) {
        let (w, target) = if classes.inside[t] {
            (1.0, &input[t * channels..(t + 1) * channels])
        } else {
            (OUTSIDE_WEIGHT, &guess[t * channels..(t + 1) * channels])
        };
        let target: Vec<f64> = target.iter().map(|&v| f64::from(v)).collect();
        sys.add_anchor(w, t as u32, &target);
    }
    let x = sys.solve()?;
    let mut out = input.to_vec();
    for (t, &u) in unknown.iter().enumerate() {
        if u != u32::MAX {
            for c in 0..channels {
                out[t * channels + c] = x[u as usize * channels + c] as f32;
            }
        }
    }
    Ok(out)
}

/// Fills texels outside `known` with the mean of their already-filled
/// 4-neighbours, growing outwards from the known texels (breadth first).
pub fn dilate(grid: &TexelGrid, input: &[f32], channels: usize, known: &[bool]) -> Vec<f32> {
    let (w, h) = (grid.width, grid.height);
    let mut out = input.to_vec();
    let mut filled = known.to_vec();
    let mut queue: VecDeque<usize> = VecDeque::new();
    let neighbours = |i: usize| {
        let (x, y) = (i % w, i / w);
        [
            (x > 0).then(|| i - 1),
            (x + 1 < w).then(|| i + 1),
            (y > 0).then(|| i - w),
            (y + 1 < h).then(|| i + w),
        ]
    };
    for (i, _) in known.iter().enumerate().filter(|(_, k)| **k) {
        for j in neighbours(i).into_iter().flatten() {
            if !known[j] {
                queue.push_back(j);
            }
        }
    }
    while let Some(i) = queue.pop_front() {
        if filled[i] {
            continue;
        }
        let mut sum = [0.0f32; 4];
        let mut count = 0.0f32;
        for j in neighbours(i).into_iter().flatten() {
            if filled[j] {
                for c in 0..channels {
                    sum[c] += out[j * channels + c];
                }
                count += 1.0;
            } else {
                queue.push_back(j);
            }
        }
        for c in 0..channels {
            out[i * channels + c] = sum[c] / count;
        }
        filled[i] = true;
    }
    out
}
