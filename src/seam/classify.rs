//! Which seams to close: sides that should agree, or sides painted apart.
//!
//! Seam erasure assumes that the two sides of a seam roughly match and only
//! disagree through a bake or parameterisation error ("What are we not
//! trying to fix", seed 003). Hand-painted atlases also cut charts along
//! panel edges and material boundaries, where the change of colour *is* the
//! art; forcing those sides to agree repaints the charts around them (a
//! helmet's dark panels get white frames painted in), and the bilinear line
//! such a seam shows is invisible beside the colour change anyway.
//!
//! Each seam edge is judged by its *jump*: the RMS difference, in 8-bit
//! levels, between the colours its two sides' own charts paint along it.
//! A side's colour at a point is the bilinear sample with the taps that fall
//! outside its chart dropped and the rest reweighted (failing any, the
//! nearest texel of the chart within `NEAREST_RADIUS`). Gutter texels never
//! count: an atlas with a black gutter shows 40–60-level jumps in its raw
//! bilinear samples, and its seams must still close.
//!
//! The rule has three zones. Edges whose jump is within `ALWAYS_CLOSE`
//! (16 levels) are closed: their sides are meant to agree. Edges beyond the
//! tolerance (`DEFAULT_TOLERANCE`, 48 levels, `--seam-tolerance`) are left
//! as painted. Between the two, an edge is closed unless closing it repaints
//! a chart on either side: after the erasure, every chart whose PSNR fell
//! under [`HARM_PSNR_DB`](super::charts::HARM_PSNR_DB) has its edges of this
//! middle zone left (*spared*), and the erasure runs again
//! ([`SeamVerdicts::spare`]). Should a chart still be repainted, every
//! closed edge that touches it, by a side or by its bilinear footprint, is
//! left as a last resort, the agreeing zone's included, and the erasure
//! runs once more ([`SeamVerdicts::spare_touching`]): a chart shifted by
//! eight levels or more costs more than the seam line it would close. What
//! is still repainted after that is reported, chart by chart, with its
//! cause. A jump alone cannot tell a gradient painted
//! twice out of register (the cube example: 18–46 levels along one chart,
//! all accidental) from a panel painted beside a frame (hand-painted
//! vehicles and controllers: 16–48 levels, all on purpose); what closing
//! would cost the charts can.
//!
//! In `global` mode the mean difference between each pair of charts is taken
//! out first: a chart-wide colour offset is what global mode exists to
//! spread over the charts, so only what varies along the seams beyond it
//! can mark them as painted apart.

use super::charts::Charts;
use super::grid::TexelGrid;
use super::quadrature::Segment;
use crate::model::SeamSet;

/// Edges whose sides differ by at most this (8-bit levels, RMS along the
/// edge) are always closed. The contract's bound: on the shared models the
/// seams meant to agree sit below it (blub and WaterBottle entirely, Fox's
/// fur 90% of its seam length, CesiumMan's body 80%).
pub const ALWAYS_CLOSE: f64 = 16.0;

/// Edges whose sides differ by more than this are left as painted. The
/// contract's bound: the charts painted apart on the shared models jump
/// 70–190 levels (Fox's chart painted another colour, CesiumMan's logo disc,
/// the Duck's eyes); between [`ALWAYS_CLOSE`] and this, what closing costs
/// the charts decides.
pub const DEFAULT_TOLERANCE: f64 = 48.0;

/// Samples along an edge, per texel of its longer half-edge: four per texel
/// see every texel the edge's bilinear footprint covers.
const SAMPLES_PER_TEXEL: f64 = 4.0;

/// At most this many samples judge one edge, however long: an edge spanning
/// thousands of texels is judged as well by an even spread of this many.
const MAX_SAMPLES: usize = 4096;

/// How far (texels, each axis) a side's colour may be looked up when none of
/// its bilinear taps lies in its chart (a sliver chart thinner than a texel).
const NEAREST_RADIUS: i64 = 3;

/// How seams are judged.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClassifyOptions {
    /// Edges whose jump is at most this many 8-bit levels are closed.
    pub tolerance: f64,
    /// Take out each chart pair's mean difference before judging (global mode).
    pub remove_chart_offsets: bool,
}

