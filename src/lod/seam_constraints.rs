//! The seam test of seam-aware decimation (Liu et al. 2017, §5): which
//! vertices may move, and whether a simplified mesh kept every seam as the
//! erased texture expects it.
//!
//! A seam vertex may collapse only along its seam onto a seam neighbour,
//! and only where, on both sides, the two seam edges it joins are collinear
//! in UV with the same length ratio: then both sides map the new, longer
//! edge the same way, and the texels erased along the two old edges lie
//! along it. Seam corners (other than two seam edges), vertices where more
//! than two wedges meet, and boundary or non-manifold vertices never move.

use std::collections::{BTreeMap, HashMap};

use super::simplify::Mesh;

/// The connectivity of a mesh welded by position: wedges (vertices) that
/// share a position are one welded vertex, as the simplifier sees them.
pub struct Topology {
    /// Welded id of each vertex.
    pub weld: Vec<u32>,
    /// Per welded edge (lower id, higher id): its half-edges as the wedges
    /// at the lower and at the higher end.
    edges: HashMap<(u32, u32), Vec<(u32, u32)>>,
    /// Per welded vertex: its seam neighbours (welded ids).
    seam_neighbours: Vec<Vec<u32>>,
    /// Per welded vertex: the distinct wedges the triangles use there.
    wedges: Vec<Vec<u32>>,
    /// Per welded vertex: on a boundary or a non-manifold edge.
    fixed: Vec<bool>,
}

/// Counts of what the seam test decided.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LockCounts {
    /// Welded vertices on a seam.
    pub seam: usize,
    /// Of those, how many are locked.
    pub seam_locked: usize,
    /// Boundary and non-manifold welded vertices (locked).
    pub fixed: usize,
}

fn edge_key(a: u32, b: u32) -> (u32, u32) {
    (a.min(b), a.max(b))
}

impl Topology {
    pub fn new(mesh: &Mesh<'_>) -> Topology {
        let mut ids: HashMap<[u32; 3], u32> = HashMap::new();
        let weld: Vec<u32> = mesh
            .positions
            .iter()
            .map(|p| {
                let next = ids.len() as u32;
                *ids.entry(p.map(f32::to_bits)).or_insert(next)
            })
            .collect();
        let n = ids.len();
        let mut edges: HashMap<(u32, u32), Vec<(u32, u32)>> = HashMap::new();
        let mut wedges: Vec<Vec<u32>> = vec![Vec::new(); n];
        for t in mesh.indices.chunks_exact(3) {
            for k in 0..3 {
                let (a, b) = (
                    mesh.uv_wedge[t[k] as usize],
                    mesh.uv_wedge[t[(k + 1) % 3] as usize],
                );
                let (wa, wb) = (weld[a as usize], weld[b as usize]);
                if !wedges[wa as usize].contains(&a) {
                    wedges[wa as usize].push(a);
                }
                if wa == wb {
                    continue;
                }
                let half = if wa < wb { (a, b) } else { (b, a) };
                edges.entry(edge_key(wa, wb)).or_default().push(half);
            }
        }
        let mut seam_neighbours: Vec<Vec<u32>> = vec![Vec::new(); n];
        let mut fixed = vec![false; n];
        // Sorted, so that neighbour lists (and every walk along them) do
        // not depend on the hash map's order.
        let mut keys: Vec<&(u32, u32)> = edges.keys().collect();
        keys.sort_unstable();
        for &(lo, hi) in keys {
            let halves = &edges[&(lo, hi)];
            match halves.as_slice() {
                [h1, h2] => {
                    if h1 != h2 {
                        seam_neighbours[lo as usize].push(hi);
                        seam_neighbours[hi as usize].push(lo);
                    }
                }
                _ => {
                    fixed[lo as usize] = true;
                    fixed[hi as usize] = true;
                }
            }
        }
        Topology {
            weld,
            edges,
            seam_neighbours,
            wedges,
            fixed,
        }
    }

    /// The wedge at `to` of the half-edge (`from`, `to`) whose wedge at
    /// `from` is `wedge`: following one side of a seam one edge on.
    fn across(&self, from: u32, to: u32, wedge: u32) -> Option<u32> {
        let halves = self.edges.get(&edge_key(from, to))?;
        halves.iter().find_map(|&(lo, hi)| {
            if from < to {
                (lo == wedge).then_some(hi)
            } else {
                (hi == wedge).then_some(lo)
            }
        })
    }

    /// Per vertex, whether it is locked, and whether it is a seam vertex
    /// free to move along its seam: the seam test of every welded vertex.
    pub fn seam_locks(
        &self,
        mesh: &Mesh<'_>,
        tolerance: f64,
    ) -> (Vec<bool>, Vec<bool>, LockCounts) {
        let mut welded_lock = vec![false; self.wedges.len()];
        let mut welded_free = vec![false; self.wedges.len()];
        let mut counts = LockCounts::default();
        for w in 0..self.wedges.len() {
            if self.fixed[w] {
                welded_lock[w] = true;
                counts.fixed += 1;
                continue;
            }
            let neighbours = &self.seam_neighbours[w];
            if neighbours.is_empty() {
                continue;
            }
            counts.seam += 1;
            let free = neighbours.len() == 2
                && self.wedges[w].len() == 2
                && self.collapsible(mesh, w as u32, neighbours[0], neighbours[1], tolerance);
            if free {
                welded_free[w] = true;
            } else {
                welded_lock[w] = true;
                counts.seam_locked += 1;
            }
        }
        (
            self.per_vertex(&welded_lock),
            self.per_vertex(&welded_free),
            counts,
        )
    }

