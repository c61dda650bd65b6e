//! The seams picture (`<name>.seams.png`): what seam erasure and BC1 did to
//! one texture's seams, for a person to check at a glance.
//!
//! Layout, top to bottom, on a dark background with a `MARGIN` all round:
//!
//! 1. **Overview panel**: the shipped (last) version dimmed to a third, scaled
//!    so that its longer side is at most `MAX_PANEL` pixels (and, for small
//!    textures, enlarged by an integer factor to at least `MIN_PANEL`), with
//!    every seam half-edge drawn over it. Hue says the class (closed or left
//!    as painted); brightness says the edge's residual after BC1.
//! 2. **Legend**: two rows of swatches, closed then left, from residual 0
//!    (dim) to `FULL_BRIGHT_LEVELS` or more (bright), each named.
//! 3. **Close-up strip** (only when some edge is closed): a title row naming
//!    the versions, then one row per worst closed edge (up to `STRIP_ROWS`);
//!    each row holds, for each version in turn (for a job: input, erased,
//!    regular BC1, seam-aware BC1; for a level of detail: erased and the
//!    DDS), a tile around half-edge `a` and a tile around half-edge `b`, at
//!    full brightness, the first with the edge's jump in that version
//!    written on it.
//!
//! The words are drawn with a bitmap font of its own (`font.rs`): the
//! picture needs a few dozen glyphs, not a font renderer.

use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder, Rgb, RgbImage};

use crate::model::{SeamEdge, SeamSet, Wrap};
use crate::seam::TexelGrid;

mod font;
use font::{draw_text, text_width, GLYPH_H};

/// What the seams picture shows for one texture (mip level 0) on one mesh.
pub struct SeamPicture<'a> {
    /// Width, height and wrap modes of the texture.
    pub grid: &'a TexelGrid,
    /// The versions of the texture the close-ups set side by side, in
    /// order (for a job: input, erased, regular BC1 and what the DDS
    /// holds). The last is what ships: the overview shows it, and each
    /// line's brightness is its residual there.
    pub versions: Vec<Version<'a>>,
    /// Every seam edge.
    pub seams: &'a SeamSet,
    /// Per seam edge (same order as `seams.seams`): true when the edge was
    /// closed (its sides made to agree), false when it was left as painted.
    pub closed: &'a [bool],
    /// For an alpha judged apart from the colour: per seam edge, whether its
    /// alpha was closed. Edges whose colour closed but whose alpha was left
    /// as painted are drawn in their own hue.
    pub alpha_closed: Option<&'a [bool]>,
}

/// One version of the texture, named as the close-ups' title row names it.
#[derive(Clone, Copy)]
pub struct Version<'a> {
    pub name: &'static str,
    /// RGB texels, 3 interleaved f32 values per texel in \[0,1\], row-major,
    /// `grid.width * grid.height` texels.
    pub data: &'a [f32],
}

/// The versions of a job's picture: input, erased, regular BC1, and what
/// the DDS holds (equal to the regular one when seam-aware encoding is off).
pub fn job_versions<'a>(
    input: &'a [f32],
    erased: &'a [f32],
    regular: &'a [f32],
    shipped: &'a [f32],
) -> Vec<Version<'a>> {
    vec![
        Version {
            name: "INPUT",
            data: input,
        },
        Version {
            name: "ERASED",
            data: erased,
        },
        Version {
            name: "REGULAR BC1",
            data: regular,
        },
        Version {
            name: "SEAM-AWARE BC1",
            data: shipped,
        },
    ]
}

