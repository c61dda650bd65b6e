//! The seam test of seam-aware decimation (Liu, Ferguson, Jacobson and
//! Gingold, "Seamless", ACM TOG 36(6), 2017, §5.1): which seam vertices may
//! go, and whether a simplified mesh kept every seam as the erased texture
//! expects it.
//!
//! A seam vertex may collapse only along its seam onto a seam neighbour,
//! and only where both sides of the seam still map the merged edge the way
//! the texture was erased for. The paper asks for exact collinearity in UV
//! with equal length ratios on both sides, which no vertex of a curved seam
//! passes (its §6 straightens seams first, warping the texture, to get
//! them to collapse). Here the test is made against the *original* seam
//! instead, with a tolerance in texels: a surviving seam edge samples the
//! chord between its kept ends on each side, and it stays closed where
//! every removed vertex lies within the tolerance of that chord on both
//! sides, at parameters along it that agree between the sides. Erasure
//! matches both the values and the cross-seam derivatives along the seam,
//! so sampling beside it by a fraction of a texel, correspondingly on both
//! sides, differs only to second order; the figures measured on every
//! level (`lods` in the report) are what vouches for the tolerance.
//!
//! The seams are chains of seam vertices with two seam edges and two
//! wedges, between corners (other than two seam edges, more than two
//! wedges, a boundary or a non-manifold edge) that never move. Because the
//! test is made against the original chain rather than the current
//! neighbours, collapses do not accumulate deviation: however many
//! vertices a surviving edge replaces, all of them are within the
//! tolerance of it.

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
    /// Per welded vertex: on a boundary or a non-manifold edge.
    fixed: Vec<bool>,
    /// Per welded vertex: used with more than one UV (on a seam, or where
    /// charts touch at a point only).
    split: Vec<bool>,
    chains: Vec<Chain>,
    /// Per welded vertex inside a chain (not at its ends): the chain, and
    /// its place along it.
    place: Vec<Option<(u32, u32)>>,
    /// Per welded corner: the chains that start or end there.
    corner_chains: HashMap<u32, Vec<u32>>,
}

/// A seam between two corners (the same one, for a closed loop): its
/// welded vertices in order, and on each side the wedge at each of them.
struct Chain {
    vertices: Vec<u32>,
    sides: [Vec<u32>; 2],
}

/// Counts of what the seam test decided.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LockCounts {
    /// Welded vertices on a seam (still in the mesh).
    pub seam: usize,
    /// Of those, how many the seam test holds: corners, and vertices whose
    /// removal would move the seam's chord beyond the tolerance.
    pub seam_locked: usize,
    /// Boundary and non-manifold welded vertices (locked).
    pub fixed: usize,
}

/// Per vertex of the mesh, the flags of one simplification stage.
pub struct StageFlags {
    /// Must not move.
    pub lock: Vec<bool>,
    pub counts: LockCounts,
    /// The seam vertices freed, with what their chords would take of the
    /// budget (when the texture is judged).
    pub planned: Vec<(u32, Vec<f64>)>,
}

/// A measure of seams on the texture itself (see [`super::seam_texture`]),
/// in slots (per image the primitive samples, its closed seams and all
/// of its seams), each a length-weighted mean square of the difference
/// between the sides that a level must keep within an allowance.
pub trait ChordJudge: Sync {
    /// Per slot, a stretch of seam measured as one edge from its first
    /// vertex to its last (`sides`: each side's vertices along the
    /// original seam, ends included, in the same order): its length times
    /// its mean squared difference, and its length. `None` where no chord
    /// may replace the stretch (it runs over both closed and left seams).
    fn terms(&self, mesh: &Mesh<'_>, sides: [&[u32]; 2]) -> Option<Vec<[f64; 2]>>;

    /// Per slot, how much a level's mean square may exceed the full
    /// mesh's.
    fn allowances(&self) -> Vec<f64>;
}

/// What the chords a primitive's levels have made so far spent of the
/// allowance, per slot of its [`ChordJudge`]. A chord changes a slot's
/// length-weighted mean square num/den; keeping num − target·den ≤ 0, with
/// target the full mesh's mean square plus the allowance, keeps the level
/// within it, and each chord's share of that is additive.
pub struct Budget {
    target: Vec<f64>,
    /// What is left: allowance × the full mesh's seam length, less what
    /// the chords made so far took.
    room: Vec<f64>,
    /// The room at the start, to weigh the slots against each other.
    start: Vec<f64>,
}

impl Budget {
    fn fits(&self, taken: &[f64]) -> bool {
        taken.iter().zip(&self.room).all(|(t, r)| *t <= *r)
    }

