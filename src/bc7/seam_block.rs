//! One block's turn in the seam-aware search ([`super::seam_aware`]): with
//! its neighbours fixed, the block's share of the energy is a quadratic
//! vᵀMv − 2rᵀv per channel in its 16 decoded texels v (in \[0, 1\]). The
//! search scores candidates by their exact integer decode under that
//! quadratic:
//! * the block as it is;
//! * the regular encoder's block for the quadratic's unconstrained optimum
//!   M⁻¹r (the texels that would best close the seams), which may change
//!   the mode, partition, rotation or index selection;
//! * from each, the float endpoints that minimise the quadratic with the
//!   mode, partition, p-bits and indices fixed (decoded values are linear
//!   in the endpoints up to the spec's rounding), quantised, then ±1 moves
//!   of each endpoint code and a change of each index, while the energy
//!   falls.

// Small dense matrices indexed by texel and unknown in step.
#![allow(clippy::needless_range_loop)]

use super::encode::{self, Effort, Texels};
use super::fit::quantise;
use super::modes::{weights, MODES};
use super::params::Params;
use super::partitions::subset;

/// The block's quadratic: M for the colour channels and for alpha (their
/// seams may differ), r per channel RGBA.
pub struct Local {
    pub m: [[[f64; 16]; 16]; 2],
    pub r: [[f64; 16]; 4],
}

impl Local {
    fn m_of(&self, c: usize) -> &[[f64; 16]; 16] {
        &self.m[usize::from(c == 3)]
    }

    /// vᵀMv − 2rᵀv summed over the channels.
    pub fn energy(&self, v: &[[f64; 4]; 16]) -> f64 {
        let mut e = 0.0;
        for c in 0..4 {
            let m = self.m_of(c);
            for k in 0..16 {
                let mv: f64 = (0..16).map(|l| m[k][l] * v[l][c]).sum();
                e += v[k][c] * (mv - 2.0 * self.r[c][k]);
            }
        }
        e
    }

    /// Per channel, the texel values minimising the quadratic, clamped to
    /// \[0, 1\] (Cholesky; a tiny ridge keeps padding texels, which carry no
    /// weight, defined).
    fn optimum(&self) -> [[f64; 4]; 16] {
        let mut out = [[0.0; 4]; 16];
        for g in 0..2 {
            let Some(l) = cholesky(&self.m[g]) else {
                continue;
            };
            let channels = if g == 0 { 0..3 } else { 3..4 };
            for c in channels {
                let x = cholesky_solve(&l, &self.r[c]);
                for k in 0..16 {
                    out[k][c] = x[k].clamp(0.0, 1.0);
                }
            }
        }
        out
    }
}

/// Ridge added to M's diagonal for the optimum: far below any texel's weight.
const RIDGE: f64 = 1e-9;