/// Why the picture could not be drawn.
#[derive(Debug, thiserror::Error)]
pub enum PictureError {
    /// A texel buffer's length does not match the grid (a caller bug).
    #[error("seams picture: `{buffer}` holds {len} values, expected {expected} (3 per texel)")]
    BufferSize {
        buffer: String,
        len: usize,
        expected: usize,
    },
    /// `closed` does not have one entry per seam edge (a caller bug).
    #[error("seams picture: {closed} closed flags for {seams} seam edges")]
    ClosedFlags { closed: usize, seams: usize },
    /// No version to show (a caller bug).
    #[error("seams picture: no version of the texture to show")]
    NoVersions,
    /// The texture has no texels.
    #[error("seams picture: empty texture ({width}x{height})")]
    Empty { width: usize, height: usize },
    #[error("seams picture: cannot encode PNG: {0}")]
    Encode(#[from] image::ImageError),
}

/// Texel buffers are RGB.
const CHANNELS: usize = 3;

/// Dark fill behind and between everything, so panels and tiles stand apart.
const BACKGROUND: [u8; 3] = [18, 18, 22];
/// Space around the picture's content and between its sections.
const MARGIN: u32 = 8;

/// A longer side above this is box-filtered down: the picture stays small
/// enough to open anywhere, and seams are still a pixel apart on most models.
const MAX_PANEL: usize = 1024;
/// Small textures are enlarged (nearest neighbour, integer factor) to at
/// least this, so seam lines are not drawn over a postage stamp.
const MIN_PANEL: usize = 512;
/// The overview texture is dimmed so the seam lines are what one sees first.
const PANEL_BRIGHTNESS: f32 = 1.0 / 3.0;

/// Closed edges: a cyan-green, far from most skin and wood tones.
const CLOSED_HUE: [u8; 3] = [0, 255, 190];
/// Edges left as painted: magenta, clearly not the closed hue.
const LEFT_HUE: [u8; 3] = [255, 70, 210];
/// Edges whose colour closed while their alpha, painted apart, was left:
/// amber, between the two and unlike either.
const ALPHA_LEFT_HUE: [u8; 3] = [255, 176, 0];
/// Residual (8-bit levels, RMS) at which a line reaches full brightness:
/// around here a BC1 seam starts to be visible.
const FULL_BRIGHT_LEVELS: f64 = 8.0;
/// Brightness of a line with zero residual, as a fraction of full: still
/// above the dimmed texture so every seam can be found.
const DIM_LINE: f64 = 0.45;

/// Residual sampling density along a half-edge (samples per texel of length).
const SAMPLES_PER_TEXEL: f64 = 4.0;
/// Cap on residual samples, so a huge edge costs a bounded time.
const MAX_SAMPLES: usize = 4096;
/// UVs farther out than this are treated as broken: not sampled, and their
/// residual is infinite (the edge then sorts as the worst). Keeps texel
/// indices far from integer overflow.
const MAX_ABS_UV: f64 = 1e6;
/// An edge spanning more wrap periods than this (per axis) is drawn in the
/// first ones only; real edges span one or two.
const MAX_PERIODS: i64 = 4;

/// Legend swatches per class, residual 0 to [`FULL_BRIGHT_LEVELS`].
const LEGEND_STEPS: u32 = 5;
/// As tall as a line of text, which names each row.
const SWATCH_PX: u32 = TEXT_SCALE * GLYPH_H;
const SWATCH_GAP: u32 = 2;

/// Close-ups are shown for this many closed edges, the worst first.
const STRIP_ROWS: usize = 4;
/// Texels per side of a close-up crop: enough to see the chart's gutter.
const CROP_TEXELS: u32 = 16;
/// Nearest-neighbour enlargement of a close-up, so single texels are visible.
const ZOOM: u32 = 8;
const TILE_PX: u32 = CROP_TEXELS * ZOOM;
/// Gap between the `a` and `b` tiles of one version.
const TILE_GAP: u32 = 3;
/// Wider gap between versions, so the pairs read as pairs.
const VERSION_GAP: u32 = 12;
/// Gap between strip rows.
const ROW_GAP: u32 = 6;

/// Font pixels are this many picture pixels square.
const TEXT_SCALE: u32 = 2;
/// Words on the dark background.
const TEXT: [u8; 3] = [230, 230, 230];
/// The strip's title row: a line of text and a gap.
const TITLE_H: u32 = TEXT_SCALE * GLYPH_H + ROW_GAP;
/// Words over a close-up sit on a box this dark, inset this far.
const LABEL_BACKGROUND: [u8; 3] = [0, 0, 0];
const LABEL_PAD: u32 = 2;

/// A pixel rectangle of the picture.
#[derive(Clone, Copy, Debug)]
struct Rect {
    x: u32,
    y: u32,
    w: u32,
    h: u32,
}

/// Draws the picture; returns PNG bytes (8-bit RGB). Deterministic: same
/// input, same bytes.
pub fn seams_png(p: &SeamPicture) -> Result<Vec<u8>, PictureError> {
    validate(p)?;
    let shipped = shipped(p);
    let residuals: Vec<f64> = p
        .seams
        .seams
        .iter()
        .map(|e| residual(p.grid, shipped, e))
        .collect();
    let rows = worst_closed(p.closed, &residuals);

    let (pw, ph) = panel_size(p.grid.width, p.grid.height);
    let panel = Rect {
        x: MARGIN,
        y: MARGIN,
        w: pw,
        h: ph,
    };
    let legend_top = panel.y + panel.h + MARGIN;
    let hues = legend_hues(p);
    let legend_h = hues.len() as u32 * (SWATCH_PX + SWATCH_GAP) - SWATCH_GAP;
    let strip_top = legend_top + legend_h + MARGIN;
    let strip_h = match rows.len() as u32 {
        0 => 0,
        n => TITLE_H + n * TILE_PX + (n - 1) * ROW_GAP + MARGIN,
    };
    let legend_w = legend_width(&hues);
    let content_w = if rows.is_empty() {
        pw.max(legend_w)
    } else {
        pw.max(strip_width(p.versions.len())).max(legend_w)
    };
    let mut img =
        RgbImage::from_pixel(content_w + 2 * MARGIN, strip_top + strip_h, Rgb(BACKGROUND));

    draw_panel_texture(&mut img, p, panel);
    draw_panel_seams(&mut img, p, &residuals, panel);
    draw_legend(&mut img, &hues, MARGIN, legend_top);
    draw_strip(&mut img, p, &rows, strip_top);
    encode_png(&img)
}

fn validate(p: &SeamPicture) -> Result<(), PictureError> {
    let (width, height) = (p.grid.width, p.grid.height);
    if width == 0 || height == 0 {
        return Err(PictureError::Empty { width, height });
    }
    if p.versions.is_empty() {
        return Err(PictureError::NoVersions);
    }
    let expected = width * height * CHANNELS;
    for v in &p.versions {
        if v.data.len() != expected {
            return Err(PictureError::BufferSize {
                buffer: v.name.to_string(),
                len: v.data.len(),
                expected,
            });
        }
    }
    for flags in std::iter::once(p.closed).chain(p.alpha_closed) {
        if flags.len() != p.seams.seams.len() {
            return Err(PictureError::ClosedFlags {
                closed: flags.len(),
                seams: p.seams.seams.len(),
            });
        }
    }
    Ok(())
}

/// The version that ships (validated: there is one).
fn shipped<'a>(p: &SeamPicture<'a>) -> &'a [f32] {
    p.versions.last().map_or(&[], |v| v.data)
}

