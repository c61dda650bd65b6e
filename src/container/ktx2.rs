//! KTX 2.0 files (Khronos, "KTX File Format Specification", version 2.0)
//! for BC1, BC3 and BC7, optionally Zstandard-supercompressed level by
//! level (supercompressionScheme 2).
//!
//! Layout, all little-endian: the 12-byte identifier; the header (vkFormat,
//! typeSize 1, pixelWidth, pixelHeight, pixelDepth 0, layerCount 0,
//! faceCount 1, levelCount, supercompressionScheme); the index (dfd and kvd
//! offsets and lengths, u32; sgd offset and length, u64, both 0: neither
//! scheme used here has global data); the level index, level 0 first, 24
//! bytes a level (byteOffset, byteLength, uncompressedByteLength); the Data
//! Format Descriptor; the key/value data; then the levels, the smallest
//! first, each at an offset that is a multiple of lcm(block bytes, 4)
//! (8 for BC1, 16 for BC3 and BC7) when not supercompressed, of 1 when.
//!
//! vkFormat. BC3 is BC3_UNORM_BLOCK (137) / BC3_SRGB_BLOCK (138); BC7 is
//! BC7_UNORM_BLOCK (145) / BC7_SRGB_BLOCK (146). BC1 is written as
//! BC1_RGB_UNORM_BLOCK (131) / BC1_RGB_SRGB_BLOCK (132) unless a block
//! decodes a transparent texel (a three-colour block with an index 3:
//! this crate's punch-through alpha for `MASK` textures), and then as
//! BC1_RGBA_UNORM_BLOCK (133) / BC1_RGBA_SRGB_BLOCK (134). Vulkan decodes
//! that index as opaque black under the RGB formats and as transparent
//! black under the RGBA ones, which is what Direct3D and the DDS files
//! give for every BC1 block: so the RGBA formats are needed for exactly
//! those textures, and the RGB ones tell a loader that the others are
//! opaque.
//!
//! Data Format Descriptor (Khronos Data Format Specification 1.3, § 5 and
//! the BC1–BC7 models of § 5.6.5), one basic descriptor block as KTX-
//! Software's `ktx create` writes it: colorModel KHR_DF_MODEL_BC1A (128),
//! BC3 (130) or BC7 (134); primaries BT709; transfer sRGB (2) or linear
//! (1); flags alpha-straight; texelBlockDimension 3, 3, 0, 0 (a 4×4 block,
//! stored minus one); bytesPlane0 the block's bytes, supercompressed or
//! not (the DFD describes the inflated blocks). Samples, each with
//! positions 0, sampleLower 0 and sampleUpper 0xFFFFFFFF: BC1, one of 64
//! bits, channel BC1A_COLOR (0), or BC1A_ALPHAPRESENT (1) for the RGBA
//! formats; BC3, two of 64 bits, BC3_ALPHA (15) at bit 0 then BC3_COLOR
//! (0) at bit 64; BC7, one of 128 bits, BC7_COLOR (0). In an sRGB format
//! the alpha sample carries the LINEAR qualifier (0x10): alpha is never
//! sRGB-encoded.
//!
//! Key/value data, sorted by key: `KTXorientation` = `rd` (texel (0, 0) at
//! the top left, rows going down: the blocks' order, and glTF's),
//! `KTXwriter` = `Seamstress <version>`, and with zstd `KTXwriterScParams`
//! = `--zstd <level>`. Values are NUL-terminated strings.
//!
//! The reader accepts what the writer produces and the same layout from
//! other writers (2D, one face, no array layers); anything else is an
//! error naming the problem, never a panic.

use std::borrow::Cow;
use std::io::Read;

use super::{
    check_shape, level_byte_len, mip_size, u32_at, BlockFormat, ColorSpace, ContainerError,
    EncodedTexture,
};

/// «KTX 20»\r\n\x1A\n.
pub const IDENTIFIER: [u8; 12] = [
    0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A,
];
/// Identifier, header and index: where the level index starts.
const HEADER_LEN: usize = 80;
const LEVEL_ENTRY_LEN: usize = 24;

