//! One mip level of one texture encoded as BC7: the regular encoding, then
//! the seam-aware search from it ([`crate::bc7::seam_aware`]).
//!
//! BC7 decodes exactly, the same on every GPU, so unlike BC1 there is one
//! decoding to keep the seams closed under and one set of figures.

use std::time::Instant;

use super::alpha::{AlphaFormat, AlphaPlan};
use super::level::ErasedLevel;
use super::{PipelineError, ProcessOptions};
use crate::bc1::seam_aware::SeamAwareOptions;
use crate::bc7::seam_aware::{optimise, Problem};
use crate::bc7::{self, EncodeOptions};
use crate::model::{Texture, TextureBinding};
use crate::seam::metric::seam_points_texel_length;

/// A level's BC7 encoding, the one the file holds.
pub(super) struct Bc7Level {
    pub(super) shipped: Vec<bc7::Block>,
    pub(super) encode_ms: u64,
    pub(super) seam_aware_ms: u64,
}

/// Whether the file keeps the level's alpha.
fn keeps_alpha(plan: Option<&AlphaPlan>) -> bool {
    plan.is_some_and(|p| p.format == AlphaFormat::Bc7)
}

/// The level as the encoder takes it: RGBA in 8 bits, grey replicated,
/// alpha opaque unless the file keeps it.
pub(super) fn rgba8(t: &Texture, keep_alpha: bool) -> Vec<u8> {
    let to8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let ch = t.channels;
    t.data
        .chunks(ch)
        .flat_map(|px| {
            let (rgb, a) = match ch {
                1 => ([px[0]; 3], 1.0),
                2 => ([px[0]; 3], px[1]),
                3 => ([px[0], px[1], px[2]], 1.0),
                _ => ([px[0], px[1], px[2]], px[3]),
            };
            let a = if keep_alpha { a } else { 1.0 };
            [to8(rgb[0]), to8(rgb[1]), to8(rgb[2]), to8(a)]
        })
        .collect()
}

/// The regular BC7 encoding of a level.
pub(super) fn encode_regular(
    b: &TextureBinding,
    level: &ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<(Vec<bc7::Block>, u64), PipelineError> {
    let t = Instant::now();
    let (w, h) = (level.grid.width, level.grid.height);
    let rgba = rgba8(&level.stored, keeps_alpha(plan));
    let enc = EncodeOptions::new(opts.bc7_level, keeps_alpha(plan));
    let blocks =
        bc7::encode_image(&rgba, w, h, &enc).map_err(|e| PipelineError::encode(&b.name, e))?;
    Ok((blocks, t.elapsed().as_millis() as u64))
}

/// Encodes a level: regular BC7, then the seam-aware search from it.
pub(super) fn encode_level(
    b: &TextureBinding,
    level: &ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<Bc7Level, PipelineError> {
    let (regular, encode_ms) = encode_regular(b, level, opts, plan)?;
    let (shipped, seam_aware_ms) = encode_seam_aware(b, level, &regular, opts, plan)?;
    Ok(Bc7Level {
        shipped,
        encode_ms,
        seam_aware_ms,
    })
}

/// Decodes BC7 blocks to RGB in \[0, 1\] and, where the file keeps it,
/// alpha.
pub(super) fn decode(
    name: &str,
    blocks: &[bc7::Block],
    width: usize,
    height: usize,
) -> Result<(Vec<f32>, Vec<f32>), PipelineError> {
    let rgba =
        bc7::decode_image(blocks, width, height).map_err(|e| PipelineError::encode(name, e))?;
    let f = |v: u8| f32::from(v) / 255.0;
    let rgb = rgba
        .chunks_exact(4)
        .flat_map(|px| [f(px[0]), f(px[1]), f(px[2])])
        .collect();
    let alpha = rgba.chunks_exact(4).map(|px| f(px[3])).collect();
    Ok((rgb, alpha))
}

/// The seam-aware search from the regular encoding (which it returns as
/// it is when seam-aware encoding is off or no seam is closed). Alpha, where
/// the file keeps it and the material blends, keeps closed the seams closed
/// for it.
pub(super) fn encode_seam_aware(
    b: &TextureBinding,
    level: &ErasedLevel,
    regular: &[bc7::Block],
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<(Vec<bc7::Block>, u64), PipelineError> {
    let t = Instant::now();
    let mut shipped = regular.to_vec();
    if opts.seam_aware && !level.closed.seams.is_empty() {
        let points = seam_points_texel_length(&level.grid, &level.closed);
        let alpha_points = match plan {
            Some(p) if p.format == AlphaFormat::Bc7 && p.erase => Some(
                level
                    .alpha
                    .as_ref()
                    .map(|g| seam_points_texel_length(&level.grid, &g.closed)),
            ),
            _ => None,
        };
        let rgba = rgba_f32(&level.stored, keeps_alpha(plan));
        let rgb: Vec<f32> = rgba
            .chunks_exact(4)
            .flat_map(|px| [px[0], px[1], px[2]])
            .collect();
        let alpha: Option<Vec<f32>> =
            keeps_alpha(plan).then(|| rgba.chunks_exact(4).map(|px| px[3]).collect());
        let problem = Problem {
            width: level.grid.width,
            height: level.grid.height,
            rgb: &rgb,
            alpha: alpha.as_deref(),
            inside: &level.classes.inside,
            points: &points,
            // Alpha erased along its own seams keeps those closed; alpha
            // kept as painted (a mask, or a material that does not blend)
            // is only reproduced.
            alpha_points: Some(
                alpha_points
                    .as_ref()
                    .map_or(&[][..], |own| own.as_deref().unwrap_or(&points)),
            ),
            level: opts.bc7_level,
        };
        let sa_opts = SeamAwareOptions {
            alpha: opts.seam_weight,
            ..SeamAwareOptions::default()
        };
        optimise(&problem, &mut shipped, &sa_opts)
            .map_err(|e| PipelineError::encode(&b.name, e))?
            .log("bc7");
    }
    Ok((shipped, t.elapsed().as_millis() as u64))
}

/// [`rgba8`] in \[0, 1\]: what the seam-aware search measures against.
fn rgba_f32(t: &Texture, keep_alpha: bool) -> Vec<f32> {
    rgba8(t, keep_alpha)
        .into_iter()
        .map(|v| f32::from(v) / 255.0)
        .collect()
}
