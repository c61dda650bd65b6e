//! BC3's alpha block (the BC4 block): two 8-bit endpoints and sixteen
//! 3-bit indices, and its encoder.
//!
//! A block holds eight values: with a0 > a1, the endpoints and six values
//! between them; otherwise the endpoints, four values between them, 0 and
//! 255 (so a block can span a hard cut-out edge and a soft gradient at
//! once). GPUs round the interpolated values their own way
//! ([`Decoder::alpha_palette`]), so, as for colour, the encoder scores its
//! candidates under every decoder of its [`Target`].

use rayon::prelude::*;

use super::{block_dims, Decoder, Target};

/// One 8-byte alpha block. Texel k (row-major in the 4×4 block) has its
/// index at bits 3k..3k+2 of the 48-bit field after the endpoints.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct AlphaBlock {
    pub a0: u8,
    pub a1: u8,
    pub indices: u64,
}

/// Endpoint candidates span this many levels either side of the block's
/// extremes: the rounding of NVIDIA's and AMD's weights is often better
/// served by an endpoint a level or two off.
const ENDPOINT_RADIUS: i32 = 2;

impl AlphaBlock {
    /// A block that decodes to `v` everywhere under every decoder.
    pub fn solid(v: u8) -> AlphaBlock {
        AlphaBlock {
            a0: v,
            a1: v,
            indices: 0,
        }
    }

    pub fn to_bytes(&self) -> [u8; 8] {
        let mut out = [0u8; 8];
        out[0] = self.a0;
        out[1] = self.a1;
        out[2..8].copy_from_slice(&self.indices.to_le_bytes()[..6]);
        out
    }

    pub fn from_bytes(bytes: [u8; 8]) -> AlphaBlock {
        let mut idx = [0u8; 8];
        idx[..6].copy_from_slice(&bytes[2..8]);
        AlphaBlock {
            a0: bytes[0],
            a1: bytes[1],
            indices: u64::from_le_bytes(idx),
        }
    }

    #[inline]
    pub fn index(&self, k: usize) -> u8 {
        ((self.indices >> (3 * (k & 15))) & 7) as u8
    }

    pub fn with_indices(a0: u8, a1: u8, idx: &[u8; 16]) -> AlphaBlock {
        let indices = idx
            .iter()
            .enumerate()
            .fold(0u64, |acc, (k, &i)| acc | (u64::from(i & 7) << (3 * k)));
        AlphaBlock { a0, a1, indices }
    }

    /// The sixteen alphas in \[0, 1\], row-major, as `decoder` decodes them.
    pub fn decode_with(&self, decoder: Decoder) -> [f32; 16] {
        let p = decoder.alpha_palette(self.a0, self.a1);
        std::array::from_fn(|k| p[self.index(k) as usize] / 255.0)
    }
}

/// Palettes of one endpoint pair under each decoder, 0–255.
fn palettes(a0: u8, a1: u8, decoders: &[Decoder]) -> Vec<[f32; 8]> {
    decoders.iter().map(|d| d.alpha_palette(a0, a1)).collect()
}

/// Each texel's best index under `pal` (mean squared error over the
/// decoders) and the block's weighted error.
fn select(values: &[f32; 16], weights: &[f32; 16], pal: &[[f32; 8]]) -> ([u8; 16], f32) {
    let mut idx = [0u8; 16];
    let mut total = 0.0;
    for k in 0..16 {
        let (mut best, mut best_e) = (0u8, f32::INFINITY);
        for i in 0..8 {
            let e: f32 = pal.iter().map(|p| (p[i] - values[k]).powi(2)).sum();
            if e < best_e {
                (best, best_e) = (i as u8, e);
            }
        }
        idx[k] = best;
        total += weights[k] * best_e;
    }
    (idx, total)
}