pub const VK_FORMAT_BC1_RGB_UNORM_BLOCK: u32 = 131;
pub const VK_FORMAT_BC1_RGB_SRGB_BLOCK: u32 = 132;
pub const VK_FORMAT_BC1_RGBA_UNORM_BLOCK: u32 = 133;
pub const VK_FORMAT_BC1_RGBA_SRGB_BLOCK: u32 = 134;
pub const VK_FORMAT_BC3_UNORM_BLOCK: u32 = 137;
pub const VK_FORMAT_BC3_SRGB_BLOCK: u32 = 138;
pub const VK_FORMAT_BC7_UNORM_BLOCK: u32 = 145;
pub const VK_FORMAT_BC7_SRGB_BLOCK: u32 = 146;

pub const SUPERCOMPRESSION_NONE: u32 = 0;
pub const SUPERCOMPRESSION_ZSTD: u32 = 2;

/// The zstd levels `write_ktx2` takes, as the `zstd` tool numbers them.
pub const ZSTD_LEVELS: std::ops::RangeInclusive<i32> = 1..=22;

const KHR_DF_MODEL_BC1A: u8 = 128;
const KHR_DF_MODEL_BC3: u8 = 130;
const KHR_DF_MODEL_BC7: u8 = 134;
const KHR_DF_PRIMARIES_BT709: u8 = 1;
const KHR_DF_TRANSFER_LINEAR: u8 = 1;
const KHR_DF_TRANSFER_SRGB: u8 = 2;
const KHR_DF_VERSION: u32 = 2;
const KHR_DF_CHANNEL_COLOR: u8 = 0;
const KHR_DF_CHANNEL_BC1A_ALPHAPRESENT: u8 = 1;
const KHR_DF_CHANNEL_BC3_ALPHA: u8 = 15;
const KHR_DF_SAMPLE_DATATYPE_LINEAR: u8 = 0x10;
/// Basic descriptor block without its samples, and one sample.
const DFD_BLOCK_LEN: usize = 24;
const DFD_SAMPLE_LEN: usize = 16;

/// The vkFormat for `format` in `color_space`; `alpha` picks BC1's RGBA
/// formats (see the module's notes), and is ignored for BC3 and BC7.
pub fn vk_format(format: BlockFormat, color_space: ColorSpace, alpha: bool) -> u32 {
    let srgb = color_space == ColorSpace::Srgb;
    match (format, alpha, srgb) {
        (BlockFormat::Bc1, false, false) => VK_FORMAT_BC1_RGB_UNORM_BLOCK,
        (BlockFormat::Bc1, false, true) => VK_FORMAT_BC1_RGB_SRGB_BLOCK,
        (BlockFormat::Bc1, true, false) => VK_FORMAT_BC1_RGBA_UNORM_BLOCK,
        (BlockFormat::Bc1, true, true) => VK_FORMAT_BC1_RGBA_SRGB_BLOCK,
        (BlockFormat::Bc3, _, false) => VK_FORMAT_BC3_UNORM_BLOCK,
        (BlockFormat::Bc3, _, true) => VK_FORMAT_BC3_SRGB_BLOCK,
        (BlockFormat::Bc7, _, false) => VK_FORMAT_BC7_UNORM_BLOCK,
        (BlockFormat::Bc7, _, true) => VK_FORMAT_BC7_SRGB_BLOCK,
    }
}

/// The block format, colour space and BC1 alpha of a vkFormat.
fn from_vk_format(vk: u32) -> Option<(BlockFormat, ColorSpace, bool)> {
    BlockFormat::ALL
        .into_iter()
        .flat_map(|f| {
            [ColorSpace::Linear, ColorSpace::Srgb]
                .into_iter()
                .flat_map(move |c| [(f, c, false), (f, c, true)])
        })
        .filter(|&(f, _, alpha)| !alpha || f == BlockFormat::Bc1)
        .find(|&(f, c, alpha)| vk_format(f, c, alpha) == vk)
}

