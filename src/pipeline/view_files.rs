//! The files the view page reads besides the textures: each texel's chart
//! (`<name>.charts.png`), for a renderer that discards the filter taps
//! outside a fragment's chart, and every seam edge with its verdict and
//! residuals (`<name>.edges.json`), to find the seams on the model.

use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder};
use serde::Serialize;

use crate::model::SeamSet;
use crate::picture::residual;
use crate::seam::charts::Charts;
use crate::seam::TexelGrid;

/// `of_texel` as an RGB PNG: chart `c` is stored as `c + 1` in 24 bits, red
/// the lowest byte; 0 is no chart (a gutter texel). A shader reads it back
/// exactly with nearest sampling.
pub(super) fn charts_png(grid: &TexelGrid, charts: &Charts) -> Result<Vec<u8>, image::ImageError> {
    let rgb: Vec<u8> = charts
        .of_texel
        .iter()
        .flat_map(|&c| {
            let id = if c == Charts::NONE { 0 } else { c + 1 };
            [id as u8, (id >> 8) as u8, (id >> 16) as u8]
        })
        .collect();
    let mut out = Vec::new();
    PngEncoder::new(&mut out).write_image(
        &rgb,
        grid.width as u32,
        grid.height as u32,
        ExtendedColorType::Rgb8,
    )?;
    Ok(out)
}

/// One seam edge as the page reads it.
#[derive(Serialize)]
struct Edge {
    /// The two half-edges, UV endpoints.
    a: [[f32; 2]; 2],
    b: [[f32; 2]; 2],
    /// Made to agree.
    closed: bool,
    /// Left although its jump was within the tolerance: closing it would
    /// have repainted a chart.
    spared: bool,
    /// The jump it was judged by, in 8-bit levels.
    jump: f32,
    /// RMS difference between its sides' bilinear samples, in 8-bit
    /// levels, in each version: `input`, `erased`, `regular`, `seam_aware`.
    residual: [f32; 4],
}

#[derive(Serialize)]
struct Edges<'a> {
    width: usize,
    height: usize,
    /// What the residuals are of, in order.
    versions: [&'a str; 4],
    edges: Vec<Edge>,
}

/// The texels of one texture's versions, RGB in \[0, 1\].
pub(super) struct Versions<'a> {
    pub(super) input: &'a [f32],
    pub(super) erased: &'a [f32],
    pub(super) regular: &'a [f32],
    pub(super) seam_aware: &'a [f32],
}

/// Every seam edge, worst residual in the input first.
pub(super) fn edges_json(
    grid: &TexelGrid,
    seams: &SeamSet,
    closed: &[bool],
    jump: &[f64],
    tolerance: Option<f64>,
    v: &Versions<'_>,
) -> Result<Vec<u8>, serde_json::Error> {
    // Rounded: the page needs no more, and the file stays a tenth the size.
    let round = |x: f64| {
        if x.is_finite() {
            ((x * 1000.0).round() / 1000.0) as f32
        } else {
            f32::MAX
        }
    };
    let uv = |h: [[f64; 2]; 2]| h.map(|p| p.map(|x| x as f32));
    let mut edges: Vec<Edge> = seams
        .seams
        .iter()
        .enumerate()
        .map(|(i, e)| {
            let closed = closed.get(i).copied().unwrap_or(false);
            let jump = jump.get(i).copied().unwrap_or(0.0);
            Edge {
                a: uv(e.a),
                b: uv(e.b),
                closed,
                spared: !closed && tolerance.is_some_and(|t| jump <= t),
                jump: round(jump),
                residual: [v.input, v.erased, v.regular, v.seam_aware]
                    .map(|data| round(residual(grid, data, e))),
            }
        })
        .collect();
    edges.sort_by(|x, y| y.residual[0].total_cmp(&x.residual[0]));
    serde_json::to_vec(&Edges {
        width: grid.width,
        height: grid.height,
        versions: ["input", "erased", "regular", "seam_aware"],
        edges,
    })
}