/// The verdict on every seam edge, in the order of [`SeamSet::seams`].
#[derive(Clone, Debug, PartialEq)]
pub struct SeamVerdicts {
    /// The jump each edge was judged by, in 8-bit levels.
    pub jump: Vec<f64>,
    /// True for the edges to close; false for those painted apart.
    pub closed: Vec<bool>,
    /// Edges of the middle zone left because closing them repainted a chart.
    pub spared: usize,
}

impl SeamVerdicts {
    /// Every edge closed: the behaviour before seams were judged (`--erase-all`).
    pub fn all_closed(seams: &SeamSet) -> Self {
        SeamVerdicts {
            jump: vec![0.0; seams.seams.len()],
            closed: vec![true; seams.seams.len()],
            spared: 0,
        }
    }

    /// Leaves the closed edges of the middle zone (jump above
    /// [`ALWAYS_CLOSE`]) that have a side in a chart marked in `harmed`.
    /// Returns how many it left.
    pub fn spare(&mut self, seams: &SeamSet, charts: &Charts, harmed: &[bool]) -> usize {
        let mut spared = 0;
        for ((s, closed), jump) in seams.seams.iter().zip(&mut self.closed).zip(&self.jump) {
            let hurt = s.triangles.iter().any(|&t| {
                let chart = charts.of_triangle.get(t as usize).copied();
                chart.is_some_and(|c| harmed.get(c as usize).copied().unwrap_or(false))
            });
            if *closed && *jump > ALWAYS_CLOSE && hurt {
                *closed = false;
                spared += 1;
            }
        }
        self.spared += spared;
        spared
    }

    /// The last resort for a chart that sparing the middle zone left
    /// repainted: leaves every closed edge, whatever its jump, whose sides
    /// or bilinear footprint touch a chart marked in `harmed`. Sides that
    /// agree to within [`ALWAYS_CLOSE`] are closed by contract, but not at
    /// the price of a chart: a seam line of a few levels is what the
    /// erasure removes, a chart shifted by eight or more is what it must
    /// never paint. Returns how many it left.
    pub fn spare_touching(
        &mut self,
        grid: &TexelGrid,
        seams: &SeamSet,
        charts: &Charts,
        harmed: &[bool],
    ) -> usize {
        let mut spared = 0;
        for (s, closed) in seams.seams.iter().zip(&mut self.closed) {
            if *closed
                && charts
                    .touched_by(grid, s)
                    .iter()
                    .any(|&c| harmed.get(c as usize).copied().unwrap_or(false))
            {
                *closed = false;
                spared += 1;
            }
        }
        self.spared += spared;
        spared
    }

    pub fn closed_count(&self) -> usize {
        self.closed.iter().filter(|c| **c).count()
    }
}

/// The colour differences sampled along one edge, per channel.
struct EdgeSamples {
    /// Σ over samples of the difference (side a − side b), per channel.
    sum: [f64; 4],
    /// Σ over samples of the squared difference, per channel.
    sum_sq: [f64; 4],
    count: usize,
}

impl EdgeSamples {
    fn add(&mut self, a: &[f64; 4], b: &[f64; 4], compared: usize) {
        for c in 0..compared {
            let d = a[c] - b[c];
            self.sum[c] += d;
            self.sum_sq[c] += d * d;
        }
        self.count += 1;
    }
}

