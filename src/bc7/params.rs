//! A BC7 block unpacked into its fields, packed back bit for bit, and
//! decoded by the spec's integer arithmetic (Khronos Data Format
//! Specification 1.3, section 20.3; Microsoft, "BC7 Format").

use super::bits::{BitReader, BitWriter};
use super::modes::{expand, interpolate, weights, PBits, MODES};
use super::partitions::{anchor, subset};

/// Every field of a block of a valid mode.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Params {
    pub mode: u8,
    pub partition: u8,
    /// 0: none; 1, 2, 3: alpha swapped with R, G or B after decoding.
    pub rotation: u8,
    /// Mode 4: 0 when colour takes the 2-bit indices, 1 when the 3-bit.
    pub index_selection: u8,
    /// Stored endpoint codes, p-bits apart: `[subset][endpoint][RGBA]`.
    pub ends: [[[u8; 4]; 2]; 3],
    /// `[subset][endpoint]`; both entries equal in mode 1.
    pub pbits: [[u8; 2]; 3],
    /// The first index set, and the second (modes 4 and 5 only).
    pub indices: [[u8; 16]; 2],
}

impl Params {
    /// Whether index set `set` drives the colour channels (else alpha),
    /// in modes 4 and 5.
    fn set_is_colour(&self, set: usize) -> bool {
        (set == 0) == (self.index_selection == 0)
    }

    /// The 8-bit value of endpoint `e` of subset `s`, channels RGBA.
    pub fn endpoint(&self, s: usize, e: usize) -> [u32; 4] {
        let m = &MODES[self.mode as usize & 7];
        let has_p = m.pbits != PBits::None;
        let code = |bits: u32, c: usize| {
            let v = u32::from(self.ends[s][e][c]) & ((1 << bits) - 1);
            if has_p {
                expand((v << 1) | u32::from(self.pbits[s][e] & 1), bits + 1)
            } else {
                expand(v, bits)
            }
        };
        let a = if m.alpha_bits == 0 {
            255
        } else {
            code(m.alpha_bits, 3)
        };
        [
            code(m.colour_bits, 0),
            code(m.colour_bits, 1),
            code(m.colour_bits, 2),
            a,
        ]
    }

    /// The 16 texels (row-major RGBA) this block decodes to.
    pub fn decode(&self) -> [[u8; 4]; 16] {
        let m = &MODES[self.mode as usize & 7];
        let mut ends = [[[0u32; 4]; 2]; 3];
        for (s, pair) in ends.iter_mut().enumerate().take(m.subsets) {
            *pair = [self.endpoint(s, 0), self.endpoint(s, 1)];
        }
        std::array::from_fn(|k| self.texel_from(&ends, k))
    }

    /// Texel `k` alone (for searches that change one index at a time).
    pub fn decode_texel(&self, k: usize) -> [u8; 4] {
        let m = &MODES[self.mode as usize & 7];
        let s = subset(m.subsets, usize::from(self.partition), k);
        let mut ends = [[[0u32; 4]; 2]; 3];
        ends[s] = [self.endpoint(s, 0), self.endpoint(s, 1)];
        self.texel_from(&ends, k)
    }

    fn texel_from(&self, ends: &[[[u32; 4]; 2]; 3], k: usize) -> [u8; 4] {
        let m = &MODES[self.mode as usize & 7];
        let (colour_set, alpha_set) = if m.separate_alpha() && self.index_selection == 1 {
            (1, 0)
        } else if m.separate_alpha() {
            (0, 1)
        } else {
            (0, 0)
        };
        let wc = weights(m.index_bits[colour_set]);
        let wa = weights(m.index_bits[alpha_set]);
        let s = subset(m.subsets, usize::from(self.partition), k);
        let [e0, e1] = ends[s];
        let fc = wc[usize::from(self.indices[colour_set][k]) & (wc.len() - 1)];
        let fa = wa[usize::from(self.indices[alpha_set][k]) & (wa.len() - 1)];
        let mut t = [
            interpolate(e0[0], e1[0], fc) as u8,
            interpolate(e0[1], e1[1], fc) as u8,
            interpolate(e0[2], e1[2], fc) as u8,
            interpolate(e0[3], e1[3], fa) as u8,
        ];
        if (1..=3).contains(&self.rotation) {
            t.swap(3, usize::from(self.rotation) - 1);
        }
        t
    }

