//! Levels of detail in glTF: reading each mesh's triangles, and writing the
//! levels back as new index accessors over the same vertex accessors, so
//! every attribute (normals, tangents, skin weights, colours, every
//! TEXCOORD set, as floats or as stored) is carried unchanged.
//!
//! The model carries its levels with `MSFT_lod` on each node that has a
//! simplified mesh (`MSFT_screencoverage` in the node's extras gives the
//! screen coverage each level is meant for); a level on its own is the same
//! model with each primitive's indices replaced.

use std::collections::{BTreeMap, HashMap};

use gltf::mesh::util::ReadIndices;
use gltf::mesh::{Mode, Semantic};
use serde_json::{json, Map, Value};

use super::simplify::Mesh;
use super::LodError;
use crate::model::load::document_and_buffers;
use crate::model::rewrite::{pack_glb, split_glb};
use crate::model::Resolver;

pub const LOD_EXTENSION: &str = "MSFT_lod";
pub const COVERAGE_EXTRA: &str = "MSFT_screencoverage";

/// Screen coverage (fraction of the viewport's height) at which the full
/// mesh is needed: a model filling half the view.
const FULL_DETAIL_COVERAGE: f64 = 0.5;

/// glTF's `ELEMENT_ARRAY_BUFFER` buffer-view target.
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

/// One primitive's triangles, as the simplifier takes them.
pub struct PrimitiveData {
    pub positions: Vec<[f32; 3]>,
    pub normals: Option<Vec<[f32; 3]>>,
    pub uv_sets: Vec<Vec<[f32; 2]>>,
    /// A triangle list, each vertex replaced by the first vertex with the
    /// same value in every attribute (so duplicates do not look like seams).
    pub indices: Vec<u32>,
    /// Per vertex, the first vertex with the same position and UVs.
    pub uv_wedge: Vec<u32>,
}

impl PrimitiveData {
    pub fn mesh(&self) -> Mesh<'_> {
        Mesh {
            positions: &self.positions,
            normals: self.normals.as_deref(),
            uv_sets: &self.uv_sets,
            indices: &self.indices,
            uv_wedge: &self.uv_wedge,
        }
    }
}

pub enum Primitive {
    Simplify(PrimitiveData),
    /// Not triangles (points, lines, strips, fans): the same in every level.
    Keep,
}

pub struct MeshSource {
    pub primitives: Vec<Primitive>,
    /// Why the mesh is the same in every level, when it is.
    pub kept_whole: Option<String>,
}

/// Every mesh of the model (`.glb` or `.gltf` bytes) as the simplifier
/// takes it.
pub fn read_meshes(main: &[u8], files: &dyn Resolver) -> Result<Vec<MeshSource>, LodError> {
    let (document, buffers) =
        document_and_buffers(main, files).map_err(|e| LodError::Model(e.to_string()))?;
    let mut out = Vec::new();
    for mesh in document.meshes() {
        let morphs = mesh.primitives().any(|p| p.morph_targets().len() > 0);
        if morphs {
            out.push(MeshSource {
                primitives: Vec::new(),
                kept_whole: Some(format!(
                    "mesh {} has morph targets, which the simplifier cannot carry",
                    mesh.index()
                )),
            });
            continue;
        }
        let mut primitives = Vec::new();
        let mut kept_whole = None;
        for prim in mesh.primitives() {
            if prim.mode() != Mode::Triangles {
                primitives.push(Primitive::Keep);
                continue;
            }
            match read_primitive(&prim, &buffers) {
                Some(data) => primitives.push(Primitive::Simplify(data)),
                None => {
                    kept_whole = Some(format!(
                        "mesh {} primitive {} cannot be read as triangles",
                        mesh.index(),
                        prim.index()
                    ));
                    break;
                }
            }
        }
        out.push(MeshSource {
            primitives,
            kept_whole,
        });
    }
    Ok(out)
}

