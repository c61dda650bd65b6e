//! Rewriting a model so that it uses the DDS files: `MSFT_texture_dds`.
//!
//! For every image that has a DDS file, a new image entry points at the DDS
//! and each texture sampling the image names it in
//! `extensions.MSFT_texture_dds.source`. The texture's own `source` stays
//! the fallback for viewers without the extension (it is used, not
//! required), now the erased PNG: the original would show the seams that
//! were closed. (JPEG sources become PNG there too: a JPEG re-encoding
//! would add block noise across the seams the erasure just made agree.) A
//! `.gltf` refers to both files by relative URI and keeps its buffers; a
//! `.glb` appends both to its BIN chunk (its bytes before stay as they
//! were), so one file out serves one file in.

use std::collections::BTreeMap;

use percent_encoding::{utf8_percent_encode, AsciiSet, CONTROLS};
use serde_json::{json, Map, Value};

pub const EXTENSION: &str = "MSFT_texture_dds";
pub const DDS_MIME: &str = "image/vnd-ms.dds";
pub const PNG_MIME: &str = "image/png";

/// Characters escaped in a URI path segment (RFC 3986 keeps unreserved ones).
const SEGMENT: &AsciiSet = &CONTROLS
    .add(b' ')
    .add(b'"')
    .add(b'#')
    .add(b'%')
    .add(b'<')
    .add(b'>')
    .add(b'?')
    .add(b'[')
    .add(b'\\')
    .add(b']')
    .add(b'^')
    .add(b'`')
    .add(b'{')
    .add(b'|')
    .add(b'}');

#[derive(Debug, thiserror::Error)]
pub enum RewriteError {
    #[error("GLB: {0}")]
    Container(String),
    #[error("invalid glTF JSON: {0}")]
    Json(String),
    #[error("image {0} does not exist in the model")]
    NoSuchImage(usize),
    #[error("DDS file name {0:?} cannot be a relative URI")]
    BadName(String),
    #[error("image {0} was padded, but a KHR_texture_transform sampling it rotates the UVs")]
    RotatedTransform(usize),
}

pub const TRANSFORM_EXTENSION: &str = "KHR_texture_transform";

/// A GLB split into its JSON and BIN chunks.
pub struct Glb<'a> {
    pub json: &'a [u8],
    pub bin: Option<&'a [u8]>,
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    let s = b.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

/// Splits a GLB container (glTF 2.0 §4.4). Unknown chunks are dropped, as
/// the specification allows.
pub fn split_glb(bytes: &[u8]) -> Result<Glb<'_>, RewriteError> {
    let bad = |m: &str| RewriteError::Container(m.to_string());
    if !bytes.starts_with(b"glTF") || u32_at(bytes, 4) != Some(2) {
        return Err(bad("not a version 2 GLB"));
    }
    let length = u32_at(bytes, 8).ok_or_else(|| bad("truncated header"))? as usize;
    let body = bytes
        .get(..length)
        .ok_or_else(|| bad("shorter than its header says"))?;
    let mut at = 12usize;
    let (mut json, mut bin) = (None, None);
    while at + 8 <= body.len() {
        let len = u32_at(body, at).ok_or_else(|| bad("truncated chunk"))? as usize;
        let ty = &body[at + 4..at + 8];
        let start = at + 8;
        let data = start
            .checked_add(len)
            .and_then(|end| body.get(start..end))
            .ok_or_else(|| bad("chunk past the end"))?;
        match ty {
            b"JSON" if json.is_none() => json = Some(data),
            b"BIN\0" if json.is_some() && bin.is_none() => bin = Some(data),
            _ => {}
        }
        at = (start + len).saturating_add(3) & !3;
    }
    Ok(Glb {
        json: json.ok_or_else(|| bad("no JSON chunk"))?,
        bin,
    })
}