fn encode_png(img: &RgbImage) -> Result<Vec<u8>, PictureError> {
    let mut out = Vec::new();
    PngEncoder::new(&mut out).write_image(
        img.as_raw(),
        img.width(),
        img.height(),
        ExtendedColorType::Rgb8,
    )?;
    Ok(out)
}

// ---------------------------------------------------------------- residual

/// RMS difference, in 8-bit levels, between the bilinear samples of `data`
/// on the edge's two half-edges at matching γ (averaged over γ and over the
/// three channels). Samples sit at the midpoints of equal γ steps, so the
/// corners an edge shares with its neighbours are not counted twice.
pub fn residual(grid: &TexelGrid, data: &[f32], e: &SeamEdge) -> f64 {
    let sane = |h: &[[f64; 2]; 2]| h.iter().flatten().all(|c| c.abs() <= MAX_ABS_UV);
    if !sane(&e.a) || !sane(&e.b) {
        return f64::INFINITY;
    }
    let (a, b) = (
        e.a.map(|uv| grid.to_texel(uv)),
        e.b.map(|uv| grid.to_texel(uv)),
    );
    let texels = texel_length(a).max(texel_length(b));
    let n = ((texels * SAMPLES_PER_TEXEL).ceil() as usize).clamp(1, MAX_SAMPLES);
    let mut sum = 0.0;
    for k in 0..n {
        let g = (k as f64 + 0.5) / n as f64;
        let (pa, pb) = (lerp(a[0], a[1], g), lerp(b[0], b[1], g));
        for c in 0..CHANNELS {
            let d = grid.sample(data, CHANNELS, c, pa) - grid.sample(data, CHANNELS, c, pb);
            sum += d * d;
        }
    }
    (sum / (n * CHANNELS) as f64).sqrt() * 255.0
}

fn texel_length(h: [[f64; 2]; 2]) -> f64 {
    (h[1][0] - h[0][0]).hypot(h[1][1] - h[0][1])
}

fn lerp(p: [f64; 2], q: [f64; 2], t: f64) -> [f64; 2] {
    [p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])]
}

/// Indices of the closed edges with the largest residuals, worst first, at
/// most [`STRIP_ROWS`]; equal residuals go by edge index, for determinism.
fn worst_closed(closed: &[bool], residuals: &[f64]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..residuals.len()).filter(|&i| closed[i]).collect();
    idx.sort_by(|&i, &j| residuals[j].total_cmp(&residuals[i]).then(i.cmp(&j)));
    idx.truncate(STRIP_ROWS);
    idx
}

/// The hue of edge `i`'s class: closed, left, or closed in colour with its
/// alpha left.
fn hue_of(p: &SeamPicture, i: usize) -> [u8; 3] {
    match (p.closed[i], p.alpha_closed.map(|a| a[i])) {
        (true, Some(false)) => ALPHA_LEFT_HUE,
        (true, _) => CLOSED_HUE,
        (false, _) => LEFT_HUE,
    }
}

/// The hues the legend shows, one row each, with their names.
fn legend_hues(p: &SeamPicture) -> Vec<([u8; 3], &'static str)> {
    let mut hues = vec![
        (
            CLOSED_HUE,
            "CLOSED (BRIGHTER: LARGER RESIDUAL, 0 TO 8+ LEVELS)",
        ),
        (LEFT_HUE, "LEFT AS PAINTED"),
    ];
    if p.alpha_closed.is_some() {
        hues.push((ALPHA_LEFT_HUE, "COLOUR CLOSED, ALPHA LEFT AS PAINTED"));
    }
    hues
}

/// The legend's width: its swatches and its longest name.
fn legend_width(hues: &[([u8; 3], &str)]) -> u32 {
    let names = hues
        .iter()
        .map(|(_, name)| text_width(name, TEXT_SCALE))
        .max()
        .unwrap_or(0);
    LEGEND_STEPS * (SWATCH_PX + SWATCH_GAP) + VERSION_GAP + names
}

/// The class hue scaled by residual: [`DIM_LINE`] of full at 0, full at
/// [`FULL_BRIGHT_LEVELS`] and above (and for a residual that is not a number).
fn edge_colour(hue: [u8; 3], residual: f64) -> Rgb<u8> {
    let t = if residual.is_nan() {
        1.0
    } else {
        (residual / FULL_BRIGHT_LEVELS).clamp(0.0, 1.0)
    };
    let scale = DIM_LINE + (1.0 - DIM_LINE) * t;
    Rgb(hue.map(|c| (f64::from(c) * scale).round() as u8))
}

// ---------------------------------------------------------------- overview

/// Panel size for a `width`×`height` texture: longer side at most
/// [`MAX_PANEL`], and small textures enlarged by an integer factor to reach
/// at least [`MIN_PANEL`].
fn panel_size(width: usize, height: usize) -> (u32, u32) {
    let long = width.max(height);
    let (w, h) = if long > MAX_PANEL {
        let scale = |n: usize| ((n * MAX_PANEL + long / 2) / long).max(1);
        (scale(width), scale(height))
    } else {
        let k = MIN_PANEL.div_ceil(long);
        (width * k, height * k)
    };
    (w as u32, h as u32)
}

