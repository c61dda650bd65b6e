//! A texture's block-compressed file: its levels' blocks, in the container
//! the options name (DDS, or KTX2 with optional Zstandard).

use super::{Container, PipelineError, ProcessOptions};
use crate::bc1::dds::MipLevel;
use crate::bc7;
use crate::container::dds::{write_dds, DdsHeader};
use crate::container::ktx2::write_ktx2;
use crate::container::{BlockFormat, ColorSpace, EncodedTexture};
use crate::model::TextureBinding;

/// One mip level's blocks, as the file holds them.
pub(super) enum Shipped {
    /// BC1, or BC3 where it carries alpha blocks.
    Bc1(MipLevel),
    Bc7 {
        width: u32,
        height: u32,
        blocks: Vec<bc7::Block>,
    },
}

/// The file of `levels` (level 0 first): its name and its bytes.
pub(super) fn texture_file(
    b: &TextureBinding,
    levels: Vec<Shipped>,
    opts: &ProcessOptions,
) -> Result<(String, Vec<u8>), PipelineError> {
    let color_space = color_space(b);
    let fail = |e| PipelineError::encode(&b.name, e);
    let texture = encoded(levels, color_space).map_err(fail)?;
    let (extension, bytes) = match opts.container {
        Container::Dds => {
            // BC7 exists only under the DX10 header; BC1 and BC3 keep the
            // legacy one, which every reader takes, unless asked.
            let header = if opts.dx10 || texture.format == BlockFormat::Bc7 {
                DdsHeader::Dx10
            } else {
                DdsHeader::Legacy
            };
            ("dds", write_dds(&texture, header).map_err(fail)?)
        }
        Container::Ktx2 => {
            let zstd = (opts.zstd > 0).then_some(i32::from(opts.zstd));
            ("ktx2", write_ktx2(&texture, zstd).map_err(fail)?)
        }
    };
    Ok((format!("{}.{extension}", b.name), bytes))
}

/// `<name>.regular.dds`: level 0's regular BC1 (or BC3) encoding, a DDS
/// with the legacy header whatever the job's container, since it exists
/// for the view page, whose loader reads DDS.
pub(super) fn regular_file(
    b: &TextureBinding,
    level: MipLevel,
) -> Result<(String, Vec<u8>), PipelineError> {
    let color_space = color_space(b);
    let fail = |e| PipelineError::encode(&b.name, e);
    let texture = encoded(vec![Shipped::Bc1(level)], color_space).map_err(fail)?;
    let bytes = write_dds(&texture, DdsHeader::Legacy).map_err(fail)?;
    Ok((format!("{}.regular.dds", b.name), bytes))
}

/// How the texture's values are encoded: sRGB for colour (base colour,
/// emissive), linear for data.
fn color_space(b: &TextureBinding) -> ColorSpace {
    if b.srgb {
        ColorSpace::Srgb
    } else {
        ColorSpace::Linear
    }
}

fn encoded(
    levels: Vec<Shipped>,
    color_space: ColorSpace,
) -> Result<EncodedTexture, crate::container::ContainerError> {
    match levels.first() {
        Some(Shipped::Bc7 { width, height, .. }) => {
            let (width, height) = (*width, *height);
            let levels = levels
                .into_iter()
                .map(|l| match l {
                    Shipped::Bc7 { blocks, .. } => blocks.iter().flat_map(|b| b.0).collect(),
                    // One texture's levels share a format.
                    Shipped::Bc1(_) => Vec::new(),
                })
                .collect();
            let texture = EncodedTexture {
                format: BlockFormat::Bc7,
                color_space,
                width,
                height,
                levels,
            };
            texture.validate()?;
            Ok(texture)
        }
        _ => {
            let bc1: Vec<MipLevel> = levels
                .into_iter()
                .filter_map(|l| match l {
                    Shipped::Bc1(m) => Some(m),
                    Shipped::Bc7 { .. } => None,
                })
                .collect();
            EncodedTexture::from_mip_levels(&bc1, color_space)
        }
    }
}
