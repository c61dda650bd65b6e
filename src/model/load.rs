//! Loading glTF 2.0 (`.gltf` and `.glb`) into a [`Model`].
//!
//! Everything that comes from the file is treated as hostile: the container,
//! the JSON, every offset and index is checked before it is used, and
//! external references resolve only to files inside the model's folder.
//! The `gltf` crate parses and schema-validates the JSON; the GLB container,
//! buffers, images and accessor data are handled here, because the crate's
//! importer refuses data-URI images and its readers assume valid offsets.

use std::borrow::Cow;
use std::collections::hash_map::Entry;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::io;
use std::path::{Path, PathBuf};

use gltf::json;
use gltf::json::accessor::{ComponentType, Type};
use gltf::json::mesh::{Mode, Semantic};
use gltf::json::validation::Checked;

use super::image::{ImageHeader, Texture, TextureError};
use super::sniff::Foreign;
use super::{AlphaUse, Model, Skipped, TextureBinding, UvTriangle, Wrap};

/// What to load and how much to trust.
#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Also process occlusion and metallic-roughness maps.
    pub extra_maps: bool,
    /// Largest accepted texture width and height, checked before decoding.
    pub max_texture_size: u32,
    /// Most triangles accepted over all bindings. Primitives may share one
    /// index accessor, so a small file can describe an enormous mesh.
    pub max_triangles: usize,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            extra_maps: false,
            max_texture_size: 16384,
            max_triangles: 1 << 25,
        }
    }
}

/// Largest file a model may refer to (an image, or a buffer whose
/// byteLength says so): what one job may read into memory.
const MAX_FILE_BYTES: u64 = 2 << 30;

/// How much longer than its byteLength a buffer file may be (padding,
/// trailing bytes some exporters leave); a longer one is refused unread.
const BUFFER_SLACK: u64 = 64 << 10;

/// Extensions that may appear in `extensionsRequired`: the ones this loader
/// applies (texture transform, quantized attributes) or that cannot change
/// which texels the triangles sample (emissive strength).
pub const SUPPORTED_REQUIRED_EXTENSIONS: &[&str] = &[
    "KHR_texture_transform",
    "KHR_mesh_quantization",
    "KHR_materials_emissive_strength",
];

/// A failed load: which file, and what is wrong with it. Displays as one line.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {kind}")]
pub struct LoadError {
    /// The model file as the caller named it.
    pub file: String,
    pub kind: LoadErrorKind,
}

impl LoadError {
    /// True when the input is at fault (CLI exit status 2); false for
    /// failures of the machine or the program (exit status 1).
    pub fn is_bad_input(&self) -> bool {
        self.kind.is_bad_input()
    }
}

/// What went wrong. Messages carry their own context (which buffer, accessor,
/// mesh, primitive) and hold no line breaks.
#[derive(Debug, thiserror::Error)]
pub enum LoadErrorKind {
    /// The operating system failed to read a file that exists (or the model
    /// file itself, which may not exist).
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: io::Error },
    /// A file the model refers to is not there.
    #[error("{what}: file \"{uri}\" not found")]
    Missing { what: String, uri: String },
    /// A URI that is not allowed to be followed.
    #[error("{what}: URI \"{uri}\" refused: {reason}")]
    Refused {
        what: String,
        uri: String,
        reason: String,
    },
    /// The container or JSON cannot be parsed, or fails the glTF schema.
    #[error("{0}")]
    Malformed(String),
    /// Not glTF at all: another format, named, or nothing recognised.
    #[error("{0}")]
    NotGltf(Foreign),
    #[error("required extension {0} is not supported")]
    UnsupportedExtension(String),
    /// Parsed, but the data is inconsistent: ranges, indices, counts,
    /// non-finite values.
    #[error("{0}")]
    Invalid(String),
    #[error("image {image}: {source}")]
    Texture { image: usize, source: TextureError },
}

impl LoadErrorKind {
    pub fn is_bad_input(&self) -> bool {
        match self {
            LoadErrorKind::Io { source, .. } => matches!(
                source.kind(),
                io::ErrorKind::NotFound | io::ErrorKind::IsADirectory
            ),
            LoadErrorKind::Texture { source, .. } => source.is_bad_input(),
            _ => true,
        }
    }
}

/// Why a [`Resolver`] could not supply a file.
#[derive(Debug, thiserror::Error)]
pub enum ResolveError {
    #[error("not found")]
    NotFound,
    /// The name is inside the folder but what it points at is not (a symlink).
    #[error("resolves outside the model's folder")]
    Escapes,
    #[error("not a regular file")]
    NotAFile,
    #[error("{0}")]
    Io(#[from] io::Error),
}

/// Supplies the files a model refers to.
///
/// `path` is always relative, `/`-separated, made only of normal components
/// (no `.`, `..`, empty, or absolute parts), percent-decoded: the loader has
/// already refused everything else.
pub trait Resolver {
    fn read(&self, path: &str) -> Result<Cow<'_, [u8]>, ResolveError>;

    /// The file's size in bytes, without reading it where that is possible,
    /// so a file far larger than the model declares is refused unread.
    fn len(&self, path: &str) -> Result<u64, ResolveError> {
        self.read(path).map(|b| b.len() as u64)
    }

    /// Whether `read` would succeed, for files the model names but that
    /// are not processed.
    fn check(&self, path: &str) -> Result<(), ResolveError> {
        self.read(path).map(drop)
    }
}

/// Files inside one folder on disk.
#[derive(Clone, Debug)]
pub struct DirResolver {
    root: PathBuf,
}

impl DirResolver {
    pub fn new(dir: &Path) -> io::Result<Self> {
        Ok(DirResolver {
            root: dir.canonicalize()?,
        })
    }

    fn locate(&self, path: &str) -> Result<PathBuf, ResolveError> {
        let joined = path
            .split('/')
            .fold(self.root.clone(), |acc, part| acc.join(part));
        let real = match joined.canonicalize() {
            Ok(p) => p,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Err(ResolveError::NotFound),
            Err(e) => return Err(ResolveError::Io(e)),
        };
        if !real.starts_with(&self.root) {
            return Err(ResolveError::Escapes);
        }
        if !real.metadata()?.is_file() {
            return Err(ResolveError::NotAFile);
        }
        Ok(real)
    }
}

impl Resolver for DirResolver {
    fn read(&self, path: &str) -> Result<Cow<'_, [u8]>, ResolveError> {
        let real = self.locate(path)?;
        Ok(Cow::Owned(std::fs::read(real)?))
    }

    fn check(&self, path: &str) -> Result<(), ResolveError> {
        self.locate(path).map(drop)
    }

    fn len(&self, path: &str) -> Result<u64, ResolveError> {
        Ok(self.locate(path)?.metadata()?.len())
    }
}

/// In-memory files keyed by their path relative to the model, `/`-separated
/// (`"scene.bin"`, `"textures/albedo.png"`).
impl Resolver for HashMap<String, Vec<u8>> {
    fn read(&self, path: &str) -> Result<Cow<'_, [u8]>, ResolveError> {
        self.get(path)
            .map(|v| Cow::Borrowed(v.as_slice()))
            .ok_or(ResolveError::NotFound)
    }
}

impl Resolver for BTreeMap<String, Vec<u8>> {
    fn read(&self, path: &str) -> Result<Cow<'_, [u8]>, ResolveError> {
        self.get(path)
            .map(|v| Cow::Borrowed(v.as_slice()))
            .ok_or(ResolveError::NotFound)
    }
}

/// No files at all: for a self-contained `.glb` or `.gltf`.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoFiles;

impl Resolver for NoFiles {
    fn read(&self, _path: &str) -> Result<Cow<'_, [u8]>, ResolveError> {
        Err(ResolveError::NotFound)
    }
}

/// Loads a `.glb`, or a `.gltf` whose external files lie in its folder.
pub fn load(path: &Path, opts: &LoadOptions) -> Result<Model, LoadError> {
    plan(path, opts)?.decode()
}

