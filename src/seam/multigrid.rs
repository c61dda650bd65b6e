//! Multigrid-preconditioned conjugate gradients for the erasure system.
//!
//! Far from the seams the system is a screened Poisson equation on the texel
//! lattice, which geometric multigrid solves in a few cycles. Near the seams
//! it is not: the seam terms (weight 1e10) tie texels on the two sides of a
//! cut, which lie far apart in the texture, and no lattice interpolation can
//! follow such a tie (a coarse hat function on one side alone would carry the
//! full seam penalty). So every level keeps the texels near the seams as
//! unknowns of their own ("exact" nodes, identity in the prolongation), and
//! coarsens only the rest, bilinearly by two per level. Coarsening stops
//! once the lattice part is no larger than the exact part, and that level,
//! the exact nodes plus a lattice of their size, is factored directly (by
//! connected piece: the bands of charts apart from each other do not touch).
//!
//! The smoother follows the same split. Gauss–Seidel relaxes the lattice
//! rows; the exact rows, whose stiff ties a pointwise sweep cannot follow, are
//! relaxed together by one block solve. Their block of the operator is the
//! same on every level (the prolongation is the identity there), so one
//! factorisation serves them all (split by seam strip into a few parts that
//! are solved in parallel). Against Gauss–Seidel on every row with a
//! three-texel margin, this (with a one-texel margin) takes Fox from 14 CG
//! iterations to 9 and blub from 7 to 5.
//!
//! Coarse operators are Galerkin products PᵀAP, so every level describes the
//! same energy. Levels above the coarsest keep most rows in closed form
//! ([`CoarseMatrix`]); the coarsest, to be factored, is in compressed rows.
//! A V-cycle whose post-smoother reverses its pre-smoother is a symmetric
//! preconditioner, and CG turns it into the solution of the fine system to
//! the tolerance below: the hierarchy decides only how fast.

use rayon::prelude::*;

use super::coarse::CoarseMatrix;
use super::sparse::{by_channels, Rows, SymCsr};
use super::stencil::StencilMatrix;
use super::system::{Cholesky, SolveError};
use super::transfer::Transfer;

/// CG stops when the error it leaves is estimated below this (in \[0, 1\]
/// units: 5e-4 of an 8-bit level, half the band's tolerance, and an eighth
/// of a 16-bit step). The preconditioned iteration contracts the error by a
/// steady ratio ρ per step (measured as the ratio of successive largest
/// steps), so what remains after a step of size s is about s·ρ/(1 − ρ).
const ERROR_TOLERANCE: f64 = 5e-4 / 255.0;
/// The ratio assumed until two steps have been measured, and its ceiling
/// (above it the estimate would be unreliable; the rule then waits for the
/// step itself to fall below the tolerance).
const MAX_RATIO: f64 = 0.5;
/// Or when every channel's residual falls below this fraction of its right-hand side's.
const RELATIVE_TOLERANCE: f64 = 1e-10;
const MAX_ITERATIONS: usize = 100;
/// Stop coarsening when the lattice part of a level has at most this many
/// nodes, or at most as many as the exact part (see [`Hierarchy::new`]).
const COARSEST_LATTICE: usize = 2048;
/// Relative diagonal shift of the coarsest lattice nodes (see [`Hierarchy::new`]).
const COARSE_SHIFT: f64 = 1e-6;
/// Elements per parallel task of the vector kernels.
const CHUNK: usize = 1 << 15;

/// The place of an unknown in the hierarchy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Node {
    /// Kept as an unknown of its own on every level.
    Exact,
    /// A lattice node at integer coordinates (in units of the level's spacing).
    Lattice(u32, u32),
}

pub struct Hierarchy {
    /// The finest operator, level 0.
    fine: StencilMatrix,
    /// The operators of levels 1 to L − 1, where L = `transfers.len()` is
    /// the coarsest level (its factor is kept apart, see [`solve`]; L = 0
    /// factors the fine one).
    coarse: Vec<CoarseMatrix>,
    /// `transfers[l]` prolongs from level l+1 to level l.
    transfers: Vec<Transfer>,
    /// The exact nodes of each level above the coarsest, and the factor of
    /// their block, which is the same on every level (P is the identity there).
    exact: Vec<Vec<u32>>,
    exact_block: Vec<BlockPart>,
    /// Per level above the coarsest: the exact rows' entries in lattice
    /// columns, all the pre-smoothing's exact correction reads.
    exact_lattice: Vec<LatticeEntries>,
    /// How Gauss–Seidel sweeps each level above the coarsest.
    sweeps: Vec<Sweep>,
}

