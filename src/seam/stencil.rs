//! The band's matrix, with most of its rows left implicit.
//!
//! Away from the seams a row of the erasure system is the five-point stencil
//! of the gradient term plus the change anchor: the same off-diagonal value
//! (−w_grad) to each neighbour in the band, and a diagonal. Unknowns are
//! numbered in texel order, so the left and right neighbours are the previous
//! and next unknowns; such a row needs its diagonal, the unknowns above and
//! below, and two bits (21 bytes with its place among the stored rows, where
//! compressed rows take about 75). Rows that carry seam terms, a few percent,
//! are stored in compressed rows.
//! Both kinds list their entries in column order, so every kernel of
//! [`Rows`] gives the same bits as on the whole matrix in compressed rows.

use rayon::prelude::*;

use super::sparse::{by_channels, relax_row, Rows, SymCsr, TensorRows};
use super::system::SolveError;
use super::transfer::Transfer;

/// No neighbour / a stencil row (not stored).
pub const NONE: u32 = u32::MAX;
/// `sides` bits: row i−1, row i+1 is a neighbour.
pub const LEFT: u8 = 1;
pub const RIGHT: u8 = 2;

#[derive(Clone, Debug, Default)]
pub struct StencilMatrix {
    n: usize,
    /// The off-diagonal value of every stencil row.
    off: f64,
    diag: Vec<f64>,
    up: Vec<u32>,
    down: Vec<u32>,
    sides: Vec<u8>,
    /// A row's index among the stored rows, or [`NONE`].
    stored: Vec<u32>,
    ptr: Vec<usize>,
    col: Vec<u32>,
    val: Vec<f64>,
}

/// The stencil half of a [`StencilMatrix`]: one entry per row.
#[derive(Default)]
pub struct StencilRows {
    pub diag: Vec<f64>,
    pub up: Vec<u32>,
    pub down: Vec<u32>,
    pub sides: Vec<u8>,
}

/// The stored half: the rows (increasing) and their entries, sorted by column.
#[derive(Default)]
pub struct StoredRows {
    pub rows: Vec<u32>,
    pub ptr: Vec<usize>,
    pub col: Vec<u32>,
    pub val: Vec<f64>,
}

impl StencilMatrix {
    /// Checks that the parts describe a matrix whose rows are sorted by
    /// column, hold a positive diagonal and stay in range.
    pub fn from_parts(off: f64, s: StencilRows, mut g: StoredRows) -> Result<Self, SolveError> {
        let n = s.diag.len();
        if g.ptr.is_empty() {
            g.ptr.push(0);
        }
        let bad = |msg: String| Err(SolveError::Assembly(msg));
        if s.up.len() != n || s.down.len() != n || s.sides.len() != n {
            return bad(format!("stencil arrays of unequal length for {n} rows"));
        }
        if g.ptr.len() != g.rows.len() + 1 || g.ptr.last() != Some(&g.col.len()) {
            return bad("stored rows and their pointers disagree".into());
        }
        let mut stored = crate::heap::filled(n, NONE);
        let mut last = None;
        for (k, &i) in g.rows.iter().enumerate() {
            if i as usize >= n || last.is_some_and(|l| l >= i) {
                return bad(format!("stored row {i} out of order or range"));
            }
            last = Some(i);
            stored[i as usize] = k as u32;
            let cols = &g.col[g.ptr[k]..g.ptr[k + 1]];
            if cols.windows(2).any(|w| w[0] >= w[1]) || cols.iter().any(|&c| c as usize >= n) {
                return bad(format!("row {i}: columns unsorted or out of range"));
            }
        }
        // In parallel, reporting the first bad row whatever the thread count.
        let first_bad = stored.par_iter().enumerate().find_map_first(|(i, &k)| {
            if k != NONE {
                return None;
            }
            if s.diag[i].is_nan() || s.diag[i] <= 0.0 {
                return Some(SolveError::NotPositiveDefinite(format!(
                    "row {i} has no positive diagonal"
                )));
            }
            let (up, down, sides) = (s.up[i], s.down[i], s.sides[i]);
            let left_ok = sides & LEFT == 0 || i > 0;
            let right_ok = sides & RIGHT == 0 || i + 1 < n;
            // Column order: up < left (i − 1) < i < right (i + 1) < down.
            let lowest_side = if sides & LEFT != 0 {
                i.saturating_sub(1)
            } else {
                i
            };
            let highest_side = if sides & RIGHT != 0 { i + 1 } else { i };
            let up_ok = up == NONE || (up as usize) < lowest_side;
            let down_ok = down == NONE || (down as usize > highest_side && (down as usize) < n);
            (!(left_ok && right_ok && up_ok && down_ok))
                .then(|| SolveError::Assembly(format!("stencil row {i} out of order or range")))
        });
        if let Some(e) = first_bad {
            return Err(e);
        }
        // Stored rows keep their own diagonal.
        let mut diag = s.diag;
        for (k, &i) in g.rows.iter().enumerate() {
            let cols = &g.col[g.ptr[k]..g.ptr[k + 1]];
            match cols.binary_search(&i) {
                Ok(e) if g.val[g.ptr[k] + e] > 0.0 => diag[i as usize] = g.val[g.ptr[k] + e],
                _ => {
                    return Err(SolveError::NotPositiveDefinite(format!(
                        "row {i} has no positive diagonal"
                    )))
                }
            }
        }
        Ok(StencilMatrix {
            n,
            off,
            diag,
            up: s.up,
            down: s.down,
            sides: s.sides,
            stored,
            ptr: g.ptr,
            col: g.col,
            val: g.val,
        })
    }

