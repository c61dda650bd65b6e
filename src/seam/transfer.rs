//! Prolongation and restriction between two multigrid levels.
//!
//! Exact nodes map to themselves; a lattice node interpolates bilinearly from
//! the lattice of twice its spacing. Both directions are read off two index
//! grids (which unknown sits at each lattice point, on either level) instead
//! of a stored matrix: on a 2048² band that is 40 MB instead of about 90,
//! and coarsening writes no matrix at all.

use rayon::prelude::*;

use super::multigrid::Node;
use super::sparse::{by_channels, Rows};

/// No unknown at a lattice point; in a node's place: not on the lattice.
const NONE: u32 = u32::MAX;
/// Coarse unknowns per parallel task of [`Transfer::restrict`], fine ones
/// per task of [`Transfer::prolong_add`].
const CHUNK: usize = 8192;
/// Fine unknowns per parallel task of [`Transfer::coarsen`].
const COARSEN_RUN: usize = 1 << 14;
/// Coarse unknowns per task of [`Transfer::restrict_residual`]: its fine
/// residual span (about three times as many values) stays in cache.
const SPAN_CHUNK: usize = 4096;

/// The coarse unknowns a fine one interpolates from ([`Transfer::parent_square`]).
#[derive(Clone, Copy, Debug)]
pub enum Square {
    /// An exact node (its coarse index).
    Exact(u32),
    /// The lattice points (x, y) to (x + 1, y + 1), weighted by `wx[dx]·wy[dy]`.
    At {
        x: u32,
        y: u32,
        wx: [f64; 2],
        wy: [f64; 2],
    },
}

/// The bilinear weights along one axis: a coarse node's own point, then the
/// two points halfway to its neighbours.
const HALF: f64 = 0.5;

/// A lattice of unknown indices, `NONE` where no unknown sits.
#[derive(Clone, Debug, Default)]
struct Grid {
    w: u32,
    h: u32,
    id: Vec<u32>,
}

impl Grid {
    #[inline]
    fn at(&self, x: u32, y: u32) -> u32 {
        if x < self.w && y < self.h {
            self.id[(y * self.w + x) as usize]
        } else {
            NONE
        }
    }
}

#[derive(Clone, Debug, Default)]
pub struct Transfer {
    pub fine: usize,
    pub coarse: usize,
    /// Per fine unknown: its lattice point, or [NONE, its coarse unknown].
    fine_at: Vec<[u32; 2]>,
    /// Per coarse unknown: its lattice point, or [NONE, its fine unknown].
    coarse_at: Vec<[u32; 2]>,
    fine_grid: Grid,
    coarse_grid: Grid,
    /// Per run of [`SPAN_CHUNK`] coarse unknowns, the fine unknowns they
    /// read: first and one past the last.
    spans: Vec<(usize, usize)>,
}

/// Along one axis: an even coordinate sits on a coarse node, an odd one halfway.
#[inline]
fn parents(x: u32) -> ([(u32, f64); 2], usize) {
    if x.is_multiple_of(2) {
        ([(x / 2, 1.0), (0, 0.0)], 1)
    } else {
        ([(x / 2, HALF), (x / 2 + 1, HALF)], 2)
    }
}