fn cholesky(m: &[[f64; 16]; 16]) -> Option<[[f64; 16]; 16]> {
    let mut l = [[0.0; 16]; 16];
    for i in 0..16 {
        for j in 0..=i {
            let mut s = m[i][j] + if i == j { RIDGE } else { 0.0 };
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                if s <= 0.0 {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    Some(l)
}

fn cholesky_solve(l: &[[f64; 16]; 16], b: &[f64; 16]) -> [f64; 16] {
    let mut y = [0.0; 16];
    for i in 0..16 {
        let s: f64 = (0..i).map(|k| l[i][k] * y[k]).sum();
        y[i] = (b[i] - s) / l[i][i];
    }
    let mut x = [0.0; 16];
    for i in (0..16).rev() {
        let s: f64 = (i + 1..16).map(|k| l[k][i] * x[k]).sum();
        x[i] = (y[i] - s) / l[i][i];
    }
    x
}

/// The decoded texels of a block, in \[0, 1\].
pub fn values(p: &Params) -> [[f64; 4]; 16] {
    p.decode().map(|t| t.map(|v| f64::from(v) / 255.0))
}

/// What a block's search may do.
pub struct BlockSearch<'a> {
    pub effort: &'a Effort,
    /// Encoder weights (alpha's 0 when alpha does not matter).
    pub weights: [f32; 4],
    /// Whether the alpha channel is part of the energy.
    pub alpha: bool,
}

/// Rounds of ±1 code moves and index changes per candidate.
const ROUNDS: usize = 3;

impl BlockSearch<'_> {
    /// The best block found and its local energy; `current` when nothing
    /// beats it.
    /// `reencode`: also try the regular encoder's block for the seams'
    /// optimum (the first sweep does; later ones refine what they have).
    pub fn improve(&self, local: &Local, current: Params, reencode: bool) -> (Params, f64) {
        let mut best = (current, local.energy(&values(&current)));
        let mut starts = vec![current];
        if reencode {
            let target = local
                .optimum()
                .map(|t| t.map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8));
            starts.push(encode::encode_block(
                &Texels::new(&target, &self.weights),
                self.effort,
            ));
        }
        for start in starts {
            let e = local.energy(&values(&start));
            if e < best.1 {
                best = (start, e);
            }
            let refined = self.refine(local, start);
            if refined.1 < best.1 {
                best = refined;
            }
        }
        best
    }

    /// Endpoints solved and quantised for the block's structure, then
    /// code and index moves.
    fn refine(&self, local: &Local, start: Params) -> (Params, f64) {
        let mut p = self.solve_endpoints(local, start);
        let mut e = local.energy(&values(&p));
        let start_e = local.energy(&values(&start));
        if start_e < e {
            (p, e) = (start, start_e);
        }
        for _ in 0..ROUNDS {
            let mut moved = self.move_codes(local, &mut p, &mut e);
            moved |= move_indices(local, &mut p, &mut e);
            if !moved {
                break;
            }
        }
        (p, e)
    }

    /// The stored channels a block's endpoints may change in: alpha's only
    /// when it is part of the energy.
    fn stored_channels(&self, p: &Params) -> Vec<usize> {
        let has_alpha = MODES[usize::from(p.mode & 7)].alpha_bits > 0;
        (0..4)
            .filter(|&sc| sc < 3 || has_alpha)
            .filter(|&sc| self.alpha || output_channel(p, sc) != 3)
            .collect()
    }

    /// With mode, partition, p-bits and indices fixed: per stored channel,
    /// the float endpoints minimising the quadratic, quantised.
    fn solve_endpoints(&self, local: &Local, start: Params) -> Params {
        let m = &MODES[usize::from(start.mode & 7)];
        let mut p = start;
        let n = 2 * m.subsets;
        let sets = index_sets(&start);
        for sc in self.stored_channels(&start) {
            let out = output_channel(&start, sc);
            let set = if sc == 3 { sets.1 } else { sets.0 };
            let ws = weights(m.index_bits[set]);
            // A: texel k's value = Σ_j a[k][j]·x_j over the endpoints x.
            let mut a = [[0.0f64; 6]; 16];
            for k in 0..16 {
                let s = subset(m.subsets, usize::from(start.partition), k);
                let f = f64::from(ws[usize::from(start.indices[set][k]) & (ws.len() - 1)]) / 64.0;
                a[k][2 * s] = 1.0 - f;
                a[k][2 * s + 1] = f;
            }
            let mm = local.m_of(out);
            let mut h = [[0.0f64; 6]; 6];
            let mut g = [0.0f64; 6];
            for i in 0..n {
                for k in 0..16 {
                    if a[k][i] == 0.0 {
                        continue;
                    }
                    g[i] += a[k][i] * local.r[out][k];
                    for l in 0..16 {
                        let ml = mm[k][l] * a[k][i];
                        if ml != 0.0 {
                            for j in 0..n {
                                h[i][j] += ml * a[l][j];
                            }
                        }
                    }
                }
            }
            // Pull towards the current endpoints, so that an endpoint no
            // texel uses stays put.
            for i in 0..n {
                let cur = f64::from(start.endpoint(i / 2, i % 2)[sc]) / 255.0;
                h[i][i] += ENDPOINT_RIDGE;
                g[i] += ENDPOINT_RIDGE * cur;
            }
            let Some(x) = solve_small(h, g, n) else {
                continue;
            };
            let bits = if sc < 3 { m.colour_bits } else { m.alpha_bits };
            for (i, v) in x.iter().enumerate().take(n) {
                let (s, e) = (i / 2, i % 2);
                p.ends[s][e][sc] = quantise((v * 255.0) as f32, bits, m.pbits, start.pbits[s][e]);
            }
        }
        p
    }

    /// One round of ±1 moves of each endpoint code; true when one lowered
    /// the energy.
    fn move_codes(&self, local: &Local, p: &mut Params, e: &mut f64) -> bool {
        let m = &MODES[usize::from(p.mode & 7)];
        let mut moved = false;
        for sc in self.stored_channels(p) {
            let max = (1i32 << if sc < 3 { m.colour_bits } else { m.alpha_bits }) - 1;
            for s in 0..m.subsets {
                for end in 0..2 {
                    for step in [-1i32, 1] {
                        let q = i32::from(p.ends[s][end][sc]) + step;
                        if !(0..=max).contains(&q) {
                            continue;
                        }
                        let mut c = *p;
                        c.ends[s][end][sc] = q as u8;
                        let ce = local.energy(&values(&c));
                        if ce < *e - 1e-15 {
                            (*p, *e) = (c, ce);
                            moved = true;
                        }
                    }
                }
            }
        }
        moved
    }
}