    /// Splits a matrix into stencil rows (entries `off` at i − 1, i + 1 and
    /// at most one column below and one above those) and stored rows.
    pub fn from_csr(a: &SymCsr, off: f64) -> Result<Self, SolveError> {
        let n = a.n;
        let mut s = StencilRows {
            diag: vec![0.0; n],
            up: vec![NONE; n],
            down: vec![NONE; n],
            sides: vec![0; n],
        };
        let mut g = StoredRows {
            ptr: vec![0],
            ..Default::default()
        };
        for i in 0..n {
            let mut entries = Vec::new();
            a.for_each(i, |j, v| entries.push((j, v)));
            let (mut up, mut down, mut sides) = (NONE, NONE, 0u8);
            let mut fits = true;
            for &(j, v) in &entries {
                if j == i {
                    s.diag[i] = v;
                    continue;
                }
                fits &= v == off;
                if j + 1 == i {
                    sides |= LEFT;
                } else if j == i + 1 {
                    sides |= RIGHT;
                } else if j < i && up == NONE {
                    up = j as u32;
                } else if j > i && down == NONE {
                    down = j as u32;
                } else {
                    fits = false;
                }
            }
            if fits {
                (s.up[i], s.down[i], s.sides[i]) = (up, down, sides);
            } else {
                g.rows.push(i as u32);
                for (j, v) in entries {
                    g.col.push(j as u32);
                    g.val.push(v);
                }
                g.ptr.push(g.col.len());
            }
        }
        Self::from_parts(off, s, g)
    }

    /// How many rows are stored in compressed form.
    pub fn stored_rows(&self) -> usize {
        self.ptr.len().saturating_sub(1)
    }
}

impl Rows for StencilMatrix {
    fn n(&self) -> usize {
        self.n
    }

    #[inline]
    fn diagonal(&self, i: usize) -> f64 {
        self.diag[i]
    }

    // Forced in optimised builds: every kernel's row loop calls it, and a
    // call per row costs more than the row.
    #[cfg_attr(not(debug_assertions), inline(always))]
    fn for_each(&self, i: usize, mut f: impl FnMut(usize, f64)) {
        let k = self.stored[i];
        if k != NONE {
            let k = k as usize;
            for e in self.ptr[k]..self.ptr[k + 1] {
                f(self.col[e] as usize, self.val[e]);
            }
            return;
        }
        let (sides, off) = (self.sides[i], self.off);
        if self.up[i] != NONE {
            f(self.up[i] as usize, off);
        }
        if sides & LEFT != 0 {
            f(i - 1, off);
        }
        f(i, self.diag[i]);
        if sides & RIGHT != 0 {
            f(i + 1, off);
        }
        if self.down[i] != NONE {
            f(self.down[i] as usize, off);
        }
    }

    /// Its full five-point rows whose four neighbours are the lattice nodes
    /// beside them, with a = (1, 0) and b = (0, 1).
    fn tensor_rows(&self, p: &Transfer) -> Option<TensorRows> {
        let d = (0..self.n)
            .into_par_iter()
            .with_min_len(1 << 13)
            .map(|i| {
                let full = self.stored[i] == NONE
                    && self.sides[i] == LEFT | RIGHT
                    && self.up[i] != NONE
                    && self.down[i] != NONE;
                // Only a full row has a left neighbour, i − 1.
                if full
                    && p.beside_on_lattice(
                        i,
                        [self.up[i], i as u32 - 1, i as u32 + 1, self.down[i]],
                    )
                {
                    self.diag[i]
                } else {
                    f64::NAN
                }
            })
            .collect();
        Some(TensorRows {
            d,
            off: self.off,
            a: [1.0, 0.0],
            b: [0.0, 1.0],
        })
    }

    unsafe fn gauss_seidel_raw(
        &self,
        rows: &[u32],
        r: &[f64],
        z: *mut f64,
        ch: usize,
        forward: bool,
    ) {
        // SAFETY: the caller's contract, passed on.
        unsafe { by_channels!(ch, self.gauss_seidel_n(rows, r, z, forward)) }
    }
}

