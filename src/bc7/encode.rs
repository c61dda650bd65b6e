//! The block encoder: which modes, partitions, rotations and index
//! selections to try at each effort level, and the assembly of each
//! candidate's subset fits ([`super::fit`]) into a block. Every candidate
//! is scored by its exact decode; the lowest weighted squared error wins.

use super::estimate::Scores;
use super::fit::{fit, Fit, FitEffort, Setup};
use super::modes::MODES;
use super::params::Params;
use super::partitions::subset;
use crate::bc1::Level;

/// How hard one block is tried.
#[derive(Clone, Copy, Debug)]
pub struct Effort {
    pub fit: FitEffort,
    /// Partitions fitted in full per two-subset mode (1, 3, 7), best
    /// estimates first.
    pub two: usize,
    /// Partitions fitted in full per three-subset mode (0, 2).
    pub three: usize,
    /// Try modes 4 and 5 under every rotation (else rotation 0 only).
    pub rotations: bool,
    /// Try mode 7 on opaque blocks too.
    pub mode7_opaque: bool,
    /// Try mode 4 on blocks whose alpha does not vary.
    pub mode4_opaque: bool,
    /// Stop trying modes once a block's error is at most this.
    pub good_enough: f32,
}

/// A block error (weighted squared 8-bit levels over the 16 texels) below
/// which `fast` and `default` stop trying modes: half a level per texel in
/// RMS. Together with the projected 4-bit index search and mode 4 left to
/// `best` on opaque blocks, it took `default` on the bench's Fox crop from
/// 0.72 to 1.41 MPix/s for 0.9 dB (62.80 to 61.91, still above ISPC basic).
const GOOD_ENOUGH: f32 = 4.0;

/// Effort per level. Measured by `cargo bench --bench bc7` (one thread,
/// 512² crops of the shared models' base colours; PSNR over RGB, RGBA for
/// Duck-alpha), beside intel_tex_2 (ISPC):
/// * `fast`: above ISPC very_fast on every image (50.2–64.5 dB) at
///   2.2–4.3 MPix/s.
/// * `default`: above ISPC basic on every image (Fox 61.91 against 61.08,
///   Duck 61.69/61.45, blub 65.11/64.52, CesiumMan 50.96/50.64,
///   WaterBottle 58.12/57.09, Duck-alpha 54.70/54.08) at 0.53–1.18× its
///   speed (WaterBottle 1.20 against 2.26 MPix/s, the slowest ratio).
/// * `best`: above ISPC slow on every image (Fox 63.38/61.84, Duck
///   62.87/62.64, blub 65.45/64.68, CesiumMan 51.16/50.91, WaterBottle
///   58.42/57.85, Duck-alpha 55.01/54.22) at 0.4–1.5× its speed.
pub fn effort(level: Level) -> Effort {
    match level {
        Level::Fast => Effort {
            fit: FitEffort {
                refine: 1,
                pbit_search: false,
                code_search: 0,
            },
            two: 1,
            three: 0,
            rotations: false,
            mode7_opaque: false,
            mode4_opaque: false,
            good_enough: GOOD_ENOUGH,
        },
        Level::Default => Effort {
            fit: FitEffort {
                refine: 2,
                pbit_search: true,
                code_search: 0,
            },
            two: 3,
            three: 1,
            rotations: true,
            mode7_opaque: false,
            mode4_opaque: false,
            good_enough: GOOD_ENOUGH,
        },
        Level::Best => Effort {
            fit: FitEffort {
                refine: 4,
                pbit_search: true,
                code_search: 2,
            },
            two: 12,
            three: 6,
            rotations: true,
            mode7_opaque: true,
            mode4_opaque: true,
            good_enough: 0.0,
        },
    }
}

/// One block's texels (0–255) and the channel weights.
pub struct Texels {
    pub px: [[f32; 4]; 16],
    pub w: [f32; 4],
}

impl Texels {
    pub fn new(rgba: &[[u8; 4]; 16], w: &[f32; 4]) -> Self {
        Texels {
            px: rgba.map(|t| t.map(f32::from)),
            w: w.map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 }),
        }
    }

    /// Whether alpha matters here and is not 255 everywhere.
    fn alpha_varies(&self) -> bool {
        self.w[3] > 0.0 && self.px.iter().any(|t| t[3] < 255.0)
    }
}

/// A block and its error.
#[derive(Clone, Copy, Debug)]
pub struct Candidate {
    pub params: Params,
    pub err: f32,
}

fn keep_better(best: &mut Option<Candidate>, c: Option<Candidate>) {
    if let Some(c) = c {
        if best.is_none_or(|b| c.err < b.err) {
            *best = Some(c);
        }
    }
}

/// The error bound a new candidate must beat.
fn bound(best: &Option<Candidate>) -> f32 {
    best.map_or(f32::MAX, |b| b.err)
}

