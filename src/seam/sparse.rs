//! The kernels the multigrid solver runs on symmetric matrices (products,
//! Gauss–Seidel sweeps and the Galerkin triple product), written once
//! against [`Rows`], and symmetric matrices in compressed rows.
//!
//! Vectors hold `ch` channels per unknown, interleaved, so one pass over the
//! matrix serves every channel. Every kernel gives the same bits whatever the
//! thread count: rows are split into fixed chunks, each computed in a fixed order.

use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use rayon::prelude::*;

use super::coarse::{Closed, CoarseMatrix};
use super::system::SolveError;
use super::transfer::{Square, Transfer};

/// Calls a kernel with the channel count as a constant (1 to 4), so that its
/// per-row channel loops unroll and short copies stay inline.
macro_rules! by_channels {
    ($ch:expr, $recv:ident . $f:ident ( $($arg:expr),* )) => {
        match $ch {
            1 => $recv.$f::<1>($($arg),*),
            2 => $recv.$f::<2>($($arg),*),
            3 => $recv.$f::<3>($($arg),*),
            4 => $recv.$f::<4>($($arg),*),
            c => panic!("{c} channels: at most 4 are supported"),
        }
    };
    ($ch:expr, $f:ident ( $($arg:expr),* )) => {
        match $ch {
            1 => $f::<1>($($arg),*),
            2 => $f::<2>($($arg),*),
            3 => $f::<3>($($arg),*),
            4 => $f::<4>($($arg),*),
            c => panic!("{c} channels: at most 4 are supported"),
        }
    };
}
pub(super) use by_channels;

/// Rows per parallel task: large enough to amortise scheduling, small enough
/// to balance two to a few dozen threads.
const CHUNK: usize = 8192;

/// A symmetric matrix with both triangles stored, rows sorted by column.
/// Being symmetric, its CSR arrays are also its CSC arrays.
#[derive(Clone, Debug, Default)]
pub struct SymCsr {
    pub n: usize,
    pub ptr: Vec<usize>,
    pub col: Vec<u32>,
    pub val: Vec<f64>,
    /// Position of each row's diagonal entry in `col`/`val`.
    diag: Vec<usize>,
}

impl SymCsr {
    /// From rows already sorted by column, each holding its diagonal.
    pub fn from_parts(ptr: Vec<usize>, col: Vec<u32>, val: Vec<f64>) -> Result<Self, SolveError> {
        let n = ptr.len().saturating_sub(1);
        if let Some(&c) = col.iter().find(|&&c| c as usize >= n) {
            return Err(SolveError::Assembly(format!(
                "column {c} out of range for {n} rows"
            )));
        }
        let mut diag = Vec::with_capacity(n);
        for i in 0..n {
            let row = &col[ptr[i]..ptr[i + 1]];
            match row.binary_search(&(i as u32)) {
                Ok(k) if val[ptr[i] + k] > 0.0 => diag.push(ptr[i] + k),
                _ => {
                    return Err(SolveError::NotPositiveDefinite(format!(
                        "row {i} has no positive diagonal"
                    )))
                }
            }
        }
        Ok(SymCsr {
            n,
            ptr,
            col,
            val,
            diag,
        })
    }

    /// Scales the diagonal entries of the rows where `pick` holds by `1 + shift`.
    pub fn shift_diagonal(&mut self, shift: f64, pick: impl Fn(usize) -> bool) {
        for i in 0..self.n {
            if pick(i) {
                self.val[self.diag[i]] *= 1.0 + shift;
            }
        }
    }

    /// For faer's Cholesky, which reads the lower triangle of a CSC matrix.
    /// Consumes the rows: a coarsest level's are tens of megabytes.
    pub fn into_faer(self) -> SparseColMat<u32, f64> {
        SparseColMat::new(
            SymbolicSparseColMat::new_checked(
                self.n,
                self.n,
                self.ptr.iter().map(|&p| p as u32).collect(),
                None,
                self.col,
            ),
            self.val,
        )
    }
}

/// Rows per parallel run of [`Rows::submatrix`].
const SUBMATRIX_RUN: usize = 8192;

