//! BC1 decoders as GPUs implement them.
//!
//! BC1 fixes how endpoints expand (565 → 888 by bit replication) but not how
//! the two interpolated palette entries are rounded. The float palette of
//! SPEC §5 (`ideal`) is what the metric has always assumed; NVIDIA's texture
//! units round with integer formulas (measured on an H200: every line of
//! `../shared/decoders/nvidia_bc1_table.txt` is reproduced below, and in
//! four-colour mode green lands up to 5.3 levels off the float palette);
//! AMD's use other formulas again (published with rgbcx, not measured here).
//! A seam tuned to a fraction of a level under one decoder can open by whole
//! levels under another, so the seam-aware encoder scores its candidates
//! under the decoders it targets.
//!
//! The decode is per channel: a palette entry of one channel depends only on
//! that channel's two endpoint fields and on the block's mode.

use serde::{Deserialize, Serialize};

/// How the interpolated palette entries are rounded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Decoder {
    /// The float palette: (2a+b)/3, (a+2b)/3; (a+b)/2 (D3D10, SPEC §5).
    Ideal,
    /// NVIDIA's texture units (measured).
    Nvidia,
    /// AMD's (rgbcx's published formulas).
    Amd,
}

impl Decoder {
    pub const ALL: [Decoder; 3] = [Decoder::Ideal, Decoder::Nvidia, Decoder::Amd];

    pub fn name(self) -> &'static str {
        match self {
            Decoder::Ideal => "ideal",
            Decoder::Nvidia => "nvidia",
            Decoder::Amd => "amd",
        }
    }

    /// The four palette values (8-bit scale, 0–255; fractional for `ideal`)
    /// of channel `ch` (0 red, 1 green, 2 blue) with endpoint fields `x0`,
    /// `x1` (5 or 6 bits). `four_colour` is the block's mode (c0 > c1);
    /// in three-colour mode entry 3 is black.
    pub fn palette(self, four_colour: bool, ch: usize, x0: u8, x1: u8) -> [f32; 4] {
        let (a, b) = (expand(ch, x0), expand(ch, x1));
        let (e2, e3) = if four_colour {
            (self.third(ch, x0, x1, a, b), self.third(ch, x1, x0, b, a))
        } else {
            (self.half(ch, x0, x1, a, b), 0.0)
        };
        [f32::from(a), f32::from(b), e2, e3]
    }

    /// [`Decoder::palette`] of four-colour mode, from a table made once:
    /// endpoint searches score thousands of candidate pairs per block row
    /// (25 pairs × 3 channels × up to 4 rounds per block when retargeting;
    /// some 700 per block and sweep in the seam-aware search), and a lookup
    /// is 8× faster on Fox than the integer formulas.
    #[inline]
    pub fn four_colour_palette(self, ch: usize, x0: u8, x1: u8) -> [f32; 4] {
        four_colour_palettes().levels[self.palette_at(ch, x0, x1)]
    }

    /// [`Decoder::four_colour_palette`] in \[0, 1\] (each value / 255), as
    /// the seam-aware search's f64 energies take it.
    #[inline]
    pub fn four_colour_palette_unit(self, ch: usize, x0: u8, x1: u8) -> [f64; 4] {
        four_colour_palettes().unit[self.palette_at(ch, x0, x1)]
    }

    /// Every [`Decoder::four_colour_palette_unit`] of decoder
    /// `Decoder::ALL[d]` and channel `ch`, for a search that scores many
    /// endpoint pairs: the table is reached once, not once per pair.
    #[inline]
    pub(crate) fn four_colour_unit_table(d: usize, ch: usize) -> UnitPalettes {
        let start = Self::table_index(d, ch, 0, 0);
        UnitPalettes(&four_colour_palettes().unit[start..start + SIDE * SIDE])
    }

    #[inline]
    fn palette_at(self, ch: usize, x0: u8, x1: u8) -> usize {
        let d = Decoder::ALL.iter().position(|&a| a == self).unwrap_or(0);
        Self::table_index(d, ch, x0, x1)
    }

    #[inline]
    fn table_index(d: usize, ch: usize, x0: u8, x1: u8) -> usize {
        ((d * 3 + ch) * SIDE + x0 as usize) * SIDE + x1 as usize
    }

    /// Entry 2 of four-colour mode: two thirds of `a`, one third of `b`.
    fn third(self, ch: usize, x0: u8, x1: u8, a: u8, b: u8) -> f32 {
        let (x0, x1, a, b) = (u32::from(x0), u32::from(x1), i32::from(a), i32::from(b));
        match self {
            Decoder::Ideal => (2 * a + b) as f32 / 3.0,
            Decoder::Nvidia if ch == 1 => nvidia_green(a, b, 80),
            Decoder::Nvidia => (((2 * x0 + x1) * 22) / 8) as f32,
            Decoder::Amd => ((43 * a + 21 * b + 32) >> 6) as f32,
        }
    }

    /// Entry 2 of three-colour mode: the mean of the endpoints.
    fn half(self, ch: usize, x0: u8, x1: u8, a: u8, b: u8) -> f32 {
        let (x0, x1, a, b) = (u32::from(x0), u32::from(x1), i32::from(a), i32::from(b));
        match self {
            Decoder::Ideal => (a + b) as f32 / 2.0,
            Decoder::Nvidia if ch == 1 => nvidia_green(a, b, 128),
            Decoder::Nvidia => (((x0 + x1) * 33) / 8) as f32,
            Decoder::Amd => ((a + b + 1) >> 1) as f32,
        }
    }
}

