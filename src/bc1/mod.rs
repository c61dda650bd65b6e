//! BC1 (DXT1): block encoder at three effort levels, the exact float
//! decoder that every metric uses, and DDS files (SPEC §5).
//!
//! Values are f32 RGB in \[0, 1\] on both sides. The encoder minimises the
//! (optionally weighted) squared RGB error against the exact float palette;
//! opaque output uses four-colour blocks only (c0 > c1, or c0 = c1 with all
//! indices 0 for a solid block).
//!
//! Images are encoded block by block in parallel; each block depends only on
//! its own texels, so the output is the same whatever the thread count.

pub mod alpha;
pub mod alpha_seam_aware;
mod block;
pub mod dds;
pub mod decoder;
mod encode;
mod fast;
pub mod punch;
mod retarget;
pub mod seam_aware;

use std::fmt;
use std::str::FromStr;

use rayon::prelude::*;

pub use block::{expand565, pack565, unpack565, Block};
pub use decoder::{Decoder, Target};

/// Encoder effort. `Default` is the pipeline's default.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Level {
    /// Principal axis and one exact least-squares refit (over 100 MPix/s
    /// on one core).
    Fast,
    /// Adds index moves with refits and a short local endpoint search
    /// (over 10 MPix/s on one core).
    #[default]
    Default,
    /// Adds full cluster fit (two passes) and a long local search.
    Best,
}

impl Level {
    pub const ALL: [Level; 3] = [Level::Fast, Level::Default, Level::Best];

    /// The command-line name: `fast`, `default` or `best`.
    pub fn name(self) -> &'static str {
        match self {
            Level::Fast => "fast",
            Level::Default => "default",
            Level::Best => "best",
        }
    }
}

impl fmt::Display for Level {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown BC1 level {0:?} (expected fast, default or best)")]
pub struct ParseLevelError(pub String);

impl FromStr for Level {
    type Err = ParseLevelError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "fast" => Ok(Level::Fast),
            "default" => Ok(Level::Default),
            "best" => Ok(Level::Best),
            _ => Err(ParseLevelError(s.to_string())),
        }
    }
}

/// Why an image could not be encoded or decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Bc1Error {
    #[error("image is empty ({width}x{height})")]
    Empty { width: usize, height: usize },
    #[error("{channels} channels per texel; BC1 needs at least 3")]
    TooFewChannels { channels: usize },
    #[error("buffer holds {got} values, a {width}x{height} image needs {need}")]
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
    (width.div_ceil(4).max(1), height.div_ceil(4).max(1))
}

/// Texel index of slot `k` (row-major, 0–15) of block `b` of a `width`-wide
/// image `bw` blocks across, or `None` where the slot is padding past the
/// image.
#[inline]
pub fn block_texel(
    (width, height): (usize, usize),
    bw: usize,
    b: usize,
    k: usize,
) -> Option<usize> {
    let (x, y) = ((b % bw) * 4 + k % 4, (b / bw) * 4 + k / 4);
    (x < width && y < height).then(|| y * width + x)
}

/// Encodes one block of texels (row-major, RGB in \[0, 1\]; values outside
/// are clamped, NaN counts as 0).
pub fn encode_block(texels: &[[f32; 3]; 16], level: Level) -> Block {
    encode_block_weighted(texels, &[1.0; 16], level)
}

/// Like [`encode_block`], minimising Σ w_k·|decoded_k − texel_k|².
/// Negative or non-finite weights count as 0; if every weight is 0 the
/// texels are weighted equally.
pub fn encode_block_weighted(texels: &[[f32; 3]; 16], weights: &[f32; 16], level: Level) -> Block {
    let t = encode::Texels::from_rgb(texels, weights);
    encode::encode_one(&t, &encode::effort(level))
}

/// Encodes an image of `width`×`height` texels stored row-major with
/// `stride_channels` f32 values per texel, of which the first three are
/// RGB in \[0, 1\]. Edges that are not a multiple of 4 are padded by
/// replicating the last row and column. Blocks are returned row-major.
pub fn encode_image(
    rgb: &[f32],
    width: usize,
    height: usize,
    stride_channels: usize,
    level: Level,
) -> Result<Vec<Block>, Bc1Error> {
    if width == 0 || height == 0 {
        return Err(Bc1Error::Empty { width, height });
    }
    if stride_channels < 3 {
        return Err(Bc1Error::TooFewChannels {
            channels: stride_channels,
        });
    }
    let need = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(stride_channels))
        .unwrap_or(usize::MAX);
    if rgb.len() < need {
        return Err(Bc1Error::BufferSize {
            width,
            height,
            need,
            got: rgb.len(),
        });
    }
    let (bw, bh) = block_dims(width, height);
    let effort = encode::effort(level);
    let mut blocks = vec![Block::default(); bw * bh];
    blocks.par_chunks_mut(bw).enumerate().for_each(|(by, row)| {
        encode::encode_row(rgb, width, height, stride_channels, by, row, &effort);
    });
    Ok(blocks)
}

