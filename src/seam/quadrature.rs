//! Exact integration along half-edges (SPEC §3).
//!
//! Along a straight half-edge the bilinear interpolant is a quadratic in γ
//! inside each texel cell. Splitting \[0, 1\] wherever either half-edge crosses
//! an integer x or y leaves pieces on which every integrand we need (D: degree
//! 4; the C1 term: degree 2) is a polynomial of degree ≤ 5, which 3-point
//! Gauss–Legendre integrates exactly. So each integral becomes a weighted sum
//! of squared linear functionals of the texels: one [`QuadPoint`] per Gauss
//! point, shared by the metric, the erasure matrix and seam-aware BC1.

use super::grid::{Tap, TexelGrid};

const GAUSS_X: [f64; 3] = [-0.774_596_669_241_483_4, 0.0, 0.774_596_669_241_483_4];
const GAUSS_W: [f64; 3] = [5.0 / 9.0, 8.0 / 9.0, 5.0 / 9.0];

/// Pieces shorter than this (in γ) carry no measurable weight; skipping them
/// avoids evaluating a cell chosen from a midpoint that rounding put on a boundary.
const MIN_PIECE: f64 = 1e-14;

/// A half-edge in texel coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub start: [f64; 2],
    pub end: [f64; 2],
}

impl Segment {
    pub fn from_uv(grid: &TexelGrid, uv: [[f64; 2]; 2]) -> Self {
        Segment {
            start: grid.to_texel(uv[0]),
            end: grid.to_texel(uv[1]),
        }
    }

    #[inline]
    pub fn at(&self, g: f64) -> [f64; 2] {
        [
            self.start[0] + g * (self.end[0] - self.start[0]),
            self.start[1] + g * (self.end[1] - self.start[1]),
        ]
    }

    pub fn length(&self) -> f64 {
        let d = [self.end[0] - self.start[0], self.end[1] - self.start[1]];
        d[0].hypot(d[1])
    }

    /// Unit normal pointing towards `inside` (texel space), or `None` for a
    /// half-edge too short to have a direction.
    pub fn inward_normal(&self, inside: [f64; 2]) -> Option<[f64; 2]> {
        let d = [self.end[0] - self.start[0], self.end[1] - self.start[1]];
        let len = d[0].hypot(d[1]);
        if len < 1e-9 {
            return None;
        }
        let n = [-d[1] / len, d[0] / len];
        let to_inside = [inside[0] - self.start[0], inside[1] - self.start[1]];
        let s = n[0] * to_inside[0] + n[1] * to_inside[1];
        Some(if s < 0.0 { [-n[0], -n[1]] } else { n })
    }

    /// Appends every γ in (0,1) where this segment crosses an integer x or y.
    fn crossings(&self, out: &mut Vec<f64>) {
        for axis in 0..2 {
            let (a, b) = (self.start[axis], self.end[axis]);
            let d = b - a;
            if d == 0.0 {
                continue;
            }
            let (lo, hi) = (a.min(b), a.max(b));
            let mut k = lo.floor() + 1.0;
            while k < hi {
                out.push((k - a) / d);
                k += 1.0;
            }
        }
    }
}

/// Where the integrand is evaluated on one side of an edge.
#[derive(Clone, Copy, Debug)]
pub struct SidePoint {
    pub cell: [i64; 2],
    pub p: [f64; 2],
}

/// Calls `f(weight, points)` for every Gauss point of the pieces of \[0, 1\]
/// delimited by the cell crossings of all `segs`; `weight` integrates over
/// γ ∈ \[0, 1\] (the weights sum to 1). `points[k]` is the point on `segs[k]`.
pub fn for_each_gauss_point<const N: usize>(
    segs: &[Segment; N],
    mut f: impl FnMut(f64, &[SidePoint; N]),
) {
    let mut cuts = vec![0.0, 1.0];
    for s in segs {
        s.crossings(&mut cuts);
    }
    cuts.sort_by(f64::total_cmp);
    for w in cuts.windows(2) {
        let (g0, g1) = (w[0], w[1]);
        if g1 - g0 < MIN_PIECE {
            continue;
        }
        let mid = 0.5 * (g0 + g1);
        let half = 0.5 * (g1 - g0);
        let cells = segs.map(|s| {
            let p = s.at(mid);
            [p[0].floor() as i64, p[1].floor() as i64]
        });
        for q in 0..3 {
            let g = mid + half * GAUSS_X[q];
            let mut pts = [SidePoint {
                cell: [0, 0],
                p: [0.0, 0.0],
            }; N];
            for k in 0..N {
                pts[k] = SidePoint {
                    cell: cells[k],
                    p: segs[k].at(g),
                };
            }
            f(half * GAUSS_W[q], &pts);
        }
    }
}