    /// Makes every anchor index's top bit 0, as the format requires, by
    /// swapping the endpoints of a subset and mirroring its indices: the
    /// weights are symmetric (w[n−1−i] = 64 − w\[i\]), so the block decodes
    /// the same.
    fn fix_anchors(&mut self) {
        let m = MODES[self.mode as usize & 7];
        let sets = if m.separate_alpha() { 2 } else { 1 };
        for set in 0..sets {
            let bits = m.index_bits[set];
            let top = (1u8 << bits) - 1;
            let channels = match (m.separate_alpha(), self.set_is_colour(set)) {
                (false, _) => 0..4,
                (true, true) => 0..3,
                (true, false) => 3..4,
            };
            for s in 0..m.subsets {
                let a = anchor(m.subsets, usize::from(self.partition), s);
                if self.indices[set][a] >> (bits - 1) == 0 {
                    continue;
                }
                for k in 0..16 {
                    if subset(m.subsets, usize::from(self.partition), k) == s {
                        self.indices[set][k] = top - (self.indices[set][k] & top);
                    }
                }
                for c in channels.clone() {
                    let [e0, e1] = &mut self.ends[s];
                    std::mem::swap(&mut e0[c], &mut e1[c]);
                }
                if m.pbits == PBits::Unique {
                    self.pbits[s].swap(0, 1);
                }
            }
        }
    }

    /// The block's 16 bytes (after the anchor fix-up).
    pub fn pack(&self) -> [u8; 16] {
        let mut p = *self;
        p.fix_anchors();
        let m = &MODES[p.mode as usize & 7];
        let mut w = BitWriter::default();
        w.write(1 << p.mode, u32::from(p.mode) + 1);
        w.write(u32::from(p.partition), m.partition_bits);
        w.write(u32::from(p.rotation), m.rotation_bits);
        w.write(u32::from(p.index_selection), m.index_selection_bits);
        for c in 0..4 {
            let bits = if c < 3 { m.colour_bits } else { m.alpha_bits };
            for s in 0..m.subsets {
                for e in 0..2 {
                    w.write(u32::from(p.ends[s][e][c]), bits);
                }
            }
        }
        for s in 0..m.subsets {
            match m.pbits {
                PBits::None => {}
                PBits::Shared => w.write(u32::from(p.pbits[s][0]), 1),
                PBits::Unique => {
                    w.write(u32::from(p.pbits[s][0]), 1);
                    w.write(u32::from(p.pbits[s][1]), 1);
                }
            }
        }
        for set in 0..2 {
            let bits = m.index_bits[set];
            if bits == 0 {
                continue;
            }
            for k in 0..16 {
                let is_anchor = (0..m.subsets).any(|s| {
                    (set == 0 || s == 0) && anchor(m.subsets, usize::from(p.partition), s) == k
                });
                w.write(u32::from(p.indices[set][k]), bits - u32::from(is_anchor));
            }
        }
        debug_assert_eq!(w.position(), 128);
        w.bytes()
    }

    /// The fields of a block, or `None` for the reserved mode (first byte 0).
    pub fn unpack(bytes: &[u8; 16]) -> Option<Params> {
        if bytes[0] == 0 {
            return None;
        }
        let mode = bytes[0].trailing_zeros() as u8;
        let m = &MODES[usize::from(mode)];
        let mut r = BitReader::new(bytes);
        r.read(u32::from(mode) + 1);
        let mut p = Params {
            mode,
            partition: r.read(m.partition_bits),
            rotation: r.read(m.rotation_bits),
            index_selection: r.read(m.index_selection_bits),
            ..Params::default()
        };
        for c in 0..4 {
            let bits = if c < 3 { m.colour_bits } else { m.alpha_bits };
            for s in 0..m.subsets {
                for e in 0..2 {
                    p.ends[s][e][c] = r.read(bits);
                }
            }
        }
        for s in 0..m.subsets {
            match m.pbits {
                PBits::None => {}
                PBits::Shared => {
                    let b = r.read(1);
                    p.pbits[s] = [b, b];
                }
                PBits::Unique => p.pbits[s] = [r.read(1), r.read(1)],
            }
        }
        for set in 0..2 {
            let bits = m.index_bits[set];
            if bits == 0 {
                continue;
            }
            for k in 0..16 {
                let is_anchor = (0..m.subsets).any(|s| {
                    (set == 0 || s == 0) && anchor(m.subsets, usize::from(p.partition), s) == k
                });
                p.indices[set][k] = r.read(bits - u32::from(is_anchor));
            }
        }
        Some(p)
    }
}
