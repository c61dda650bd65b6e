//! Partition preselection: each partition scored by the error of fitting
//! each subset with a line through its texels (the scatter left off the
//! subset's principal axis, as in Intel's ISPC BC7 kernel), without any
//! quantisation. Only the best few are then fitted in full.

use super::fit::principal_axis;
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

/// The scatter of `n` texels with summed terms `s` off their principal axis.
fn line_error(s: &Terms, n: f32) -> f32 {
    if n < 2.0 {
        return 0.0;
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
    if trace <= 0.0 {
        return 0.0;
    }
    let v = principal_axis(&cov);
    let along: f32 = (0..4)
        .map(|a| v[a] * (0..4).map(|b| cov[a][b] * v[b]).sum::<f32>())
        .sum();
    (trace - along).max(0.0)
}

/// The `keep` partitions (of the first `count`) of a `subsets`-subset mode
/// with the lowest estimated error, best first.
pub fn rank(
    px: &[[f32; 4]; 16],
    w: &[f32; 4],
    subsets: usize,
    count: usize,
    keep: usize,
) -> Vec<u8> {
    let sw: [f32; 4] = std::array::from_fn(|c| w[c].max(0.0).sqrt());
    let per: [Terms; 16] = std::array::from_fn(|k| terms(&px[k], &sw));
    let mut total = [0f32; 14];
    for t in &per {
        for (a, b) in total.iter_mut().zip(t) {
            *a += b;
        }
    }
    let mut scored: Vec<(f32, u8)> = (0..count)
        .map(|p| {
            let mut sums = [[0f32; 14]; 3];
            let mut n = [0f32; 3];
            for (k, t) in per.iter().enumerate() {
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
            let e: f32 = (0..subsets).map(|s| line_error(&sums[s], n[s])).sum();
            (e, p as u8)
        })
        .collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    scored.truncate(keep);
    scored.into_iter().map(|(_, p)| p).collect()
}