impl Hierarchy {
    /// Builds the levels below `fine`, whose unknowns sit at `nodes`, and
    /// returns the coarsest level's operator, to be factored, beside them.
    /// `exact_rows` lists the exact nodes among `nodes` ([`exact_rows`]).
    /// The exact block's factor is left to the caller ([`solve`]).
    fn new(
        fine: StencilMatrix,
        nodes: Vec<Node>,
        exact_rows: Vec<u32>,
    ) -> Result<(Self, SymCsr), SolveError> {
        let t = std::time::Instant::now();
        let mut coarse: Vec<CoarseMatrix> = Vec::new();
        let mut last: Option<SymCsr> = None;
        let mut transfers = Vec::new();
        let mut nodes = nodes;
        let mut exact = Vec::new();
        let mut sweeps = Vec::new();
        let mut exact_lattice = Vec::new();
        // Which rows of the last level have the closed form (see `TensorRows`).
        let mut tensor = None;
        let mut exact_rows = exact_rows;
        loop {
            let exact_count = exact_rows.len();
            exact.push(exact_rows);
            if is_coarsest(nodes.len(), exact_count) {
                break;
            }
            // Both walk the level's rows on one thread: side by side.
            let (((transfer, next), coarsen_ms), (sweep, sweep_ms)) = rayon::join(
                || {
                    let tl = std::time::Instant::now();
                    (Transfer::coarsen(&nodes), tl.elapsed().as_millis() as u64)
                },
                || {
                    let tl = std::time::Instant::now();
                    let rows = exact.last().expect("this level's exact rows");
                    let sweep = match coarse.last() {
                        Some(a) => (Sweep::new(a, &nodes), LatticeEntries::new(a, rows, &nodes)),
                        None => (
                            Sweep::new(&fine, &nodes),
                            LatticeEntries::new(&fine, rows, &nodes),
                        ),
                    };
                    (sweep, tl.elapsed().as_millis() as u64)
                },
            );
            let (sweep, entries) = sweep;
            sweeps.push(sweep);
            exact_lattice.push(entries);
            let tl = std::time::Instant::now();
            exact_rows = self::exact_rows(&next);
            let (rows, closed, mb) = if is_coarsest(next.len(), exact_rows.len()) {
                // To be factored: in compressed rows.
                let (ac, _) = match coarse.last() {
                    Some(a) => a.galerkin_with(&transfer, true, tensor.as_ref())?,
                    None => fine.galerkin_with(&transfer, true, None)?,
                };
                let entry = std::mem::size_of::<u32>() + std::mem::size_of::<f64>();
                let counts = (ac.n, 0, ac.col.len() * entry / (1 << 20));
                last = Some(ac);
                counts
            } else {
                let (ac, next_tensor) = match coarse.last() {
                    Some(a) => a.galerkin_closed(&transfer, tensor.as_ref())?,
                    None => fine.galerkin_closed(&transfer, None)?,
                };
                tensor = next_tensor;
                let counts = (ac.n(), ac.closed_rows(), ac.bytes() / (1 << 20));
                coarse.push(ac);
                counts
            };
            tracing::debug!(
                rss_mb = crate::heap::resident_mb(),
                sweep_ms,
                coarsen_ms,
                galerkin_ms = tl.elapsed().as_millis() as u64,
                rows,
                closed,
                mb,
                "multigrid level"
            );
            transfers.push(transfer);
            nodes = next;
        }
        let galerkin = t.elapsed();
        exact.pop();
        // Hat functions of neighbouring lattice nodes can coincide on a lone
        // texel at a ragged band edge, which leaves the Galerkin operator
        // singular. A relative diagonal shift keeps the coarsest factor
        // positive definite; CG still converges to the unshifted fine solution.
        let mut last = match last {
            Some(a) => a,
            None => fine.to_csr()?,
        };
        last.shift_diagonal(COARSE_SHIFT, |i| nodes[i] != Node::Exact);
        tracing::debug!(
            rss_mb = crate::heap::resident_mb(),
            levels = transfers.len() + 1,
            fine = fine.n(),
            coarsest = last.n,
            coarsest_exact = nodes.iter().filter(|n| **n == Node::Exact).count(),
            galerkin_ms = galerkin.as_millis() as u64,
            "multigrid levels"
        );
        let h = Hierarchy {
            fine,
            coarse,
            transfers,
            exact,
            exact_block: Vec::new(),
            exact_lattice,
            sweeps,
        };
        Ok((h, last))
    }

    /// z += the exact correction on level `l`'s exact nodes, the rest held.
    ///
    /// Not on the level above the coarsest: there the coarse correction is
    /// exact, an A-orthogonal projection onto the range of P, which holds
    /// every exact direction (P is the identity on exact nodes). So it undoes
    /// any change the pre-smoothing correction made to exact nodes, and leaves
    /// a residual orthogonal to them, zero on exact rows, for the
    /// post-smoothing one to find (Fox: the same CG steps to nine digits; the
    /// coarsest level's diagonal shift is all that tells them apart).
    ///
    /// `fresh`: z is still zero on the exact rows (the way down), so their
    /// residual needs only their entries in lattice columns (the same values:
    /// subtracting a zero product changes no partial sum, at most the sign
    /// of a zero one).
    fn exact_correction<A: Rows>(
        &self,
        a: &A,
        l: usize,
        r: &[f64],
        z: &mut [f64],
        ch: usize,
        fresh: bool,
    ) {
        let Some(rows) = self.exact.get(l) else {
            return;
        };
        if self.exact_block.is_empty() || l + 1 == self.transfers.len() {
            return;
        }
        let mut s = vec![0.0; rows.len() * ch];
        match fresh {
            true => self.exact_lattice[l].residual(rows, r, z, &mut s, ch),
            false => a.residual_rows(rows, r, z, &mut s, ch),
        }
        assert!(z.len() >= a.n() * ch);
        BlockPart::solve(&self.exact_block, &s, ch, |k, c, d| {
            let i = rows[k] as usize;
            let zi = z[i * ch + c..i * ch + c + d.len()].iter_mut();
            zi.zip(d).for_each(|(zc, dc)| *zc += dc);
        });
    }

