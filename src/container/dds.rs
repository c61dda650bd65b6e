//! DDS files (Microsoft, "DDS Programming Guide": DDS_HEADER,
//! DDS_PIXELFORMAT, DDS_HEADER_DXT10): 'DDS ' + the 124-byte header, with
//! FourCC `DXT1` (BC1) or `DXT5` (BC3), or FourCC `DX10` + the 20-byte DX10
//! header naming a DXGI format: BC1_UNORM (71) / BC1_UNORM_SRGB (72),
//! BC3_UNORM (77) / BC3_UNORM_SRGB (78), BC7_UNORM (98) / BC7_UNORM_SRGB
//! (99). Then every mip level, level 0 first, each its blocks row-major
//! with no padding.
//!
//! BC7 has no FourCC, so it is always written with the DX10 header. A
//! legacy header cannot say sRGB or linear: such files are read as
//! [`ColorSpace::Linear`], what Direct3D makes of `DXT1`/`DXT5`.
//!
//! The reader accepts what the writer produces (and the same layout from
//! other writers); anything else is an error, never a panic.

use super::{
    check_shape, level_byte_len, mip_size, u32_at, BlockFormat, ColorSpace, ContainerError,
    EncodedTexture,
};

const MAGIC: &[u8; 4] = b"DDS ";
const HEADER_SIZE: u32 = 124;
const PIXELFORMAT_SIZE: u32 = 32;
const DX10_HEADER_LEN: usize = 20;
/// Magic and header.
const LEGACY_LEN: usize = 4 + HEADER_SIZE as usize;

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
pub const DXGI_FORMAT_BC7_UNORM: u32 = 98;
pub const DXGI_FORMAT_BC7_UNORM_SRGB: u32 = 99;
const D3D10_RESOURCE_DIMENSION_TEXTURE2D: u32 = 3;

/// Which header a DDS file carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DdsHeader {
    /// FourCC `DXT1` or `DXT5`, read by every DDS reader; BC1 and BC3
    /// only, colour space unsaid.
    Legacy,
    /// FourCC `DX10` and the DX10 header, whose DXGI format says sRGB or
    /// linear.
    Dx10,
}

/// A DDS file read back.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DdsFile {
    pub header: DdsHeader,
    pub texture: EncodedTexture,
}

/// The DXGI format of `format` in `color_space`.
pub fn dxgi_format(format: BlockFormat, color_space: ColorSpace) -> u32 {
    let srgb = color_space == ColorSpace::Srgb;
    match (format, srgb) {
        (BlockFormat::Bc1, false) => DXGI_FORMAT_BC1_UNORM,
        (BlockFormat::Bc1, true) => DXGI_FORMAT_BC1_UNORM_SRGB,
        (BlockFormat::Bc3, false) => DXGI_FORMAT_BC3_UNORM,
        (BlockFormat::Bc3, true) => DXGI_FORMAT_BC3_UNORM_SRGB,
        (BlockFormat::Bc7, false) => DXGI_FORMAT_BC7_UNORM,
        (BlockFormat::Bc7, true) => DXGI_FORMAT_BC7_UNORM_SRGB,
    }
}

fn from_dxgi(format: u32) -> Option<(BlockFormat, ColorSpace)> {
    BlockFormat::ALL
        .into_iter()
        .flat_map(|f| [(f, ColorSpace::Linear), (f, ColorSpace::Srgb)])
        .find(|&(f, c)| dxgi_format(f, c) == format)
}

