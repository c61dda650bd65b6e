//! One BC1 block: two RGB565 endpoints and sixteen 2-bit indices, and the
//! decoder every metric in the crate relies on (SPEC §5).

use super::decoder::Decoder;

/// 5-bit channel values expanded to 8 bits by bit replication.
pub(crate) const EXPAND5: [u8; 32] = {
    let mut t = [0u8; 32];
    let mut i = 0;
    while i < 32 {
        t[i] = ((i << 3) | (i >> 2)) as u8;
        i += 1;
    }
    t
};

/// 6-bit channel values expanded to 8 bits by bit replication.
pub(crate) const EXPAND6: [u8; 64] = {
    let mut t = [0u8; 64];
    let mut i = 0;
    while i < 64 {
        t[i] = ((i << 2) | (i >> 4)) as u8;
        i += 1;
    }
    t
};

/// Packs quantised channels (r in 0..32, g in 0..64, b in 0..32) into RGB565.
/// Out-of-range inputs are masked, never a panic.
#[inline]
pub fn pack565(r5: u8, g6: u8, b5: u8) -> u16 {
    (u16::from(r5 & 31) << 11) | (u16::from(g6 & 63) << 5) | u16::from(b5 & 31)
}

/// Splits an RGB565 value into its quantised channels (r5, g6, b5).
#[inline]
pub fn unpack565(c: u16) -> (u8, u8, u8) {
    ((c >> 11) as u8 & 31, (c >> 5) as u8 & 63, c as u8 & 31)
}

/// Expands an RGB565 value to 8-bit RGB by bit replication.
#[inline]
pub fn expand565(c: u16) -> [u8; 3] {
    let (r, g, b) = unpack565(c);
    [
        EXPAND5[r as usize],
        EXPAND6[g as usize],
        EXPAND5[b as usize],
    ]
}

/// One 8-byte BC1 block.
///
/// Index bits: texel k (row-major inside the 4×4 block) sits at bits
/// 2k..2k+1 of `indices`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Block {
    pub c0: u16,
    pub c1: u16,
    pub indices: u32,
}

impl Block {
    /// A block that decodes to one colour everywhere (c0 = c1, all indices 0).
    pub fn solid(c: u16) -> Block {
        Block {
            c0: c,
            c1: c,
            indices: 0,
        }
    }

    /// Little-endian c0, c1, indices: the layout GPUs read.
    pub fn to_bytes(&self) -> [u8; 8] {
        let mut out = [0u8; 8];
        out[0..2].copy_from_slice(&self.c0.to_le_bytes());
        out[2..4].copy_from_slice(&self.c1.to_le_bytes());
        out[4..8].copy_from_slice(&self.indices.to_le_bytes());
        out
    }