/// Read access to the rows of a symmetric matrix, and the kernels the
/// multigrid solver runs on it. Rows list their entries in increasing column
/// order, diagonal included, so every kernel sums in the same order whatever
/// the storage.
pub trait Rows: Sync {
    fn n(&self) -> usize;
    /// The diagonal entry of row `i`.
    fn diagonal(&self, i: usize) -> f64;
    /// Calls `f(column, value)` for each entry of row `i`, in column order.
    fn for_each(&self, i: usize, f: impl FnMut(usize, f64));

    /// The rows that have the tensor form over the lattice `p` coarsens
    /// (see [`TensorRows`]), where the storage tells; `None` otherwise.
    fn tensor_rows(&self, _p: &Transfer) -> Option<TensorRows> {
        None
    }

    /// y = A x.
    fn apply(&self, x: &[f64], y: &mut [f64], ch: usize) {
        by_channels!(ch, apply_n(self, x, y))
    }

    /// y = A x, and per channel Σ x_i·y_i and max |x_i|, summed over fixed
    /// runs of `rows` rows (so the bits do not depend on the thread count),
    /// the runs' sums then added in order.
    fn apply_dot(&self, x: &[f64], y: &mut [f64], ch: usize, rows: usize) -> ([f64; 4], [f64; 4]) {
        by_channels!(ch, apply_dot_n(self, x, y, rows))
    }

    /// r = b − A x.
    fn residual(&self, b: &[f64], x: &[f64], r: &mut [f64], ch: usize) {
        by_channels!(ch, residual_n(self, b, x, r))
    }

    /// b ← b − A x.
    fn residual_in_place(&self, b: &mut [f64], x: &[f64], ch: usize) {
        by_channels!(ch, residual_in_place_n(self, b, x))
    }

    /// (b − A x) on the consecutive rows `rows`, into `out`, in the calling
    /// task (the same bits as [`Self::residual`] on those rows).
    fn residual_span(
        &self,
        rows: std::ops::Range<usize>,
        b: &[f64],
        x: &[f64],
        out: &mut [f64],
        ch: usize,
    ) {
        by_channels!(ch, residual_span_n(self, rows, b, x, out))
    }

    /// (b − A z) on the rows `rows`, gathered in their order.
    fn residual_rows(&self, rows: &[u32], b: &[f64], z: &[f64], out: &mut [f64], ch: usize) {
        by_channels!(ch, residual_rows_n(self, rows, b, z, out))
    }

    /// One Gauss–Seidel sweep on A z = r in place over `rows`, forwards or
    /// backwards. A forward sweep followed by a backward one is a symmetric smoother.
    fn gauss_seidel(&self, rows: &[u32], r: &[f64], z: &mut [f64], ch: usize, forward: bool) {
        let n = self.n();
        assert!(ch <= 4 && z.len() >= n * ch && r.len() >= n * ch);
        assert!(rows.iter().all(|&i| (i as usize) < n));
        // SAFETY: `z` is exclusively borrowed and long enough for every row
        // and column index (columns are below n, as `Rows` requires).
        unsafe { self.gauss_seidel_raw(rows, r, z.as_mut_ptr(), ch, forward) }
    }

    /// [`Self::gauss_seidel`] through a raw pointer, so that tasks may sweep
    /// disjoint sets of rows of one vector at once.
    ///
    /// # Safety
    /// `z` must hold `n·ch` values; `rows` must be below `n`, `ch` at most 4,
    /// and no other thread may write an entry this sweep reads or writes, or
    /// read an entry it writes, while it runs.
    unsafe fn gauss_seidel_raw(
        &self,
        rows: &[u32],
        r: &[f64],
        z: *mut f64,
        ch: usize,
        forward: bool,
    ) {
        // SAFETY: the caller's contract, passed on.
        unsafe { by_channels!(ch, gauss_seidel_n(self, rows, r, z, forward)) }
    }