    /// What a chord would take, as a share of the start room (the largest
    /// over slots), to try the cheapest first.
    fn share(&self, delta: &[f64]) -> f64 {
        delta
            .iter()
            .zip(&self.start)
            .map(|(d, s)| {
                if *s > 0.0 {
                    d / s
                } else if *d > 0.0 {
                    f64::INFINITY
                } else {
                    0.0
                }
            })
            .fold(f64::NEG_INFINITY, f64::max)
    }

    /// Takes what the planned chords whose middle vertex is gone took.
    pub fn spend(&mut self, planned: &[(u32, Vec<f64>)], present: &[bool]) {
        for (w, delta) in planned {
            if !present[*w as usize] {
                for (r, d) in self.room.iter_mut().zip(delta) {
                    *r -= d;
                }
            }
        }
    }
}

/// What a chord must satisfy to replace a stretch of seam.
#[derive(Clone, Copy)]
pub struct ChordRule<'a> {
    /// The largest deviation from the seam (in UV: off the chord, or
    /// between the sides along it) allowed where no texture is judged.
    pub tolerance: f64,
    /// Where the texture is judged: the judge, and the largest deviation
    /// it is asked about.
    pub judge: Option<(&'a dyn ChordJudge, f64)>,
}

impl ChordRule<'_> {
    /// The geometric test alone, with `tolerance` in UV.
    pub fn geometric(tolerance: f64) -> ChordRule<'static> {
        ChordRule {
            tolerance,
            judge: None,
        }
    }
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
        let split = wedges.iter().map(|w| w.len() > 1).collect();
        let mut topo = Topology {
            weld,
            edges,
            seam_neighbours,
            fixed,
            split,
            chains: Vec::new(),
            place: vec![None; n],
            corner_chains: HashMap::new(),
        };
        topo.find_chains(&wedges);
        topo
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

    /// The two half-edges of seam edge (`from`, `to`), each as its wedges
    /// at `from` and at `to`.
    fn sides_of(&self, from: u32, to: u32) -> Option<[(u32, u32); 2]> {
        let halves = self.edges.get(&edge_key(from, to))?;
        let [h1, h2] = halves.as_slice() else {
            return None;
        };
        let orient = |&(lo, hi): &(u32, u32)| if from < to { (lo, hi) } else { (hi, lo) };
        Some([orient(h1), orient(h2)])
    }

    /// Whether welded vertex `w` can sit inside a chain: two seam edges,
    /// two wedges, each side followable across both.
    fn movable(&self, w: u32, wedges: &[Vec<u32>]) -> bool {
        let nb = &self.seam_neighbours[w as usize];
        let ws = &wedges[w as usize];
        if self.fixed[w as usize] || nb.len() != 2 || ws.len() != 2 {
            return false;
        }
        let (Some(p), Some(n)) = (self.sides_of(w, nb[0]), self.sides_of(w, nb[1])) else {
            return false;
        };
        // Each wedge is one side: it starts one half-edge towards each
        // neighbour, and the two wedges start different ones.
        let at = |s: [(u32, u32); 2]| [s[0].0, s[1].0];
        let (pa, na) = (at(p), at(n));
        pa[0] != pa[1] && ws.iter().all(|x| pa.contains(x) && na.contains(x))
    }

    fn find_chains(&mut self, wedges: &[Vec<u32>]) {
        let n = self.seam_neighbours.len();
        let movable: Vec<bool> = (0..n as u32).map(|w| self.movable(w, wedges)).collect();
        let mut walked = vec![false; n];
        let starts: Vec<u32> = (0..n as u32)
            .filter(|&w| !self.seam_neighbours[w as usize].is_empty() && !movable[w as usize])
            .collect();
        // Chains from every corner first; what is left are closed loops of
        // movable vertices, each anchored at its lowest vertex.
        let loops: Vec<u32> = (0..n as u32).filter(|&w| movable[w as usize]).collect();
        for start in starts.into_iter().chain(loops) {
            if movable[start as usize] && walked[start as usize] {
                continue;
            }
            let neighbours = self.seam_neighbours[start as usize].clone();
            for first in neighbours {
                if movable[first as usize] && walked[first as usize] {
                    continue;
                }
                if let Some(chain) = self.walk(start, first, &movable) {
                    if chain.vertices.len() < 3 {
                        // Corner to corner: nothing along it can move.
                        continue;
                    }
                    for &v in &chain.vertices[1..chain.vertices.len() - 1] {
                        walked[v as usize] = true;
                    }
                    walked[start as usize] = true;
                    self.add_chain(chain);
                }
                if movable[start as usize] {
                    // A loop is walked once, from its anchor either way.
                    break;
                }
            }
        }
    }

    /// The chain from corner `start` through `first` to the next corner
    /// (or back to `start`).
    fn walk(&self, start: u32, first: u32, movable: &[bool]) -> Option<Chain> {
        let sides = self.sides_of(start, first)?;
        let mut vertices = vec![start, first];
        let mut wedge_sides = [vec![sides[0].0, sides[0].1], vec![sides[1].0, sides[1].1]];
        let (mut prev, mut cur) = (start, first);
        while movable[cur as usize] && cur != start {
            let nb = &self.seam_neighbours[cur as usize];
            let next = if nb[0] == prev { nb[1] } else { nb[0] };
            for side in &mut wedge_sides {
                let w = *side.last().expect("a chain has vertices");
                side.push(self.across(cur, next, w)?);
            }
            vertices.push(next);
            (prev, cur) = (cur, next);
            if vertices.len() > self.seam_neighbours.len() + 1 {
                return None;
            }
        }
        Some(Chain {
            vertices,
            sides: wedge_sides,
        })
    }

    fn add_chain(&mut self, chain: Chain) {
        let id = self.chains.len() as u32;
        let last = chain.vertices.len() - 1;
        for (k, &v) in chain.vertices.iter().enumerate() {
            if k == 0 || k == last {
                let list = self.corner_chains.entry(v).or_default();
                if !list.contains(&id) {
                    list.push(id);
                }
            } else {
                self.place[v as usize] = Some((id, k as u32));
            }
        }
        self.chains.push(chain);
    }

    /// A welded flag spread to every vertex of that position.
    pub fn per_vertex(&self, welded: &[bool]) -> Vec<bool> {
        self.weld.iter().map(|&w| welded[w as usize]).collect()
    }

    /// Which welded vertices the triangles of `indices` use.
    pub fn present(&self, indices: &[u32]) -> Vec<bool> {
        let mut present = vec![false; self.seam_neighbours.len()];
        for &i in indices {
            present[self.weld[i as usize] as usize] = true;
        }
        present
    }

    /// How far the chord from place `i` to place `j` of `chain` strays
    /// from the original seam between them, in UV (the largest, over
    /// every removed vertex and both sides, of its distance off the chord
    /// and of the disagreement between the sides on where along the chord
    /// it falls); `None` where the seam folds back along the chord.
    fn chord_deviation(&self, mesh: &Mesh<'_>, chain: &Chain, i: usize, j: usize) -> Option<f64> {
        let mut worst = 0.0f64;
        for uv in mesh.uv_sets {
            let at = |s: usize, k: usize| uv[chain.sides[s][k] as usize];
            if (i..=j).all(|k| at(0, k) == at(1, k)) {
                // Continuous in this set: no seam of this set to keep.
                continue;
            }
            for m in i + 1..j {
                let (t0, l0, off0) = on_chord(at(0, i), at(0, j), at(0, m))?;
                let (t1, l1, off1) = on_chord(at(1, i), at(1, j), at(1, m))?;
                let slide = (t0 - t1).abs() * l0.max(l1);
                worst = worst.max(off0).max(off1).max(slide);
            }
        }
        Some(worst)
    }

    /// Whether the chord from place `i` to place `j` of `chain` passes
    /// `rule`, and how far it strays from the seam (in UV).
    fn chord_passes(
        &self,
        mesh: &Mesh<'_>,
        chain: &Chain,
        i: usize,
        j: usize,
        rule: &ChordRule<'_>,
    ) -> Option<f64> {
        let deviation = self.chord_deviation(mesh, chain, i, j)?;
        let passes = match rule.judge {
            None => deviation <= rule.tolerance,
            Some((_, most)) => deviation <= most,
        };
        passes.then_some(deviation)
    }

    /// The judge's terms of the stretch from place `i` to place `j`.
    fn terms(
        &self,
        mesh: &Mesh<'_>,
        judge: &dyn ChordJudge,
        chain: &Chain,
        i: usize,
        j: usize,
    ) -> Option<Vec<[f64; 2]>> {
        judge.terms(mesh, [&chain.sides[0][i..=j], &chain.sides[1][i..=j]])
    }

    /// The budget of a primitive's levels: the judge's allowance over the
    /// full mesh's seams. `None` without a judge.
    pub fn budget(&self, mesh: &Mesh<'_>, rule: &ChordRule<'_>) -> Option<Budget> {
        let (judge, _) = rule.judge?;
        let allowances = judge.allowances();
        let mut num = vec![0.0; allowances.len()];
        let mut den = vec![0.0; allowances.len()];
        let mut keys: Vec<&(u32, u32)> = self.edges.keys().collect();
        keys.sort_unstable();
        for &(lo, hi) in keys {
            let Some(sides) = self.sides_of(lo, hi) else {
                continue;
            };
            if sides[0] == sides[1] {
                continue;
            }
            let (a, b) = ([sides[0].0, sides[0].1], [sides[1].0, sides[1].1]);
            if let Some(terms) = judge.terms(mesh, [&a, &b]) {
                for (s, [n, d]) in terms.into_iter().enumerate() {
                    num[s] += n;
                    den[s] += d;
                }
            }
        }
        let target: Vec<f64> = (0..allowances.len())
            .map(|s| num[s] / den[s].max(f64::MIN_POSITIVE) + allowances[s])
            .collect();
        let room: Vec<f64> = (0..allowances.len())
            .map(|s| allowances[s] * den[s])
            .collect();
        Some(Budget {
            target,
            start: room.clone(),
            room,
        })
    }

    /// The flags of one stage of simplification from the mesh `current`
    /// (indices into the same vertices): a seam vertex is free where
    /// removing it, merging its two current seam edges, makes a chord that
    /// passes `rule` against the original seam; of two free neighbours
    /// along a seam only one (the one whose chord strays less) is freed
    /// per stage, so that every chord a stage can make is one tested here.
    /// With a budget, chords are freed cheapest first while it lasts.
    pub fn stage_flags(
        &self,
        mesh: &Mesh<'_>,
        current: &[u32],
        rule: &ChordRule<'_>,
        budget: Option<&Budget>,
    ) -> StageFlags {
        let present = self.present(current);
        let n = present.len();
        let mut free = vec![false; n];
        let mut counts = LockCounts::default();
        // (cost, chain, place among the present ones, what it takes)
        let mut candidates: Vec<(f64, u32, usize, Vec<f64>)> = Vec::new();
        let mut passing = vec![false; n];
        let judged = rule.judge.zip(budget);
        // Per chain, the places still present.
        let mut kept: Vec<Vec<usize>> = Vec::with_capacity(self.chains.len());
        for (c, chain) in self.chains.iter().enumerate() {
            let places: Vec<usize> = (0..chain.vertices.len())
                .filter(|&k| present[chain.vertices[k] as usize])
                .collect();
            for p in 1..places.len().saturating_sub(1) {
                let (i, k, j) = (places[p - 1], places[p], places[p + 1]);
                let Some(d) = self.chord_passes(mesh, chain, i, j, rule) else {
                    continue;
                };
                let (cost, delta) = match judged {
                    None => (d, Vec::new()),
                    Some(((judge, _), budget)) => {
                        let (Some(whole), Some(before), Some(after)) = (
                            self.terms(mesh, judge, chain, i, j),
                            self.terms(mesh, judge, chain, i, k),
                            self.terms(mesh, judge, chain, k, j),
                        ) else {
                            continue;
                        };
                        let delta: Vec<f64> = (0..whole.len())
                            .map(|s| {
                                let num = whole[s][0] - before[s][0] - after[s][0];
                                let den = whole[s][1] - before[s][1] - after[s][1];
                                num - budget.target[s] * den
                            })
                            .collect();
                        if !budget.fits(&delta) {
                            continue;
                        }
                        (budget.share(&delta), delta)
                    }
                };
                passing[chain.vertices[k] as usize] = true;
                candidates.push((cost, c as u32, p, delta));
            }
            kept.push(places);
        }
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then((a.1, a.2).cmp(&(b.1, b.2))));
        let mut taken = budget.map_or(Vec::new(), |b| vec![0.0; b.room.len()]);
        let mut planned = Vec::new();
        for (_, c, p, delta) in candidates {
            let chain = &self.chains[c as usize];
            let places = &kept[c as usize];
            let neighbour_free = |q: usize| free[chain.vertices[places[q]] as usize];
            if neighbour_free(p - 1) || neighbour_free(p + 1) {
                continue;
            }
            if let Some(b) = budget.filter(|_| !delta.is_empty()) {
                let sum: Vec<f64> = taken.iter().zip(&delta).map(|(t, d)| t + d).collect();
                if !b.fits(&sum) {
                    continue;
                }
                taken = sum;
            }
            let w = chain.vertices[places[p]];
            free[w as usize] = true;
            planned.push((w, delta));
        }
        let mut lock = vec![false; n];
        for w in 0..n {
            if !present[w] {
                continue;
            }
            if self.fixed[w] {
                lock[w] = true;
                counts.fixed += 1;
            } else if self.split[w] || !self.seam_neighbours[w].is_empty() {
                // Charts touching at a point only, and a seam's end where
                // its sides meet at one UV, count as seam corners.
                counts.seam += 1;
                counts.seam_locked += usize::from(!passing[w]);
                lock[w] = !free[w];
            }
        }
        StageFlags {
            lock: self.per_vertex(&lock),
            counts,
            planned,
        }
    }

    /// The welded vertices whose removal a simplified mesh (`lod`, made
    /// from `current`, both indices into the same vertices) got wrong:
    /// removed seam vertices under a
    /// surviving seam edge that does not run along one chain on both sides
    /// as a chord passing `rule`. Empty when every surviving seam edge maps
    /// the removed seam the way the erased texture was made for.
    pub fn violations(
        &self,
        mesh: &Mesh<'_>,
        current: &[u32],
        lod: &[u32],
        rule: &ChordRule<'_>,
    ) -> Vec<u32> {
        let present = self.present(lod);
        let mut lod_edges: BTreeMap<(u32, u32), Vec<(u32, u32)>> = BTreeMap::new();
        for t in lod.chunks_exact(3) {
            for k in 0..3 {
                let (a, b) = (
                    mesh.uv_wedge[t[k] as usize],
                    mesh.uv_wedge[t[(k + 1) % 3] as usize],
                );
                let (wa, wb) = (self.weld[a as usize], self.weld[b as usize]);
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
            if h1 == h2 {
                continue;
            }
            if let Some(full) = self.edges.get(&(u, w)) {
                let (mut a, mut b) = (full.clone(), vec![*h1, *h2]);
                a.sort_unstable();
                b.sort_unstable();
                if a == b {
                    // A seam edge of the full mesh, untouched.
                    continue;
                }
            }
            match self.explain(mesh, u, w, [*h1, *h2], &present, rule) {
                Ok(()) => {}
                Err(removed) if !removed.is_empty() => bad.extend(removed),
                Err(_) => {
                    // A seam edge that no chain explains: hold the removed
                    // seam vertices around it, or where none was removed
                    // (the triangles of a chart between two seams collapsed,
                    // and the charts on either side met), every vertex
                    // removed around it.
                    let before = bad.len();
                    for end in [u, w] {
                        bad.extend(
                            self.seam_neighbours[end as usize]
                                .iter()
                                .filter(|&&x| !present[x as usize]),
                        );
                    }
                    if bad.len() == before {
                        for t in current.chunks_exact(3) {
                            let ws = [t[0], t[1], t[2]].map(|i| self.weld[i as usize]);
                            if ws.contains(&u) || ws.contains(&w) {
                                bad.extend(ws.iter().filter(|&&x| !present[x as usize]));
                            }
                        }
                    }
                }
            }
        }
        bad.sort_unstable();
        bad.dedup();
        bad
    }

    /// Whether the new seam edge (`u`, `w`) (`u` < `w`), given by its two
    /// half-edges, replaces a stretch of one chain as a chord passing
    /// `rule`; else the removed vertices of that stretch (empty when
    /// no chain holds it).
    fn explain(
        &self,
        mesh: &Mesh<'_>,
        u: u32,
        w: u32,
        halves: [(u32, u32); 2],
        present: &[bool],
        rule: &ChordRule<'_>,
    ) -> Result<(), Vec<u32>> {
        let chains_of = |v: u32| -> Vec<u32> {
            match self.place[v as usize] {
                Some((c, _)) => vec![c],
                None => self.corner_chains.get(&v).cloned().unwrap_or_default(),
            }
        };
        for c in chains_of(u) {
            let chain = &self.chains[c as usize];
            let last = chain.vertices.len() - 1;
            let places =
                |v: u32| -> Vec<usize> { (0..=last).filter(|&k| chain.vertices[k] == v).collect() };
            for i in places(u) {
                for j in places(w) {
                    let (lo, hi) = (i.min(j), i.max(j));
                    if hi - lo < 2 {
                        continue;
                    }
                    let removed: Vec<u32> = chain.vertices[lo + 1..hi].to_vec();
                    if removed.iter().any(|&v| present[v as usize]) {
                        continue;
                    }
                    // The half-edges' wedges, as (at u, at w), must be the
                    // chain's two sides at those places.
                    let side = |s: usize| (chain.sides[s][i], chain.sides[s][j]);
                    let mut want = [side(0), side(1)];
                    let mut got = halves;
                    want.sort_unstable();
                    got.sort_unstable();
                    let consistent =
                        want == got && self.chord_passes(mesh, chain, lo, hi, rule).is_some();
                    return if consistent { Ok(()) } else { Err(removed) };
                }
            }
        }
        Err(Vec::new())
    }

    /// Welded vertices inside chains (free to move where the test allows).
    pub fn chain_vertex_count(&self) -> usize {
        self.place.iter().filter(|p| p.is_some()).count()
    }
}