    pub fn from_bytes(bytes: [u8; 8]) -> Block {
        Block {
            c0: u16::from_le_bytes([bytes[0], bytes[1]]),
            c1: u16::from_le_bytes([bytes[2], bytes[3]]),
            indices: u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]),
        }
    }

    /// True when the block uses the four-colour palette (c0 > c1).
    pub fn is_four_colour(&self) -> bool {
        self.c0 > self.c1
    }

    /// The 2-bit index of texel `k` (0..16, row-major); `k` is taken mod 16.
    #[inline]
    pub fn index(&self, k: usize) -> u8 {
        ((self.indices >> (2 * (k & 15))) & 3) as u8
    }

    /// The palette on the 0..255 scale, as exact floats: the 1/3 and 1/2
    /// mixes are not rounded to integers.
    ///
    /// c0 > c1: {c0, c1, (2c0+c1)/3, (c0+2c1)/3}; otherwise
    /// {c0, c1, (c0+c1)/2, black}.
    pub fn palette255(&self) -> [[f32; 3]; 4] {
        let a = expand565(self.c0).map(f32::from);
        let b = expand565(self.c1).map(f32::from);
        let mut p = [a, b, [0.0; 3], [0.0; 3]];
        for ch in 0..3 {
            if self.c0 > self.c1 {
                p[2][ch] = (2.0 * a[ch] + b[ch]) / 3.0;
                p[3][ch] = (a[ch] + 2.0 * b[ch]) / 3.0;
            } else {
                p[2][ch] = (a[ch] + b[ch]) / 2.0;
            }
        }
        p
    }

    /// The palette in \[0, 1\]: [`Block::palette255`] divided by 255. This is
    /// the value set that [`Block::decode`] returns.
    pub fn palette(&self) -> [[f32; 3]; 4] {
        self.palette255().map(|c| c.map(|v| v / 255.0))
    }

    /// The palette in \[0, 1\] as `decoder` rounds it.
    pub fn palette_with(&self, decoder: Decoder) -> [[f32; 3]; 4] {
        let (a, b) = (unpack565(self.c0), unpack565(self.c1));
        let (a, b) = ([a.0, a.1, a.2], [b.0, b.1, b.2]);
        let four = self.c0 > self.c1;
        let per: [[f32; 4]; 3] = std::array::from_fn(|ch| decoder.palette(four, ch, a[ch], b[ch]));
        std::array::from_fn(|i| std::array::from_fn(|ch| per[ch][i] / 255.0))
    }

    /// The sixteen texels in \[0, 1\], row-major, as `decoder` decodes them.
    pub fn decode_with(&self, decoder: Decoder) -> [[f32; 3]; 16] {
        let p = self.palette_with(decoder);
        std::array::from_fn(|k| p[self.index(k) as usize])
    }

    /// The sixteen texels in \[0, 1\], row-major.
    pub fn decode(&self) -> [[f32; 3]; 16] {
        let p = self.palette();
        std::array::from_fn(|k| p[self.index(k) as usize])
    }

    /// Weighted squared error of this block against `texels` (both in \[0, 1\]),
    /// Σ w_k·|decoded_k − texel_k|².
    pub fn error(&self, texels: &[[f32; 3]; 16], weights: &[f32; 16]) -> f32 {
        let d = self.decode();
        let mut e = 0.0f32;
        for k in 0..16 {
            let mut s = 0.0;
            for ch in 0..3 {
                let diff = d[k][ch] - texels[k][ch];
                s += diff * diff;
            }
            e += weights[k] * s;
        }
        e
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// xorshift64*: deterministic test data without a dependency.
    pub(crate) struct Rng(u64);
    impl Rng {
        pub(crate) fn new(seed: u64) -> Rng {
            Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
        }
        pub(crate) fn next_u64(&mut self) -> u64 {
            let mut x = self.0;
            x ^= x >> 12;
            x ^= x << 25;
            x ^= x >> 27;
            self.0 = x;
            x.wrapping_mul(0x2545_F491_4F6C_DD1D)
        }
    }

    #[test]
    fn expansion_replicates_bits() {
        assert_eq!(EXPAND5[0], 0);
        assert_eq!(EXPAND5[31], 255);
        assert_eq!(EXPAND5[16], 132);
        assert_eq!(EXPAND6[63], 255);
        assert_eq!(EXPAND6[32], 130);
        assert_eq!(expand565(0xFFFF), [255, 255, 255]);
        assert_eq!(expand565(pack565(1, 2, 3)), [8, 8, 24]);
        assert_eq!(unpack565(pack565(17, 40, 9)), (17, 40, 9));
    }

    #[test]
    fn bytes_round_trip_little_endian() {
        let b = Block {
            c0: 0x1234,
            c1: 0xABCD,
            indices: 0xDEAD_BEEF,
        };
        assert_eq!(
            b.to_bytes(),
            [0x34, 0x12, 0xCD, 0xAB, 0xEF, 0xBE, 0xAD, 0xDE]
        );
        assert_eq!(Block::from_bytes(b.to_bytes()), b);
    }

    #[test]
    fn palette_follows_spec_in_both_modes() {
        let four = Block {
            c0: pack565(31, 63, 31),
            c1: 0,
            indices: 0b11_10_01_00,
        };
        let p = four.palette255();
        assert_eq!(p[0], [255.0; 3]);
        assert_eq!(p[1], [0.0; 3]);
        assert_eq!(p[2], [170.0; 3]);
        assert_eq!(p[3], [85.0; 3]);
        let d = four.decode();
        assert_eq!(d[0], [1.0; 3]);
        assert_eq!(d[1], [0.0; 3]);
        assert_eq!(d[2], [170.0 / 255.0; 3]);
        assert_eq!(d[3], [85.0 / 255.0; 3]);
        assert_eq!(d[4], [1.0; 3]);

        let three = Block {
            c0: pack565(1, 0, 0),
            c1: pack565(2, 0, 0),
            indices: 0b11_10,
        };
        let p = three.palette255();
        assert_eq!(p[2], [(8.0 + 16.0) / 2.0, 0.0, 0.0]);
        assert_eq!(p[3], [0.0; 3]);
        // Thirds are not rounded.
        let odd = Block {
            c0: pack565(1, 0, 0),
            c1: 0,
            indices: 0,
        };
        assert_eq!(odd.palette255()[2][0], 16.0 / 3.0);
    }

    /// Cross-check against an independent decoder on random blocks.
    /// texture2ddecoder expands by bit replication as SPEC §5 does and
    /// truncates the mixes to integers, so it must equal the floor of our
    /// exact palette everywhere.
    #[test]
    fn decode_matches_independent_decoder() {
        let mut rng = Rng::new(7);
        let mut out = [0u32; 16];
        for n in 0..50_000 {
            let v = rng.next_u64();
            let mut block = Block {
                c0: v as u16,
                c1: (v >> 16) as u16,
                indices: (v >> 32) as u32,
            };
            if n % 4 == 0 {
                block.c1 = block.c0;
            }
            texture2ddecoder::decode_bc1_block(&block.to_bytes(), &mut out);
            let pal = block.palette255();
            let ours = block.decode();
            for k in 0..16 {
                let p = pal[block.index(k) as usize];
                let theirs = [(out[k] >> 16) & 255, (out[k] >> 8) & 255, out[k] & 255];
                for ch in 0..3 {
                    assert_eq!(
                        p[ch].floor(),
                        theirs[ch] as f32,
                        "block {block:?} texel {k}"
                    );
                    assert_eq!(ours[k][ch], p[ch] / 255.0);
                }
            }
        }
    }
}
