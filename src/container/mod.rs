//! Texture containers for block-compressed textures: DDS ([`dds`]) and
//! KTX 2.0 ([`ktx2`]), over one format-neutral description of what they
//! hold, [`EncodedTexture`].
//!
//! Block layout, common to BC1, BC3 and BC7 (Microsoft, "Texture Block
//! Compression in Direct3D 11"; Khronos Data Format Specification 1.3,
//! §§ 19–21): a level of w×h texels is ⌈w/4⌉×⌈h/4⌉ blocks of 4×4 texels,
//! row-major from the top-left, each 8 bytes (BC1) or 16 bytes (BC3,
//! BC7); level k is level 0 halved k times, rounding down, at least 1.
//!
//! The containers only carry bytes: whether a block is a good encoding is
//! the encoders' business, never checked here.

pub mod dds;
pub mod ktx2;

use std::fmt;

use crate::bc1::alpha::AlphaBlock;
use crate::bc1::dds::MipLevel;
use crate::bc1::Block;

/// The largest width or height read or written. Vulkan's desktop GPUs stop
/// at 32768 (D3D at 16384); the bound keeps what a damaged or hostile
/// header can make a reader allocate to about 1.4 GiB (a BC7 chain).
pub const MAX_SIDE: u32 = 32768;

/// How the texels are packed into blocks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BlockFormat {
    /// BC1 (DXT1): 8 bytes a block; colour only, or one-bit alpha through
    /// three-colour blocks.
    Bc1,
    /// BC3 (DXT5): 16 bytes a block, an alpha block then a BC1 colour
    /// block (decoded in four-colour mode).
    Bc3,
    /// BC7: 16 bytes a block.
    Bc7,
}

impl BlockFormat {
    pub const ALL: [BlockFormat; 3] = [BlockFormat::Bc1, BlockFormat::Bc3, BlockFormat::Bc7];

    /// Bytes in one 4×4 block.
    pub const fn block_bytes(self) -> usize {
        match self {
            BlockFormat::Bc1 => 8,
            BlockFormat::Bc3 | BlockFormat::Bc7 => 16,
        }
    }

    pub const fn name(self) -> &'static str {
        match self {
            BlockFormat::Bc1 => "BC1",
            BlockFormat::Bc3 => "BC3",
            BlockFormat::Bc7 => "BC7",
        }
    }
}

impl fmt::Display for BlockFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// How the decoded values map to colours: sRGB-encoded (base colour and
/// emissive textures in glTF) or linear (every other texture), which
/// decides whether the GPU decodes through the sRGB curve when sampling.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ColorSpace {
    Srgb,
    Linear,
}