    /// The principal submatrix on `rows` (increasing), renumbered 0..rows.len().
    fn submatrix(&self, rows: &[u32]) -> Result<SymCsr, SolveError> {
        let mut local = crate::heap::filled(self.n(), u32::MAX);
        for (k, &i) in rows.iter().enumerate() {
            local[i as usize] = k as u32;
        }
        // Rows in parallel runs, joined in order: the exact block of a
        // many-seam atlas's band is millions of entries, taken while the
        // rest of the solver's set-up waits.
        let runs: Vec<(Vec<usize>, Vec<u32>, Vec<f64>)> = rows
            .par_chunks(SUBMATRIX_RUN)
            .map(|run| {
                let (mut len, mut col, mut val) = (Vec::with_capacity(run.len()), vec![], vec![]);
                for &i in run {
                    self.for_each(i as usize, |j, v| {
                        let k = local[j];
                        if k != u32::MAX {
                            col.push(k);
                            val.push(v);
                        }
                    });
                    len.push(col.len());
                }
                (len, col, val)
            })
            .collect();
        let entries = runs.iter().map(|r| r.1.len()).sum();
        let mut ptr = Vec::with_capacity(rows.len() + 1);
        ptr.push(0);
        let (mut col, mut val) = (Vec::with_capacity(entries), Vec::with_capacity(entries));
        for (len, c, v) in runs {
            let base = col.len();
            ptr.extend(len.iter().map(|l| base + l));
            col.extend_from_slice(&c);
            val.extend_from_slice(&v);
        }
        SymCsr::from_parts(ptr, col, val)
    }

    /// The whole matrix in compressed rows.
    fn to_csr(&self) -> Result<SymCsr, SolveError> {
        let n = self.n();
        let mut ptr = Vec::with_capacity(n + 1);
        ptr.push(0);
        let mut col = Vec::new();
        let mut val = Vec::new();
        for i in 0..n {
            self.for_each(i, |j, v| {
                col.push(j as u32);
                val.push(v);
            });
            ptr.push(col.len());
        }
        SymCsr::from_parts(ptr, col, val)
    }

    /// The Galerkin product Pᵀ A P, row by row over the coarse unknowns.
    ///
    /// With `lattice`, rows use where P places the coarse unknowns: a lattice row couples
    /// only to the 3×3 lattice nodes around it (a bilinear P widens a stencil
    /// of reach one by at most one coarse step) and to unknowns off the
    /// lattice, so it sums into nine fixed slots and a short list instead of
    /// an accumulator over all coarse unknowns; rows off the lattice (and
    /// every row without `lattice`) sum into a list that is sorted once.
    fn galerkin(&self, p: &Transfer, lattice: bool) -> Result<SymCsr, SolveError> {
        Ok(self.galerkin_with(p, lattice, None)?.0)
    }

    /// [`Self::galerkin`], given which fine rows have the tensor form (for a
    /// matrix with stencil rows it finds them itself), and returning which
    /// coarse rows have it: their next Galerkin rows are in closed form too.
    fn galerkin_with(
        &self,
        p: &Transfer,
        lattice: bool,
        tensor: Option<&TensorRows>,
    ) -> Result<(SymCsr, Option<TensorRows>), SolveError> {
        let (parts, coarse_tensor) = self.galerkin_parts(p, lattice, tensor, false);
        let (ptr, col, val) = join_stored(parts.into_iter().map(|g| (g.lens, g.col, g.val)));
        Ok((SymCsr::from_parts(ptr, col, val)?, coarse_tensor))
    }

    /// [`Self::galerkin_with`] on the lattice, keeping the rows with the
    /// tensor form in closed form (see [`CoarseMatrix`]).
    fn galerkin_closed(
        &self,
        p: &Transfer,
        tensor: Option<&TensorRows>,
    ) -> Result<(CoarseMatrix, Option<TensorRows>), SolveError> {
        let (parts, coarse_tensor) = self.galerkin_parts(p, true, tensor, true);
        let form = coarse_tensor
            .as_ref()
            .map(CoarseMatrix::form)
            .unwrap_or_default();
        let mut closed = Vec::new();
        let mut stored = Vec::with_capacity(parts.len());
        for g in parts {
            closed.push(g.closed);
            stored.push((g.lens, g.col, g.val));
        }
        let (ptr, col, val) = join_stored(stored.into_iter());
        // The first part's rows were reserved for all (see `galerkin_rows`).
        let mut closed = closed.into_iter();
        let mut rows = closed.next().unwrap_or_default();
        for c in closed {
            rows.par_extend(c.into_par_iter());
        }
        // Without tensor rows every row is stored.
        if rows.is_empty() {
            rows = vec![Closed::STORED; p.coarse];
        }
        Ok((
            CoarseMatrix::from_parts(form, rows, ptr, col, val)?,
            coarse_tensor,
        ))
    }

