//! UV charts: the connected pieces of an atlas.
//!
//! Triangles that share a UV edge (the same two UV points, whichever mesh
//! they come from) belong to one chart; a seam is where one 3D edge lands
//! in two charts, or twice in one. Each inside texel is labelled with a
//! chart that covers it, so that a seam side's colour can be read as its own
//! chart paints it, without the gutter between charts.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU32, Ordering};

use rayon::prelude::*;

use super::grid::TexelGrid;
use super::metric::{in_chunks, TEXELS_PER_TASK};
use super::quadrature::{for_each_cell, Segment};
use super::texels::for_each_texel_inside;
use crate::model::{SeamEdge, UvTriangle};

/// UVs are compared after rounding to this many steps per unit: far finer
/// than any texel, coarse enough that the same vertex written twice (by two
/// primitives, or after a texture transform) joins.
const UV_STEPS: f64 = (1u64 << 20) as f64;

/// The charts of the triangles that sample one texture.
#[derive(Clone, Debug)]
pub struct Charts {
    /// Chart of each triangle, numbered `0..count` in order of first appearance.
    pub of_triangle: Vec<u32>,
    /// Chart of each texel, [`Charts::NONE`] where no triangle covers it. Where
    /// charts overlap (mirrored halves sharing UVs), the last triangle wins.
    pub of_texel: Vec<u32>,
    pub count: usize,
}

/// The chart of each triangle: which triangles share UV edges, whatever the
/// texture's size. Found once per texture and read by every mip level (a
/// hash of every UV edge: 14 000 triangles take a few milliseconds, a
/// dozen times over down a mip chain that waits for each).
#[derive(Clone, Debug, Default)]
pub struct ChartLabels {
    /// Chart of each triangle, numbered `0..count` in order of first appearance.
    of_triangle: Vec<u32>,
    count: usize,
}

impl ChartLabels {
    pub fn new(triangles: &[UvTriangle]) -> Self {
        let mut parent: Vec<u32> = (0..triangles.len() as u32).collect();
        let mut first_with_edge: HashMap<[[i64; 2]; 2], u32> = HashMap::new();
        for (ti, t) in triangles.iter().enumerate() {
            let q = t.uvs.map(|uv| uv.map(|x| (x * UV_STEPS).round() as i64));
            for k in 0..3 {
                let (p, r) = (q[k], q[(k + 1) % 3]);
                let key = if p <= r { [p, r] } else { [r, p] };
                match first_with_edge.get(&key) {
                    Some(&other) => union(&mut parent, ti as u32, other),
                    None => {
                        first_with_edge.insert(key, ti as u32);
                    }
                }
            }
        }
        let mut number: HashMap<u32, u32> = HashMap::new();
        let of_triangle: Vec<u32> = (0..triangles.len() as u32)
            .map(|t| {
                let root = find(&mut parent, t);
                let next = number.len() as u32;
                *number.entry(root).or_insert(next)
            })
            .collect();
        ChartLabels {
            of_triangle,
            count: number.len(),
        }
    }
}

impl Charts {
    pub const NONE: u32 = u32::MAX;

    pub fn new(grid: &TexelGrid, triangles: &[UvTriangle]) -> Self {
        Self::labelled(grid, triangles, &ChartLabels::new(triangles))
    }

    /// The charts of `labels`, found for `triangles`, on `grid`'s texels.
    pub fn labelled(grid: &TexelGrid, triangles: &[UvTriangle], labels: &ChartLabels) -> Self {
        let of_triangle = labels.of_triangle.clone();
        // Where triangles overlap the last one wins, that is the highest
        // numbered: rasterised side by side, each texel keeps the largest
        // number that reaches it, whatever order they land in.
        let last: Vec<AtomicU32> = (0..grid.len())
            .into_par_iter()
            .map(|_| AtomicU32::new(0))
            .collect();
        triangles.par_iter().enumerate().for_each(|(t, tri)| {
            for_each_texel_inside(grid, tri, |i| {
                last[i as usize].fetch_max(t as u32 + 1, Ordering::Relaxed);
            })
        });
        let of_texel = last
            .into_par_iter()
            .map(|t| match t.into_inner() {
                0 => Self::NONE,
                t => of_triangle[t as usize - 1],
            })
            .collect();
        Charts {
            of_triangle,
            of_texel,
            count: labels.count,
        }
    }