/// A block-compressed texture, whichever container it came from or goes to.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EncodedTexture {
    pub format: BlockFormat,
    pub color_space: ColorSpace,
    /// Level 0's size in texels.
    pub width: u32,
    pub height: u32,
    /// Level 0 first; each its blocks' bytes, row-major
    /// ([`level_byte_len`] of them).
    pub levels: Vec<Vec<u8>>,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ContainerError {
    #[error("no mip levels to write")]
    NoLevels,
    #[error("texture is {width}x{height}; each side must be 1 to {max} texels")]
    Dimensions { width: u32, height: u32, max: u32 },
    #[error("{count} mip levels; a {width}x{height} texture has at most {max}")]
    TooManyLevels {
        count: usize,
        width: u32,
        height: u32,
        max: usize,
    },
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
    #[error("mip level {level} has {got} alpha blocks; {need} expected (every level or none)")]
    AlphaBlocks {
        level: usize,
        got: usize,
        need: usize,
    },
    #[error("mip level {level} has {got} bytes of blocks; {need} expected")]
    LevelBytes {
        level: usize,
        got: usize,
        need: usize,
    },
    #[error("{0} blocks are not BC1 or BC3 blocks")]
    NotBc1OrBc3(BlockFormat),
    #[error("a legacy DDS header (FourCC) cannot hold {0}; use the DX10 header")]
    LegacyHeader(BlockFormat),
    #[error("zstd level {0} is out of range; 1 to 22")]
    ZstdLevel(i32),
    #[error("zstd: {0}")]
    Zstd(String),
    #[error("{what}: file is {len} bytes; {need} needed")]
    Truncated {
        what: &'static str,
        len: usize,
        need: usize,
    },
    #[error("not a DDS file (bad magic)")]
    DdsMagic,
    #[error("bad DDS header: {0}")]
    DdsHeader(&'static str),
    #[error("DDS pixel format is not BC1, BC3 or BC7 (FourCC {0:?})")]
    DdsFourCc([u8; 4]),
    #[error("DDS DX10 header: DXGI format {0} is not BC1, BC3 or BC7 (UNORM or UNORM_SRGB)")]
    DxgiFormat(u32),
    #[error("DDS DX10 header: only single 2D textures are supported")]
    Dx10Layout,
    #[error("pixel data is {got} bytes; {need} expected")]
    DataSize { got: usize, need: usize },
    #[error("not a KTX 2.0 file (bad identifier)")]
    Ktx2Identifier,
    #[error("bad KTX2 header: {0}")]
    Ktx2Header(String),
    #[error("KTX2 vkFormat {0} is not BC1, BC3 or BC7 (UNORM or SRGB)")]
    VkFormat(u32),
    #[error("KTX2 supercompression scheme {0} is not supported (0, none, or 2, Zstandard)")]
    Supercompression(u32),
    #[error("KTX2 level index, level {level}: {problem}")]
    LevelIndex { level: usize, problem: String },
    #[error("bad KTX2 data format descriptor: {0}")]
    Dfd(String),
    #[error("bad KTX2 key/value data: {0}")]
    KeyValue(String),
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

/// Blocks across and down a `width`×`height` level.
pub fn block_counts(width: u32, height: u32) -> (usize, usize) {
    (
        width.div_ceil(4).max(1) as usize,
        height.div_ceil(4).max(1) as usize,
    )
}

/// Bytes of blocks in one `width`×`height` level (saturating; sides of
/// [`MAX_SIDE`] or less never saturate).
pub fn level_byte_len(format: BlockFormat, width: u32, height: u32) -> usize {
    let (bw, bh) = block_counts(width, height);
    bw.saturating_mul(bh).saturating_mul(format.block_bytes())
}

/// Checks that sides are within 1..=[`MAX_SIDE`] and that `count` levels
/// fit a mip chain.
fn check_shape(width: u32, height: u32, count: usize) -> Result<(), ContainerError> {
    if !(1..=MAX_SIDE).contains(&width) || !(1..=MAX_SIDE).contains(&height) {
        return Err(ContainerError::Dimensions {
            width,
            height,
            max: MAX_SIDE,
        });
    }
    let max = full_chain_len(width, height);
    if count > max {
        return Err(ContainerError::TooManyLevels {
            count,
            width,
            height,
            max,
        });
    }
    Ok(())
}

impl EncodedTexture {
    /// Size of level `level` in texels.
    pub fn level_size(&self, level: usize) -> (u32, u32) {
        mip_size(self.width, self.height, level)
    }

    /// Checks what every writer relies on: at least one level, sides
    /// within bounds, no more levels than the chain has, and each level
    /// exactly its blocks' bytes.
    pub fn validate(&self) -> Result<(), ContainerError> {
        if self.levels.is_empty() {
            return Err(ContainerError::NoLevels);
        }
        check_shape(self.width, self.height, self.levels.len())?;
        for (k, data) in self.levels.iter().enumerate() {
            let (w, h) = self.level_size(k);
            let need = level_byte_len(self.format, w, h);
            if data.len() != need {
                return Err(ContainerError::LevelBytes {
                    level: k,
                    got: data.len(),
                    need,
                });
            }
        }
        Ok(())
    }

    /// BC1 levels (no alpha blocks) or BC3 levels (alpha blocks on every
    /// level) as this crate's encoders make them. Level k must be level 0
    /// halved k times.
    pub fn from_mip_levels(
        levels: &[MipLevel],
        color_space: ColorSpace,
    ) -> Result<EncodedTexture, ContainerError> {
        let first = levels.first().ok_or(ContainerError::NoLevels)?;
        let (w0, h0) = (first.width, first.height);
        check_shape(w0, h0, levels.len())?;
        let bc3 = !first.alpha.is_empty();
        let format = if bc3 {
            BlockFormat::Bc3
        } else {
            BlockFormat::Bc1
        };
        let mut out = Vec::with_capacity(levels.len());
        for (k, lvl) in levels.iter().enumerate() {
            let (ew, eh) = mip_size(w0, h0, k);
            if (lvl.width, lvl.height) != (ew, eh) {
                return Err(ContainerError::LevelSize {
                    level: k,
                    width: lvl.width,
                    height: lvl.height,
                    expected_width: ew,
                    expected_height: eh,
                });
            }
            let (bw, bh) = block_counts(ew, eh);
            let need = bw * bh;
            if lvl.blocks.len() != need {
                return Err(ContainerError::LevelBlocks {
                    level: k,
                    got: lvl.blocks.len(),
                    need,
                });
            }
            let alpha_need = if bc3 { need } else { 0 };
            if lvl.alpha.len() != alpha_need {
                return Err(ContainerError::AlphaBlocks {
                    level: k,
                    got: lvl.alpha.len(),
                    need: alpha_need,
                });
            }
            let mut data = Vec::with_capacity(need * format.block_bytes());
            for (i, b) in lvl.blocks.iter().enumerate() {
                if let Some(a) = lvl.alpha.get(i) {
                    data.extend_from_slice(&a.to_bytes());
                }
                data.extend_from_slice(&b.to_bytes());
            }
            out.push(data);
        }
        Ok(EncodedTexture {
            format,
            color_space,
            width: w0,
            height: h0,
            levels: out,
        })
    }

    /// The levels as this crate's BC1/BC3 types; BC7 has none.
    pub fn to_mip_levels(&self) -> Result<Vec<MipLevel>, ContainerError> {
        let bc3 = match self.format {
            BlockFormat::Bc1 => false,
            BlockFormat::Bc3 => true,
            BlockFormat::Bc7 => return Err(ContainerError::NotBc1OrBc3(self.format)),
        };
        self.validate()?;
        let eight = |c: &[u8]| {
            let mut b = [0u8; 8];
            b.copy_from_slice(c);
            b
        };
        Ok(self
            .levels
            .iter()
            .enumerate()
            .map(|(k, data)| {
                let (width, height) = self.level_size(k);
                let mut blocks = Vec::new();
                let mut alpha = Vec::new();
                for c in data.chunks_exact(self.format.block_bytes()) {
                    if bc3 {
                        alpha.push(AlphaBlock::from_bytes(eight(&c[..8])));
                    }
                    blocks.push(Block::from_bytes(eight(&c[c.len() - 8..])));
                }
                MipLevel {
                    width,
                    height,
                    blocks,
                    alpha,
                }
            })
            .collect())
    }

    /// Whether any BC1 block decodes a transparent texel: a three-colour
    /// block (c0 ≤ c1) with an index 3 (punch-through alpha, `MASK`
    /// textures). False for BC3 and BC7, whose alpha is always there.
    pub fn bc1_punches_through(&self) -> bool {
        self.format == BlockFormat::Bc1
            && self.levels.iter().any(|data| {
                data.chunks_exact(8).any(|c| {
                    let c0 = u16::from_le_bytes([c[0], c[1]]);
                    let c1 = u16::from_le_bytes([c[2], c[3]]);
                    let idx = u32::from_le_bytes([c[4], c[5], c[6], c[7]]);
                    c0 <= c1 && (0..16).any(|t| (idx >> (2 * t)) & 3 == 3)
                })
            })
    }
}

/// Little-endian u32 at `off`; 0 past the end (callers check lengths).
fn u32_at(bytes: &[u8], off: usize) -> u32 {
    let mut w = [0u8; 4];
    if let Some(s) = off.checked_add(4).and_then(|end| bytes.get(off..end)) {
        w.copy_from_slice(s);
    }
    u32::from_le_bytes(w)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bc1_block(c0: u16, c1: u16, indices: u32) -> Vec<u8> {
        Block { c0, c1, indices }.to_bytes().to_vec()
    }

    #[test]
    fn level_sizes_halve_and_round_up_to_blocks() {
        assert_eq!(full_chain_len(211, 97), 8);
        assert_eq!(full_chain_len(1, 1), 1);
        assert_eq!(mip_size(211, 97, 1), (105, 48));
        assert_eq!(mip_size(211, 97, 7), (1, 1));
        assert_eq!(level_byte_len(BlockFormat::Bc1, 5, 3), 2 * 8);
        assert_eq!(level_byte_len(BlockFormat::Bc7, 1, 1), 16);
        assert_eq!(level_byte_len(BlockFormat::Bc3, 211, 97), 53 * 25 * 16);
    }

    #[test]
    fn validate_names_the_problem() {
        let mut t = EncodedTexture {
            format: BlockFormat::Bc7,
            color_space: ColorSpace::Linear,
            width: 8,
            height: 4,
            levels: vec![vec![0; 32], vec![0; 16], vec![0; 16], vec![0; 16]],
        };
        assert_eq!(t.validate(), Ok(()));
        t.levels[1].pop();
        assert_eq!(
            t.validate(),
            Err(ContainerError::LevelBytes {
                level: 1,
                got: 15,
                need: 16
            })
        );
        t.levels[1].push(0);
        t.levels.push(vec![0; 16]);
        assert!(matches!(
            t.validate(),
            Err(ContainerError::TooManyLevels { max: 4, .. })
        ));
        t.levels.clear();
        assert_eq!(t.validate(), Err(ContainerError::NoLevels));
        t.levels.push(vec![0; 16]);
        t.width = MAX_SIDE + 1;
        assert!(matches!(
            t.validate(),
            Err(ContainerError::Dimensions { .. })
        ));
    }

    #[test]
    fn mip_levels_convert_both_ways() {
        let blocks = |n: usize, k: u16| -> Vec<Block> {
            (0..n)
                .map(|i| Block {
                    c0: 0xF800 | i as u16,
                    c1: k,
                    indices: (i as u32).wrapping_mul(0x9E37_79B9),
                })
                .collect()
        };
        let bc1 = vec![
            MipLevel {
                width: 9,
                height: 5,
                blocks: blocks(6, 1),
                alpha: vec![],
            },
            MipLevel {
                width: 4,
                height: 2,
                blocks: blocks(1, 2),
                alpha: vec![],
            },
        ];
        let t = EncodedTexture::from_mip_levels(&bc1, ColorSpace::Srgb).unwrap();
        assert_eq!(t.format, BlockFormat::Bc1);
        assert_eq!(t.levels[0][..8], bc1[0].blocks[0].to_bytes());
        assert_eq!(t.to_mip_levels().unwrap(), bc1);

        let mut bc3 = bc1.clone();
        for l in &mut bc3 {
            l.alpha = (0..l.blocks.len())
                .map(|i| AlphaBlock::with_indices(i as u8, 200, &[(i % 8) as u8; 16]))
                .collect();
        }
        let t = EncodedTexture::from_mip_levels(&bc3, ColorSpace::Linear).unwrap();
        assert_eq!(t.format, BlockFormat::Bc3);
        // Alpha block first, then the colour block.
        assert_eq!(t.levels[0][..8], bc3[0].alpha[0].to_bytes());
        assert_eq!(t.levels[0][8..16], bc3[0].blocks[0].to_bytes());
        assert_eq!(t.to_mip_levels().unwrap(), bc3);

        let bc7 = EncodedTexture {
            format: BlockFormat::Bc7,
            ..t
        };
        assert_eq!(
            bc7.to_mip_levels(),
            Err(ContainerError::NotBc1OrBc3(BlockFormat::Bc7))
        );
    }

    #[test]
    fn punch_through_is_index_three_of_a_three_colour_block() {
        let tex = |data: Vec<u8>| EncodedTexture {
            format: BlockFormat::Bc1,
            color_space: ColorSpace::Srgb,
            width: 4,
            height: 4,
            levels: vec![data],
        };
        // Four-colour block: index 3 is a colour.
        assert!(!tex(bc1_block(0xFFFF, 0x0000, u32::MAX)).bc1_punches_through());
        // Three-colour block without index 3: opaque.
        assert!(!tex(bc1_block(0x0000, 0xFFFF, 0xAAAA_AAAA)).bc1_punches_through());
        // Three-colour block with one index 3: a transparent texel.
        assert!(tex(bc1_block(0x1234, 0x1234, 0b11 << 30)).bc1_punches_through());
        let mut bc7 = tex(vec![0xFF; 16]);
        bc7.format = BlockFormat::Bc7;
        assert!(!bc7.bc1_punches_through());
    }
}
