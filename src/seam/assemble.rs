//! The erasure energy (SPEC §4) as a sparse system over the band's unknowns.
//!
//! Rows come out in texel order, already sorted, so a 2048² band of two
//! million unknowns assembles with no global sort, in parallel runs of
//! texture rows. A row away from the seams is its lattice stencil (change
//! anchor and gradient links), kept implicit ([`StencilMatrix`]); a row with
//! seam entries is that stencil merged with them, stored in full. Only the
//! seam terms are sorted, after the Gauss points that share the same eight
//! texels (all the points of one cell pair, for both the difference and the
//! C1 term) have been summed into one dense 8×8 block.

use rayon::prelude::*;

use super::grid::TexelGrid;
use super::quadrature::QuadPoint;
use super::sparse::by_channels;
use super::stencil::{StencilMatrix, StencilRows, StoredRows, LEFT, NONE, RIGHT};
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

impl Weights {
    /// A lower bound on the eigenvalues of the system [`assemble`] makes:
    /// every row's diagonal holds its texel's anchor, and every other term
    /// is a square, positive semi-definite.
    pub fn floor(&self) -> f64 {
        self.change.min(self.free_anchor)
    }
}

/// A seam block: up to eight texels and their dense coupling.
struct Block {
    texels: [u32; 8],
    len: usize,
    a: [[f64; 8]; 8],
}

/// Assembles `A x = b` for the texels with `unknown[t] != u32::MAX`
/// (numbered in texel order); the others are held at `held` (the input, or
/// a solution a local re-solve corrects), while the change and gradient
/// terms keep to `input`. `b` is interleaved by channel.
#[allow(clippy::too_many_arguments)]
pub fn assemble(
    grid: &TexelGrid,
    input: &[f32],
    held: &[f32],
    channels: usize,
    classes: &TexelClasses,
    seam: &SeamBlocks,
    unknown: &[u32],
    n: usize,
    w: &Weights,
) -> Result<(StencilMatrix, Vec<f64>), SolveError> {
    let ch = channels;
    let mut rhs = crate::heap::filled(n * ch, 0.0f64);
    let ts = std::time::Instant::now();
    let seam_rows = seam_entries(seam, unknown, ch, &mut rhs)?;
    tracing::debug!(
        elapsed_ms = ts.elapsed().as_millis() as u64,
        points = seam.points,
        entries = seam_rows.len(),
        "seam entries"
    );

    // Unknowns are numbered in texel order, so a run of texture rows holds a
    // run of unknowns, and the runs fill their slices of the stencil arrays
    // in parallel; the few stored rows come back per run, in order.
    let (wd, ht) = (grid.width, grid.height);
    let rows_per_task = (ROWS_PER_TASK / wd.max(1)).max(1);
    let tasks: Vec<std::ops::Range<usize>> = (0..ht)
        .step_by(rows_per_task)
        .map(|y| y * wd..((y + rows_per_task).min(ht)) * wd)
        .collect();
    let counts: Vec<usize> = tasks
        .par_iter()
        .map(|texels| {
            unknown[texels.clone()]
                .iter()
                .filter(|&&u| u != NONE)
                .count()
        })
        .collect();
    let mut stencil = StencilRows {
        diag: crate::heap::filled(n, 0.0),
        up: crate::heap::filled(n, NONE),
        down: crate::heap::filled(n, NONE),
        sides: crate::heap::filled(n, 0),
    };
    let mut jobs = Vec::with_capacity(tasks.len());
    {
        let mut diag = &mut stencil.diag[..];
        let mut up = &mut stencil.up[..];
        let mut down = &mut stencil.down[..];
        let mut sides = &mut stencil.sides[..];
        let mut b = &mut rhs[..];
        for (texels, &count) in tasks.into_iter().zip(&counts) {
            let (d, dr) = std::mem::take(&mut diag).split_at_mut(count);
            let (u, ur) = std::mem::take(&mut up).split_at_mut(count);
            let (o, or) = std::mem::take(&mut down).split_at_mut(count);
            let (s, sr) = std::mem::take(&mut sides).split_at_mut(count);
            let (r, rr) = std::mem::take(&mut b).split_at_mut(count * ch);
            (diag, up, down, sides, b) = (dr, ur, or, sr, rr);
            let out = Out {
                diag: d,
                up: u,
                down: o,
                sides: s,
                rhs: r,
            };
            jobs.push((texels, out));
        }
    }
    let parts: Vec<StoredRows> = jobs
        .into_par_iter()
        .map(|(texels, out)| {
            by_channels!(
                ch,
                lattice_rows(
                    grid,
                    (input, held),
                    classes,
                    unknown,
                    w,
                    &seam_rows,
                    texels,
                    out
                )
            )
        })
        .collect();
    let mut stored = StoredRows {
        ptr: vec![0],
        ..Default::default()
    };
    for part in parts {
        let base = stored.col.len();
        stored.rows.extend(part.rows);
        stored.ptr.extend(part.ptr.iter().skip(1).map(|p| p + base));
        stored.col.extend(part.col);
        stored.val.extend(part.val);
    }
    Ok((StencilMatrix::from_parts(-w.grad, stencil, stored)?, rhs))
}