    /// The Galerkin rows in one part per thread, and the coarse tensor rows.
    /// With `closed`, a row with the tensor form whose 3×3 lattice points
    /// are numbered in raster order is kept as its `d` and neighbours
    /// (length 0 in the stored arrays).
    fn galerkin_parts(
        &self,
        p: &Transfer,
        lattice: bool,
        tensor: Option<&TensorRows>,
        closed: bool,
    ) -> (Vec<GalerkinPart>, Option<TensorRows>) {
        let nc = p.coarse;
        // One task per thread: a few large parts are handed back to the
        // system once joined, where many small ones would stay in the heap.
        // A row's sum runs in a fixed order whichever task computes it.
        let tasks = rayon::current_num_threads().clamp(1, nc.max(1));
        let per = nc.div_ceil(tasks);
        let own = match tensor {
            None if lattice => self.tensor_rows(p),
            _ => None,
        };
        let tensor = if lattice {
            tensor.or(own.as_ref())
        } else {
            None
        };
        let parts: Vec<GalerkinPart> = (0..tasks)
            .into_par_iter()
            .map(|b| {
                let rows = (b * per).min(nc)..((b + 1) * per).min(nc);
                // Room for every row in the first part: the others are appended to it.
                let reserve = if b == 0 { nc } else { rows.len() };
                self.galerkin_rows(p, rows, lattice, tensor, closed, reserve)
            })
            .collect();
        let coarse_tensor = tensor.map(|t| TensorRows {
            d: parts.iter().flat_map(|c| c.forms.iter().copied()).collect(),
            off: t.off,
            a: coarsen_1d(t.a),
            b: coarsen_1d(t.b),
        });
        (parts, coarse_tensor)
    }

    /// Rows `rows` of Pᵀ A P (not inlined: a symbol of its own in
    /// profiles), with room for `reserve` rows in the arrays.
    ///
    /// A coarse lattice row whose nine fine rows all have the tensor form
    /// (`tensor`), with one `d`, has it too, and is written in closed form.
    #[inline(never)]
    fn galerkin_rows(
        &self,
        p: &Transfer,
        rows: std::ops::Range<usize>,
        lattice: bool,
        tensor: Option<&TensorRows>,
        closed: bool,
        reserve: usize,
    ) -> GalerkinPart {
        let mut lens = Vec::with_capacity(rows.len());
        let mut forms = Vec::with_capacity(if tensor.is_some() { rows.len() } else { 0 });
        let mut closed_rows = Vec::with_capacity(if closed && tensor.is_some() {
            reserve
        } else {
            0
        });
        // Bilinear coarsening keeps about nine entries a row (closed-form
        // rows none). Reserved memory that is never written is never
        // faulted in either.
        let mut out_col = Vec::with_capacity(reserve * 10);
        let mut out_val = Vec::with_capacity(reserve * 10);
        let mut list: Vec<(u32, f64)> = Vec::new();
        let mut entries: Vec<(usize, f64)> = Vec::new();
        let coarse = tensor.map(|t| (coarsen_1d(t.a), coarsen_1d(t.b), t.off));
        for k in rows {
            let before = out_col.len();
            list.clear();
            let centre = p.placement(k).filter(|_| lattice);
            let (fine, len) = p.fine_of(k);
            // The rows' common d, when all nine have the tensor form (NaN
            // marks the others, and equals nothing).
            let uniform = match (centre, tensor) {
                (Some(_), Some(t)) if len == 9 => {
                    let d = t.d[fine[4].0];
                    fine.iter().all(|&(i, _)| t.d[i] == d).then_some(d)
                }
                _ => None,
            };
            if tensor.is_some() {
                forms.push(uniform.unwrap_or(f64::NAN));
            }
            let mut kept = Closed::STORED;
            match (centre, uniform.zip(coarse)) {
                (Some(c), Some((d, _))) if closed && closed_neighbours(p, c, k, d, &mut kept) => {}
                (Some(c), Some((d, (a, b, off)))) => tensor_row(p, c, d, off, a, b, &mut list),
                (Some(c), None) => {
                    galerkin_lattice_row(self, p, c, &fine[..len], &mut entries, &mut list)
                }
                (None, _) => {
                    for &(i, wi) in &fine[..len] {
                        self.for_each(i, |j, aij| {
                            let wa = wi * aij;
                            p.for_each_parent(j, |l, wj| list.push((l as u32, wa * wj)));
                        });
                    }
                }
            }
            if closed && tensor.is_some() {
                closed_rows.push(kept);
            }
            // Stable, so equal columns are summed in the order they came.
            list.sort_by_key(|e| e.0);
            for &(c, v) in &list {
                if out_col.len() > before && out_col.last() == Some(&c) {
                    *out_val.last_mut().expect("a value per column") += v;
                } else {
                    out_col.push(c);
                    out_val.push(v);
                }
            }
            lens.push(out_col.len() - before);
        }
        GalerkinPart {
            lens,
            col: out_col,
            val: out_val,
            forms,
            closed: closed_rows,
        }
    }
}

