//! How far the erasure's change reaches: the first band's predictor.
//!
//! Away from the seams the change δ obeys (c − Δ)δ = 0 (see `erase`), so
//! there it is the response of c − Δ to sources on the seam texels. This
//! module estimates that response from the input's jumps alone: each seam
//! texel with half-jump a gets the source a·(1 − r²)/r, the one that makes a
//! straight line of such texels carry a and decay as a·r^d (r the decay per
//! texel), and the responses are summed. Against the largest 1D decay from
//! any seam texel, which is right only beside long seams of even jump, the
//! sum lets short seams, seam ends and jumps that vary along a seam fade as
//! they do in the plane. Measured against the solve on every texel of Fox
//! (2048², local mode): each texel whose change reaches the band's tolerance
//! has an estimate of at least that, and beyond 40 texels from the seams the
//! change stays below 0.84 times the estimate made on the texel lattice
//! itself (median 0.2).
//!
//! It is an estimate, not a bound: the band check after the solve keeps the
//! result exact, and the caller leaves a margin so that it rarely has to.
//!
//! The response is smooth on the scale of the decay length L, so it is found
//! on a lattice coarser by a power of two F with L/F ≥ `MIN_CELLS_PER_DECAY`:
//! there (c·F² − Δ)P = the sources summed per cell, which over-relaxed
//! red–black Gauss–Seidel solves from zero (Fox: 51 sweeps of a 256² lattice,
//! about 15 ms). The texture's edges are mirrors, as the texel lattice has no
//! neighbours beyond them.

/// The coarse lattice resolves the decay length by at least this many cells.
const MIN_CELLS_PER_DECAY: f64 = 1.5;
/// Sweeps stop once no value moves by more than this fraction of the level
/// the caller asks about (the error shrinks by ω − 1 per sweep, so what is
/// left is (ω − 1)/(2 − ω) times the last move: 1.4 on Fox).
const SETTLED: f64 = 1e-3;
const MAX_SWEEPS: usize = 4000;

/// The estimated change, on a lattice coarser than the texels by `factor`.
pub struct FarField {
    factor: usize,
    /// Coarse cells per row and column.
    cols: usize,
    rows: usize,
    values: Vec<f64>,
    /// Where each texel column lies between cell centres (see [`between`]).
    columns: Vec<(u32, u32, f64)>,
}

impl FarField {
    /// The response to `jumps` (texel, largest jump across the seam there,
    /// a texel may repeat) on a `width`×`height` lattice whose change decays
    /// by `ratio` per texel, accurate around `level`.
    pub fn new(width: usize, height: usize, jumps: &[(u32, f64)], ratio: f64, level: f64) -> Self {
        let decay_len = -1.0 / ratio.ln();
        let mut factor = 1;
        while decay_len / (2 * factor) as f64 >= MIN_CELLS_PER_DECAY {
            factor *= 2;
        }
        let (cols, rows) = (width.div_ceil(factor), height.div_ceil(factor));
        // A texel repeats in `jumps` (once for each seam point it serves):
        // its source takes its largest half-jump, once, in the order of first
        // appearance (so the sums' bits are fixed).
        let mut largest = crate::heap::filled(width * height, 0.0f32);
        for &(t, j) in jumps {
            let a = &mut largest[t as usize];
            *a = a.max(0.5 * j as f32);
        }
        let strength = (1.0 - ratio * ratio) / ratio;
        let mut source = vec![0.0; cols * rows];
        for &(t, _) in jumps {
            let a = std::mem::take(&mut largest[t as usize]);
            if a > 0.0 {
                let (x, y) = (t as usize % width, t as usize / width);
                source[(y / factor) * cols + x / factor] += f64::from(a) * strength;
            }
        }
        // (c·F² + 4)·P_i − Σ neighbours P_j = source_i, c = 1/r + r − 2.
        let c = 1.0 / ratio + ratio - 2.0;
        let diag = c * (factor * factor) as f64 + 4.0;
        // Over-relaxed by the optimum for Jacobi's contraction 4/diag: the
        // error then shrinks by ω − 1 per sweep (0.58 at Fox's 2.6 cells per
        // decay length, against 0.93 for plain Gauss–Seidel).
        let jacobi = 4.0 / diag;
        let omega = 2.0 / (1.0 + (1.0 - jacobi * jacobi).sqrt());
        let mut values = vec![0.0; cols * rows];
        let settled = SETTLED * level;
        for _ in 0..MAX_SWEEPS {
            let red = sweep(&mut values, &source, cols, rows, diag, omega, 0);
            let black = sweep(&mut values, &source, cols, rows, diag, omega, 1);
            if red.max(black) <= settled {
                break;
            }
        }
        let columns = (0..width)
            .map(|x| between(centre(x, factor), cols))
            .map(|(i, j, f)| (i as u32, j as u32, f))
            .collect();
        FarField {
            factor,
            cols,
            rows,
            values,
            columns,
        }
    }