/// Loads a model from memory. `main_name` names it in errors; `files`
/// supplies what its URIs refer to (a map of name → bytes, a folder, or
/// [`NoFiles`]).
pub fn load_from_memory(
    main_name: &str,
    main: &[u8],
    files: &dyn Resolver,
    opts: &LoadOptions,
) -> Result<Model, LoadError> {
    plan_from_memory(main_name, main, files, opts)?.decode()
}

/// Reads and checks everything of a `.glb` or `.gltf` on disk but the
/// texels: see [`Plan`].
pub fn plan(path: &Path, opts: &LoadOptions) -> Result<Plan, LoadError> {
    let file = printable(&path.display().to_string());
    let io_err = |source: io::Error| LoadError {
        file: file.clone(),
        kind: LoadErrorKind::Io {
            path: file.clone(),
            source,
        },
    };
    let bytes = std::fs::read(path).map_err(io_err)?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let resolver = DirResolver::new(dir).map_err(io_err)?;
    plan_from_memory(&file, &bytes, &resolver, opts)
}

/// [`plan`] for a model in memory, as [`load_from_memory`] takes it.
pub fn plan_from_memory(
    main_name: &str,
    main: &[u8],
    files: &dyn Resolver,
    opts: &LoadOptions,
) -> Result<Plan, LoadError> {
    // Images without a name of their own are called after the model, so
    // that a batch's files do not all say `image0`.
    let stem = Path::new(main_name)
        .file_stem()
        .map(|s| sanitize(&s.to_string_lossy()))
        .unwrap_or_default();
    match Loader::run(main, files, opts, &stem) {
        Ok(mut plan) => {
            plan.file = printable(main_name);
            Ok(plan)
        }
        Err(kind) => Err(LoadError {
            file: printable(main_name),
            kind,
        }),
    }
}

/// A model read and checked up to its images' headers: every container,
/// buffer, accessor and URI, the triangles of each texture, and each
/// image's size and channels; no texel decoded yet. What a job will cost
/// is known from it (`crate::budget`) before any large allocation.
#[derive(Clone, Debug)]
pub struct Plan {
    file: String,
    pub textures: Vec<PlannedTexture>,
    pub skipped: Vec<Skipped>,
    /// Which primitive samples which image, and how: what a level of
    /// detail of that primitive is measured against.
    pub samplings: Vec<Sampling>,
    max_texture_size: u32,
}

/// One primitive sampling one image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sampling {
    pub mesh: usize,
    pub primitive: usize,
    pub image: usize,
    /// The TEXCOORD set, and the KHR_texture_transform applied to it (a
    /// row-major 2×3 affine map), as the image's triangles have them.
    pub set: u32,
    pub transform: Option<[f64; 6]>,
}

impl Sampling {
    /// A UV of the set, as the image's triangles have it.
    pub fn uv(&self, uv: [f32; 2]) -> [f64; 2] {
        apply(self.transform, uv)
    }
}

/// One texture of a [`Plan`]: a [`TextureBinding`] whose image is still encoded.
#[derive(Clone, Debug)]
pub struct PlannedTexture {
    pub image: usize,
    pub name: String,
    pub header: ImageHeader,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    pub srgb: bool,
    /// A KHR_texture_transform that samples it rotates the UVs.
    pub rotated: bool,
    /// How its materials use its alpha channel.
    pub alpha: AlphaUse,
    pub triangles: Vec<UvTriangle>,
    bytes: Vec<u8>,
}

impl Plan {
    /// The model file, as errors name it.
    pub fn file(&self) -> &str {
        &self.file
    }

    /// Decodes every image: the loaded model.
    pub fn decode(self) -> Result<Model, LoadError> {
        let started = std::time::Instant::now();
        let mut bindings = Vec::with_capacity(self.textures.len());
        for t in self.textures {
            let image = t.image;
            let texture =
                Texture::decode(&t.bytes, self.max_texture_size).map_err(|source| LoadError {
                    file: self.file.clone(),
                    kind: LoadErrorKind::Texture { image, source },
                })?;
            tracing::debug!(
                image,
                name = t.name.as_str(),
                width = texture.width,
                height = texture.height,
                channels = texture.channels,
                triangles = t.triangles.len(),
                "texture bound"
            );
            bindings.push(TextureBinding {
                image,
                name: t.name,
                texture,
                wrap_s: t.wrap_s,
                wrap_t: t.wrap_t,
                srgb: t.srgb,
                rotated: t.rotated,
                alpha: t.alpha,
                triangles: t.triangles,
            });
        }
        tracing::info!(
            file = self.file.as_str(),
            textures = bindings.len(),
            skipped = self.skipped.len(),
            ms = started.elapsed().as_millis() as u64,
            "model loaded"
        );
        Ok(Model {
            bindings,
            skipped: self.skipped,
        })
    }
}

/// Control characters would break the one-line error contract.
fn printable(s: &str) -> String {
    s.chars()
        .map(|c| if c.is_control() { '?' } else { c })
        .collect()
}

fn invalid(msg: impl Into<String>) -> LoadErrorKind {
    LoadErrorKind::Invalid(printable(&msg.into()))
}

fn malformed(msg: impl Into<String>) -> LoadErrorKind {
    LoadErrorKind::Malformed(printable(&msg.into()))
}

// ---------------------------------------------------------------- container

struct Container<'a> {
    json: &'a [u8],
    bin: Option<&'a [u8]>,
}

fn read_u32(b: &[u8], at: usize) -> Option<u32> {
    let s = b.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

fn split_container(bytes: &[u8]) -> Result<Container<'_>, LoadErrorKind> {
    if let Some(foreign) = Foreign::sniff(bytes) {
        return Err(LoadErrorKind::NotGltf(foreign));
    }
    if !bytes.starts_with(b"glTF") {
        let json = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        return Ok(Container { json, bin: None });
    }
    let bad = |m: String| malformed(format!("GLB: {m}"));
    let version = read_u32(bytes, 4).ok_or_else(|| bad("truncated header".into()))?;
    if version != 2 {
        return Err(bad(format!("version {version}, only 2 is supported")));
    }
    let length = read_u32(bytes, 8).ok_or_else(|| bad("truncated header".into()))? as usize;
    if length > bytes.len() {
        return Err(bad(format!(
            "header says {length} bytes, file has {}",
            bytes.len()
        )));
    }
    if length < 20 {
        return Err(bad(format!("length {length} leaves no room for a chunk")));
    }
    let body = &bytes[..length];
    let mut at = 12usize;
    let mut json = None;
    let mut bin = None;
    while at + 8 <= body.len() {
        let (Some(len), Some(ty)) = (read_u32(body, at), body.get(at + 4..at + 8)) else {
            break;
        };
        let start = at + 8;
        let end = start
            .checked_add(len as usize)
            .filter(|&e| e <= body.len())
            .ok_or_else(|| {
                bad(format!(
                    "chunk at byte {at} claims {len} bytes, past the end ({length})"
                ))
            })?;
        let data = &body[start..end];
        match ty {
            b"JSON" if json.is_none() && at == 12 => json = Some(data),
            b"BIN\0" if json.is_some() && bin.is_none() => bin = Some(data),
            _ if at == 12 => return Err(bad("first chunk is not JSON".into())),
            // Unknown chunks are to be ignored (glTF 2.0 §4.4.3.1).
            _ => {}
        }
        at = end.saturating_add(3) & !3;
    }
    let json = json.ok_or_else(|| bad("no JSON chunk".into()))?;
    Ok(Container { json, bin })
}