impl Transfer {
    /// One coarsening step from unknowns at `nodes`; returns the coarse
    /// unknowns' places too. Coarse unknowns are numbered in the order the
    /// fine ones first reach them, so an exact node keeps its rank among
    /// the exact nodes and the lattice stays in about raster order.
    pub fn coarsen(nodes: &[Node]) -> (Transfer, Vec<Node>) {
        let (fw, fh) = nodes
            .par_iter()
            .map(|n| match *n {
                Node::Lattice(x, y) => (x + 1, y + 1),
                Node::Exact => (0, 0),
            })
            .reduce(|| (0, 0), |a, b| (a.0.max(b.0), a.1.max(b.1)));
        let (cw, ch) = (fw / 2 + 1, fh / 2 + 1);
        let mut fine_grid = Grid {
            w: fw,
            h: fh,
            id: crate::heap::filled(fw as usize * fh as usize, NONE),
        };
        for (i, n) in nodes.iter().enumerate() {
            if let Node::Lattice(x, y) = *n {
                fine_grid.id[(y * fw + x) as usize] = i as u32;
            }
        }
        // A coarse lattice point is numbered when the lowest fine unknown
        // that reaches it comes: the same numbering as one pass in fine
        // order that creates each coarse point on first reach. So each
        // point first gets that lowest unknown (NONE, above every index,
        // where none reaches it); then each run of fine unknowns lists the
        // coarse points it brings, in parallel, and the runs are joined in
        // order. Every listed point is numbered below, the others stay
        // NONE: the grid becomes the coarse index grid in place.
        let mut coarse_grid = Grid {
            w: cw,
            h: ch,
            id: crate::heap::filled(cw as usize * ch as usize, NONE),
        };
        coarse_grid
            .id
            .par_chunks_mut(cw as usize)
            .enumerate()
            .for_each(|(cy, row)| {
                let cy = cy as u32;
                let ys = (2 * cy).saturating_sub(1)..(2 * cy + 2).min(fh);
                for (cx, first) in (0..cw).zip(row.iter_mut()) {
                    let xs = (2 * cx).saturating_sub(1) as usize..(2 * cx + 2).min(fw) as usize;
                    for fy in ys.clone() {
                        let at = (fy * fw) as usize;
                        for &j in &fine_grid.id[at + xs.start..at + xs.end] {
                            *first = (*first).min(j);
                        }
                    }
                }
            });
        let runs: Vec<Vec<[u32; 2]>> = nodes
            .par_chunks(COARSEN_RUN)
            .enumerate()
            .map(|(b, run)| {
                let mut out = Vec::with_capacity(run.len() / 3);
                for (k, n) in run.iter().enumerate() {
                    let i = (b * COARSEN_RUN + k) as u32;
                    match *n {
                        Node::Exact => out.push([NONE, i]),
                        Node::Lattice(x, y) => {
                            let (py, ny) = parents(y);
                            let (px, nx) = parents(x);
                            for &(cy, _) in &py[..ny] {
                                for &(cx, _) in &px[..nx] {
                                    if coarse_grid.at(cx, cy) == i {
                                        out.push([cx, cy]);
                                    }
                                }
                            }
                        }
                    }
                }
                out
            })
            .collect();
        let mut coarse_at = Vec::with_capacity(runs.iter().map(Vec::len).sum());
        for run in runs {
            coarse_at.extend(run);
        }
        let mut fine_at: Vec<[u32; 2]> = nodes
            .par_iter()
            .map(|n| match *n {
                Node::Lattice(x, y) => [x, y],
                Node::Exact => [NONE, NONE],
            })
            .collect();
        for (k, &[x, y]) in coarse_at.iter().enumerate() {
            if x == NONE {
                fine_at[y as usize][1] = k as u32;
            } else {
                coarse_grid.id[(y * cw + x) as usize] = k as u32;
            }
        }
        let coarse: Vec<Node> = coarse_at
            .par_iter()
            .map(|&[x, y]| {
                if x == NONE {
                    Node::Exact
                } else {
                    Node::Lattice(x, y)
                }
            })
            .collect();
        let mut t = Transfer {
            fine: nodes.len(),
            coarse: coarse.len(),
            fine_at,
            coarse_at,
            fine_grid,
            coarse_grid,
            spans: Vec::new(),
        };
        t.spans = (0..t.coarse.div_ceil(SPAN_CHUNK))
            .into_par_iter()
            .map(|b| {
                let (mut lo, mut hi) = (usize::MAX, 0);
                for k in b * SPAN_CHUNK..((b + 1) * SPAN_CHUNK).min(t.coarse) {
                    t.for_each_fine(k, |i, _| {
                        lo = lo.min(i);
                        hi = hi.max(i + 1);
                    });
                }
                (lo.min(hi), hi)
            })
            .collect();
        (t, coarse)
    }