/// Joins per-part row lengths and entries into compressed rows. The first
/// part's arrays were reserved for the whole (see `galerkin_rows`), so only
/// the rest is copied, and into pages that no earlier array has touched.
#[allow(clippy::type_complexity)]
fn join_stored(
    parts: impl Iterator<Item = (Vec<usize>, Vec<u32>, Vec<f64>)>,
) -> (Vec<usize>, Vec<u32>, Vec<f64>) {
    let parts: Vec<_> = parts.collect();
    let rows: usize = parts.iter().map(|p| p.0.len()).sum();
    let total: usize = parts.iter().map(|p| p.1.len()).sum();
    let mut parts = parts.into_iter();
    let (lens, mut col, mut val) = parts.next().unwrap_or_default();
    col.reserve_exact(total - col.len());
    val.reserve_exact(total - val.len());
    let mut ptr = Vec::with_capacity(rows + 1);
    ptr.push(0);
    for l in lens {
        ptr.push(ptr.last().copied().unwrap_or(0) + l);
    }
    for (lens, c, v) in parts {
        for l in lens {
            ptr.push(ptr.last().copied().unwrap_or(0) + l);
        }
        // Into the reserved room, by all threads (see `heap::filled`).
        col.par_extend(c.into_par_iter());
        val.par_extend(v.into_par_iter());
    }
    (ptr, col, val)
}

/// One task's Galerkin rows: per row its length in `col`/`val`, and its d
/// where it has the tensor form (`forms`, empty without tensor rows); with
/// closed-form rows asked for, per row its closed form or
/// [`Closed::STORED`].
pub struct GalerkinPart {
    lens: Vec<usize>,
    col: Vec<u32>,
    val: Vec<f64>,
    forms: Vec<f64>,
    closed: Vec<Closed>,
}

/// The closed form of coarse row `k` at lattice point `[x, y]` into `out`,
/// if its 3×3 lattice points are numbered in raster order (then the row's
/// entries in that order are in column order, as [`Rows`] asks).
#[inline]
fn closed_neighbours(p: &Transfer, [x, y]: [u32; 2], k: usize, d: f64, out: &mut Closed) -> bool {
    let mut at = [0u32; 9];
    for dy in 0..3u32 {
        for dx in 0..3u32 {
            let (lx, ly) = ((x + dx).wrapping_sub(1), (y + dy).wrapping_sub(1));
            at[(dy * 3 + dx) as usize] = lattice_index(p, lx, ly);
        }
    }
    if at[4] as usize != k || at.windows(2).any(|w| w[0] >= w[1]) {
        return false;
    }
    *out = Closed {
        d,
        around: [at[0], at[1], at[2], at[3], at[5], at[6], at[7], at[8]],
    };
    true
}