fn parse_root(json_bytes: &[u8]) -> Result<json::Root, LoadErrorKind> {
    // `Root::from_slice` and `Document::from_json` are not generic: their
    // serde and validation code is compiled once in gltf-json and gltf, not
    // again (unoptimised, twice) in this crate.
    let parse = || {
        json::Root::from_slice(json_bytes).map_err(|e| malformed(format!("invalid glTF JSON: {e}")))
    };
    let root = parse()?;

    for ext in &root.extensions_required {
        if !SUPPORTED_REQUIRED_EXTENSIONS.contains(&ext.as_str()) {
            return Err(LoadErrorKind::UnsupportedExtension(printable(ext)));
        }
    }
    // gltf-json's primitive check indexes the accessor array with the
    // POSITION index before anything has checked it.
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            for (sem, acc) in &prim.attributes {
                if acc.value() >= root.accessors.len() {
                    return Err(malformed(format!(
                        "mesh {m} primitive {p}: attribute {} refers to accessor {}, there are {}",
                        semantic_name(sem),
                        acc.value(),
                        root.accessors.len()
                    )));
                }
            }
        }
    }

    let errors: Vec<String> = match gltf::Document::from_json(root) {
        Ok(document) => return Ok(document.into_json()),
        Err(gltf::Error::Validation(errors)) => errors
            .iter()
            // Required extensions were judged above, against what this
            // loader honours rather than what gltf-json knows.
            .filter(|(path, _)| !path.as_str().starts_with("extensionsRequired"))
            .map(|(path, err)| format!("{}: {}", path.as_str(), err))
            .collect(),
        Err(e) => vec![e.to_string()],
    };
    if let Some(first) = errors.first() {
        let more = match errors.len() {
            1 => String::new(),
            n => format!(" (and {} more)", n - 1),
        };
        return Err(malformed(format!("invalid glTF: {first}{more}")));
    }
    // Only required extensions that gltf-json does not know were reported,
    // and the check consumed the document: parse it again.
    parse()
}

fn semantic_name(s: &Checked<Semantic>) -> String {
    match s {
        Checked::Valid(Semantic::Positions) => "POSITION".into(),
        Checked::Valid(Semantic::Normals) => "NORMAL".into(),
        Checked::Valid(Semantic::Tangents) => "TANGENT".into(),
        Checked::Valid(Semantic::Colors(n)) => format!("COLOR_{n}"),
        Checked::Valid(Semantic::TexCoords(n)) => format!("TEXCOORD_{n}"),
        Checked::Valid(Semantic::Joints(n)) => format!("JOINTS_{n}"),
        Checked::Valid(Semantic::Weights(n)) => format!("WEIGHTS_{n}"),
        Checked::Valid(Semantic::Extras(s)) => s.clone(),
        Checked::Invalid => "(invalid)".into(),
    }
}

// --------------------------------------------------------------------- URIs

enum UriTarget<'u> {
    /// The part after `data:`.
    Data(&'u str),
    /// A checked relative path, percent-decoded.
    File(String),
}

fn is_data_uri(uri: &str) -> bool {
    uri.get(..5)
        .is_some_and(|head| head.eq_ignore_ascii_case("data:"))
}

/// The checked, percent-decoded relative path a URI names, or `None` for a
/// data URI or one that is refused.
pub(crate) fn relative_file(uri: &str) -> Option<String> {
    match classify_uri(uri) {
        Ok(UriTarget::File(path)) => Some(path),
        _ => None,
    }
}

/// Classifies a URI, refusing anything that could leave the model's folder.
fn classify_uri(uri: &str) -> Result<UriTarget<'_>, String> {
    if is_data_uri(uri) {
        return Ok(UriTarget::Data(uri.get(5..).unwrap_or("")));
    }
    if uri.is_empty() {
        return Err("empty URI".into());
    }
    // RFC 3986: a scheme is the part before the first ':' when it precedes
    // any '/', '?' or '#'.
    let head = uri.split(['/', '?', '#']).next().unwrap_or("");
    if let Some((scheme, _)) = head.split_once(':') {
        return Err(format!(
            "scheme \"{scheme}:\" is not allowed, only relative paths and data: URIs are"
        ));
    }
    let decoded = percent_encoding::percent_decode_str(uri)
        .decode_utf8()
        .map_err(|_| "not UTF-8 after percent-decoding".to_string())?;
    if decoded.starts_with('/') {
        return Err("absolute path".into());
    }
    let mut parts = Vec::new();
    for part in decoded.split('/') {
        match part {
            "" | "." => continue,
            ".." => return Err("\"..\" would leave the model's folder".into()),
            _ => {}
        }
        if part.contains(['\\', ':', '\0']) {
            return Err("path component with '\\', ':' or NUL".into());
        }
        parts.push(part);
    }
    if parts.is_empty() {
        return Err("names no file".into());
    }
    Ok(UriTarget::File(parts.join("/")))
}

fn decode_data_uri(rest: &str) -> Result<Vec<u8>, String> {
    use base64::engine::{DecodePaddingMode, GeneralPurpose, GeneralPurposeConfig};
    use base64::Engine as _;
    let (meta, data) = rest
        .split_once(',')
        .ok_or_else(|| "data: URI without ','".to_string())?;
    let is_base64 = meta
        .rsplit(';')
        .next()
        .is_some_and(|p| p.trim().eq_ignore_ascii_case("base64"));
    if !is_base64 {
        return Ok(percent_encoding::percent_decode_str(data).collect());
    }
    let engine = GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        GeneralPurposeConfig::new()
            .with_decode_padding_mode(DecodePaddingMode::Indifferent)
            .with_decode_allow_trailing_bits(true),
    );
    let data: Cow<'_, str> = if data.contains('%') {
        percent_encoding::percent_decode_str(data).decode_utf8_lossy()
    } else {
        Cow::Borrowed(data)
    };
    let cleaned: Vec<u8> = data.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
    engine
        .decode(cleaned)
        .map_err(|e| format!("bad base64 in data: URI: {e}"))
}

/// Short form of a URI for messages: data URIs are huge.
fn uri_for_message(uri: &str) -> String {
    if is_data_uri(uri) {
        return "data:…".into();
    }
    let mut s: String = uri.chars().take(200).collect();
    if s.len() < uri.len() {
        s.push('…');
    }
    printable(&s)
}

/// Reads what `uri` names, refusing (unread) a file of more than `max_len`
/// bytes.
fn fetch<'r>(
    what: &str,
    uri: &str,
    files: &'r dyn Resolver,
    max_len: u64,
) -> Result<Cow<'r, [u8]>, LoadErrorKind> {
    let refused = |reason: String| LoadErrorKind::Refused {
        what: what.to_string(),
        uri: uri_for_message(uri),
        reason: printable(&reason),
    };
    match classify_uri(uri).map_err(refused)? {
        UriTarget::Data(rest) => decode_data_uri(rest)
            .map(Cow::Owned)
            .map_err(|e| invalid(format!("{what}: {e}"))),
        UriTarget::File(path) => {
            let len = files
                .len(&path)
                .map_err(|e| resolve_error(what, uri, &path, e))?;
            if len > max_len {
                return Err(refused(format!(
                    "the file holds {len} bytes, more than the {max_len} accepted"
                )));
            }
            files
                .read(&path)
                .map_err(|e| resolve_error(what, uri, &path, e))
        }
    }
}

fn check_uri(what: &str, uri: &str, files: &dyn Resolver) -> Result<(), LoadErrorKind> {
    match classify_uri(uri) {
        Err(reason) => Err(LoadErrorKind::Refused {
            what: what.to_string(),
            uri: uri_for_message(uri),
            reason: printable(&reason),
        }),
        Ok(UriTarget::Data(_)) => Ok(()),
        Ok(UriTarget::File(path)) => files
            .check(&path)
            .map_err(|e| resolve_error(what, uri, &path, e)),
    }
}

fn resolve_error(what: &str, uri: &str, path: &str, e: ResolveError) -> LoadErrorKind {
    match e {
        ResolveError::NotFound => LoadErrorKind::Missing {
            what: what.to_string(),
            uri: uri_for_message(uri),
        },
        ResolveError::Escapes => LoadErrorKind::Refused {
            what: what.to_string(),
            uri: uri_for_message(uri),
            reason: "resolves outside the model's folder".into(),
        },
        ResolveError::NotAFile => invalid(format!(
            "{what}: \"{}\" is not a regular file",
            uri_for_message(uri)
        )),
        // A name the system cannot even look up is the model's fault.
        ResolveError::Io(source) if source.raw_os_error() == Some(libc::ENAMETOOLONG) => {
            LoadErrorKind::Refused {
                what: what.to_string(),
                uri: uri_for_message(uri),
                reason: "the name is too long".into(),
            }
        }
        ResolveError::Io(source) => LoadErrorKind::Io {
            path: uri_for_message(path),
            source,
        },
    }
}