/// (colour model, samples as (bit offset, bit length, channel id)).
fn dfd_layout(format: BlockFormat, alpha: bool) -> (u8, &'static [(u16, u8, u8)]) {
    match format {
        BlockFormat::Bc1 if alpha => (
            KHR_DF_MODEL_BC1A,
            &[(0, 64, KHR_DF_CHANNEL_BC1A_ALPHAPRESENT)],
        ),
        BlockFormat::Bc1 => (KHR_DF_MODEL_BC1A, &[(0, 64, KHR_DF_CHANNEL_COLOR)]),
        BlockFormat::Bc3 => (
            KHR_DF_MODEL_BC3,
            &[
                (0, 64, KHR_DF_CHANNEL_BC3_ALPHA),
                (64, 64, KHR_DF_CHANNEL_COLOR),
            ],
        ),
        BlockFormat::Bc7 => (KHR_DF_MODEL_BC7, &[(0, 128, KHR_DF_CHANNEL_COLOR)]),
    }
}

fn transfer(color_space: ColorSpace) -> u8 {
    match color_space {
        ColorSpace::Srgb => KHR_DF_TRANSFER_SRGB,
        ColorSpace::Linear => KHR_DF_TRANSFER_LINEAR,
    }
}

/// The whole DFD: dfdTotalSize, then one basic descriptor block.
fn dfd_bytes(format: BlockFormat, color_space: ColorSpace, alpha: bool) -> Vec<u8> {
    let (model, samples) = dfd_layout(format, alpha);
    let block_len = DFD_BLOCK_LEN + DFD_SAMPLE_LEN * samples.len();
    let mut words: Vec<u32> = vec![
        (4 + block_len) as u32,
        0, // vendor Khronos, descriptor type basic
        KHR_DF_VERSION | (block_len as u32) << 16,
        u32::from_le_bytes([
            model,
            KHR_DF_PRIMARIES_BT709,
            transfer(color_space),
            0, // alpha straight
        ]),
        u32::from_le_bytes([3, 3, 0, 0]),
        format.block_bytes() as u32, // bytesPlane0; planes 1..=7 empty
        0,
    ];
    for &(offset, bits, channel) in samples {
        let mut channel_type = channel;
        if color_space == ColorSpace::Srgb && channel == KHR_DF_CHANNEL_BC3_ALPHA {
            channel_type |= KHR_DF_SAMPLE_DATATYPE_LINEAR;
        }
        words.push(u32::from(offset) | u32::from(bits - 1) << 16 | u32::from(channel_type) << 24);
        words.push(0); // sample position
        words.push(0); // sampleLower
        words.push(u32::MAX); // sampleUpper
    }
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}

/// The key/value pairs written, sorted by key.
fn key_values(zstd: Option<i32>) -> Vec<(&'static str, String)> {
    let mut kv = vec![
        ("KTXorientation", "rd".to_string()),
        (
            "KTXwriter",
            format!("Seamstress {}", env!("CARGO_PKG_VERSION")),
        ),
    ];
    if let Some(level) = zstd {
        kv.push(("KTXwriterScParams", format!("--zstd {level}")));
    }
    kv
}

fn kvd_bytes(zstd: Option<i32>) -> Vec<u8> {
    let mut out = Vec::new();
    for (key, value) in key_values(zstd) {
        let len = key.len() + 1 + value.len() + 1;
        out.extend_from_slice(&(len as u32).to_le_bytes());
        out.extend_from_slice(key.as_bytes());
        out.push(0);
        out.extend_from_slice(value.as_bytes());
        out.push(0);
        out.resize(out.len().next_multiple_of(4), 0);
    }
    out
}

/// Where levels start when not supercompressed: lcm(block bytes, 4),
/// which is the block size for 8- and 16-byte blocks.
fn level_alignment(format: BlockFormat, scheme: u32) -> usize {
    if scheme == SUPERCOMPRESSION_NONE {
        format.block_bytes()
    } else {
        1
    }
}