/// NVIDIA's alpha weights (of a1, ×4096) for indices 2..7, measured:
/// `../shared/decoders/nvidia_bc3_alpha.bin`.
const NVIDIA_ALPHA_EIGHT: [i32; 6] = [578, 1156, 1784, 2312, 2940, 3518];
const NVIDIA_ALPHA_SIX: [i32; 4] = [770, 1540, 2556, 3326];

impl Decoder {
    /// The eight values (0–255; fractional for `ideal`) of a BC3/BC4 alpha
    /// block with endpoints `a0`, `a1`. a0 > a1: six interpolated values
    /// in sevenths; otherwise four in fifths, then 0 and 255.
    ///
    /// NVIDIA's weights are close to, but not, sevenths and fifths
    /// (measured, up to 6.6 levels off). AMD publishes no alpha rule and we
    /// could not measure one: it takes the ideal weights rounded to the
    /// nearest level, as D3D10 allows.
    pub fn alpha_palette(self, a0: u8, a1: u8) -> [f32; 8] {
        let (a, b) = (i32::from(a0), i32::from(a1));
        let eight = a0 > a1;
        let mut p = [a as f32, b as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 255.0];
        let (steps, n) = if eight { (7, 6) } else { (5, 4) };
        for k in 0..n {
            let i = k as i32 + 1;
            p[k + 2] = match self {
                Decoder::Ideal => ((steps - i) * a + i * b) as f32 / steps as f32,
                Decoder::Nvidia => {
                    let w = if eight {
                        NVIDIA_ALPHA_EIGHT[k]
                    } else {
                        NVIDIA_ALPHA_SIX[k]
                    };
                    (((4096 - w) * a + w * b + 2048) >> 12) as f32
                }
                Decoder::Amd => {
                    let num = (steps - i) * a + i * b;
                    ((2 * num + steps) / (2 * steps)) as f32
                }
            };
        }
        p
    }
}

/// The decoders an encoding is made for: the integer searches score their
/// candidates under each of them.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// The float palette (SPEC §5).
    Ideal,
    /// NVIDIA's texture units.
    Nvidia,
    /// AMD's.
    Amd,
    /// All three at once: one file for any GPU.
    #[default]
    Robust,
}

impl Target {
    /// The decoders whose mean error the searches minimise.
    pub fn decoders(self) -> &'static [Decoder] {
        match self {
            Target::Ideal => &[Decoder::Ideal],
            Target::Nvidia => &[Decoder::Nvidia],
            Target::Amd => &[Decoder::Amd],
            Target::Robust => &Decoder::ALL,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Target::Ideal => "ideal",
            Target::Nvidia => "nvidia",
            Target::Amd => "amd",
            Target::Robust => "robust",
        }
    }
}

/// NVIDIA's green: (256·a + t(d/4) + 128 + w·d) / 256 with d = b − a on the
/// 8-bit expansions, t truncating toward zero (w = 80 for a third, 128 for
/// a half). The numerator is never negative.
fn nvidia_green(a: i32, b: i32, w: i32) -> f32 {
    let d = b - a;
    ((256 * a + d / 4 + 128 + w * d) / 256) as f32
}

/// 5- or 6-bit field → 8 bits by bit replication.
fn expand(ch: usize, x: u8) -> u8 {
    if ch == 1 {
        (x << 2) | (x >> 4)
    } else {
        (x << 3) | (x >> 2)
    }
}

/// Endpoint fields per side of the palette table: 6-bit green's 64 (5-bit
/// channels use the first 32 × 32).
const SIDE: usize = 64;

/// Per decoder (in [`Decoder::ALL`] order) and channel: every pair's
/// four-colour palette, 64 × 64 pairs, on 0..255 and in \[0, 1\].
struct FourColourPalettes {
    levels: Vec<[f32; 4]>,
    unit: Vec<[f64; 4]>,
}