    /// Whether each texel's centre lies in a triangle (the inside texels of
    /// [`TexelClasses`](super::texels::TexelClasses)).
    pub fn inside(&self) -> Vec<bool> {
        self.of_texel.par_iter().map(|&c| c != Self::NONE).collect()
    }

    /// The chart of texel `i`, if any triangle covers it.
    #[inline]
    pub fn texel(&self, i: u32) -> Option<u32> {
        let c = self.of_texel[i as usize];
        (c != Self::NONE).then_some(c)
    }

    /// The charts closing `edge` can change directly: those of its two
    /// sides, and those of every texel the bilinear samples along either
    /// half-edge read (a sliver chart under a seam's footprint is repainted
    /// by the seam without being one of its sides). Sorted, without repeats.
    pub fn touched_by(&self, grid: &TexelGrid, edge: &SeamEdge) -> Vec<u32> {
        let mut out: Vec<u32> = edge
            .triangles
            .iter()
            .filter_map(|&t| self.of_triangle.get(t as usize).copied())
            .collect();
        for half in [edge.a, edge.b] {
            for_each_cell(Segment::from_uv(grid, half), |[cx, cy]| {
                out.extend(
                    grid.cell_corners(cx, cy)
                        .iter()
                        .filter_map(|&i| self.texel(i)),
                );
            });
        }
        out.sort_unstable();
        out.dedup();
        out
    }

    /// Texels and UV bounds (`[min, max]` of the triangles' UVs) of every chart.
    pub fn extents(&self, triangles: &[UvTriangle]) -> Vec<ChartExtent> {
        let mut out = vec![
            ChartExtent {
                texels: 0,
                uv_min: [f64::INFINITY; 2],
                uv_max: [f64::NEG_INFINITY; 2],
            };
            self.count
        ];
        for (t, &c) in triangles.iter().zip(&self.of_triangle) {
            let e = &mut out[c as usize];
            for uv in t.uvs {
                e.uv_min = [e.uv_min[0].min(uv[0]), e.uv_min[1].min(uv[1])];
                e.uv_max = [e.uv_max[0].max(uv[0]), e.uv_max[1].max(uv[1])];
            }
        }
        for &c in self.of_texel.iter().filter(|&&c| c != Self::NONE) {
            out[c as usize].texels += 1;
        }
        out
    }
}

/// Where a chart lies: enough to find it in the atlas.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChartExtent {
    pub texels: usize,
    pub uv_min: [f64; 2],
    pub uv_max: [f64; 2],
}

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let up = parent[parent[i as usize] as usize];
        parent[i as usize] = up;
        i = up;
    }
    i
}

fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    // The smaller root stays, so the partition does not depend on the order
    // in which edges are met.
    if ra != rb {
        let (lo, hi) = (ra.min(rb), ra.max(rb));
        parent[hi as usize] = lo;
    }
}

/// Per-chart PSNR of `image` against `reference` over each chart's texels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChartFidelity {
    /// Charts large enough to judge (at least [`MIN_CHART_TEXELS`]).
    pub charts: usize,
    /// The lowest PSNR among them, in dB; `None` when none changed.
    pub worst_psnr: Option<f64>,
    /// How many fall under [`HARM_PSNR_DB`].
    pub under_threshold: usize,
}

/// Charts with fewer texels are too small to judge by PSNR: a sliver of a
/// few texels along a seam always changes, and is not art anyone sees.
pub const MIN_CHART_TEXELS: usize = 64;

/// Below this PSNR a chart has visibly been repainted: BC1 alone keeps
/// charts of real art above it (35–45 dB), and closing seams whose sides
/// agree costs a few dB at most.
pub const HARM_PSNR_DB: f64 = 30.0;

/// Which charts per-chart PSNRs (as [`Charts::psnr_per_chart`] gives them)
/// put under [`HARM_PSNR_DB`].
pub fn harmed(psnr: &[Option<f64>]) -> Vec<bool> {
    psnr.iter()
        .map(|p| p.is_some_and(|p| p < HARM_PSNR_DB))
        .collect()
}