/// Texels per parallel assembly task (whole texture rows).
const ROWS_PER_TASK: usize = 1 << 16;

/// One run's slices of the stencil arrays and of the right-hand side.
struct Out<'a> {
    diag: &'a mut [f64],
    up: &'a mut [u32],
    down: &'a mut [u32],
    sides: &'a mut [u8],
    rhs: &'a mut [f64],
}

/// The rows of the unknowns among `texels`: lattice stencil (change anchor
/// and gradient links, at most five entries), merged with the seam entries
/// where a row has any (those rows are returned, stored in full).
#[allow(clippy::too_many_arguments)]
fn lattice_rows<const C: usize>(
    grid: &TexelGrid,
    (input, held): (&[f32], &[f32]),
    classes: &TexelClasses,
    unknown: &[u32],
    w: &Weights,
    seam_rows: &[(u32, u32, f64)],
    texels: std::ops::Range<usize>,
    out: Out<'_>,
) -> StoredRows {
    let (wd, ht) = (grid.width, grid.height);
    let movable = |s: usize| classes.inside[s] || classes.free[s];
    let mut stored = StoredRows {
        ptr: vec![0],
        ..Default::default()
    };
    let first = texels.clone().map(|t| unknown[t]).find(|&u| u != NONE);
    let Some(first) = first else {
        return stored;
    };
    let start = seam_rows.partition_point(|e| e.0 < first);
    let mut seam = seam_rows[start..].iter().peekable();
    let mut lattice: Vec<(u32, f64)> = Vec::with_capacity(5);
    let mut k = 0;
    for t in texels {
        let u = unknown[t];
        if u == NONE {
            continue;
        }
        let (x, y) = (t % wd, t / wd);
        let anchor = if classes.free[t] {
            w.free_anchor
        } else {
            w.change
        };
        let mut diag = anchor;
        let rhs = &mut out.rhs[k * C..(k + 1) * C];
        let p0: [f32; C] = input[t * C..(t + 1) * C].try_into().expect("C values");
        let mut r: [f64; C] = p0.map(|v| anchor * f64::from(v));
        // Only a row with seam entries is stored, and needs its entries listed.
        let seam_row = seam.peek().is_some_and(|e| e.0 == u);
        lattice.clear();
        let (mut up, mut down, mut sides) = (NONE, NONE, 0u8);
        // Neighbours in increasing texel order (up, left, right, down), so
        // their unknowns come out sorted; the diagonal goes between left and right.
        let neighbours = [
            (y > 0).then(|| t - wd),
            (x > 0).then(|| t - 1),
            (x + 1 < wd).then(|| t + 1),
            (y + 1 < ht).then(|| t + wd),
        ];
        for (side, s) in neighbours.into_iter().enumerate() {
            if side == 2 && seam_row {
                lattice.push((u, 0.0));
            }
            let Some(s) = s.filter(|&s| movable(s)) else {
                continue;
            };
            // w_grad·((p_t − p_s) − target)², target = p0_t − p0_s between inside texels.
            diag += w.grad;
            let both_inside = classes.inside[t] && classes.inside[s];
            let us = unknown[s];
            let ps: [f32; C] = input[s * C..(s + 1) * C].try_into().expect("C values");
            let hs: [f32; C] = held[s * C..(s + 1) * C].try_into().expect("C values");
            for c in 0..C {
                let (a, b) = (f64::from(p0[c]), f64::from(ps[c]));
                let target = if both_inside { a - b } else { 0.0 };
                let held = if us == NONE { f64::from(hs[c]) } else { 0.0 };
                r[c] += w.grad * (target + held);
            }
            if us != NONE {
                if seam_row {
                    lattice.push((us, -w.grad));
                }
                match side {
                    0 => up = us,
                    1 => sides |= LEFT,
                    2 => sides |= RIGHT,
                    _ => down = us,
                }
            }
        }
        for (b, r) in rhs.iter_mut().zip(&r) {
            *b += r;
        }
        out.diag[k] = diag;
        k += 1;
        if !seam_row {
            let k = k - 1;
            (out.up[k], out.down[k], out.sides[k]) = (up, down, sides);
            continue;
        }
        for e in lattice.iter_mut() {
            if e.0 == u {
                e.1 = diag;
            }
        }
        // Merge with this row's seam entries (sorted by column).
        stored.rows.push(u);
        let mut li = lattice.iter().peekable();
        let mut entry = |c: u32, v: f64| {
            stored.col.push(c);
            stored.val.push(v);
        };
        loop {
            let next_seam = seam.peek().filter(|e| e.0 == u).map(|e| (e.1, e.2));
            match (li.peek(), next_seam) {
                (None, None) => break,
                (Some(&&(lc, lv)), Some((sc, sv))) if lc == sc => {
                    entry(lc, lv + sv);
                    li.next();
                    seam.next();
                }
                (Some(&&(lc, lv)), Some((sc, _))) if lc < sc => {
                    entry(lc, lv);
                    li.next();
                }
                (Some(&&(lc, lv)), None) => {
                    entry(lc, lv);
                    li.next();
                }
                (_, Some((sc, sv))) => {
                    entry(sc, sv);
                    seam.next();
                }
            }
        }
        stored.ptr.push(stored.col.len());
    }
    stored
}