/// [`encode_image`], then each block fitted to the palettes of the
/// decoders `target` names (see `retarget.rs`): under NVIDIA's or AMD's
/// rounding the float palette's best block is a few levels off.
pub fn encode_image_for(
    rgb: &[f32],
    width: usize,
    height: usize,
    stride_channels: usize,
    level: Level,
    target: Target,
) -> Result<Vec<Block>, Bc1Error> {
    let mut blocks = encode_image(rgb, width, height, stride_channels, level)?;
    retarget::retarget(&mut blocks, rgb, width, height, stride_channels, target);
    Ok(blocks)
}

/// Decodes row-major blocks to an RGB image of `width`×`height` texels
/// (3 f32 per texel in \[0, 1\], padding dropped) with the float palette.
pub fn decode_image(blocks: &[Block], width: usize, height: usize) -> Result<Vec<f32>, Bc1Error> {
    decode_image_with(blocks, width, height, Decoder::Ideal)
}

/// [`decode_image`] as `decoder` rounds the palette.
pub fn decode_image_with(
    blocks: &[Block],
    width: usize,
    height: usize,
    decoder: Decoder,
) -> Result<Vec<f32>, Bc1Error> {
    if width == 0 || height == 0 {
        return Err(Bc1Error::Empty { width, height });
    }
    let (bw, bh) = block_dims(width, height);
    if blocks.len() != bw * bh {
        return Err(Bc1Error::BlockCount {
            width,
            height,
            need: bw * bh,
            got: blocks.len(),
        });
    }
    let mut out = vec![0.0f32; width * height * 3];
    out.par_chunks_mut(width * 3 * 4)
        .zip(blocks.par_chunks(bw))
        .for_each(|(rows, brow)| {
            let rows_here = rows.len() / (width * 3);
            for (bx, b) in brow.iter().enumerate() {
                let d = b.decode_with(decoder);
                for j in 0..rows_here {
                    for i in 0..4 {
                        let x = bx * 4 + i;
                        if x >= width {
                            break;
                        }
                        let o = (j * width + x) * 3;
                        rows[o..o + 3].copy_from_slice(&d[j * 4 + i]);
                    }
                }
            }
        });
    Ok(out)
}

/// RGB PSNR in dB of `decoded` against `reference`, both RGB f32 images of
/// the same size (3 values per texel, in \[0, 1\]): 10·log10(1/MSE).
/// Infinite when they are equal; `None` when the sizes differ or are empty.
pub fn psnr(reference: &[f32], decoded: &[f32]) -> Option<f64> {
    if reference.len() != decoded.len() || reference.is_empty() {
        return None;
    }
    let se: f64 = reference
        .iter()
        .zip(decoded)
        .map(|(&a, &b)| {
            let d = f64::from(a) - f64::from(b);
            d * d
        })
        .sum();
    let mse = se / reference.len() as f64;
    Some(if mse > 0.0 {
        10.0 * (1.0 / mse).log10()
    } else {
        f64::INFINITY
    })
}

#[cfg(test)]
mod tests {
    use super::block::tests::Rng;
    use super::*;

    fn random_block(rng: &mut Rng, spread: u64) -> [[f32; 3]; 16] {
        let base: [u64; 3] = std::array::from_fn(|_| rng.next_u64() % (256 - spread));
        std::array::from_fn(|_| {
            std::array::from_fn(|ch| (base[ch] + rng.next_u64() % (spread + 1)) as f32 / 255.0)
        })
    }

    fn check_four_colour(b: &Block) {
        assert!(
            b.c0 > b.c1 || (b.c0 == b.c1 && b.indices == 0),
            "not a four-colour block: {b:?}"
        );
    }

    #[test]
    fn level_names_parse() {
        for l in Level::ALL {
            assert_eq!(l.name().parse::<Level>(), Ok(l));
            assert_eq!(l.to_string(), l.name());
        }
        assert_eq!("BEST".parse::<Level>(), Ok(Level::Best));
        assert!("medium".parse::<Level>().is_err());
        assert_eq!(Level::default(), Level::Default);
    }