/// A weighted squared linear functional: contributes `weight · (Σ taps·p)²`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QuadPoint {
    pub weight: f64,
    pub taps: [Tap; 8],
}

impl QuadPoint {
    /// Σ taps·p for channel `c` of interleaved `data`.
    #[inline]
    pub fn apply(&self, data: &[f32], channels: usize, c: usize) -> f64 {
        self.taps
            .iter()
            .map(|&(i, w)| w * f64::from(data[i as usize * channels + c]))
            .sum()
    }
}

/// Taps of the difference of two bilinear samples, `a − b`.
#[inline]
pub fn difference_taps(a: [Tap; 4], b: [Tap; 4]) -> [Tap; 8] {
    [
        a[0],
        a[1],
        a[2],
        a[3],
        (b[0].0, -b[0].1),
        (b[1].0, -b[1].1),
        (b[2].0, -b[2].1),
        (b[3].0, -b[3].1),
    ]
}

/// The seam difference B(e1(γ)) − B(e2(γ)) at the Gauss points of one seam,
/// each weighted by `scale` times its quadrature weight.
pub fn seam_difference_points(
    grid: &TexelGrid,
    e1: Segment,
    e2: Segment,
    scale: f64,
    out: &mut Vec<QuadPoint>,
) {
    for_each_gauss_point(&[e1, e2], |w, pts| {
        let a = grid.bilinear_taps(pts[0].cell, pts[0].p);
        let b = grid.bilinear_taps(pts[1].cell, pts[1].p);
        out.push(QuadPoint {
            weight: scale * w,
            taps: difference_taps(a, b),
        });
    });
}

/// The C1 mismatch ∇B(e1)·n1 + ∇B(e2)·n2 (inward unit normals) at the Gauss
/// points of one seam: zero when the texture continues smoothly across it.
pub fn seam_derivative_points(
    grid: &TexelGrid,
    e1: Segment,
    e2: Segment,
    n1: [f64; 2],
    n2: [f64; 2],
    scale: f64,
    out: &mut Vec<QuadPoint>,
) {
    for_each_gauss_point(&[e1, e2], |w, pts| {
        let a = grid.derivative_taps(pts[0].cell, pts[0].p, n1);
        let b = grid.derivative_taps(pts[1].cell, pts[1].p, n2);
        out.push(QuadPoint {
            weight: scale * w,
            taps: [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3]],
        });
    });
}

