//! Which seam edges of a level of detail run along seams the erased texture
//! closed.
//!
//! Seams left as painted disagree by tens of levels on purpose; averaged
//! with the closed ones they drown what a level does to the seams that
//! matter, so each level is also measured over its closed seams alone. A
//! level's seam edge joins two seam vertices of the full mesh (the levels
//! reuse its vertices) and replaces the chain of full-mesh seam edges
//! between them; it counts as closed when every edge of that chain was.
//! Seam vertices are told apart by position as well as UVs: mirrored
//! charts share their UVs.

use std::collections::{HashMap, HashSet};

use crate::model::{SeamEdge, SeamSet, UvTriangle};

/// Both sides' UV points of a seam vertex, in a fixed order.
type UvPair = [[u64; 2]; 2];

/// A seam vertex: where it is (its mesh group and position; mirrored
/// charts share their UVs, not their positions) and how both sides map it.
type Node = (u32, [u32; 3], UvPair);

fn uv_pair(p: [f64; 2], q: [f64; 2]) -> UvPair {
    let (p, q) = (p.map(f64::to_bits), q.map(f64::to_bits));
    if p <= q {
        [p, q]
    } else {
        [q, p]
    }
}

fn uv_key(a: [[f64; 2]; 2], b: [[f64; 2]; 2]) -> (UvPair, UvPair) {
    let (n0, n1) = (uv_pair(a[0], b[0]), uv_pair(a[1], b[1]));
    if n0 <= n1 {
        (n0, n1)
    } else {
        (n1, n0)
    }
}

/// The two ends of seam edge `e` of `triangles`, as nodes.
fn ends(e: &SeamEdge, triangles: &[UvTriangle]) -> (Node, Node) {
    let t = triangles.get(e.triangles[0] as usize);
    let at = |uv: [f64; 2]| {
        t.and_then(|t| {
            let k = t.uvs.iter().position(|&x| x == uv)?;
            Some((t.group, t.positions[k].map(f32::to_bits)))
        })
        .unwrap_or((u32::MAX, [0; 3]))
    };
    let node = |k: usize| {
        let (group, position) = at(e.a[k]);
        (group, position, uv_pair(e.a[k], e.b[k]))
    };
    (node(0), node(1))
}

/// The full mesh's seams as chains, each edge with whether it was closed.
pub struct ClosedSeams {
    adjacency: HashMap<Node, Vec<(Node, bool)>>,
    /// Every seam edge of the full mesh by its UVs, and whether it was
    /// closed.
    by_uv: HashMap<(UvPair, UvPair), bool>,
}

impl ClosedSeams {
    /// `full`: the full mesh's seams, found in `triangles`; `closed`: the
    /// closed ones, each as its two half-edges' UV endpoints.
    pub fn new(
        full: &SeamSet,
        triangles: &[UvTriangle],
        closed: &[[[[f64; 2]; 2]; 2]],
    ) -> ClosedSeams {
        let closed: HashSet<(UvPair, UvPair)> = closed.iter().map(|&[a, b]| uv_key(a, b)).collect();
        let mut adjacency: HashMap<Node, Vec<(Node, bool)>> = HashMap::new();
        let mut by_uv = HashMap::new();
        for e in &full.seams {
            let key = uv_key(e.a, e.b);
            let is_closed = closed.contains(&key);
            by_uv.insert(key, is_closed);
            let (n0, n1) = ends(e, triangles);
            adjacency.entry(n0).or_default().push((n1, is_closed));
            adjacency.entry(n1).or_default().push((n0, is_closed));
        }
        ClosedSeams { adjacency, by_uv }
    }

    /// Per seam edge of `level` (found in `triangles`), whether it runs
    /// along closed seams only. An edge whose chain cannot be followed
    /// (its seam branches) counts as closed: measured rather than excused.
    pub fn classify(&self, level: &SeamSet, triangles: &[UvTriangle]) -> Vec<bool> {
        level
            .seams
            .iter()
            .map(|e| {
                let (n0, n1) = ends(e, triangles);
                self.chain_closed(n0, n1).unwrap_or(true)
            })
            .collect()
    }