/// Writes `tex` as a KTX 2.0 file; `zstd` Some(level), 1 to 22,
/// supercompresses each level with Zstandard. The same texture and level
/// give the same bytes.
pub fn write_ktx2(tex: &EncodedTexture, zstd: Option<i32>) -> Result<Vec<u8>, ContainerError> {
    tex.validate()?;
    if let Some(level) = zstd {
        if !ZSTD_LEVELS.contains(&level) {
            return Err(ContainerError::ZstdLevel(level));
        }
    }
    let alpha = tex.bc1_punches_through();
    let stored: Vec<Cow<[u8]>> = tex
        .levels
        .iter()
        .map(|data| match zstd {
            Some(level) => zstd::bulk::compress(data, level)
                .map(Cow::Owned)
                .map_err(|e| ContainerError::Zstd(e.to_string())),
            None => Ok(Cow::Borrowed(&data[..])),
        })
        .collect::<Result<_, _>>()?;
    let scheme = if zstd.is_some() {
        SUPERCOMPRESSION_ZSTD
    } else {
        SUPERCOMPRESSION_NONE
    };
    let n = tex.levels.len();
    let dfd = dfd_bytes(tex.format, tex.color_space, alpha);
    let kvd = kvd_bytes(zstd);
    let dfd_offset = HEADER_LEN + n * LEVEL_ENTRY_LEN;
    let kvd_offset = dfd_offset + dfd.len();
    let align = level_alignment(tex.format, scheme);
    // Levels go smallest first, so that a loader streaming the file can
    // show a small level before the large ones arrive.
    let mut offsets = vec![0usize; n];
    let mut end = kvd_offset + kvd.len();
    for k in (0..n).rev() {
        end = end.next_multiple_of(align);
        offsets[k] = end;
        end += stored[k].len();
    }

    let mut out = Vec::with_capacity(end);
    let put = |out: &mut Vec<u8>, v: u32| out.extend_from_slice(&v.to_le_bytes());
    let put64 = |out: &mut Vec<u8>, v: usize| out.extend_from_slice(&(v as u64).to_le_bytes());
    out.extend_from_slice(&IDENTIFIER);
    put(&mut out, vk_format(tex.format, tex.color_space, alpha));
    put(&mut out, 1); // typeSize: block-compressed data has no endianness
    put(&mut out, tex.width);
    put(&mut out, tex.height);
    put(&mut out, 0); // pixelDepth: 2D
    put(&mut out, 0); // layerCount: not an array
    put(&mut out, 1); // faceCount
    put(&mut out, n as u32);
    put(&mut out, scheme);
    // DFD and KVD are a few dozen bytes after the level index, whose
    // length MAX_SIDE bounds: the offsets fit u32.
    put(&mut out, dfd_offset as u32);
    put(&mut out, dfd.len() as u32);
    put(&mut out, kvd_offset as u32);
    put(&mut out, kvd.len() as u32);
    put64(&mut out, 0); // sgdByteOffset
    put64(&mut out, 0); // sgdByteLength
    for (k, data) in stored.iter().enumerate() {
        put64(&mut out, offsets[k]);
        put64(&mut out, data.len());
        put64(&mut out, tex.levels[k].len());
    }
    out.extend_from_slice(&dfd);
    out.extend_from_slice(&kvd);
    for k in (0..n).rev() {
        out.resize(offsets[k], 0); // mipPadding
        out.extend_from_slice(&stored[k]);
    }
    debug_assert_eq!(out.len(), end);
    Ok(out)
}

fn u64_at(bytes: &[u8], off: usize) -> u64 {
    let mut w = [0u8; 8];
    if let Some(s) = off.checked_add(8).and_then(|end| bytes.get(off..end)) {
        w.copy_from_slice(s);
    }
    u64::from_le_bytes(w)
}

/// `bytes[off..off + len]`, or an error naming `what` when it leaves the
/// file.
fn region<'a>(
    bytes: &'a [u8],
    off: u64,
    len: u64,
    what: &'static str,
) -> Result<&'a [u8], ContainerError> {
    let end = off.saturating_add(len);
    match (usize::try_from(off), usize::try_from(end)) {
        (Ok(o), Ok(e)) if e <= bytes.len() => Ok(&bytes[o..e]),
        _ => Err(ContainerError::Truncated {
            what,
            len: bytes.len(),
            need: usize::try_from(end).unwrap_or(usize::MAX),
        }),
    }
}

