//! Mip chains: wrap-aware 2×2 box filtering.

use crate::model::{Texture, Wrap};

/// Size of mip level `level` of a `width`×`height` texture (each side halves, at least 1).
pub fn level_size(width: usize, height: usize, level: usize) -> (usize, usize) {
    ((width >> level).max(1), (height >> level).max(1))
}

/// Number of levels in the full chain down to 1×1.
pub fn chain_len(width: usize, height: usize) -> usize {
    let mut n = 1;
    let (mut w, mut h) = (width, height);
    while w > 1 || h > 1 {
        w = (w / 2).max(1);
        h = (h / 2).max(1);
        n += 1;
    }
    n
}

/// The next mip level: each texel averages the 2×2 texels above it. Where an
/// odd size leaves a footprint hanging over the edge, the sampler's wrap
/// mode decides which texel it reads, as the GPU would.
pub fn downsample(t: &Texture, wrap_s: Wrap, wrap_t: Wrap) -> Texture {
    let (w, h) = ((t.width / 2).max(1), (t.height / 2).max(1));
    let ch = t.channels;
    let mut data = vec![0.0f32; w * h * ch];
    for y in 0..h {
        for x in 0..w {
            let xs = [
                wrap_s.index(2 * x as i64, t.width),
                wrap_s.index(2 * x as i64 + 1, t.width),
            ];
            let ys = [
                wrap_t.index(2 * y as i64, t.height),
                wrap_t.index(2 * y as i64 + 1, t.height),
            ];
            for c in 0..ch {
                let mut s = 0.0f32;
                for &sy in &ys {
                    for &sx in &xs {
                        s += t.data[(sy * t.width + sx) * ch + c];
                    }
                }
                data[(y * w + x) * ch + c] = 0.25 * s;
            }
        }
    }
    Texture {
        width: w,
        height: h,
        channels: ch,
        data,
        encoding: t.encoding,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::TextureEncoding;

    fn tex(w: usize, h: usize, data: Vec<f32>) -> Texture {
        Texture {
            width: w,
            height: h,
            channels: 1,
            data,
            encoding: TextureEncoding {
                channels: 1,
                bits: 8,
            },
        }
    }

    #[test]
    fn box_filter_averages_and_preserves_the_mean() {
        let t = tex(4, 2, vec![0.0, 1.0, 0.5, 0.5, 1.0, 0.0, 0.25, 0.75]);
        let d = downsample(&t, Wrap::Repeat, Wrap::Repeat);
        assert_eq!((d.width, d.height), (2, 1));
        assert_eq!(d.data, vec![0.5, 0.5]);
    }

    #[test]
    fn odd_sizes_follow_the_wrap_mode() {
        let t = tex(3, 1, vec![0.0, 0.0, 1.0]);
        // Width 3 → 1: texels 0 and 1 (rows repeat by clamp).
        assert_eq!(
            downsample(&t, Wrap::Repeat, Wrap::ClampToEdge).data,
            vec![0.0]
        );
        assert_eq!(chain_len(211, 211), 8);
        assert_eq!(chain_len(1, 1), 1);
        assert_eq!(level_size(211, 100, 7), (1, 1));
    }
}