/// One decoder's four-colour palettes of one channel in \[0, 1\], by
/// endpoint pair (see [`Decoder::four_colour_unit_table`]).
#[derive(Clone, Copy)]
pub(crate) struct UnitPalettes(&'static [[f64; 4]]);

impl UnitPalettes {
    /// The palette of 565 endpoint values `x0`, `x1` (each below 64).
    #[inline]
    pub(crate) fn at(self, x0: usize, x1: usize) -> [f64; 4] {
        self.0[x0 * SIDE + x1]
    }
}

fn four_colour_palettes() -> &'static FourColourPalettes {
    static TABLE: std::sync::OnceLock<FourColourPalettes> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut levels = vec![[0.0; 4]; Decoder::ALL.len() * 3 * SIDE * SIDE];
        for (d, dec) in Decoder::ALL.iter().enumerate() {
            for ch in 0..3 {
                let top = if ch == 1 { 64 } else { 32 };
                for x0 in 0..top {
                    for x1 in 0..top {
                        levels[((d * 3 + ch) * SIDE + x0) * SIDE + x1] =
                            dec.palette(true, ch, x0 as u8, x1 as u8);
                    }
                }
            }
        }
        let unit = levels
            .iter()
            .map(|p| p.map(|v| f64::from(v) / 255.0))
            .collect();
        FourColourPalettes { levels, unit }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_palette_table_is_the_formulas() {
        for dec in Decoder::ALL {
            for ch in 0..3 {
                let top = if ch == 1 { 64 } else { 32 };
                for x0 in 0..top {
                    for x1 in 0..top {
                        let p = dec.palette(true, ch, x0, x1);
                        assert_eq!(dec.four_colour_palette(ch, x0, x1), p);
                        let unit = dec.four_colour_palette_unit(ch, x0, x1);
                        assert_eq!(unit, p.map(|v| f64::from(v) / 255.0));
                    }
                }
            }
        }
    }

    /// Every line of the table read from an NVIDIA H200's texture unit.
    #[test]
    fn nvidia_reproduces_the_measured_table() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/decoders/nvidia_bc1_table.txt");
        let table =
            std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let mut lines = 0;
        for line in table
            .lines()
            .filter(|l| !l.starts_with('#') && !l.is_empty())
        {
            let f: Vec<u32> = line
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            let (mode, ch, x0, x1) = (f[0], f[1] as usize, f[2] as u8, f[3] as u8);
            let want = [f[4], f[5], f[6], f[7]].map(|v| v as f32);
            let got = Decoder::Nvidia.palette(mode == 4, ch, x0, x1);
            assert_eq!(got, want, "{line}");
            lines += 1;
        }
        assert_eq!(lines, 11_296);
    }

    /// Every value read from an NVIDIA H200's BC3 alpha decoder, for every
    /// endpoint pair and index.
    #[test]
    fn nvidia_reproduces_the_measured_alpha_table() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/decoders/nvidia_bc3_alpha.bin");
        let table = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(table.len(), 256 * 256 * 8);
        for a0 in 0..=255u8 {
            for a1 in 0..=255u8 {
                let at = (usize::from(a0) * 256 + usize::from(a1)) * 8;
                let want = table[at..at + 8].iter().map(|&v| f32::from(v));
                let got = Decoder::Nvidia.alpha_palette(a0, a1);
                assert!(got.iter().copied().eq(want), "a0 {a0} a1 {a1}: {got:?}");
            }
        }
        // The ideal palette in sevenths and fifths.
        assert_eq!(
            Decoder::Ideal.alpha_palette(7, 0),
            [7.0, 0.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0]
        );
        assert_eq!(
            Decoder::Ideal.alpha_palette(0, 5),
            [0.0, 5.0, 1.0, 2.0, 3.0, 4.0, 0.0, 255.0]
        );
    }

    /// AMD's weights (43 and 21 sixty-fourths) are not thirds: with its
    /// rounding, an entry lands up to 1⅔ levels off the float palette.
    #[test]
    fn ideal_is_the_float_palette_and_amd_rounds_near_it() {
        for four in [true, false] {
            for ch in 0..3 {
                let top = if ch == 1 { 63u8 } else { 31 };
                for x0 in 0..=top {
                    for x1 in 0..=top {
                        let i = Decoder::Ideal.palette(four, ch, x0, x1);
                        let a = Decoder::Amd.palette(four, ch, x0, x1);
                        for k in 0..4 {
                            let off = (i[k] - a[k]).abs();
                            assert!(off <= 5.0 / 3.0 + 1e-4, "{four} {ch} {x0} {x1} {k}: {off}");
                        }
                    }
                }
            }
        }
        let p = Decoder::Ideal.palette(true, 0, 31, 0);
        assert_eq!(p, [255.0, 0.0, 170.0, 85.0]);
    }
}
