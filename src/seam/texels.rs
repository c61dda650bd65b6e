//! Which texels the erasure may change, and how (SPEC §4).
//!
//! * inside: the centre lies in (or on the edge of) a UV triangle;
//! * seam texels: corners of the cells that seam or silhouette half-edges
//!   cross (they carry the seam and C1 terms);
//! * free: seam texels that are not inside (gutter texels whose only job is
//!   to make the bilinear samples at the seams agree).

use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;

use super::grid::TexelGrid;
use super::quadrature::{for_each_cell, Segment};
use crate::model::{SeamSet, UvTriangle};

#[derive(Clone, Debug)]
pub struct TexelClasses {
    pub inside: Vec<bool>,
    pub seam: Vec<bool>,
    pub free: Vec<bool>,
}

impl TexelClasses {
    pub fn new(grid: &TexelGrid, triangles: &[UvTriangle], seams: &SeamSet) -> Self {
        Self::with_inside(grid, inside_mask(grid, triangles), seams)
    }

    /// The classes with the inside texels already known (a level's
    /// [`Charts`](super::charts::Charts) mark the same texels: every solve
    /// of the level shares them instead of rasterising its triangles again).
    pub fn with_inside(grid: &TexelGrid, inside: Vec<bool>, seams: &SeamSet) -> Self {
        let mut seam = vec![false; grid.len()];
        let mut mark = |seg: Segment| {
            for_each_cell(seg, |c| {
                for i in grid.cell_corners(c[0], c[1]) {
                    seam[i as usize] = true;
                }
            })
        };
        for s in &seams.seams {
            mark(Segment::from_uv(grid, s.a));
            mark(Segment::from_uv(grid, s.b));
        }
        for s in &seams.silhouettes {
            mark(Segment::from_uv(grid, s.uv));
        }
        let free = seam
            .par_iter()
            .zip(&inside)
            .map(|(&s, &i)| s && !i)
            .collect();
        TexelClasses { inside, seam, free }
    }
}

/// Marks every texel whose centre lies in or on a UV triangle, wrap-aware.
/// The triangles are rasterised side by side: a texel is only ever set, so
/// the mask does not depend on their order.
pub fn inside_mask(grid: &TexelGrid, triangles: &[UvTriangle]) -> Vec<bool> {
    let mask: Vec<AtomicBool> = (0..grid.len()).map(|_| AtomicBool::new(false)).collect();
    triangles.par_iter().for_each(|t| {
        for_each_texel_inside(grid, t, |i| mask[i as usize].store(true, Ordering::Relaxed));
    });
    mask.into_iter().map(AtomicBool::into_inner).collect()
}

/// Calls `f` with the (wrapped) index of every texel whose centre lies in or
/// on `t`; degenerate triangles hold none.
pub fn for_each_texel_inside(grid: &TexelGrid, t: &UvTriangle, mut f: impl FnMut(u32)) {
    // Centres exactly on a shared edge must count for one of the two triangles.
    const EPS: f64 = 1e-9;
    let q = t.uvs.map(|uv| grid.to_texel(uv));
    let (a, b, c) = (q[0], q[1], q[2]);
    let d = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1]);
    if d.abs() < 1e-12 {
        return;
    }
    let x0 = a[0].min(b[0]).min(c[0]).floor() as i64;
    let x1 = a[0].max(b[0]).max(c[0]).ceil() as i64;
    let y0 = a[1].min(b[1]).min(c[1]).floor() as i64;
    let y1 = a[1].max(b[1]).max(c[1]).ceil() as i64;
    // A triangle spanning more than the image marks every texel anyway.
    let x1 = x1.min(x0 + 2 * grid.width as i64);
    let y1 = y1.min(y0 + 2 * grid.height as i64);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (px, py) = (x as f64, y as f64);
            let l0 = ((b[1] - c[1]) * (px - c[0]) + (c[0] - b[0]) * (py - c[1])) / d;
            let l1 = ((c[1] - a[1]) * (px - c[0]) + (a[0] - c[0]) * (py - c[1])) / d;
            if l0 >= -EPS && l1 >= -EPS && 1.0 - l0 - l1 >= -EPS {
                f(grid.index(x, y));
            }
        }
    }
}