    /// z = M⁻¹ r, one V-cycle; `z` must be zero on entry.
    fn vcycle(&self, coarsest: &[BlockPart], r: &[f64], z: &mut [f64], ws: &mut [Work], ch: usize) {
        self.descend(0, r, z, ws, ch);
        self.ascend(coarsest, 0, r, z, ws, ch);
    }

    /// The V-cycle's way down from level `l` (right-hand side `r`, `z` zero):
    /// on each level above the coarsest, pre-smoothing and the restriction of
    /// the residual into `ws`. Needs no coarsest factor, so the first cycle
    /// runs it while that factor is being made (see [`solve`]).
    fn descend(&self, l: usize, r: &[f64], z: &mut [f64], ws: &mut [Work], ch: usize) {
        let Some((w, rest)) = ws.split_first_mut() else {
            return;
        };
        match l {
            0 => self.presmooth(&self.fine, l, r, z, &mut w.coarse_rhs, ch),
            _ => self.presmooth(&self.coarse[l - 1], l, r, z, &mut w.coarse_rhs, ch),
        }
        w.coarse_z.par_chunks_mut(CHUNK).for_each(|c| c.fill(0.0));
        self.descend(l + 1, &w.coarse_rhs, &mut w.coarse_z, rest, ch);
    }

    /// The way back up to level `l` after [`Self::descend`]: the coarsest
    /// solve, then on each level the prolonged correction and post-smoothing
    /// (the pre-smoothing's steps in reverse, so the cycle stays symmetric).
    fn ascend(
        &self,
        coarsest: &[BlockPart],
        l: usize,
        r: &[f64],
        z: &mut [f64],
        ws: &mut [Work],
        ch: usize,
    ) {
        let Some((w, rest)) = ws.split_first_mut() else {
            BlockPart::solve(coarsest, r, ch, |k, c, d| {
                z[k * ch + c..k * ch + c + d.len()].copy_from_slice(d);
            });
            return;
        };
        self.ascend(coarsest, l + 1, &w.coarse_rhs, &mut w.coarse_z, rest, ch);
        self.transfers[l].prolong_add(&w.coarse_z, z, ch);
        match l {
            0 => self.postsmooth(&self.fine, l, r, z, ch),
            _ => self.postsmooth(&self.coarse[l - 1], l, r, z, ch),
        }
    }

    fn presmooth<A: Rows>(
        &self,
        a: &A,
        l: usize,
        r: &[f64],
        z: &mut [f64],
        coarse_rhs: &mut [f64],
        ch: usize,
    ) {
        self.sweeps[l].run(a, r, z, ch, true);
        self.exact_correction(a, l, r, z, ch, true);
        self.transfers[l].restrict_residual(a, r, z, coarse_rhs, ch);
    }

    fn postsmooth<A: Rows>(&self, a: &A, l: usize, r: &[f64], z: &mut [f64], ch: usize) {
        self.exact_correction(a, l, r, z, ch, false);
        self.sweeps[l].run(a, r, z, ch, false);
    }

    fn workspace(&self, ch: usize) -> Vec<Work> {
        self.transfers
            .iter()
            .map(|p| Work {
                coarse_rhs: crate::heap::filled(p.coarse * ch, 0.0),
                coarse_z: crate::heap::filled(p.coarse * ch, 0.0),
            })
            .collect()
    }
}

/// The indices of the exact nodes among `nodes`.
fn exact_rows(nodes: &[Node]) -> Vec<u32> {
    nodes
        .iter()
        .enumerate()
        .filter(|(_, n)| **n == Node::Exact)
        .map(|(i, _)| i as u32)
        .collect()
}

/// Whether a level of `n` unknowns, `exact` of them exact, is the coarsest.
///
/// Every level carries all the exact nodes, and the coarsest factor must
/// take them anyway; once the lattice is no larger than they are, factoring
/// it too costs little, while coarser lattices approximate the ties near the
/// seams ever worse. Stopping there takes Fox from 8 CG iterations to 5 and
/// blub (global) from 8 to 3.
fn is_coarsest(n: usize, exact: usize) -> bool {
    n - exact <= COARSEST_LATTICE.max(exact)
}

/// The exact block and the coarsest level are split into at most this many
/// parts, whole connected pieces (seam strips; the bands of separate charts)
/// each, factored and solved in parallel. A fixed count, so the bits do not
/// depend on the number of threads.
const BLOCK_PARTS: usize = 4;

/// One part of a split matrix: its rows (for the exact block, indices into a
/// level's exact list) and their factor.
struct BlockPart {
    rows: Vec<u32>,
    factor: Cholesky,
}

