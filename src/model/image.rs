//! Decoded texture images as float texels, and writing them back.

use std::io::Cursor;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ExtendedColorType, ImageDecoder, ImageEncoder, ImageReader, Limits};

/// How the texels were stored, so they can be written back the same way.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TextureEncoding {
    /// Channels in the source image: 1 (grey), 2 (grey+alpha), 3 (RGB), 4 (RGBA).
    pub channels: u8,
    /// 8 or 16.
    pub bits: u8,
}

impl TextureEncoding {
    /// The largest stored value: 255 for 8 bits, 65535 for 16.
    pub fn max_value(&self) -> u32 {
        (1u32 << self.bits) - 1
    }
}

/// What an image's header announces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageHeader {
    pub width: u32,
    pub height: u32,
    /// 1 (grey), 2 (grey+alpha), 3 (RGB), 4 (RGBA).
    pub channels: u8,
    /// 8 or 16.
    pub bits: u8,
}

/// A texture as the seam engine sees it: row-major texels, `channels` f32
/// values in \[0, 1\] each, in the image's stored encoding (no sRGB decode).
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: Vec<f32>,
    pub encoding: TextureEncoding,
}

/// Why an image could not be decoded or written.
#[derive(Debug, thiserror::Error)]
pub enum TextureError {
    /// The header announces more texels than allowed; nothing was decoded.
    #[error("image is {width}x{height}, above the limit of {limit} texels per side")]
    TooLarge { width: u32, height: u32, limit: u32 },
    #[error("image is empty ({width}x{height})")]
    Empty { width: u32, height: u32 },
    #[error("image format is not PNG or JPEG")]
    UnknownFormat,
    #[error("cannot decode image: {0}")]
    Decode(String),
    #[error("cannot encode PNG: {0}")]
    Encode(String),
    /// The texture's fields disagree with each other (a caller bug, not bad input).
    #[error("inconsistent texture: {0}")]
    Inconsistent(String),
}

impl TextureError {
    /// True when the image data itself is at fault (as opposed to encoding a
    /// texture that the program built).
    pub fn is_bad_input(&self) -> bool {
        matches!(
            self,
            TextureError::TooLarge { .. }
                | TextureError::Empty { .. }
                | TextureError::UnknownFormat
                | TextureError::Decode(_)
        )
    }
}

/// Working memory a decoder may use beyond the output buffer (PNG line
/// buffers, JPEG component planes).
const DECODER_SCRATCH_BYTES: u64 = 256 << 20;

/// The fast deflate: Fox's erased 2048² texture in 18 ms and 1.30 MB,
/// against 250 ms and 1.00 MB at the default level (a tenth of the whole
/// job's CPU time, for a file that ships beside a 2.8 MB DDS).
const PNG_COMPRESSION: CompressionType = CompressionType::Fast;

/// Error messages from the decoders may span lines; reports need one line.
fn one_line(s: impl std::fmt::Display) -> String {
    s.to_string()
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .collect()
}

impl Texture {
    /// Reads a PNG's or JPEG's header only: its size and channels, checked
    /// against `max_size` per side. Costs nothing however large the image
    /// announces itself, so budgets are decided before any texel exists.
    pub fn probe(bytes: &[u8], max_size: u32) -> Result<ImageHeader, TextureError> {
        let decoder = Self::header_decoder(bytes, max_size)?;
        let (width, height) = decoder.dimensions();
        let colour = decoder.color_type();
        Ok(ImageHeader {
            width,
            height,
            channels: colour.channel_count(),
            bits: if colour.bytes_per_pixel() / colour.channel_count() > 1 {
                16
            } else {
                8
            },
        })
    }