    /// Per vertex, whether it is on a UV seam.
    pub fn on_seam(&self) -> Vec<bool> {
        let welded: Vec<bool> = self.seam_neighbours.iter().map(|n| !n.is_empty()).collect();
        self.per_vertex(&welded)
    }

    /// A welded flag spread to every vertex of that position.
    pub fn per_vertex(&self, welded: &[bool]) -> Vec<bool> {
        self.weld.iter().map(|&w| welded[w as usize]).collect()
    }

    /// The seam test at welded vertex `w` between seam neighbours `p`, `n`.
    fn collapsible(&self, mesh: &Mesh<'_>, w: u32, p: u32, n: u32, tolerance: f64) -> bool {
        let wedges = &self.wedges[w as usize];
        let mut sides = Vec::with_capacity(2);
        for &wk in wedges {
            match (self.across(w, p, wk), self.across(w, n, wk)) {
                (Some(pk), Some(nk)) => sides.push([pk, wk, nk]),
                _ => return false,
            }
        }
        let [a, b] = [sides[0], sides[1]];
        mesh.uv_sets.iter().all(|uv| {
            let at = |s: [u32; 3]| s.map(|v| uv[v as usize]);
            let (ua, ub) = (at(a), at(b));
            if ua == ub {
                // Continuous in this set: no seam of this set to keep.
                return true;
            }
            match (
                on_segment(ua[0], ua[2], ua[1], tolerance),
                on_segment(ub[0], ub[2], ub[1], tolerance),
            ) {
                (Some((ta, la)), Some((tb, lb))) => (ta - tb).abs() * la.max(lb) <= tolerance,
                _ => false,
            }
        })
    }

    /// The welded vertices whose removal a simplified mesh (`lod` indices
    /// into the same vertices) got wrong: removed seam vertices that, on
    /// either side, do not lie on the surviving seam edge that replaced
    /// them at the position its other side puts them. Empty when every
    /// surviving seam edge maps the removed seam the way the erased texture
    /// was made for.
    pub fn violations(&self, mesh: &Mesh<'_>, lod: &[u32], tolerance: f64) -> Vec<u32> {
        let n = self.wedges.len();
        let mut present = vec![false; n];
        let mut lod_edges: BTreeMap<(u32, u32), Vec<(u32, u32)>> = BTreeMap::new();
        for t in lod.chunks_exact(3) {
            for k in 0..3 {
                let (a, b) = (
                    mesh.uv_wedge[t[k] as usize],
                    mesh.uv_wedge[t[(k + 1) % 3] as usize],
                );
                let (wa, wb) = (self.weld[a as usize], self.weld[b as usize]);
                present[wa as usize] = true;
                if wa != wb {
                    let half = if wa < wb { (a, b) } else { (b, a) };
                    lod_edges.entry(edge_key(wa, wb)).or_default().push(half);
                }
            }
        }
        let mut bad = Vec::new();
        for (&(u, w), halves) in &lod_edges {
            let [h1, h2] = halves.as_slice() else {
                continue;
            };
            if h1 == h2 || self.edges.contains_key(&(u, w)) {
                // Not a seam, or a seam edge of the full mesh, untouched.
                continue;
            }
            let Some(path) = self.seam_path(u, w, &present) else {
                // A seam edge that no chain of removed seam vertices
                // explains: hold the removed seam vertices around it.
                for end in [u, w] {
                    bad.extend(
                        self.seam_neighbours[end as usize]
                            .iter()
                            .filter(|&&x| !present[x as usize]),
                    );
                }
                continue;
            };
            if !self.path_consistent(mesh, u, w, [*h1, *h2], &path, tolerance) {
                bad.extend(&path);
            }
        }
        bad.sort_unstable();
        bad.dedup();
        bad
    }

    /// The removed seam vertices between `u` and `w` along the seam.
    fn seam_path(&self, u: u32, w: u32, present: &[bool]) -> Option<Vec<u32>> {
        for &first in &self.seam_neighbours[u as usize] {
            let (mut prev, mut cur) = (u, first);
            let mut path = Vec::new();
            while !present[cur as usize] && self.seam_neighbours[cur as usize].len() == 2 {
                path.push(cur);
                if path.len() > self.wedges.len() {
                    break;
                }
                let nb = &self.seam_neighbours[cur as usize];
                let next = if nb[0] == prev { nb[1] } else { nb[0] };
                (prev, cur) = (cur, next);
            }
            if cur == w && !path.is_empty() {
                return Some(path);
            }
        }
        None
    }

