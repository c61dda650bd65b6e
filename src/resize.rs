//! Texture sizes every consumer takes.
//!
//! BC1 codes 4×4 blocks, and WebGL refuses a compressed texture whose level
//! 0 sides are not multiples of 4 (`WEBGL_compressed_texture_s3tc`); some
//! older GPUs want powers of two. Before anything else, a texture whose size
//! does not fit is brought to one that does, in one of two ways:
//!
//! * **Padding** keeps every texel as it is: texels are added past the right
//!   and bottom edges, and the UVs are scaled by old/new size on each axis
//!   (here the triangles', in the rewritten model a `KHR_texture_transform`
//!   scale), so every UV samples what it sampled before. The added texels
//!   hold what the sampler read past the edge: the edge texel for
//!   `CLAMP_TO_EDGE`; for the wrapping modes, the texel the wrap reached,
//!   the first added column standing right of the last and the last added
//!   column left of the first (two added texels at least, so both fit).
//!   That is exact while the UVs stay inside one period (`[0, 1]`).
//! * **Resampling** changes the size and keeps the UVs: each new texel is
//!   the texture as the GPU sampled it at the new texel's centre (bilinear,
//!   the sampler's wrap). It is used where padding cannot be exact: UVs that
//!   tile the texture, a `KHR_texture_transform` that rotates them (a
//!   rotation and an unequal per-axis scale do not compose into one
//!   transform), or `pow2`. Sizes only grow, so nothing is filtered away.
//!
//! The report says which was done ([`SizeChange`]).

use serde::{Deserialize, Serialize};

use crate::model::{Texture, TextureBinding, Wrap};

/// What to do with a texture whose sides are not multiples of 4.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Resize {
    /// Pad (or, where padding cannot be exact, resample) to the next
    /// multiple of 4.
    #[default]
    Mul4,
    /// Resample to the next power of two on each side.
    Pow2,
    /// Leave the size alone (BC1 pads the last blocks; WebGL refuses it).
    None,
}

/// How a texture's size was changed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    Padded,
    Resampled,
}

/// A texture's size change, for the report and the rewritten model.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SizeChange {
    pub from: [usize; 2],
    pub to: [usize; 2],
    pub method: Method,
    /// What the UVs are multiplied by (padding only): old/new size per axis.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub uv_scale: Option<[f64; 2]>,
}

/// Fewest texels added on an axis whose sampler wraps: one stands right of
/// the last column, one left of the first.
const WRAP_PAD: usize = 2;

/// The binding brought to a size `resize` allows, and what was done; `None`
/// when its size already fits.
pub fn fit(b: &TextureBinding, resize: Resize) -> Option<(TextureBinding, SizeChange)> {
    let (w, h) = (b.texture.width, b.texture.height);
    let (nw, nh) = match resize {
        Resize::None => return None,
        Resize::Pow2 => (w.next_power_of_two(), h.next_power_of_two()),
        Resize::Mul4 => (w.next_multiple_of(4), h.next_multiple_of(4)),
    };
    if (nw, nh) == (w, h) {
        return None;
    }
    let mut out = b.clone();
    let change = match padded_size(b, resize) {
        Some((pw, ph)) => {
            let scale = [w as f64 / pw as f64, h as f64 / ph as f64];
            out.texture = pad(&b.texture, pw, ph, b.wrap_s, b.wrap_t);
            for t in &mut out.triangles {
                for uv in &mut t.uvs {
                    uv[0] *= scale[0];
                    uv[1] *= scale[1];
                }
            }
            SizeChange {
                from: [w, h],
                to: [pw, ph],
                method: Method::Padded,
                uv_scale: Some(scale),
            }
        }
        None => {
            out.texture = resample(&b.texture, nw, nh, b.wrap_s, b.wrap_t);
            SizeChange {
                from: [w, h],
                to: [nw, nh],
                method: Method::Resampled,
                uv_scale: None,
            }
        }
    };
    tracing::info!(
        image = b.image,
        from_width = w,
        from_height = h,
        to_width = change.to[0],
        to_height = change.to[1],
        method = ?change.method,
        "texture size changed"
    );
    Some((out, change))
}