fn read_primitive(prim: &gltf::Primitive<'_>, buffers: &[Vec<u8>]) -> Option<PrimitiveData> {
    let reader = prim.reader(|b| buffers.get(b.index()).map(Vec::as_slice));
    let positions: Vec<[f32; 3]> = reader.read_positions()?.collect();
    let n = positions.len();
    let fits = |len: usize| len == n;
    let normals: Option<Vec<[f32; 3]>> = reader.read_normals().map(Iterator::collect);
    let mut uv_sets = Vec::new();
    while let Some(uv) = reader.read_tex_coords(uv_sets.len() as u32) {
        uv_sets.push(uv.into_f32().collect::<Vec<_>>());
    }
    let raw: Vec<u32> = match reader.read_indices() {
        Some(ReadIndices::U8(i)) => i.map(u32::from).collect(),
        Some(ReadIndices::U16(i)) => i.map(u32::from).collect(),
        Some(ReadIndices::U32(i)) => i.collect(),
        None => (0..u32::try_from(n).ok()?).collect(),
    };
    if normals.as_ref().is_some_and(|v| !fits(v.len()))
        || uv_sets.iter().any(|v| !fits(v.len()))
        || raw.iter().any(|&i| i as usize >= n)
    {
        return None;
    }
    let usable = raw.len() - raw.len() % 3;

    // Every attribute's value per vertex, so that vertices equal in all of
    // them count as one. An attribute the reader does not know (a custom
    // `_NAME`) cannot be compared: each vertex then stays its own.
    let uv_wedge = {
        let mut first: HashMap<Vec<u32>, u32> = HashMap::new();
        (0..n)
            .map(|k| {
                let mut key: Vec<u32> = positions[k].map(f32::to_bits).to_vec();
                for set in &uv_sets {
                    key.extend(set[k].map(f32::to_bits));
                }
                *first.entry(key).or_insert(k as u32)
            })
            .collect()
    };
    let custom = prim
        .attributes()
        .any(|(s, _)| matches!(s, Semantic::Extras(_)));
    let canonical: Vec<u32> = if custom {
        (0..n as u32).collect()
    } else {
        let mut keys: Vec<Vec<u32>> = vec![Vec::new(); n];
        let mut push = |k: usize, vals: &[f32]| keys[k].extend(vals.iter().map(|v| v.to_bits()));
        for (k, p) in positions.iter().enumerate() {
            push(k, p);
        }
        for (k, v) in normals.iter().flatten().enumerate() {
            push(k, v);
        }
        for set in &uv_sets {
            for (k, v) in set.iter().enumerate() {
                push(k, v);
            }
        }
        if let Some(t) = reader.read_tangents() {
            for (k, v) in t.enumerate().take(n) {
                push(k, &v);
            }
        }
        let mut s = 0;
        while let Some(c) = reader.read_colors(s) {
            for (k, v) in c.into_rgba_f32().enumerate().take(n) {
                push(k, &v);
            }
            s += 1;
        }
        let mut s = 0;
        while let Some(j) = reader.read_joints(s) {
            for (k, v) in j.into_u16().enumerate().take(n) {
                push(k, &v.map(f32::from));
            }
            s += 1;
        }
        let mut s = 0;
        while let Some(w) = reader.read_weights(s) {
            for (k, v) in w.into_f32().enumerate().take(n) {
                push(k, &v);
            }
            s += 1;
        }
        let mut first: HashMap<&[u32], u32> = HashMap::new();
        keys.iter()
            .enumerate()
            .map(|(k, key)| *first.entry(key.as_slice()).or_insert(k as u32))
            .collect()
    };
    let indices = raw[..usable]
        .iter()
        .map(|&i| canonical[i as usize])
        .collect();
    Some(PrimitiveData {
        positions,
        normals,
        uv_sets,
        indices,
        uv_wedge,
    })
}

/// One level: per simplified mesh, per primitive, its indices (`None`:
/// the primitive as it is). Meshes absent are the same in every level.
pub type LevelIndices = BTreeMap<usize, Vec<Option<Vec<u32>>>>;

/// A model's bytes, and the buffer file beside it (name, bytes) if any.
pub type WithBeside = (Vec<u8>, Option<(String, Vec<u8>)>);

/// A parsed model being added to: its JSON, and where new bytes go.
struct Edit {
    root: Value,
    glb: bool,
    buffer: usize,
    data: Vec<u8>,
    /// The new bytes are a file beside a `.gltf` (or a GLB whose first
    /// buffer is external), by this name.
    external: Option<String>,
}

fn json_err(e: impl std::fmt::Display) -> LodError {
    LodError::Model(e.to_string())
}

fn array<'v>(root: &'v mut Value, key: &str) -> Result<&'v mut Vec<Value>, LodError> {
    root.as_object_mut()
        .ok_or_else(|| json_err("the root is not an object"))?
        .entry(key)
        .or_insert_with(|| Value::Array(Vec::new()))
        .as_array_mut()
        .ok_or_else(|| json_err(format!("\"{key}\" is not an array")))
}

