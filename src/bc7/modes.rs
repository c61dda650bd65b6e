//! The eight BC7 modes (Khronos Data Format Specification 1.3, table 110;
//! Microsoft, "BC7 Format"): what each stores and with how many bits.

/// How a mode stores the endpoints' lowest bit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PBits {
    /// No p-bits: endpoints are stored at full width.
    None,
    /// One bit per subset, shared by both endpoints (mode 1).
    Shared,
    /// One bit per endpoint (modes 0, 3, 6, 7).
    Unique,
}

/// One mode's layout.
#[derive(Clone, Copy, Debug)]
pub struct Mode {
    pub subsets: usize,
    pub partition_bits: u32,
    pub rotation_bits: u32,
    pub index_selection_bits: u32,
    /// Stored bits per colour channel, p-bit excluded.
    pub colour_bits: u32,
    /// Stored bits per alpha channel, p-bit excluded; 0: alpha decodes to 255.
    pub alpha_bits: u32,
    pub pbits: PBits,
    /// Bits per index of the first index set, and of the second (0: none).
    pub index_bits: [u32; 2],
}

impl Mode {
    /// Whether colour and alpha have index sets of their own (modes 4, 5).
    pub fn separate_alpha(&self) -> bool {
        self.index_bits[1] != 0
    }
}

// One argument per column of the specification's table.
#[allow(clippy::too_many_arguments)]
const fn mode(
    subsets: usize,
    partition_bits: u32,
    rotation_bits: u32,
    index_selection_bits: u32,
    colour_bits: u32,
    alpha_bits: u32,
    pbits: PBits,
    index_bits: [u32; 2],
) -> Mode {
    Mode {
        subsets,
        partition_bits,
        rotation_bits,
        index_selection_bits,
        colour_bits,
        alpha_bits,
        pbits,
        index_bits,
    }
}

pub const MODES: [Mode; 8] = [
    mode(3, 4, 0, 0, 4, 0, PBits::Unique, [3, 0]),
    mode(2, 6, 0, 0, 6, 0, PBits::Shared, [3, 0]),
    mode(3, 6, 0, 0, 5, 0, PBits::None, [2, 0]),
    mode(2, 6, 0, 0, 7, 0, PBits::Unique, [2, 0]),
    mode(1, 0, 2, 1, 5, 6, PBits::None, [2, 3]),
    mode(1, 0, 2, 0, 7, 8, PBits::None, [2, 2]),
    mode(1, 0, 0, 0, 7, 7, PBits::Unique, [4, 0]),
    mode(2, 6, 0, 0, 5, 5, PBits::Unique, [2, 0]),
];

/// Interpolation weights (of the second endpoint, out of 64) for 2-, 3- and
/// 4-bit indices.
const WEIGHTS2: [u32; 4] = [0, 21, 43, 64];
const WEIGHTS3: [u32; 8] = [0, 9, 18, 27, 37, 46, 55, 64];
const WEIGHTS4: [u32; 16] = [0, 4, 9, 13, 17, 21, 26, 30, 34, 38, 43, 47, 51, 55, 60, 64];

/// The weights of `bits`-bit indices (2, 3 or 4).
pub fn weights(bits: u32) -> &'static [u32] {
    match bits {
        2 => &WEIGHTS2,
        3 => &WEIGHTS3,
        _ => &WEIGHTS4,
    }
}

/// The spec's interpolation of two 8-bit endpoint values.
#[inline]
pub fn interpolate(e0: u32, e1: u32, w: u32) -> u32 {
    ((64 - w) * e0 + w * e1 + 32) >> 6
}

/// An endpoint of `precision` bits (p-bit included) widened to 8 bits by
/// replicating its high bits, as the spec does.
#[inline]
pub fn expand(code: u32, precision: u32) -> u32 {
    if precision >= 8 {
        code & 0xff
    } else {
        let v = code << (8 - precision);
        (v | (v >> precision)) & 0xff
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_mode_fills_128_bits() {
        for (m, md) in MODES.iter().enumerate() {
            let ends = 2 * md.subsets as u32;
            let pb = match md.pbits {
                PBits::None => 0,
                PBits::Shared => md.subsets as u32,
                PBits::Unique => ends,
            };
            let idx0 = 16 * md.index_bits[0] - md.subsets as u32;
            let idx1 = if md.index_bits[1] > 0 {
                16 * md.index_bits[1] - 1
            } else {
                0
            };
            let total = (m as u32 + 1)
                + md.partition_bits
                + md.rotation_bits
                + md.index_selection_bits
                + ends * (3 * md.colour_bits + md.alpha_bits)
                + pb
                + idx0
                + idx1;
            assert_eq!(total, 128, "mode {m}");
        }
    }

    #[test]
    fn expansion_reaches_both_ends() {
        for p in 4..=8 {
            assert_eq!(expand(0, p), 0);
            assert_eq!(expand((1 << p) - 1, p), 255);
        }
        assert_eq!(expand(0b10000, 5), 0b1000_0100);
    }
}