/// The size padding brings `b` to under `Mul4`, when padding is exact.
fn padded_size(b: &TextureBinding, resize: Resize) -> Option<(usize, usize)> {
    if resize != Resize::Mul4 || b.rotated {
        return None;
    }
    let (w, h) = (b.texture.width, b.texture.height);
    let range = |axis: usize| {
        b.triangles
            .iter()
            .flat_map(|t| t.uvs.iter().map(move |uv| uv[axis]))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            })
    };
    let axis = |n: usize, wrap: Wrap, (lo, hi): (f64, f64)| -> Option<usize> {
        if n.is_multiple_of(4) {
            return Some(n);
        }
        // No sample reaches past the edge: whatever is added is never read.
        let inner = lo >= 0.5 / n as f64 && hi <= 1.0 - 0.5 / n as f64;
        match wrap {
            Wrap::ClampToEdge => Some(n.next_multiple_of(4)),
            _ if inner => Some(n.next_multiple_of(4)),
            _ if lo >= 0.0 && hi <= 1.0 => Some((n + WRAP_PAD).next_multiple_of(4)),
            _ => None,
        }
    };
    Some((axis(w, b.wrap_s, range(0))?, axis(h, b.wrap_t, range(1))?))
}

/// Which source texel an added texel at `i` (≥ `n`, < `m`) repeats.
fn pad_source(i: usize, n: usize, m: usize, wrap: Wrap) -> usize {
    match wrap {
        Wrap::ClampToEdge => n - 1,
        // Left of texel 0 on the next period: the last added texel.
        _ if i == m - 1 => wrap.index(-1, n),
        _ => wrap.index(n as i64, n),
    }
}

fn pad(t: &Texture, nw: usize, nh: usize, wrap_s: Wrap, wrap_t: Wrap) -> Texture {
    let c = t.channels;
    let col = |x: usize| {
        if x < t.width {
            x
        } else {
            pad_source(x, t.width, nw, wrap_s)
        }
    };
    let row = |y: usize| {
        if y < t.height {
            y
        } else {
            pad_source(y, t.height, nh, wrap_t)
        }
    };
    let mut data = Vec::with_capacity(nw * nh * c);
    for y in 0..nh {
        let sy = row(y);
        for x in 0..nw {
            let at = (sy * t.width + col(x)) * c;
            data.extend_from_slice(&t.data[at..at + c]);
        }
    }
    like(t, nw, nh, data)
}

/// A texture of `t`'s channels and encoding, `nw`×`nh`, holding `data`.
fn like(t: &Texture, nw: usize, nh: usize, data: Vec<f32>) -> Texture {
    Texture {
        width: nw,
        height: nh,
        channels: t.channels,
        data,
        encoding: t.encoding,
    }
}