impl Edit {
    /// `external`: the name of the buffer file where the model cannot
    /// carry bytes itself; `None` forces a GLB whose binary chunk is the
    /// first buffer (the other buffers renumbered).
    fn open(main: &[u8], external: Option<&str>) -> Result<Edit, LodError> {
        let parse = |json: &[u8]| -> Result<Value, LodError> {
            let json = json.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(json);
            serde_json::from_slice(json).map_err(json_err)
        };
        let (mut root, bin, glb) = if main.starts_with(b"glTF") {
            let parts = split_glb(main).map_err(json_err)?;
            (parse(parts.json)?, parts.bin.map(<[u8]>::to_vec), true)
        } else {
            (parse(main)?, None, false)
        };
        let first_is_bin = glb
            && root["buffers"]
                .get(0)
                .is_some_and(|b| b.get("uri").is_none());
        if first_is_bin {
            return Ok(Edit {
                root,
                glb,
                buffer: 0,
                data: bin.unwrap_or_default(),
                external: None,
            });
        }
        match external {
            Some(name) => {
                let buffers = array(&mut root, "buffers")?;
                buffers.push(json!({ "uri": name, "byteLength": 0 }));
                let buffer = buffers.len() - 1;
                Ok(Edit {
                    root,
                    glb,
                    buffer,
                    data: Vec::new(),
                    external: Some(name.to_string()),
                })
            }
            None => {
                array(&mut root, "buffers")?.insert(0, json!({ "byteLength": 0 }));
                for view in array(&mut root, "bufferViews")? {
                    if let Some(b) = view.get("buffer").and_then(Value::as_u64) {
                        view["buffer"] = json!(b + 1);
                    }
                }
                Ok(Edit {
                    root,
                    glb: true,
                    buffer: 0,
                    data: Vec::new(),
                    external: None,
                })
            }
        }
    }

    /// A new index accessor: 16-bit where the vertices allow.
    fn push_indices(&mut self, indices: &[u32]) -> Result<usize, LodError> {
        self.data.resize(self.data.len().next_multiple_of(4), 0);
        let at = self.data.len();
        let wide = indices.iter().any(|&i| i > u32::from(u16::MAX) - 1);
        for &i in indices {
            if wide {
                self.data.extend_from_slice(&i.to_le_bytes());
            } else {
                self.data.extend_from_slice(&(i as u16).to_le_bytes());
            }
        }
        let length = self.data.len() - at;
        let views = array(&mut self.root, "bufferViews")?;
        views.push(json!({
            "buffer": self.buffer, "byteOffset": at, "byteLength": length,
            "target": ELEMENT_ARRAY_BUFFER
        }));
        let view = views.len() - 1;
        let accessors = array(&mut self.root, "accessors")?;
        accessors.push(json!({
            "bufferView": view,
            "componentType": if wide { 5125 } else { 5123 },
            "count": indices.len(),
            "type": "SCALAR"
        }));
        Ok(accessors.len() - 1)
    }

    /// Mesh `m`'s JSON with each primitive given its level's indices.
    fn level_mesh(&mut self, m: usize, prims: &[Option<Vec<u32>>]) -> Result<Value, LodError> {
        let mut mesh = self.root["meshes"]
            .get(m)
            .cloned()
            .ok_or_else(|| json_err(format!("mesh {m} does not exist")))?;
        for (p, indices) in prims.iter().enumerate() {
            let Some(indices) = indices else {
                continue;
            };
            let accessor = self.push_indices(indices)?;
            let prim = mesh["primitives"]
                .get_mut(p)
                .and_then(Value::as_object_mut)
                .ok_or_else(|| json_err(format!("mesh {m} has no primitive {p}")))?;
            prim.insert("indices".into(), json!(accessor));
        }
        Ok(mesh)
    }

    /// The bytes: the model in its container, and the buffer file beside
    /// it where there is one.
    fn finish(mut self) -> Result<WithBeside, LodError> {
        self.data.resize(self.data.len().next_multiple_of(4), 0);
        self.root["buffers"][self.buffer]["byteLength"] = json!(self.data.len());
        if self.glb {
            let json = serde_json::to_vec(&self.root).map_err(json_err)?;
            return Ok(match self.external {
                None => (pack_glb(&json, Some(&self.data)), None),
                Some(name) => {
                    // The GLB's own binary chunk, if any, is untouched.
                    (pack_glb(&json, None), Some((name, self.data)))
                }
            });
        }
        let mut out = serde_json::to_vec_pretty(&self.root).map_err(json_err)?;
        out.push(b'\n');
        Ok((out, self.external.map(|n| (n, self.data))))
    }
}

