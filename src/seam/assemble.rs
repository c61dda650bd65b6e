//! The erasure energy (SPEC §4) as a sparse system over the band's unknowns.
//!
//! Rows come out in texel order, already sorted, so a 2048² band of two
//! million unknowns assembles with no global sort, in parallel runs of
//! texture rows: each row is its lattice stencil (change anchor and gradient
//! links, at most five entries) merged with its seam entries. Only the seam
//! terms are sorted, after the Gauss points that share the same eight texels
//! (all the points of one cell pair, for both the difference and the C1
//! term) have been summed into one dense 8×8 block.

use std::collections::HashMap;

use rayon::prelude::*;

use super::grid::TexelGrid;
use super::quadrature::QuadPoint;
use super::sparse::SymCsr;
use super::system::SolveError;
use super::texels::TexelClasses;

/// What the energy weighs, per term.
pub struct Weights {
    /// E_change per texel: w_change / |T|.
    pub change: f64,
    /// Free texels are outside T; a vanishing anchor keeps a free cluster with
    /// no path to an inside texel from leaving the system singular.
    pub free_anchor: f64,
    pub grad: f64,
}

/// A seam block: up to eight unknowns and their dense coupling.
struct Block {
    unknowns: [u32; 8],
    len: usize,
    a: [[f64; 8]; 8],
}

/// Assembles `A x = b` for the texels with `unknown[t] != u32::MAX`
/// (numbered in texel order); the others are held at `input`.
/// `b` is interleaved by channel.
#[allow(clippy::too_many_arguments)]
pub fn assemble(
    grid: &TexelGrid,
    input: &[f32],
    channels: usize,
    classes: &TexelClasses,
    points: &[QuadPoint],
    unknown: &[u32],
    n: usize,
    w: &Weights,
) -> Result<(SymCsr, Vec<f64>), SolveError> {
    let ch = channels;
    let mut rhs = vec![0.0f64; n * ch];
    let ts = std::time::Instant::now();
    let seam_rows = seam_entries(points, unknown, input, ch, n, &mut rhs);
    tracing::debug!(
        elapsed_ms = ts.elapsed().as_millis() as u64,
        points = points.len(),
        entries = seam_rows.len(),
        "seam entries"
    );

    // Unknowns are numbered in texel order, so a run of texture rows holds a
    // run of unknowns. The runs are assembled in parallel twice: once to
    // count each row's entries, then straight into their slices of the
    // arrays (no part is copied, so the peak holds the matrix once).
    let (wd, ht) = (grid.width, grid.height);
    let rows_per_task = (ROWS_PER_TASK / wd.max(1)).max(1);
    let tasks: Vec<std::ops::Range<usize>> = (0..ht)
        .step_by(rows_per_task)
        .map(|y| y * wd..((y + rows_per_task).min(ht)) * wd)
        .collect();
    let rows = |texels: std::ops::Range<usize>, sink: &mut dyn Sink| {
        lattice_rows(
            grid, input, ch, classes, unknown, w, &seam_rows, texels, sink,
        )
    };
    let lens: Vec<Vec<usize>> = tasks
        .par_iter()
        .map(|texels| {
            let mut count = Count::default();
            rows(texels.clone(), &mut count);
            count.lens
        })
        .collect();
    let mut ptr = Vec::with_capacity(n + 1);
    ptr.push(0);
    for &l in lens.iter().flatten() {
        ptr.push(ptr.last().copied().unwrap_or(0) + l);
    }
    let total = ptr.last().copied().unwrap_or(0);
    let mut col = vec![0u32; total];
    let mut val = vec![0.0f64; total];
    let mut jobs = Vec::with_capacity(tasks.len());
    let (mut col_rest, mut val_rest, mut rhs_rest) = (&mut col[..], &mut val[..], &mut rhs[..]);
    for (texels, lens) in tasks.into_iter().zip(&lens) {
        let entries: usize = lens.iter().sum();
        let (c, cr) = std::mem::take(&mut col_rest).split_at_mut(entries);
        let (v, vr) = std::mem::take(&mut val_rest).split_at_mut(entries);
        let (r, rr) = std::mem::take(&mut rhs_rest).split_at_mut(lens.len() * ch);
        (col_rest, val_rest, rhs_rest) = (cr, vr, rr);
        jobs.push((texels, Fill::new(c, v, r, ch)));
    }
    jobs.into_par_iter()
        .for_each(|(texels, mut fill)| rows(texels, &mut fill));
    Ok((SymCsr::from_parts(ptr, col, val)?, rhs))
}