impl Charts {
    /// PSNR (dB) of each chart over the first `compared` channels against
    /// `reference`: `None` for charts under [`MIN_CHART_TEXELS`], infinite
    /// for charts that did not change.
    pub fn psnr_per_chart(
        &self,
        image: &[f32],
        reference: &[f32],
        channels: usize,
        compared: usize,
    ) -> Vec<Option<f64>> {
        self.squared_errors(image, reference, channels, compared)
            .psnr()
    }

    /// What [`Charts::psnr_per_chart`] is made of.
    pub fn squared_errors(
        &self,
        image: &[f32],
        reference: &[f32],
        channels: usize,
        compared: usize,
    ) -> ChartSse {
        let parts = in_chunks(self.of_texel.len(), TEXELS_PER_TASK, |range| {
            let mut sum = vec![0.0f64; self.count];
            let mut texels = vec![0usize; self.count];
            for t in range {
                let c = self.of_texel[t];
                if c == Self::NONE {
                    continue;
                }
                for k in 0..compared {
                    let d =
                        f64::from(image[t * channels + k]) - f64::from(reference[t * channels + k]);
                    sum[c as usize] += d * d;
                }
                texels[c as usize] += 1;
            }
            (sum, texels)
        });
        let mut out = ChartSse {
            sum: vec![0.0f64; self.count],
            texels: vec![0usize; self.count],
            compared,
        };
        for (ps, pn) in parts {
            for c in 0..self.count {
                out.sum[c] += ps[c];
                out.texels[c] += pn[c];
            }
        }
        out
    }

    /// How much each chart was changed, summed up, so that one repainted
    /// chart is not averaged away.
    pub fn fidelity(
        &self,
        image: &[f32],
        reference: &[f32],
        channels: usize,
        compared: usize,
    ) -> ChartFidelity {
        self.squared_errors(image, reference, channels, compared)
            .fidelity()
    }
}

/// Per chart, squared differences summed over its texels, and its texel
/// count: kept so that the figures can be corrected where a few texels
/// change.
#[derive(Clone, Debug)]
pub struct ChartSse {
    pub sum: Vec<f64>,
    pub texels: Vec<usize>,
    /// Channels summed per texel.
    pub compared: usize,
}

impl ChartSse {
    /// As [`Charts::psnr_per_chart`].
    pub fn psnr(&self) -> Vec<Option<f64>> {
        self.sum
            .iter()
            .zip(&self.texels)
            .map(|(s, n)| {
                (*n >= MIN_CHART_TEXELS).then(|| 10.0 * ((n * self.compared) as f64 / s).log10())
            })
            .collect()
    }

    /// As [`Charts::fidelity`].
    pub fn fidelity(&self) -> ChartFidelity {
        let judged: Vec<f64> = self.psnr().into_iter().flatten().collect();
        let changed = judged.iter().copied().filter(|p| p.is_finite());
        ChartFidelity {
            charts: judged.len(),
            worst_psnr: changed.clone().reduce(f64::min),
            under_threshold: changed.filter(|p| *p < HARM_PSNR_DB).count(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Wrap;

    fn tri(uvs: [[f64; 2]; 3]) -> UvTriangle {
        UvTriangle {
            group: 0,
            positions: [[0.0; 3]; 3],
            uvs,
        }
    }

    #[test]
    fn triangles_sharing_a_uv_edge_form_one_chart() {
        let grid = TexelGrid {
            width: 16,
            height: 16,
            wrap_s: Wrap::ClampToEdge,
            wrap_t: Wrap::ClampToEdge,
        };
        let t = [
            tri([[0.0, 0.0], [0.4, 0.0], [0.0, 0.4]]),
            tri([[0.6, 0.6], [1.0, 0.6], [0.6, 1.0]]),
            tri([[0.4, 0.0], [0.4, 0.4], [0.0, 0.4]]),
        ];
        let c = Charts::new(&grid, &t);
        assert_eq!(c.count, 2);
        assert_eq!(c.of_triangle, vec![0, 1, 0]);
        assert_eq!(c.texel(grid.index(2, 2)), Some(0));
        assert_eq!(c.texel(grid.index(12, 12)), Some(1));
        assert_eq!(c.texel(grid.index(15, 0)), None);
    }
}