/// Checks the basic descriptor block against the vkFormat: the fields a
/// decoder relies on (model, transfer, block size and bytes).
/// Supercompressed files from older libktx versions are "unsized"
/// (bytesPlane0 0), which its current version (and this writer) no longer
/// writes but still reads: so are they here.
fn check_dfd(
    dfd: &[u8],
    format: BlockFormat,
    color_space: ColorSpace,
    alpha: bool,
    scheme: u32,
) -> Result<(), ContainerError> {
    let bad = |s: String| Err(ContainerError::Dfd(s));
    if dfd.len() < 4 + DFD_BLOCK_LEN {
        return bad(format!(
            "{} bytes; a basic descriptor block needs {}",
            dfd.len(),
            4 + DFD_BLOCK_LEN
        ));
    }
    let total = u32_at(dfd, 0) as usize;
    if total != dfd.len() {
        return bad(format!(
            "dfdTotalSize is {total}; dfdByteLength is {}",
            dfd.len()
        ));
    }
    if u32_at(dfd, 4) != 0 {
        return bad("first block is not Khronos's basic descriptor block".into());
    }
    let version = u32_at(dfd, 8) & 0xFFFF;
    let block_len = (u32_at(dfd, 8) >> 16) as usize;
    if version != KHR_DF_VERSION {
        return bad(format!("version {version}; 2 expected"));
    }
    if block_len < DFD_BLOCK_LEN
        || !(block_len - DFD_BLOCK_LEN).is_multiple_of(DFD_SAMPLE_LEN)
        || 4 + block_len > dfd.len()
    {
        return bad(format!("descriptor block size {block_len} is inconsistent"));
    }
    let (model, samples) = dfd_layout(format, alpha);
    let [got_model, _primaries, got_transfer, _flags] = u32_at(dfd, 12).to_le_bytes();
    if got_model != model {
        return bad(format!("colorModel {got_model}; {format} is {model}"));
    }
    let want_transfer = transfer(color_space);
    if got_transfer != want_transfer {
        return bad(format!(
            "transferFunction {got_transfer}; the vkFormat's is {want_transfer}"
        ));
    }
    let dims = u32_at(dfd, 16).to_le_bytes();
    if dims != [3, 3, 0, 0] {
        return bad(format!(
            "texelBlockDimension {dims:?}; 4x4 blocks are [3, 3, 0, 0]"
        ));
    }
    let bytes_plane0 = dfd[20];
    let unsized_ok = scheme != SUPERCOMPRESSION_NONE && bytes_plane0 == 0;
    if usize::from(bytes_plane0) != format.block_bytes() && !unsized_ok {
        return bad(format!(
            "bytesPlane0 {bytes_plane0}; {format} blocks are {} bytes",
            format.block_bytes()
        ));
    }
    let got_samples = (block_len - DFD_BLOCK_LEN) / DFD_SAMPLE_LEN;
    if got_samples != samples.len() {
        return bad(format!(
            "{got_samples} samples; {format} has {}",
            samples.len()
        ));
    }
    Ok(())
}

/// Checks the key/value entries' framing and that the orientation, if
/// given, is the blocks' own (`rd`).
fn check_kvd(kvd: &[u8]) -> Result<(), ContainerError> {
    let bad = |s: String| Err(ContainerError::KeyValue(s));
    let mut off = 0usize;
    while off < kvd.len() {
        if kvd.len() - off < 4 {
            return bad(format!("entry at {off} has no room for its length"));
        }
        let len = u32_at(kvd, off) as usize;
        let Some(entry) = kvd.get(off + 4..).and_then(|r| r.get(..len)) else {
            return bad(format!("entry at {off} of {len} bytes runs past the data"));
        };
        let Some(nul) = entry.iter().position(|&b| b == 0) else {
            return bad(format!("entry at {off} has no NUL after its key"));
        };
        let (key, value) = (&entry[..nul], &entry[nul + 1..]);
        if key == b"KTXorientation" {
            let value = value.strip_suffix(&[0]).unwrap_or(value);
            if !value.starts_with(b"rd") {
                return bad(format!(
                    "KTXorientation {:?}; only \"rd\" (rows top-down) is read",
                    String::from_utf8_lossy(value)
                ));
            }
        }
        off = (off + 4 + len).next_multiple_of(4);
    }
    Ok(())
}