    #[test]
    fn blocks_are_four_colour_and_levels_improve() {
        let mut rng = Rng::new(11);
        let mut totals = [0.0f64; 3];
        for n in 0..400 {
            let spread = [0, 1, 3, 8, 30, 120, 255][n % 7];
            let tx = random_block(&mut rng, spread);
            let mut errs = [0.0f32; 3];
            for (li, l) in Level::ALL.into_iter().enumerate() {
                let b = encode_block(&tx, l);
                check_four_colour(&b);
                errs[li] = b.error(&tx, &[1.0; 16]);
                totals[li] += f64::from(errs[li]);
            }
            // Best starts from default's result and only keeps improvements
            // (up to float rounding between equal-error candidates).
            assert!(errs[2] <= errs[1] * (1.0 + 1e-4), "{errs:?}");
            assert!(errs[1] <= errs[0] * (1.0 + 1e-4), "{errs:?}");
        }
        assert!(totals[1] < totals[0], "{totals:?}");
        assert!(totals[2] < totals[1], "{totals:?}");
    }

    #[test]
    fn solid_blocks_hit_the_best_single_colour() {
        for v in 0..=255u32 {
            let c = [
                v as f32 / 255.0,
                (255 - v) as f32 / 255.0,
                (v * 7 % 256) as f32 / 255.0,
            ];
            let tx = [c; 16];
            for l in Level::ALL {
                let b = encode_block(&tx, l);
                check_four_colour(&b);
                let d = b.decode();
                assert!(d.iter().all(|t| *t == d[0]));
                // A 1/3 mix of 5-bit levels lands within 1.5 levels of any
                // 8-bit value.
                for ch in 0..3 {
                    assert!((d[0][ch] - c[ch]).abs() * 255.0 <= 1.5, "{v} {l} {d:?}");
                }
            }
        }
        // Exact 565 colours come back exactly.
        let tx = [[
            expand565(0x7BEF)[0] as f32 / 255.0,
            expand565(0x7BEF)[1] as f32 / 255.0,
            expand565(0x7BEF)[2] as f32 / 255.0,
        ]; 16];
        assert_eq!(encode_block(&tx, Level::Fast).error(&tx, &[1.0; 16]), 0.0);
    }

    #[test]
    fn two_exact_colours_are_lossless() {
        let a = expand565(pack565(20, 40, 5)).map(|v| v as f32 / 255.0);
        let b = expand565(pack565(3, 9, 30)).map(|v| v as f32 / 255.0);
        let tx: [[f32; 3]; 16] = std::array::from_fn(|k| if k % 3 == 0 { a } else { b });
        for l in Level::ALL {
            let blk = encode_block(&tx, l);
            check_four_colour(&blk);
            assert!(blk.error(&tx, &[1.0; 16]) < 1e-10, "{l}");
        }
    }

    #[test]
    fn weights_steer_the_fit() {
        let mut rng = Rng::new(21);
        let mut better = 0;
        for _ in 0..200 {
            let tx = random_block(&mut rng, 200);
            let mut w = [0.05f32; 16];
            w[..4].fill(10.0);
            let plain = encode_block(&tx, Level::Default);
            let weighted = encode_block_weighted(&tx, &w, Level::Default);
            check_four_colour(&weighted);
            if weighted.error(&tx, &w) <= plain.error(&tx, &w) {
                better += 1;
            }
        }
        assert!(better >= 190, "{better}");
        // Degenerate weights and values never panic.
        let tx = random_block(&mut rng, 100);
        let mut odd = [1.0f32; 16];
        odd[3] = f32::NAN;
        odd[4] = -1.0;
        odd[5] = f32::INFINITY;
        let mut sparse = [0.0f32; 16];
        sparse[7] = 2.0;
        let mut bad = tx;
        bad[0] = [f32::NAN, -3.0, 7.0];
        bad[1] = [f32::INFINITY, f32::NEG_INFINITY, 0.5];
        for l in Level::ALL {
            for w in [[0.0; 16], odd, sparse] {
                check_four_colour(&encode_block_weighted(&tx, &w, l));
            }
            check_four_colour(&encode_block(&bad, l));
            // Zero weights count as no weights at all.
            assert_eq!(
                encode_block_weighted(&tx, &[0.0; 16], l),
                encode_block(&tx, l)
            );
        }
        // One texel that matters is hit exactly when it is a 565 colour.
        let c = expand565(pack565(9, 50, 21)).map(|v| v as f32 / 255.0);
        let mut one = tx;
        one[7] = c;
        for l in Level::ALL {
            let b = encode_block_weighted(&one, &sparse, l);
            assert!(b.error(&one, &sparse) < 1e-10, "{l}");
        }
    }

    fn gradient(w: usize, h: usize, ch: usize) -> Vec<f32> {
        let mut img = vec![0.0f32; w * h * ch];
        for y in 0..h {
            for x in 0..w {
                let o = (y * w + x) * ch;
                // Colours along a line, plus a little texture.
                let t = (x + 2 * y) as f32 / (w + 2 * h) as f32;
                img[o] = t;
                img[o + 1] = 0.2 + 0.5 * t;
                img[o + 2] = 1.0 - t + ((x * 7 + y * 13) % 5) as f32 / 255.0;
                if ch > 3 {
                    img[o + 3] = 0.5;
                }
            }
        }
        img
    }

