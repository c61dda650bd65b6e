//! BC7 (BPTC UNORM): our block encoder at three effort levels and a
//! decoder bit-exact to the specification (Khronos Data Format
//! Specification 1.3, section 20.3; Microsoft, "BC7 Format", Direct3D 11).
//!
//! Texels are RGBA u8 on both sides. The encoder minimises the weighted
//! squared 8-bit error over every mode (0–7) with its partitions, p-bits,
//! rotations and index selections; the weight of alpha is 0 for a texture
//! whose alpha does not matter, which frees the encoder to spend every bit
//! on colour (alpha then decodes to 255 wherever the mode allows it, and
//! never below 251).
//!
//! Images are encoded block by block in parallel; each block depends only on
//! its own texels, so the output is the same whatever the thread count.

mod bits;
mod encode;
mod estimate;
mod fit;
mod modes;
mod params;
mod partitions;
pub mod seam_aware;
mod seam_block;
mod solid;

use rayon::prelude::*;

pub use crate::bc1::Level;
pub use params::Params;

/// One 16-byte BC7 block, as stored in a file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Block(pub [u8; 16]);

impl Block {
    /// The 16 texels (row-major RGBA) the block decodes to. The reserved
    /// mode (first byte 0) decodes to transparent black, as Direct3D does.
    pub fn decode(&self) -> [[u8; 4]; 16] {
        Params::unpack(&self.0).map_or([[0; 4]; 16], |p| p.decode())
    }

    /// The block's fields, or `None` for the reserved mode.
    pub fn params(&self) -> Option<Params> {
        Params::unpack(&self.0)
    }

    pub fn from_params(p: &Params) -> Block {
        Block(p.pack())
    }

    /// The block's mode (0–7), or `None` for the reserved mode.
    pub fn mode(&self) -> Option<u8> {
        (self.0[0] != 0).then(|| self.0[0].trailing_zeros() as u8)
    }
}

/// How to encode: effort, and the error weight of each channel (RGBA).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EncodeOptions {
    pub level: Level,
    /// Squared-error weight per channel; alpha's is 0 when alpha does not
    /// matter. Negative or non-finite weights count as 0.
    pub weights: [f32; 4],
}

impl EncodeOptions {
    /// Equal weights, with alpha's 0 unless `alpha_matters`.
    pub fn new(level: Level, alpha_matters: bool) -> Self {
        EncodeOptions {
            level,
            weights: [1.0, 1.0, 1.0, if alpha_matters { 1.0 } else { 0.0 }],
        }
    }

    /// Weights alpha only when some texel of `rgba` is not opaque.
    pub fn for_image(level: Level, rgba: &[u8]) -> Self {
        EncodeOptions::new(level, has_alpha(rgba))
    }
}

/// Whether some texel of an RGBA u8 image has alpha below 255.
pub fn has_alpha(rgba: &[u8]) -> bool {
    rgba.chunks_exact(4).any(|t| t[3] != 255)
}

/// Why an image could not be encoded or decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Bc7Error {
    #[error("image is empty ({width}x{height})")]
    Empty { width: usize, height: usize },
    #[error("buffer holds {got} bytes, a {width}x{height} RGBA image needs {need}")]
    BufferSize {
        width: usize,
        height: usize,
        need: usize,
        got: usize,
    },
    #[error("{got} blocks given, a {width}x{height} image needs {need}")]
    BlockCount {
        width: usize,
        height: usize,
        need: usize,
        got: usize,
    },
}

/// Blocks across and down for an image: max(1, ⌈w/4⌉) × max(1, ⌈h/4⌉).
pub fn block_dims(width: usize, height: usize) -> (usize, usize) {
    crate::bc1::block_dims(width, height)
}

/// Encodes one block of texels (row-major RGBA).
pub fn encode_block(texels: &[[u8; 4]; 16], opts: &EncodeOptions) -> Block {
    let t = encode::Texels::new(texels, &opts.weights);
    Block(encode::encode_block(&t, &encode::effort(opts.level)).pack())
}