/// Inflates one zstd-supercompressed level to exactly `expected` bytes,
/// never holding more than that (plus one) whatever the frame claims.
fn inflate(data: &[u8], expected: usize, level: usize) -> Result<Vec<u8>, ContainerError> {
    let fail = |what: String| ContainerError::Zstd(format!("level {level}: {what}"));
    let decoder =
        zstd::stream::read::Decoder::with_buffer(data).map_err(|e| fail(e.to_string()))?;
    let mut out = Vec::new();
    decoder
        .take(expected as u64 + 1)
        .read_to_end(&mut out)
        .map_err(|e| fail(e.to_string()))?;
    if out.len() != expected {
        return Err(fail(format!(
            "inflates to {}{} bytes; uncompressedByteLength is {expected}",
            if out.len() > expected { "over " } else { "" },
            out.len().min(expected),
        )));
    }
    Ok(out)
}

/// Reads a KTX 2.0 file of BC1, BC3 or BC7 blocks, inflating
/// Zstandard-supercompressed levels.
pub fn read_ktx2(bytes: &[u8]) -> Result<EncodedTexture, ContainerError> {
    if bytes.len() < IDENTIFIER.len() {
        return Err(ContainerError::Truncated {
            what: "KTX2 identifier",
            len: bytes.len(),
            need: IDENTIFIER.len(),
        });
    }
    if bytes[..IDENTIFIER.len()] != IDENTIFIER {
        return Err(ContainerError::Ktx2Identifier);
    }
    if bytes.len() < HEADER_LEN {
        return Err(ContainerError::Truncated {
            what: "KTX2 header",
            len: bytes.len(),
            need: HEADER_LEN,
        });
    }
    let header = |i: usize| u32_at(bytes, 12 + 4 * i);
    let vk = header(0);
    let (format, color_space, alpha) = from_vk_format(vk).ok_or(ContainerError::VkFormat(vk))?;
    let bad = |s: String| Err(ContainerError::Ktx2Header(s));
    let [type_size, width, height, depth, layers, faces, level_count, scheme] =
        std::array::from_fn(|i| header(i + 1));
    if type_size != 1 {
        return bad(format!(
            "typeSize {type_size}; block-compressed formats have 1"
        ));
    }
    if depth != 0 {
        return bad(format!("pixelDepth {depth}; only 2D textures are read"));
    }
    if layers != 0 {
        return bad(format!("layerCount {layers}; array textures are not read"));
    }
    if faces != 1 {
        return bad(format!("faceCount {faces}; cube maps are not read"));
    }
    if scheme != SUPERCOMPRESSION_NONE && scheme != SUPERCOMPRESSION_ZSTD {
        return Err(ContainerError::Supercompression(scheme));
    }
    if u64_at(bytes, 72) != 0 {
        return bad("supercompression global data present; neither scheme read has any".into());
    }
    // levelCount 0 asks a loader to make the mips; the file holds level 0.
    let count = level_count.max(1) as usize;
    check_shape(width, height, count)?;
    let index_end = HEADER_LEN + count * LEVEL_ENTRY_LEN;
    if bytes.len() < index_end {
        return Err(ContainerError::Truncated {
            what: "KTX2 level index",
            len: bytes.len(),
            need: index_end,
        });
    }
    let dfd = region(
        bytes,
        header(9).into(),
        header(10).into(),
        "KTX2 data format descriptor",
    )?;
    check_dfd(dfd, format, color_space, alpha, scheme)?;
    let kvd = region(
        bytes,
        header(11).into(),
        header(12).into(),
        "KTX2 key/value data",
    )?;
    check_kvd(kvd)?;

    let align = level_alignment(format, scheme);
    let mut levels = Vec::with_capacity(count);
    for k in 0..count {
        let entry = HEADER_LEN + k * LEVEL_ENTRY_LEN;
        let (offset, length, uncompressed) = (
            u64_at(bytes, entry),
            u64_at(bytes, entry + 8),
            u64_at(bytes, entry + 16),
        );
        let (w, h) = mip_size(width, height, k);
        let need = level_byte_len(format, w, h);
        let problem = |problem: String| ContainerError::LevelIndex { level: k, problem };
        if uncompressed != need as u64 {
            return Err(problem(format!(
                "uncompressedByteLength {uncompressed}; a {w}x{h} level of {format} is {need} bytes"
            )));
        }
        if scheme == SUPERCOMPRESSION_NONE && length != uncompressed {
            return Err(problem(format!(
                "byteLength {length} differs from uncompressedByteLength {uncompressed}"
            )));
        }
        if offset < index_end as u64 {
            return Err(problem(format!(
                "byteOffset {offset} lies inside the header and level index"
            )));
        }
        if !offset.is_multiple_of(align as u64) {
            return Err(problem(format!(
                "byteOffset {offset} is not a multiple of {align}"
            )));
        }
        let Ok(data) = region(bytes, offset, length, "KTX2 level") else {
            return Err(problem(format!(
                "bytes {offset}..{} lie past the end of the file ({} bytes)",
                offset.saturating_add(length),
                bytes.len()
            )));
        };
        levels.push(if scheme == SUPERCOMPRESSION_ZSTD {
            inflate(data, need, k)?
        } else {
            data.to_vec()
        });
    }
    Ok(EncodedTexture {
        format,
        color_space,
        width,
        height,
        levels,
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
                    // Endpoints in descending order keep BC1 blocks in
                    // four-colour mode: opaque.
                    .map(|i| {
                        if i % 8 == 1 {
                            0xFF
                        } else {
                            (i * 31 + k * 7) as u8 & 0x7F
                        }
                    })
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

    fn u64_of(bytes: &[u8], off: usize) -> u64 {
        u64_at(bytes, off)
    }

    #[test]
    fn header_index_and_levels_follow_the_spec() {
        let t = texture(BlockFormat::Bc3, ColorSpace::Srgb, 13, 6);
        let bytes = write_ktx2(&t, None).unwrap();
        assert_eq!(bytes[..12], IDENTIFIER);
        let h = |i: usize| u32_at(&bytes, 12 + 4 * i);
        assert_eq!(
            [h(0), h(1), h(2), h(3), h(4), h(5), h(6), h(7), h(8)],
            [138, 1, 13, 6, 0, 0, 1, 4, 0]
        );
        // DFD right after the level index: 4 levels of 24 bytes.
        assert_eq!(h(9), 80 + 4 * 24);
        assert_eq!(h(10), 4 + 24 + 2 * 16);
        assert_eq!(h(11), h(9) + h(10));
        assert_eq!(u64_of(&bytes, 64), 0);
        assert_eq!(u64_of(&bytes, 72), 0);
        // Levels: smallest first, each on a 16-byte boundary, and the
        // index lists level 0 first.
        let entries: Vec<(u64, u64, u64)> = (0..4)
            .map(|k| {
                let e = 80 + 24 * k;
                (
                    u64_of(&bytes, e),
                    u64_of(&bytes, e + 8),
                    u64_of(&bytes, e + 16),
                )
            })
            .collect();
        let sizes = [4 * 2 * 16, 2 * 16, 16, 16];
        for (k, &(off, len, raw)) in entries.iter().enumerate() {
            assert_eq!((len, raw), (sizes[k], sizes[k]));
            assert_eq!(off % 16, 0);
            assert_eq!(&bytes[off as usize..(off + len) as usize], &t.levels[k][..]);
        }
        assert!(entries[3].0 < entries[2].0 && entries[1].0 < entries[0].0);
        let kvd_end = (h(11) + h(12)) as u64;
        assert_eq!(entries[3].0, kvd_end.next_multiple_of(16));
        assert_eq!(bytes.len() as u64, entries[0].0 + entries[0].1);
    }

    #[test]
    fn dfd_matches_what_ktx_create_writes() {
        let words = |b: Vec<u8>| -> Vec<u32> {
            b.chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
                .collect()
        };
        // BC3 sRGB: model 130, BT709, sRGB; alpha (15, LINEAR) then colour.
        assert_eq!(
            words(dfd_bytes(BlockFormat::Bc3, ColorSpace::Srgb, false)),
            [
                60,
                0,
                2 | 56 << 16,
                130 | 1 << 8 | 2 << 16,
                0x0303,
                16,
                0,
                63 << 16 | 0x1F << 24,
                0,
                0,
                u32::MAX,
                64 | 63 << 16,
                0,
                0,
                u32::MAX,
            ]
        );
        // BC1 linear, opaque and punch-through; BC7 sRGB.
        let bc1 = words(dfd_bytes(BlockFormat::Bc1, ColorSpace::Linear, false));
        assert_eq!(
            bc1[..7],
            [44, 0, 2 | 40 << 16, 128 | 1 << 8 | 1 << 16, 0x0303, 8, 0]
        );
        assert_eq!(bc1[7..], [63 << 16, 0, 0, u32::MAX]);
        let bc1a = words(dfd_bytes(BlockFormat::Bc1, ColorSpace::Srgb, true));
        assert_eq!(bc1a[7], 63 << 16 | 1 << 24);
        let bc7 = words(dfd_bytes(BlockFormat::Bc7, ColorSpace::Srgb, false));
        assert_eq!(bc7[3], 134 | 1 << 8 | 2 << 16);
        assert_eq!(bc7[5], 16);
        assert_eq!(bc7[7..], [127 << 16, 0, 0, u32::MAX]);
    }

    #[test]
    fn key_values_are_sorted_and_padded() {
        let kvd = kvd_bytes(Some(19));
        assert_eq!(kvd.len() % 4, 0);
        let mut keys = Vec::new();
        let mut off = 0;
        while off < kvd.len() {
            let len = u32_at(&kvd, off) as usize;
            let entry = &kvd[off + 4..off + 4 + len];
            let nul = entry.iter().position(|&b| b == 0).unwrap();
            keys.push(String::from_utf8(entry[..nul].to_vec()).unwrap());
            assert_eq!(entry.last(), Some(&0));
            off = (off + 4 + len).next_multiple_of(4);
        }
        assert_eq!(keys, ["KTXorientation", "KTXwriter", "KTXwriterScParams"]);
        let mut sorted = keys.clone();
        sorted.sort();
        assert_eq!(keys, sorted);
    }

    #[test]
    fn bc1_with_transparent_texels_is_rgba() {
        let mut t = texture(BlockFormat::Bc1, ColorSpace::Srgb, 8, 8);
        assert_eq!(u32_at(&write_ktx2(&t, None).unwrap(), 12), 132);
        // c0 = c1 = 0 and every index 3: a transparent block.
        t.levels[1] = [0, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF].to_vec();
        let bytes = write_ktx2(&t, None).unwrap();
        assert_eq!(u32_at(&bytes, 12), 134);
        assert_eq!(read_ktx2(&bytes).unwrap(), t);
        t.color_space = ColorSpace::Linear;
        assert_eq!(u32_at(&write_ktx2(&t, Some(3)).unwrap(), 12), 133);
    }

    #[test]
    fn unsized_dfd_is_read_only_when_supercompressed() {
        let t = texture(BlockFormat::Bc1, ColorSpace::Srgb, 8, 8);
        for zstd in [None, Some(1)] {
            let mut b = write_ktx2(&t, zstd).unwrap();
            let bytes_plane0 = u32_at(&b, 12 + 4 * 9) as usize + 20;
            assert_eq!(b[bytes_plane0], 8);
            b[bytes_plane0] = 0;
            match zstd {
                Some(_) => assert_eq!(read_ktx2(&b).unwrap(), t),
                None => assert!(matches!(read_ktx2(&b), Err(ContainerError::Dfd(_)))),
            }
        }
    }

    #[test]
    fn zstd_levels_round_trip_deterministically() {
        let t = texture(BlockFormat::Bc7, ColorSpace::Linear, 37, 19);
        let a = write_ktx2(&t, Some(19)).unwrap();
        assert_eq!(a, write_ktx2(&t, Some(19)).unwrap());
        assert_eq!(u32_at(&a, 12 + 4 * 8), SUPERCOMPRESSION_ZSTD);
        assert_eq!(read_ktx2(&a).unwrap(), t);
        for bad in [0, 23, -1] {
            assert_eq!(
                write_ktx2(&t, Some(bad)),
                Err(ContainerError::ZstdLevel(bad))
            );
        }
    }
}
