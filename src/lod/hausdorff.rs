//! Symmetric Hausdorff distance between two triangle meshes over one vertex
//! buffer, sampled on both surfaces: each side's samples (vertices, edge
//! midpoints and centroids of its triangles) measured against the other
//! side's surface, the larger of the two largest distances kept.

/// Samples per parallel task: each costs a ring search of a few cells.
const SAMPLES_PER_TASK: usize = 1024;

/// Grid cells per triangle of the searched surface: about one triangle per
/// cell keeps both the cell lists and the ring search short.
const CELLS_PER_TRIANGLE: f64 = 1.0;

/// Cells per axis at most (memory bound for long, thin models).
const MAX_CELLS_PER_AXIS: usize = 128;

use rayon::prelude::*;

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn add_scaled(a: V3, b: V3, s: f64) -> V3 {
    [a[0] + b[0] * s, a[1] + b[1] * s, a[2] + b[2] * s]
}

fn triangles(positions: &[[f32; 3]], indices: &[u32]) -> Vec<[V3; 3]> {
    let p = |i: u32| positions[i as usize].map(f64::from);
    indices
        .chunks_exact(3)
        .map(|t| [p(t[0]), p(t[1]), p(t[2])])
        .collect()
}

/// One surface measured against many: its triangles, their search grid
/// and its samples made once.
pub struct Reference {
    tris: Vec<[V3; 3]>,
    grid: Grid,
    samples: Vec<V3>,
    sampled: usize,
}

impl Reference {
    /// `indices` into `positions`, sampled on up to `sampled` triangles
    /// (see [`Reference::symmetric`]).
    pub fn new(positions: &[[f32; 3]], indices: &[u32], sampled: usize) -> Reference {
        let tris = triangles(positions, indices);
        let grid = Grid::new(&tris);
        let samples = samples(&tris, sampled);
        Reference {
            tris,
            grid,
            samples,
            sampled,
        }
    }

    /// The symmetric Hausdorff distance to `indices` (into the same
    /// positions), in the positions' units, each side sampled on up to the
    /// reference's number of triangles (every k-th beyond it).
    pub fn symmetric(&self, positions: &[[f32; 3]], indices: &[u32]) -> f64 {
        let other = triangles(positions, indices);
        if self.tris.is_empty() || other.is_empty() {
            return 0.0;
        }
        let to_other = Grid::new(&other);
        let away = farthest(&self.samples, &to_other, &other);
        let back = farthest(&samples(&other, self.sampled), &self.grid, &self.tris);
        away.max(back)
    }
}

fn samples(tris: &[[V3; 3]], most: usize) -> Vec<V3> {
    let step = tris.len().div_ceil(most.max(1)).max(1);
    let mut out = Vec::new();
    for t in tris.iter().step_by(step) {
        out.extend_from_slice(t);
        for k in 0..3 {
            let (u, v) = (t[k], t[(k + 1) % 3]);
            out.push(add_scaled(u, sub(v, u), 0.5));
        }
        let c = add_scaled(add_scaled(t[0], t[1], 1.0), t[2], 1.0);
        out.push(c.map(|x| x / 3.0));
    }
    out
}

/// The largest distance from one of `samples` to the surface `to` (searched
/// through `grid`). Samples are measured in parallel; the largest of them
/// does not depend on the order.
fn farthest(samples: &[V3], grid: &Grid, to: &[[V3; 3]]) -> f64 {
    samples
        .par_iter()
        .with_min_len(SAMPLES_PER_TASK)
        .map(|&q| grid.distance(to, q))
        .reduce(|| 0.0, f64::max)
}

struct Grid {
    lo: V3,
    cell: f64,
    dims: [usize; 3],
    cells: Vec<Vec<u32>>,
}

