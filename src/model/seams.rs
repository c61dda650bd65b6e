//! Welding and seam extraction (SPEC §2).
//!
//! glTF splits vertices wherever UVs differ, so the mesh is welded by exact
//! object-space position first; an edge of the welded mesh with two incident
//! triangles whose UV half-edges differ is a seam.

use std::collections::HashMap;

use super::UvTriangle;

/// Two half-edges tolerate this much disagreement (in texels) and still count as one edge.
const SAME_UV_TEXELS: f64 = 1e-3;

/// A seam: one 3D edge mapped to two different UV half-edges.
///
/// Both half-edges are oriented so that γ ∈ \[0, 1\] is the same 3D point on
/// both: `a[0]`/`b[0]` are the UVs of the same welded vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeamEdge {
    pub a: [[f64; 2]; 2],
    pub b: [[f64; 2]; 2],
    /// UV of the vertex opposite each half-edge in its triangle (gives the inward side).
    pub a_opposite: [f64; 2],
    pub b_opposite: [f64; 2],
    /// 3D length of the edge.
    pub length: f64,
    /// Index (in the triangles given to [`find_seams`]) of the triangle that
    /// holds each half-edge: `a`'s, then `b`'s.
    pub triangles: [u32; 2],
}

/// A UV boundary that is not a seam: a mesh boundary or a non-manifold edge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SilhouetteEdge {
    pub uv: [[f64; 2]; 2],
    pub opposite: [f64; 2],
}

/// All seam and silhouette edges of the triangles that sample one texture.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SeamSet {
    pub seams: Vec<SeamEdge>,
    pub silhouettes: Vec<SilhouetteEdge>,
}

impl SeamSet {
    /// Total 3D length of all seams (L in SPEC §3).
    pub fn total_length(&self) -> f64 {
        self.seams.iter().map(|s| s.length).sum()
    }

    /// The seams whose entry in `keep` is true, with every silhouette.
    pub fn select(&self, keep: &[bool]) -> SeamSet {
        SeamSet {
            seams: self
                .seams
                .iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .map(|(s, _)| *s)
                .collect(),
            silhouettes: self.silhouettes.clone(),
        }
    }
}

struct HalfEdge {
    /// UVs at the lower and higher welded vertex id.
    uv: [[f64; 2]; 2],
    opposite: [f64; 2],
    length: f64,
    triangle: u32,
}

/// The welded mesh's edges with the UV half-edges that meet at each: the
/// size-independent part of seam finding, made once per texture and read
/// by every mip level (welding is most of [`find_seams`]' time, about 30 ms
/// on a 14 000-triangle atlas, and the mip chain waits for it level by level).
#[derive(Default)]
pub struct MeshEdges {
    /// One entry per welded edge, in order of first appearance.
    edges: Vec<Vec<HalfEdge>>,
}

impl MeshEdges {
    /// Welds `triangles` by exact object-space position and pairs their edges.
    pub fn new(triangles: &[UvTriangle]) -> Self {
        let mut weld: HashMap<(u32, [u32; 3]), u32> = HashMap::new();
        let mut edge_slot: HashMap<(u32, u32), usize> = HashMap::new();
        let mut edges: Vec<Vec<HalfEdge>> = Vec::new();

        for (ti, t) in triangles.iter().enumerate() {
            let ids = t.positions.map(|p| {
                let key = (t.group, p.map(f32::to_bits));
                let next = weld.len() as u32;
                *weld.entry(key).or_insert(next)
            });
            for k in 0..3 {
                let (i, j, o) = (k, (k + 1) % 3, (k + 2) % 3);
                let (lo, hi) = if ids[i] <= ids[j] { (i, j) } else { (j, i) };
                if ids[i] == ids[j] {
                    // Both ends weld to one point: a collapsed edge bounds nothing.
                    continue;
                }
                let length = distance(t.positions[lo], t.positions[hi]);
                let half = HalfEdge {
                    uv: [t.uvs[lo], t.uvs[hi]],
                    opposite: t.uvs[o],
                    length,
                    triangle: ti as u32,
                };
                let key = (ids[lo], ids[hi]);
                let slot = *edge_slot.entry(key).or_insert_with(|| {
                    edges.push(Vec::new());
                    edges.len() - 1
                });
                edges[slot].push(half);
            }
        }
        MeshEdges { edges }
    }