/// The block (values 0–255, row-major) that minimises Σ w·(decoded − value)²
/// averaged over `decoders`: both modes, endpoints around the extremes.
pub fn encode_alpha_block(
    values: &[f32; 16],
    weights: &[f32; 16],
    decoders: &[Decoder],
) -> AlphaBlock {
    let q = |v: f32| v.clamp(0.0, 255.0).round() as i32;
    let lo = values.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if q(lo) == q(hi) {
        return AlphaBlock::solid(q(lo) as u8);
    }
    // Six-value mode covers 0 and 255 by itself: its endpoints span the
    // values strictly between.
    let inner: Vec<f32> = values
        .iter()
        .copied()
        .filter(|&v| v > 0.5 && v < 254.5)
        .collect();
    let (ilo, ihi) = inner
        .iter()
        .fold((hi, lo), |(a, b), &v| (a.min(v), b.max(v)));
    let mut best = (AlphaBlock::solid(q(lo) as u8), f32::INFINITY);
    let mut consider = |a0: i32, a1: i32| {
        if !(0..=255).contains(&a0) || !(0..=255).contains(&a1) {
            return;
        }
        let (a0, a1) = (a0 as u8, a1 as u8);
        let (idx, e) = select(values, weights, &palettes(a0, a1, decoders));
        if e < best.1 {
            best = (AlphaBlock::with_indices(a0, a1, &idx), e);
        }
    };
    let r = ENDPOINT_RADIUS;
    for i in -r..=r {
        for j in -r..=r {
            consider(q(hi) + i, q(lo) + j);
            if !inner.is_empty() {
                consider(q(ilo) + i, q(ihi) + j);
            }
        }
    }
    best.0
}

/// Encodes an alpha image (`width`×`height`, one value per texel in
/// \[0, 1\], row-major) for the decoders `target` names; edges that are not
/// a multiple of 4 are padded by repeating the last row and column.
pub fn encode_alpha_image(
    alpha: &[f32],
    width: usize,
    height: usize,
    target: Target,
) -> Vec<AlphaBlock> {
    let (bw, bh) = block_dims(width, height);
    let decoders = target.decoders();
    let mut blocks = vec![AlphaBlock::default(); bw * bh];
    blocks.par_chunks_mut(bw).enumerate().for_each(|(by, row)| {
        for (bx, out) in row.iter_mut().enumerate() {
            let values: [f32; 16] = std::array::from_fn(|k| {
                let x = (bx * 4 + k % 4).min(width - 1);
                let y = (by * 4 + k / 4).min(height - 1);
                alpha[y * width + x] * 255.0
            });
            *out = encode_alpha_block(&values, &[1.0; 16], decoders);
        }
    });
    blocks
}

/// Decodes alpha blocks to one value per texel in \[0, 1\].
pub fn decode_alpha_image(
    blocks: &[AlphaBlock],
    width: usize,
    height: usize,
    decoder: Decoder,
) -> Vec<f32> {
    let bw = block_dims(width, height).0;
    let mut out = vec![0.0f32; width * height];
    for (b, block) in blocks.iter().enumerate() {
        let d = block.decode_with(decoder);
        for (k, v) in d.iter().enumerate() {
            let (x, y) = ((b % bw) * 4 + k % 4, (b / bw) * 4 + k / 4);
            if x < width && y < height {
                out[y * width + x] = *v;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_round_trip() {
        let idx: [u8; 16] = std::array::from_fn(|k| (k * 5 % 8) as u8);
        let b = AlphaBlock::with_indices(200, 13, &idx);
        let back = AlphaBlock::from_bytes(b.to_bytes());
        assert_eq!(back, b);
        assert!((0..16).all(|k| back.index(k) == idx[k]));
    }

    #[test]
    fn solid_and_two_level_blocks_are_exact_under_every_decoder() {
        for d in Decoder::ALL {
            let b = encode_alpha_block(&[77.0; 16], &[1.0; 16], &[d]);
            assert!(b
                .decode_with(d)
                .iter()
                .all(|&v| (v * 255.0 - 77.0).abs() < 1e-4));
            // A cut-out edge with a soft middle: 0, 255 and values between.
            let v: [f32; 16] = std::array::from_fn(|k| [0.0, 255.0, 100.0, 140.0][k % 4]);
            let b = encode_alpha_block(&v, &[1.0; 16], &[d]);
            let got = b.decode_with(d);
            for k in 0..16 {
                let off = (got[k] * 255.0 - v[k]).abs();
                assert!(off <= 1.0, "{d:?} texel {k}: {off}");
            }
        }
    }

    #[test]
    fn gradients_land_within_a_few_levels() {
        let v: [f32; 16] = std::array::from_fn(|k| 40.0 + 9.0 * k as f32);
        for t in [Target::Ideal, Target::Nvidia, Target::Amd, Target::Robust] {
            let b = encode_alpha_block(&v, &[1.0; 16], t.decoders());
            for d in t.decoders() {
                let got = b.decode_with(*d);
                let worst = (0..16)
                    .map(|k| (got[k] * 255.0 - v[k]).abs())
                    .fold(0.0f32, f32::max);
                assert!(worst <= 12.0, "{t:?} {d:?}: {worst}");
            }
        }
    }
}