    #[test]
    fn image_round_trip_with_padding() {
        for (w, h) in [(1, 1), (3, 5), (4, 4), (13, 6), (211, 9)] {
            let img = gradient(w, h, 4);
            let blocks = encode_image(&img, w, h, 4, Level::Default).unwrap();
            assert_eq!(blocks.len(), w.div_ceil(4) * h.div_ceil(4));
            let dec = decode_image(&blocks, w, h).unwrap();
            assert_eq!(dec.len(), w * h * 3);
            let rgb: Vec<f32> = img.chunks(4).flat_map(|t| t[..3].to_vec()).collect();
            let p = psnr(&rgb, &dec).unwrap();
            assert!(p > 25.0, "{w}x{h}: {p}");
            // Padding replicates edges: the padded block equals the block
            // encoded from an explicitly padded copy.
            let (bw, bh) = block_dims(w, h);
            let mut padded = vec![0.0f32; bw * 4 * bh * 4 * 3];
            for y in 0..bh * 4 {
                for x in 0..bw * 4 {
                    let s = (y.min(h - 1) * w + x.min(w - 1)) * 4;
                    let d = (y * bw * 4 + x) * 3;
                    padded[d..d + 3].copy_from_slice(&img[s..s + 3]);
                }
            }
            let again = encode_image(&padded, bw * 4, bh * 4, 3, Level::Default).unwrap();
            assert_eq!(again, blocks);
        }
    }

    #[test]
    fn any_texel_stride_gives_the_same_blocks() {
        let (w, h) = (37, 10);
        let rgb = gradient(w, h, 3);
        for l in Level::ALL {
            let base = encode_image(&rgb, w, h, 3, l).unwrap();
            for stride in [4, 5] {
                let mut wide = vec![0.25f32; w * h * stride];
                for t in 0..w * h {
                    wide[t * stride..t * stride + 3].copy_from_slice(&rgb[t * 3..t * 3 + 3]);
                }
                assert_eq!(
                    encode_image(&wide, w, h, stride, l).unwrap(),
                    base,
                    "{l} {stride}"
                );
            }
        }
    }

    #[test]
    fn image_output_independent_of_threads() {
        let (w, h) = (64, 48);
        let img = gradient(w, h, 3);
        for l in Level::ALL {
            let one = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .unwrap()
                .install(|| encode_image(&img, w, h, 3, l).unwrap());
            let many = rayon::ThreadPoolBuilder::new()
                .num_threads(3)
                .build()
                .unwrap()
                .install(|| encode_image(&img, w, h, 3, l).unwrap());
            assert_eq!(one, many);
        }
    }

    /// A block's encoding does not depend on its neighbours, on how it was
    /// batched, or on whether it came through the image or the block API.
    #[test]
    fn image_blocks_equal_single_block_encodes() {
        let (w, h) = (75, 9);
        let mut rng = Rng::new(99);
        let mut img = gradient(w, h, 3);
        for v in img.iter_mut().step_by(7) {
            *v = (rng.next_u64() % 256) as f32 / 255.0;
        }
        let (bw, _) = block_dims(w, h);
        for l in Level::ALL {
            let blocks = encode_image(&img, w, h, 3, l).unwrap();
            for (n, b) in blocks.iter().enumerate() {
                let (bx, by) = (n % bw, n / bw);
                let tx: [[f32; 3]; 16] = std::array::from_fn(|k| {
                    let x = (bx * 4 + k % 4).min(w - 1);
                    let y = (by * 4 + k / 4).min(h - 1);
                    let o = (y * w + x) * 3;
                    [img[o], img[o + 1], img[o + 2]]
                });
                assert_eq!(*b, encode_block(&tx, l), "{l} block {n}");
            }
        }
    }

    #[test]
    fn bad_image_arguments_are_errors() {
        let img = vec![0.5f32; 30];
        assert!(matches!(
            encode_image(&img, 0, 4, 3, Level::Fast),
            Err(Bc1Error::Empty { .. })
        ));
        assert!(matches!(
            encode_image(&img, 4, 4, 2, Level::Fast),
            Err(Bc1Error::TooFewChannels { .. })
        ));
        assert!(matches!(
            encode_image(&img, 4, 4, 3, Level::Fast),
            Err(Bc1Error::BufferSize { .. })
        ));
        assert!(matches!(
            encode_image(&img, usize::MAX, 4, 3, Level::Fast),
            Err(Bc1Error::BufferSize { .. })
        ));
        assert!(matches!(
            decode_image(&[Block::default(); 3], 8, 8),
            Err(Bc1Error::BlockCount { .. })
        ));
        assert!(psnr(&[0.0], &[0.0, 1.0]).is_none());
    }
}
