//! DDS files holding BC1 data (SPEC §5): 'DDS ' + 124-byte header with
//! FourCC `DXT1`, or FourCC `DX10` + the 20-byte DX10 header with
//! DXGI_FORMAT_BC1_UNORM (71) or BC1_UNORM_SRGB (72); then every mip level
//! in order, each max(1,⌈w/4⌉)·max(1,⌈h/4⌉)·8 bytes. BC3 (for textures
//! whose alpha blends) is the same with FourCC `DXT5` or BC3_UNORM (77) /
//! BC3_UNORM_SRGB (78), and 16 bytes a block: the alpha block, then the
//! colour block (always decoded in four-colour mode).
//!
//! The reader accepts what the writer produces (and the same layout from
//! other writers); anything else is an error, never a panic.

use super::alpha::AlphaBlock;
use super::block::Block;
use super::block_dims;

const MAGIC: &[u8; 4] = b"DDS ";
const HEADER_SIZE: u32 = 124;
const PIXELFORMAT_SIZE: u32 = 32;
const DX10_HEADER_LEN: usize = 20;

const DDSD_CAPS: u32 = 0x1;
const DDSD_HEIGHT: u32 = 0x2;
const DDSD_WIDTH: u32 = 0x4;
const DDSD_PIXELFORMAT: u32 = 0x1000;
const DDSD_MIPMAPCOUNT: u32 = 0x2_0000;
const DDSD_LINEARSIZE: u32 = 0x8_0000;
const DDPF_FOURCC: u32 = 0x4;
const DDSCAPS_COMPLEX: u32 = 0x8;
const DDSCAPS_TEXTURE: u32 = 0x1000;
const DDSCAPS_MIPMAP: u32 = 0x40_0000;

const FOURCC_DXT1: &[u8; 4] = b"DXT1";
const FOURCC_DXT5: &[u8; 4] = b"DXT5";
const FOURCC_DX10: &[u8; 4] = b"DX10";
pub const DXGI_FORMAT_BC1_UNORM: u32 = 71;
pub const DXGI_FORMAT_BC1_UNORM_SRGB: u32 = 72;
pub const DXGI_FORMAT_BC3_UNORM: u32 = 77;
pub const DXGI_FORMAT_BC3_UNORM_SRGB: u32 = 78;
const D3D10_RESOURCE_DIMENSION_TEXTURE2D: u32 = 3;

