//! What the DDS keeps of a texture's alpha channel.
//!
//! BC1 is opaque, so a base colour whose materials use alpha must go into
//! another format or lose it:
//! * `MASK` (cut-outs): BC1 with one-bit alpha (`bc1a`): a texel is drawn
//!   or not, and that is all a mask needs. Transparent texels get index 3
//!   of a three-colour block, opaque ones never do, so no texel changes its
//!   opacity class. Erasure leaves alpha alone (closing an alpha seam would
//!   move texels across the cutoff).
//! * `BLEND`, or masks at different cutoffs: BC3 (BC1 colour and an
//!   interpolated alpha block). Alpha is erased as a channel of its own
//!   along the seams erasure closes, and its blocks encoded seam-aware.
//! * `OPAQUE` with alpha below 1 in the image: BC3, alpha kept as it is
//!   (not erased: the material does not use it, some other reader may).
//!
//! `--alpha drop|bc1a|bc3` overrides the choice.
//!
//! BC7 (`--format bc7`) carries alpha in its own blocks: whatever alpha is
//! in use is kept there (`bc7`), erased along the seams where the material
//! blends, as for BC3; `--alpha drop` still drops it.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::Format;
use crate::model::{AlphaUse, Texture, TextureBinding};

/// The `--alpha` option.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlphaOption {
    /// From the materials and the image, as the module docs say.
    #[default]
    Auto,
    /// Opaque BC1 whatever the materials say (reported as a warning when
    /// they use alpha).
    Drop,
    /// BC1 with one-bit alpha at the material's cutoff (0.5 without one).
    Bc1a,
    /// BC3.
    Bc3,
}

/// The format a texture's alpha goes into.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AlphaFormat {
    /// Opaque BC1: the alpha the image holds is not in the DDS.
    Dropped,
    /// BC1 with one-bit alpha: texels under `cutoff` transparent.
    Bc1a,
    /// BC3: interpolated alpha.
    Bc3,
    /// BC7: alpha in the same blocks as the colour.
    Bc7,
}

/// One texture's alpha handling, decided before any work.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlphaPlan {
    pub format: AlphaFormat,
    /// The opacity threshold of `bc1a`, and of the class checks of `MASK`.
    pub cutoff: Option<f32>,
    /// Erasure closes alpha seams too (only where alpha blends).
    pub erase: bool,
    pub material: AlphaUse,
}

/// What to do with `b`'s alpha; `None` when there is none to keep (no
/// alpha channel, or an opaque image under opaque materials).
pub fn plan(b: &TextureBinding, option: AlphaOption, format: Format) -> Option<AlphaPlan> {
    let values = channel(&b.texture)?;
    let below_one = values.iter().any(|&a| a < 1.0);
    let material = b.alpha;
    if material == AlphaUse::Opaque && !below_one {
        return None;
    }
    let mask_cutoff = match material {
        AlphaUse::Mask { cutoff } => Some(cutoff),
        _ => None,
    };
    let bc3 = |erase| AlphaPlan {
        format: AlphaFormat::Bc3,
        cutoff: mask_cutoff,
        erase,
        material,
    };
    let bc1a = |cutoff: f32| AlphaPlan {
        format: AlphaFormat::Bc1a,
        cutoff: Some(cutoff),
        erase: false,
        material,
    };
    let blends = material == AlphaUse::Blend;
    if format == Format::Bc7 && option != AlphaOption::Drop {
        return Some(AlphaPlan {
            format: AlphaFormat::Bc7,
            cutoff: mask_cutoff,
            erase: blends,
            material,
        });
    }
    Some(match option {
        AlphaOption::Drop => AlphaPlan {
            format: AlphaFormat::Dropped,
            cutoff: mask_cutoff,
            erase: false,
            material,
        },
        AlphaOption::Bc1a => bc1a(mask_cutoff.unwrap_or(0.5)),
        AlphaOption::Bc3 => bc3(blends),
        AlphaOption::Auto => match material {
            // A cutoff of 0 draws everything and one over 1 nothing: one
            // bit cannot say which texels sit exactly on such a cutoff.
            AlphaUse::Mask { cutoff } if cutoff > 0.0 && cutoff <= 1.0 => bc1a(cutoff),
            AlphaUse::Mask { .. } | AlphaUse::Opaque => bc3(false),
            AlphaUse::Blend => bc3(true),
        },
    })
}

/// The alpha channel of `t` (grey+alpha or RGBA), one value per texel.
pub fn channel(t: &Texture) -> Option<Vec<f32>> {
    let c = t.channels;
    (c == 2 || c == 4).then(|| t.data.chunks(c).map(|px| px[c - 1]).collect())
}

/// Puts `input`'s alpha back into `solved` (same layout): erasure solves
/// every channel, and alpha that the materials do not blend stays as
/// painted.
pub fn restore(solved: &mut [f32], input: &Texture) {
    let c = input.channels;
    if c != 2 && c != 4 {
        return;
    }
    for (s, i) in solved.chunks_mut(c).zip(input.data.chunks(c)) {
        s[c - 1] = i[c - 1];
    }
}

/// The transparent texels of `bc1a` at `cutoff`.
pub fn transparent(alpha: &[f32], cutoff: f32) -> Vec<bool> {
    alpha.iter().map(|&a| a < cutoff).collect()
}

/// Alpha figures of one version of a texture.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AlphaMetrics {
    /// Length-weighted RMS alpha difference across the seams, 8-bit levels.
    pub seam_rms: Option<f64>,
    /// The same over the seams closed.
    pub seam_rms_closed: Option<f64>,
    /// Alpha PSNR over inside texels against the input's alpha.
    pub psnr: Option<f64>,
    /// The lowest alpha PSNR of any UV chart against the input, and how
    /// many charts fall under 30 dB; absent where no chart's alpha changed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worst_chart_psnr: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub charts_under_30db: Option<usize>,
    /// For encodings: against the erased alpha, the one encoded (the
    /// encoding's own cost).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub encoding_psnr: Option<f64>,
    /// For `MASK` materials: inside texels on the other side of the cutoff
    /// than in the input.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opacity_changes: Option<usize>,
}

/// The report's `alpha`: what was done and how alpha came through.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AlphaReport {
    pub format: AlphaFormat,
    /// How the materials use it.
    pub material: AlphaUse,
    /// Whether erasure closed alpha seams.
    pub erased_seams: bool,
    pub input: AlphaMetrics,
    pub erased: AlphaMetrics,
    /// The regular (not seam-aware) encoding's alpha under each decoder.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub regular: Option<BTreeMap<&'static str, AlphaMetrics>>,
    /// The DDS's alpha under each decoder (mip level 0); absent for
    /// `dropped` and without a DDS.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dds: Option<BTreeMap<&'static str, AlphaMetrics>>,
}

/// Inside texels whose opacity class at `cutoff` differs between `a` and `b`.
pub fn opacity_changes(a: &[f32], b: &[f32], cutoff: f32, inside: &[bool]) -> usize {
    a.iter()
        .zip(b)
        .zip(inside)
        .filter(|((x, y), inside)| **inside && ((**x < cutoff) != (**y < cutoff)))
        .count()
}
