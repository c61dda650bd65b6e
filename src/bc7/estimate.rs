//! Partition preselection: each partition scored by the error of fitting
//! each subset with a line through its texels (the scatter left off the
//! subset's principal axis), plus the error of quantising the texels along
//! that axis to the mode's index levels, without any endpoint quantisation.
//! Only the best few are then fitted in full.
//!
//! The second term matters on smooth art: there every partition leaves
//! almost nothing off its axes, and what tells partitions apart is how
//! finely each subset's indices step along its range. Texels spread evenly
//! over a range with variance λ (summed over the subset) and quantised to
//! L levels leave λ/(L−1)² of squared error.

use super::partitions::subset;

/// Per-texel terms summed by subset: the weighted value y (4) and the
/// upper triangle of y·yᵀ (10).
type Terms = [f32; 14];

fn terms(t: &[f32; 4], sw: &[f32; 4]) -> Terms {
    let y: [f32; 4] = std::array::from_fn(|c| t[c] * sw[c]);
    let mut out = [0f32; 14];
    out[..4].copy_from_slice(&y);
    let mut i = 4;
    for a in 0..4 {
        for b in a..4 {
            out[i] = y[a] * y[b];
            i += 1;
        }
    }
    out
}

/// The scatter of `n` texels with summed terms `s`: (off their principal
/// axis, along it). The axis's variance is the Rayleigh quotient after three power
/// steps on the covariance scaled by its trace (which keeps f32 in range
/// without normalising at each step).
fn line_error(s: &Terms, n: f32) -> (f32, f32) {
    if n < 2.0 {
        return (0.0, 0.0);
    }
    let mut cov = [[0f32; 4]; 4];
    let mut i = 4;
    for a in 0..4 {
        for b in a..4 {
            let v = s[i] - s[a] * s[b] / n;
            cov[a][b] = v;
            cov[b][a] = v;
            i += 1;
        }
    }
    let trace = cov[0][0] + cov[1][1] + cov[2][2] + cov[3][3];
    if trace <= 1e-3 {
        return (0.0, 0.0);
    }
    let inv = 1.0 / trace;
    let mut m = cov;
    for row in &mut m {
        for v in row.iter_mut() {
            *v *= inv;
        }
    }
    let start = (0..4)
        .max_by(|&a, &b| m[a][a].total_cmp(&m[b][b]))
        .unwrap_or(0);
    let mul = |v: &[f32; 4]| -> [f32; 4] {
        std::array::from_fn(|a| m[a][0] * v[0] + m[a][1] * v[1] + m[a][2] * v[2] + m[a][3] * v[3])
    };
    let v = mul(&mul(&m[start]));
    let mv = mul(&v);
    let vv: f32 = v.iter().map(|x| x * x).sum();
    if vv <= 0.0 {
        return (0.0, 0.0);
    }
    let along = (v.iter().zip(&mv).map(|(a, b)| a * b).sum::<f32>() / vv).clamp(0.0, 1.0);
    (trace * (1.0 - along), trace * along)
}

/// Per partition (of 64) of a `subsets`-subset mode and per subset: the
/// scatter off the subset's axis and along it.
pub struct Scores {
    subsets: usize,
    per: [[(f32, f32); 3]; 64],
}

impl Scores {
    pub fn new(px: &[[f32; 4]; 16], w: &[f32; 4], subsets: usize) -> Scores {
        let sw: [f32; 4] = std::array::from_fn(|c| w[c].max(0.0).sqrt());
        let per_texel: [Terms; 16] = std::array::from_fn(|k| terms(&px[k], &sw));
        let mut total = [0f32; 14];
        for t in &per_texel {
            for (a, b) in total.iter_mut().zip(t) {
                *a += b;
            }
        }
        let mut per = [[(0f32, 0f32); 3]; 64];
        for (p, out) in per.iter_mut().enumerate() {
            let mut sums = [[0f32; 14]; 3];
            let mut n = [0f32; 3];
            for (k, t) in per_texel.iter().enumerate() {
                let s = subset(subsets, p, k);
                if s == 0 {
                    continue;
                }
                n[s] += 1.0;
                for (a, b) in sums[s].iter_mut().zip(t) {
                    *a += b;
                }
            }
            n[0] = 16.0 - n[1] - n[2];
            for i in 0..14 {
                sums[0][i] = total[i] - sums[1][i] - sums[2][i];
            }
            for s in 0..subsets {
                out[s] = line_error(&sums[s], n[s]);
            }
        }
        Scores { subsets, per }
    }

    /// The `keep` partitions among the first `count` with the lowest
    /// estimate for indices of `index_bits` bits, best first.
    pub fn best(&self, index_bits: u32, count: usize, keep: usize) -> Vec<u8> {
        let steps = ((1u32 << index_bits) - 1) as f32;
        let along = 1.0 / (steps * steps);
        let mut scored: Vec<(f32, u8)> = self.per[..count.min(64)]
            .iter()
            .enumerate()
            .map(|(p, s)| {
                let e: f32 = s[..self.subsets]
                    .iter()
                    .map(|(off, on)| off + on * along)
                    .sum();
                (e, p as u8)
            })
            .collect();
        let by_error = |a: &(f32, u8), b: &(f32, u8)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        if keep < scored.len() && keep > 0 {
            scored.select_nth_unstable_by(keep - 1, by_error);
            scored.truncate(keep);
        }
        scored.sort_unstable_by(by_error);
        scored.into_iter().map(|(_, p)| p).collect()
    }
}