/// Pull of the endpoint solve towards the current endpoints (values in
/// \[0, 1\]): negligible beside any texel's weight.
const ENDPOINT_RIDGE: f64 = 1e-6;

/// The index sets of colour and alpha (the same set outside modes 4, 5).
fn index_sets(p: &Params) -> (usize, usize) {
    let m = &MODES[usize::from(p.mode & 7)];
    match (m.separate_alpha(), p.index_selection) {
        (false, _) => (0, 0),
        (true, 0) => (0, 1),
        (true, _) => (1, 0),
    }
}

/// The output channel a stored channel lands in after the rotation.
fn output_channel(p: &Params, sc: usize) -> usize {
    let rot = usize::from(p.rotation);
    match rot {
        1..=3 if sc == 3 => rot - 1,
        1..=3 if sc == rot - 1 => 3,
        _ => sc,
    }
}

/// Each texel's index in each set tried at every value, kept where the
/// energy falls; true when one did. A change moves one texel by δ, which
/// changes the energy by δ²M_kk + 2δ(Mv − r)_k per channel.
fn move_indices(local: &Local, p: &mut Params, e: &mut f64) -> bool {
    let m = &MODES[usize::from(p.mode & 7)];
    let sets = if m.separate_alpha() { 2 } else { 1 };
    let mut v = values(p);
    let mut mv = [[0.0f64; 16]; 4];
    for c in 0..4 {
        let mm = local.m_of(c);
        for k in 0..16 {
            mv[c][k] = (0..16).map(|l| mm[k][l] * v[l][c]).sum();
        }
    }
    let mut moved = false;
    for set in 0..sets {
        let levels = 1u8 << m.index_bits[set];
        for k in 0..16 {
            for i in 0..levels {
                if i == p.indices[set][k] {
                    continue;
                }
                let mut c = *p;
                c.indices[set][k] = i;
                let t = c.decode_texel(k).map(|x| f64::from(x) / 255.0);
                let mut de = 0.0;
                for ch in 0..4 {
                    let d = t[ch] - v[k][ch];
                    if d != 0.0 {
                        let mm = local.m_of(ch);
                        de += d * d * mm[k][k] + 2.0 * d * (mv[ch][k] - local.r[ch][k]);
                    }
                }
                if de < -1e-15 {
                    for ch in 0..4 {
                        let d = t[ch] - v[k][ch];
                        if d != 0.0 {
                            let mm = local.m_of(ch);
                            for l in 0..16 {
                                mv[ch][l] += mm[l][k] * d;
                            }
                        }
                    }
                    v[k] = t;
                    *p = c;
                    *e += de;
                    moved = true;
                }
            }
        }
    }
    moved
}

/// Solves the `n`×`n` system by Gaussian elimination with partial
/// pivoting; `None` when it is singular.
fn solve_small(mut h: [[f64; 6]; 6], mut g: [f64; 6], n: usize) -> Option<[f64; 6]> {
    for col in 0..n {
        let piv = (col..n).max_by(|&a, &b| h[a][col].abs().total_cmp(&h[b][col].abs()))?;
        if h[piv][col].abs() < 1e-15 {
            return None;
        }
        h.swap(col, piv);
        g.swap(col, piv);
        for row in col + 1..n {
            let f = h[row][col] / h[col][col];
            for j in col..n {
                h[row][j] -= f * h[col][j];
            }
            g[row] -= f * g[col];
        }
    }
    let mut x = [0.0; 6];
    for i in (0..n).rev() {
        let s: f64 = (i + 1..n).map(|j| h[i][j] * x[j]).sum();
        x[i] = (g[i] - s) / h[i][i];
    }
    Some(x)
}