/// Judges every seam of `seams` on the input texture `data`.
pub fn classify(
    grid: &TexelGrid,
    data: &[f32],
    channels: usize,
    compared: usize,
    seams: &SeamSet,
    charts: &Charts,
    opts: &ClassifyOptions,
) -> SeamVerdicts {
    let sides = |s: &crate::model::SeamEdge| {
        s.triangles
            .map(|t| charts.of_triangle.get(t as usize).copied().unwrap_or(0))
    };
    let samples: Vec<EdgeSamples> = seams
        .seams
        .iter()
        .map(|s| {
            let c = sides(s);
            edge_samples(grid, data, channels, compared, charts, s.a, s.b, c)
        })
        .collect();

    // The mean difference of each chart pair, oriented from the lower chart
    // number to the higher, weighted by the sample count of its edges.
    let mut offsets: std::collections::BTreeMap<(u32, u32), ([f64; 4], usize)> = Default::default();
    if opts.remove_chart_offsets {
        for (s, e) in seams.seams.iter().zip(&samples) {
            let [ca, cb] = sides(s);
            let sign = if ca <= cb { 1.0 } else { -1.0 };
            let entry = offsets.entry((ca.min(cb), ca.max(cb))).or_default();
            for k in 0..compared {
                entry.0[k] += sign * e.sum[k];
            }
            entry.1 += e.count;
        }
    }

    let jump: Vec<f64> = seams
        .seams
        .iter()
        .zip(&samples)
        .map(|(s, e)| {
            if e.count == 0 {
                return 0.0;
            }
            let n = e.count as f64;
            let mut sq = 0.0;
            for k in 0..compared {
                let mut m = 0.0;
                if opts.remove_chart_offsets {
                    let [ca, cb] = sides(s);
                    let sign = if ca <= cb { 1.0 } else { -1.0 };
                    let (sum, count) = offsets[&(ca.min(cb), ca.max(cb))];
                    m = sign * sum[k] / count as f64;
                }
                // Σ(d − m)² = Σd² − 2mΣd + n·m²
                sq += e.sum_sq[k] - 2.0 * m * e.sum[k] + n * m * m;
            }
            255.0 * (sq.max(0.0) / (n * compared as f64)).sqrt()
        })
        .collect();
    let closed = jump.iter().map(|&j| j <= opts.tolerance).collect();
    SeamVerdicts {
        jump,
        closed,
        spared: 0,
    }
}

#[allow(clippy::too_many_arguments)]
fn edge_samples(
    grid: &TexelGrid,
    data: &[f32],
    channels: usize,
    compared: usize,
    charts: &Charts,
    a: [[f64; 2]; 2],
    b: [[f64; 2]; 2],
    sides: [u32; 2],
) -> EdgeSamples {
    let (ea, eb) = (Segment::from_uv(grid, a), Segment::from_uv(grid, b));
    let extent = |s: &Segment| {
        let (p, q) = (s.at(0.0), s.at(1.0));
        (q[0] - p[0]).abs().max((q[1] - p[1]).abs())
    };
    let texels = extent(&ea).max(extent(&eb));
    let n = ((texels * SAMPLES_PER_TEXEL).ceil() as usize).clamp(2, MAX_SAMPLES);
    let mut out = EdgeSamples {
        sum: [0.0; 4],
        sum_sq: [0.0; 4],
        count: 0,
    };
    let raw = |p: [f64; 2]| {
        let mut c = [0.0; 4];
        for (k, v) in c.iter_mut().enumerate().take(compared) {
            *v = grid.sample(data, channels, k, p);
        }
        Some(c)
    };
    // Sides as their own charts paint them; where no sample finds both
    // charts (a side collapsed to a point, or a sliver far from any texel
    // centre), the texture as it is sampled there, gutter and all, is all
    // there is to judge by.
    for own_charts in [true, false] {
        for k in 0..n {
            let g = (k as f64 + 0.5) / n as f64;
            let (pa, pb) = (ea.at(g), eb.at(g));
            let (ca, cb) = if own_charts {
                (
                    side_colour(grid, data, channels, compared, charts, sides[0], pa),
                    side_colour(grid, data, channels, compared, charts, sides[1], pb),
                )
            } else {
                (raw(pa), raw(pb))
            };
            if let (Some(ca), Some(cb)) = (ca, cb) {
                out.add(&ca, &cb, compared);
            }
        }
        if out.count > 0 {
            break;
        }
    }
    out
}