// ---------------------------------------------------------------- accessors

#[derive(Clone, Copy, Debug)]
struct ViewInfo {
    buffer: usize,
    start: usize,
    len: usize,
    stride: Option<usize>,
}

#[derive(Clone, Copy, Debug)]
struct Span {
    view: usize,
    offset: usize,
    stride: usize,
}

#[derive(Clone, Copy, Debug)]
struct SparseInfo {
    count: usize,
    index_type: ComponentType,
    indices: Span,
    values: Span,
}

#[derive(Clone, Copy, Debug)]
struct AccessorInfo {
    ct: ComponentType,
    ty: Type,
    normalized: bool,
    count: usize,
    elem: usize,
    base: Option<Span>,
    sparse: Option<SparseInfo>,
}

fn type_name(t: Type) -> &'static str {
    match t {
        Type::Scalar => "SCALAR",
        Type::Vec2 => "VEC2",
        Type::Vec3 => "VEC3",
        Type::Vec4 => "VEC4",
        Type::Mat2 => "MAT2",
        Type::Mat3 => "MAT3",
        Type::Mat4 => "MAT4",
    }
}

fn component_name(c: ComponentType) -> &'static str {
    match c {
        ComponentType::I8 => "BYTE",
        ComponentType::U8 => "UNSIGNED_BYTE",
        ComponentType::I16 => "SHORT",
        ComponentType::U16 => "UNSIGNED_SHORT",
        ComponentType::U32 => "UNSIGNED_INT",
        ComponentType::F32 => "FLOAT",
    }
}

/// Bytes of one element; matrix columns are padded to 4 bytes (glTF §3.6.2.4).
fn element_size(ct: ComponentType, ty: Type) -> usize {
    let c = ct.size();
    let (cols, rows) = match ty {
        Type::Mat2 => (2, 2),
        Type::Mat3 => (3, 3),
        Type::Mat4 => (4, 4),
        other => return c * other.multiplicity(),
    };
    cols * ((rows * c + 3) & !3)
}

fn to_usize(v: u64, what: &str) -> Result<usize, LoadErrorKind> {
    usize::try_from(v).map_err(|_| invalid(format!("{what}: {v} is too large")))
}

/// Checks that `count` elements of `elem` bytes, `stride` apart, starting at
/// `offset` in `view`, lie inside it.
fn check_span(
    what: &str,
    views: &[ViewInfo],
    view: usize,
    offset: usize,
    stride: usize,
    count: usize,
    elem: usize,
) -> Result<(), LoadErrorKind> {
    let v = views
        .get(view)
        .ok_or_else(|| invalid(format!("{what}: bufferView {view} does not exist")))?;
    let end = stride
        .checked_mul(count - 1)
        .and_then(|n| n.checked_add(offset))
        .and_then(|n| n.checked_add(elem));
    match end {
        Some(end) if end <= v.len => Ok(()),
        _ => Err(invalid(format!(
            "{what}: {count} elements of {elem} bytes at offset {offset}, stride {stride} \
             do not fit in bufferView {view} ({} bytes)",
            v.len
        ))),
    }
}

fn accessor_info(
    i: usize,
    acc: &json::Accessor,
    views: &[ViewInfo],
    buffer_bytes: usize,
) -> Result<AccessorInfo, LoadErrorKind> {
    let what = format!("accessor {i}");
    let ct = match acc.component_type {
        Checked::Valid(json::accessor::GenericComponentType(ct)) => ct,
        Checked::Invalid => return Err(invalid(format!("{what}: invalid componentType"))),
    };
    let ty = match acc.type_ {
        Checked::Valid(t) => t,
        Checked::Invalid => return Err(invalid(format!("{what}: invalid type"))),
    };
    let count = to_usize(acc.count.0, &what)?;
    if count == 0 {
        return Err(invalid(format!("{what}: count is 0")));
    }
    let elem = element_size(ct, ty);
    let offset = to_usize(acc.byte_offset.map_or(0, |o| o.0), &what)?;
    let base = match acc.buffer_view {
        Some(view) => {
            let view = view.value();
            let declared = views.get(view).and_then(|v| v.stride);
            let stride = declared.unwrap_or(elem);
            if stride < elem {
                return Err(invalid(format!(
                    "{what}: byteStride {stride} of bufferView {view} is smaller than its \
                     {elem}-byte elements"
                )));
            }
            check_span(&what, views, view, offset, stride, count, elem)?;
            Some(Span {
                view,
                offset,
                stride,
            })
        }
        // Only sparse accessors may lack a view; their size is not backed
        // by data, so bound it by what the file could plausibly describe.
        None if count > buffer_bytes.max(1 << 16) => {
            return Err(invalid(format!(
                "{what}: count {count} without a bufferView is implausible for \
                 {buffer_bytes} bytes of buffers"
            )))
        }
        None => None,
    };
    let sparse = match &acc.sparse {
        None => None,
        Some(s) => {
            let sw = format!("{what} sparse");
            let scount = to_usize(s.count.0, &sw)?;
            if scount == 0 || scount > count {
                return Err(invalid(format!(
                    "{sw}: count {scount} is not within 1..={count}"
                )));
            }
            let index_type = match s.indices.component_type {
                Checked::Valid(json::accessor::IndexComponentType(t)) => t,
                Checked::Invalid => {
                    return Err(invalid(format!("{sw}: invalid index componentType")))
                }
            };
            let isize_ = index_type.size();
            let indices = Span {
                view: s.indices.buffer_view.value(),
                offset: to_usize(s.indices.byte_offset.0, &sw)?,
                stride: isize_,
            };
            check_span(
                &format!("{sw} indices"),
                views,
                indices.view,
                indices.offset,
                isize_,
                scount,
                isize_,
            )?;
            let values = Span {
                view: s.values.buffer_view.value(),
                offset: to_usize(s.values.byte_offset.0, &sw)?,
                stride: elem,
            };
            check_span(
                &format!("{sw} values"),
                views,
                values.view,
                values.offset,
                elem,
                scount,
                elem,
            )?;
            Some(SparseInfo {
                count: scount,
                index_type,
                indices,
                values,
            })
        }
    };
    Ok(AccessorInfo {
        ct,
        ty,
        normalized: acc.normalized,
        count,
        elem,
        base,
        sparse,
    })
}

fn component_f32(b: &[u8], ct: ComponentType, normalized: bool) -> f32 {
    match (ct, normalized) {
        (ComponentType::F32, _) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        (ComponentType::U8, true) => f32::from(b[0]) / 255.0,
        (ComponentType::U8, false) => f32::from(b[0]),
        (ComponentType::I8, true) => (f32::from(b[0] as i8) / 127.0).max(-1.0),
        (ComponentType::I8, false) => f32::from(b[0] as i8),
        (ComponentType::U16, true) => f32::from(u16::from_le_bytes([b[0], b[1]])) / 65535.0,
        (ComponentType::U16, false) => f32::from(u16::from_le_bytes([b[0], b[1]])),
        (ComponentType::I16, true) => {
            (f32::from(i16::from_le_bytes([b[0], b[1]])) / 32767.0).max(-1.0)
        }
        (ComponentType::I16, false) => f32::from(i16::from_le_bytes([b[0], b[1]])),
        (ComponentType::U32, true) => {
            (f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])) / 4294967295.0) as f32
        }
        (ComponentType::U32, false) => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
    }
}

fn component_u32(b: &[u8], ct: ComponentType) -> u32 {
    match ct {
        ComponentType::U8 => u32::from(b[0]),
        ComponentType::U16 => u32::from(u16::from_le_bytes([b[0], b[1]])),
        _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
    }
}

// ------------------------------------------------------------------- loader