impl Grid {
    fn new(tris: &[[V3; 3]]) -> Grid {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in tris.iter().flatten() {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        let ext = sub(hi, lo);
        let longest = ext
            .iter()
            .copied()
            .fold(0.0, f64::max)
            .max(f64::MIN_POSITIVE);
        // Cells of the side that gives about CELLS_PER_TRIANGLE cells per
        // triangle over the box, flat axes counted at the longest's 1/1000.
        let volume: f64 = ext.iter().map(|e| e.max(longest * 1e-3)).product();
        let wanted = (tris.len() as f64 * CELLS_PER_TRIANGLE).max(1.0);
        let mut cell = (volume / wanted).cbrt();
        cell = cell.max(longest / MAX_CELLS_PER_AXIS as f64);
        let dims = ext.map(|e| ((e / cell).floor() as usize + 1).min(MAX_CELLS_PER_AXIS));
        let mut cells = vec![Vec::new(); dims[0] * dims[1] * dims[2]];
        let mut g = Grid {
            lo,
            cell,
            dims,
            cells: Vec::new(),
        };
        for (i, t) in tris.iter().enumerate() {
            let mut a = [usize::MAX; 3];
            let mut b = [0usize; 3];
            for v in t {
                let c = g.cell_of(*v);
                for k in 0..3 {
                    a[k] = a[k].min(c[k]);
                    b[k] = b[k].max(c[k]);
                }
            }
            for x in a[0]..=b[0] {
                for y in a[1]..=b[1] {
                    for z in a[2]..=b[2] {
                        cells[g.index([x, y, z])].push(i as u32);
                    }
                }
            }
        }
        g.cells = cells;
        g
    }

    fn cell_of(&self, p: V3) -> [usize; 3] {
        let mut c = [0usize; 3];
        for k in 0..3 {
            let f = ((p[k] - self.lo[k]) / self.cell).floor();
            c[k] = (f.max(0.0) as usize).min(self.dims[k] - 1);
        }
        c
    }

    fn index(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// Distance from `q` to the nearest triangle, searching rings of cells
    /// outward until no farther ring can hold a nearer one.
    fn distance(&self, tris: &[[V3; 3]], q: V3) -> f64 {
        let c = self.cell_of(q);
        // How far q is from its (clamped) cell's box: a ring r cells out
        // is at least r·cell − outside away.
        let mut outside2 = 0.0;
        for k in 0..3 {
            let lo = self.lo[k] + c[k] as f64 * self.cell;
            let hi = lo + self.cell;
            let d = (lo - q[k]).max(q[k] - hi).max(0.0);
            outside2 += d * d;
        }
        let outside = outside2.sqrt();
        let max_ring = self.dims.iter().copied().max().unwrap_or(1);
        let mut best = f64::INFINITY;
        for r in 0..=max_ring {
            let r_i = r as isize;
            for dz in -r_i..=r_i {
                for dy in -r_i..=r_i {
                    for dx in -r_i..=r_i {
                        if dx.abs().max(dy.abs()).max(dz.abs()) != r_i {
                            continue;
                        }
                        let cc = [c[0] as isize + dx, c[1] as isize + dy, c[2] as isize + dz];
                        if (0..3).any(|k| cc[k] < 0 || cc[k] >= self.dims[k] as isize) {
                            continue;
                        }
                        let cell = self.index(cc.map(|x| x as usize));
                        for &t in &self.cells[cell] {
                            best = best.min(point_triangle(q, &tris[t as usize]));
                        }
                    }
                }
            }
            if best <= r as f64 * self.cell - outside {
                break;
            }
        }
        best
    }
}

/// Distance from `p` to triangle `t` (closest point by Voronoi regions).
fn point_triangle(p: V3, t: &[V3; 3]) -> f64 {
    let [a, b, c] = *t;
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    let dist = |x: V3| {
        let d = sub(p, x);
        dot(d, d).sqrt()
    };
    if d1 <= 0.0 && d2 <= 0.0 {
        return dist(a);
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return dist(b);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return dist(add_scaled(a, ab, d1 / (d1 - d3)));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return dist(c);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return dist(add_scaled(a, ac, d2 / (d2 - d6)));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return dist(add_scaled(b, sub(c, b), w));
    }
    let denom = va + vb + vc;
    if denom.abs() < f64::MIN_POSITIVE {
        return dist(a).min(dist(b)).min(dist(c));
    }
    let (v, w) = (vb / denom, vc / denom);
    dist(add_scaled(add_scaled(a, ab, v), ac, w))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_surface_is_at_distance_zero_from_itself_and_a_dent_is_measured() {
        let positions = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.5, 0.5, 0.25],
        ];
        let flat = [0, 1, 2, 2, 1, 3];
        let reference = Reference::new(&positions, &flat, 100);
        assert!(reference.symmetric(&positions, &flat) < 1e-12);
        let tent = [0, 1, 4, 1, 3, 4, 3, 2, 4, 2, 0, 4];
        let d = reference.symmetric(&positions, &tent);
        assert!((d - 0.25).abs() < 1e-9, "{d}");
    }
}
