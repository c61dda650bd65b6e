//! DDS files holding BC1 data (SPEC §5), in this crate's BC1/BC3 block
//! types: the front that the pipeline and tests use over the general DDS
//! reader and writer of [`crate::container::dds`], which holds the layout
//! (legacy FourCC `DXT1`/`DXT5` header, or `DX10` + DXGI_FORMAT_BC1_UNORM
//! (71) / BC1_UNORM_SRGB (72) / BC3_UNORM (77) / BC3_UNORM_SRGB (78)).
//! BC3 (for textures whose alpha blends) is 16 bytes a block: the alpha
//! block, then the colour block (always decoded in four-colour mode).
//!
//! The reader accepts what the writer produces (and the same layout from
//! other writers); anything else, BC7 included, is an error, never a panic.

use super::alpha::AlphaBlock;
use super::block::Block;
use crate::container::dds::DdsHeader;
use crate::container::{self, ColorSpace, EncodedTexture};

pub use crate::container::dds::{
    DXGI_FORMAT_BC1_UNORM, DXGI_FORMAT_BC1_UNORM_SRGB, DXGI_FORMAT_BC3_UNORM,
    DXGI_FORMAT_BC3_UNORM_SRGB,
};
/// The containers' error, under the name this module has always used.
pub use crate::container::ContainerError as DdsError;
pub use crate::container::{full_chain_len, mip_size};

/// Which header the file carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DdsHeaderKind {
    /// Legacy header, FourCC `DXT1` (or `DXT5` for BC3).
    Legacy,
    /// DX10 extension header; `srgb` selects BC1_UNORM_SRGB (for base
    /// colour and emissive textures) over BC1_UNORM.
    Dx10 { srgb: bool },
}

/// One mip level: its size in texels and its blocks, row-major.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MipLevel {
    pub width: u32,
    pub height: u32,
    pub blocks: Vec<Block>,
    /// BC3's alpha blocks, one per colour block; empty for BC1.
    pub alpha: Vec<AlphaBlock>,
}

/// A DDS file read back.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DdsImage {
    pub header: DdsHeaderKind,
    /// Level 0 first; dimensions halve (rounding down, at least 1).
    pub levels: Vec<MipLevel>,
}

/// Bytes of BC1 data for one level.
pub fn level_bytes(width: u32, height: u32) -> usize {
    container::level_byte_len(container::BlockFormat::Bc1, width, height)
}

/// Writes a DDS file. More than one level means a mip chain: level k must
/// be level 0's size halved k times (rounding down, at least 1).
pub fn write_dds(levels: &[MipLevel], header: DdsHeaderKind) -> Result<Vec<u8>, DdsError> {
    let (kind, color_space) = match header {
        DdsHeaderKind::Legacy => (DdsHeader::Legacy, ColorSpace::Linear),
        DdsHeaderKind::Dx10 { srgb: false } => (DdsHeader::Dx10, ColorSpace::Linear),
        DdsHeaderKind::Dx10 { srgb: true } => (DdsHeader::Dx10, ColorSpace::Srgb),
    };
    let tex = EncodedTexture::from_mip_levels(levels, color_space)?;
    container::dds::write_dds(&tex, kind)
}