/// The entries of the Galerkin row of the coarse lattice node at `centre`
/// (fine unknowns `fine` with their weights) into `list`, unsorted.
///
/// Its lattice entries fall in the 3×3 coarse points around it (a bilinear
/// P widens a stencil of reach one by at most one coarse step). Each fine
/// lattice neighbour spreads over a 2×2 square of coarse points (weight 0 on
/// the far side of an even coordinate), summed into a 5×5 window without a
/// branch on the parities (which no predictor follows), and each point is
/// looked up once at the end.
#[inline]
fn galerkin_lattice_row<A: Rows + ?Sized>(
    a: &A,
    p: &Transfer,
    [x, y]: [u32; 2],
    fine: &[(usize, f64)],
    entries: &mut Vec<(usize, f64)>,
    list: &mut Vec<(u32, f64)>,
) {
    const W: usize = 5;
    let mut slot = [0.0f64; W * W];
    let mut touched = 0u32;
    for &(i, wi) in fine {
        // Gathered first: the loop below is too large to inline into each
        // of a row's entries.
        entries.clear();
        a.for_each(i, |j, aij| entries.push((j, aij)));
        for &(j, aij) in entries.iter() {
            let wa = wi * aij;
            match p.parent_square(j) {
                Square::Exact(l) => list.push((l, wa)),
                Square::At {
                    x: bx,
                    y: by,
                    wx,
                    wy,
                } if bx + 2 >= x && bx <= x + 1 && by + 2 >= y && by <= y + 1 => {
                    let s = (by + 2 - y) as usize * W + (bx + 2 - x) as usize;
                    slot[s] += wa * (wx[0] * wy[0]);
                    slot[s + 1] += wa * (wx[1] * wy[0]);
                    slot[s + W] += wa * (wx[0] * wy[1]);
                    slot[s + W + 1] += wa * (wx[1] * wy[1]);
                    let (ox, oy) = ((wx[1] != 0.0) as u32, (wy[1] != 0.0) as u32);
                    touched |= (1 | ox << 1 | oy << W | (ox & oy) << (W + 1)) << s;
                }
                // Not expected from bilinear coarsening; stay correct regardless.
                Square::At { .. } => p.for_each_parent(j, |l, wj| list.push((l as u32, wa * wj))),
            }
        }
    }
    for (s, &v) in slot.iter().enumerate() {
        if touched & (1 << s) != 0 {
            let (lx, ly) = (
                (x + (s % W) as u32).wrapping_sub(2),
                (y + (s / W) as u32).wrapping_sub(2),
            );
            list.push((lattice_index(p, lx, ly), v));
        }
    }
}

/// Rows of one level that are, over the 3×3 lattice nodes around them, the
/// stencil d·(a⊗a) + off·(b⊗a + a⊗b): a and b are 1D three-point stencils
/// (centre, side) shared by the level, `off` is the fine lattice's
/// off-diagonal value and d a row's own. The finest lattice's full
/// five-point rows have this form with a = (1, 0) and b = (0, 1); a bilinear
/// Galerkin product keeps it (see `coarsen_1d`), so most of every coarse
/// level can be written in closed form.
#[derive(Clone, Debug, Default)]
pub struct TensorRows {
    /// Per row: its d, NaN where the row does not have the form.
    pub d: Vec<f64>,
    pub off: f64,
    pub a: [f64; 2],
    pub b: [f64; 2],
}

/// hᵀ s h for a 1D three-point stencil s = (centre, side) and the hat
/// h = (½, 1, ½) on the fine points around each coarse one: the same node
/// collects 3/2 of s's centre and 2 of its side, the next node 1/4 and 1.
fn coarsen_1d([c, s]: [f64; 2]) -> [f64; 2] {
    [1.5 * c + 2.0 * s, 0.25 * c + s]
}

/// The Galerkin row of the coarse lattice node at (x, y) in closed form:
/// d·(a⊗a) + off·(b⊗a + a⊗b) with a and b the coarse level's 1D stencils.
#[inline]
fn tensor_row(
    p: &Transfer,
    [x, y]: [u32; 2],
    d: f64,
    off: f64,
    a: [f64; 2],
    b: [f64; 2],
    list: &mut Vec<(u32, f64)>,
) {
    for dy in 0..3u32 {
        for dx in 0..3u32 {
            let (i, j) = ((dx != 1) as usize, (dy != 1) as usize);
            let v = d * (a[i] * a[j]) + off * (b[i] * a[j] + a[i] * b[j]);
            let (lx, ly) = ((x + dx).wrapping_sub(1), (y + dy).wrapping_sub(1));
            list.push((lattice_index(p, lx, ly), v));
        }
    }
}

/// The coarse unknown at a lattice point a fine lattice node interpolates
/// from (on the grid by construction, `Transfer::coarsen`).
#[inline]
fn lattice_index(p: &Transfer, x: u32, y: u32) -> u32 {
    p.coarse_at_point(x, y)
        .expect("a parent on the coarse grid") as u32
}

impl Rows for SymCsr {
    fn n(&self) -> usize {
        self.n
    }

    #[inline]
    fn diagonal(&self, i: usize) -> f64 {
        self.val[self.diag[i]]
    }

