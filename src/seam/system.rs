//! Assembly of sparse symmetric positive-definite systems and their solve.
//!
//! Every energy here is a sum of weighted squares of linear functionals of the
//! texels, so the system is assembled as outer products of "tap" rows; only
//! the lower triangle is stored, and faer's supernodal Cholesky (with its
//! default AMD fill-reducing ordering) factors it once for all channels.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, LltRef, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::{SparseColMat, Triplet};
use faer::{Conj, Mat, MatMut, Par, Side};

use super::grid::Tap;

#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    #[error("sparse matrix assembly failed: {0}")]
    Assembly(String),
    #[error("the system is not positive definite ({0})")]
    NotPositiveDefinite(String),
    #[error("the iterative solve did not converge in {0} iterations")]
    NotConverged(usize),
}

/// A system `A x = b` over `n` unknowns and `channels` right-hand sides,
/// where texels map to unknowns through `unknown` (`u32::MAX`: fixed).
pub struct SpdSystem<'a> {
    unknown: &'a [u32],
    n: usize,
    channels: usize,
    /// The lower triangle by row: `(column, value)` with column ≤ row, each
    /// column once. A tap row's outer product repeats the entries of its
    /// neighbours' (the seam-aware system's 156 k points on Fox push 5 M
    /// products into 58 k entries): summed as they come, in rows a few
    /// dozen long, they never become the list of millions that sorting
    /// into columns took longer than factoring.
    lower: Vec<Vec<(u32, f64)>>,
    rhs: Vec<f64>,
}

impl<'a> SpdSystem<'a> {
    pub fn new(unknown: &'a [u32], n: usize, channels: usize) -> Self {
        SpdSystem {
            unknown,
            n,
            channels,
            lower: vec![Vec::new(); n],
            rhs: vec![0.0; n * channels],
        }
    }

    pub fn unknowns(&self) -> usize {
        self.n
    }

    #[inline]
    pub fn unknown_of(&self, texel: u32) -> Option<u32> {
        let u = self.unknown[texel as usize];
        (u != u32::MAX).then_some(u)
    }

    /// Adds `weight · (Σ taps·p − target)²` for every channel, where texels
    /// that are not unknowns are held at `fixed` (interleaved by channel).
    /// `target` gives one value per channel; at most 16 distinct unknowns.
    pub fn add_square(&mut self, weight: f64, taps: &[Tap], target: &[f64], fixed: &[f32]) {
        let ch = self.channels;
        let mut free: [(u32, f64); 16] = [(0, 0.0); 16];
        let mut nfree = 0;
        let mut offset = [0.0f64; 4];
        offset[..ch].copy_from_slice(&target[..ch]);
        for &(t, w) in taps {
            if w == 0.0 {
                continue;
            }
            match self.unknown_of(t) {
                Some(u) => {
                    if let Some(slot) = free[..nfree].iter_mut().find(|s| s.0 == u) {
                        slot.1 += w;
                    } else {
                        free[nfree] = (u, w);
                        nfree += 1;
                    }
                }
                None => {
                    for (c, o) in offset[..ch].iter_mut().enumerate() {
                        *o -= w * f64::from(fixed[t as usize * ch + c]);
                    }
                }
            }
        }
        for k in 0..nfree {
            let (uk, wk) = free[k];
            for &(ul, wl) in &free[..=k] {
                let (r, c) = if uk >= ul { (uk, ul) } else { (ul, uk) };
                self.add_entry(r, c, weight * wk * wl);
            }
            for (c, o) in offset[..ch].iter().enumerate() {
                self.rhs[uk as usize * ch + c] += weight * wk * o;
            }
        }
    }

    /// Adds `weight · (p_t − target)²` for one texel (a diagonal term).
    pub fn add_anchor(&mut self, weight: f64, texel: u32, target: &[f64]) {
        if let Some(u) = self.unknown_of(texel) {
            self.add_entry(u, u, weight);
            let ch = self.channels;
            let rhs = &mut self.rhs[u as usize * ch..(u as usize + 1) * ch];
            for (b, t) in rhs.iter_mut().zip(target) {
                *b += weight * t;
            }
        }
    }

    /// `A[r][c] += v`, for c ≤ r.
    #[inline]
    fn add_entry(&mut self, r: u32, c: u32, v: f64) {
        let row = &mut self.lower[r as usize];
        match row.iter_mut().find(|e| e.0 == c) {
            Some(e) => e.1 += v,
            None => row.push((c, v)),
        }
    }