impl BlockPart {
    /// Splits `block` into its connected pieces, dealt out to at most
    /// [`BLOCK_PARTS`] parts of about equal size, and factors each part.
    fn split(block: SymCsr) -> Result<Vec<BlockPart>, SolveError> {
        let n = block.n;
        let mut parent: Vec<u32> = (0..n as u32).collect();
        fn find(parent: &mut [u32], mut i: u32) -> u32 {
            while parent[i as usize] != i {
                parent[i as usize] = parent[parent[i as usize] as usize];
                i = parent[i as usize];
            }
            i
        }
        for i in 0..n {
            for e in block.ptr[i]..block.ptr[i + 1] {
                let (a, b) = (find(&mut parent, i as u32), find(&mut parent, block.col[e]));
                if a != b {
                    parent[a.max(b) as usize] = a.min(b);
                }
            }
        }
        // Pieces in order of their first row, each to the smallest part so far.
        let mut part_of_root = vec![u32::MAX; n];
        let mut sizes = [0usize; BLOCK_PARTS];
        let mut rows: Vec<Vec<u32>> = vec![Vec::new(); BLOCK_PARTS];
        let mut piece_size = vec![0usize; n];
        for i in 0..n as u32 {
            let root = find(&mut parent, i);
            piece_size[root as usize] += 1;
        }
        for i in 0..n as u32 {
            let root = find(&mut parent, i) as usize;
            if part_of_root[root] == u32::MAX {
                let smallest = (0..BLOCK_PARTS).min_by_key(|&p| sizes[p]).unwrap_or(0);
                part_of_root[root] = smallest as u32;
                sizes[smallest] += piece_size[root];
            }
            rows[part_of_root[root] as usize].push(i);
        }
        if n > 0 && rows.iter().any(|r| r.len() == n) {
            // One piece (a many-seam atlas's seams all meet): the part is the
            // block itself, whose copy would be the same matrix.
            let rows = (0..n as u32).collect();
            let factor = Cholesky::new(&block.into_faer())?;
            return Ok(vec![BlockPart { rows, factor }]);
        }
        rows.into_par_iter()
            .filter(|r| !r.is_empty())
            .map(|rows| {
                let factor = Cholesky::new(&block.submatrix(&rows)?.into_faer())?;
                Ok(BlockPart { rows, factor })
            })
            .collect()
    }

    /// Solves the split block for `s` (`ch` channels, interleaved), the
    /// parts in parallel, and hands each row's solution to `put` (row, first
    /// channel, values). `put` runs under a lock: a handful of values per
    /// row, against a solve's many.
    ///
    /// A block in one piece (a many-seam atlas) is solved as two tasks, each
    /// for some of the channels: a triangular solve is a chain of dependent
    /// steps that one thread walks alone, and each channel's steps are its
    /// own, the same whichever others are solved beside it (blub_atlas level
    /// 0 spent 0.4 s of its CG on one thread in these solves).
    fn solve(
        parts: &[BlockPart],
        s: &[f64],
        ch: usize,
        put: impl FnMut(usize, usize, &[f64]) + Send,
    ) {
        let put = std::sync::Mutex::new(put);
        let split = match parts.len() == 1 && ch >= 2 {
            true => ch.div_ceil(2),
            false => ch,
        };
        let tasks: Vec<(&BlockPart, std::ops::Range<usize>)> = parts
            .iter()
            .flat_map(|p| [(p, 0..split), (p, split..ch)])
            .filter(|(_, c)| !c.is_empty())
            .collect();
        tasks.par_iter().for_each(|(p, channels)| {
            let cw = channels.len();
            let mut b = Vec::with_capacity(p.rows.len() * cw);
            for &k in &p.rows {
                b.extend_from_slice(
                    &s[k as usize * ch + channels.start..k as usize * ch + channels.end],
                );
            }
            let d = p.factor.solve_interleaved(&b, cw);
            let mut put = put.lock().unwrap_or_else(|e| e.into_inner());
            for (m, &k) in p.rows.iter().enumerate() {
                put(k as usize, channels.start, &d[m * cw..(m + 1) * cw]);
            }
        });
    }
}

/// Some rows' entries in some columns, in compressed rows.
struct LatticeEntries {
    ptr: Vec<usize>,
    col: Vec<u32>,
    val: Vec<f64>,
}

impl LatticeEntries {
    /// The entries of `rows` of `a` in the columns of lattice nodes, in column order.
    fn new<A: Rows>(a: &A, rows: &[u32], nodes: &[Node]) -> Self {
        let mut e = LatticeEntries {
            ptr: Vec::with_capacity(rows.len() + 1),
            col: Vec::new(),
            val: Vec::new(),
        };
        e.ptr.push(0);
        for &i in rows {
            a.for_each(i as usize, |j, v| {
                if nodes[j] != Node::Exact {
                    e.col.push(j as u32);
                    e.val.push(v);
                }
            });
            e.ptr.push(e.col.len());
        }
        e
    }

