//! The BC7 partition tables and anchor indices (Microsoft, "BC7 Format",
//! Direct3D 11 documentation; Khronos Data Format Specification 1.3,
//! section 20.3, tables 112-114).
//!
//! A texel's subset is read from its bits: bit `k` of a two-subset mask,
//! bits `2k..2k+2` of a three-subset mask, for texel `k` in row-major order.

/// Two-subset partitions: bit `k` is texel `k`'s subset.
const TWO: [u16; 64] = [
    0xcccc, 0x8888, 0xeeee, 0xecc8, 0xc880, 0xfeec, 0xfec8, 0xec80, 0xc800, 0xffec, 0xfe80, 0xe800,
    0xffe8, 0xff00, 0xfff0, 0xf000, 0xf710, 0x008e, 0x7100, 0x08ce, 0x008c, 0x7310, 0x3100, 0x8cce,
    0x088c, 0x3110, 0x6666, 0x366c, 0x17e8, 0x0ff0, 0x718e, 0x399c, 0xaaaa, 0xf0f0, 0x5a5a, 0x33cc,
    0x3c3c, 0x55aa, 0x9696, 0xa55a, 0x73ce, 0x13c8, 0x324c, 0x3bdc, 0x6996, 0xc33c, 0x9966, 0x0660,
    0x0272, 0x04e4, 0x4e40, 0x2720, 0xc936, 0x936c, 0x39c6, 0x639c, 0x9336, 0x9cc6, 0x817e, 0xe718,
    0xccf0, 0x0fcc, 0x7744, 0xee22,
];

/// Three-subset partitions: bits `2k..2k+2` are texel `k`'s subset.
const THREE: [u32; 64] = [
    0xaa685050, 0x6a5a5040, 0x5a5a4200, 0x5450a0a8, 0xa5a50000, 0xa0a05050, 0x5555a0a0, 0x5a5a5050,
    0xaa550000, 0xaa555500, 0xaaaa5500, 0x90909090, 0x94949494, 0xa4a4a4a4, 0xa9a59450, 0x2a0a4250,
    0xa5945040, 0x0a425054, 0xa5a5a500, 0x55a0a0a0, 0xa8a85454, 0x6a6a4040, 0xa4a45000, 0x1a1a0500,
    0x0050a4a4, 0xaaa59090, 0x14696914, 0x69691400, 0xa08585a0, 0xaa821414, 0x50a4a450, 0x6a5a0200,
    0xa9a58000, 0x5090a0a8, 0xa8a09050, 0x24242424, 0x00aa5500, 0x24924924, 0x24499224, 0x50a50a50,
    0x500aa550, 0xaaaa4444, 0x66660000, 0xa5a0a5a0, 0x50a050a0, 0x69286928, 0x44aaaa44, 0x66666600,
    0xaa444444, 0x54a854a8, 0x95809580, 0x96969600, 0xa85454a8, 0x80959580, 0xaa141414, 0x96960000,
    0xaaaa1414, 0xa05050a0, 0xa0a5a5a0, 0x96000000, 0x40804080, 0xa9a8a9a8, 0xaaaaaa44, 0x2a4a5254,
];

/// Anchor texel of subset 1 in the two-subset partitions.
const ANCHOR_TWO: [u8; 64] = [
    15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 2, 8, 2, 2, 8, 8, 15, 2, 8,
    2, 2, 8, 8, 2, 2, 15, 15, 6, 8, 2, 8, 15, 15, 2, 8, 2, 2, 2, 15, 15, 6, 6, 2, 6, 8, 15, 15, 2,
    2, 15, 15, 15, 15, 15, 2, 2, 15,
];

/// Anchor texels of subsets 1 and 2 in the three-subset partitions.
const ANCHOR_THREE: [[u8; 64]; 2] = [
    [
        3, 3, 15, 15, 8, 3, 15, 15, 8, 8, 6, 6, 6, 5, 3, 3, 3, 3, 8, 15, 3, 3, 6, 10, 5, 8, 8, 6,
        8, 5, 15, 15, 8, 15, 3, 5, 6, 10, 8, 15, 15, 3, 15, 5, 15, 15, 15, 15, 3, 15, 5, 5, 5, 8,
        5, 10, 5, 10, 8, 13, 15, 12, 3, 3,
    ],
    [
        15, 8, 8, 3, 15, 15, 3, 8, 15, 15, 15, 15, 15, 15, 15, 8, 15, 8, 15, 3, 15, 8, 15, 8, 3,
        15, 6, 10, 15, 15, 10, 8, 15, 3, 15, 10, 10, 8, 9, 10, 6, 15, 8, 15, 3, 6, 6, 8, 15, 3, 15,
        15, 15, 15, 15, 15, 15, 15, 15, 15, 3, 15, 15, 8,
    ],
];

/// Subset of texel `k` under partition `p` of a `subsets`-subset mode
/// (1, 2 or 3); `p` is taken modulo 64.
#[inline]
pub fn subset(subsets: usize, p: usize, k: usize) -> usize {
    match subsets {
        2 => usize::from((TWO[p & 63] >> k) & 1 == 1),
        3 => ((THREE[p & 63] >> (2 * k)) & 3) as usize,
        _ => 0,
    }
}

/// Anchor texel of subset `s` (texel 0 for subset 0).
#[inline]
pub fn anchor(subsets: usize, p: usize, s: usize) -> usize {
    match (subsets, s) {
        (_, 0) => 0,
        (2, _) => usize::from(ANCHOR_TWO[p & 63]),
        (3, 1 | 2) => usize::from(ANCHOR_THREE[s - 1][p & 63]),
        _ => 0,
    }
}

/// Every texel's subset under partition `p`.
#[cfg(test)]
pub fn subsets_of(subsets: usize, p: usize) -> [u8; 16] {
    std::array::from_fn(|k| subset(subsets, p, k) as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchors_lie_in_their_subsets_and_each_subset_is_used() {
        for p in 0..64 {
            for n in [2, 3] {
                for s in 0..n {
                    assert_eq!(subset(n, p, anchor(n, p, s)), s, "{n} {p} {s}");
                }
            }
        }
        // Spec spot checks: two-subset partition 13 is the top/bottom split,
        // three-subset partition 8 the three horizontal bands.
        assert_eq!(
            subsets_of(2, 13),
            [0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1]
        );
        assert_eq!(
            subsets_of(3, 8),
            [0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]
        );
    }
}
