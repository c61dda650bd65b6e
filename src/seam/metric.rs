//! The seam discontinuity metric (SPEC §3) and inside-texel PSNR.

use rayon::prelude::*;

use super::grid::TexelGrid;
use super::quadrature::{seam_difference_points, QuadPoint, Segment};
use crate::model::SeamSet;

/// Dtotal as a sum of weighted squared texel functionals, built once per
/// texture size and seam set and then evaluated on any number of images.
#[derive(Clone, Debug)]
pub struct SeamMetric {
    /// Weights include l/L, so Σ weight·(Σ taps·p)² is Dtotal for one channel.
    pub points: Vec<QuadPoint>,
}

impl SeamMetric {
    pub fn new(grid: &TexelGrid, seams: &SeamSet) -> Self {
        let total = seams.total_length();
        let mut points = Vec::new();
        if total > 0.0 {
            for s in &seams.seams {
                let e1 = Segment::from_uv(grid, s.a);
                let e2 = Segment::from_uv(grid, s.b);
                seam_difference_points(grid, e1, e2, s.length / total, &mut points);
            }
        }
        SeamMetric { points }
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Dtotal summed over the first `compared` channels of interleaved `data`.
    pub fn dtotal(&self, data: &[f32], channels: usize, compared: usize) -> f64 {
        self.dtotal_with(compared, |t, c| data[t * channels + c])
    }

    /// Dtotal of the image whose channel `c` at texel `t` is `value(t, c)`.
    pub fn dtotal_with(&self, compared: usize, value: impl Fn(usize, usize) -> f32 + Sync) -> f64 {
        in_chunks(self.points.len(), POINTS_PER_TASK, |range| {
            self.points[range]
                .iter()
                .map(|q| {
                    (0..compared)
                        .map(|c| {
                            let v: f64 = q
                                .taps
                                .iter()
                                .map(|&(t, w)| w * f64::from(value(t as usize, c)))
                                .sum();
                            q.weight * v.powi(2)
                        })
                        .sum::<f64>()
                })
                .sum::<f64>()
        })
        .into_iter()
        .sum()
    }

    /// Length-weighted RMS difference across the seams, in 8-bit levels;
    /// `None` when there are no seams to measure.
    pub fn seam_rms(&self, data: &[f32], channels: usize, compared: usize) -> Option<f64> {
        self.seam_rms_with(compared, |t, c| data[t * channels + c])
    }

    /// [`SeamMetric::seam_rms`] of the image `value(t, c)`.
    pub fn seam_rms_with(
        &self,
        compared: usize,
        value: impl Fn(usize, usize) -> f32 + Sync,
    ) -> Option<f64> {
        if self.is_empty() {
            return None;
        }
        let d = self.dtotal_with(compared, value);
        Some(255.0 * (d.max(0.0) / compared as f64).sqrt())
    }
}

/// Channels that carry colour (alpha is processed but never compared).
pub fn colour_channels(channels: usize) -> usize {
    match channels {
        1 | 2 => 1,
        _ => 3,
    }
}

/// PSNR in dB over the texels where `mask` is set, first `compared` channels,
/// against `reference`; `None` when the two agree exactly there (or nothing is inside).
pub fn psnr(
    image: &[f32],
    reference: &[f32],
    channels: usize,
    compared: usize,
    mask: &[bool],
) -> Option<f64> {
    squared_error(image, reference, channels, compared, mask).psnr()
}

/// Squared differences summed over some values of an image, and how many:
/// what a PSNR is made of, kept so that it can be corrected where a few
/// texels change.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sse {
    pub sum: f64,
    pub values: usize,
}

impl Sse {
    /// In dB (values in \[0, 1\]); `None` for no values or no difference.
    pub fn psnr(self) -> Option<f64> {
        (self.values > 0 && self.sum != 0.0).then(|| 10.0 * (self.values as f64 / self.sum).log10())
    }
}

/// The [`Sse`] behind [`psnr`].
pub fn squared_error(
    image: &[f32],
    reference: &[f32],
    channels: usize,
    compared: usize,
    mask: &[bool],
) -> Sse {
    let parts = in_chunks(mask.len(), TEXELS_PER_TASK, |range| {
        let mut sum = 0.0;
        let mut n = 0usize;
        for t in range.filter(|&t| mask[t]) {
            for c in 0..compared {
                let d = f64::from(image[t * channels + c]) - f64::from(reference[t * channels + c]);
                sum += d * d;
            }
            n += compared;
        }
        (sum, n)
    });
    let (sum, values) = parts
        .into_iter()
        .fold((0.0, 0), |(s, n), (ps, pn)| (s + ps, n + pn));
    Sse { sum, values }
}

/// Texels per parallel task of the image-wide sums.
pub(crate) const TEXELS_PER_TASK: usize = 1 << 16;
/// Seam points per parallel task of [`SeamMetric::dtotal`].
const POINTS_PER_TASK: usize = 1 << 12;

/// `part` of each run of `chunk` indices below `n`, in order. The runs are
/// fixed by `n` and `chunk` alone, and their results are combined by the
/// caller in order, so the sums do not depend on the thread count.
pub(crate) fn in_chunks<T: Send>(
    n: usize,
    chunk: usize,
    part: impl Fn(std::ops::Range<usize>) -> T + Sync,
) -> Vec<T> {
    (0..n.div_ceil(chunk))
        .into_par_iter()
        .map(|i| part(i * chunk..((i + 1) * chunk).min(n)))
        .collect()
}

/// The seam differences at the Gauss points of every seam, weighted by the
/// seam's length in texels (the mean of its two half-edges): Σ weight·(Σ
/// taps·p)² is then ∫|B₁ − B₂|² ds over the seams, in texel-length units.
pub fn seam_points_texel_length(grid: &TexelGrid, seams: &SeamSet) -> Vec<QuadPoint> {
    let mut points = Vec::new();
    for s in &seams.seams {
        let e1 = Segment::from_uv(grid, s.a);
        let e2 = Segment::from_uv(grid, s.b);
        let len = 0.5 * (e1.length() + e2.length());
        seam_difference_points(grid, e1, e2, len, &mut points);
    }
    points
}