/// Writes `tex` as a DDS file. More than one level makes a mip chain.
pub fn write_dds(tex: &EncodedTexture, header: DdsHeader) -> Result<Vec<u8>, ContainerError> {
    tex.validate()?;
    let fourcc = match (header, tex.format) {
        (DdsHeader::Dx10, _) => FOURCC_DX10,
        (DdsHeader::Legacy, BlockFormat::Bc1) => FOURCC_DXT1,
        (DdsHeader::Legacy, BlockFormat::Bc3) => FOURCC_DXT5,
        (DdsHeader::Legacy, BlockFormat::Bc7) => {
            return Err(ContainerError::LegacyHeader(BlockFormat::Bc7))
        }
    };
    let mips = tex.levels.len() > 1;
    let dx10 = header == DdsHeader::Dx10;
    let data_len: usize = tex.levels.iter().map(Vec::len).sum();
    let mut out =
        Vec::with_capacity(LEGACY_LEN + if dx10 { DX10_HEADER_LEN } else { 0 } + data_len);
    let put = |out: &mut Vec<u8>, v: u32| out.extend_from_slice(&v.to_le_bytes());

    out.extend_from_slice(MAGIC);
    put(&mut out, HEADER_SIZE);
    let mut flags = DDSD_CAPS | DDSD_HEIGHT | DDSD_WIDTH | DDSD_PIXELFORMAT | DDSD_LINEARSIZE;
    if mips {
        flags |= DDSD_MIPMAPCOUNT;
    }
    put(&mut out, flags);
    put(&mut out, tex.height);
    put(&mut out, tex.width);
    // Level 0's bytes: under 2^32 within MAX_SIDE, saturated all the same.
    put(
        &mut out,
        u32::try_from(tex.levels[0].len()).unwrap_or(u32::MAX),
    );
    put(&mut out, 0); // depth
    put(&mut out, if mips { tex.levels.len() as u32 } else { 0 });
    for _ in 0..11 {
        put(&mut out, 0); // reserved1
    }
    put(&mut out, PIXELFORMAT_SIZE);
    put(&mut out, DDPF_FOURCC);
    out.extend_from_slice(fourcc);
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
    if dx10 {
        put(&mut out, dxgi_format(tex.format, tex.color_space));
        put(&mut out, D3D10_RESOURCE_DIMENSION_TEXTURE2D);
        put(&mut out, 0); // misc flags
        put(&mut out, 1); // array size
        put(&mut out, 0); // misc flags 2: alpha mode unknown
    }
    for data in &tex.levels {
        out.extend_from_slice(data);
    }
    Ok(out)
}