/// Texels per parallel assembly task (whole texture rows).
const ROWS_PER_TASK: usize = 1 << 16;

/// Where [`lattice_rows`] puts what it assembles.
trait Sink {
    fn entry(&mut self, col: u32, val: f64);
    /// Ends a row, with its right-hand side from the lattice terms.
    fn end_row(&mut self, rhs: &[f64; 4]);
}

/// Counts each row's entries.
#[derive(Default)]
struct Count {
    lens: Vec<usize>,
    current: usize,
}

impl Sink for Count {
    fn entry(&mut self, _: u32, _: f64) {
        self.current += 1;
    }
    fn end_row(&mut self, _: &[f64; 4]) {
        self.lens.push(std::mem::take(&mut self.current));
    }
}

/// Writes the rows of one run into their slices of the matrix and adds
/// their right-hand sides to theirs.
struct Fill<'a> {
    col: &'a mut [u32],
    val: &'a mut [f64],
    rhs: &'a mut [f64],
    ch: usize,
    at: usize,
    row: usize,
}

impl<'a> Fill<'a> {
    fn new(col: &'a mut [u32], val: &'a mut [f64], rhs: &'a mut [f64], ch: usize) -> Self {
        Fill {
            col,
            val,
            rhs,
            ch,
            at: 0,
            row: 0,
        }
    }
}

impl Sink for Fill<'_> {
    fn entry(&mut self, col: u32, val: f64) {
        self.col[self.at] = col;
        self.val[self.at] = val;
        self.at += 1;
    }
    fn end_row(&mut self, rhs: &[f64; 4]) {
        let ch = self.ch;
        for (b, r) in self.rhs[self.row * ch..(self.row + 1) * ch]
            .iter_mut()
            .zip(rhs)
        {
            *b += r;
        }
        self.row += 1;
    }
}

/// The rows of the unknowns among `texels`: lattice stencil (change anchor
/// and gradient links, at most five entries) merged with the seam entries.
#[allow(clippy::too_many_arguments)]
fn lattice_rows(
    grid: &TexelGrid,
    input: &[f32],
    ch: usize,
    classes: &TexelClasses,
    unknown: &[u32],
    w: &Weights,
    seam_rows: &[(u32, u32, f64)],
    texels: std::ops::Range<usize>,
    out: &mut dyn Sink,
) {
    let (wd, ht) = (grid.width, grid.height);
    let movable = |s: usize| classes.inside[s] || classes.free[s];
    let first = texels.clone().map(|t| unknown[t]).find(|&u| u != u32::MAX);
    let Some(first) = first else {
        return;
    };
    let start = seam_rows.partition_point(|e| e.0 < first);
    let mut seam = seam_rows[start..].iter().peekable();
    let mut lattice: Vec<(u32, f64)> = Vec::with_capacity(5);
    for t in texels {
        let u = unknown[t];
        if u == u32::MAX {
            continue;
        }
        let (x, y) = (t % wd, t / wd);
        let anchor = if classes.free[t] {
            w.free_anchor
        } else {
            w.change
        };
        let mut diag = anchor;
        let mut rhs = [0.0f64; 4];
        for (c, r) in rhs[..ch].iter_mut().enumerate() {
            *r += anchor * f64::from(input[t * ch + c]);
        }
        lattice.clear();
        // Neighbours in increasing texel order (up, left, right, down), so
        // their unknowns come out sorted; the diagonal goes between left and right.
        let neighbours = [
            (y > 0).then(|| t - wd),
            (x > 0).then(|| t - 1),
            (x + 1 < wd).then(|| t + 1),
            (y + 1 < ht).then(|| t + wd),
        ];
        for (k, s) in neighbours.into_iter().enumerate() {
            if k == 2 {
                lattice.push((u, 0.0));
            }
            let Some(s) = s.filter(|&s| movable(s)) else {
                continue;
            };
            // w_grad·((p_t − p_s) − target)², target = p0_t − p0_s between inside texels.
            diag += w.grad;
            let both_inside = classes.inside[t] && classes.inside[s];
            for (c, r) in rhs[..ch].iter_mut().enumerate() {
                let (a, b) = (f64::from(input[t * ch + c]), f64::from(input[s * ch + c]));
                let target = if both_inside { a - b } else { 0.0 };
                let held = if unknown[s] == u32::MAX { b } else { 0.0 };
                *r += w.grad * (target + held);
            }
            if unknown[s] != u32::MAX {
                lattice.push((unknown[s], -w.grad));
            }
        }
        for e in lattice.iter_mut() {
            if e.0 == u {
                e.1 = diag;
            }
        }
        // Merge with this row's seam entries (sorted by column).
        let mut li = lattice.iter().peekable();
        loop {
            let next_seam = seam.peek().filter(|e| e.0 == u).map(|e| (e.1, e.2));
            match (li.peek(), next_seam) {
                (None, None) => break,
                (Some(&&(lc, lv)), Some((sc, sv))) if lc == sc => {
                    out.entry(lc, lv + sv);
                    li.next();
                    seam.next();
                }
                (Some(&&(lc, lv)), Some((sc, _))) if lc < sc => {
                    out.entry(lc, lv);
                    li.next();
                }
                (Some(&&(lc, lv)), None) => {
                    out.entry(lc, lv);
                    li.next();
                }
                (_, Some((sc, sv))) => {
                    out.entry(sc, sv);
                    seam.next();
                }
            }
        }
        out.end_row(&rhs);
    }
}