/// One way a material samples an image.
#[derive(Clone, Copy, Debug)]
struct TexUse {
    image: usize,
    role: &'static str,
    set: u32,
    /// Row-major 2×3 affine map from KHR_texture_transform.
    transform: Option<[f64; 6]>,
    wrap: (Wrap, Wrap),
    srgb: bool,
    alpha: AlphaUse,
}

struct MaterialUses {
    /// Per material, the images it samples, in a fixed order.
    uses: Vec<Vec<TexUse>>,
    /// Images used as tangent-space normal maps → first material doing so.
    normal_maps: BTreeMap<usize, usize>,
}

/// Where a texture is used, for messages and the sRGB flag.
#[derive(Clone, Copy)]
struct UseSite {
    material: usize,
    role: &'static str,
    srgb: bool,
}

#[derive(Default)]
struct BindingBuilder {
    wrap: Option<(Wrap, Wrap)>,
    srgb: bool,
    rotated: bool,
    alpha: AlphaUse,
    triangles: Vec<UvTriangle>,
}

struct Loader<'a> {
    root: json::Root,
    buffers: Vec<Cow<'a, [u8]>>,
    views: Vec<ViewInfo>,
    accessors: Vec<AccessorInfo>,
}

impl<'a> Loader<'a> {
    fn run(
        main: &'a [u8],
        files: &'a dyn Resolver,
        opts: &LoadOptions,
        stem: &str,
    ) -> Result<Plan, LoadErrorKind> {
        let container = split_container(main)?;
        let root = parse_root(container.json)?;
        let buffers = load_buffers(&root, container.bin, files)?;
        let views = view_infos(&root, &buffers)?;
        let buffer_bytes = buffers.iter().map(|b| b.len()).sum();
        let accessors = root
            .accessors
            .iter()
            .enumerate()
            .map(|(i, a)| accessor_info(i, a, &views, buffer_bytes))
            .collect::<Result<Vec<_>, _>>()?;
        let loader = Loader {
            root,
            buffers,
            views,
            accessors,
        };
        loader.check_images(files)?;
        loader.plan(files, opts, stem)
    }

    fn view_bytes(&self, view: usize) -> Result<&[u8], LoadErrorKind> {
        self.views
            .get(view)
            .and_then(|v| {
                self.buffers
                    .get(v.buffer)?
                    .get(v.start..v.start.checked_add(v.len)?)
            })
            .ok_or_else(|| invalid(format!("bufferView {view} is out of range")))
    }

    /// Reads every element of an accessor (sparse substitution applied)
    /// through `parse`, which receives exactly one element's bytes.
    fn collect<T: Copy>(
        &self,
        idx: usize,
        what: &str,
        zero: T,
        parse: impl Fn(&[u8]) -> T,
    ) -> Result<Vec<T>, LoadErrorKind> {
        let info = self.accessor(idx, what)?;
        let oob = || invalid(format!("{what}: data out of range"));
        let mut out = match info.base {
            Some(span) => {
                let bytes = self.view_bytes(span.view)?;
                let mut v = Vec::with_capacity(info.count);
                for k in 0..info.count {
                    let at = span.offset + k * span.stride;
                    v.push(parse(bytes.get(at..at + info.elem).ok_or_else(oob)?));
                }
                v
            }
            None => vec![zero; info.count],
        };
        if let Some(s) = info.sparse {
            let ib = self.view_bytes(s.indices.view)?;
            let vb = self.view_bytes(s.values.view)?;
            let isz = s.index_type.size();
            let mut prev: Option<usize> = None;
            for k in 0..s.count {
                let at = s.indices.offset + k * isz;
                let target =
                    component_u32(ib.get(at..at + isz).ok_or_else(oob)?, s.index_type) as usize;
                if target >= info.count || prev.is_some_and(|p| target <= p) {
                    return Err(invalid(format!(
                        "{what}: sparse index {target} is out of order or out of range for {} elements",
                        info.count
                    )));
                }
                prev = Some(target);
                let at = s.values.offset + k * info.elem;
                out[target] = parse(vb.get(at..at + info.elem).ok_or_else(oob)?);
            }
        }
        Ok(out)
    }

    fn accessor(&self, idx: usize, what: &str) -> Result<&AccessorInfo, LoadErrorKind> {
        self.accessors
            .get(idx)
            .ok_or_else(|| invalid(format!("{what}: accessor does not exist")))
    }

    /// Reads a float vector attribute, accepting the component types glTF
    /// (with KHR_mesh_quantization) allows for it.
    fn read_vec<const N: usize>(
        &self,
        idx: usize,
        what: &str,
        ty: Type,
    ) -> Result<Vec<[f32; N]>, LoadErrorKind> {
        let info = *self.accessor(idx, what)?;
        if info.ty != ty || ty.multiplicity() != N {
            return Err(invalid(format!(
                "{what}: type {}, expected {}",
                type_name(info.ty),
                type_name(ty)
            )));
        }
        if info.ct == ComponentType::U32 {
            return Err(invalid(format!(
                "{what}: component type {} is not allowed for vertex attributes",
                component_name(info.ct)
            )));
        }
        let cs = info.ct.size();
        let values = self.collect(idx, what, [0.0f32; N], |b| {
            let mut out = [0.0f32; N];
            for (c, o) in out.iter_mut().enumerate() {
                *o = component_f32(&b[c * cs..], info.ct, info.normalized);
            }
            out
        })?;
        if let Some(k) = values.iter().position(|v| v.iter().any(|x| !x.is_finite())) {
            return Err(invalid(format!("{what}: element {k} is not finite")));
        }
        Ok(values)
    }

    fn read_indices(&self, idx: usize, what: &str) -> Result<Vec<u32>, LoadErrorKind> {
        let info = *self.accessor(idx, what)?;
        if info.ty != Type::Scalar
            || !matches!(
                info.ct,
                ComponentType::U8 | ComponentType::U16 | ComponentType::U32
            )
        {
            return Err(invalid(format!(
                "{what}: {} {} cannot hold indices",
                type_name(info.ty),
                component_name(info.ct)
            )));
        }
        self.collect(idx, what, 0u32, |b| component_u32(b, info.ct))
    }

    /// Every image a URI names must be reachable, whether processed or not:
    /// a model with a dangling or escaping reference is broken.
    fn check_images(&self, files: &dyn Resolver) -> Result<(), LoadErrorKind> {
        for (i, img) in self.root.images.iter().enumerate() {
            match (&img.uri, &img.buffer_view) {
                (Some(uri), None) => check_uri(&format!("image {i}"), uri, files)?,
                (None, Some(view)) => {
                    self.view_bytes(view.value())?;
                }
                _ => {
                    return Err(invalid(format!(
                        "image {i}: needs exactly one of uri and bufferView"
                    )))
                }
            }
        }
        Ok(())
    }

