//! Models: glTF/GLB loading, texture bindings, welding and seam extraction.
//!
//! A loaded [`Model`] is already reduced to what the seam engine needs: for
//! every processed image, its decoded texels, its wrap modes, and every
//! triangle that samples it, with UVs in texture space (KHR_texture_transform
//! applied, TEXCOORD set resolved).

pub mod image;
pub mod load;
pub mod rewrite;
pub mod seams;
pub mod sniff;

pub use self::image::{ImageHeader, Texture, TextureEncoding, TextureError};
pub use load::{
    load, load_from_memory, plan, plan_from_memory, DirResolver, LoadError, LoadErrorKind,
    LoadOptions, NoFiles, Plan, PlannedTexture, Resolver,
};
pub use seams::{find_seams, MeshEdges, SeamEdge, SeamSet, SilhouetteEdge};

/// Sampler wrap mode along one texture axis (glTF sampler `wrapS`/`wrapT`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Wrap {
    #[default]
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

impl Wrap {
    /// Maps an integer texel index onto `0..n` as the sampler would.
    #[inline]
    pub fn index(self, i: i64, n: usize) -> usize {
        let n = n as i64;
        let r = match self {
            Wrap::Repeat => i.rem_euclid(n),
            Wrap::ClampToEdge => i.clamp(0, n - 1),
            Wrap::MirroredRepeat => {
                let m = i.rem_euclid(2 * n);
                if m < n {
                    m
                } else {
                    2 * n - 1 - m
                }
            }
        };
        r as usize
    }
}

/// How the materials that sample a texture as base colour use its alpha
/// channel (glTF `alphaMode`, `alphaCutoff`).
#[derive(Clone, Copy, Debug, PartialEq, Default, serde::Serialize)]
#[serde(tag = "mode", rename_all = "snake_case")]
pub enum AlphaUse {
    /// Alpha is ignored (`OPAQUE`, or the texture is not a base colour).
    #[default]
    Opaque,
    /// Texels at or above `cutoff` are drawn, the rest discarded.
    Mask { cutoff: f32 },
    /// Alpha blends: every value matters. Also where materials mask the
    /// texture at different cutoffs, which one bit per texel cannot serve.
    Blend,
}

impl AlphaUse {
    /// The use that serves both: blending over masking over opaque.
    pub fn merge(self, other: AlphaUse) -> AlphaUse {
        match (self, other) {
            (AlphaUse::Blend, _) | (_, AlphaUse::Blend) => AlphaUse::Blend,
            (AlphaUse::Mask { cutoff: a }, AlphaUse::Mask { cutoff: b }) if a != b => {
                AlphaUse::Blend
            }
            (m @ AlphaUse::Mask { .. }, _) | (_, m @ AlphaUse::Mask { .. }) => m,
            _ => AlphaUse::Opaque,
        }
    }
}

/// One triangle that samples a texture.
///
/// `group` scopes welding: vertices are welded only between triangles of the
/// same group (one mesh and one TEXCOORD set), as SPEC §2 requires.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UvTriangle {
    pub group: u32,
    /// Object-space positions, exactly as stored (welding compares bits).
    pub positions: [[f32; 3]; 3],
    /// UVs after KHR_texture_transform, in glTF's convention (origin top-left).
    pub uvs: [[f64; 2]; 3],
}

/// An image that the model uses as base colour or emissive, with every
/// triangle that samples it (across materials, primitives and meshes).
#[derive(Clone, Debug)]
pub struct TextureBinding {
    /// Index of the image in the glTF `images` array.
    pub image: usize,
    /// A file-name-safe name, unique within the model (image name, URI stem, or `image<N>`).
    pub name: String,
    pub texture: Texture,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    /// True when a material samples it as base colour or emissive (sRGB data).
    pub srgb: bool,
    /// A KHR_texture_transform that samples it rotates the UVs (so the
    /// texture cannot be padded with a per-axis UV scale).
    pub rotated: bool,
    /// How its materials use its alpha channel.
    pub alpha: AlphaUse,
    pub triangles: Vec<UvTriangle>,
}

/// Something in the model that was deliberately not processed, with why.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Skipped {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub image: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mesh: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub primitive: Option<usize>,
    pub reason: String,
}

/// A loaded model: the textures to process and what was skipped.
#[derive(Clone, Debug)]
pub struct Model {
    pub bindings: Vec<TextureBinding>,
    pub skipped: Vec<Skipped>,
}