/// The seam-aware texture, dimmed, box-filtered into `r`. Panel pixel `x`
/// averages texels `⌊x·W/w⌋ .. ⌈(x+1)·W/w⌉`: a box filter when shrinking, and
/// exactly nearest neighbour when enlarging by an integer factor.
fn draw_panel_texture(img: &mut RgbImage, p: &SeamPicture, r: Rect) {
    let (tw, th) = (p.grid.width, p.grid.height);
    let span = |px: u32, n: usize, out: u32| {
        let (px, out) = (px as usize, out as usize);
        let lo = px * n / out;
        (lo, ((px + 1) * n).div_ceil(out).max(lo + 1))
    };
    for py in 0..r.h {
        let (y0, y1) = span(py, th, r.h);
        for px in 0..r.w {
            let (x0, x1) = span(px, tw, r.w);
            let mut sum = [0.0f32; CHANNELS];
            for y in y0..y1 {
                for x in x0..x1 {
                    let t = (y * tw + x) * CHANNELS;
                    for (s, v) in sum.iter_mut().zip(&shipped(p)[t..t + CHANNELS]) {
                        *s += v;
                    }
                }
            }
            let scale = PANEL_BRIGHTNESS / ((y1 - y0) * (x1 - x0)) as f32;
            img.put_pixel(r.x + px, r.y + py, Rgb(sum.map(|s| to_u8(s * scale))));
        }
    }
}

/// Every half-edge of every seam, as lines over the panel. Left edges go
/// first and closed ones on top (they are what the picture is for); within a
/// class, larger residuals on top.
fn draw_panel_seams(img: &mut RgbImage, p: &SeamPicture, residuals: &[f64], r: Rect) {
    let mut order: Vec<usize> = (0..residuals.len()).collect();
    order.sort_by(|&i, &j| {
        (p.closed[i].cmp(&p.closed[j]))
            .then(residuals[i].total_cmp(&residuals[j]))
            .then(i.cmp(&j))
    });
    // Texel-space point → panel pixel coordinates (pixel x covers [x, x+1)).
    let sx = f64::from(r.w) / p.grid.width as f64;
    let sy = f64::from(r.h) / p.grid.height as f64;
    let to_panel = |t: [f64; 2]| {
        [
            f64::from(r.x) + (t[0] + 0.5) * sx,
            f64::from(r.y) + (t[1] + 0.5) * sy,
        ]
    };
    for i in order {
        let e = &p.seams.seams[i];
        let colour = edge_colour(hue_of(p, i), residuals[i]);
        for half in [e.a, e.b] {
            for [s, t] in wrapped_copies(p.grid, half) {
                let (s, t) = (p.grid.to_texel(s), p.grid.to_texel(t));
                draw_line(img, r, to_panel(s), to_panel(t), colour);
            }
        }
    }
}

/// The half-edge `h` (UV) brought into \[0,1\]² by the texture's wrap modes:
/// one copy per wrap period it touches, each to be clipped to the panel.
/// Under clamp-to-edge only the copy in place is drawn (the rest is clipped).
fn wrapped_copies(grid: &TexelGrid, h: [[f64; 2]; 2]) -> Vec<[[f64; 2]; 2]> {
    let axis = |wrap: Wrap, k: usize| period_maps(wrap, h[0][k].min(h[1][k]), h[0][k].max(h[1][k]));
    let (us, vs) = (axis(grid.wrap_s, 0), axis(grid.wrap_t, 1));
    let mut out = Vec::with_capacity(us.len() * vs.len());
    for &(su, ou) in &us {
        for &(sv, ov) in &vs {
            out.push(h.map(|uv| [su * uv[0] + ou, sv * uv[1] + ov]));
        }
    }
    out
}

/// The affine maps `u ↦ s·u + o` that take each wrap period that
/// `[lo, hi]` touches onto \[0, 1\], as the sampler does: a shift under
/// repeat, a shift or a reflection under mirrored repeat.
fn period_maps(wrap: Wrap, lo: f64, hi: f64) -> Vec<(f64, f64)> {
    if wrap == Wrap::ClampToEdge || !lo.is_finite() || !hi.is_finite() {
        return vec![(1.0, 0.0)];
    }
    // `as` saturates for huge values; such copies are simply clipped away.
    let first = lo.floor() as i64;
    let last = (hi.floor() as i64).min(first.saturating_add(MAX_PERIODS - 1));
    (first..=last)
        .map(|k| match wrap {
            Wrap::MirroredRepeat if k.rem_euclid(2) == 1 => (-1.0, k as f64 + 1.0),
            _ => (1.0, -(k as f64)),
        })
        .collect()
}

/// Swatches for each class from residual 0 to [`FULL_BRIGHT_LEVELS`]:
/// closed on the first row, left on the second.
fn draw_legend(img: &mut RgbImage, hues: &[([u8; 3], &str)], x: u32, y: u32) {
    for (row, &(hue, name)) in hues.iter().enumerate() {
        let top = y + row as u32 * (SWATCH_PX + SWATCH_GAP);
        for s in 0..LEGEND_STEPS {
            let level = FULL_BRIGHT_LEVELS * f64::from(s) / f64::from(LEGEND_STEPS - 1);
            let r = Rect {
                x: x + s * (SWATCH_PX + SWATCH_GAP),
                y: top,
                w: SWATCH_PX,
                h: SWATCH_PX,
            };
            fill(img, r, edge_colour(hue, level));
        }
        let text_x = x + LEGEND_STEPS * (SWATCH_PX + SWATCH_GAP) + VERSION_GAP;
        draw_text(img, text_x, top, name, TEXT_SCALE, Rgb(TEXT));
    }
}

// ---------------------------------------------------------------- strip

/// Left edge of tile `k` of a strip row, relative to the row.
fn tile_x(k: u32) -> u32 {
    k * TILE_PX + (k / 2) * VERSION_GAP + (k % 2) * TILE_GAP
}