    fn image_bytes(
        &self,
        i: usize,
        files: &'a dyn Resolver,
    ) -> Result<Cow<'_, [u8]>, LoadErrorKind> {
        let img = &self.root.images[i];
        match (&img.uri, &img.buffer_view) {
            (Some(uri), _) => fetch(&format!("image {i}"), uri, files, MAX_FILE_BYTES),
            (None, Some(view)) => Ok(Cow::Borrowed(self.view_bytes(view.value())?)),
            (None, None) => Err(invalid(format!("image {i}: no uri and no bufferView"))),
        }
    }

    fn texture_use(
        &self,
        info: &json::texture::Info,
        role: &'static str,
        srgb: bool,
        material: usize,
    ) -> Result<TexUse, LoadErrorKind> {
        let transform = info
            .extensions
            .as_ref()
            .and_then(|e| e.texture_transform.as_ref());
        let at = UseSite {
            material,
            role,
            srgb,
        };
        self.make_use(info.index.value(), info.tex_coord, transform, at)
    }

    /// gltf-json types KHR_texture_transform only on plain texture infos;
    /// on the occlusion texture it stays raw JSON.
    fn occlusion_use(
        &self,
        occ: &json::material::OcclusionTexture,
        material: usize,
    ) -> Result<TexUse, LoadErrorKind> {
        let raw = occ
            .extensions
            .as_ref()
            .and_then(|e| e.others.get("KHR_texture_transform"));
        let transform: Option<json::extensions::texture::TextureTransform> = raw
            .map(|v| json::deserialize::from_value(v.clone()))
            .transpose()
            .map_err(|e| {
                malformed(format!(
                    "material {material} occlusionTexture: bad KHR_texture_transform: {e}"
                ))
            })?;
        let at = UseSite {
            material,
            role: "occlusionTexture",
            srgb: false,
        };
        self.make_use(occ.index.value(), occ.tex_coord, transform.as_ref(), at)
    }

    fn make_use(
        &self,
        texture: usize,
        tex_coord: u32,
        tt: Option<&json::extensions::texture::TextureTransform>,
        at: UseSite,
    ) -> Result<TexUse, LoadErrorKind> {
        let UseSite {
            material,
            role,
            srgb,
        } = at;
        let (image, wrap) = self.texture_source(texture)?;
        let mut set = tex_coord;
        let mut transform = None;
        if let Some(t) = tt {
            let [ox, oy] = t.offset.0;
            let r = t.rotation.0;
            let [sx, sy] = t.scale.0;
            if ![ox, oy, r, sx, sy].iter().all(|v| v.is_finite()) {
                return Err(invalid(format!(
                    "material {material} {role}: KHR_texture_transform has non-finite values"
                )));
            }
            let (ox, oy, r, sx, sy) = (
                f64::from(ox),
                f64::from(oy),
                f64::from(r),
                f64::from(sx),
                f64::from(sy),
            );
            let (s, c) = r.sin_cos();
            // T·R·S with R = [[cos, sin], [-sin, cos]] (KHR_texture_transform).
            transform = Some([c * sx, s * sy, ox, -s * sx, c * sy, oy]);
            if let Some(n) = t.tex_coord {
                set = n;
            }
        }
        Ok(TexUse {
            image,
            role,
            set,
            transform,
            wrap,
            srgb,
            alpha: AlphaUse::Opaque,
        })
    }

    fn texture_source(&self, texture: usize) -> Result<(usize, (Wrap, Wrap)), LoadErrorKind> {
        let tex = self
            .root
            .textures
            .get(texture)
            .ok_or_else(|| invalid(format!("texture {texture} does not exist")))?;
        let image = tex.source.value();
        if image >= self.root.images.len() {
            return Err(invalid(format!(
                "texture {texture}: image {image} does not exist"
            )));
        }
        let wrap = match tex.sampler {
            None => (Wrap::Repeat, Wrap::Repeat),
            Some(s) => {
                let s = self.root.samplers.get(s.value()).ok_or_else(|| {
                    invalid(format!(
                        "texture {texture}: sampler {} does not exist",
                        s.value()
                    ))
                })?;
                (to_wrap(&s.wrap_s), to_wrap(&s.wrap_t))
            }
        };
        Ok((image, wrap))
    }

    fn material_uses(&self, opts: &LoadOptions) -> Result<MaterialUses, LoadErrorKind> {
        let mut uses = Vec::with_capacity(self.root.materials.len());
        let mut normal_maps = BTreeMap::new();
        for (m, mat) in self.root.materials.iter().enumerate() {
            let pbr = &mat.pbr_metallic_roughness;
            let mut list = Vec::new();
            if let Some(info) = &pbr.base_color_texture {
                let mut u = self.texture_use(info, "baseColorTexture", true, m)?;
                u.alpha = match mat.alpha_mode {
                    Checked::Valid(json::material::AlphaMode::Opaque) => AlphaUse::Opaque,
                    Checked::Valid(json::material::AlphaMode::Mask) => AlphaUse::Mask {
                        cutoff: mat.alpha_cutoff.map_or(0.5, |c| c.0),
                    },
                    Checked::Valid(json::material::AlphaMode::Blend) => AlphaUse::Blend,
                    Checked::Invalid => {
                        return Err(invalid(format!(
                            "material {m}: alphaMode is not OPAQUE, MASK or BLEND"
                        )))
                    }
                };
                list.push(u);
            }
            if let Some(info) = &mat.emissive_texture {
                list.push(self.texture_use(info, "emissiveTexture", true, m)?);
            }
            if opts.extra_maps {
                if let Some(info) = &pbr.metallic_roughness_texture {
                    list.push(self.texture_use(info, "metallicRoughnessTexture", false, m)?);
                }
                if let Some(occ) = &mat.occlusion_texture {
                    list.push(self.occlusion_use(occ, m)?);
                }
            }
            if let Some(n) = &mat.normal_texture {
                let (image, _) = self.texture_source(n.index.value())?;
                normal_maps.entry(image).or_insert(m);
            }
            uses.push(list);
        }
        Ok(MaterialUses { uses, normal_maps })
    }

    fn plan(
        &self,
        files: &'a dyn Resolver,
        opts: &LoadOptions,
        stem: &str,
    ) -> Result<Plan, LoadErrorKind> {
        let MaterialUses { uses, normal_maps } = self.material_uses(opts)?;
        let mut builders: BTreeMap<usize, BindingBuilder> = BTreeMap::new();
        let mut skipped = Vec::new();
        let mut groups: HashMap<(usize, u32), u32> = HashMap::new();
        let mut total_triangles = 0usize;
        let mut samplings = Vec::new();

        for (m, mesh) in self.root.meshes.iter().enumerate() {
            for (p, prim) in mesh.primitives.iter().enumerate() {
                let here = format!("mesh {m} primitive {p}");
                let pos_idx = prim
                    .attributes
                    .get(&Checked::Valid(Semantic::Positions))
                    .map(|a| a.value())
                    .ok_or_else(|| invalid(format!("{here}: no POSITION attribute")))?;
                let vertex_count = self.accessor(pos_idx, &here)?.count;
                for (sem, acc) in &prim.attributes {
                    let n = self.accessor(acc.value(), &here)?.count;
                    if n != vertex_count {
                        return Err(invalid(format!(
                            "{here}: attribute {} has {n} elements, POSITION has {vertex_count}",
                            semantic_name(sem)
                        )));
                    }
                }
                let indices = match prim.indices {
                    Some(acc) => {
                        let what = format!("accessor {} (indices of {here})", acc.value());
                        let idx = self.read_indices(acc.value(), &what)?;
                        if let Some(&bad) = idx.iter().find(|&&i| i as usize >= vertex_count) {
                            return Err(invalid(format!(
                                "{what}: index {bad} out of range for {vertex_count} vertices"
                            )));
                        }
                        Some(idx)
                    }
                    None => None,
                };

                let material_uses: &[TexUse] = match prim.material {
                    Some(mat) => uses.get(mat.value()).map_or(&[], |u| u.as_slice()),
                    None => &[],
                };
                if material_uses.is_empty() {
                    continue;
                }
                let mode = match prim.mode {
                    Checked::Valid(mode) => mode,
                    Checked::Invalid => return Err(invalid(format!("{here}: invalid mode"))),
                };
                if !matches!(
                    mode,
                    Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
                ) {
                    let name = mode_name(mode);
                    tracing::debug!(mesh = m, primitive = p, mode = name, "primitive skipped");
                    skipped.push(Skipped {
                        image: None,
                        mesh: Some(m),
                        primitive: Some(p),
                        reason: format!("mode {name} has no triangles"),
                    });
                    continue;
                }
                let corners = match &indices {
                    Some(idx) => triangulate(mode, idx),
                    None => {
                        let n = u32::try_from(vertex_count).map_err(|_| {
                            invalid(format!("{here}: {vertex_count} vertices without indices"))
                        })?;
                        triangulate(mode, &(0..n).collect::<Vec<u32>>())
                    }
                };
                let positions: Vec<[f32; 3]> = self.read_vec(
                    pos_idx,
                    &format!("accessor {pos_idx} (POSITION of {here})"),
                    Type::Vec3,
                )?;

                let mut uv_cache: HashMap<u32, Vec<[f32; 2]>> = HashMap::new();
                let mut seen: HashSet<(usize, u32, Option<[u64; 6]>)> = HashSet::new();
                for u in material_uses {
                    let key = (u.image, u.set, u.transform.map(|t| t.map(f64::to_bits)));
                    if !seen.insert(key) {
                        continue;
                    }
                    let Some(uv_acc) = prim
                        .attributes
                        .get(&Checked::Valid(Semantic::TexCoords(u.set)))
                        .map(|a| a.value())
                    else {
                        tracing::warn!(
                            mesh = m,
                            primitive = p,
                            image = u.image,
                            texcoord = u.set,
                            "primitive lacks the TEXCOORD set its material samples"
                        );
                        skipped.push(Skipped {
                            image: Some(u.image),
                            mesh: Some(m),
                            primitive: Some(p),
                            reason: format!(
                                "{} uses TEXCOORD_{}, which the primitive lacks",
                                u.role, u.set
                            ),
                        });
                        continue;
                    };
                    let uvs = match uv_cache.entry(u.set) {
                        Entry::Occupied(e) => e.into_mut(),
                        Entry::Vacant(e) => {
                            let what = format!("accessor {uv_acc} (TEXCOORD_{} of {here})", u.set);
                            e.insert(self.read_vec::<2>(uv_acc, &what, Type::Vec2)?)
                        }
                    };
                    samplings.push(Sampling {
                        mesh: m,
                        primitive: p,
                        image: u.image,
                        set: u.set,
                        transform: u.transform,
                    });
                    let next_group = groups.len() as u32;
                    let group = *groups.entry((m, u.set)).or_insert(next_group);
                    let b = builders.entry(u.image).or_default();
                    match b.wrap {
                        None => b.wrap = Some(u.wrap),
                        Some(w) if w != u.wrap => tracing::warn!(
                            image = u.image,
                            mesh = m,
                            primitive = p,
                            "image sampled with different wrap modes, keeping the first"
                        ),
                        Some(_) => {}
                    }
                    b.srgb |= u.srgb;
                    b.alpha = b.alpha.merge(u.alpha);
                    b.rotated |= u.transform.is_some_and(|t| t[1] != 0.0 || t[3] != 0.0);
                    total_triangles += corners.len();
                    if total_triangles > opts.max_triangles {
                        return Err(invalid(format!(
                            "more than {} triangles (at {here})",
                            opts.max_triangles
                        )));
                    }
                    b.triangles.reserve(corners.len());
                    for tri in &corners {
                        let t = UvTriangle {
                            group,
                            positions: tri.map(|v| positions[v as usize]),
                            uvs: tri.map(|v| apply(u.transform, uvs[v as usize])),
                        };
                        if t.uvs.iter().flatten().any(|x| !x.is_finite()) {
                            return Err(invalid(format!(
                                "{here}: {} UVs are not finite after KHR_texture_transform",
                                u.role
                            )));
                        }
                        b.triangles.push(t);
                    }
                }
            }
        }

        let mut textures = Vec::new();
        let mut names = NameSet::default();
        for (image, b) in builders {
            if b.triangles.is_empty() {
                skipped.push(Skipped {
                    image: Some(image),
                    mesh: None,
                    primitive: None,
                    reason: "no triangles sample it".into(),
                });
                continue;
            }
            let bytes = self.image_bytes(image, files)?.into_owned();
            let header = Texture::probe(&bytes, opts.max_texture_size)
                .map_err(|source| LoadErrorKind::Texture { image, source })?;
            let name = names.claim(&self.image_name_candidates(image), stem, image);
            let (wrap_s, wrap_t) = b.wrap.unwrap_or_default();
            textures.push(PlannedTexture {
                image,
                name,
                header,
                wrap_s,
                wrap_t,
                srgb: b.srgb,
                rotated: b.rotated,
                alpha: b.alpha,
                triangles: b.triangles,
                bytes,
            });
        }
        for (image, material) in normal_maps {
            if textures.iter().any(|t| t.image == image) {
                continue;
            }
            tracing::debug!(image, material, "normal map skipped");
            skipped.push(Skipped {
                image: Some(image),
                mesh: None,
                primitive: None,
                reason: "tangent-space normal map".into(),
            });
        }
        Ok(Plan {
            file: String::new(),
            textures,
            skipped,
            samplings,
            max_texture_size: opts.max_texture_size,
        })
    }

    fn image_name_candidates(&self, image: usize) -> Vec<String> {
        let img = &self.root.images[image];
        let mut out = Vec::new();
        if let Some(n) = &img.name {
            out.push(n.clone());
        }
        if let Some(uri) = &img.uri {
            if let Ok(UriTarget::File(path)) = classify_uri(uri) {
                out.push(path.rsplit('/').next().unwrap_or("").to_string());
            }
        }
        out
    }
}