    /// Factors once and solves for all channels; returns `x` interleaved by channel.
    pub fn solve(self) -> Result<Vec<f64>, SolveError> {
        let (n, ch) = (self.n, self.channels);
        if n == 0 {
            return Ok(Vec::new());
        }
        let t = std::time::Instant::now();
        let triplets: Vec<Triplet<u32, u32, f64>> = (self.lower.iter().enumerate())
            .flat_map(|(r, row)| row.iter().map(move |&(c, v)| Triplet::new(r as u32, c, v)))
            .collect();
        drop(self.lower);
        let a = SparseColMat::<u32, f64>::try_new_from_triplets(n, n, &triplets)
            .map_err(|e| SolveError::Assembly(format!("{e:?}")))?;
        drop(triplets);
        let assembled = t.elapsed();
        let llt = Cholesky::new(&a)?;
        let factored = t.elapsed();
        let x = llt.solve_interleaved(&self.rhs, ch);
        tracing::debug!(
            unknowns = n,
            nonzeros = a.compute_nnz(),
            factor_nonzeros = llt.factor.len(),
            assemble_ms = assembled.as_millis() as u64,
            factor_ms = (factored - assembled).as_millis() as u64,
            solve_ms = (t.elapsed() - factored).as_millis() as u64,
            "sparse solve"
        );
        Ok(x)
    }
}

/// A sparse Cholesky factor LLᵀ = PAPᵀ (AMD ordering; supernodal or
/// simplicial, as faer judges from the fill).
pub struct Cholesky {
    symbolic: SymbolicCholesky<u32>,
    factor: Vec<f64>,
}

impl Cholesky {
    /// Factors the lower triangle of `a`.
    pub fn new(a: &SparseColMat<u32, f64>) -> Result<Self, SolveError> {
        let err = |e: &dyn std::fmt::Debug| SolveError::Assembly(format!("{e:?}"));
        let t = std::time::Instant::now();
        // faer's own minimum-degree path first sorts every column by
        // transposing the matrix twice; the matrices here come sorted
        // (compressed rows of a symmetric matrix, or built from triplets), so
        // the ordering is taken straight from them: the same order, about a
        // tenth less of its time.
        let n = a.nrows();
        let (mut order, mut inverse) = (vec![0u32; n], vec![0u32; n]);
        let mut mem = MemBuffer::try_new(amd::order_scratch::<u32>(n, a.compute_nnz()))
            .map_err(|e| err(&e))?;
        amd::order(
            &mut order,
            &mut inverse,
            a.symbolic(),
            amd::Control::default(),
            MemStack::new(&mut mem),
        )
        .map_err(|e| err(&e))?;
        drop(mem);
        let symbolic = factorize_symbolic_cholesky(
            a.symbolic(),
            Side::Lower,
            SymmetricOrdering::Custom(PermRef::new_checked(&order, &inverse, n)),
            Default::default(),
        )
        .map_err(|e| err(&e))?;
        let symbolic_ms = t.elapsed().as_millis() as u64;
        let mut factor = vec![0.0; symbolic.len_val()];
        let par = Par::rayon(0);
        let mut mem = MemBuffer::try_new(
            symbolic.factorize_numeric_llt_scratch::<f64>(par, Default::default()),
        )
        .map_err(|e| err(&e))?;
        symbolic
            .factorize_numeric_llt(
                &mut factor,
                a.as_ref(),
                Side::Lower,
                Default::default(),
                par,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .map_err(|e| SolveError::NotPositiveDefinite(format!("{e:?}")))?;
        tracing::trace!(
            rows = a.nrows(),
            nonzeros = a.compute_nnz(),
            factor_nonzeros = factor.len(),
            supernodal = matches!(
                symbolic.raw(),
                faer::sparse::linalg::cholesky::SymbolicCholeskyRaw::Supernodal(_)
            ),
            symbolic_ms,
            numeric_ms = t.elapsed().as_millis() as u64 - symbolic_ms,
            "factored"
        );
        Ok(Cholesky { symbolic, factor })
    }

    /// A⁻¹·b for `ch` right-hand sides interleaved in `b`, interleaved alike.
    pub fn solve_interleaved(&self, b: &[f64], ch: usize) -> Vec<f64> {
        let n = b.len() / ch.max(1);
        let mut m = Mat::<f64>::from_fn(n, ch, |i, c| b[i * ch + c]);
        self.solve_in_place(m.as_mut());
        let mut x = vec![0.0; n * ch];
        for i in 0..n {
            for c in 0..ch {
                x[i * ch + c] = m[(i, c)];
            }
        }
        x
    }

    /// Overwrites `rhs` (one column per channel) with A⁻¹·rhs.
    fn solve_in_place(&self, rhs: MatMut<'_, f64>) {
        // Sequential: with a handful of right-hand sides the triangular solves
        // are memory-bound, and forking per supernode costs more than it saves.
        let mut mem = MemBuffer::new(
            self.symbolic
                .solve_in_place_scratch::<f64>(rhs.ncols(), Par::Seq),
        );
        LltRef::new(&self.symbolic, &self.factor).solve_in_place_with_conj(
            Conj::No,
            rhs,
            Par::Seq,
            MemStack::new(&mut mem),
        );
    }
}
