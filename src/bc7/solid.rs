//! Single-colour fits: for a subset of (nearly) one colour, the endpoint
//! codes whose interpolation at one index weight lands nearest each 8-bit
//! value, from tables over every code pair (the approach of Rich
//! Geldreich's bc7enc and of stb_dxt's single-colour tables). Rounding
//! endpoints to their nearest codes instead leaves such subsets off by a
//! level in most channels, which on flat art costs several dB.

// Small fixed arrays indexed by channel, texel and value in step;
// iterator chains would hide which index is which.
#![allow(clippy::needless_range_loop)]

use std::sync::OnceLock;

use super::modes::{expand, interpolate, weights, PBits};

/// For each target value: the codes of both endpoints and the decoded
/// value's distance from the target.
pub type Table = [(u8, u8, u8); 256];

const BITS: usize = 5; // 4..=8
const KINDS: usize = 3; // PBits::None, Shared, Unique
const PAIRS: usize = 4; // (p0, p1)
const WEIGHTS: usize = 16 + 8 + 4;

fn key(bits: u32, pbits: PBits, p: [u8; 2], weight_slot: usize) -> usize {
    let kind = match pbits {
        PBits::None => 0,
        PBits::Shared => 1,
        PBits::Unique => 2,
    };
    let b = (bits.clamp(4, 8) - 4) as usize;
    let pair = usize::from(p[0] & 1) * 2 + usize::from(p[1] & 1);
    ((b * KINDS + kind) * PAIRS + pair) * WEIGHTS + weight_slot
}

/// Where the weights of `index_bits`-bit indices start among the slots.
fn weight_base(index_bits: u32) -> usize {
    match index_bits {
        4 => 0,
        3 => 16,
        _ => 24,
    }
}

static TABLES: OnceLock<Vec<OnceLock<Box<Table>>>> = OnceLock::new();

fn build(bits: u32, pbits: PBits, p: [u8; 2], w: u32) -> Box<Table> {
    let max = (1u32 << bits) - 1;
    let dec = |q: u32, p: u8| match pbits {
        PBits::None => expand(q, bits),
        _ => expand((q << 1) | u32::from(p), bits + 1),
    };
    let mut t: Box<Table> = Box::new([(0, 0, u8::MAX); 256]);
    for q0 in 0..=max {
        let e0 = dec(q0, p[0]);
        for q1 in 0..=max {
            let v = interpolate(e0, dec(q1, p[1]), w) as usize;
            // Exact hits first; near misses fill the gaps below.
            if t[v].2 != 0 {
                t[v] = (q0 as u8, q1 as u8, 0);
            }
        }
    }
    // Values no pair hits take the nearest value that one does.
    let hit: Vec<usize> = (0..256).filter(|&v| t[v].2 == 0).collect();
    for v in 0..256 {
        if t[v].2 != 0 {
            if let Some(&h) = hit.iter().min_by_key(|&&h| h.abs_diff(v)) {
                t[v] = (t[h].0, t[h].1, h.abs_diff(v).min(255) as u8);
            }
        }
    }
    t
}

/// The table for one channel layout, p-bit pair and index weight slot.
pub fn table(bits: u32, pbits: PBits, p: [u8; 2], index_bits: u32, index: usize) -> &'static Table {
    let all = TABLES.get_or_init(|| {
        (0..BITS * KINDS * PAIRS * WEIGHTS)
            .map(|_| OnceLock::new())
            .collect()
    });
    let slot = weight_base(index_bits) + index;
    let w = weights(index_bits)[index.min(weights(index_bits).len() - 1)];
    all[key(bits, pbits, p, slot)].get_or_init(|| build(bits, pbits, p, w))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_decode_to_their_claims() {
        for (bits, pb) in [
            (7, PBits::Unique),
            (5, PBits::None),
            (6, PBits::Shared),
            (8, PBits::None),
        ] {
            for p in [[0u8, 0], [1, 1], [0, 1]] {
                for index in [1usize, 2] {
                    let t = table(bits, pb, p, 2, index);
                    let w = weights(2)[index];
                    for v in 0..256usize {
                        let (q0, q1, err) = t[v];
                        let dec = |q: u8, p: u8| match pb {
                            PBits::None => expand(u32::from(q), bits),
                            _ => expand((u32::from(q) << 1) | u32::from(p), bits + 1),
                        };
                        let got = interpolate(dec(q0, p[0]), dec(q1, p[1]), w) as usize;
                        assert_eq!(got.abs_diff(v), usize::from(err), "{bits} {pb:?} {p:?} {v}");
                    }
                }
            }
        }
        // Mode 5's colour (7 bits, no p-bit) hits every 8-bit value.
        assert!(table(7, PBits::None, [0, 0], 2, 1).iter().all(|e| e.2 == 0));
    }
}
