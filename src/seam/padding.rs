//! Padding for seams left as painted.
//!
//! A seam that is not closed still shows whatever its bilinear footprint
//! reads: where that footprint reaches past the chart into the gutter, the
//! gutter's colour (a black background, a neighbouring chart's bleed) is
//! blended into the rendered edge. Each such gutter texel is filled from the
//! chart on its own side of the seam, so that the edge shows the colour its
//! chart paints and nothing else.

use std::collections::BTreeMap;

use super::charts::Charts;
use super::grid::TexelGrid;
use super::quadrature::{for_each_cell, Segment};
use crate::model::SeamSet;

/// How far (texels, each axis) a gutter texel looks for its chart's texels.
/// Footprint texels sit at most one texel off the chart; two more reach
/// past a sliver chart's thin end.
const REACH: i64 = 3;

/// One gutter texel to fill: the chart it is filled from, found at this
/// squared distance, and where the texel sits (unwrapped lattice position).
#[derive(Clone, Copy)]
struct Claim {
    distance2: i64,
    chart: u32,
    at: [i64; 2],
}

/// Fills, in `data`, the gutter texels that the half-edges of the seams
/// *not* selected by `closed` read, from their own side's chart. Returns how
/// many texels were filled.
///
/// Each value is the inverse-square-distance mean of the chart's texels
/// within `REACH`, read from the input before any texel is filled, so the
/// result does not depend on the order of the seams. A gutter texel that two
/// left seams read is filled from the chart nearer to it (the lower chart
/// number on a tie).
pub fn pad_left_seams(
    grid: &TexelGrid,
    data: &mut [f32],
    channels: usize,
    seams: &SeamSet,
    closed: &[bool],
    charts: &Charts,
) -> usize {
    let mut claims: BTreeMap<u32, Claim> = BTreeMap::new();
    for (s, _) in seams.seams.iter().zip(closed).filter(|(_, c)| !**c) {
        for (uv, t) in [(s.a, s.triangles[0]), (s.b, s.triangles[1])] {
            let Some(&chart) = charts.of_triangle.get(t as usize) else {
                continue;
            };
            for_each_cell(Segment::from_uv(grid, uv), |cell| {
                for dy in 0..2 {
                    for dx in 0..2 {
                        let at = [cell[0] + dx, cell[1] + dy];
                        claim(grid, charts, chart, at, &mut claims);
                    }
                }
            });
        }
    }
    // Claims are gutter texels and means read chart texels only, so filling
    // in place reads the input as painted (no copy of the image needed).
    let mut filled = 0;
    for (&i, c) in &claims {
        if let Some(value) = chart_mean(grid, data, channels, charts, c) {
            data[i as usize * channels..][..channels].copy_from_slice(&value[..channels]);
            filled += 1;
        }
    }
    filled
}

fn claim(
    grid: &TexelGrid,
    charts: &Charts,
    chart: u32,
    at: [i64; 2],
    claims: &mut BTreeMap<u32, Claim>,
) {
    let i = grid.index(at[0], at[1]);
    if charts.texel(i).is_some() {
        return;
    }
    let Some(distance2) = nearest(grid, charts, chart, at) else {
        return;
    };
    let new = Claim {
        distance2,
        chart,
        at,
    };
    claims
        .entry(i)
        .and_modify(|old| {
            if (distance2, chart) < (old.distance2, old.chart) {
                *old = new;
            }
        })
        .or_insert(new);
}

/// Squared distance from `at` to the nearest texel of `chart` within reach.
fn nearest(grid: &TexelGrid, charts: &Charts, chart: u32, at: [i64; 2]) -> Option<i64> {
    let mut best = None;
    for dy in -REACH..=REACH {
        for dx in -REACH..=REACH {
            if charts.of_texel[grid.index(at[0] + dx, at[1] + dy) as usize] == chart {
                let d2 = dx * dx + dy * dy;
                best = Some(best.map_or(d2, |b: i64| b.min(d2)));
            }
        }
    }
    best
}

fn chart_mean(
    grid: &TexelGrid,
    data: &[f32],
    channels: usize,
    charts: &Charts,
    c: &Claim,
) -> Option<[f32; 4]> {
    let mut acc = [0.0f64; 4];
    let mut weight = 0.0;
    for dy in -REACH..=REACH {
        for dx in -REACH..=REACH {
            let j = grid.index(c.at[0] + dx, c.at[1] + dy) as usize;
            if charts.of_texel[j] != c.chart {
                continue;
            }
            let w = 1.0 / (dx * dx + dy * dy) as f64;
            for (k, a) in acc.iter_mut().enumerate().take(channels) {
                *a += w * f64::from(data[j * channels + k]);
            }
            weight += w;
        }
    }
    (weight > 0.0).then(|| acc.map(|a| (a / weight) as f32))
}
