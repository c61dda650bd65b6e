//! Rewriting a model so that it uses the DDS files: `MSFT_texture_dds`.
//!
//! For every image that has a DDS file, a new image entry points at the DDS
//! and each texture sampling the image names it in
//! `extensions.MSFT_texture_dds.source`. The texture's own `source` keeps the
//! original image, so viewers without the extension still show the model
//! (the extension is used, not required). Only the JSON changes: a `.gltf`
//! keeps its buffers and images, a `.glb` keeps its BIN chunk byte for byte,
//! and the DDS files stay external, referenced by relative URI.

use std::collections::BTreeMap;

use percent_encoding::{utf8_percent_encode, AsciiSet, CONTROLS};
use serde_json::{json, Map, Value};

pub const EXTENSION: &str = "MSFT_texture_dds";
pub const DDS_MIME: &str = "image/vnd-ms.dds";

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
}

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
        if name.is_empty() || name.starts_with('/') || name.split('/').any(|p| p == "..") {
            return Err(RewriteError::BadName(name.clone()));
        }
        dds_image.insert(image, images.len());
        images.push(json!({
            "uri": utf8_percent_encode(name, SEGMENT).to_string(),
            "mimeType": DDS_MIME,
        }));
    }

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

/// Rewrites a whole model file (`.glb` or `.gltf` bytes) with
/// [`add_dds_sources`]; the result has the same container as the input.
pub fn rewrite_model(main: &[u8], dds: &BTreeMap<usize, String>) -> Result<Vec<u8>, RewriteError> {
    let parse = |json: &[u8]| -> Result<Value, RewriteError> {
        let json = json.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(json);
        serde_json::from_slice(json).map_err(|e| RewriteError::Json(e.to_string()))
    };
    let serialise =
        |v: &Value| serde_json::to_vec(v).map_err(|e| RewriteError::Json(e.to_string()));
    if main.starts_with(b"glTF") {
        let glb = split_glb(main)?;
        let mut root = parse(glb.json)?;
        add_dds_sources(&mut root, dds)?;
        Ok(pack_glb(&serialise(&root)?, glb.bin))
    } else {
        let mut root = parse(main)?;
        add_dds_sources(&mut root, dds)?;
        let mut out =
            serde_json::to_vec_pretty(&root).map_err(|e| RewriteError::Json(e.to_string()))?;
        out.push(b'\n');
        Ok(out)
    }
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
    fn glb_round_trip_keeps_the_bin_chunk() {
        let json = serde_json::to_vec(&model()).unwrap();
        let bin = [1u8, 2, 3, 4, 5];
        let glb = pack_glb(&json, Some(&bin));
        assert_eq!(glb.len() % 4, 0);
        let dds = BTreeMap::from([(1, "b.dds".to_string())]);
        let out = rewrite_model(&glb, &dds).unwrap();
        let parts = split_glb(&out).unwrap();
        assert_eq!(&parts.bin.unwrap()[..5], &bin);
        let root: Value = serde_json::from_slice(parts.json).unwrap();
        assert_eq!(root["textures"][1]["extensions"][EXTENSION]["source"], 2);
        assert_eq!(u32_at(&out, 8).unwrap() as usize, out.len());
    }
}