    /// The coarse unknowns fine unknown `i` interpolates from, with weights
    /// (the first `len` of them).
    #[inline]
    pub fn coarse_of(&self, i: usize) -> ([(usize, f64); 4], usize) {
        let mut out = [(0, 0.0); 4];
        let mut len = 0;
        self.for_each_parent(i, |k, w| {
            out[len] = (k, w);
            len += 1;
        });
        (out, len)
    }

    /// Calls `f` with each coarse unknown fine unknown `i` interpolates
    /// from and its weight, in the order of [`Self::coarse_of`].
    #[inline(always)]
    pub fn for_each_parent(&self, i: usize, mut f: impl FnMut(usize, f64)) {
        let [x, y] = self.fine_at[i];
        if x == NONE {
            f(y as usize, 1.0);
            return;
        }
        let (py, ny) = parents(y);
        let (px, nx) = parents(x);
        for &(cy, wy) in &py[..ny] {
            for &(cx, wx) in &px[..nx] {
                // A fine lattice node's parents are on the grid (`coarsen`).
                let k = self.coarse_grid.id[(cy * self.coarse_grid.w + cx) as usize];
                f(k as usize, wx * wy);
            }
        }
    }

    /// The coarse points fine unknown `i` interpolates from, as the 2×2
    /// square from its lower corner (weight 0 on the far side of an even
    /// coordinate), or its exact coarse unknown.
    #[inline(always)]
    pub fn parent_square(&self, i: usize) -> Square {
        let [x, y] = self.fine_at[i];
        if x == NONE {
            return Square::Exact(y);
        }
        // `parents` leaves weight 0 in an even coordinate's second place.
        let ([(bx, wx0), (_, wx1)], _) = parents(x);
        let ([(by, wy0), (_, wy1)], _) = parents(y);
        Square::At {
            x: bx,
            y: by,
            wx: [wx0, wx1],
            wy: [wy0, wy1],
        }
    }

    /// Whether fine unknown `i` is a lattice node and `nb` (above, left,
    /// right, below) are the lattice nodes beside it.
    #[inline]
    pub fn beside_on_lattice(&self, i: usize, nb: [u32; 4]) -> bool {
        let [x, y] = self.fine_at[i];
        if x == NONE || x == 0 || y == 0 {
            return false;
        }
        let at = [[x, y - 1], [x - 1, y], [x + 1, y], [x, y + 1]];
        nb.iter()
            .zip(at)
            .all(|(&j, xy)| self.fine_at.get(j as usize) == Some(&xy))
    }

    /// The coarse unknown at lattice point (x, y); `None` if there is none.
    #[inline]
    pub fn coarse_at_point(&self, x: u32, y: u32) -> Option<usize> {
        let k = self.coarse_grid.at(x, y);
        (k != NONE).then_some(k as usize)
    }

    /// Coarse unknown `k`'s lattice point, `None` for an exact node.
    #[inline]
    pub fn placement(&self, k: usize) -> Option<[u32; 2]> {
        let [x, y] = self.coarse_at[k];
        (x != NONE).then_some([x, y])
    }

    /// The fine unknowns coarse unknown `k` contributes to, with weights, in
    /// raster order (the first `len` of them).
    #[inline]
    pub fn fine_of(&self, k: usize) -> ([(usize, f64); 9], usize) {
        let mut out = [(0, 0.0); 9];
        let mut len = 0;
        self.for_each_fine(k, |i, w| {
            out[len] = (i, w);
            len += 1;
        });
        (out, len)
    }

    /// Calls `f` with each fine unknown coarse unknown `k` contributes to
    /// and its weight, in the order of [`Self::fine_of`]. (A closure, not an
    /// array: the restriction's inner loop, at about 5 ns a tap through the
    /// array, spent as long gathering as computing the residual.)
    #[inline(always)]
    pub fn for_each_fine(&self, k: usize, mut f: impl FnMut(usize, f64)) {
        let [x, y] = self.coarse_at[k];
        if x == NONE {
            f(y as usize, 1.0);
            return;
        }
        let g = &self.fine_grid;
        let (w, h) = (g.w as usize, g.h as usize);
        let (x, y) = (2 * x as usize, 2 * y as usize);
        let columns = x.saturating_sub(1)..(x + 2).min(w);
        for fy in y.saturating_sub(1)..(y + 2).min(h) {
            let wy = if fy == y { 1.0 } else { HALF };
            let row = &g.id[fy * w..(fy + 1) * w];
            for fx in columns.clone() {
                let i = row[fx];
                if i != NONE {
                    let wx = if fx == x { 1.0 } else { HALF };
                    f(i as usize, wx * wy);
                }
            }
        }
    }