/// The model (`.glb` or `.gltf`) with its levels of detail through
/// `MSFT_lod`: each node whose mesh was simplified gets one node per level
/// (outside the scene, as the extension has them) with the level's mesh.
/// `external` names the buffer file for the levels' indices where the
/// model's binary chunk cannot hold them; it is returned with its bytes.
pub fn with_lods(
    main: &[u8],
    levels: &[LevelIndices],
    ratios: &[f64],
    external: &str,
) -> Result<WithBeside, LodError> {
    if main.starts_with(b"glTF") {
        // A GLB whose binary chunk is lost on re-packing would lose data.
        let bin = split_glb(main).map_err(json_err)?.bin;
        if bin.is_some() && !first_buffer_is_bin(main)? {
            return Err(json_err("the GLB's binary chunk is not its first buffer"));
        }
    }
    let mut edit = Edit::open(main, Some(external))?;
    // Per level, mesh → its level mesh's index.
    let mut level_meshes: Vec<BTreeMap<usize, usize>> = Vec::with_capacity(levels.len());
    for (k, level) in levels.iter().enumerate() {
        let mut map = BTreeMap::new();
        for (&m, prims) in level {
            let mut mesh = edit.level_mesh(m, prims)?;
            if let Some(name) = mesh.get("name").and_then(Value::as_str) {
                mesh["name"] = json!(format!("{name}_LOD{}", k + 1));
            }
            let meshes = array(&mut edit.root, "meshes")?;
            meshes.push(mesh);
            map.insert(m, meshes.len() - 1);
        }
        level_meshes.push(map);
    }
    let coverage: Vec<f64> = ratios
        .iter()
        .map(|r| FULL_DETAIL_COVERAGE * r)
        .chain([0.0])
        .collect();
    let node_count = edit.root["nodes"].as_array().map_or(0, Vec::len);
    let mut any = false;
    for n in 0..node_count {
        let node = &edit.root["nodes"][n];
        let Some(m) = node.get("mesh").and_then(Value::as_u64) else {
            continue;
        };
        let m = m as usize;
        if level_meshes.iter().any(|l| !l.contains_key(&m)) || levels.is_empty() {
            continue;
        }
        let mut ids = Vec::with_capacity(levels.len());
        for (k, map) in level_meshes.iter().enumerate() {
            let mut lod = Map::new();
            let node = &edit.root["nodes"][n];
            for key in ["translation", "rotation", "scale", "matrix", "skin"] {
                if let Some(v) = node.get(key) {
                    lod.insert(key.into(), v.clone());
                }
            }
            if let Some(name) = node.get("name").and_then(Value::as_str) {
                lod.insert("name".into(), json!(format!("{name}_LOD{}", k + 1)));
            }
            lod.insert("mesh".into(), json!(map[&m]));
            let nodes = array(&mut edit.root, "nodes")?;
            nodes.push(Value::Object(lod));
            ids.push(nodes.len() - 1);
        }
        let node = edit.root["nodes"][n]
            .as_object_mut()
            .ok_or_else(|| json_err(format!("node {n} is not an object")))?;
        let extensions = node
            .entry("extensions")
            .or_insert_with(|| Value::Object(Map::new()));
        if let Some(e) = extensions.as_object_mut() {
            e.insert(LOD_EXTENSION.into(), json!({ "ids": ids }));
        }
        let extras = node
            .entry("extras")
            .or_insert_with(|| Value::Object(Map::new()));
        if let Some(e) = extras.as_object_mut() {
            e.insert(COVERAGE_EXTRA.into(), json!(coverage));
        }
        any = true;
    }
    if any {
        let used = array(&mut edit.root, "extensionsUsed")?;
        if !used.iter().any(|e| e.as_str() == Some(LOD_EXTENSION)) {
            used.push(json!(LOD_EXTENSION));
        }
    }
    edit.finish()
}

fn first_buffer_is_bin(main: &[u8]) -> Result<bool, LodError> {
    let json = split_glb(main).map_err(json_err)?.json;
    let root: Value = serde_json::from_slice(json).map_err(json_err)?;
    Ok(root["buffers"]
        .get(0)
        .is_some_and(|b| b.get("uri").is_none()))
}

/// One level on its own, as a GLB: the model with each simplified
/// primitive's indices replaced, and every file it referred to still
/// referred to the same way (the same textures serve every level).
pub fn level_glb(main: &[u8], level: &LevelIndices) -> Result<Vec<u8>, LodError> {
    let mut edit = Edit::open(main, None)?;
    for (&m, prims) in level {
        let mesh = edit.level_mesh(m, prims)?;
        array(&mut edit.root, "meshes")?[m] = mesh;
    }
    Ok(edit.finish()?.0)
}