fn check_rgba(len: usize, width: usize, height: usize) -> Result<(), Bc7Error> {
    if width == 0 || height == 0 {
        return Err(Bc7Error::Empty { width, height });
    }
    let need = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(4))
        .unwrap_or(usize::MAX);
    if len < need {
        return Err(Bc7Error::BufferSize {
            width,
            height,
            need,
            got: len,
        });
    }
    Ok(())
}

/// The texels of block (`bx`, `by`) of an RGBA u8 image, edges replicated
/// past the image.
pub fn block_texels(
    rgba: &[u8],
    width: usize,
    height: usize,
    bx: usize,
    by: usize,
) -> [[u8; 4]; 16] {
    std::array::from_fn(|k| {
        let x = (bx * 4 + k % 4).min(width - 1);
        let y = (by * 4 + k / 4).min(height - 1);
        let o = (y * width + x) * 4;
        [rgba[o], rgba[o + 1], rgba[o + 2], rgba[o + 3]]
    })
}

/// Encodes an RGBA u8 image (row-major, 4 bytes per texel). Edges that are
/// not a multiple of 4 are padded by replicating the last row and column.
/// Blocks are returned row-major.
pub fn encode_image(
    rgba: &[u8],
    width: usize,
    height: usize,
    opts: &EncodeOptions,
) -> Result<Vec<Block>, Bc7Error> {
    check_rgba(rgba.len(), width, height)?;
    let (bw, bh) = block_dims(width, height);
    let effort = encode::effort(opts.level);
    let mut blocks = vec![Block::default(); bw * bh];
    blocks.par_chunks_mut(bw).enumerate().for_each(|(by, row)| {
        for (bx, b) in row.iter_mut().enumerate() {
            let t = encode::Texels::new(&block_texels(rgba, width, height, bx, by), &opts.weights);
            *b = Block(encode::encode_block(&t, &effort).pack());
        }
    });
    Ok(blocks)
}

/// Decodes row-major blocks to an RGBA u8 image of `width`×`height`
/// texels (padding dropped).
pub fn decode_image(blocks: &[Block], width: usize, height: usize) -> Result<Vec<u8>, Bc7Error> {
    if width == 0 || height == 0 {
        return Err(Bc7Error::Empty { width, height });
    }
    let (bw, bh) = block_dims(width, height);
    if blocks.len() != bw * bh {
        return Err(Bc7Error::BlockCount {
            width,
            height,
            need: bw * bh,
            got: blocks.len(),
        });
    }
    let mut out = vec![0u8; width * height * 4];
    out.par_chunks_mut(width * 4 * 4)
        .zip(blocks.par_chunks(bw))
        .for_each(|(rows, brow)| {
            let rows_here = rows.len() / (width * 4);
            for (bx, b) in brow.iter().enumerate() {
                let d = b.decode();
                for j in 0..rows_here {
                    for i in 0..4 {
                        let x = bx * 4 + i;
                        if x < width {
                            let o = (j * width + x) * 4;
                            rows[o..o + 4].copy_from_slice(&d[j * 4 + i]);
                        }
                    }
                }
            }
        });
    Ok(out)
}

/// PSNR in dB over the channels `channels` (e.g. `0..3` for RGB) of two
/// RGBA u8 images of the same size: 10·log10(255²/MSE). Infinite when
/// they agree; `None` when the sizes differ or are empty.
pub fn psnr(reference: &[u8], decoded: &[u8], channels: std::ops::Range<usize>) -> Option<f64> {
    if reference.len() != decoded.len() || reference.is_empty() || channels.is_empty() {
        return None;
    }
    let mut se = 0.0f64;
    let mut n = 0usize;
    for (a, b) in reference.chunks_exact(4).zip(decoded.chunks_exact(4)) {
        for c in channels.clone() {
            let d = f64::from(a[c]) - f64::from(b[c]);
            se += d * d;
            n += 1;
        }
    }
    let mse = se / n as f64;
    Some(if mse > 0.0 {
        10.0 * (255.0 * 255.0 / mse).log10()
    } else {
        f64::INFINITY
    })
}