    /// The seams and silhouettes for a `width`×`height` texture: whether
    /// two half-edges differ is judged in texels.
    pub fn seams(&self, width: usize, height: usize) -> SeamSet {
        let (w, h) = (width as f64, height as f64);
        let differs = |p: [f64; 2], q: [f64; 2]| {
            let dx = (p[0] - q[0]) * w;
            let dy = (p[1] - q[1]) * h;
            dx.abs().max(dy.abs()) > SAME_UV_TEXELS
        };

        let mut set = SeamSet::default();
        for halves in &self.edges {
            match halves.as_slice() {
                [e1, e2] => {
                    if differs(e1.uv[0], e2.uv[0]) || differs(e1.uv[1], e2.uv[1]) {
                        set.seams.push(SeamEdge {
                            a: e1.uv,
                            b: e2.uv,
                            a_opposite: e1.opposite,
                            b_opposite: e2.opposite,
                            length: e1.length,
                            triangles: [e1.triangle, e2.triangle],
                        });
                    }
                }
                halves => set
                    .silhouettes
                    .extend(halves.iter().map(|e| SilhouetteEdge {
                        uv: e.uv,
                        opposite: e.opposite,
                    })),
            }
        }
        set
    }
}

/// Finds the seams of `triangles` for a `width`×`height` texture.
///
/// Output order follows the first appearance of each edge in `triangles`, so
/// it is deterministic for a given model.
pub fn find_seams(triangles: &[UvTriangle], width: usize, height: usize) -> SeamSet {
    MeshEdges::new(triangles).seams(width, height)
}

fn distance(p: [f32; 3], q: [f32; 3]) -> f64 {
    let d = [0, 1, 2].map(|k| f64::from(p[k]) - f64::from(q[k]));
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri(p: [[f32; 3]; 3], uv: [[f64; 2]; 3]) -> UvTriangle {
        UvTriangle {
            group: 0,
            positions: p,
            uvs: uv,
        }
    }

    const P: [[f32; 3]; 4] = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 0.]];

    #[test]
    fn shared_uv_edge_is_not_a_seam() {
        let t = [
            tri([P[0], P[1], P[2]], [[0., 0.], [0.5, 0.], [0., 0.5]]),
            tri([P[1], P[3], P[2]], [[0.5, 0.], [0.5, 0.5], [0., 0.5]]),
        ];
        let s = find_seams(&t, 64, 64);
        assert!(s.seams.is_empty());
        assert_eq!(s.silhouettes.len(), 4);
    }

    #[test]
    fn split_uv_edge_is_a_seam_oriented_consistently() {
        // The shared 3D edge P1–P2 maps to two different places in UV.
        let t = [
            tri([P[0], P[1], P[2]], [[0., 0.], [0.5, 0.], [0., 0.5]]),
            tri([P[1], P[3], P[2]], [[0.9, 0.1], [0.9, 0.9], [0.6, 0.9]]),
        ];
        let s = find_seams(&t, 64, 64);
        assert_eq!(s.seams.len(), 1);
        let e = s.seams[0];
        // Endpoint 0 of both half-edges is the same welded vertex.
        let same_start = e.a[0] == [0.5, 0.] && e.b[0] == [0.9, 0.1];
        let same_start_rev = e.a[0] == [0., 0.5] && e.b[0] == [0.6, 0.9];
        assert!(same_start || same_start_rev, "{e:?}");
        assert!((e.length - 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn welding_stays_within_a_group() {
        let mut b = tri([P[1], P[3], P[2]], [[0.9, 0.1], [0.9, 0.9], [0.6, 0.9]]);
        b.group = 1;
        let t = [tri([P[0], P[1], P[2]], [[0., 0.], [0.5, 0.], [0., 0.5]]), b];
        assert!(find_seams(&t, 64, 64).seams.is_empty());
    }

    #[test]
    fn sub_tolerance_uv_difference_is_not_a_seam() {
        let d = 0.5e-3 / 64.0;
        let t = [
            tri([P[0], P[1], P[2]], [[0., 0.], [0.5, 0.], [0., 0.5]]),
            tri(
                [P[1], P[3], P[2]],
                [[0.5 + d, 0.], [0.5, 0.5], [0., 0.5 + d]],
            ),
        ];
        assert!(find_seams(&t, 64, 64).seams.is_empty());
    }
}
