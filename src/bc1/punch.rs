//! BC1 with one-bit alpha ("punch-through", for `MASK` materials).
//!
//! A block in three-colour mode (c0 ≤ c1) decodes index 3 as transparent
//! black on every GPU; its opaque texels share the two endpoints and their
//! mean. So a block that holds a transparent texel is re-encoded in that
//! mode with index 3 on exactly its transparent texels, and every other
//! block stays in four-colour mode, which has no transparent entry: no
//! texel changes its opacity class, whatever the colour search does.

use rayon::prelude::*;

use super::{block_dims, encode_block_weighted, pack565, unpack565, Block, Decoder, Level, Target};

/// Rounds of ±1 steps on the endpoint fields before the search stops.
const SEARCH_ROUNDS: usize = 24;

/// Re-encodes every block of `blocks` (row-major, `width`×`height` texels)
/// that holds a texel marked in `transparent`, in three-colour mode, for
/// the decoders of `target`. `rgb` is 3 values per texel in \[0, 1\].
pub fn punch_through(
    blocks: &mut [Block],
    rgb: &[f32],
    transparent: &[bool],
    width: usize,
    height: usize,
    target: Target,
) {
    let bw = block_dims(width, height).0;
    let decoders = target.decoders();
    blocks.par_iter_mut().enumerate().for_each(|(b, block)| {
        let at = |k: usize| {
            let x = ((b % bw) * 4 + k % 4).min(width - 1);
            let y = ((b / bw) * 4 + k / 4).min(height - 1);
            y * width + x
        };
        let clear: [bool; 16] = std::array::from_fn(|k| transparent[at(k)]);
        if !clear.iter().any(|&c| c) {
            return;
        }
        let texels: [[f32; 3]; 16] =
            std::array::from_fn(|k| std::array::from_fn(|c| rgb[at(k) * 3 + c]));
        *block = encode_punch_block(&texels, &clear, decoders);
    });
}

/// A three-colour block: index 3 on the `clear` texels, the best of
/// entries 0–2 (mean squared error over `decoders`) on the others.
pub fn encode_punch_block(
    texels: &[[f32; 3]; 16],
    clear: &[bool; 16],
    decoders: &[Decoder],
) -> Block {
    if clear.iter().all(|&c| c) {
        return Block {
            c0: 0,
            c1: 0,
            indices: u32::MAX,
        };
    }
    let weights: [f32; 16] = std::array::from_fn(|k| if clear[k] { 0.0 } else { 1.0 });
    let start = encode_block_weighted(texels, &weights, Level::Default);
    let fields = |c: u16| {
        let (r, g, b) = unpack565(c);
        [i32::from(r), i32::from(g), i32::from(b)]
    };
    let mut q = [fields(start.c0), fields(start.c1)];
    let mut best = evaluate(q, texels, clear, decoders);
    for _ in 0..SEARCH_ROUNDS {
        let mut improved = false;
        for e in 0..2 {
            for ch in 0..3 {
                let top = if ch == 1 { 63 } else { 31 };
                for step in [-1, 1] {
                    let mut c = q;
                    c[e][ch] += step;
                    if !(0..=top).contains(&c[e][ch]) {
                        continue;
                    }
                    let got = evaluate(c, texels, clear, decoders);
                    if got.1 < best.1 {
                        (q, best, improved) = (c, got, true);
                    }
                }
            }
        }
        if !improved {
            break;
        }
    }
    best.0
}

/// The three-colour block of endpoint fields `q`, and its error.
fn evaluate(
    q: [[i32; 3]; 2],
    texels: &[[f32; 3]; 16],
    clear: &[bool; 16],
    decoders: &[Decoder],
) -> (Block, f32) {
    let pack = |f: [i32; 3]| pack565(f[0] as u8, f[1] as u8, f[2] as u8);
    let (a, b) = (pack(q[0]), pack(q[1]));
    let mut block = Block {
        c0: a.min(b),
        c1: a.max(b),
        indices: 0,
    };
    let pals: Vec<[[f32; 3]; 4]> = decoders.iter().map(|d| block.palette_with(*d)).collect();
    let mut total = 0.0;
    for k in 0..16 {
        let i = if clear[k] {
            3
        } else {
            let err = |i: usize| -> f32 {
                pals.iter()
                    .map(|p| {
                        (0..3)
                            .map(|c| (p[i][c] - texels[k][c]).powi(2))
                            .sum::<f32>()
                    })
                    .sum()
            };
            let i = (0..3)
                .min_by(|&x, &y| err(x).total_cmp(&err(y)))
                .unwrap_or(0);
            total += err(i);
            i
        };
        block.indices |= (i as u32) << (2 * k);
    }
    (block, total)
}

/// Each texel's alpha (0 or 1) as BC1 decodes it: 0 exactly on index 3 of
/// a three-colour block.
pub fn punch_alpha(blocks: &[Block], width: usize, height: usize) -> Vec<f32> {
    let bw = block_dims(width, height).0;
    let mut out = vec![1.0f32; width * height];
    for (y, row) in out.chunks_mut(width).enumerate() {
        for (x, a) in row.iter_mut().enumerate() {
            let b = &blocks[(y / 4) * bw + x / 4];
            if !b.is_four_colour() && b.index((y % 4) * 4 + x % 4) == 3 {
                *a = 0.0;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transparent_texels_and_only_they_decode_transparent() {
        let texels: [[f32; 3]; 16] =
            std::array::from_fn(|k| [k as f32 / 15.0, 0.5, 1.0 - k as f32 / 15.0]);
        let clear: [bool; 16] = std::array::from_fn(|k| k % 3 == 0);
        for t in [Target::Ideal, Target::Robust] {
            let mut blocks = [Block::default(); 4];
            let rgb: Vec<f32> = (0..64).flat_map(|k| texels[k % 16]).collect();
            // Transparent texels in the top two rows only: two blocks of
            // four punch through.
            let mask: Vec<bool> = (0..64).map(|k| clear[k % 16] && k < 16).collect();
            punch_through(&mut blocks, &rgb, &mask, 8, 8, t);
            let alpha = punch_alpha(&blocks, 8, 8);
            for (k, a) in alpha.iter().enumerate() {
                assert_eq!(*a == 0.0, mask[k], "{t:?} texel {k}");
            }
            // Opaque texels stay near their colour.
            let b = encode_punch_block(&texels, &clear, t.decoders());
            let d = b.decode_with(Decoder::Ideal);
            for k in (0..16).filter(|&k| !clear[k]) {
                let off = (0..3)
                    .map(|c| (d[k][c] - texels[k][c]).abs())
                    .fold(0.0, f32::max);
                assert!(off < 0.2, "{t:?} texel {k}: {off}");
            }
        }
    }
}