/// The colour that `chart` paints at texel-space point `p`: the bilinear taps
/// inside the chart, reweighted; failing those, its nearest texel.
fn side_colour(
    grid: &TexelGrid,
    data: &[f32],
    channels: usize,
    compared: usize,
    charts: &Charts,
    chart: u32,
    p: [f64; 2],
) -> Option<[f64; 4]> {
    let cell = [p[0].floor() as i64, p[1].floor() as i64];
    let mut acc = [0.0; 4];
    let mut weight = 0.0;
    for (i, w) in grid.bilinear_taps(cell, p) {
        if w > 0.0 && charts.of_texel[i as usize] == chart {
            for c in 0..compared {
                acc[c] += w * f64::from(data[i as usize * channels + c]);
            }
            weight += w;
        }
    }
    if weight > 1e-9 {
        return Some(acc.map(|v| v / weight));
    }
    let (x, y) = (p[0].round() as i64, p[1].round() as i64);
    let mut best: Option<(f64, u32)> = None;
    for dy in -NEAREST_RADIUS..=NEAREST_RADIUS {
        for dx in -NEAREST_RADIUS..=NEAREST_RADIUS {
            let i = grid.index(x + dx, y + dy);
            if charts.of_texel[i as usize] != chart {
                continue;
            }
            let d = (x + dx) as f64 - p[0];
            let e = (y + dy) as f64 - p[1];
            let d2 = d * d + e * e;
            if best.is_none_or(|(b, _)| d2 < b) {
                best = Some((d2, i));
            }
        }
    }
    best.map(|(_, i)| {
        let mut c = [0.0; 4];
        for (k, v) in c.iter_mut().enumerate().take(compared) {
            *v = f64::from(data[i as usize * channels + k]);
        }
        c
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{find_seams, UvTriangle, Wrap};

    const P: [[f32; 3]; 4] = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 0.]];

    /// Two triangles of one quad, cut apart in UV along their shared 3D edge
    /// into two charts with a black gutter between them; chart `b` painted
    /// `paint_b` where chart `a` is painted `paint_a` (both as functions of
    /// the texel position along the cut).
    fn two_charts(
        paint_a: impl Fn(f64) -> f32,
        paint_b: impl Fn(f64) -> f32,
        opts: &ClassifyOptions,
    ) -> SeamVerdicts {
        let grid = TexelGrid {
            width: 64,
            height: 64,
            wrap_s: Wrap::ClampToEdge,
            wrap_t: Wrap::ClampToEdge,
        };
        let tris = [
            UvTriangle {
                group: 0,
                positions: [P[0], P[1], P[2]],
                uvs: [[0.05, 0.05], [0.45, 0.05], [0.05, 0.45]],
            },
            UvTriangle {
                group: 0,
                positions: [P[1], P[3], P[2]],
                uvs: [[0.95, 0.55], [0.95, 0.95], [0.55, 0.95]],
            },
        ];
        let seams = find_seams(&tris, grid.width, grid.height);
        assert_eq!(seams.seams.len(), 1);
        let charts = Charts::new(&grid, &tris);
        let mut data = vec![0.0f32; grid.len()];
        for (i, v) in data.iter_mut().enumerate() {
            // Position along the cut, 0 at P1 and 1 at P2: chart a's runs
            // from v = 0.05 to 0.45, chart b's from 0.55 to 0.95.
            let v_uv = ((i / 64) as f64 + 0.5) / 64.0;
            *v = match charts.texel(i as u32) {
                Some(0) => paint_a((v_uv - 0.05) / 0.4),
                Some(_) => paint_b((v_uv - 0.55) / 0.4),
                None => 0.0,
            };
        }
        classify(&grid, &data, 1, 1, &seams, &charts, opts)
    }

    const LOCAL: ClassifyOptions = ClassifyOptions {
        tolerance: DEFAULT_TOLERANCE,
        remove_chart_offsets: false,
    };
    const GLOBAL: ClassifyOptions = ClassifyOptions {
        tolerance: DEFAULT_TOLERANCE,
        remove_chart_offsets: true,
    };

    #[test]
    fn agreeing_charts_close_whatever_the_gutter_holds() {
        let v = two_charts(|_| 0.8, |_| 0.8 + 4.0 / 255.0, &LOCAL);
        assert!(v.closed[0], "{v:?}");
        assert!((v.jump[0] - 4.0).abs() < 0.5, "{v:?}");
    }

    #[test]
    fn charts_painted_apart_are_left() {
        let v = two_charts(|_| 0.2, |_| 0.2 + 100.0 / 255.0, &LOCAL);
        assert!(!v.closed[0], "{v:?}");
        assert!((v.jump[0] - 100.0).abs() < 1.0, "{v:?}");
    }

    /// [`two_charts`]'s quad, with a sliver chart of its own beside the
    /// cut in chart `a`'s half of the atlas, under the cut's bilinear
    /// footprint but no side of it.
    fn quad_and_sliver() -> (TexelGrid, Vec<UvTriangle>) {
        let grid = TexelGrid {
            width: 64,
            height: 64,
            wrap_s: Wrap::ClampToEdge,
            wrap_t: Wrap::ClampToEdge,
        };
        let tris = vec![
            UvTriangle {
                group: 0,
                positions: [P[0], P[1], P[2]],
                uvs: [[0.05, 0.05], [0.45, 0.05], [0.05, 0.45]],
            },
            UvTriangle {
                group: 0,
                positions: [P[1], P[3], P[2]],
                uvs: [[0.95, 0.55], [0.95, 0.95], [0.55, 0.95]],
            },
            UvTriangle {
                group: 0,
                positions: [[5., 5., 5.], [6., 5., 5.], [5., 6., 5.]],
                uvs: [[0.455, 0.05], [0.52, 0.05], [0.455, 0.12]],
            },
        ];
        (grid, tris)
    }

    #[test]
    fn a_chart_under_a_seams_footprint_is_touched_by_it() {
        let (grid, tris) = quad_and_sliver();
        let seams = find_seams(&tris, grid.width, grid.height);
        let charts = Charts::new(&grid, &tris);
        assert_eq!((seams.seams.len(), charts.count), (1, 3));
        assert_eq!(charts.touched_by(&grid, &seams.seams[0]), vec![0, 1, 2]);
        let far = UvTriangle {
            uvs: [[0.6, 0.05], [0.7, 0.05], [0.6, 0.15]],
            ..tris[2]
        };
        let tris = [tris[0], tris[1], far];
        let charts = Charts::new(&grid, &tris);
        assert_eq!(charts.touched_by(&grid, &seams.seams[0]), vec![0, 1]);
    }

    #[test]
    fn only_the_last_resort_spares_an_agreeing_seam() {
        let (grid, tris) = quad_and_sliver();
        let seams = find_seams(&tris, grid.width, grid.height);
        let charts = Charts::new(&grid, &tris);
        let agreeing = || SeamVerdicts {
            jump: vec![4.0],
            closed: vec![true],
            spared: 0,
        };
        // The middle zone's rule leaves sides within 16 levels closed,
        // whatever it costs.
        let mut v = agreeing();
        assert_eq!(v.spare(&seams, &charts, &[true, false, false]), 0);
        assert!(v.closed[0]);
        // The last resort spares it for a harmed side chart, and for a
        // harmed chart under its footprint, but for no other.
        for harmed in [[true, false, false], [false, false, true]] {
            let mut v = agreeing();
            assert_eq!(v.spare_touching(&grid, &seams, &charts, &harmed), 1);
            assert_eq!((v.closed[0], v.spared), (false, 1));
        }
        let mut v = agreeing();
        let far = UvTriangle {
            uvs: [[0.6, 0.05], [0.7, 0.05], [0.6, 0.15]],
            ..tris[2]
        };
        let charts = Charts::new(&grid, &[tris[0], tris[1], far]);
        assert_eq!(
            v.spare_touching(&grid, &seams, &charts, &[false, false, true]),
            0
        );
        assert!(v.closed[0]);
    }

    #[test]
    fn global_mode_closes_a_chart_wide_offset() {
        let offset = 60.0 / 255.0;
        let local = two_charts(
            |t| 0.3 + 0.2 * t as f32,
            |t| 0.3 + 0.2 * t as f32 + offset,
            &LOCAL,
        );
        let global = two_charts(
            |t| 0.3 + 0.2 * t as f32,
            |t| 0.3 + 0.2 * t as f32 + offset,
            &GLOBAL,
        );
        assert!(!local.closed[0] && global.closed[0], "{local:?} {global:?}");
        // What varies along the seam beyond the offset still counts.
        let crossed = two_charts(|t| t as f32, |t| 1.0 - t as f32, &GLOBAL);
        assert!(!crossed.closed[0], "{crossed:?}");
    }
}