/// Packs a GLB: JSON padded with spaces, BIN with zeros, both to 4 bytes.
pub fn pack_glb(json: &[u8], bin: Option<&[u8]>) -> Vec<u8> {
    let pad = |n: usize| (4 - n % 4) % 4;
    let json_len = json.len() + pad(json.len());
    let bin_len = bin.map(|b| b.len() + pad(b.len()));
    let total = 12 + 8 + json_len + bin_len.map_or(0, |l| 8 + l);
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json);
    out.resize(out.len() + pad(json.len()), b' ');
    if let (Some(bin), Some(len)) = (bin, bin_len) {
        out.extend_from_slice(&(len as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
        out.resize(out.len() + pad(bin.len()), 0);
    }
    out
}

/// Adds `MSFT_texture_dds` to `root` for the images in `dds` (image index →
/// DDS file name, relative to the model). Returns how many textures now
/// reference a DDS image. An empty map leaves the JSON untouched.
pub fn add_dds_sources(
    root: &mut Value,
    dds: &BTreeMap<usize, String>,
) -> Result<usize, RewriteError> {
    if dds.is_empty() {
        return Ok(0);
    }
    let obj = root
        .as_object_mut()
        .ok_or_else(|| RewriteError::Json("the root is not an object".into()))?;
    let images = obj
        .entry("images")
        .or_insert_with(|| Value::Array(Vec::new()))
        .as_array_mut()
        .ok_or_else(|| RewriteError::Json("\"images\" is not an array".into()))?;
    let mut dds_image = BTreeMap::new();
    for (&image, name) in dds {
        if image >= images.len() {
            return Err(RewriteError::NoSuchImage(image));
        }
        dds_image.insert(image, images.len());
        images.push(json!({ "uri": relative_uri(name)?, "mimeType": DDS_MIME }));
    }
    reference_dds_images(obj, &dds_image)
}

/// A file name beside the model as a relative URI.
fn relative_uri(name: &str) -> Result<String, RewriteError> {
    if name.is_empty() || name.starts_with('/') || name.split('/').any(|p| p == "..") {
        return Err(RewriteError::BadName(name.to_string()));
    }
    Ok(utf8_percent_encode(name, SEGMENT).to_string())
}

/// Points every texture whose source is a key of `dds_image` at the DDS
/// image it maps to, through `MSFT_texture_dds`, and lists the extension.
fn reference_dds_images(
    obj: &mut Map<String, Value>,
    dds_image: &BTreeMap<usize, usize>,
) -> Result<usize, RewriteError> {
    let mut referenced = 0;
    if let Some(textures) = obj.get_mut("textures").and_then(Value::as_array_mut) {
        for texture in textures.iter_mut() {
            let Some(t) = texture.as_object_mut() else {
                continue;
            };
            let source = t.get("source").and_then(Value::as_u64);
            let Some(&dds_index) = source.and_then(|s| dds_image.get(&(s as usize))) else {
                continue;
            };
            let extensions = t
                .entry("extensions")
                .or_insert_with(|| Value::Object(Map::new()));
            let Some(extensions) = extensions.as_object_mut() else {
                return Err(RewriteError::Json(
                    "a texture's \"extensions\" is not an object".into(),
                ));
            };
            extensions.insert(EXTENSION.into(), json!({ "source": dds_index }));
            referenced += 1;
        }
    }
    if dds_image.is_empty() {
        return Ok(referenced);
    }

    let used = obj
        .entry("extensionsUsed")
        .or_insert_with(|| Value::Array(Vec::new()))
        .as_array_mut()
        .ok_or_else(|| RewriteError::Json("\"extensionsUsed\" is not an array".into()))?;
    if !used.iter().any(|e| e.as_str() == Some(EXTENSION)) {
        used.push(Value::String(EXTENSION.into()));
    }
    Ok(referenced)
}

/// The files beside it that a model file refers to (buffers and images by
/// relative URI, in order, without repeats): what a rewritten `.gltf` needs
/// next to it.
pub fn referenced_files(main: &[u8]) -> Result<Vec<String>, RewriteError> {
    let json = if main.starts_with(b"glTF") {
        split_glb(main)?.json
    } else {
        main
    };
    let json = json.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(json);
    let root: Value =
        serde_json::from_slice(json).map_err(|e| RewriteError::Json(e.to_string()))?;
    let mut out: Vec<String> = Vec::new();
    for list in ["buffers", "images"] {
        for item in root[list].as_array().map(Vec::as_slice).unwrap_or(&[]) {
            let path = item["uri"].as_str().and_then(super::load::relative_file);
            if let Some(path) = path {
                if !out.contains(&path) {
                    out.push(path);
                }
            }
        }
    }
    Ok(out)
}

/// What one processed image becomes in the rewritten model: the DDS, and
/// the erased PNG as the fallback for viewers without DDS support (the
/// original would show the seams again).
pub struct Replacement<'a> {
    /// The DDS file's name and bytes; `None` where the blocks went into
    /// another container (KTX2), which no ratified extension carries: the
    /// image is then the erased PNG alone.
    pub dds: Option<(&'a str, &'a [u8])>,
    pub fallback_name: &'a str,
    pub fallback: &'a [u8],
    /// The image was padded: what its UVs are multiplied by, per axis.
    pub uv_scale: Option<[f64; 2]>,
}