/// Reads a BC1, BC3 or BC7 DDS file (legacy `DXT1`/`DXT5`, or DX10 with
/// one of the six DXGI formats of [`dxgi_format`]).
pub fn read_dds(bytes: &[u8]) -> Result<DdsFile, ContainerError> {
    if bytes.len() < LEGACY_LEN {
        return Err(ContainerError::Truncated {
            what: "DDS header",
            len: bytes.len(),
            need: LEGACY_LEN,
        });
    }
    if &bytes[0..4] != MAGIC {
        return Err(ContainerError::DdsMagic);
    }
    if u32_at(bytes, 4) != HEADER_SIZE {
        return Err(ContainerError::DdsHeader("header size is not 124"));
    }
    let flags = u32_at(bytes, 8);
    let height = u32_at(bytes, 12);
    let width = u32_at(bytes, 16);
    let mip_count = u32_at(bytes, 28);
    if u32_at(bytes, 76) != PIXELFORMAT_SIZE {
        return Err(ContainerError::DdsHeader("pixel format size is not 32"));
    }
    if u32_at(bytes, 80) & DDPF_FOURCC == 0 {
        return Err(ContainerError::DdsHeader("pixel format has no FourCC"));
    }
    let mut fourcc = [0u8; 4];
    fourcc.copy_from_slice(&bytes[84..88]);
    let (header, format, color_space, data_start) = if &fourcc == FOURCC_DXT1 {
        (
            DdsHeader::Legacy,
            BlockFormat::Bc1,
            ColorSpace::Linear,
            LEGACY_LEN,
        )
    } else if &fourcc == FOURCC_DXT5 {
        (
            DdsHeader::Legacy,
            BlockFormat::Bc3,
            ColorSpace::Linear,
            LEGACY_LEN,
        )
    } else if &fourcc == FOURCC_DX10 {
        let need = LEGACY_LEN + DX10_HEADER_LEN;
        if bytes.len() < need {
            return Err(ContainerError::Truncated {
                what: "DDS DX10 header",
                len: bytes.len(),
                need,
            });
        }
        let dxgi = u32_at(bytes, LEGACY_LEN);
        let (format, color_space) = from_dxgi(dxgi).ok_or(ContainerError::DxgiFormat(dxgi))?;
        if u32_at(bytes, LEGACY_LEN + 4) != D3D10_RESOURCE_DIMENSION_TEXTURE2D
            || u32_at(bytes, LEGACY_LEN + 12) != 1
        {
            return Err(ContainerError::Dx10Layout);
        }
        (DdsHeader::Dx10, format, color_space, need)
    } else {
        return Err(ContainerError::DdsFourCc(fourcc));
    };
    if width == 0 || height == 0 {
        return Err(ContainerError::DdsHeader("zero width or height"));
    }
    // Some writers set the count without the flag, or 1 with it.
    let count = if flags & DDSD_MIPMAPCOUNT != 0 && mip_count > 1 {
        mip_count as usize
    } else {
        1
    };
    check_shape(width, height, count)?;
    let data = &bytes[data_start..];
    let sizes: Vec<usize> = (0..count)
        .map(|k| {
            let (w, h) = mip_size(width, height, k);
            level_byte_len(format, w, h)
        })
        .collect();
    let need = sizes.iter().sum();
    if data.len() != need {
        return Err(ContainerError::DataSize {
            got: data.len(),
            need,
        });
    }
    let mut levels = Vec::with_capacity(count);
    let mut off = 0;
    for n in sizes {
        levels.push(data[off..off + n].to_vec());
        off += n;
    }
    Ok(DdsFile {
        header,
        texture: EncodedTexture {
            format,
            color_space,
            width,
            height,
            levels,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(format: BlockFormat, color_space: ColorSpace, w: u32, h: u32) -> EncodedTexture {
        let levels = (0..super::super::full_chain_len(w, h))
            .map(|k| {
                let (lw, lh) = mip_size(w, h, k);
                (0..level_byte_len(format, lw, lh))
                    .map(|i| (i * 31 + k * 7) as u8)
                    .collect()
            })
            .collect();
        EncodedTexture {
            format,
            color_space,
            width: w,
            height: h,
            levels,
        }
    }

    #[test]
    fn bc7_uses_the_dx10_header() {
        for (cs, dxgi) in [
            (ColorSpace::Srgb, DXGI_FORMAT_BC7_UNORM_SRGB),
            (ColorSpace::Linear, DXGI_FORMAT_BC7_UNORM),
        ] {
            let t = texture(BlockFormat::Bc7, cs, 13, 6);
            let bytes = write_dds(&t, DdsHeader::Dx10).unwrap();
            assert_eq!(&bytes[84..88], b"DX10");
            assert_eq!(u32_at(&bytes, 128), dxgi);
            assert_eq!(u32_at(&bytes, 132), 3);
            assert_eq!(u32_at(&bytes, 140), 1);
            // Linear size: level 0's bytes, 16 a block.
            assert_eq!(u32_at(&bytes, 20), 4 * 2 * 16);
            assert_eq!(u32_at(&bytes, 28), 4);
            // Blocks of 13x6, 6x3, 3x1, 1x1.
            let blocks = [8, 2, 1, 1];
            assert_eq!(bytes.len(), 148 + blocks.iter().sum::<usize>() * 16);
            let back = read_dds(&bytes).unwrap();
            assert_eq!(back.header, DdsHeader::Dx10);
            assert_eq!(back.texture, t);
            assert_eq!(
                write_dds(&t, DdsHeader::Legacy),
                Err(ContainerError::LegacyHeader(BlockFormat::Bc7))
            );
        }
    }

    #[test]
    fn every_format_round_trips() {
        for format in BlockFormat::ALL {
            for cs in [ColorSpace::Srgb, ColorSpace::Linear] {
                for (w, h) in [(1, 1), (5, 3), (64, 16)] {
                    let mut t = texture(format, cs, w, h);
                    let back = read_dds(&write_dds(&t, DdsHeader::Dx10).unwrap()).unwrap();
                    assert_eq!(back.texture, t);
                    t.levels.truncate(1);
                    let back = read_dds(&write_dds(&t, DdsHeader::Dx10).unwrap()).unwrap();
                    assert_eq!(back.texture, t);
                    if format != BlockFormat::Bc7 {
                        let bytes = write_dds(&t, DdsHeader::Legacy).unwrap();
                        let back = read_dds(&bytes).unwrap();
                        assert_eq!(back.header, DdsHeader::Legacy);
                        assert_eq!(back.texture.color_space, ColorSpace::Linear);
                        assert_eq!(back.texture.levels, t.levels);
                    }
                }
            }
        }
    }

    #[test]
    fn reader_names_the_damage() {
        let t = texture(BlockFormat::Bc7, ColorSpace::Srgb, 20, 12);
        let bytes = write_dds(&t, DdsHeader::Dx10).unwrap();
        for cut in 0..bytes.len() {
            assert!(read_dds(&bytes[..cut]).is_err());
        }
        let mut wrong = bytes.clone();
        wrong[128..132].copy_from_slice(&97u32.to_le_bytes());
        assert_eq!(read_dds(&wrong), Err(ContainerError::DxgiFormat(97)));
        let mut huge = bytes.clone();
        huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            read_dds(&huge),
            Err(ContainerError::Dimensions { .. })
        ));
        let mut levels = bytes.clone();
        levels[28..32].copy_from_slice(&9u32.to_le_bytes());
        assert!(matches!(
            read_dds(&levels),
            Err(ContainerError::TooManyLevels { max: 5, .. })
        ));
        let mut extra = bytes;
        extra.push(0);
        assert!(matches!(
            read_dds(&extra),
            Err(ContainerError::DataSize { .. })
        ));
    }
}