    /// out = (r − A z) on `rows` (the rows these entries were taken from),
    /// where z is zero outside the entries' columns.
    fn residual(&self, rows: &[u32], r: &[f64], z: &[f64], out: &mut [f64], ch: usize) {
        out.par_chunks_mut(ROWS_PER_TASK * ch)
            .enumerate()
            .for_each(|(b, os)| {
                for (m, o) in os.chunks_exact_mut(ch).enumerate() {
                    let k = b * ROWS_PER_TASK + m;
                    let i = rows[k] as usize;
                    o.copy_from_slice(&r[i * ch..(i + 1) * ch]);
                    for e in self.ptr[k]..self.ptr[k + 1] {
                        let (j, v) = (self.col[e] as usize, self.val[e]);
                        for c in 0..ch {
                            o[c] -= v * z[j * ch + c];
                        }
                    }
                }
            });
    }
}

/// Rows per parallel task of [`LatticeEntries::residual`].
const ROWS_PER_TASK: usize = 4096;

/// Lattice rows per stripe of this many lattice rows.
const STRIPE: u32 = 8;

/// Gauss–Seidel on one level's lattice rows (the exact rows are relaxed by
/// the block solve: no pointwise sweep can follow their seam ties).
///
/// The rows go in stripes of [`STRIPE`] lattice rows. A lattice row couples
/// only to lattice rows one lattice step away and to exact rows, so stripes of
/// the same parity share nothing a sweep writes, and run in parallel: even
/// stripes, then odd ones (the backward sweep reverses everything). This is
/// Gauss–Seidel in a fixed order, whatever the number of threads.
struct Sweep {
    /// `stripes[c]`: the stripes of parity c, each its rows in increasing order.
    stripes: [Vec<Vec<u32>>; 2],
}

impl Sweep {
    fn new<A: Rows>(a: &A, nodes: &[Node]) -> Self {
        let stripe_of = |i: usize| match nodes[i] {
            Node::Lattice(_, y) => Some(y / STRIPE),
            Node::Exact => None,
        };
        let count = nodes
            .iter()
            .filter_map(|n| match n {
                Node::Lattice(_, y) => Some(y / STRIPE + 1),
                Node::Exact => None,
            })
            .max()
            .unwrap_or(0) as usize;
        let mut by_stripe = vec![Vec::new(); count];
        let mut local = true;
        for i in 0..a.n() {
            let Some(s) = stripe_of(i) else { continue };
            by_stripe[s as usize].push(i as u32);
            a.for_each(i, |j, _| {
                if let Some(t) = stripe_of(j) {
                    local &= s.abs_diff(t) <= 1;
                }
            });
        }
        if !local {
            // Not expected from bilinear coarsening; stay correct regardless.
            let mut rows: Vec<u32> = by_stripe.into_iter().flatten().collect();
            rows.sort_unstable();
            return Sweep {
                stripes: [vec![rows], Vec::new()],
            };
        }
        let mut stripes = [Vec::new(), Vec::new()];
        for (s, rows) in by_stripe.into_iter().enumerate() {
            if !rows.is_empty() {
                stripes[s % 2].push(rows);
            }
        }
        Sweep { stripes }
    }

    fn run<A: Rows>(&self, a: &A, r: &[f64], z: &mut [f64], ch: usize, forward: bool) {
        assert!(ch <= 4 && z.len() >= a.n() * ch && r.len() >= a.n() * ch);
        let order = if forward { [0, 1] } else { [1, 0] };
        let shared = Shared(z.as_mut_ptr());
        for colour in order {
            self.stripes[colour].par_iter().for_each(|rows| {
                // SAFETY: `z` is exclusively borrowed for this call and holds
                // n·ch values; the rows come from 0..n (`Sweep::new`). A task
                // writes only its own rows, and reads its own rows, rows of
                // the other parity (which no task writes in this phase) and
                // exact rows (which no sweep writes), as `Sweep::new` checked.
                unsafe { a.gauss_seidel_raw(rows, r, shared.get(), ch, forward) };
            });
        }
    }
}

/// A pointer that may cross threads, for tasks that write disjoint entries
/// (see [`Sweep::run`]).
#[derive(Clone, Copy)]
struct Shared(*mut f64);
unsafe impl Send for Shared {}
unsafe impl Sync for Shared {}

impl Shared {
    fn get(self) -> *mut f64 {
        self.0
    }
}

/// Scratch vectors of one level of the V-cycle.
struct Work {
    coarse_rhs: Vec<f64>,
    coarse_z: Vec<f64>,
}

/// Per-channel sums of `f(u_i, v_i)`, in fixed chunks so the bits do not
/// depend on the thread count.
fn dots<const C: usize>(u: &[f64], v: &[f64]) -> [f64; 4] {
    let ch = C;
    let parts: Vec<[f64; 4]> = u
        .par_chunks(CHUNK * ch)
        .zip(v.par_chunks(CHUNK * ch))
        .map(|(a, b)| {
            let mut d = [0.0f64; 4];
            for (x, y) in a.chunks_exact(ch).zip(b.chunks_exact(ch)) {
                for c in 0..ch {
                    d[c] += x[c] * y[c];
                }
            }
            d
        })
        .collect();
    let mut d = [0.0f64; 4];
    for p in parts {
        for c in 0..4 {
            d[c] += p[c];
        }
    }
    d
}