/// The model (`.glb` or `.gltf` bytes) rewritten to use the DDS files, in
/// the same container. Each image in `images` becomes its erased PNG and
/// gains a DDS image that its textures name through `MSFT_texture_dds`.
/// A `.gltf` refers to both by relative URI (the files sit beside it); a
/// `.glb` carries both in its binary chunk, so one file out serves one file
/// in (unless its first buffer is external, when it refers to them too).
pub fn rewrite_model(
    main: &[u8],
    images: &BTreeMap<usize, Replacement<'_>>,
) -> Result<Vec<u8>, RewriteError> {
    let parse = |json: &[u8]| -> Result<Value, RewriteError> {
        let json = json.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(json);
        serde_json::from_slice(json).map_err(|e| RewriteError::Json(e.to_string()))
    };
    let serialise =
        |v: &Value| serde_json::to_vec(v).map_err(|e| RewriteError::Json(e.to_string()));
    if main.starts_with(b"glTF") {
        let glb = split_glb(main)?;
        let mut root = parse(glb.json)?;
        let mut bin = glb.bin.map(<[u8]>::to_vec).unwrap_or_default();
        if embed(&mut root, &mut bin, images)? {
            return Ok(pack_glb(&serialise(&root)?, Some(&bin)));
        }
        refer(&mut root, images)?;
        Ok(pack_glb(&serialise(&root)?, glb.bin))
    } else {
        let mut root = parse(main)?;
        refer(&mut root, images)?;
        let mut out =
            serde_json::to_vec_pretty(&root).map_err(|e| RewriteError::Json(e.to_string()))?;
        out.push(b'\n');
        Ok(out)
    }
}

/// [`rewrite_model`], but every image referred to as a file beside the
/// model, a `.glb` too (its binary chunk kept as it was): the base of a
/// level of detail written as its own file, which shares the textures.
pub fn rewrite_model_referring(
    main: &[u8],
    images: &BTreeMap<usize, Replacement<'_>>,
) -> Result<Vec<u8>, RewriteError> {
    if !main.starts_with(b"glTF") {
        return rewrite_model(main, images);
    }
    let glb = split_glb(main)?;
    let json = glb.json.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(glb.json);
    let mut root: Value =
        serde_json::from_slice(json).map_err(|e| RewriteError::Json(e.to_string()))?;
    refer(&mut root, images)?;
    let json = serde_json::to_vec(&root).map_err(|e| RewriteError::Json(e.to_string()))?;
    Ok(pack_glb(&json, glb.bin))
}