/// A strip row's width: two tiles per version.
fn strip_width(versions: usize) -> u32 {
    tile_x(2 * versions as u32 - 1) + TILE_PX
}

/// One row per edge in `rows`: for each version, the crops around half-edge
/// `a` and half-edge `b`.
fn draw_strip(img: &mut RgbImage, p: &SeamPicture, rows: &[usize], top: u32) {
    if rows.is_empty() {
        return;
    }
    for (k, v) in p.versions.iter().enumerate() {
        let x = MARGIN + tile_x(2 * k as u32);
        draw_text(img, x, top, v.name, TEXT_SCALE, Rgb(TEXT));
    }
    for (row, &e) in rows.iter().enumerate() {
        let edge = &p.seams.seams[e];
        let y = top + TITLE_H + row as u32 * (TILE_PX + ROW_GAP);
        let mut k = 0;
        for data in p.versions.iter().map(|v| v.data) {
            for half in [edge.a, edge.b] {
                let r = Rect {
                    x: MARGIN + tile_x(k),
                    y,
                    w: TILE_PX,
                    h: TILE_PX,
                };
                draw_tile(img, p.grid, data, half, r);
                if k % 2 == 0 {
                    draw_label(img, r, &jump_label(residual(p.grid, data, edge)));
                }
                k += 1;
            }
        }
    }
}

/// What a close-up says of its version: the edge's jump in 8-bit levels.
fn jump_label(levels: f64) -> String {
    if levels.is_finite() {
        format!("JUMP {levels:.1}")
    } else {
        "JUMP -".to_string()
    }
}

/// `text` at the bottom-left corner of tile `r`, on a dark box so that it
/// reads over any texture.
fn draw_label(img: &mut RgbImage, r: Rect, text: &str) {
    let (w, h) = (
        text_width(text, TEXT_SCALE) + 2 * LABEL_PAD,
        TEXT_SCALE * GLYPH_H + 2 * LABEL_PAD,
    );
    let boxed = Rect {
        x: r.x,
        y: r.y + r.h - h,
        w: w.min(r.w),
        h,
    };
    fill(img, boxed, Rgb(LABEL_BACKGROUND));
    draw_text(
        img,
        boxed.x + LABEL_PAD,
        boxed.y + LABEL_PAD,
        text,
        TEXT_SCALE,
        Rgb(TEXT),
    );
}

/// A [`CROP_TEXELS`]² crop of `data` centred on the half-edge's midpoint,
/// enlarged ×[`ZOOM`], full brightness, with the half-edge drawn over it.
/// Texels outside the image come through the wrap modes, as the GPU sees them.
fn draw_tile(img: &mut RgbImage, grid: &TexelGrid, data: &[f32], half: [[f64; 2]; 2], r: Rect) {
    let (s, t) = (grid.to_texel(half[0]), grid.to_texel(half[1]));
    let mid = lerp(s, t, 0.5);
    // The crop's centre, texel corner ⌊mid⌋ + ½, is within half a texel of `mid`.
    let before = i64::from(CROP_TEXELS / 2 - 1);
    let (i0, j0) = (texel_floor(mid[0]) - before, texel_floor(mid[1]) - before);
    for tj in 0..CROP_TEXELS {
        for ti in 0..CROP_TEXELS {
            let at = grid.index(i0 + i64::from(ti), j0 + i64::from(tj)) as usize * CHANNELS;
            let rgb = [0, 1, 2].map(|c| to_u8(data[at + c]));
            let block = Rect {
                x: r.x + ti * ZOOM,
                y: r.y + tj * ZOOM,
                w: ZOOM,
                h: ZOOM,
            };
            fill(img, block, Rgb(rgb));
        }
    }
    let zoom = f64::from(ZOOM);
    let to_tile = |p: [f64; 2]| {
        [
            f64::from(r.x) + (p[0] - i0 as f64 + 0.5) * zoom,
            f64::from(r.y) + (p[1] - j0 as f64 + 0.5) * zoom,
        ]
    };
    draw_line(img, r, to_tile(s), to_tile(t), Rgb(CLOSED_HUE));
}

/// `⌊x⌋` as a texel index, kept far from overflow for broken coordinates.
fn texel_floor(x: f64) -> i64 {
    let limit = MAX_ABS_UV * 1e6;
    if x.is_finite() {
        x.clamp(-limit, limit).floor() as i64
    } else {
        0
    }
}

// ---------------------------------------------------------------- drawing

fn fill(img: &mut RgbImage, r: Rect, colour: Rgb<u8>) {
    for y in r.y..r.y + r.h {
        for x in r.x..r.x + r.w {
            img.put_pixel(x, y, colour);
        }
    }
}

/// A 1-pixel line from `p` to `q` (pixel coordinates; pixel x covers
/// \[x, x+1)), clipped to `clip`: a DDA stepping one pixel along the major axis.
fn draw_line(img: &mut RgbImage, clip: Rect, p: [f64; 2], q: [f64; 2], colour: Rgb<u8>) {
    if clip.w == 0 || clip.h == 0 {
        return;
    }
    let bounds = [
        f64::from(clip.x),
        f64::from(clip.y),
        f64::from(clip.x + clip.w),
        f64::from(clip.y + clip.h),
    ];
    let Some((p, q)) = clip_segment(p, q, bounds) else {
        return;
    };
    let steps = (q[0] - p[0]).abs().max((q[1] - p[1]).abs()).ceil().max(1.0) as u32;
    // A point on the clip's far side (x = x + w) belongs to the last column.
    let px = |v: f64, lo: u32, n: u32| {
        (v.floor() as i64).clamp(i64::from(lo), i64::from(lo + n - 1)) as u32
    };
    for k in 0..=steps {
        let at = lerp(p, q, f64::from(k) / f64::from(steps));
        img.put_pixel(px(at[0], clip.x, clip.w), px(at[1], clip.y, clip.h), colour);
    }
}