    /// Whether, on both sides of the surviving seam edge (`u`, `w`) given
    /// by its two half-edges, the removed vertices of `path` lie on the
    /// edge in UV at parameters that agree between the sides.
    fn path_consistent(
        &self,
        mesh: &Mesh<'_>,
        u: u32,
        w: u32,
        halves: [(u32, u32); 2],
        path: &[u32],
        tolerance: f64,
    ) -> bool {
        // Each half-edge's wedges at u and at w.
        let ends = halves.map(|(lo, hi)| if u < w { (lo, hi) } else { (hi, lo) });
        let mut sides: Vec<Vec<u32>> = Vec::with_capacity(2);
        for (wu, ww) in ends {
            let mut wedge = wu;
            let mut prev = u;
            let mut chain = Vec::with_capacity(path.len());
            for &x in path {
                let Some(next) = self.across(prev, x, wedge) else {
                    return false;
                };
                chain.push(next);
                (prev, wedge) = (x, next);
            }
            if self.across(prev, w, wedge) != Some(ww) {
                return false;
            }
            sides.push(chain);
        }
        mesh.uv_sets.iter().all(|uv| {
            let at = |v: u32| uv[v as usize];
            let (a, b) = (ends[0], ends[1]);
            let same = at(a.0) == at(b.0)
                && at(a.1) == at(b.1)
                && sides[0]
                    .iter()
                    .zip(&sides[1])
                    .all(|(&x, &y)| at(x) == at(y));
            if same {
                return true;
            }
            sides[0].iter().zip(&sides[1]).all(|(&x, &y)| {
                match (
                    on_segment(at(a.0), at(a.1), at(x), tolerance),
                    on_segment(at(b.0), at(b.1), at(y), tolerance),
                ) {
                    (Some((ta, la)), Some((tb, lb))) => (ta - tb).abs() * la.max(lb) <= tolerance,
                    _ => false,
                }
            })
        })
    }
}

/// Where `v` lies on the segment `p`–`n` in UV: its parameter in (0, 1)
/// and the segment's length, when it is within `tolerance` of the segment.
fn on_segment(p: [f32; 2], n: [f32; 2], v: [f32; 2], tolerance: f64) -> Option<(f64, f64)> {
    let d = [f64::from(n[0] - p[0]), f64::from(n[1] - p[1])];
    let e = [f64::from(v[0] - p[0]), f64::from(v[1] - p[1])];
    let len2 = d[0] * d[0] + d[1] * d[1];
    if len2 <= 0.0 {
        return None;
    }
    let len = len2.sqrt();
    let t = (e[0] * d[0] + e[1] * d[1]) / len2;
    let off = (e[0] * d[1] - e[1] * d[0]).abs() / len;
    (off <= tolerance && t > 0.0 && t < 1.0).then_some((t, len))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two quads side by side in 3D along a seam x = 0 of three vertices,
    /// mapped to two charts: `right_uv` places the middle seam vertex of
    /// the second chart.
    fn strip(right_mid: [f32; 2]) -> (Vec<[f32; 3]>, Vec<[f32; 2]>, Vec<u32>) {
        let positions = vec![
            // left chart: x = -1 column, then seam column
            [-1.0, 0.0, 0.0],
            [-1.0, 1.0, 0.0],
            [-1.0, 2.0, 0.0],
            [0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 2.0, 0.0],
            // right chart: seam column again, then x = 1
            [0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 2.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [1.0, 2.0, 0.0],
        ];
        let uvs = vec![
            [0.0, 0.0],
            [0.0, 0.1],
            [0.0, 0.2],
            [0.1, 0.0],
            [0.1, 0.1],
            [0.1, 0.2],
            [0.5, 0.0],
            right_mid,
            [0.5, 0.4],
            [0.6, 0.0],
            [0.6, 0.2],
            [0.6, 0.4],
        ];
        let indices = vec![
            0, 3, 1, 1, 3, 4, 1, 4, 2, 2, 4, 5, // left
            6, 9, 7, 7, 9, 10, 7, 10, 8, 8, 10, 11, // right
        ];
        (positions, uvs, indices)
    }

    fn mid_locked(right_mid: [f32; 2]) -> bool {
        let (positions, uvs, indices) = strip(right_mid);
        let sets = [uvs];
        let mesh = Mesh {
            positions: &positions,
            normals: None,
            uv_sets: &sets,
            indices: &indices,
            uv_wedge: &(0..12).collect::<Vec<u32>>(),
        };
        let topo = Topology::new(&mesh);
        let (locks, _, counts) = topo.seam_locks(&mesh, 1e-4);
        assert_eq!(counts.seam, 1);
        locks[4]
    }

    #[test]
    fn a_seam_vertex_moves_only_where_both_sides_agree() {
        // Both sides straight, the middle vertex halfway on each.
        assert!(!mid_locked([0.5, 0.2]));
        // Straight, but at a third on one side: the ratios disagree.
        assert!(mid_locked([0.5, 0.4 / 3.0]));
        // Off the line on one side.
        assert!(mid_locked([0.52, 0.2]));
    }
}