/// Solves A x = b (`ch` ≤ 4 interleaved channels), A = `fine` with its
/// unknowns at `nodes`, by CG preconditioned with one V-cycle of the
/// hierarchy built for it, from the guess `x0`. Returns x and the iteration
/// count (0 where `x0` is already within the tolerance). `floor` is a lower
/// bound on A's eigenvalues: the erasure's smallest anchor weight, as A is
/// the diagonal of anchors plus squares (gradients, seam sums, C1 terms).
///
/// `b` is taken by value and becomes the residual: on a 2048² band each
/// vector is about 50 MB, and each megabyte a process touches for the first
/// time costs a page fault per page.
pub fn solve(
    fine: StencilMatrix,
    nodes: Vec<Node>,
    b: Vec<f64>,
    ch: usize,
    x0: Vec<f64>,
    floor: f64,
) -> Result<(Vec<f64>, usize), SolveError> {
    by_channels!(ch, solve_n(fine, nodes, b, x0, floor))
}

/// CG's state once its first V-cycle has come down to the coarsest level.
struct Start {
    r: Vec<f64>,
    zq: Vec<f64>,
    p: Vec<f64>,
    ws: Vec<Work>,
}

fn solve_n<const C: usize>(
    fine: StencilMatrix,
    nodes: Vec<Node>,
    b: Vec<f64>,
    x0: Vec<f64>,
    floor: f64,
) -> Result<(Vec<f64>, usize), SolveError> {
    let ch = C;
    let bb = dots::<C>(&b, &b);
    let mut r = b;
    fine.residual_in_place(&mut r, &x0, ch);
    // A is `floor` times the identity plus a positive semi-definite rest, so
    // the guess is off by at most |r|/floor in any value. Where that is
    // within CG's tolerance already (a texture whose seams agree as painted,
    // such as WaterBottle's emissive map: |r| = 2e-15, the bound a third of
    // the tolerance), the hierarchy and its factors, most of a solve's
    // time, are not made at all.
    let rr = dots::<C>(&r, &r);
    if (0..ch).all(|c| rr[c].sqrt() <= ERROR_TOLERANCE * floor) {
        return Ok((x0, 0));
    }
    // The hierarchy's construction keeps both threads busy on its own; the
    // two factorisations are each one thread's work where the matrix is one
    // piece (a many-seam atlas). So the levels come first, then the coarsest
    // level is factored on one thread while the other factors the exact
    // block and takes CG as far as the coarsest solve of its first cycle,
    // and makes CG's search direction. (Beside the levels' construction, the
    // exact block left the coarsest factorisation alone at the end, one
    // thread idle for most of it: blub_atlas level 0, 0.4–0.7 s.) Split by
    // connected piece, the factorisations take the other thread too once
    // its work is done (Fox: four parts, 31 522 + 8 664 + 2 687 + 25 745
    // unknowns). Without a level below the fine one there is no smoother
    // to use the exact block.
    let exact = exact_rows(&nodes);
    let block = match exact.is_empty() || is_coarsest(nodes.len(), exact.len()) {
        true => None,
        false => Some(fine.submatrix(&exact)?),
    };
    let (mut m, last) = Hierarchy::new(fine, nodes, exact)?;
    let t = std::time::Instant::now();
    let n = m.fine.n();
    let (coarsest, start) = rayon::join(
        || BlockPart::split(last),
        || {
            let tb = std::time::Instant::now();
            m.exact_block = block.map_or(Ok(Vec::new()), BlockPart::split)?;
            tracing::debug!(
                rss_mb = crate::heap::resident_mb(),
                elapsed_ms = tb.elapsed().as_millis() as u64,
                "exact block factored"
            );
            let m = &m;
            let mut ws = m.workspace(ch);
            // `zq` holds the preconditioned residual z, and A p in its turn: A p
            // is spent on updating x and r before the next V-cycle writes z.
            let mut zq = crate::heap::filled(n * ch, 0.0);
            m.descend(0, &r, &mut zq, &mut ws, ch);
            let p = crate::heap::filled(n * ch, 0.0);
            Ok::<_, SolveError>(Start { r, zq, p, ws })
        },
    );
    let (coarsest, start) = (coarsest?, start?);
    tracing::debug!(
        rss_mb = crate::heap::resident_mb(),
        elapsed_ms = t.elapsed().as_millis() as u64,
        "coarsest level factored"
    );
    let Start {
        mut r,
        mut zq,
        mut p,
        mut ws,
    } = start;
    let m = &m;
    let a = &m.fine;
    let mut x = x0;
    m.ascend(&coarsest, 0, &r, &mut zq, &mut ws, ch);
    p.par_chunks_mut(CHUNK * ch)
        .zip(zq.par_chunks(CHUNK * ch))
        .for_each(|(p, z)| p.copy_from_slice(z));
    let mut rz = dots::<C>(&r, &zq);
    let (mut last_step, mut last_ratio) = (0.0f64, MAX_RATIO);
    for it in 1..=MAX_ITERATIONS {
        let (pq, pmax) = a.apply_dot(&p, &mut zq, ch, CHUNK);
        let mut alpha = [0.0f64; 4];
        for c in 0..ch {
            alpha[c] = if pq[c] > 0.0 { rz[c] / pq[c] } else { 0.0 };
        }
        // The largest change this step makes: |α·p_i| = |α|·|p_i| exactly,
        // and rounding keeps order, so this is the largest of the products.
        let step = (0..ch)
            .map(|c| alpha[c].abs() * pmax[c])
            .fold(0.0f64, f64::max);
        // x takes its step later, in the pass that updates p (or before
        // returning): one pass over the vectors less per iteration.
        // A p is spent here: zq is cleared in the same pass, for the V-cycle.
        let parts: Vec<[f64; 4]> = r
            .par_chunks_mut(CHUNK * ch)
            .zip(zq.par_chunks_mut(CHUNK * ch))
            .map(|(rs, qs)| {
                let mut rr = [0.0f64; 4];
                for (ri, qi) in rs.chunks_exact_mut(ch).zip(qs.chunks_exact_mut(ch)) {
                    for c in 0..ch {
                        ri[c] -= alpha[c] * qi[c];
                        rr[c] += ri[c] * ri[c];
                        qi[c] = 0.0;
                    }
                }
                rr
            })
            .collect();
        let mut rr = [0.0f64; 4];
        for pr in parts {
            for c in 0..4 {
                rr[c] += pr[c];
            }
        }
        tracing::trace!(
            iteration = it,
            step_levels = step * 255.0,
            residual = (rr[0] / bb[0]).sqrt(),
            "cg"
        );
        // CG's steps do not shrink evenly: take the worse of the last two ratios.
        let measured = if last_step > 0.0 {
            step / last_step
        } else {
            MAX_RATIO
        };
        let ratio = measured.max(last_ratio).min(MAX_RATIO);
        (last_step, last_ratio) = (step, measured);
        let remaining = step * ratio / (1.0 - ratio);
        if remaining <= ERROR_TOLERANCE
            || (0..ch).all(|c| rr[c] <= RELATIVE_TOLERANCE.powi(2) * bb[c])
        {
            x.par_chunks_mut(CHUNK * ch)
                .zip(p.par_chunks(CHUNK * ch))
                .for_each(|(xs, ps)| {
                    for (xi, pi) in xs.chunks_exact_mut(ch).zip(ps.chunks_exact(ch)) {
                        for c in 0..ch {
                            xi[c] += alpha[c] * pi[c];
                        }
                    }
                });
            return Ok((x, it));
        }
        m.vcycle(&coarsest, &r, &mut zq, &mut ws, ch);
        let rz_new = dots::<C>(&r, &zq);
        let mut beta = [0.0f64; 4];
        for c in 0..ch {
            beta[c] = if rz[c] > 0.0 { rz_new[c] / rz[c] } else { 0.0 };
        }
        rz = rz_new;
        x.par_chunks_mut(CHUNK * ch)
            .zip(p.par_chunks_mut(CHUNK * ch))
            .zip(zq.par_chunks(CHUNK * ch))
            .for_each(|((xs, ps), zs)| {
                for ((xi, pi), zi) in xs
                    .chunks_exact_mut(ch)
                    .zip(ps.chunks_exact_mut(ch))
                    .zip(zs.chunks_exact(ch))
                {
                    for c in 0..ch {
                        xi[c] += alpha[c] * pi[c];
                        pi[c] = zi[c] + beta[c] * pi[c];
                    }
                }
            });
    }
    Err(SolveError::NotConverged(MAX_ITERATIONS))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every unknown's mass in [`problem`].
    const MASS: f64 = 1e-2;

    /// A w×h five-point lattice with mass, plus three exact unknowns tied
    /// stiffly to each other and to a few lattice nodes, as seam rows are.
    fn problem(w: u32, h: u32) -> (SymCsr, Vec<Node>) {
        let mut nodes: Vec<Node> = (0..w * h).map(|i| Node::Lattice(i % w, i / w)).collect();
        nodes.extend([Node::Exact; 3]);
        let n = nodes.len();
        let mut rows = vec![std::collections::BTreeMap::<usize, f64>::new(); n];
        let mut link = |a: usize, b: usize, wt: f64| {
            *rows[a].entry(a).or_default() += wt;
            *rows[b].entry(b).or_default() += wt;
            *rows[a].entry(b).or_default() -= wt;
            *rows[b].entry(a).or_default() -= wt;
        };
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                if x + 1 < w {
                    link(i, i + 1, 1.0);
                }
                if y + 1 < h {
                    link(i, i + w as usize, 1.0);
                }
            }
        }
        let e = (w * h) as usize;
        link(e, e + 1, 1e6);
        link(e + 1, e + 2, 3e5);
        link(e, 10, 1.0);
        link(e + 1, 4 * w as usize + 4, 2.0);
        link(e + 2, 4 * w as usize + 5, 1.0);
        let mut ptr = vec![0];
        let (mut col, mut val) = (Vec::new(), Vec::new());
        for (i, row) in rows.iter().enumerate() {
            for (&j, &v) in row {
                col.push(j as u32);
                val.push(v + if i == j { MASS } else { 0.0 });
            }
            ptr.push(col.len());
        }
        (SymCsr::from_parts(ptr, col, val).unwrap(), nodes)
    }

    #[test]
    fn lattice_galerkin_equals_the_general_triple_product() {
        let (a, nodes) = problem(9, 7);
        let (p, coarse) = Transfer::coarsen(&nodes);
        assert!(coarse.len() < nodes.len());
        let fast = a.galerkin(&p, true).unwrap();
        let general = a.galerkin(&p, false).unwrap();
        assert_eq!(fast.ptr, general.ptr);
        assert_eq!(fast.col, general.col);
        for (x, y) in fast.val.iter().zip(&general.val) {
            assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{x} vs {y}");
        }
    }

    #[test]
    fn closed_form_rows_equal_the_general_triple_product() {
        let (a, nodes) = problem(80, 60);
        let (p, coarse_nodes) = Transfer::coarsen(&nodes);
        let fine = StencilMatrix::from_csr(&a, -1.0).unwrap();
        let tensor = fine.tensor_rows(&p).expect("stencil rows");
        // Most of the lattice's interior takes the closed form.
        assert!(tensor.d.iter().filter(|d| !d.is_nan()).count() > 30 * 20);
        let (fast, coarse_tensor) = fine.galerkin_with(&p, true, None).unwrap();
        let general = a.galerkin(&p, false).unwrap();
        let same = |fast: &SymCsr, general: &SymCsr| {
            assert_eq!(fast.ptr, general.ptr);
            assert_eq!(fast.col, general.col);
            for (x, y) in fast.val.iter().zip(&general.val) {
                assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{x} vs {y}");
            }
        };
        same(&fast, &general);
        // Kept in closed form, the rows list the same entries, to the bit.
        let (closed, closed_tensor) = fine.galerkin_closed(&p, None).unwrap();
        assert!(closed.closed_rows() > 30 * 20, "{}", closed.closed_rows());
        let identical = |a: &SymCsr, b: &SymCsr| {
            assert_eq!((&a.ptr, &a.col), (&b.ptr, &b.col));
            assert!(a
                .val
                .iter()
                .zip(&b.val)
                .all(|(x, y)| x.to_bits() == y.to_bits()));
        };
        identical(&closed.to_csr().unwrap(), &fast);
        assert_eq!(
            closed_tensor.as_ref().map(|t| t.d.len()),
            coarse_tensor.as_ref().map(|t| t.d.len())
        );
        // And one level further, from the closed-form rows of the first.
        let coarse_tensor = coarse_tensor.expect("tensor rows carried down");
        assert!(coarse_tensor.d.iter().filter(|d| !d.is_nan()).count() > 10 * 5);
        let (p2, _) = Transfer::coarsen(&coarse_nodes);
        let (fast2, _) = fast.galerkin_with(&p2, true, Some(&coarse_tensor)).unwrap();
        same(&fast2, &general.galerkin(&p2, false).unwrap());
        let (closed2, _) = closed.galerkin_closed(&p2, Some(&coarse_tensor)).unwrap();
        identical(&closed2.to_csr().unwrap(), &fast2);
    }

    /// `problem(120, 80)`, large enough for three levels, with a solution
    /// and its right-hand side.
    fn solved_problem() -> (SymCsr, Vec<Node>, Vec<f64>, Vec<f64>) {
        let (a, nodes) = problem(120, 80);
        let x: Vec<f64> = (0..a.n * 3).map(|i| (i as f64 * 0.61).sin()).collect();
        let mut b = vec![0.0; a.n * 3];
        a.apply(&x, &mut b, 3);
        (a, nodes, x, b)
    }

    fn largest_difference(x: &[f64], y: &[f64]) -> f64 {
        x.iter()
            .zip(y)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn multigrid_cg_solves_the_system() {
        let (a, nodes, x_true, b) = solved_problem();
        let fine = StencilMatrix::from_csr(&a, -1.0).unwrap();
        assert!(fine.stored_rows() > 0 && fine.stored_rows() < 20);
        let (m, _) = Hierarchy::new(fine, nodes.clone(), exact_rows(&nodes)).unwrap();
        assert!(m.transfers.len() >= 2, "{} levels", m.transfers.len() + 1);
        let fine = StencilMatrix::from_csr(&a, -1.0).unwrap();
        let (x, _) = solve(fine, nodes, b, 3, vec![0.0; a.n * 3], MASS).unwrap();
        let worst = largest_difference(&x, &x_true);
        // CG stops once its estimated remaining error is below 1e-4 of a level.
        assert!(worst < 1e-5, "{worst}");
    }

    #[test]
    fn a_guess_that_solves_the_system_is_returned_untouched() {
        let (a, nodes, x_true, b) = solved_problem();
        let fine = || StencilMatrix::from_csr(&a, -1.0).unwrap();
        let (x, iterations) =
            solve(fine(), nodes.clone(), b.clone(), 3, x_true.clone(), MASS).unwrap();
        assert_eq!((iterations, &x), (0, &x_true));
        // One value off by a thousandth of a level is a residual CG must remove.
        let mut near = x_true.clone();
        near[a.n / 2 * 3] += 1e-3 / 255.0;
        let (x, iterations) = solve(fine(), nodes, b, 3, near, MASS).unwrap();
        assert!(iterations >= 1);
        let worst = largest_difference(&x, &x_true);
        assert!(worst < 1e-5, "{worst}");
    }
}