    /// Whether the full mesh's seam edge with these half-edges (each as
    /// its UV endpoints, the two in the same order) was closed; `None`
    /// where it has no such seam edge.
    pub fn edge_closed(&self, a: [[f64; 2]; 2], b: [[f64; 2]; 2]) -> Option<bool> {
        self.by_uv.get(&uv_key(a, b)).copied()
    }

    /// Whether every full-mesh seam edge from `from` to `to` was closed,
    /// following seam vertices that have two seam edges.
    fn chain_closed(&self, from: Node, to: Node) -> Option<bool> {
        let first = self.adjacency.get(&from)?;
        if let Some(&(_, c)) = first.iter().find(|(n, _)| *n == to) {
            return Some(c);
        }
        let limit = self.adjacency.len();
        for &(start, c) in first {
            let (mut prev, mut cur, mut all) = (from, start, c);
            for _ in 0..limit {
                if cur == to {
                    return Some(all);
                }
                let nb = match self.adjacency.get(&cur) {
                    Some(nb) if nb.len() == 2 => nb,
                    _ => break,
                };
                let &(next, c) = if nb[0].0 == prev { &nb[1] } else { &nb[0] };
                all &= c;
                (prev, cur) = (cur, next);
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edge(a: [[f64; 2]; 2], b: [[f64; 2]; 2]) -> SeamEdge {
        SeamEdge {
            a,
            b,
            a_opposite: [0.0; 2],
            b_opposite: [0.0; 2],
            length: 1.0,
            triangles: [0, 1],
        }
    }

    #[test]
    fn a_level_edge_is_closed_when_the_chain_it_replaces_was() {
        // A seam of three edges along y, the middle one left; one
        // triangle per side of each edge holds its half-edge.
        let a = |y: f64| [0.1, y];
        let b = |y: f64| [0.6, y];
        let p = |y: f64| [0.0, y as f32, 0.0];
        // The seam edge from y0 to y1, its two sides' triangles added.
        let seam_edge = |triangles: &mut Vec<UvTriangle>, y0: f64, y1: f64| {
            let t = triangles.len() as u32;
            for side in [a, b] {
                triangles.push(UvTriangle {
                    group: 0,
                    positions: [p(y0), p(y1), [1.0, 0.0, 0.0]],
                    uvs: [side(y0), side(y1), [0.9, 0.9]],
                });
            }
            let mut e = edge([a(y0), a(y1)], [b(y0), b(y1)]);
            e.triangles = [t, t + 1];
            e
        };
        let mut triangles = Vec::new();
        let full = SeamSet {
            seams: (0..3)
                .map(|k| seam_edge(&mut triangles, 0.1 * k as f64, 0.1 * (k + 1) as f64))
                .collect(),
            silhouettes: Vec::new(),
        };
        let closed: Vec<_> = [0, 2]
            .iter()
            .map(|&k| [full.seams[k].a, full.seams[k].b])
            .collect();
        let chains = ClosedSeams::new(&full, &triangles, &closed);
        assert_eq!(chains.classify(&full, &triangles), vec![true, false, true]);
        assert_eq!(
            chains.edge_closed(full.seams[1].a, full.seams[1].b),
            Some(false)
        );

        // A level's edges, each in a triangle of its own.
        let mut level_triangles = Vec::new();
        let mut level_edge = |y0: f64, y1: f64| seam_edge(&mut level_triangles, y0, y1);
        let level = SeamSet {
            seams: vec![
                // The first edge, reversed on both sides.
                level_edge(0.1, 0.0),
                // Over the left edge.
                level_edge(0.0, 0.2),
                // From a point on no seam: measured.
                level_edge(0.05, 0.3),
            ],
            silhouettes: Vec::new(),
        };
        assert_eq!(
            chains.classify(&level, &level_triangles),
            vec![true, false, true]
        );
    }
}