/// Liang–Barsky: the part of segment `p`–`q` inside the closed box
/// `[x0, y0, x1, y1]`, or `None` when none is (or a coordinate is not finite).
fn clip_segment(p: [f64; 2], q: [f64; 2], b: [f64; 4]) -> Option<([f64; 2], [f64; 2])> {
    if !p.iter().chain(&q).all(|c| c.is_finite()) {
        return None;
    }
    let d = [q[0] - p[0], q[1] - p[1]];
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (dir, room) in [
        (-d[0], p[0] - b[0]),
        (d[0], b[2] - p[0]),
        (-d[1], p[1] - b[1]),
        (d[1], b[3] - p[1]),
    ] {
        if dir == 0.0 {
            if room < 0.0 {
                return None; // parallel to this side and outside it
            }
        } else if dir < 0.0 {
            t0 = t0.max(room / dir);
        } else {
            t1 = t1.min(room / dir);
        }
    }
    (t0 <= t1).then(|| (lerp(p, q, t0), lerp(p, q, t1)))
}

/// A \[0,1\] value to an 8-bit level; NaN shows as black rather than failing.
fn to_u8(v: f32) -> u8 {
    if v.is_nan() {
        0
    } else {
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const N: usize = 32;
    /// Panel of a 32² texture: enlarged ×16.
    const PANEL: u32 = 512;
    const LEGEND_H: u32 = 2 * SWATCH_PX + SWATCH_GAP;
    const STRIP_TOP: u32 = MARGIN + PANEL + MARGIN + LEGEND_H + MARGIN;
    /// The first row of close-ups, below the title row.
    const ROWS_TOP: u32 = STRIP_TOP + TITLE_H;

    /// A 32² texture with two charts (rectangles) and three seams:
    /// 0, closed, whose sides agree in `seam_aware` (residual 0);
    /// 1, closed, whose `b` side lies in a bright patch (large residual);
    /// 2, left as painted, a vertical edge at u = ½.
    struct Fixture {
        grid: TexelGrid,
        input: Vec<f32>,
        erased: Vec<f32>,
        seam_aware: Vec<f32>,
        seams: SeamSet,
    }

    fn image_of(f: impl Fn(usize, usize) -> [f32; 3]) -> Vec<f32> {
        (0..N * N).flat_map(|t| f(t % N, t / N)).collect()
    }

    fn edge(a: [[f64; 2]; 2], b: [[f64; 2]; 2]) -> SeamEdge {
        SeamEdge {
            a,
            b,
            a_opposite: [0.0, 0.0],
            b_opposite: [1.0, 1.0],
            length: 1.0,
            triangles: [0, 1],
        }
    }

    fn fixture() -> Fixture {
        let input = image_of(|x, y| match (x, y) {
            (2..14, 2..30) => [0.8, 0.3, 0.2],
            (18..30, 2..30) => [0.2, 0.4, 0.8],
            _ => [0.0; 3],
        });
        let erased = image_of(|x, _| [0.1, 0.1, x as f32 / N as f32]);
        let seam_aware = image_of(|x, y| match (x, y) {
            (16.., 20..28) => [0.9; 3],
            _ => [0.5; 3],
        });
        let seams = SeamSet {
            seams: vec![
                edge([[0.1, 0.25], [0.4, 0.25]], [[0.6, 0.25], [0.9, 0.25]]),
                edge([[0.1, 0.75], [0.4, 0.75]], [[0.6, 0.75], [0.9, 0.75]]),
                edge([[0.5, 0.1], [0.5, 0.4]], [[0.5, 0.6], [0.5, 0.9]]),
            ],
            silhouettes: vec![],
        };
        let grid = TexelGrid {
            width: N,
            height: N,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        };
        Fixture {
            grid,
            input,
            erased,
            seam_aware,
            seams,
        }
    }

    impl Fixture {
        fn picture<'a>(&'a self, closed: &'a [bool]) -> SeamPicture<'a> {
            SeamPicture {
                grid: &self.grid,
                versions: job_versions(&self.input, &self.erased, &self.erased, &self.seam_aware),
                seams: &self.seams,
                closed,
                alpha_closed: None,
            }
        }

        fn draw(&self, closed: &[bool]) -> RgbImage {
            let png = seams_png(&self.picture(closed)).unwrap();
            image::load_from_memory(&png).unwrap().to_rgb8()
        }
    }

    /// The picture pixel at UV `uv` of the overview panel.
    fn panel_px(uv: [f64; 2]) -> (u32, u32) {
        let at = |t: f64| MARGIN + (t * f64::from(PANEL)) as u32;
        (at(uv[0]), at(uv[1]))
    }

    fn is_closed_hue(c: Rgb<u8>) -> bool {
        let [r, g, b] = c.0;
        g > r.saturating_add(60) && b > r.saturating_add(40)
    }

    #[test]
    fn residual_measures_side_disagreement_in_levels() {
        let f = fixture();
        let r: Vec<f64> = f
            .seams
            .seams
            .iter()
            .map(|e| residual(&f.grid, &f.seam_aware, e))
            .collect();
        assert!(r[0].abs() < 1e-9, "{r:?}");
        assert!((r[1] - 0.4 * 255.0).abs() < 1e-3, "{r:?}");
        assert!(r[2] > FULL_BRIGHT_LEVELS, "{r:?}");
        assert_eq!(worst_closed(&[true, true, false], &r), vec![1, 0]);
        // Ties go by edge index.
        assert_eq!(worst_closed(&[true; 3], &[1.0, 2.0, 1.0]), vec![1, 0, 2]);
    }

    #[test]
    fn alpha_left_where_the_colour_closed_has_a_hue_of_its_own() {
        let f = fixture();
        let (closed, alpha) = ([true, true, false], [false, true, false]);
        let p = SeamPicture {
            alpha_closed: Some(&alpha),
            ..f.picture(&closed)
        };
        let img = image::load_from_memory(&seams_png(&p).unwrap())
            .unwrap()
            .to_rgb8();
        let (x, y) = panel_px([0.25, 0.25]);
        let [r, g, b] = img.get_pixel(x, y).0;
        assert!(r > g && g > b && b == 0, "amber: {:?}", [r, g, b]);
        let (x, y) = panel_px([0.25, 0.75]);
        assert!(is_closed_hue(*img.get_pixel(x, y)));
        let short = [true];
        let p = SeamPicture {
            alpha_closed: Some(&short),
            ..f.picture(&closed)
        };
        assert!(matches!(
            seams_png(&p),
            Err(PictureError::ClosedFlags {
                closed: 1,
                seams: 3
            })
        ));
    }

    #[test]
    fn overview_lines_have_class_hue_and_residual_brightness() {
        let f = fixture();
        let img = f.draw(&[true, true, false]);
        let (x, y) = panel_px([0.25, 0.25]);
        let calm = *img.get_pixel(x, y);
        let (x, y) = panel_px([0.25, 0.75]);
        let rough = *img.get_pixel(x, y);
        assert!(
            is_closed_hue(calm) && is_closed_hue(rough),
            "{calm:?} {rough:?}"
        );
        assert!(
            rough.0[1] > calm.0[1] && rough.0[2] > calm.0[2],
            "{calm:?} {rough:?}"
        );
        assert_eq!(rough, edge_colour(CLOSED_HUE, 1e9));
        // Both half-edges are drawn: `b` of the calm edge too.
        let (x, y) = panel_px([0.75, 0.25]);
        assert_eq!(*img.get_pixel(x, y), calm);
        // The left edge is in its own hue, red above green.
        let (x, y) = panel_px([0.5, 0.25]);
        let left = img.get_pixel(x, y).0;
        assert!(left[0] > left[1].saturating_add(100), "{left:?}");
        // Off the lines, the texture shows dimmed: 0.5 / 3 of full.
        let (x, y) = panel_px([0.3, 0.5]);
        assert_eq!(img.get_pixel(x, y).0, [43; 3]);
    }

    #[test]
    fn strip_exists_iff_an_edge_is_closed() {
        let f = fixture();
        let none = f.draw(&[false; 3]);
        // The legend's words are wider than a small panel.
        let legend_w = legend_width(&legend_hues(&f.picture(&[false; 3])));
        assert_eq!(
            none.dimensions(),
            (PANEL.max(legend_w) + 2 * MARGIN, STRIP_TOP)
        );
        let one = f.draw(&[false, false, true]);
        assert_eq!(
            one.dimensions(),
            (strip_width(4) + 2 * MARGIN, ROWS_TOP + TILE_PX + MARGIN)
        );
        let two = f.draw(&[true, true, false]);
        let h = ROWS_TOP + 2 * TILE_PX + ROW_GAP + MARGIN;
        assert_eq!(two.dimensions(), (strip_width(4) + 2 * MARGIN, h));
    }

    #[test]
    fn strip_rows_show_worst_edge_first_at_full_brightness() {
        let f = fixture();
        let img = f.draw(&[true, true, false]);
        // Row 0 is edge 1. Its crops start at texel (0,16) for `a` and
        // (16,16) for `b`; texel (6,6) of the crop is off the line (row 64).
        let texel = |tile: u32| {
            let c = 6 * ZOOM + ZOOM / 2;
            img.get_pixel(MARGIN + tile_x(tile) + c, ROWS_TOP + c).0
        };
        assert_eq!(texel(0), [204, 77, 51], "input, side a: chart A");
        assert_eq!(texel(6), [128; 3], "seam_aware, side a");
        assert_eq!(texel(7), [230; 3], "seam_aware, side b: the bright patch");
        // The half-edge crosses its tile at row (23.5 - 16 + 0.5) · 8 = 64.
        let line = img.get_pixel(MARGIN + tile_x(7) + 60, ROWS_TOP + 64);
        assert_eq!(line.0, CLOSED_HUE);
    }

    /// The pixels of `text` drawn alone, as (x, y) offsets from its corner.
    fn lit(text: &str) -> Vec<(u32, u32)> {
        let mut img = RgbImage::new(text_width(text, TEXT_SCALE) + 1, 20);
        draw_text(&mut img, 0, 0, text, TEXT_SCALE, Rgb(TEXT));
        img.enumerate_pixels()
            .filter(|p| p.2 .0 == TEXT)
            .map(|p| (p.0, p.1))
            .collect()
    }

    fn shows(img: &RgbImage, x: u32, y: u32, text: &str) -> bool {
        lit(text)
            .into_iter()
            .all(|(dx, dy)| img.get_pixel(x + dx, y + dy).0 == TEXT)
    }

    #[test]
    fn words_name_the_columns_the_lines_and_each_jump() {
        let f = fixture();
        let img = f.draw(&[true, true, false]);
        for (v, name) in ["INPUT", "ERASED", "REGULAR BC1", "SEAM-AWARE BC1"]
            .iter()
            .enumerate()
        {
            let x = MARGIN + tile_x(2 * v as u32);
            assert!(shows(&img, x, STRIP_TOP, name), "{name}");
        }
        assert!(!shows(&img, MARGIN + tile_x(2), STRIP_TOP, "INPUT"));
        let legend_x = MARGIN + LEGEND_STEPS * (SWATCH_PX + SWATCH_GAP) + VERSION_GAP;
        let legend_top = MARGIN + PANEL + MARGIN;
        assert!(shows(&img, legend_x, legend_top, "CLOSED"));
        assert!(shows(
            &img,
            legend_x,
            legend_top + SWATCH_PX + SWATCH_GAP,
            "LEFT AS PAINTED"
        ));
        // Row 0 is edge 1: its seam-aware jump is 0.4 × 255 = 102 levels.
        let label_y = ROWS_TOP + TILE_PX - TEXT_SCALE * GLYPH_H - LABEL_PAD;
        let jump = jump_label(residual(&f.grid, &f.seam_aware, &f.seams.seams[1]));
        assert_eq!(jump, "JUMP 102.0");
        assert!(shows(&img, MARGIN + tile_x(6) + LABEL_PAD, label_y, &jump));
        assert!(!shows(&img, MARGIN + tile_x(4) + LABEL_PAD, label_y, &jump));
    }

    #[test]
    fn same_input_same_bytes() {
        let f = fixture();
        let closed = [true, false, true];
        let a = seams_png(&f.picture(&closed)).unwrap();
        let b = seams_png(&f.picture(&closed)).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn inconsistent_inputs_are_errors() {
        let f = fixture();
        let mut p = f.picture(&[true]);
        assert!(matches!(
            seams_png(&p),
            Err(PictureError::ClosedFlags {
                closed: 1,
                seams: 3
            })
        ));
        p.closed = &[true; 3];
        p.versions[2].data = &f.input[..10];
        assert!(matches!(
            seams_png(&p),
            Err(PictureError::BufferSize { ref buffer, len: 10, .. }) if buffer == "REGULAR BC1"
        ));
        p.versions.clear();
        assert!(matches!(seams_png(&p), Err(PictureError::NoVersions)));
    }

    #[test]
    fn panel_shrinks_large_and_enlarges_small_textures() {
        assert_eq!(panel_size(2048, 1024), (1024, 512));
        assert_eq!(panel_size(4096, 4096), (1024, 1024));
        assert_eq!(panel_size(1024, 1024), (1024, 1024));
        assert_eq!(panel_size(128, 128), (512, 512));
        assert_eq!(panel_size(100, 50), (600, 300));
        assert_eq!(panel_size(1, 1), (512, 512));
    }

    #[test]
    fn large_texture_is_box_filtered() {
        // Columns alternating 0 and 1: each panel pixel averages a pair.
        let (w, h) = (2048, 2);
        let data: Vec<f32> = (0..w * h).flat_map(|t| [(t % 2) as f32; 3]).collect();
        let grid = TexelGrid {
            width: w,
            height: h,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        };
        let seams = SeamSet::default();
        let p = SeamPicture {
            grid: &grid,
            versions: job_versions(&data, &data, &data, &data),
            seams: &seams,
            closed: &[],
            alpha_closed: None,
        };
        let img = image::load_from_memory(&seams_png(&p).unwrap())
            .unwrap()
            .to_rgb8();
        assert_eq!(img.width(), 1024 + 2 * MARGIN);
        for x in [0, 1, 500, 1023] {
            let v = img.get_pixel(MARGIN + x, MARGIN).0;
            assert!(v.iter().all(|&c| c == 42 || c == 43), "{x}: {v:?}");
        }
    }

    #[test]
    fn wrap_modes_bring_half_edges_into_the_texture() {
        assert_eq!(period_maps(Wrap::Repeat, 1.2, 1.4), vec![(1.0, -1.0)]);
        assert_eq!(
            period_maps(Wrap::Repeat, 0.9, 1.1),
            vec![(1.0, 0.0), (1.0, -1.0)]
        );
        assert_eq!(
            period_maps(Wrap::MirroredRepeat, 1.2, 1.4),
            vec![(-1.0, 2.0)]
        );
        assert_eq!(period_maps(Wrap::ClampToEdge, 1.2, 1.4), vec![(1.0, 0.0)]);
        assert_eq!(
            period_maps(Wrap::Repeat, -5.0, 50.0).len(),
            MAX_PERIODS as usize
        );
    }

    #[test]
    fn lines_are_clipped() {
        let b = [0.0, 0.0, 10.0, 10.0];
        assert_eq!(
            clip_segment([-5.0, 5.0], [15.0, 5.0], b),
            Some(([0.0, 5.0], [10.0, 5.0]))
        );
        assert_eq!(clip_segment([-5.0, -1.0], [15.0, -1.0], b), None);
        assert_eq!(clip_segment([f64::NAN, 0.0], [1.0, 1.0], b), None);
        let mut img = RgbImage::new(4, 4);
        let r = Rect {
            x: 1,
            y: 1,
            w: 2,
            h: 2,
        };
        draw_line(&mut img, r, [-100.0, 2.5], [100.0, 2.5], Rgb([9; 3]));
        let lit: Vec<(u32, u32)> = img
            .enumerate_pixels()
            .filter(|p| p.2 .0 == [9; 3])
            .map(|p| (p.0, p.1))
            .collect();
        assert_eq!(lit, vec![(1, 2), (2, 2)]);
    }
}