    /// (Pᵀ r) at coarse unknown `k`, with `r` holding fine unknowns from `first` on.
    #[inline(always)]
    fn gather<const C: usize>(&self, k: usize, r: &[f64], first: usize) -> [f64; C] {
        let mut s = [0.0f64; C];
        self.for_each_fine(k, |i, w| {
            let ri = &r[(i - first) * C..(i - first + 1) * C];
            for c in 0..C {
                s[c] += w * ri[c];
            }
        });
        s
    }

    /// rc = Pᵀ r.
    pub fn restrict(&self, r: &[f64], rc: &mut [f64], ch: usize) {
        by_channels!(ch, self.restrict_n(r, rc))
    }

    fn restrict_n<const C: usize>(&self, r: &[f64], rc: &mut [f64]) {
        rc.par_chunks_mut(CHUNK * C)
            .enumerate()
            .for_each(|(b, out)| {
                for (k, o) in out.chunks_exact_mut(C).enumerate() {
                    o.copy_from_slice(&self.gather::<C>(b * CHUNK + k, r, 0));
                }
            });
    }

    /// rc = Pᵀ (r − A z), without the fine residual as a whole: each task
    /// computes the span of fine rows its coarse unknowns read (coarse
    /// unknowns are numbered in the order fine ones first reach them, so a
    /// run of them reads a run of fine rows, give or take two lattice rows;
    /// [`Self::coarsen`] finds the spans) and restricts from there. The same
    /// bits as [`Self::restrict`] on the residual, one pass and one fine
    /// vector less.
    pub fn restrict_residual<A: Rows>(
        &self,
        a: &A,
        r: &[f64],
        z: &[f64],
        rc: &mut [f64],
        ch: usize,
    ) {
        by_channels!(ch, self.restrict_residual_n(a, r, z, rc))
    }

    fn restrict_residual_n<const C: usize>(
        &self,
        a: &impl Rows,
        r: &[f64],
        z: &[f64],
        rc: &mut [f64],
    ) {
        rc.par_chunks_mut(SPAN_CHUNK * C)
            .zip(&self.spans)
            .enumerate()
            .for_each_init(Vec::<f64>::new, |res, (b, (out, &(lo, hi)))| {
                res.resize((hi - lo) * C, 0.0);
                a.residual_span(lo..hi, r, z, res, C);
                for (k, o) in out.chunks_exact_mut(C).enumerate() {
                    o.copy_from_slice(&self.gather::<C>(b * SPAN_CHUNK + k, res, lo));
                }
            });
    }

    /// z += P zc.
    pub fn prolong_add(&self, zc: &[f64], z: &mut [f64], ch: usize) {
        by_channels!(ch, self.prolong_add_n(zc, z))
    }