/// The seam terms summed per cell pair: what the system takes from them that
/// does not depend on the band. Every texel a seam term reads lies at a seam,
/// which every band holds wherever it may move (see `erase`), so which taps
/// are unknowns is known before the band is. So is the entries' order: the
/// band numbers its unknowns in texel order, so entries sorted by texel stay
/// sorted by unknown, whatever the band.
pub struct SeamBlocks {
    /// The texels the blocks couple, increasing.
    texels: Vec<u32>,
    /// The blocks' entries as (row, column, value), rows and columns indices
    /// into `texels`, sorted by both, equal ones summed in point order.
    entries: Vec<(u32, u32, f64)>,
    /// Right-hand side terms of the taps held at their input value, per
    /// texel, in the order of the points (and summed in that order).
    held: Vec<(u32, [f64; 4])>,
    points: usize,
}

impl SeamBlocks {
    /// Sums the points' outer products into one dense block per set of
    /// movable texels, the held taps into right-hand side terms, and sorts
    /// the blocks' entries.
    pub fn new(points: &[QuadPoint], movable: &[bool], input: &[f32], ch: usize) -> Self {
        let mut blocks: Vec<Block> = Vec::new();
        let mut held_terms = Vec::new();
        // Keyed by eight texel numbers a hash needs no defence for.
        let mut index: rustc_hash::FxHashMap<[u32; 8], usize> = Default::default();
        for q in points {
            let mut free = [(u32::MAX, 0.0f64); 8];
            let mut nfree = 0;
            let mut offset = [0.0f64; 4];
            let mut held = false;
            for &(t, wt) in &q.taps {
                if wt == 0.0 {
                    continue;
                }
                if !movable[t as usize] {
                    held = true;
                    for (c, o) in offset[..ch].iter_mut().enumerate() {
                        *o -= wt * f64::from(input[t as usize * ch + c]);
                    }
                } else if let Some(slot) = free[..nfree].iter_mut().find(|s| s.0 == t) {
                    slot.1 += wt;
                } else {
                    free[nfree] = (t, wt);
                    nfree += 1;
                }
            }
            if nfree == 0 {
                continue;
            }
            // Near the seams every tap is usually free: no terms then.
            if held {
                for &(t, wt) in &free[..nfree] {
                    let mut b = [0.0f64; 4];
                    for c in 0..ch {
                        b[c] = q.weight * wt * offset[c];
                    }
                    held_terms.push((t, b));
                }
            }
            let key = free.map(|f| f.0);
            // The points of one cell pair come one after another: try the last block first.
            let b = match blocks.last() {
                Some(last) if last.texels == key => blocks.len() - 1,
                _ => *index.entry(key).or_insert_with(|| {
                    blocks.push(Block {
                        texels: key,
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
        drop(index);
        let (texels, entries) = sorted_entries(&blocks);
        SeamBlocks {
            texels,
            entries,
            held: held_terms,
            points: points.len(),
        }
    }
}

/// Rows per parallel task of [`sorted_entries`].
const MERGE_ROWS: usize = 4096;

/// The blocks' texels (increasing) and their entries over those texels'
/// indices, sorted by row and column with duplicates summed.
fn sorted_entries(blocks: &[Block]) -> (Vec<u32>, Vec<(u32, u32, f64)>) {
    let mut texels: Vec<u32> = blocks
        .iter()
        .flat_map(|b| b.texels[..b.len].iter().copied())
        .collect();
    texels.sort_unstable();
    texels.dedup();
    let index = |t: u32| texels.binary_search(&t).expect("a block's texel") as u32;
    let keys: Vec<[u32; 8]> = blocks
        .iter()
        .map(|b| {
            let mut key = [NONE; 8];
            for (k, &t) in b.texels[..b.len].iter().enumerate() {
                key[k] = index(t);
            }
            key
        })
        .collect();
    // Each row lists the blocks it lies in, in block order (a counting
    // sort of (block, place) pairs by row): a row's entries are then its
    // blocks' rows, gathered, sorted by column (stably) and summed in the
    // order the points came, with no list of every product in between, and
    // rows apart from each other in parallel.
    let n = texels.len();
    let mut start = vec![0u32; n + 1];
    for (key, b) in keys.iter().zip(blocks) {
        for &u in &key[..b.len] {
            start[u as usize + 1] += 1;
        }
    }
    for i in 0..n {
        start[i + 1] += start[i];
    }
    let mut member = vec![(0u32, 0u8); start[n] as usize];
    let mut next = start.clone();
    for (i, (key, b)) in keys.iter().zip(blocks).enumerate() {
        for (k, &u) in key[..b.len].iter().enumerate() {
            member[next[u as usize] as usize] = (i as u32, k as u8);
            next[u as usize] += 1;
        }
    }
    drop(next);
    let merge_rows = |rows: std::ops::Range<usize>| {
        let mut out = Vec::new();
        let mut row: Vec<(u32, f64)> = Vec::new();
        for i in rows {
            row.clear();
            for &(bi, k) in &member[start[i] as usize..start[i + 1] as usize] {
                let (key, b) = (&keys[bi as usize], &blocks[bi as usize]);
                let a = &b.a[k as usize];
                row.extend(key[..b.len].iter().zip(a).map(|(&v, &x)| (v, x)));
            }
            row.sort_by_key(|e| e.0);
            for &(c, v) in &row {
                match out.last_mut() {
                    Some((r, m, sum)) if *r == i as u32 && *m == c => *sum += v,
                    _ => out.push((i as u32, c, v)),
                }
            }
        }
        out
    };
    let chunks: Vec<Vec<(u32, u32, f64)>> = (0..n.div_ceil(MERGE_ROWS))
        .into_par_iter()
        .map(|c| merge_rows(c * MERGE_ROWS..((c + 1) * MERGE_ROWS).min(n)))
        .collect();
    let merged = chunks.concat();
    (texels, merged)
}

/// The seam blocks' entries as (row, column, value) over the band's unknowns
/// (`unknown`: per texel), sorted by row and column, and their held terms
/// added to `rhs`.
fn seam_entries(
    seam: &SeamBlocks,
    unknown: &[u32],
    ch: usize,
    rhs: &mut [f64],
) -> Result<Vec<(u32, u32, f64)>, SolveError> {
    let outside = |t: u32| SolveError::Assembly(format!("seam texel {t} lies outside the band"));
    for &(t, b) in &seam.held {
        let u = unknown[t as usize];
        if u == NONE {
            return Err(outside(t));
        }
        for c in 0..ch {
            rhs[u as usize * ch + c] += b[c];
        }
    }
    let mut of = Vec::with_capacity(seam.texels.len());
    for &t in &seam.texels {
        match unknown[t as usize] {
            NONE => return Err(outside(t)),
            u => of.push(u),
        }
    }
    Ok(seam
        .entries
        .par_iter()
        .map(|&(r, c, v)| (of[r as usize], of[c as usize], v))
        .collect())
}