/// Encodes one block.
pub fn encode_block(t: &Texels, e: &Effort) -> Params {
    let mut best: Option<Candidate> = None;
    keep_better(&mut best, joint::<4>(t, 6, 0, &e.fit, f32::MAX));
    let varies = t.alpha_varies();
    let done = |best: &Option<Candidate>| best.is_some_and(|b| b.err <= e.good_enough);
    let modes: &[u8] = if varies || e.mode4_opaque {
        &[5, 4]
    } else {
        &[5]
    };
    for &m in modes {
        let rotations = if e.rotations { 0..4 } else { 0..1 };
        let selections = if m == 4 { 0..2 } else { 0..1 };
        for r in rotations {
            for s in selections.clone() {
                if done(&best) {
                    return best.map_or_else(Params::default, |b| b.params);
                }
                let b = bound(&best);
                keep_better(&mut best, separate(t, m, r, s, &e.fit, b));
            }
        }
    }
    if e.two > 0 && !done(&best) {
        let scores = Scores::new(&t.px, &t.w, 2);
        if varies || e.mode7_opaque {
            for p in scores.best(2, 64, e.two) {
                let b = bound(&best);
                keep_better(&mut best, joint::<4>(t, 7, p, &e.fit, b));
            }
        }
        if !varies {
            for (m, bits) in [(3u8, 2), (1, 3)] {
                for p in scores.best(bits, 64, e.two) {
                    let b = bound(&best);
                    keep_better(&mut best, joint::<3>(t, m, p, &e.fit, b));
                }
            }
        }
    }
    if e.three > 0 && !varies && !done(&best) {
        let scores = Scores::new(&t.px, &t.w, 3);
        for (m, bits, count) in [(2u8, 2, 64), (0, 3, 16)] {
            for p in scores.best(bits, count, e.three) {
                let b = bound(&best);
                keep_better(&mut best, joint::<3>(t, m, p, &e.fit, b));
            }
        }
    }
    best.map_or_else(Params::default, |b| b.params)
}

/// A mode whose channels share one index set (0–3, 6, 7) under partition
/// `partition`: `N` = 3 fits RGB (alpha decodes to 255), 4 fits RGBA.
pub fn joint<const N: usize>(
    t: &Texels,
    mode: u8,
    partition: u8,
    fe: &FitEffort,
    bound: f32,
) -> Option<Candidate> {
    let m = &MODES[usize::from(mode)];
    let mut params = Params {
        mode,
        partition,
        ..Params::default()
    };
    let mut err = 0.0;
    if N == 3 {
        err = t.px.iter().map(|p| t.w[3] * (255.0 - p[3]).powi(2)).sum();
    }
    let bits: [u32; N] = std::array::from_fn(|c| if c < 3 { m.colour_bits } else { m.alpha_bits });
    let setup = Setup {
        bits,
        pbits: m.pbits,
        index_bits: m.index_bits[0],
        w: std::array::from_fn(|c| t.w[c]),
    };
    for s in 0..m.subsets {
        let mut members = [0usize; 16];
        let mut n = 0;
        let mut px = [[0f32; N]; 16];
        for k in 0..16 {
            if subset(m.subsets, usize::from(partition), k) == s {
                members[n] = k;
                px[n] = std::array::from_fn(|c| t.px[k][c]);
                n += 1;
            }
        }
        let f: Fit<N> = fit(&px[..n], &setup, fe);
        err += f.err;
        if err >= bound {
            return None;
        }
        for e in 0..2 {
            for c in 0..N {
                params.ends[s][e][c] = f.codes[e][c];
            }
        }
        params.pbits[s] = f.pbits;
        for (i, &k) in members[..n].iter().enumerate() {
            params.indices[0][k] = f.indices[i];
        }
    }
    Some(Candidate { params, err })
}

/// Mode 4 or 5 with `rotation` and `selection`: the colour channels and
/// the (rotated) alpha fitted apart, each with its own indices.
pub fn separate(
    t: &Texels,
    mode: u8,
    rotation: u8,
    selection: u8,
    fe: &FitEffort,
    bound: f32,
) -> Option<Candidate> {
    let m = &MODES[usize::from(mode)];
    let swap = |mut v: [f32; 4]| {
        if rotation > 0 {
            v.swap(3, usize::from(rotation) - 1);
        }
        v
    };
    let px: [[f32; 4]; 16] = t.px.map(swap);
    let w = swap(t.w);
    let (colour_set, alpha_set) = if selection == 1 { (1, 0) } else { (0, 1) };
    let colour: [[f32; 3]; 16] = px.map(|p| [p[0], p[1], p[2]]);
    let alpha: [[f32; 1]; 16] = px.map(|p| [p[3]]);
    let cf = fit(
        &colour,
        &Setup {
            bits: [m.colour_bits; 3],
            pbits: m.pbits,
            index_bits: m.index_bits[colour_set],
            w: [w[0], w[1], w[2]],
        },
        fe,
    );
    if cf.err >= bound {
        return None;
    }
    let af = fit(
        &alpha,
        &Setup {
            bits: [m.alpha_bits],
            pbits: m.pbits,
            index_bits: m.index_bits[alpha_set],
            w: [w[3]],
        },
        fe,
    );
    let err = cf.err + af.err;
    if err >= bound {
        return None;
    }
    let mut params = Params {
        mode,
        rotation,
        index_selection: selection,
        ..Params::default()
    };
    for e in 0..2 {
        params.ends[0][e][..3].copy_from_slice(&cf.codes[e]);
        params.ends[0][e][3] = af.codes[e][0];
    }
    params.indices[colour_set] = cf.indices;
    params.indices[alpha_set] = af.indices;
    Some(Candidate { params, err })
}