    #[inline]
    fn for_each(&self, i: usize, mut f: impl FnMut(usize, f64)) {
        for e in self.ptr[i]..self.ptr[i + 1] {
            f(self.col[e] as usize, self.val[e]);
        }
    }
}

/// Row `i` of A x, summed in the row's column order.
#[inline(always)]
fn row_product<const C: usize>(a: &(impl Rows + ?Sized), i: usize, x: &[f64]) -> [f64; C] {
    let mut s = [0.0f64; C];
    a.for_each(i, |j, v| {
        let xj = &x[j * C..(j + 1) * C];
        for c in 0..C {
            s[c] += v * xj[c];
        }
    });
    s
}

fn apply_n<const C: usize>(a: &(impl Rows + ?Sized), x: &[f64], y: &mut [f64]) {
    y.par_chunks_mut(CHUNK * C).enumerate().for_each(|(b, ys)| {
        for (k, yi) in ys.chunks_exact_mut(C).enumerate() {
            yi.copy_from_slice(&row_product::<C>(a, b * CHUNK + k, x));
        }
    });
}

fn apply_dot_n<const C: usize>(
    a: &(impl Rows + ?Sized),
    x: &[f64],
    y: &mut [f64],
    rows: usize,
) -> ([f64; 4], [f64; 4]) {
    let parts: Vec<([f64; 4], [f64; 4])> = y
        .par_chunks_mut(rows * C)
        .enumerate()
        .map(|(b, ys)| {
            let (mut d, mut m) = ([0.0f64; 4], [0.0f64; 4]);
            for (k, yi) in ys.chunks_exact_mut(C).enumerate() {
                let i = b * rows + k;
                let s = row_product::<C>(a, i, x);
                yi.copy_from_slice(&s);
                for c in 0..C {
                    d[c] += x[i * C + c] * s[c];
                    m[c] = m[c].max(x[i * C + c].abs());
                }
            }
            (d, m)
        })
        .collect();
    let (mut d, mut m) = ([0.0f64; 4], [0.0f64; 4]);
    for (pd, pm) in parts {
        for c in 0..4 {
            d[c] += pd[c];
            m[c] = m[c].max(pm[c]);
        }
    }
    (d, m)
}

fn residual_n<const C: usize>(a: &(impl Rows + ?Sized), b: &[f64], x: &[f64], r: &mut [f64]) {
    r.par_chunks_mut(CHUNK * C)
        .enumerate()
        .for_each(|(blk, rs)| {
            let first = blk * CHUNK;
            residual_span_n::<C>(a, first..first + rs.len() / C, b, x, rs);
        });
}

fn residual_in_place_n<const C: usize>(a: &(impl Rows + ?Sized), b: &mut [f64], x: &[f64]) {
    b.par_chunks_mut(CHUNK * C)
        .enumerate()
        .for_each(|(blk, bs)| {
            for (k, bi) in bs.chunks_exact_mut(C).enumerate() {
                let s = row_product::<C>(a, blk * CHUNK + k, x);
                for c in 0..C {
                    bi[c] -= s[c];
                }
            }
        });
}

fn residual_span_n<const C: usize>(
    a: &(impl Rows + ?Sized),
    rows: std::ops::Range<usize>,
    b: &[f64],
    x: &[f64],
    r: &mut [f64],
) {
    for (i, ri) in rows.zip(r.chunks_exact_mut(C)) {
        let s = row_product::<C>(a, i, x);
        for c in 0..C {
            ri[c] = b[i * C + c] - s[c];
        }
    }
}

fn residual_rows_n<const C: usize>(
    a: &(impl Rows + ?Sized),
    rows: &[u32],
    b: &[f64],
    z: &[f64],
    out: &mut [f64],
) {
    out.par_chunks_mut(CHUNK * C)
        .enumerate()
        .for_each(|(blk, os)| {
            for (k, o) in os.chunks_exact_mut(C).enumerate() {
                let i = rows[blk * CHUNK + k] as usize;
                let mut s: [f64; C] = b[i * C..(i + 1) * C].try_into().expect("C values");
                a.for_each(i, |j, v| {
                    let zj = &z[j * C..(j + 1) * C];
                    for c in 0..C {
                        s[c] -= v * zj[c];
                    }
                });
                o.copy_from_slice(&s);
            }
        });
}

