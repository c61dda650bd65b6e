//! Texel space and bilinear taps (SPEC §1).

use crate::model::{TextureBinding, Wrap};

/// The texel lattice of one texture: its size and how indices wrap.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TexelGrid {
    pub width: usize,
    pub height: usize,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
}

/// One term of a linear functional over texels: `weight · p[texel]`.
pub type Tap = (u32, f64);

impl TexelGrid {
    /// The lattice of a bound texture at its full size.
    pub fn of(b: &TextureBinding) -> Self {
        TexelGrid {
            width: b.texture.width,
            height: b.texture.height,
            wrap_s: b.wrap_s,
            wrap_t: b.wrap_t,
        }
    }

    pub fn len(&self) -> usize {
        self.width * self.height
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// UV → texel coordinates: texel (i,j) has its centre at (i,j); no V flip for glTF.
    #[inline]
    pub fn to_texel(&self, uv: [f64; 2]) -> [f64; 2] {
        [
            uv[0] * self.width as f64 - 0.5,
            uv[1] * self.height as f64 - 0.5,
        ]
    }

    /// Linear index of the texel at integer lattice position (i,j), wrapped.
    #[inline]
    pub fn index(&self, i: i64, j: i64) -> u32 {
        let x = self.wrap_s.index(i, self.width);
        let y = self.wrap_t.index(j, self.height);
        (y * self.width + x) as u32
    }

    /// The four corner texels of cell (cx, cy), in the order 00, 10, 01, 11.
    #[inline]
    pub fn cell_corners(&self, cx: i64, cy: i64) -> [u32; 4] {
        [
            self.index(cx, cy),
            self.index(cx + 1, cy),
            self.index(cx, cy + 1),
            self.index(cx + 1, cy + 1),
        ]
    }

    /// Bilinear interpolation at `p` as taps on the corners of cell `cell`.
    ///
    /// The cell is passed in rather than derived from `p` so that a point on a
    /// cell boundary is evaluated with the polynomial of the piece it belongs to.
    #[inline]
    pub fn bilinear_taps(&self, cell: [i64; 2], p: [f64; 2]) -> [Tap; 4] {
        let fx = p[0] - cell[0] as f64;
        let fy = p[1] - cell[1] as f64;
        let c = self.cell_corners(cell[0], cell[1]);
        [
            (c[0], (1.0 - fx) * (1.0 - fy)),
            (c[1], fx * (1.0 - fy)),
            (c[2], (1.0 - fx) * fy),
            (c[3], fx * fy),
        ]
    }

    /// The derivative of the bilinear interpolant along unit direction `n`
    /// (texel units) at `p`, as taps on the corners of `cell`.
    #[inline]
    pub fn derivative_taps(&self, cell: [i64; 2], p: [f64; 2], n: [f64; 2]) -> [Tap; 4] {
        let fx = p[0] - cell[0] as f64;
        let fy = p[1] - cell[1] as f64;
        let c = self.cell_corners(cell[0], cell[1]);
        // dB/dx = (1-fy)(p10-p00) + fy(p11-p01); dB/dy = (1-fx)(p01-p00) + fx(p11-p10).
        [
            (c[0], -n[0] * (1.0 - fy) - n[1] * (1.0 - fx)),
            (c[1], n[0] * (1.0 - fy) - n[1] * fx),
            (c[2], -n[0] * fy + n[1] * (1.0 - fx)),
            (c[3], n[0] * fy + n[1] * fx),
        ]
    }

    /// Bilinear sample of channel `c` of an interleaved image at texel-space point `p`.
    pub fn sample(&self, data: &[f32], channels: usize, c: usize, p: [f64; 2]) -> f64 {
        let cell = [p[0].floor() as i64, p[1].floor() as i64];
        self.bilinear_taps(cell, p)
            .iter()
            .map(|&(i, w)| w * f64::from(data[i as usize * channels + c]))
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn taps_reproduce_bilinear_and_its_derivative() {
        let g = TexelGrid {
            width: 4,
            height: 4,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::ClampToEdge,
        };
        let data: Vec<f32> = (0..16).map(|i| ((i * 7) % 11) as f32 / 10.0).collect();
        let f = |p: [f64; 2]| g.sample(&data, 1, 0, p);
        let p = [1.3, 2.6];
        let n = [0.6, -0.8];
        let h = 1e-6;
        let numeric = (f([p[0] + h * n[0], p[1] + h * n[1]])
            - f([p[0] - h * n[0], p[1] - h * n[1]]))
            / (2.0 * h);
        let analytic: f64 = g
            .derivative_taps([1, 2], p, n)
            .iter()
            .map(|&(i, w)| w * f64::from(data[i as usize]))
            .sum();
        assert!((numeric - analytic).abs() < 1e-6, "{numeric} vs {analytic}");
        // Weights of an interpolant sum to one; of a derivative, to zero.
        let s: f64 = g.bilinear_taps([1, 2], p).iter().map(|t| t.1).sum();
        let d: f64 = g.derivative_taps([1, 2], p, n).iter().map(|t| t.1).sum();
        assert!((s - 1.0).abs() < 1e-15 && d.abs() < 1e-15);
    }

    #[test]
    fn wrap_modes_map_indices() {
        assert_eq!(Wrap::Repeat.index(-1, 4), 3);
        assert_eq!(Wrap::Repeat.index(5, 4), 1);
        assert_eq!(Wrap::ClampToEdge.index(-3, 4), 0);
        assert_eq!(Wrap::ClampToEdge.index(9, 4), 3);
        assert_eq!(Wrap::MirroredRepeat.index(-1, 4), 0);
        assert_eq!(Wrap::MirroredRepeat.index(4, 4), 3);
        assert_eq!(Wrap::MirroredRepeat.index(8, 4), 0);
    }
}