/// Calls `f(cell)` for every texel cell a segment passes through (with repeats).
pub fn for_each_cell(seg: Segment, mut f: impl FnMut([i64; 2])) {
    let mut cuts = vec![0.0, 1.0];
    seg.crossings(&mut cuts);
    cuts.sort_by(f64::total_cmp);
    for w in cuts.windows(2) {
        if w[1] - w[0] < MIN_PIECE {
            continue;
        }
        let p = seg.at(0.5 * (w[0] + w[1]));
        f([p[0].floor() as i64, p[1].floor() as i64]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Wrap;

    fn grid(n: usize) -> TexelGrid {
        TexelGrid {
            width: n,
            height: n,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        }
    }

    fn noise(n: usize) -> Vec<f32> {
        let mut s = 0x2545_f491_u32;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                (s % 1000) as f32 / 999.0
            })
            .collect()
    }

    #[test]
    fn crossings_split_at_integer_lines() {
        let s = Segment {
            start: [0.5, 0.25],
            end: [2.5, 0.75],
        };
        let mut c = Vec::new();
        s.crossings(&mut c);
        c.sort_by(f64::total_cmp);
        assert_eq!(c, vec![0.25, 0.75]);
        let mut cells = Vec::new();
        for_each_cell(s, |c| cells.push(c));
        assert_eq!(cells, vec![[0, 0], [1, 0], [2, 0]]);
    }

    /// Two half-edges of a seam, crossing many cells at unrelated angles.
    fn seam_pair() -> (Segment, Segment) {
        let e1 = Segment {
            start: [0.3, 1.7],
            end: [5.9, 3.2],
        };
        let e2 = Segment {
            start: [6.1, 6.4],
            end: [2.2, 4.05],
        };
        (e1, e2)
    }

    #[test]
    fn gauss_pieces_integrate_seam_difference_exactly() {
        // Brute force: midpoint rule with 200k samples vs the exact quadrature.
        let g = grid(8);
        let data = noise(64);
        let (e1, e2) = seam_pair();
        let mut pts = Vec::new();
        seam_difference_points(&g, e1, e2, 1.0, &mut pts);
        let exact: f64 = pts
            .iter()
            .map(|q| q.weight * q.apply(&data, 1, 0).powi(2))
            .sum();
        let n = 200_000;
        let brute: f64 = (0..n)
            .map(|i| {
                let t = (i as f64 + 0.5) / n as f64;
                let d = g.sample(&data, 1, 0, e1.at(t)) - g.sample(&data, 1, 0, e2.at(t));
                d * d
            })
            .sum::<f64>()
            / n as f64;
        assert!(
            (exact - brute).abs() <= 1e-8 * brute.max(1e-12),
            "{exact} vs {brute}"
        );
    }

    #[test]
    fn per_cell_polynomial_is_quadratic() {
        // Within one cell, B(e(γ)) sampled at Gauss points matches the direct sample.
        let g = grid(8);
        let data = noise(64);
        let e = Segment {
            start: [1.1, 1.2],
            end: [1.9, 1.7],
        };
        for_each_gauss_point(&[e], |_, pts| {
            let via_taps: f64 = g
                .bilinear_taps(pts[0].cell, pts[0].p)
                .iter()
                .map(|&(i, w)| w * f64::from(data[i as usize]))
                .sum();
            assert!((via_taps - g.sample(&data, 1, 0, pts[0].p)).abs() < 1e-12);
        });
    }

    #[test]
    fn derivative_points_integrate_c1_exactly() {
        let g = grid(8);
        let data = noise(64);
        let (e1, e2) = seam_pair();
        let n1 = e1.inward_normal([3.0, 0.0]).unwrap();
        let n2 = e2.inward_normal([6.0, 3.0]).unwrap();
        let mut pts = Vec::new();
        seam_derivative_points(&g, e1, e2, n1, n2, 1.0, &mut pts);
        let exact: f64 = pts
            .iter()
            .map(|q| q.weight * q.apply(&data, 1, 0).powi(2))
            .sum();
        let h = 1e-7;
        let dd = |e: Segment, n: [f64; 2], t: f64| {
            let p = e.at(t);
            (g.sample(&data, 1, 0, [p[0] + h * n[0], p[1] + h * n[1]])
                - g.sample(&data, 1, 0, [p[0] - h * n[0], p[1] - h * n[1]]))
                / (2.0 * h)
        };
        let n = 100_000;
        let brute: f64 = (0..n)
            .map(|i| {
                let t = (i as f64 + 0.5) / n as f64;
                (dd(e1, n1, t) + dd(e2, n2, t)).powi(2)
            })
            .sum::<f64>()
            / n as f64;
        assert!((exact - brute).abs() <= 1e-4 * brute, "{exact} vs {brute}");
    }

    #[test]
    fn inward_normal_points_to_the_opposite_vertex() {
        let e = Segment {
            start: [0.0, 0.0],
            end: [2.0, 0.0],
        };
        assert_eq!(e.inward_normal([1.0, 5.0]), Some([-0.0, 1.0]));
        assert_eq!(e.inward_normal([1.0, -5.0]), Some([0.0, -1.0]));
        let point = Segment {
            start: [1.0, 1.0],
            end: [1.0, 1.0],
        };
        assert_eq!(point.inward_normal([0.0, 0.0]), None);
    }
}