/// The seam and C1 terms as sorted (row, col, value) entries of both
/// triangles; their right-hand side (from texels held fixed) goes into `rhs`.
fn seam_entries(
    points: &[QuadPoint],
    unknown: &[u32],
    input: &[f32],
    ch: usize,
    n: usize,
    rhs: &mut [f64],
) -> Vec<(u32, u32, f64)> {
    let mut blocks: Vec<Block> = Vec::new();
    let mut index: HashMap<[u32; 8], usize> = HashMap::new();
    for q in points {
        let mut free = [(u32::MAX, 0.0f64); 8];
        let mut nfree = 0;
        let mut offset = [0.0f64; 4];
        for &(t, wt) in &q.taps {
            if wt == 0.0 {
                continue;
            }
            let u = unknown[t as usize];
            if u == u32::MAX {
                for (c, o) in offset[..ch].iter_mut().enumerate() {
                    *o -= wt * f64::from(input[t as usize * ch + c]);
                }
            } else if let Some(slot) = free[..nfree].iter_mut().find(|s| s.0 == u) {
                slot.1 += wt;
            } else {
                free[nfree] = (u, wt);
                nfree += 1;
            }
        }
        if nfree == 0 {
            continue;
        }
        for &(u, wu) in &free[..nfree] {
            for c in 0..ch {
                rhs[u as usize * ch + c] += q.weight * wu * offset[c];
            }
        }
        let key = free.map(|f| f.0);
        // The points of one cell pair come one after another: try the last block first.
        let b = match blocks.last() {
            Some(last) if last.unknowns == key => blocks.len() - 1,
            _ => *index.entry(key).or_insert_with(|| {
                blocks.push(Block {
                    unknowns: key,
                    len: nfree,
                    a: [[0.0; 8]; 8],
                });
                blocks.len() - 1
            }),
        };
        let a = &mut blocks[b].a;
        for k in 0..nfree {
            for l in 0..nfree {
                a[k][l] += q.weight * free[k].1 * free[l].1;
            }
        }
    }
    // A counting sort by row straight from the blocks, stable (each short
    // row is then sorted by column, stably), so equal entries are summed in
    // the order the points came.
    let mut start = vec![0u32; n + 1];
    for b in &blocks {
        for &u in &b.unknowns[..b.len] {
            start[u as usize + 1] += b.len as u32;
        }
    }
    for i in 0..n {
        start[i + 1] += start[i];
    }
    let mut by_row = vec![(0u32, 0.0f64); start[n] as usize];
    let mut next = start.clone();
    for b in &blocks {
        for (k, &u) in b.unknowns[..b.len].iter().enumerate() {
            let at = &mut next[u as usize];
            for (l, &v) in b.unknowns[..b.len].iter().enumerate() {
                by_row[*at as usize] = (v, b.a[k][l]);
                *at += 1;
            }
        }
    }
    drop((next, blocks));
    let mut merged: Vec<(u32, u32, f64)> = Vec::with_capacity(by_row.len() / 2);
    for i in 0..n {
        let row = &mut by_row[start[i] as usize..start[i + 1] as usize];
        row.sort_by_key(|e| e.0);
        for &(c, v) in row.iter() {
            match merged.last_mut() {
                Some(m) if m.0 == i as u32 && m.1 == c => m.2 += v,
                _ => merged.push((i as u32, c, v)),
            }
        }
    }
    merged
}