/// The images as files beside the model.
fn refer(root: &mut Value, images: &BTreeMap<usize, Replacement<'_>>) -> Result<(), RewriteError> {
    let dds: BTreeMap<usize, String> = images
        .iter()
        .filter_map(|(&i, r)| Some((i, r.dds?.0.to_string())))
        .collect();
    for (&i, r) in images {
        let uri = relative_uri(r.fallback_name)?;
        set_image(root, i, json!({ "uri": uri, "mimeType": PNG_MIME }))?;
    }
    scale_padded(root, images)?;
    add_dds_sources(root, &dds).map(drop)
}

/// The images in the GLB's binary chunk; `false` (nothing changed) when
/// the first buffer is not the binary chunk.
fn embed(
    root: &mut Value,
    bin: &mut Vec<u8>,
    images: &BTreeMap<usize, Replacement<'_>>,
) -> Result<bool, RewriteError> {
    let buffers = array_mut(root, "buffers")?;
    match buffers.first() {
        Some(b) if b.get("uri").is_some() => return Ok(false),
        Some(_) => {}
        None => buffers.push(json!({ "byteLength": 0 })),
    }
    let mut dds_image = BTreeMap::new();
    for (&i, r) in images {
        if i >= array_mut(root, "images")?.len() {
            return Err(RewriteError::NoSuchImage(i));
        }
        let png = push_view(root, bin, r.fallback)?;
        set_image(root, i, json!({ "bufferView": png, "mimeType": PNG_MIME }))?;
        if let Some((_, bytes)) = r.dds {
            let dds = push_view(root, bin, bytes)?;
            let list = array_mut(root, "images")?;
            dds_image.insert(i, list.len());
            list.push(json!({ "bufferView": dds, "mimeType": DDS_MIME }));
        }
    }
    root["buffers"][0]["byteLength"] = json!(bin.len());
    scale_padded(root, images)?;
    let obj = root
        .as_object_mut()
        .ok_or_else(|| RewriteError::Json("the root is not an object".into()))?;
    reference_dds_images(obj, &dds_image)?;
    Ok(true)
}

/// Scales the UVs of every texture info that samples a padded image, so
/// that each UV samples the texel it sampled before the padding.
fn scale_padded(
    root: &mut Value,
    images: &BTreeMap<usize, Replacement<'_>>,
) -> Result<(), RewriteError> {
    let mut scaled = false;
    for (&image, r) in images {
        let Some(scale) = r.uv_scale else {
            continue;
        };
        let textures: Vec<u64> = root["textures"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or(&[])
            .iter()
            .enumerate()
            .filter(|(_, t)| t["source"].as_u64() == Some(image as u64))
            .map(|(k, _)| k as u64)
            .collect();
        if let Some(materials) = root.get_mut("materials") {
            scale_texture_infos(materials, &textures, scale, image)?;
        }
        scaled = true;
    }
    if scaled {
        let used = array_mut(root, "extensionsUsed")?;
        if !used.iter().any(|e| e.as_str() == Some(TRANSFORM_EXTENSION)) {
            used.push(Value::String(TRANSFORM_EXTENSION.into()));
        }
    }
    Ok(())
}

/// Every texture info under `v` (an object under a key ending in
/// `Texture`, the glTF convention, extensions included) that names one of
/// `textures` gets `scale` composed after its KHR_texture_transform:
/// P·T(o)·S(k) = T(P·o)·S(P·k) when the transform does not rotate.
fn scale_texture_infos(
    v: &mut Value,
    textures: &[u64],
    scale: [f64; 2],
    image: usize,
) -> Result<(), RewriteError> {
    match v {
        Value::Array(items) => {
            for item in items {
                scale_texture_infos(item, textures, scale, image)?;
            }
        }
        Value::Object(fields) => {
            for (key, value) in fields.iter_mut() {
                let names = value["index"]
                    .as_u64()
                    .is_some_and(|i| textures.contains(&i));
                if key.ends_with("Texture") && names {
                    compose_scale(value, scale, image)?;
                } else {
                    scale_texture_infos(value, textures, scale, image)?;
                }
            }
        }
        _ => {}
    }
    Ok(())
}

fn compose_scale(info: &mut Value, p: [f64; 2], image: usize) -> Result<(), RewriteError> {
    let Some(info) = info.as_object_mut() else {
        return Ok(());
    };
    let extensions = info
        .entry("extensions")
        .or_insert_with(|| Value::Object(Map::new()))
        .as_object_mut()
        .ok_or_else(|| {
            RewriteError::Json("a texture info's \"extensions\" is not an object".into())
        })?;
    let t = extensions
        .entry(TRANSFORM_EXTENSION)
        .or_insert_with(|| Value::Object(Map::new()))
        .as_object_mut()
        .ok_or_else(|| RewriteError::Json("KHR_texture_transform is not an object".into()))?;
    let pair = |v: Option<&Value>, default: f64| -> [f64; 2] {
        let at = |k: usize| v.and_then(|v| v[k].as_f64()).unwrap_or(default);
        [at(0), at(1)]
    };
    let rotation = t.get("rotation").and_then(Value::as_f64).unwrap_or(0.0);
    if rotation != 0.0 && p[0] != p[1] {
        return Err(RewriteError::RotatedTransform(image));
    }
    let (o, k) = (pair(t.get("offset"), 0.0), pair(t.get("scale"), 1.0));
    if o != [0.0, 0.0] {
        t.insert("offset".into(), json!([o[0] * p[0], o[1] * p[1]]));
    }
    t.insert("scale".into(), json!([k[0] * p[0], k[1] * p[1]]));
    Ok(())
}

/// `root[key]` as an array, created empty when missing.
fn array_mut<'v>(root: &'v mut Value, key: &str) -> Result<&'v mut Vec<Value>, RewriteError> {
    root.as_object_mut()
        .ok_or_else(|| RewriteError::Json("the root is not an object".into()))?
        .entry(key)
        .or_insert_with(|| Value::Array(Vec::new()))
        .as_array_mut()
        .ok_or_else(|| RewriteError::Json(format!("\"{key}\" is not an array")))
}