    fn prolong_add_n<const C: usize>(&self, zc: &[f64], z: &mut [f64]) {
        z.par_chunks_mut(CHUNK * C)
            .enumerate()
            .for_each(|(b, out)| {
                for (k, o) in out.chunks_exact_mut(C).enumerate() {
                    self.for_each_parent(b * CHUNK + k, |j, w| {
                        let zj = &zc[j * C..(j + 1) * C];
                        for c in 0..C {
                            o[c] += w * zj[c];
                        }
                    });
                }
            });
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    #[test]
    fn both_directions_describe_one_matrix() {
        // A ragged lattice with holes and two exact nodes among it.
        let mut nodes = Vec::new();
        for y in 0..7u32 {
            for x in 0..9u32 {
                if (x * 7 + y * 3) % 5 != 0 {
                    nodes.push(Node::Lattice(x, y));
                }
            }
            if y % 3 == 1 {
                nodes.push(Node::Exact);
            }
        }
        let (p, coarse) = Transfer::coarsen(&nodes);
        assert_eq!(p.coarse, coarse.len());
        let mut by_rows = vec![vec![0.0; p.coarse]; p.fine];
        for (i, row) in by_rows.iter_mut().enumerate() {
            let (c, len) = p.coarse_of(i);
            let total: f64 = c[..len].iter().map(|e| e.1).sum();
            // Every fine node interpolates with weights summing to one.
            assert_eq!(total, 1.0, "row {i}");
            for &(k, w) in &c[..len] {
                row[k] += w;
            }
        }
        for k in 0..p.coarse {
            let (f, len) = p.fine_of(k);
            let mut col = vec![0.0; p.fine];
            for &(i, w) in &f[..len] {
                col[i] += w;
            }
            for i in 0..p.fine {
                assert_eq!(col[i], by_rows[i][k], "({i}, {k})");
            }
        }
        // And restriction is the transpose of prolongation: <P zc, r> = <zc, Pᵀ r>.
        let r: Vec<f64> = (0..p.fine).map(|i| (i as f64).sin()).collect();
        let zc: Vec<f64> = (0..p.coarse).map(|k| (k as f64 * 0.7).cos()).collect();
        let mut z = vec![0.0; p.fine];
        p.prolong_add(&zc, &mut z, 1);
        let mut rc = vec![0.0; p.coarse];
        p.restrict(&r, &mut rc, 1);
        let lhs: f64 = z.iter().zip(&r).map(|(a, b)| a * b).sum();
        let rhs: f64 = zc.iter().zip(&rc).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() < 1e-12);
    }

    #[test]
    fn fused_restriction_of_the_residual_matches_the_two_passes() {
        // A lattice taller than one parallel task of coarse rows, with holes
        // and exact nodes, under a matrix that also couples distant rows.
        let mut nodes = Vec::new();
        for y in 0..130u32 {
            for x in 0..300u32 {
                if (x * 7 + y * 3) % 11 != 0 {
                    nodes.push(Node::Lattice(x, y));
                }
                if (x + y) % 97 == 0 {
                    nodes.push(Node::Exact);
                }
            }
        }
        let n = nodes.len();
        let mut rows = vec![std::collections::BTreeMap::<u32, f64>::new(); n];
        for i in 0..n {
            *rows[i].entry(i as u32).or_default() += 5.0;
            for j in [i + 1, i + 300, (i * 7919) % n] {
                if j < n && j != i {
                    let v = -(((i + j) % 5) as f64) * 0.25 - 0.1;
                    *rows[i].entry(j as u32).or_default() += v;
                    *rows[j].entry(i as u32).or_default() += v;
                    *rows[i].entry(i as u32).or_default() -= v;
                    *rows[j].entry(j as u32).or_default() -= v;
                }
            }
        }
        let (mut ptr, mut col, mut val) = (vec![0], Vec::new(), Vec::new());
        for row in &rows {
            for (&j, &v) in row {
                col.push(j);
                val.push(v);
            }
            ptr.push(col.len());
        }
        let a = crate::seam::sparse::SymCsr::from_parts(ptr, col, val).unwrap();
        let (p, _) = Transfer::coarsen(&nodes);
        assert!(p.coarse > CHUNK, "several tasks");
        let ch = 3;
        let r: Vec<f64> = (0..n * ch).map(|i| (i as f64 * 0.37).sin()).collect();
        let z: Vec<f64> = (0..n * ch).map(|i| (i as f64 * 0.11).cos()).collect();
        let mut res = vec![0.0; n * ch];
        a.residual(&r, &z, &mut res, ch);
        let mut two = vec![0.0; p.coarse * ch];
        p.restrict(&res, &mut two, ch);
        let mut fused = vec![1.0; p.coarse * ch];
        p.restrict_residual(&a, &r, &z, &mut fused, ch);
        assert_eq!(two, fused);
    }
}