/// Where `v` lies along the chord `p`–`n` in UV: its parameter, the
/// chord's length and `v`'s distance off it; `None` unless the parameter
/// is inside (0, 1).
fn on_chord(p: [f32; 2], n: [f32; 2], v: [f32; 2]) -> Option<(f64, f64, f64)> {
    let d = [f64::from(n[0] - p[0]), f64::from(n[1] - p[1])];
    let e = [f64::from(v[0] - p[0]), f64::from(v[1] - p[1])];
    let len2 = d[0] * d[0] + d[1] * d[1];
    if len2 <= 0.0 {
        return None;
    }
    let len = len2.sqrt();
    let t = (e[0] * d[0] + e[1] * d[1]) / len2;
    let off = (e[0] * d[1] - e[1] * d[0]).abs() / len;
    (t > 0.0 && t < 1.0).then_some((t, len, off))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two quads side by side in 3D along a seam x = 0 of three vertices,
    /// mapped to two charts: `right_mid` places the middle seam vertex of
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
        assert_eq!(topo.chain_vertex_count(), 1);
        let flags = topo.stage_flags(&mesh, &indices, &ChordRule::geometric(1e-4), None);
        assert_eq!(flags.counts.seam, 1);
        flags.lock[4]
    }

    #[test]
    fn a_seam_vertex_moves_only_where_both_sides_agree() {
        // Both sides straight, the middle vertex halfway on each.
        assert!(!mid_locked([0.5, 0.2]));
        // Straight, but at a third on one side: the ratios disagree.
        assert!(mid_locked([0.5, 0.4 / 3.0]));
        // Off the line on one side.
        assert!(mid_locked([0.52, 0.2]));
        // Off by less than the tolerance.
        assert!(!mid_locked([0.500_05, 0.2]));
    }
}