/// Reads a BC1 or BC3 DDS file (legacy `DXT1`/`DXT5` or DX10
/// `BC1_UNORM[_SRGB]`/`BC3_UNORM[_SRGB]`).
pub fn read_dds(bytes: &[u8]) -> Result<DdsImage, DdsError> {
    let file = container::dds::read_dds(bytes)?;
    let header = match file.header {
        DdsHeader::Legacy => DdsHeaderKind::Legacy,
        DdsHeader::Dx10 => DdsHeaderKind::Dx10 {
            srgb: file.texture.color_space == ColorSpace::Srgb,
        },
    };
    Ok(DdsImage {
        header,
        levels: file.texture.to_mip_levels()?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bc1::{encode_image, Level};

    const DDPF_FOURCC: u32 = 0x4;

    fn u32_at(bytes: &[u8], off: usize) -> u32 {
        u32::from_le_bytes(bytes[off..off + 4].try_into().unwrap())
    }

    fn texture(w: usize, h: usize) -> Vec<f32> {
        let mut v = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                v.push(((x * 3 + y) % 97) as f32 / 96.0);
                v.push((y % 31) as f32 / 30.0);
                v.push(((x ^ y) % 256) as f32 / 255.0);
            }
        }
        v
    }

    /// Box-filters by 2 (clamped at the edges); enough to make test chains.
    fn half(img: &[f32], w: usize, h: usize) -> (Vec<f32>, usize, usize) {
        let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
        let mut out = vec![0.0f32; nw * nh * 3];
        for y in 0..nh {
            for x in 0..nw {
                for ch in 0..3 {
                    let mut s = 0.0;
                    for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let sx = (2 * x + dx).min(w - 1);
                        let sy = (2 * y + dy).min(h - 1);
                        s += img[(sy * w + sx) * 3 + ch];
                    }
                    out[(y * nw + x) * 3 + ch] = s / 4.0;
                }
            }
        }
        (out, nw, nh)
    }

    fn chain(w: usize, h: usize, mips: bool) -> Vec<MipLevel> {
        let mut img = texture(w, h);
        let (mut cw, mut ch) = (w, h);
        let mut levels = Vec::new();
        loop {
            let blocks = encode_image(&img, cw, ch, 3, Level::Fast).unwrap();
            levels.push(MipLevel {
                width: cw as u32,
                height: ch as u32,
                blocks,
                alpha: Vec::new(),
            });
            if !mips || (cw == 1 && ch == 1) {
                break;
            }
            let (n, nw, nh) = half(&img, cw, ch);
            img = n;
            cw = nw;
            ch = nh;
        }
        levels
    }

    const KINDS: [DdsHeaderKind; 3] = [
        DdsHeaderKind::Legacy,
        DdsHeaderKind::Dx10 { srgb: false },
        DdsHeaderKind::Dx10 { srgb: true },
    ];

    #[test]
    fn header_fields_match_spec() {
        let levels = chain(211, 211, true);
        assert_eq!(levels.len(), 8);
        let bytes = write_dds(&levels, DdsHeaderKind::Legacy).unwrap();
        assert_eq!(&bytes[0..4], b"DDS ");
        assert_eq!(u32_at(&bytes, 4), 124);
        let flags = u32_at(&bytes, 8);
        assert_eq!(flags, 0x1 | 0x2 | 0x4 | 0x1000 | 0x2_0000 | 0x8_0000);
        assert_eq!(u32_at(&bytes, 12), 211);
        assert_eq!(u32_at(&bytes, 16), 211);
        assert_eq!(u32_at(&bytes, 20), 53 * 53 * 8);
        assert_eq!(u32_at(&bytes, 28), 8);
        assert_eq!(u32_at(&bytes, 80), DDPF_FOURCC);
        assert_eq!(&bytes[84..88], b"DXT1");
        assert_eq!(u32_at(&bytes, 108), 0x1000 | 0x8 | 0x40_0000);
        let sizes: usize = [211u32, 105, 52, 26, 13, 6, 3, 1]
            .iter()
            .map(|&s| (s as usize).div_ceil(4).pow(2) * 8)
            .sum();
        assert_eq!(bytes.len(), 128 + sizes);

        let single = write_dds(&chain(8, 4, false), DdsHeaderKind::Dx10 { srgb: true }).unwrap();
        assert_eq!(u32_at(&single, 8) & 0x2_0000, 0);
        assert_eq!(u32_at(&single, 28), 0);
        assert_eq!(u32_at(&single, 108), 0x1000);
        assert_eq!(&single[84..88], b"DX10");
        assert_eq!(u32_at(&single, 128), 72);
        assert_eq!(u32_at(&single, 132), 3);
        assert_eq!(u32_at(&single, 140), 1);
        assert_eq!(single.len(), 148 + 2 * 8);
    }

    /// Every variant read back by an independent reader (ddsfile) and by
    /// ours gives the bytes that were encoded.
    #[test]
    fn variants_read_back_with_ddsfile() {
        for (w, h) in [(211usize, 211usize), (64, 16), (5, 3), (1, 1)] {
            for mips in [false, true] {
                let levels = chain(w, h, mips);
                for kind in KINDS {
                    let bytes = write_dds(&levels, kind).unwrap();
                    let dds = ddsfile::Dds::read(&mut &bytes[..]).unwrap();
                    assert_eq!(dds.get_width(), w as u32);
                    assert_eq!(dds.get_height(), h as u32);
                    assert_eq!(dds.get_num_mipmap_levels() as usize, levels.len());
                    match kind {
                        DdsHeaderKind::Legacy => {
                            assert_eq!(dds.get_d3d_format(), Some(ddsfile::D3DFormat::DXT1));
                        }
                        DdsHeaderKind::Dx10 { srgb } => {
                            let want = if srgb {
                                ddsfile::DxgiFormat::BC1_UNorm_sRGB
                            } else {
                                ddsfile::DxgiFormat::BC1_UNorm
                            };
                            assert_eq!(dds.get_dxgi_format(), Some(want));
                        }
                    }
                    let expect: Vec<u8> = levels
                        .iter()
                        .flat_map(|l| l.blocks.iter().flat_map(|b| b.to_bytes()))
                        .collect();
                    assert_eq!(dds.get_data(0).unwrap(), &expect[..]);
                    assert_eq!(
                        dds.get_main_texture_size(),
                        Some(levels[0].blocks.len() as u32 * 8)
                    );

                    let ours = read_dds(&bytes).unwrap();
                    assert_eq!(ours.header, kind);
                    assert_eq!(ours.levels, levels);
                }
            }
        }
    }

    #[test]
    fn writer_rejects_inconsistent_levels() {
        assert_eq!(
            write_dds(&[], DdsHeaderKind::Legacy),
            Err(DdsError::NoLevels)
        );
        let mut levels = chain(16, 16, true);
        levels[2].width = 5;
        assert!(matches!(
            write_dds(&levels, DdsHeaderKind::Legacy),
            Err(DdsError::LevelSize { level: 2, .. })
        ));
        let mut levels = chain(16, 16, true);
        levels[1].blocks.pop();
        assert!(matches!(
            write_dds(&levels, DdsHeaderKind::Legacy),
            Err(DdsError::LevelBlocks { level: 1, .. })
        ));
        let mut levels = chain(4, 4, true);
        levels.push(levels[2].clone());
        assert!(matches!(
            write_dds(&levels, DdsHeaderKind::Legacy),
            Err(DdsError::TooManyLevels { .. })
        ));
        let zero = MipLevel {
            width: 0,
            height: 4,
            blocks: vec![],
            alpha: vec![],
        };
        assert!(write_dds(&[zero], DdsHeaderKind::Legacy).is_err());
    }

    #[test]
    fn bc3_round_trips_under_both_headers() {
        use crate::bc1::alpha::AlphaBlock;
        let mut levels = chain(20, 12, true);
        for (k, l) in levels.iter_mut().enumerate() {
            l.alpha = (0..l.blocks.len())
                .map(|i| {
                    let idx: [u8; 16] = std::array::from_fn(|t| ((t + i + k) % 8) as u8);
                    AlphaBlock::with_indices((i * 7) as u8, (k * 31) as u8, &idx)
                })
                .collect();
        }
        for (header, fourcc, format) in [
            (DdsHeaderKind::Legacy, *b"DXT5", None),
            (
                DdsHeaderKind::Dx10 { srgb: true },
                *b"DX10",
                Some(DXGI_FORMAT_BC3_UNORM_SRGB),
            ),
            (
                DdsHeaderKind::Dx10 { srgb: false },
                *b"DX10",
                Some(DXGI_FORMAT_BC3_UNORM),
            ),
        ] {
            let bytes = write_dds(&levels, header).unwrap();
            assert_eq!(bytes[84..88], fourcc);
            if let Some(f) = format {
                assert_eq!(u32_at(&bytes, 128), f);
            }
            // Linear size: level 0's bytes, 16 a block.
            assert_eq!(u32_at(&bytes, 20), 5 * 3 * 16);
            let back = read_dds(&bytes).unwrap();
            assert_eq!(back.header, header);
            assert_eq!(back.levels, levels);
        }
        // Alpha on some levels only is refused.
        levels[1].alpha.clear();
        assert!(matches!(
            write_dds(&levels, DdsHeaderKind::Legacy),
            Err(DdsError::AlphaBlocks { level: 1, .. })
        ));
    }

    #[test]
    fn reader_never_panics_on_damage() {
        let bytes = write_dds(&chain(20, 12, true), DdsHeaderKind::Dx10 { srgb: false }).unwrap();
        for cut in 0..bytes.len() {
            assert!(read_dds(&bytes[..cut]).is_err());
        }
        let mut rng = crate::bc1::block::tests::Rng::new(9);
        for _ in 0..5000 {
            let mut b = bytes.clone();
            for _ in 0..1 + rng.next_u64() % 4 {
                let at = (rng.next_u64() % 160) as usize;
                b[at] = rng.next_u64() as u8;
            }
            let _ = read_dds(&b);
        }
        let mut huge = bytes.clone();
        huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        huge[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        huge[28..32].copy_from_slice(&40u32.to_le_bytes());
        assert!(read_dds(&huge).is_err());
        let mut wrong = bytes.clone();
        wrong[128..132].copy_from_slice(&97u32.to_le_bytes());
        assert_eq!(read_dds(&wrong), Err(DdsError::DxgiFormat(97)));
        // BC7 is a DDS this front cannot hold in its types.
        let bc7 = crate::container::EncodedTexture {
            format: crate::container::BlockFormat::Bc7,
            color_space: ColorSpace::Srgb,
            width: 4,
            height: 4,
            levels: vec![vec![0; 16]],
        };
        let bc7 = crate::container::dds::write_dds(&bc7, DdsHeader::Dx10).unwrap();
        assert_eq!(
            read_dds(&bc7),
            Err(DdsError::NotBc1OrBc3(crate::container::BlockFormat::Bc7))
        );
        let mut dxt3 = bytes;
        dxt3[84..88].copy_from_slice(b"DXT3");
        assert_eq!(read_dds(&dxt3), Err(DdsError::DdsFourCc(*b"DXT3")));
        assert!(matches!(
            read_dds(b"not a dds"),
            Err(DdsError::Truncated { len: 9, .. })
        ));
    }
}
