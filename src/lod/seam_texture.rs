//! The seam test made on the texture itself: whether a chord that would
//! replace a stretch of seam keeps that seam as closed as it was.
//!
//! Liu et al. ("Seamless", ACM TOG 36(6), 2017, §5.1) state the criterion
//! as the seam discontinuity D staying identically zero after a collapse,
//! and give exact collinearity with equal length ratios as the geometric
//! condition for it on any texture. On a curved seam nothing passes that
//! condition, yet the erased texture is often smooth enough beside the
//! seam that a chord a few tenths of a texel off it samples the same
//! colours on both sides: D is measured here on the chord, on the erased
//! texture and on the DDS the job wrote, against the stretch of seam it
//! replaces. A chord passes when its mean squared difference between the
//! sides exceeds the stretch's (length-weighted) by no more than an
//! allowance set from the bound each level must keep (see
//! [`Allowance`]); then the level's seam RMS, a length-weighted mean of
//! those, rises by no more than the bound however many chords it has.

use crate::model::load::Sampling;
use crate::seam::grid::TexelGrid;
use crate::seam::quadrature::{seam_difference_points, QuadPoint, Segment};

use super::closed::ClosedSeams;
use super::seam_constraints::ChordJudge;
use super::simplify::Mesh;

/// One image a chord must keep closed: the erased texture, or the DDS's
/// level 0 decoded.
pub struct JudgedImage<'a> {
    pub data: &'a [f32],
    pub channels: usize,
    /// Colour channels compared (alpha is not).
    pub compared: usize,
    pub allowance: Allowance,
}

/// How much a level's mean squared difference across the seams (in
/// \[0, 1\] units, averaged over the compared channels) may exceed the full
/// mesh's: `(rms + margin)² − rms²` for the full mesh's seam RMS and the
/// margin a level may add, over the closed seams and over every seam.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Allowance {
    pub closed: f64,
    pub all: f64,
}

impl Allowance {
    /// From the full mesh's seam RMS (8-bit levels) over the closed seams
    /// and over every seam, and the margin a level may add to each.
    pub fn new(rms_closed: Option<f64>, rms_all: Option<f64>, margin: f64) -> Allowance {
        let of = |rms: Option<f64>| {
            let r = rms.unwrap_or(0.0) / 255.0;
            let m = margin / 255.0;
            (r + m) * (r + m) - r * r
        };
        Allowance {
            closed: of(rms_closed),
            all: of(rms_all),
        }
    }
}

/// One texture a primitive samples.
pub struct SampledTexture<'a> {
    pub grid: TexelGrid,
    pub sampling: Sampling,
    pub images: Vec<JudgedImage<'a>>,
    /// The full mesh's seams of this texture with their verdicts.
    pub closed: &'a ClosedSeams,
}

/// Every texture one primitive samples.
pub struct TextureJudge<'a> {
    pub textures: Vec<SampledTexture<'a>>,
}

fn mean_square(
    grid: &TexelGrid,
    image: &JudgedImage<'_>,
    a: [[f64; 2]; 2],
    b: [[f64; 2]; 2],
    points: &mut Vec<QuadPoint>,
) -> f64 {
    points.clear();
    seam_difference_points(
        grid,
        Segment::from_uv(grid, a),
        Segment::from_uv(grid, b),
        1.0,
        points,
    );
    let sum: f64 = points
        .iter()
        .map(|q| {
            (0..image.compared)
                .map(|c| q.weight * q.apply(image.data, image.channels, c).powi(2))
                .sum::<f64>()
        })
        .sum();
    sum / image.compared.max(1) as f64
}

fn distance(p: [f32; 3], q: [f32; 3]) -> f64 {
    let d = [0, 1, 2].map(|k| f64::from(p[k]) - f64::from(q[k]));
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

impl TextureJudge<'_> {
    fn slots(&self) -> usize {
        2 * self.textures.iter().map(|t| t.images.len()).sum::<usize>()
    }
}

impl ChordJudge for TextureJudge<'_> {
    fn allowances(&self) -> Vec<f64> {
        self.textures
            .iter()
            .flat_map(|t| &t.images)
            .flat_map(|image| [image.allowance.closed, image.allowance.all])
            .collect()
    }

    fn terms(&self, mesh: &Mesh<'_>, sides: [&[u32]; 2]) -> Option<Vec<[f64; 2]>> {
        let last = sides[0].len() - 1;
        let mut out = vec![[0.0; 2]; self.slots()];
        let mut slot = 0;
        let mut points = Vec::new();
        for t in &self.textures {
            let first_slot = slot;
            slot += 2 * t.images.len();
            let Some(set) = mesh.uv_sets.get(t.sampling.set as usize) else {
                continue;
            };
            let uv = |s: usize, k: usize| t.sampling.uv(set[sides[s][k] as usize]);
            if (0..=last).all(|k| uv(0, k) == uv(1, k)) {
                // Continuous in the set this texture reads.
                continue;
            }
            let edge = |s: usize, k: usize| [uv(s, k), uv(s, k + 1)];
            // Unknown edges count as closed, as the levels measure them.
            let verdicts: Vec<bool> = (0..last)
                .map(|k| t.closed.edge_closed(edge(0, k), edge(1, k)) != Some(false))
                .collect();
            let closed = verdicts[0];
            if verdicts.iter().any(|&v| v != closed) {
                // A chord over both would hide closed seams among left ones.
                return None;
            }
            let p = |k: usize| mesh.positions[sides[0][k] as usize];
            let length = distance(p(0), p(last));
            let chord = |s: usize| [uv(s, 0), uv(s, last)];
            for (k, image) in t.images.iter().enumerate() {
                let term = length * mean_square(&t.grid, image, chord(0), chord(1), &mut points);
                let at = first_slot + 2 * k;
                if closed {
                    out[at] = [term, length];
                }
                out[at + 1] = [term, length];
            }
        }
        Some(out)
    }
}