impl StencilMatrix {
    /// Gauss–Seidel as [`Rows::gauss_seidel_raw`], with the stencil rows
    /// ordered for speed: a sweep along a texture row waits on the texel it
    /// just updated, so that neighbour's term comes last and the division by
    /// the diagonal, which does not depend on it, is taken off that chain.
    ///
    /// # Safety
    /// As [`Rows::gauss_seidel_raw`], with `C` channels.
    unsafe fn gauss_seidel_n<const C: usize>(
        &self,
        rows: &[u32],
        r: &[f64],
        z: *mut f64,
        forward: bool,
    ) {
        // SAFETY: every index comes from a row or column below n, as
        // `from_parts` checked, and c < C.
        let get =
            |j: usize| -> [f64; C] { std::array::from_fn(|c| unsafe { z.add(j * C + c).read() }) };
        let sweep = |&i: &u32| {
            let i = i as usize;
            if self.stored[i] != NONE {
                // SAFETY: the caller's contract, for this row.
                unsafe { relax_row::<C>(self, i, r, z) };
                return;
            }
            let mut s: [f64; C] = r[i * C..(i + 1) * C].try_into().expect("C values");
            let (sides, off, inv) = (self.sides[i], self.off, 1.0 / self.diag[i]);
            let mut far = |j: usize| {
                let zj = get(j);
                for c in 0..C {
                    s[c] -= off * zj[c];
                }
            };
            if self.up[i] != NONE {
                far(self.up[i] as usize);
            }
            if self.down[i] != NONE {
                far(self.down[i] as usize);
            }
            let (before, after) = (sides & LEFT != 0, sides & RIGHT != 0);
            let (last, other) = if forward {
                (before.then(|| i - 1), after.then(|| i + 1))
            } else {
                (after.then(|| i + 1), before.then(|| i - 1))
            };
            if let Some(j) = other {
                far(j);
            }
            if let Some(j) = last {
                far(j);
            }
            for (c, v) in s.into_iter().enumerate() {
                // SAFETY: i < n by the caller's contract.
                unsafe { z.add(i * C + c).write(v * inv) };
            }
        };
        if forward {
            rows.iter().for_each(sweep);
        } else {
            rows.iter().rev().for_each(sweep);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_rows_read_back_as_the_matrix() {
        // A 4×3 lattice in raster order with one extra unknown tied to two
        // lattice nodes: their rows (and its own) must be stored.
        let (w, h) = (4usize, 3usize);
        let n = w * h + 1;
        let mut rows = vec![std::collections::BTreeMap::<usize, f64>::new(); n];
        let mut link = |a: usize, b: usize, wt: f64| {
            *rows[a].entry(a).or_default() += wt;
            *rows[b].entry(b).or_default() += wt;
            *rows[a].entry(b).or_default() -= wt;
            *rows[b].entry(a).or_default() -= wt;
        };
        for i in 0..w * h {
            if i % w + 1 < w {
                link(i, i + 1, 1.0);
            }
            if i + w < w * h {
                link(i, i + w, 1.0);
            }
        }
        link(12, 1, 5.0);
        link(12, 6, 1.0);
        let (mut ptr, mut col, mut val) = (vec![0], Vec::new(), Vec::new());
        for (i, row) in rows.iter().enumerate() {
            for (&j, &v) in row {
                col.push(j as u32);
                val.push(v + if i == j { 0.5 } else { 0.0 });
            }
            ptr.push(col.len());
        }
        let a = SymCsr::from_parts(ptr, col, val).unwrap();
        let s = StencilMatrix::from_csr(&a, -1.0).unwrap();
        // Row 1 has a −5 entry; row 6 has a second entry above it (12 and 10);
        // row 12 couples far away.
        assert_eq!(s.stored_rows(), 3);
        for i in 0..n {
            let (mut x, mut y) = (Vec::new(), Vec::new());
            a.for_each(i, |j, v| x.push((j, v)));
            s.for_each(i, |j, v| y.push((j, v)));
            assert_eq!(x, y, "row {i}");
            assert_eq!(a.diagonal(i), s.diagonal(i));
        }
        let back = s.to_csr().unwrap();
        assert_eq!((back.ptr, back.col, back.val), (a.ptr, a.col, a.val));
    }

    #[test]
    fn malformed_parts_are_refused() {
        let s = StencilRows {
            diag: vec![1.0, 1.0],
            up: vec![NONE, 0],
            down: vec![NONE, NONE],
            sides: vec![0, LEFT],
        };
        // Row 1's "up" neighbour 0 is also its left one.
        assert!(StencilMatrix::from_parts(-1.0, s, StoredRows::default()).is_err());
    }
}
