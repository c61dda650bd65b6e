//! Which seam edges of a level of detail run along seams the erased texture
//! closed.
//!
//! Seams left as painted disagree by tens of levels on purpose; averaged
//! with the closed ones they drown what a level does to the seams that
//! matter, so each level is also measured over its closed seams alone. A
//! level's seam edge joins two seam vertices of the full mesh (the levels
//! reuse its vertices) and replaces the chain of full-mesh seam edges
//! between them; it counts as closed when every edge of that chain was.

use std::collections::{HashMap, HashSet};

use crate::model::{SeamEdge, SeamSet};

/// A seam vertex as both sides map it: the two UV points, in a fixed order.
type Node = [[u64; 2]; 2];

fn node(p: [f64; 2], q: [f64; 2]) -> Node {
    let (p, q) = (p.map(f64::to_bits), q.map(f64::to_bits));
    if p <= q {
        [p, q]
    } else {
        [q, p]
    }
}

fn ends(e: &SeamEdge) -> (Node, Node) {
    (node(e.a[0], e.b[0]), node(e.a[1], e.b[1]))
}

fn key(n0: Node, n1: Node) -> (Node, Node) {
    if n0 <= n1 {
        (n0, n1)
    } else {
        (n1, n0)
    }
}

/// The full mesh's seams as chains, each edge with whether it was closed.
pub struct ClosedSeams {
    adjacency: HashMap<Node, Vec<(Node, bool)>>,
}

impl ClosedSeams {
    /// `full`: the full mesh's seams; `closed`: the closed ones, each as
    /// its two half-edges' UV endpoints.
    pub fn new(full: &SeamSet, closed: &[[[[f64; 2]; 2]; 2]]) -> ClosedSeams {
        let closed: HashSet<(Node, Node)> = closed
            .iter()
            .map(|&[a, b]| key(node(a[0], b[0]), node(a[1], b[1])))
            .collect();
        let mut adjacency: HashMap<Node, Vec<(Node, bool)>> = HashMap::new();
        for e in &full.seams {
            let (n0, n1) = ends(e);
            let is_closed = closed.contains(&key(n0, n1));
            adjacency.entry(n0).or_default().push((n1, is_closed));
            adjacency.entry(n1).or_default().push((n0, is_closed));
        }
        ClosedSeams { adjacency }
    }

    /// Per seam edge of `level`, whether it runs along closed seams only.
    /// An edge whose chain cannot be followed (its seam branches, or two
    /// charts share its UVs) counts as closed: measured rather than
    /// excused.
    pub fn classify(&self, level: &SeamSet) -> Vec<bool> {
        level
            .seams
            .iter()
            .map(|e| {
                let (n0, n1) = ends(e);
                self.chain_closed(n0, n1).unwrap_or(true)
            })
            .collect()
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
        // A seam of three edges, the middle one left.
        let a = |y: f64| [0.1, y];
        let b = |y: f64| [0.6, y];
        let full = SeamSet {
            seams: (0..3)
                .map(|k| {
                    let (y0, y1) = (0.1 * k as f64, 0.1 * (k + 1) as f64);
                    edge([a(y0), a(y1)], [b(y0), b(y1)])
                })
                .collect(),
            silhouettes: Vec::new(),
        };
        let closed: Vec<_> = [0, 2]
            .iter()
            .map(|&k| [full.seams[k].a, full.seams[k].b])
            .collect();
        let chains = ClosedSeams::new(&full, &closed);
        assert_eq!(chains.classify(&full), vec![true, false, true]);
        let level = SeamSet {
            seams: vec![
                // The first edge, reversed on both sides.
                edge([a(0.1), a(0.0)], [b(0.1), b(0.0)]),
                // Over the left edge.
                edge([a(0.0), a(0.2)], [b(0.0), b(0.2)]),
                // From a point on no seam: measured.
                edge([a(0.05), a(0.3)], [b(0.05), b(0.3)]),
            ],
            silhouettes: Vec::new(),
        };
        assert_eq!(chains.classify(&level), vec![true, false, true]);
    }
}