    /// The estimate along texel row `y`, interpolated bilinearly between the
    /// cell centres: a function of the texel's column.
    pub fn row(&self, y: usize) -> impl Fn(usize) -> f64 + '_ {
        let (y0, y1, fy) = between(centre(y, self.factor), self.rows);
        let r0 = &self.values[y0 * self.cols..(y0 + 1) * self.cols];
        let r1 = &self.values[y1 * self.cols..(y1 + 1) * self.cols];
        move |x| {
            let (x0, x1, fx) = self.columns[x];
            let (x0, x1) = (x0 as usize, x1 as usize);
            let top = r0[x0] + fx * (r0[x1] - r0[x0]);
            let bottom = r1[x0] + fx * (r1[x1] - r1[x0]);
            top + fy * (bottom - top)
        }
    }
}

/// Texel coordinate `t` in coarse cells (cell k's centre at k).
fn centre(t: usize, factor: usize) -> f64 {
    (t as f64 + 0.5) / factor as f64 - 0.5
}

/// The two cells around coarse coordinate `p` (clamped to 0..n) and the
/// weight of the second.
fn between(p: f64, n: usize) -> (usize, usize, f64) {
    let p = p.clamp(0.0, (n - 1) as f64);
    let i = (p.floor() as usize).min(n - 1);
    let j = (i + 1).min(n - 1);
    (i, j, p - i as f64)
}

/// One over-relaxed Gauss–Seidel half-sweep over the cells of one colour
/// ((x + y) % 2 == `colour`), neighbours beyond the edges mirrored; returns
/// the largest move.
fn sweep(
    values: &mut [f64],
    source: &[f64],
    cols: usize,
    rows: usize,
    diag: f64,
    omega: f64,
    colour: usize,
) -> f64 {
    let mut moved = 0.0f64;
    for y in 0..rows {
        let up = if y > 0 { y - 1 } else { y };
        let down = if y + 1 < rows { y + 1 } else { y };
        for x in ((y + colour) % 2..cols).step_by(2) {
            let left = if x > 0 { x - 1 } else { x };
            let right = if x + 1 < cols { x + 1 } else { x };
            let i = y * cols + x;
            let around = values[up * cols + x]
                + values[down * cols + x]
                + values[y * cols + left]
                + values[y * cols + right];
            let step = omega * ((source[i] + around) / diag - values[i]);
            moved = moved.max(step.abs());
            values[i] += step;
        }
    }
    moved
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A straight seam of even jump across a wide lattice: far from its ends
    /// the estimate decays as the 1D solution a·r^d does.
    #[test]
    fn a_long_straight_seam_decays_as_in_one_dimension() {
        let (w, h) = (512, 512);
        let ratio: f64 = 0.9;
        let jump = 2.0;
        let jumps: Vec<(u32, f64)> = (0..w).map(|x| ((256 * w + x) as u32, jump)).collect();
        let field = FarField::new(w, h, &jumps, ratio, 1e-6);
        for d in [0usize, 10, 40, 80] {
            let want = 0.5 * jump * ratio.powi(d as i32);
            let got = field.row(256 + d)(w / 2);
            // The coarse cell (4 texels here) moves the seam by up to 2
            // texels: a factor r^±2 ≈ 0.81..1.23, and a little for the lattice.
            assert!(
                (0.75..1.3).contains(&(got / want)),
                "d={d}: {got} vs {want}"
            );
        }
    }

    /// One seam texel alone: its estimate falls faster than the 1D decay.
    #[test]
    fn a_point_fades_faster_than_a_line() {
        let (w, h) = (256, 256);
        let ratio: f64 = 0.9;
        let field = FarField::new(w, h, &[((128 * w + 128) as u32, 2.0)], ratio, 1e-6);
        let got = field.row(128 + 40)(128);
        assert!(got > 0.0);
        assert!(got < 0.1 * ratio.powi(40), "{got}");
    }
}