/// Appends `bytes` to the binary chunk (4-byte aligned) as a new buffer view.
fn push_view(root: &mut Value, bin: &mut Vec<u8>, bytes: &[u8]) -> Result<usize, RewriteError> {
    bin.resize(bin.len().next_multiple_of(4), 0);
    let at = bin.len();
    bin.extend_from_slice(bytes);
    let views = array_mut(root, "bufferViews")?;
    views.push(json!({ "buffer": 0, "byteOffset": at, "byteLength": bytes.len() }));
    Ok(views.len() - 1)
}

/// Gives image `i` another source (`uri` or `bufferView`, and `mimeType`),
/// keeping its name and extras.
fn set_image(root: &mut Value, i: usize, source: Value) -> Result<(), RewriteError> {
    let image = array_mut(root, "images")?
        .get_mut(i)
        .and_then(Value::as_object_mut)
        .ok_or(RewriteError::NoSuchImage(i))?;
    for key in ["uri", "bufferView", "mimeType"] {
        image.remove(key);
    }
    if let Value::Object(fields) = source {
        image.extend(fields);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> Value {
        json!({
            "asset": {"version": "2.0"},
            "images": [{"uri": "a.png"}, {"uri": "b.png"}],
            "textures": [
                {"source": 0, "sampler": 0},
                {"source": 1},
                {"source": 0, "extensions": {"KHR_texture_basisu": {"source": 1}}}
            ],
            "extensionsUsed": ["KHR_texture_transform"]
        })
    }

    #[test]
    fn textures_of_processed_images_get_a_dds_source() {
        let mut root = model();
        let dds = BTreeMap::from([(0, "a b.dds".to_string())]);
        assert_eq!(add_dds_sources(&mut root, &dds).unwrap(), 2);
        assert_eq!(
            root["images"][2],
            json!({"uri": "a%20b.dds", "mimeType": DDS_MIME})
        );
        assert_eq!(root["textures"][0]["source"], 0);
        assert_eq!(root["textures"][0]["extensions"][EXTENSION]["source"], 2);
        assert!(root["textures"][1].get("extensions").is_none());
        assert_eq!(
            root["textures"][2]["extensions"]["KHR_texture_basisu"]["source"],
            1
        );
        assert_eq!(root["textures"][2]["extensions"][EXTENSION]["source"], 2);
        assert_eq!(
            root["extensionsUsed"],
            json!(["KHR_texture_transform", EXTENSION])
        );
        assert!(root.get("extensionsRequired").is_none());
    }

    #[test]
    fn no_dds_leaves_the_model_alone() {
        let mut root = model();
        assert_eq!(add_dds_sources(&mut root, &BTreeMap::new()).unwrap(), 0);
        assert_eq!(root, model());
    }

    #[test]
    fn unknown_images_and_escaping_names_are_refused() {
        let mut root = model();
        let dds = BTreeMap::from([(5, "x.dds".to_string())]);
        assert!(matches!(
            add_dds_sources(&mut root, &dds),
            Err(RewriteError::NoSuchImage(5))
        ));
        let dds = BTreeMap::from([(0, "../x.dds".to_string())]);
        assert!(matches!(
            add_dds_sources(&mut root, &dds),
            Err(RewriteError::BadName(_))
        ));
    }

    #[test]
    fn a_glb_carries_the_dds_and_the_fallback_in_its_bin_chunk() {
        let json = serde_json::to_vec(&model()).unwrap();
        let bin = [1u8, 2, 3, 4, 5];
        let glb = pack_glb(&json, Some(&bin));
        assert_eq!(glb.len() % 4, 0);
        let images = BTreeMap::from([(
            1,
            Replacement {
                dds: Some(("b.dds", b"DDS data")),
                fallback_name: "b.erased.png",
                fallback: b"png",
                uv_scale: None,
            },
        )]);
        let out = rewrite_model(&glb, &images).unwrap();
        assert_eq!(u32_at(&out, 8).unwrap() as usize, out.len());
        let parts = split_glb(&out).unwrap();
        let bin_out = parts.bin.unwrap();
        assert_eq!(&bin_out[..5], &bin);
        let root: Value = serde_json::from_slice(parts.json).unwrap();
        assert_eq!(root["textures"][1]["extensions"][EXTENSION]["source"], 2);
        let view = |v: &Value| {
            let v = &root["bufferViews"][v.as_u64().unwrap() as usize];
            let at = v["byteOffset"].as_u64().unwrap() as usize;
            assert_eq!(at % 4, 0);
            &bin_out[at..at + v["byteLength"].as_u64().unwrap() as usize]
        };
        assert_eq!(view(&root["images"][2]["bufferView"]), b"DDS data");
        assert_eq!(root["images"][2]["mimeType"], DDS_MIME);
        assert_eq!(view(&root["images"][1]["bufferView"]), b"png");
        assert_eq!(root["images"][1]["mimeType"], PNG_MIME);
        assert!(root["images"][1].get("uri").is_none());
        assert_eq!(root["buffers"][0]["byteLength"], bin_out.len());
        // The untouched image keeps its file.
        assert_eq!(root["images"][0]["uri"], "a.png");
    }

    #[test]
    fn a_gltf_refers_to_the_dds_and_the_erased_png_beside_it() {
        let main = serde_json::to_vec(&model()).unwrap();
        let images = BTreeMap::from([(
            0,
            Replacement {
                dds: Some(("a b.dds", b"")),
                fallback_name: "a b.erased.png",
                fallback: b"",
                uv_scale: None,
            },
        )]);
        let out = rewrite_model(&main, &images).unwrap();
        let root: Value = serde_json::from_slice(&out).unwrap();
        assert_eq!(root["images"][0]["uri"], "a%20b.erased.png");
        assert_eq!(root["images"][2]["uri"], "a%20b.dds");
        assert_eq!(
            referenced_files(&out).unwrap(),
            ["a b.erased.png", "b.png", "a b.dds"]
        );
    }
}