    fn header_decoder(
        bytes: &[u8],
        max_size: u32,
    ) -> Result<Box<dyn ImageDecoder + '_>, TextureError> {
        let reader = ImageReader::new(Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| TextureError::Decode(one_line(e)))?;
        match reader.format() {
            Some(image::ImageFormat::Png) | Some(image::ImageFormat::Jpeg) => {}
            _ => return Err(TextureError::UnknownFormat),
        }
        let decoder = reader
            .into_decoder()
            .map_err(|e| TextureError::Decode(one_line(e)))?;
        let (width, height) = decoder.dimensions();
        if width > max_size || height > max_size {
            return Err(TextureError::TooLarge {
                width,
                height,
                limit: max_size,
            });
        }
        if width == 0 || height == 0 {
            return Err(TextureError::Empty { width, height });
        }
        Ok(Box::new(decoder))
    }

    /// Decodes a PNG or JPEG. `max_size` bounds width and height each; the
    /// dimensions are read from the header and checked before any texel is
    /// decoded, so a small file announcing a huge image costs nothing.
    pub fn decode(bytes: &[u8], max_size: u32) -> Result<Texture, TextureError> {
        let mut decoder = Self::header_decoder(bytes, max_size)?;
        let total = decoder.total_bytes();
        let mut limits = Limits::default();
        limits.max_image_width = Some(max_size);
        limits.max_image_height = Some(max_size);
        limits.max_alloc = Some(total.saturating_add(DECODER_SCRATCH_BYTES));
        // Same bookkeeping as `ImageReader::decode`: the output buffer counts
        // against the budget, the rest is left to the decoder.
        limits
            .reserve(total)
            .map_err(|e| TextureError::Decode(one_line(e)))?;
        decoder
            .set_limits(limits)
            .map_err(|e| TextureError::Decode(one_line(e)))?;
        let img =
            DynamicImage::from_decoder(decoder).map_err(|e| TextureError::Decode(one_line(e)))?;
        Ok(Self::from_dynamic(img))
    }

    fn from_dynamic(img: DynamicImage) -> Texture {
        let (width, height) = (img.width() as usize, img.height() as usize);
        fn eight(raw: &[u8]) -> Vec<f32> {
            raw.iter().map(|&v| f32::from(v) / 255.0).collect()
        }
        fn sixteen(raw: &[u16]) -> Vec<f32> {
            raw.iter().map(|&v| f32::from(v) / 65535.0).collect()
        }
        let (channels, bits, data) = match img {
            DynamicImage::ImageLuma8(b) => (1, 8, eight(b.as_raw())),
            DynamicImage::ImageLumaA8(b) => (2, 8, eight(b.as_raw())),
            DynamicImage::ImageRgb8(b) => (3, 8, eight(b.as_raw())),
            DynamicImage::ImageRgba8(b) => (4, 8, eight(b.as_raw())),
            DynamicImage::ImageLuma16(b) => (1, 16, sixteen(b.as_raw())),
            DynamicImage::ImageLumaA16(b) => (2, 16, sixteen(b.as_raw())),
            DynamicImage::ImageRgb16(b) => (3, 16, sixteen(b.as_raw())),
            DynamicImage::ImageRgba16(b) => (4, 16, sixteen(b.as_raw())),
            // Neither PNG nor JPEG produce float images; keep the most
            // precision an output PNG can hold should a decoder ever do so.
            other => (4, 16, sixteen(other.to_rgba16().as_raw())),
        };
        Texture {
            width,
            height,
            channels,
            data,
            encoding: TextureEncoding {
                channels: channels as u8,
                bits,
            },
        }
    }

    /// Writes the texels as PNG with the source's channel count and bit
    /// depth (JPEG sources come out as 8-bit PNG). Values are clamped to
    /// \[0, 1\] and rounded to the nearest level; the bytes depend only on the
    /// texels.
    pub fn encode_png(&self) -> Result<Vec<u8>, TextureError> {
        let enc = self.encoding;
        if usize::from(enc.channels) != self.channels || !(1..=4).contains(&self.channels) {
            return Err(TextureError::Inconsistent(format!(
                "{} channels stored, encoding says {}",
                self.channels, enc.channels
            )));
        }
        let expected = self
            .width
            .checked_mul(self.height)
            .and_then(|n| n.checked_mul(self.channels));
        if expected != Some(self.data.len()) {
            return Err(TextureError::Inconsistent(format!(
                "{} values for {}x{}x{}",
                self.data.len(),
                self.width,
                self.height,
                self.channels
            )));
        }
        let (w, h) = match (u32::try_from(self.width), u32::try_from(self.height)) {
            (Ok(w), Ok(h)) => (w, h),
            _ => return Err(TextureError::Inconsistent("size exceeds u32".into())),
        };
        let quantize = |v: f32, max: f32| -> f32 {
            // NaN maps to 0 rather than poisoning the output.
            let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
            (v * max).round()
        };
        let (bytes, color): (Vec<u8>, ExtendedColorType) = match enc.bits {
            8 => (
                self.data
                    .iter()
                    .map(|&v| quantize(v, 255.0) as u8)
                    .collect(),
                match self.channels {
                    1 => ExtendedColorType::L8,
                    2 => ExtendedColorType::La8,
                    3 => ExtendedColorType::Rgb8,
                    _ => ExtendedColorType::Rgba8,
                },
            ),
            16 => (
                // PngEncoder takes 16-bit samples in native byte order.
                self.data
                    .iter()
                    .flat_map(|&v| (quantize(v, 65535.0) as u16).to_ne_bytes())
                    .collect(),
                match self.channels {
                    1 => ExtendedColorType::L16,
                    2 => ExtendedColorType::La16,
                    3 => ExtendedColorType::Rgb16,
                    _ => ExtendedColorType::Rgba16,
                },
            ),
            b => {
                return Err(TextureError::Inconsistent(format!(
                    "unsupported bit depth {b}"
                )))
            }
        };
        let mut out = Vec::new();
        PngEncoder::new_with_quality(&mut out, PNG_COMPRESSION, FilterType::Adaptive)
            .write_image(&bytes, w, h, color)
            .map_err(|e| TextureError::Encode(one_line(e)))?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(w: usize, h: usize, channels: usize, bits: u8, f: impl Fn(usize) -> f32) -> Texture {
        Texture {
            width: w,
            height: h,
            channels,
            data: (0..w * h * channels).map(f).collect(),
            encoding: TextureEncoding {
                channels: channels as u8,
                bits,
            },
        }
    }

    #[test]
    fn sixteen_bit_round_trip_is_exact() {
        let t = texture(7, 5, 3, 16, |i| ((i * 7919) % 65536) as f32 / 65535.0);
        let png = t.encode_png().unwrap();
        let back = Texture::decode(&png, 64).unwrap();
        assert_eq!(
            back.encoding,
            TextureEncoding {
                channels: 3,
                bits: 16
            }
        );
        assert_eq!(back, t);
    }

    #[test]
    fn grey_round_trip() {
        let t = texture(9, 4, 1, 8, |i| (i * 7 % 256) as f32 / 255.0);
        let back = Texture::decode(&t.encode_png().unwrap(), 64).unwrap();
        assert_eq!(
            back.encoding,
            TextureEncoding {
                channels: 1,
                bits: 8
            }
        );
        assert_eq!(back, t);
        let ga = texture(3, 3, 2, 16, |i| (i * 4099 % 65536) as f32 / 65535.0);
        assert_eq!(Texture::decode(&ga.encode_png().unwrap(), 64).unwrap(), ga);
    }

    #[test]
    fn rgba_round_trip_rounds_and_clamps() {
        let t = texture(4, 4, 4, 8, |i| (i % 256) as f32 / 255.0);
        let back = Texture::decode(&t.encode_png().unwrap(), 64).unwrap();
        assert_eq!(back, t);

        let mut off = t.clone();
        off.data[0] = 1.7;
        off.data[1] = -0.2;
        off.data[2] = 10.4 / 255.0;
        off.data[3] = f32::NAN;
        let back = Texture::decode(&off.encode_png().unwrap(), 64).unwrap();
        assert_eq!(&back.data[..4], &[1.0, 0.0, 10.0 / 255.0, 0.0]);
    }

    #[test]
    fn encoding_is_deterministic() {
        let t = texture(16, 16, 3, 8, |i| (i * 31 % 256) as f32 / 255.0);
        assert_eq!(t.encode_png().unwrap(), t.encode_png().unwrap());
    }

    /// A PNG announcing `w`×`h` RGBA8 whose image data is a few bytes: what
    /// a decompression bomb looks like to the header reader.
    fn png_header(w: u32, h: u32) -> Vec<u8> {
        fn chunk(png: &mut Vec<u8>, ty: &[u8], data: &[u8]) {
            png.extend_from_slice(&(data.len() as u32).to_be_bytes());
            let mut body = ty.to_vec();
            body.extend_from_slice(data);
            png.extend_from_slice(&body);
            png.extend_from_slice(&crc32(&body).to_be_bytes());
        }
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&w.to_be_bytes());
        ihdr.extend_from_slice(&h.to_be_bytes());
        ihdr.extend_from_slice(&[8, 6, 0, 0, 0]);
        let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
        chunk(&mut png, b"IHDR", &ihdr);
        chunk(
            &mut png,
            b"IDAT",
            &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
        );
        chunk(&mut png, b"IEND", &[]);
        png
    }

    fn crc32(data: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in data {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 != 0 {
                    (crc >> 1) ^ 0xEDB8_8320
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }

    #[test]
    fn refuses_huge_image_before_decoding() {
        match Texture::decode(&png_header(100_000, 100_000), 16384) {
            Err(TextureError::TooLarge {
                width: 100_000,
                height: 100_000,
                limit: 16384,
            }) => {}
            other => panic!("expected TooLarge, got {other:?}"),
        }
        // One side over the limit is enough.
        assert!(matches!(
            Texture::decode(&png_header(8, 300), 256),
            Err(TextureError::TooLarge { .. })
        ));
    }

    #[test]
    fn rejects_garbage() {
        assert!(matches!(
            Texture::decode(b"not an image at all", 64),
            Err(TextureError::UnknownFormat)
        ));
        let mut truncated = texture(8, 8, 3, 8, |_| 0.5).encode_png().unwrap();
        truncated.truncate(truncated.len() / 2);
        assert!(Texture::decode(&truncated, 64).is_err());
    }
}