fn to_wrap(w: &Checked<json::texture::WrappingMode>) -> Wrap {
    use json::texture::WrappingMode as W;
    match w {
        Checked::Valid(W::ClampToEdge) => Wrap::ClampToEdge,
        Checked::Valid(W::MirroredRepeat) => Wrap::MirroredRepeat,
        _ => Wrap::Repeat,
    }
}

fn mode_name(m: Mode) -> &'static str {
    match m {
        Mode::Points => "POINTS",
        Mode::Lines => "LINES",
        Mode::LineLoop => "LINE_LOOP",
        Mode::LineStrip => "LINE_STRIP",
        Mode::Triangles => "TRIANGLES",
        Mode::TriangleStrip => "TRIANGLE_STRIP",
        Mode::TriangleFan => "TRIANGLE_FAN",
    }
}

fn apply(t: Option<[f64; 6]>, uv: [f32; 2]) -> [f64; 2] {
    let (u, v) = (f64::from(uv[0]), f64::from(uv[1]));
    match t {
        None => [u, v],
        Some(m) => [m[0] * u + m[1] * v + m[2], m[3] * u + m[4] * v + m[5]],
    }
}

/// Triangles as glTF 2.0 §3.7.2.1 defines them for each mode, which keeps
/// the winding consistent. Strip and fan triangles that repeat a vertex are
/// dropped: they only join strips, and would add a third incidence to real
/// edges. Triangle lists are kept verbatim. Trailing indices that do not
/// complete a triangle are ignored.
fn triangulate(mode: Mode, idx: &[u32]) -> Vec<[u32; 3]> {
    let n = idx.len();
    let degenerate = |t: &[u32; 3]| t[0] == t[1] || t[1] == t[2] || t[0] == t[2];
    match mode {
        Mode::Triangles => idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        Mode::TriangleStrip if n >= 3 => (0..n - 2)
            .map(|i| {
                if i % 2 == 0 {
                    [idx[i], idx[i + 1], idx[i + 2]]
                } else {
                    [idx[i], idx[i + 2], idx[i + 1]]
                }
            })
            .filter(|t| !degenerate(t))
            .collect(),
        Mode::TriangleFan if n >= 3 => (1..n - 1)
            .map(|i| [idx[i], idx[i + 1], idx[0]])
            .filter(|t| !degenerate(t))
            .collect(),
        _ => Vec::new(),
    }
}

// ---------------------------------------------------------- buffers, views

fn load_buffers<'a>(
    root: &json::Root,
    bin: Option<&'a [u8]>,
    files: &'a dyn Resolver,
) -> Result<Vec<Cow<'a, [u8]>>, LoadErrorKind> {
    let mut out = Vec::with_capacity(root.buffers.len());
    for (i, b) in root.buffers.iter().enumerate() {
        let what = format!("buffer {i}");
        let declared = to_usize(b.byte_length.0, &what)?;
        if declared as u64 > MAX_FILE_BYTES {
            return Err(invalid(format!(
                "{what}: byteLength {declared} is above the {MAX_FILE_BYTES} bytes accepted"
            )));
        }
        let mut data: Cow<'a, [u8]> = match (&b.uri, bin) {
            // A buffer file may be padded, never much longer than declared.
            (Some(uri), _) => fetch(&what, uri, files, declared as u64 + BUFFER_SLACK)?,
            (None, Some(bin)) if i == 0 => Cow::Borrowed(bin),
            (None, _) => {
                return Err(invalid(format!(
                    "{what} has no uri and there is no GLB binary chunk for it"
                )))
            }
        };
        if data.len() < declared {
            return Err(invalid(format!(
                "{what}: byteLength is {declared} but the data holds {} bytes",
                data.len()
            )));
        }
        match &mut data {
            Cow::Borrowed(s) => *s = &s[..declared],
            Cow::Owned(v) => v.truncate(declared),
        }
        tracing::debug!(buffer = i, bytes = declared, "buffer loaded");
        out.push(data);
    }
    Ok(out)
}