/// # Safety
/// As [`Rows::gauss_seidel_raw`], with `C` channels.
unsafe fn gauss_seidel_n<const C: usize>(
    a: &(impl Rows + ?Sized),
    rows: &[u32],
    r: &[f64],
    z: *mut f64,
    forward: bool,
) {
    // SAFETY: the caller's contract, row by row.
    let sweep = |&i: &u32| unsafe { relax_row::<C>(a, i as usize, r, z) };
    if forward {
        rows.iter().for_each(sweep);
    } else {
        rows.iter().rev().for_each(sweep);
    }
}

/// One Gauss–Seidel update of row `i`, in direct form:
/// z_i = (r_i − Σ_{j≠i} a_ij z_j) / a_ii.
///
/// # Safety
/// As [`Rows::gauss_seidel_raw`] for the one row `i`, with `C` channels.
pub(super) unsafe fn relax_row<const C: usize>(
    a: &(impl Rows + ?Sized),
    i: usize,
    r: &[f64],
    z: *mut f64,
) {
    let mut s: [f64; C] = r[i * C..(i + 1) * C].try_into().expect("C values");
    // The reciprocal does not wait on the sweep, the division would.
    let inv = 1.0 / a.diagonal(i);
    a.for_each(i, |j, v| {
        if j != i {
            for (c, sc) in s.iter_mut().enumerate() {
                // SAFETY: j < n (as `Rows` requires), c < C: in bounds.
                *sc -= v * unsafe { z.add(j * C + c).read() };
            }
        }
    });
    for (c, sc) in s.iter().enumerate() {
        // SAFETY: i < n by the caller's contract.
        unsafe { z.add(i * C + c).write(sc * inv) };
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    /// A 1D Laplacian plus identity on `n` unknowns.
    fn laplacian(n: usize) -> SymCsr {
        let mut ptr = vec![0];
        let mut col = Vec::new();
        let mut val = Vec::new();
        for i in 0..n {
            if i > 0 {
                col.push(i as u32 - 1);
                val.push(-1.0);
            }
            col.push(i as u32);
            val.push(3.0);
            if i + 1 < n {
                col.push(i as u32 + 1);
                val.push(-1.0);
            }
            ptr.push(col.len());
        }
        SymCsr::from_parts(ptr, col, val).unwrap()
    }

    fn dense(a: &SymCsr) -> Vec<Vec<f64>> {
        let mut d = vec![vec![0.0; a.n]; a.n];
        for i in 0..a.n {
            for e in a.ptr[i]..a.ptr[i + 1] {
                d[i][a.col[e] as usize] += a.val[e];
            }
        }
        d
    }

    #[test]
    fn galerkin_matches_dense_triple_product() {
        use crate::seam::multigrid::Node;
        let a = laplacian(7);
        // Linear interpolation from 4 coarse nodes at fine 0, 2, 4, 6.
        let nodes: Vec<Node> = (0..7).map(|x| Node::Lattice(x, 0)).collect();
        let (p, coarse) = Transfer::coarsen(&nodes);
        assert_eq!(coarse.len(), 4);
        let ac = dense(&a.galerkin(&p, false).unwrap());
        let ad = dense(&a);
        let pd = |i: usize, k: usize| {
            let (c, len) = p.coarse_of(i);
            c[..len].iter().find(|e| e.0 == k).map_or(0.0, |e| e.1)
        };
        for k in 0..4 {
            for l in 0..4 {
                let mut s = 0.0;
                for i in 0..7 {
                    for j in 0..7 {
                        s += pd(i, k) * ad[i][j] * pd(j, l);
                    }
                }
                assert!(
                    (s - ac[k][l]).abs() < 1e-12,
                    "({k},{l}): {s} vs {}",
                    ac[k][l]
                );
            }
        }
    }

    #[test]
    fn gauss_seidel_converges_on_a_diagonally_dominant_system() {
        let a = laplacian(50);
        let x: Vec<f64> = (0..100).map(|i| (i as f64 * 0.37).cos()).collect();
        let mut b = vec![0.0; 100];
        a.apply(&x, &mut b, 2);
        let mut z = vec![0.0; 100];
        let rows: Vec<u32> = (0..50).collect();
        for k in 0..60 {
            a.gauss_seidel(&rows, &b, &mut z, 2, k % 2 == 0);
        }
        let worst = z
            .iter()
            .zip(&x)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-10, "{worst}");
    }
}