/// Which header the file carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DdsHeaderKind {
    /// Legacy header, FourCC `DXT1`.
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

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DdsError {
    #[error("no mip levels to write")]
    NoLevels,
    #[error("mip level {level} is {width}x{height}; expected {expected_width}x{expected_height}")]
    LevelSize {
        level: usize,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error("mip level {level} has {got} blocks; {need} expected")]
    LevelBlocks {
        level: usize,
        got: usize,
        need: usize,
    },
    #[error("{count} mip levels; a {width}x{height} texture has at most {max}")]
    TooManyLevels {
        count: usize,
        width: u32,
        height: u32,
        max: usize,
    },
    #[error("file is {len} bytes, too short for a DDS header")]
    Truncated { len: usize },
    #[error("not a DDS file (bad magic)")]
    BadMagic,
    #[error("bad DDS header: {0}")]
    BadHeader(&'static str),
    #[error("pixel format is not BC1 or BC3 (FourCC {0:?})")]
    NotBc1([u8; 4]),
    #[error("DX10 header: DXGI format {0} is not BC1 or BC3 (UNORM or UNORM_SRGB)")]
    Dx10Format(u32),
    #[error("mip level {level} has {got} alpha blocks; {need} expected (every level or none)")]
    AlphaBlocks {
        level: usize,
        got: usize,
        need: usize,
    },
    #[error("DX10 header: only single 2D textures are supported")]
    Dx10Layout,
    #[error("pixel data is {got} bytes; {need} expected")]
    DataSize { got: usize, need: usize },
}

/// Number of levels in a full mip chain down to 1×1.
pub fn full_chain_len(width: u32, height: u32) -> usize {
    (32 - width.max(height).max(1).leading_zeros()) as usize
}

/// Size of mip level `level` of a `width`×`height` texture.
pub fn mip_size(width: u32, height: u32, level: usize) -> (u32, u32) {
    let shift = level.min(31) as u32;
    ((width >> shift).max(1), (height >> shift).max(1))
}

/// Bytes of BC1 data for one level.
pub fn level_bytes(width: u32, height: u32) -> usize {
    let (bw, bh) = block_dims(width as usize, height as usize);
    bw.saturating_mul(bh).saturating_mul(8)
}

/// Writes a DDS file. More than one level means a mip chain: level k must
/// be level 0's size halved k times (rounding down, at least 1).
pub fn write_dds(levels: &[MipLevel], header: DdsHeaderKind) -> Result<Vec<u8>, DdsError> {
    let first = levels.first().ok_or(DdsError::NoLevels)?;
    let (w0, h0) = (first.width, first.height);
    if w0 == 0 || h0 == 0 {
        return Err(DdsError::LevelSize {
            level: 0,
            width: w0,
            height: h0,
            expected_width: w0.max(1),
            expected_height: h0.max(1),
        });
    }
    let max = full_chain_len(w0, h0);
    if levels.len() > max {
        return Err(DdsError::TooManyLevels {
            count: levels.len(),
            width: w0,
            height: h0,
            max,
        });
    }
    let bc3 = !first.alpha.is_empty();
    let mut data_len = 0usize;
    for (k, lvl) in levels.iter().enumerate() {
        let (ew, eh) = mip_size(w0, h0, k);
        if (lvl.width, lvl.height) != (ew, eh) {
            return Err(DdsError::LevelSize {
                level: k,
                width: lvl.width,
                height: lvl.height,
                expected_width: ew,
                expected_height: eh,
            });
        }
        let need = level_bytes(ew, eh) / 8;
        if lvl.blocks.len() != need {
            return Err(DdsError::LevelBlocks {
                level: k,
                got: lvl.blocks.len(),
                need,
            });
        }
        let alpha_need = if bc3 { need } else { 0 };
        if lvl.alpha.len() != alpha_need {
            return Err(DdsError::AlphaBlocks {
                level: k,
                got: lvl.alpha.len(),
                need: alpha_need,
            });
        }
        data_len += need * if bc3 { 16 } else { 8 };
    }
    let mips = levels.len() > 1;
    let dx10 = matches!(header, DdsHeaderKind::Dx10 { .. });
    let mut out = Vec::with_capacity(4 + 124 + if dx10 { DX10_HEADER_LEN } else { 0 } + data_len);
    let put = |out: &mut Vec<u8>, v: u32| out.extend_from_slice(&v.to_le_bytes());

    out.extend_from_slice(MAGIC);
    put(&mut out, HEADER_SIZE);
    let mut flags = DDSD_CAPS | DDSD_HEIGHT | DDSD_WIDTH | DDSD_PIXELFORMAT | DDSD_LINEARSIZE;
    if mips {
        flags |= DDSD_MIPMAPCOUNT;
    }
    put(&mut out, flags);
    put(&mut out, h0);
    put(&mut out, w0);
    // Level 0 of a u32-sized texture can exceed u32 bytes only beyond
    // 2^17 texels a side; saturate rather than wrap.
    put(
        &mut out,
        u32::try_from(level_bytes(w0, h0) * if bc3 { 2 } else { 1 }).unwrap_or(u32::MAX),
    );
    put(&mut out, 0); // depth
    put(&mut out, if mips { levels.len() as u32 } else { 0 });
    for _ in 0..11 {
        put(&mut out, 0);
    }
    put(&mut out, PIXELFORMAT_SIZE);
    put(&mut out, DDPF_FOURCC);
    out.extend_from_slice(match (dx10, bc3) {
        (true, _) => FOURCC_DX10,
        (false, false) => FOURCC_DXT1,
        (false, true) => FOURCC_DXT5,
    });
    for _ in 0..5 {
        put(&mut out, 0); // bit count and masks
    }
    let mut caps = DDSCAPS_TEXTURE;
    if mips {
        caps |= DDSCAPS_COMPLEX | DDSCAPS_MIPMAP;
    }
    put(&mut out, caps);
    for _ in 0..4 {
        put(&mut out, 0); // caps2, caps3, caps4, reserved2
    }
    if let DdsHeaderKind::Dx10 { srgb } = header {
        put(
            &mut out,
            match (bc3, srgb) {
                (false, false) => DXGI_FORMAT_BC1_UNORM,
                (false, true) => DXGI_FORMAT_BC1_UNORM_SRGB,
                (true, false) => DXGI_FORMAT_BC3_UNORM,
                (true, true) => DXGI_FORMAT_BC3_UNORM_SRGB,
            },
        );
        put(&mut out, D3D10_RESOURCE_DIMENSION_TEXTURE2D);
        put(&mut out, 0); // misc flags
        put(&mut out, 1); // array size
        put(&mut out, 0); // misc flags 2: alpha mode unknown
    }
    for lvl in levels {
        for (k, b) in lvl.blocks.iter().enumerate() {
            if let Some(a) = lvl.alpha.get(k) {
                out.extend_from_slice(&a.to_bytes());
            }
            out.extend_from_slice(&b.to_bytes());
        }
    }
    Ok(out)
}

fn u32_at(bytes: &[u8], off: usize) -> u32 {
    let mut w = [0u8; 4];
    if let Some(s) = bytes.get(off..off + 4) {
        w.copy_from_slice(s);
    }
    u32::from_le_bytes(w)
}

/// Reads a BC1 or BC3 DDS file (legacy `DXT1`/`DXT5` or DX10
/// `BC1_UNORM[_SRGB]`/`BC3_UNORM[_SRGB]`).
pub fn read_dds(bytes: &[u8]) -> Result<DdsImage, DdsError> {
    if bytes.len() < 128 {
        return Err(DdsError::Truncated { len: bytes.len() });
    }
    if &bytes[0..4] != MAGIC {
        return Err(DdsError::BadMagic);
    }
    if u32_at(bytes, 4) != HEADER_SIZE {
        return Err(DdsError::BadHeader("header size is not 124"));
    }
    let flags = u32_at(bytes, 8);
    let height = u32_at(bytes, 12);
    let width = u32_at(bytes, 16);
    if width == 0 || height == 0 {
        return Err(DdsError::BadHeader("zero width or height"));
    }
    let mip_count = u32_at(bytes, 28);
    if u32_at(bytes, 76) != PIXELFORMAT_SIZE {
        return Err(DdsError::BadHeader("pixel format size is not 32"));
    }
    if u32_at(bytes, 80) & DDPF_FOURCC == 0 {
        return Err(DdsError::BadHeader("pixel format has no FourCC"));
    }
    let mut fourcc = [0u8; 4];
    fourcc.copy_from_slice(&bytes[84..88]);
    let (header, data_start, bc3) = if &fourcc == FOURCC_DXT1 || &fourcc == FOURCC_DXT5 {
        (DdsHeaderKind::Legacy, 128, &fourcc == FOURCC_DXT5)
    } else if &fourcc == FOURCC_DX10 {
        if bytes.len() < 128 + DX10_HEADER_LEN {
            return Err(DdsError::Truncated { len: bytes.len() });
        }
        let (bc3, srgb) = match u32_at(bytes, 128) {
            DXGI_FORMAT_BC1_UNORM => (false, false),
            DXGI_FORMAT_BC1_UNORM_SRGB => (false, true),
            DXGI_FORMAT_BC3_UNORM => (true, false),
            DXGI_FORMAT_BC3_UNORM_SRGB => (true, true),
            f => return Err(DdsError::Dx10Format(f)),
        };
        if u32_at(bytes, 132) != D3D10_RESOURCE_DIMENSION_TEXTURE2D || u32_at(bytes, 140) != 1 {
            return Err(DdsError::Dx10Layout);
        }
        (DdsHeaderKind::Dx10 { srgb }, 128 + DX10_HEADER_LEN, bc3)
    } else {
        return Err(DdsError::NotBc1(fourcc));
    };
    let scale = if bc3 { 2 } else { 1 };
    let count = if flags & DDSD_MIPMAPCOUNT != 0 && mip_count > 1 {
        mip_count as usize
    } else {
        1
    };
    let max = full_chain_len(width, height);
    if count > max {
        return Err(DdsError::TooManyLevels {
            count,
            width,
            height,
            max,
        });
    }
    let data = &bytes[data_start..];
    let need = (0..count).fold(0usize, |acc, k| {
        let (w, h) = mip_size(width, height, k);
        acc.saturating_add(level_bytes(w, h).saturating_mul(scale))
    });
    if data.len() != need {
        return Err(DdsError::DataSize {
            got: data.len(),
            need,
        });
    }
    let mut levels = Vec::with_capacity(count);
    let mut off = 0;
    for k in 0..count {
        let (w, h) = mip_size(width, height, k);
        let n = level_bytes(w, h) * scale;
        let eight = |c: &[u8]| {
            let mut b = [0u8; 8];
            b.copy_from_slice(c);
            b
        };
        let mut blocks = Vec::with_capacity(n / 8 / scale);
        let mut alpha = Vec::new();
        for c in data[off..off + n].chunks_exact(8 * scale) {
            if bc3 {
                alpha.push(AlphaBlock::from_bytes(eight(&c[..8])));
            }
            blocks.push(Block::from_bytes(eight(&c[8 * (scale - 1)..])));
        }
        off += n;
        levels.push(MipLevel {
            width: w,
            height: h,
            blocks,
            alpha,
        });
    }
    Ok(DdsImage { header, levels })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bc1::{encode_image, Level};

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
        wrong[128..132].copy_from_slice(&98u32.to_le_bytes());
        assert_eq!(read_dds(&wrong), Err(DdsError::Dx10Format(98)));
        let mut dxt3 = bytes;
        dxt3[84..88].copy_from_slice(b"DXT3");
        assert_eq!(read_dds(&dxt3), Err(DdsError::NotBc1(*b"DXT3")));
        assert_eq!(read_dds(b"not a dds"), Err(DdsError::Truncated { len: 9 }));
    }
}