/// A model's document, checked as [`plan_from_memory`] checks it, and the
/// bytes of each of its buffers: what adding geometry to it reads from.
pub(crate) fn document_and_buffers(
    main: &[u8],
    files: &dyn Resolver,
) -> Result<(gltf::Document, Vec<Vec<u8>>), LoadErrorKind> {
    let container = split_container(main)?;
    let root = parse_root(container.json)?;
    let buffers = load_buffers(&root, container.bin, files)?
        .into_iter()
        .map(Cow::into_owned)
        .collect();
    Ok((gltf::Document::from_json_without_validation(root), buffers))
}

fn view_infos(
    root: &json::Root,
    buffers: &[Cow<'_, [u8]>],
) -> Result<Vec<ViewInfo>, LoadErrorKind> {
    root.buffer_views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let what = format!("bufferView {i}");
            let buffer = v.buffer.value();
            let blen = buffers
                .get(buffer)
                .map(|b| b.len())
                .ok_or_else(|| invalid(format!("{what}: buffer {buffer} does not exist")))?;
            let start = to_usize(v.byte_offset.map_or(0, |o| o.0), &what)?;
            let len = to_usize(v.byte_length.0, &what)?;
            if start.checked_add(len).is_none_or(|end| end > blen) {
                return Err(invalid(format!(
                    "{what}: {len} bytes at offset {start} exceed buffer {buffer} ({blen} bytes)"
                )));
            }
            Ok(ViewInfo {
                buffer,
                start,
                len,
                stride: v.byte_stride.map(|s| s.0),
            })
        })
        .collect()
}

// -------------------------------------------------------------------- names

#[derive(Default)]
struct NameSet {
    taken: HashSet<String>,
}

impl NameSet {
    /// First usable candidate, made file-name safe, else `image<N>`; made
    /// unique case-insensitively (some file systems fold case).
    /// The first usable candidate, else `stem`, else `image<N>`; made
    /// unique with `_1`, `_2`, ...
    fn claim(&mut self, candidates: &[String], stem: &str, image: usize) -> String {
        let base = candidates
            .iter()
            .map(|c| sanitize(c))
            .find(|c| !c.is_empty())
            .or_else(|| (!stem.is_empty()).then(|| stem.to_string()))
            .unwrap_or_else(|| format!("image{image}"));
        let mut name = base.clone();
        let mut k = 1;
        while self.taken.contains(&name.to_ascii_lowercase()) {
            name = format!("{base}_{k}");
            k += 1;
        }
        self.taken.insert(name.to_ascii_lowercase());
        name
    }
}

/// Restricts a name to `[A-Za-z0-9._-]`, drops an image extension and
/// leading dots, and avoids names Windows reserves.
fn sanitize(raw: &str) -> String {
    let mut s: String = raw
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect();
    for ext in [".png", ".jpg", ".jpeg"] {
        if s.len() > ext.len() && s.to_ascii_lowercase().ends_with(ext) {
            s.truncate(s.len() - ext.len());
            break;
        }
    }
    let s = s.trim_start_matches('.');
    let mut s: String = s.chars().take(96).collect();
    if s.chars().all(|c| c == '_') {
        return String::new();
    }
    let stem = s.split('.').next().unwrap_or("").to_ascii_lowercase();
    let reserved = matches!(stem.as_str(), "con" | "prn" | "aux" | "nul")
        || ((stem.starts_with("com") || stem.starts_with("lpt"))
            && stem.len() == 4
            && stem.as_bytes()[3].is_ascii_digit());
    if reserved {
        s.insert(0, '_');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uri_classification() {
        assert!(matches!(classify_uri("a%20b.bin"), Ok(UriTarget::File(p)) if p == "a b.bin"));
        assert!(matches!(classify_uri("./sub//x.png"), Ok(UriTarget::File(p)) if p == "sub/x.png"));
        for bad in [
            "../x.bin",
            "a/../../x",
            "%2e%2e/x.bin",
            "a%2F..%2F..%2Fx",
            "/etc/passwd",
            "%2Fetc%2Fpasswd",
            "http://example.com/a.bin",
            "file:///etc/passwd",
            "C:/x.bin",
            "C%3A/x.bin",
            "a\\..\\x",
            "",
            ".",
        ] {
            assert!(classify_uri(bad).is_err(), "{bad} accepted");
        }
        assert!(matches!(classify_uri("DATA:,x"), Ok(UriTarget::Data(",x"))));
        assert!(matches!(
            classify_uri("dat\u{e9}.bin"),
            Ok(UriTarget::File(_))
        ));
        assert_eq!(uri_for_message("d\u{e9}\u{e9}x"), "d\u{e9}\u{e9}x");
    }

    #[test]
    fn data_uris() {
        assert_eq!(
            decode_data_uri("application/octet-stream;base64,AAEC/w==").unwrap(),
            vec![0, 1, 2, 255]
        );
        assert_eq!(
            decode_data_uri(";base64,AAEC/w").unwrap(),
            vec![0, 1, 2, 255]
        );
        assert_eq!(decode_data_uri(",a%20b").unwrap(), b"a b".to_vec());
        assert!(decode_data_uri("image/png;base64").is_err());
        assert!(decode_data_uri(";base64,@@@").is_err());
    }

    #[test]
    fn strips_and_fans_follow_the_spec() {
        let idx = [0, 1, 2, 3, 4];
        assert_eq!(
            triangulate(Mode::TriangleStrip, &idx),
            vec![[0, 1, 2], [1, 3, 2], [2, 3, 4]]
        );
        assert_eq!(
            triangulate(Mode::TriangleFan, &idx),
            vec![[1, 2, 0], [2, 3, 0], [3, 4, 0]]
        );
        assert_eq!(triangulate(Mode::Triangles, &idx), vec![[0, 1, 2]]);
        assert_eq!(
            triangulate(Mode::TriangleStrip, &[0, 1, 2, 2, 3, 4]),
            vec![[0, 1, 2], [2, 4, 3]]
        );
        assert!(triangulate(Mode::TriangleStrip, &[0, 1]).is_empty());
    }

    #[test]
    fn names_are_safe_and_unique() {
        let mut set = NameSet::default();
        assert_eq!(set.claim(&["Albedo.PNG".into()], "", 0), "Albedo");
        assert_eq!(set.claim(&["albedo".into()], "", 1), "albedo_1");
        assert_eq!(set.claim(&["../../etc/x y".into()], "", 2), "_.._etc_x_y");
        assert_eq!(set.claim(&["".into(), "con.png".into()], "", 3), "_con");
        assert_eq!(set.claim(&["///".into()], "", 4), "image4");
        assert_eq!(set.claim(&[], "", 5), "image5");
        // Unnamed images take the model's stem.
        assert_eq!(set.claim(&[], "crate", 6), "crate");
        assert_eq!(set.claim(&["///".into()], "crate", 7), "crate_1");
    }

    #[test]
    fn glb_container_checks() {
        assert!(split_container(b"glTF").is_err());
        let mut glb = b"glTF".to_vec();
        glb.extend_from_slice(&2u32.to_le_bytes());
        glb.extend_from_slice(&3u32.to_le_bytes());
        assert!(split_container(&glb).is_err());
        let mut glb = b"glTF".to_vec();
        glb.extend_from_slice(&2u32.to_le_bytes());
        glb.extend_from_slice(&28u32.to_le_bytes());
        glb.extend_from_slice(&u32::MAX.to_le_bytes());
        glb.extend_from_slice(b"JSON{}  ");
        assert!(split_container(&glb).is_err());
    }
}