/// Bilinear samples of `t` at the centres of an `nw`×`nh` grid over the
/// same UV square, with the sampler's wrap.
fn resample(t: &Texture, nw: usize, nh: usize, wrap_s: Wrap, wrap_t: Wrap) -> Texture {
    let c = t.channels;
    // Source taps and weights along one axis for each new texel.
    let taps = |n: usize, m: usize, wrap: Wrap| -> Vec<(usize, usize, f32)> {
        (0..m)
            .map(|i| {
                let x = (i as f64 + 0.5) * n as f64 / m as f64 - 0.5;
                let x0 = x.floor();
                let f = (x - x0) as f32;
                let x0 = x0 as i64;
                (wrap.index(x0, n), wrap.index(x0 + 1, n), f)
            })
            .collect()
    };
    let (tx, ty) = (taps(t.width, nw, wrap_s), taps(t.height, nh, wrap_t));
    let at = |x: usize, y: usize, ch: usize| t.data[(y * t.width + x) * c + ch];
    let mut data = Vec::with_capacity(nw * nh * c);
    for &(y0, y1, fy) in &ty {
        for &(x0, x1, fx) in &tx {
            for ch in 0..c {
                let top = at(x0, y0, ch) * (1.0 - fx) + at(x1, y0, ch) * fx;
                let bottom = at(x0, y1, ch) * (1.0 - fx) + at(x1, y1, ch) * fx;
                data.push(top * (1.0 - fy) + bottom * fy);
            }
        }
    }
    like(t, nw, nh, data)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{TextureEncoding, UvTriangle};

    fn binding(w: usize, h: usize, wrap: Wrap, uvs: [[f64; 2]; 3]) -> TextureBinding {
        let data = (0..w * h)
            .flat_map(|i| [(i % w) as f32 / w as f32, (i / w) as f32 / h as f32, 0.5])
            .collect();
        TextureBinding {
            image: 0,
            name: "t".into(),
            texture: Texture {
                width: w,
                height: h,
                channels: 3,
                data,
                encoding: TextureEncoding {
                    channels: 3,
                    bits: 8,
                },
            },
            wrap_s: wrap,
            wrap_t: wrap,
            srgb: true,
            rotated: false,
            alpha: crate::model::AlphaUse::Opaque,
            triangles: vec![UvTriangle {
                group: 0,
                positions: [[0.0; 3]; 3],
                uvs,
            }],
        }
    }

    /// Bilinear sample at `uv` with the binding's wrap, as a GPU samples.
    fn sample(b: &TextureBinding, uv: [f64; 2]) -> Vec<f32> {
        let t = &b.texture;
        let x = uv[0] * t.width as f64 - 0.5;
        let y = uv[1] * t.height as f64 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let (xa, xb) = (b.wrap_s.index(x0, t.width), b.wrap_s.index(x0 + 1, t.width));
        let (ya, yb) = (
            b.wrap_t.index(y0, t.height),
            b.wrap_t.index(y0 + 1, t.height),
        );
        let at = |x: usize, y: usize, ch: usize| t.data[(y * t.width + x) * t.channels + ch];
        (0..t.channels)
            .map(|ch| {
                let top = at(xa, ya, ch) * (1.0 - fx) + at(xb, ya, ch) * fx;
                let bottom = at(xa, yb, ch) * (1.0 - fx) + at(xb, yb, ch) * fx;
                top * (1.0 - fy) + bottom * fy
            })
            .collect()
    }

    /// Padding must sample like the original at every UV of one period.
    fn assert_padding_exact(w: usize, h: usize, wrap: Wrap) {
        let b = binding(w, h, wrap, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]);
        let (p, change) = fit(&b, Resize::Mul4).expect("padded");
        assert_eq!(change.method, Method::Padded, "{wrap:?}");
        assert_eq!(p.texture.width % 4, 0);
        assert_eq!(p.texture.height % 4, 0);
        let s = change.uv_scale.unwrap();
        for i in 0..=40 {
            for j in 0..=40 {
                let uv = [i as f64 / 40.0, j as f64 / 40.0];
                let a = sample(&b, uv);
                let c = sample(&p, [uv[0] * s[0], uv[1] * s[1]]);
                for (x, y) in a.iter().zip(&c) {
                    assert!((x - y).abs() < 1e-5, "{wrap:?} at {uv:?}: {a:?} vs {c:?}");
                }
            }
        }
    }

    #[test]
    fn padding_samples_as_the_original_under_every_wrap() {
        for wrap in [Wrap::ClampToEdge, Wrap::Repeat, Wrap::MirroredRepeat] {
            assert_padding_exact(211, 13, wrap);
            assert_padding_exact(7, 10, wrap);
        }
    }

    #[test]
    fn wrapping_samplers_get_two_added_texels_at_least() {
        let b = binding(211, 8, Wrap::Repeat, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]);
        let (p, _) = fit(&b, Resize::Mul4).unwrap();
        assert_eq!((p.texture.width, p.texture.height), (216, 8));
        let c = binding(
            211,
            8,
            Wrap::ClampToEdge,
            [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
        );
        assert_eq!(fit(&c, Resize::Mul4).unwrap().0.texture.width, 212);
    }

    #[test]
    fn tiling_uvs_and_rotations_resample_instead() {
        let tiled = binding(10, 10, Wrap::Repeat, [[0.0, 0.0], [3.0, 0.0], [0.0, 1.0]]);
        let (r, change) = fit(&tiled, Resize::Mul4).unwrap();
        assert_eq!(change.method, Method::Resampled);
        assert_eq!((r.texture.width, r.texture.height), (12, 12));
        assert_eq!(r.triangles, tiled.triangles);
        let mut rotated = binding(10, 10, Wrap::ClampToEdge, [[0.1; 2], [0.2; 2], [0.3; 2]]);
        rotated.rotated = true;
        assert_eq!(
            fit(&rotated, Resize::Mul4).unwrap().1.method,
            Method::Resampled
        );
    }

    #[test]
    fn pow2_resamples_and_none_or_fitting_sizes_leave_it() {
        let b = binding(100, 60, Wrap::Repeat, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]);
        let (r, change) = fit(&b, Resize::Pow2).unwrap();
        assert_eq!(change.to, [128, 64]);
        assert_eq!(change.method, Method::Resampled);
        // A linear ramp resampled stays a ramp: the centre samples the centre.
        let mid = sample(&r, [0.5, 0.5]);
        let orig = sample(&b, [0.5, 0.5]);
        assert!((mid[0] - orig[0]).abs() < 0.02 && (mid[1] - orig[1]).abs() < 0.02);
        assert!(fit(&b, Resize::None).is_none());
        assert!(fit(&b, Resize::Mul4).is_none());
    }
}
