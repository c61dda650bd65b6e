//! Model loader: real assets, broken assets, confinement, generated models.

use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

use base64::Engine as _;
use serde_json::{json, Value};

use seamstress::model::{
    load, load_from_memory, LoadError, LoadErrorKind, LoadOptions, Model, NoFiles, Texture,
    TextureEncoding, TextureError, Wrap,
};

fn assets() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/assets")
}

fn load_asset(rel: &str) -> Model {
    let path = assets().join(rel);
    load(&path, &LoadOptions::default()).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

fn triangle_count(m: &Model) -> usize {
    m.bindings.iter().map(|b| b.triangles.len()).sum()
}

fn assert_close(a: [f64; 2], b: [f64; 2]) {
    assert!(
        (a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6,
        "{a:?} != {b:?}"
    );
}

/// A scratch folder per test, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> TempDir {
        let dir = std::env::temp_dir().join(format!(
            "seamstress-load-{}-{tag}-{}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

// ------------------------------------------------------------- real assets

#[test]
fn fox_loads() {
    let m = load_asset("Fox/Fox.gltf");
    assert_eq!(m.bindings.len(), 1);
    let b = &m.bindings[0];
    assert_eq!((b.texture.width, b.texture.height), (2048, 2048));
    assert_eq!(b.triangles.len(), 980);
    assert_eq!((b.wrap_s, b.wrap_t), (Wrap::Repeat, Wrap::Repeat));
    assert!(b.srgb);
    assert_eq!(b.name, "Fox", "an unnamed image takes the model's stem");
    // This copy's V range lies in 1.02..1.99 and relies on REPEAT.
    let (lo, hi) = b
        .triangles
        .iter()
        .flat_map(|t| t.uvs.iter().map(|uv| uv[1]))
        .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    assert!(lo > 1.0 && hi < 2.0, "V range {lo}..{hi}");
    assert!(m.skipped.is_empty());
}

#[test]
fn duck_loads() {
    let m = load_asset("Duck/Duck.gltf");
    assert_eq!(m.bindings.len(), 1);
    let b = &m.bindings[0];
    assert_eq!((b.texture.width, b.texture.height), (512, 512));
    assert_eq!(b.texture.channels, 4);
    assert_eq!(
        b.texture.encoding,
        TextureEncoding {
            channels: 4,
            bits: 8
        }
    );
    assert_eq!(b.texture.data.len(), 512 * 512 * 4);
    assert_eq!(b.triangles.len(), 4212);
    // Nearly degenerate UV triangles (around the eyes) are kept as they are.
    let tiny = b
        .triangles
        .iter()
        .filter(|t| {
            let [a, b, c] = t.uvs;
            ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])).abs() < 1e-8
        })
        .count();
    assert!(tiny > 0);
}

#[test]
fn box_textured_forms_agree() {
    let dir = "BoxTextured/";
    let separate = load_asset(&format!("{dir}BoxTextured-glTF/BoxTextured.gltf"));
    let binary = load_asset(&format!("{dir}BoxTextured-glTF-Binary/BoxTextured.glb"));
    let embedded = load_asset(&format!("{dir}BoxTextured-glTF-Embedded/BoxTextured.gltf"));
    for m in [&separate, &binary, &embedded] {
        assert_eq!(m.bindings.len(), 1);
        let b = &m.bindings[0];
        assert_eq!((b.texture.width, b.texture.height), (211, 211));
        assert_eq!(b.triangles.len(), 12);
        assert_eq!(b.image, 0);
        assert!(b.srgb);
    }
    let (s, g, e) = (
        &separate.bindings[0],
        &binary.bindings[0],
        &embedded.bindings[0],
    );
    assert_eq!(s.triangles, g.triangles);
    assert_eq!(s.triangles, e.triangles);
    assert_eq!(s.texture, g.texture);
    assert_eq!(s.texture, e.texture);
    // The copies differ only in their samplers.
    assert_eq!(
        (s.wrap_s, s.wrap_t),
        (Wrap::MirroredRepeat, Wrap::ClampToEdge)
    );
    assert_eq!((g.wrap_s, g.wrap_t), (Wrap::Repeat, Wrap::Repeat));
    assert_eq!((e.wrap_s, e.wrap_t), (Wrap::Repeat, Wrap::Repeat));
    assert_eq!(s.name, "CesiumLogoFlat");
    assert_eq!(g.name, "BoxTextured");
}

#[test]
fn blub_loads() {
    let m = load_asset("blub/blub.glb");
    assert_eq!(m.bindings.len(), 1);
    let b = &m.bindings[0];
    assert_eq!((b.texture.width, b.texture.height), (2048, 2048));
    assert_eq!(b.triangles.len(), 14208);
    assert_eq!((b.wrap_s, b.wrap_t), (Wrap::ClampToEdge, Wrap::ClampToEdge));
}

#[test]
fn cubes_load() {
    for (file, size) in [
        ("cube_gradient_128.glb", 128),
        ("cube_gradient_1024.glb", 1024),
        ("cube_bad_background_100.glb", 100),
    ] {
        let m = load_asset(&format!("cube/{file}"));
        assert_eq!(m.bindings.len(), 1, "{file}");
        let b = &m.bindings[0];
        assert_eq!((b.texture.width, b.texture.height), (size, size), "{file}");
        assert_eq!(b.triangles.len(), 12, "{file}");
        assert_eq!((b.wrap_s, b.wrap_t), (Wrap::ClampToEdge, Wrap::ClampToEdge));
    }
}

#[test]
fn texture_transform_is_applied() {
    let m = load_asset("TextureTransformTest/TextureTransformTest.gltf");
    assert_eq!(triangle_count(&m), 18);
    let images: Vec<usize> = m.bindings.iter().map(|b| b.image).collect();
    assert_eq!(images, [0, 1, 2, 3, 4]);
    let names: Vec<&str> = m.bindings.iter().map(|b| b.name.as_str()).collect();
    assert_eq!(names, ["UV", "Arrow", "Correct", "NotSupported", "Error"]);
    let uv = &m.bindings[0];
    assert_eq!((uv.texture.width, uv.texture.height), (256, 256));
    assert_eq!(
        (uv.wrap_s, uv.wrap_t),
        (Wrap::ClampToEdge, Wrap::ClampToEdge)
    );
    assert_eq!(uv.triangles.len(), 6);
    // Meshes 0..2 ("Offset U", "Offset V", "Offset UV") sample TEXCOORD_0 =
    // (0,0),(0.5,0),(0.5,0.5),(0,0.5) with indices 0,2,1, 2,0,3.
    let t = &uv.triangles;
    assert_close(t[0].uvs[0], [0.5, 0.0]);
    assert_close(t[0].uvs[1], [1.0, 0.5]);
    assert_close(t[0].uvs[2], [1.0, 0.0]);
    assert_close(t[2].uvs[1], [0.5, 1.0]);
    assert_close(t[4].uvs[1], [1.0, 1.0]);
    // Each mesh welds on its own.
    let groups: Vec<u32> = t.iter().map(|t| t.group).collect();
    assert!(groups[0] == groups[1] && groups[2] == groups[3] && groups[0] != groups[2]);
    assert_ne!(groups[2], groups[4]);

    let arrow = &m.bindings[1];
    assert_eq!((arrow.texture.width, arrow.texture.height), (128, 128));
    assert_eq!(arrow.triangles.len(), 6);
    // "All": offset (-0.2,-0.1), rotation 0.3, scale 1.5 on UV (1,1).
    let (s, c) = 0.3f64.sin_cos();
    let expect = [c * 1.5 + s * 1.5 - 0.2, -s * 1.5 + c * 1.5 - 0.1];
    assert_close(arrow.triangles[4].uvs[1], expect);
    assert_close(arrow.triangles[4].uvs[0], [-0.2, -0.1]);
    // "Rotation": π/8 on UV (1,1).
    let (s, c) = std::f64::consts::FRAC_PI_8.sin_cos();
    assert_close(arrow.triangles[0].uvs[1], [c + s, -s + c]);
    // "Scale".
    assert_close(arrow.triangles[2].uvs[1], [1.5, 1.5]);
    assert_eq!(arrow.triangles[0].positions[1], [0.5, -0.5, 0.0]);
}

#[test]
fn in_memory_matches_disk() {
    let dir = assets().join("BoxTextured/BoxTextured-glTF");
    let mut files = HashMap::new();
    for name in ["BoxTextured0.bin", "CesiumLogoFlat.png"] {
        files.insert(name.to_string(), std::fs::read(dir.join(name)).unwrap());
    }
    let main = std::fs::read(dir.join("BoxTextured.gltf")).unwrap();
    let opts = LoadOptions::default();
    let mem = load_from_memory("BoxTextured.gltf", &main, &files, &opts).unwrap();
    let disk = load(&dir.join("BoxTextured.gltf"), &opts).unwrap();
    assert_eq!(mem.bindings[0].triangles, disk.bindings[0].triangles);
    assert_eq!(mem.bindings[0].texture, disk.bindings[0].texture);

    let err = load_from_memory("BoxTextured.gltf", &main, &NoFiles, &opts).unwrap_err();
    assert!(matches!(err.kind, LoadErrorKind::Missing { .. }), "{err}");
    assert!(err.is_bad_input());

    let glb = std::fs::read(assets().join("BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb"))
        .unwrap();
    let m = load_from_memory("upload.glb", &glb, &NoFiles, &opts).unwrap();
    assert_eq!(m.bindings[0].triangles, disk.bindings[0].triangles);
}

#[test]
fn texture_above_limit_is_refused() {
    let opts = LoadOptions {
        max_texture_size: 200,
        ..LoadOptions::default()
    };
    let path = assets().join("BoxTextured/BoxTextured-glTF/BoxTextured.gltf");
    let err = load(&path, &opts).unwrap_err();
    assert!(
        matches!(
            err.kind,
            LoadErrorKind::Texture {
                image: 0,
                source: TextureError::TooLarge {
                    width: 211,
                    height: 211,
                    limit: 200
                }
            }
        ),
        "{err}"
    );
    assert!(err.is_bad_input());
    assert!(err.to_string().contains("above the limit"), "{err}");
}

// ---------------------------------------------------------- broken assets

fn collect_models(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            collect_models(&path, out);
        } else if matches!(
            path.extension().and_then(|e| e.to_str()),
            Some("gltf") | Some("glb")
        ) {
            out.push(path);
        }
    }
}

#[test]
fn negative_assets_fail_cleanly() {
    let root = assets().join("negative");
    let mut files = Vec::new();
    collect_models(&root, &mut files);
    files.sort();
    assert!(files.len() >= 11, "found {}", files.len());
    for path in &files {
        let result = catch_unwind(|| load(path, &LoadOptions::default()));
        let err = match result {
            Ok(Ok(_)) => panic!("{} loaded", path.display()),
            Ok(Err(e)) => e,
            Err(_) => panic!("{} panicked", path.display()),
        };
        let msg = err.to_string();
        println!("{msg}");
        assert!(!msg.contains('\n'), "{msg}");
        assert!(msg.starts_with(&path.display().to_string()), "{msg}");
        assert!(err.is_bad_input(), "{msg}");
    }
    let msg = |rel: &str| {
        load(&root.join(rel), &LoadOptions::default())
            .unwrap_err()
            .to_string()
    };
    assert!(msg("BoxTextured_draco.glb").ends_with(
        "BoxTextured_draco.glb: required extension KHR_draco_mesh_compression is not supported"
    ));
    assert!(msg("IndexOutOfRange/IndexOutOfRange.gltf").ends_with(
        "accessor 0 (indices of mesh 0 primitive 0): index 255 out of range for 24 vertices"
    ));
    assert!(msg("IndexOutOfRange/AllIndicesOutOfRange.gltf")
        .ends_with("index 65535 out of range for 24 vertices"));
    assert!(msg("MissingBin/BoxTextured.gltf")
        .ends_with("buffer 0: file \"BoxTextured0.bin\" not found"));
}

#[test]
fn missing_model_file() {
    let err = load(
        Path::new("/nonexistent/seamstress/model.glb"),
        &LoadOptions::default(),
    )
    .unwrap_err();
    assert!(err.is_bad_input());
    assert!(err
        .to_string()
        .starts_with("/nonexistent/seamstress/model.glb: "));
}

// ------------------------------------------------------- generated models

struct Prim {
    positions: Vec<[f32; 3]>,
    uvs: Vec<[f32; 2]>,
    indices: Option<Vec<u16>>,
    mode: u32,
}

fn quad() -> Prim {
    Prim {
        positions: vec![[0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.]],
        uvs: vec![[0., 1.], [1., 1.], [1., 0.], [0., 0.]],
        indices: Some(vec![0, 1, 2, 0, 2, 3]),
        mode: 4,
    }
}

fn small_png(w: usize, h: usize) -> Vec<u8> {
    Texture {
        width: w,
        height: h,
        channels: 3,
        data: (0..w * h * 3).map(|i| (i % 7) as f32 / 7.0).collect(),
        encoding: TextureEncoding {
            channels: 3,
            bits: 8,
        },
    }
    .encode_png()
    .unwrap()
}

fn data_uri(mime: &str, bytes: &[u8]) -> String {
    format!(
        "data:{mime};base64,{}",
        base64::engine::general_purpose::STANDARD.encode(bytes)
    )
}

/// A glTF with one mesh per `Prim` (one primitive each, material 0) and a
/// base-colour texture; the buffer is returned beside the JSON, whose
/// buffer URI is `buffer.bin`.
fn model(prims: &[Prim]) -> (Value, Vec<u8>) {
    let mut bin = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut meshes = Vec::new();
    let mut push_view = |bin: &mut Vec<u8>, bytes: &[u8]| -> usize {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len()}));
        bin.extend_from_slice(bytes);
        views.len() - 1
    };
    for p in prims {
        let pos: Vec<u8> = p
            .positions
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let uv: Vec<u8> = p
            .uvs
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let pv = push_view(&mut bin, &pos);
        let uvv = push_view(&mut bin, &uv);
        let pa = accessors.len();
        accessors.push(json!({"bufferView": pv, "componentType": 5126,
            "count": p.positions.len(), "type": "VEC3",
            "min": [-1e9, -1e9, -1e9], "max": [1e9, 1e9, 1e9]}));
        accessors.push(json!({"bufferView": uvv, "componentType": 5126,
            "count": p.uvs.len(), "type": "VEC2"}));
        let mut prim = json!({"attributes": {"POSITION": pa, "TEXCOORD_0": pa + 1},
            "material": 0, "mode": p.mode});
        if let Some(idx) = &p.indices {
            let bytes: Vec<u8> = idx.iter().flat_map(|v| v.to_le_bytes()).collect();
            let iv = push_view(&mut bin, &bytes);
            accessors.push(json!({"bufferView": iv, "componentType": 5123,
                "count": idx.len(), "type": "SCALAR"}));
            prim["indices"] = json!(accessors.len() - 1);
        }
        meshes.push(json!({"primitives": [prim]}));
    }
    let doc = json!({
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "buffer.bin", "byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": accessors,
        "meshes": meshes,
        "images": [{"uri": data_uri("image/png", &small_png(8, 4))}],
        "samplers": [{"wrapS": 33071, "wrapT": 33648}],
        "textures": [{"source": 0, "sampler": 0}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
    });
    (doc, bin)
}

fn load_doc(doc: &Value, bin: &[u8]) -> Result<Model, LoadError> {
    let mut files = HashMap::new();
    files.insert("buffer.bin".to_string(), bin.to_vec());
    let main = serde_json::to_vec(doc).unwrap();
    load_from_memory("test.gltf", &main, &files, &LoadOptions::default())
}

#[test]
fn generated_quad_loads() {
    let (doc, bin) = model(&[quad()]);
    let m = load_doc(&doc, &bin).unwrap();
    assert_eq!(m.bindings.len(), 1);
    let b = &m.bindings[0];
    assert_eq!(
        (b.texture.width, b.texture.height, b.texture.channels),
        (8, 4, 3)
    );
    assert_eq!(
        (b.wrap_s, b.wrap_t),
        (Wrap::ClampToEdge, Wrap::MirroredRepeat)
    );
    assert_eq!(b.triangles.len(), 2);
    assert_eq!(b.triangles[1].positions[2], [0., 1., 0.]);
    assert_eq!(b.triangles[1].uvs[2], [0., 0.]);
}

#[test]
fn strip_and_fan_are_triangulated() {
    // Strip over a 2×3 grid of vertices: 4 triangles, all facing +z.
    let strip = Prim {
        positions: vec![
            [0., 0., 0.],
            [0., 1., 0.],
            [1., 0., 0.],
            [1., 1., 0.],
            [2., 0., 0.],
            [2., 1., 0.],
        ],
        uvs: vec![[0., 0.]; 6],
        indices: None,
        mode: 5,
    };
    let fan = Prim {
        positions: vec![
            [0., 0., 0.],
            [1., 0., 0.],
            [1., 1., 0.],
            [0., 1., 0.],
            [-1., 0., 0.],
        ],
        uvs: vec![[0.5, 0.5]; 5],
        indices: Some(vec![0, 1, 2, 3, 4]),
        mode: 6,
    };
    let (doc, bin) = model(&[strip, fan]);
    let m = load_doc(&doc, &bin).unwrap();
    let tris = &m.bindings[0].triangles;
    assert_eq!(tris.len(), 4 + 3);
    let normal_z = |t: &seamstress::model::UvTriangle| {
        let [a, b, c] = t.positions;
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    };
    let z: Vec<f32> = tris.iter().map(normal_z).collect();
    assert!(z[..4].iter().all(|&z| z < 0.0), "strip winding {z:?}");
    assert!(z[4..].iter().all(|&z| z > 0.0), "fan winding {z:?}");
    assert_ne!(tris[0].group, tris[4].group);
}

#[test]
fn points_and_lines_are_skipped() {
    let mut points = quad();
    points.mode = 0;
    let mut lines = quad();
    lines.mode = 1;
    let mut loop_ = quad();
    loop_.mode = 2;
    let (doc, bin) = model(&[quad(), points, lines, loop_]);
    let m = load_doc(&doc, &bin).unwrap();
    assert_eq!(m.bindings[0].triangles.len(), 2);
    assert_eq!(m.skipped.len(), 3);
    let s = &m.skipped[1];
    assert_eq!((s.mesh, s.primitive, s.image), (Some(2), Some(0), None));
    assert_eq!(s.reason, "mode LINES has no triangles");
    assert_eq!(m.skipped[0].reason, "mode POINTS has no triangles");
}

#[test]
fn non_finite_values_are_rejected() {
    let mut p = quad();
    p.positions[2][1] = f32::NAN;
    let (doc, bin) = model(&[p]);
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert_eq!(
        err,
        "test.gltf: accessor 0 (POSITION of mesh 0 primitive 0): element 2 is not finite"
    );

    let mut p = quad();
    p.uvs[1][0] = f32::INFINITY;
    let (doc, bin) = model(&[p]);
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert!(err.contains("TEXCOORD_0 of mesh 0 primitive 0"), "{err}");
}

#[test]
fn index_and_range_errors() {
    let mut p = quad();
    p.indices = Some(vec![0, 1, 4]);
    let (doc, bin) = model(&[p]);
    let err = load_doc(&doc, &bin).unwrap_err();
    assert!(
        err.to_string()
            .ends_with("index 4 out of range for 4 vertices"),
        "{err}"
    );

    let (mut doc, bin) = model(&[quad()]);
    doc["accessors"][1]["count"] = json!(5);
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert!(err.contains("accessor 1"), "{err}");

    let (mut doc, bin) = model(&[quad()]);
    doc["buffers"][0]["byteLength"] = json!(bin.len() + 1);
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert!(err.contains("buffer 0: byteLength"), "{err}");

    let (mut doc, bin) = model(&[quad()]);
    doc["bufferViews"][0]["byteOffset"] = json!(4_000_000_000u64);
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert!(err.contains("bufferView 0"), "{err}");

    let (mut doc, bin) = model(&[quad()]);
    doc["accessors"][1]["type"] = json!("VEC3");
    assert!(load_doc(&doc, &bin).is_err());

    let (mut doc, bin) = model(&[quad()]);
    doc["extensionsRequired"] = json!(["EXT_meshopt_compression"]);
    doc["extensionsUsed"] = json!(["EXT_meshopt_compression"]);
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert_eq!(
        err,
        "test.gltf: required extension EXT_meshopt_compression is not supported"
    );

    let (mut doc, bin) = model(&[quad()]);
    doc["images"][0]["uri"] = json!("missing.png");
    let err = load_doc(&doc, &bin).unwrap_err().to_string();
    assert_eq!(err, "test.gltf: image 0: file \"missing.png\" not found");
}

#[test]
fn normalized_texcoords_and_sparse_accessors() {
    let (mut doc, mut bin) = model(&[quad()]);
    // TEXCOORD_0 as normalized u16, then one vertex overridden sparsely.
    let start = bin.len();
    for uv in [[0u16, 65535], [65535, 65535], [65535, 0], [0, 0]] {
        bin.extend(uv.iter().flat_map(|v| v.to_le_bytes()));
    }
    let sparse_idx = bin.len();
    bin.extend_from_slice(&[3u8, 0, 0, 0]);
    let sparse_val = bin.len();
    bin.extend([32768u16, 32768].iter().flat_map(|v| v.to_le_bytes()));
    doc["buffers"][0]["byteLength"] = json!(bin.len());
    let views = doc["bufferViews"].as_array_mut().unwrap();
    views.push(json!({"buffer": 0, "byteOffset": start, "byteLength": 16}));
    views.push(json!({"buffer": 0, "byteOffset": sparse_idx, "byteLength": 1}));
    views.push(json!({"buffer": 0, "byteOffset": sparse_val, "byteLength": 4}));
    let n = views.len();
    doc["accessors"][1] = json!({"bufferView": n - 3, "componentType": 5123,
        "normalized": true, "count": 4, "type": "VEC2",
        "sparse": {"count": 1,
            "indices": {"bufferView": n - 2, "componentType": 5121},
            "values": {"bufferView": n - 1}}});
    let m = load_doc(&doc, &bin).unwrap();
    let t = &m.bindings[0].triangles;
    assert_eq!(t[0].uvs[1], [1.0, 1.0]);
    let half = f64::from(32768.0f32 / 65535.0);
    assert_eq!(t[1].uvs[2], [half, half]);
}

#[test]
fn shared_image_is_one_binding_and_maps_are_chosen() {
    let (mut doc, bin) = model(&[quad(), quad()]);
    doc["images"]
        .as_array_mut()
        .unwrap()
        .push(json!({"uri": data_uri("image/png", &small_png(2, 2)), "name": "normals"}));
    doc["images"]
        .as_array_mut()
        .unwrap()
        .push(json!({"uri": data_uri("image/png", &small_png(4, 4)), "name": "ao"}));
    doc["textures"] = json!([{"source": 0}, {"source": 1}, {"source": 2}]);
    doc["materials"] = json!([
        {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}},
         "normalTexture": {"index": 1}, "occlusionTexture": {"index": 2,
            "extensions": {"KHR_texture_transform": {"offset": [0.25, 0.0]}}}},
        {"emissiveTexture": {"index": 0}},
    ]);
    doc["meshes"][1]["primitives"][0]["material"] = json!(1);
    let m = load_doc(&doc, &bin).unwrap();
    assert_eq!(m.bindings.len(), 1);
    let b = &m.bindings[0];
    assert_eq!(b.triangles.len(), 4);
    assert_eq!((b.wrap_s, b.wrap_t), (Wrap::Repeat, Wrap::Repeat));
    assert_ne!(b.triangles[0].group, b.triangles[2].group);
    assert_eq!(m.skipped.len(), 1);
    assert_eq!(m.skipped[0].image, Some(1));
    assert_eq!(m.skipped[0].reason, "tangent-space normal map");

    let mut files = HashMap::new();
    files.insert("buffer.bin".to_string(), bin.clone());
    let opts = LoadOptions {
        extra_maps: true,
        ..LoadOptions::default()
    };
    let main = serde_json::to_vec(&doc).unwrap();
    let m = load_from_memory("test.gltf", &main, &files, &opts).unwrap();
    assert_eq!(m.bindings.len(), 2);
    let ao = &m.bindings[1];
    assert_eq!((ao.image, ao.name.as_str(), ao.srgb), (2, "ao", false));
    assert_eq!(ao.triangles.len(), 2);
    assert_eq!(ao.triangles[0].uvs[0], [0.25, 1.0]);
}

#[test]
fn missing_texcoord_set_is_skipped() {
    let (mut doc, bin) = model(&[quad()]);
    doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["texCoord"] = json!(1);
    let m = load_doc(&doc, &bin).unwrap();
    assert!(m.bindings.is_empty());
    assert_eq!(m.skipped.len(), 1, "{:?}", m.skipped);
    let s = &m.skipped[0];
    assert_eq!((s.image, s.mesh, s.primitive), (Some(0), Some(0), Some(0)));
    assert_eq!(
        s.reason,
        "baseColorTexture uses TEXCOORD_1, which the primitive lacks"
    );
}

// ------------------------------------------------------------ confinement

fn write_model(dir: &Path, name: &str, buffer_uri: &str, bin: &[u8]) -> PathBuf {
    let (mut doc, _) = model(&[quad()]);
    doc["buffers"][0]["uri"] = json!(buffer_uri);
    doc["buffers"][0]["byteLength"] = json!(bin.len());
    let path = dir.join(name);
    std::fs::write(&path, serde_json::to_vec_pretty(&doc).unwrap()).unwrap();
    path
}

#[test]
fn uris_are_confined_to_the_model_folder() {
    let tmp = TempDir::new("confine");
    let inner = tmp.0.join("model");
    std::fs::create_dir_all(&inner).unwrap();
    let (_, bin) = model(&[quad()]);
    std::fs::write(tmp.0.join("x.bin"), &bin).unwrap();

    for (uri, why) in [
        ("../x.bin", "\"..\""),
        ("sub/../../x.bin", "\"..\""),
        ("%2E%2E/x.bin", "\"..\""),
        ("/etc/passwd", "absolute"),
        ("%2Fetc%2Fpasswd", "absolute"),
        ("http://example.com/a.bin", "scheme \"http:\""),
        ("file:///etc/passwd", "scheme \"file:\""),
        ("HTTPS://example.com/a.bin", "scheme"),
    ] {
        let path = write_model(&inner, "m.gltf", uri, &bin);
        let err = load(&path, &LoadOptions::default()).unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(err.kind, LoadErrorKind::Refused { .. }),
            "{uri}: {msg}"
        );
        assert!(err.is_bad_input());
        assert!(msg.contains("refused") && msg.contains(why), "{uri}: {msg}");
        assert!(msg.starts_with(&path.display().to_string()), "{msg}");
    }

    // Percent-escapes inside the folder resolve.
    std::fs::write(inner.join("my data+1.bin"), &bin).unwrap();
    let path = write_model(&inner, "ok.gltf", "my%20data%2B1.bin", &bin);
    let m = load(&path, &LoadOptions::default()).unwrap();
    assert_eq!(m.bindings[0].triangles.len(), 2);

    std::fs::create_dir_all(inner.join("sub")).unwrap();
    std::fs::write(inner.join("sub/b.bin"), &bin).unwrap();
    let path = write_model(&inner, "sub.gltf", "./sub/b.bin", &bin);
    assert!(load(&path, &LoadOptions::default()).is_ok());
}

#[cfg(unix)]
#[test]
fn symlinks_cannot_escape() {
    let tmp = TempDir::new("symlink");
    let inner = tmp.0.join("model");
    std::fs::create_dir_all(&inner).unwrap();
    let (_, bin) = model(&[quad()]);
    std::fs::write(tmp.0.join("outside.bin"), &bin).unwrap();
    std::os::unix::fs::symlink(tmp.0.join("outside.bin"), inner.join("link.bin")).unwrap();
    let path = write_model(&inner, "m.gltf", "link.bin", &bin);
    let err = load(&path, &LoadOptions::default()).unwrap_err();
    assert!(matches!(err.kind, LoadErrorKind::Refused { .. }), "{err}");
    assert!(
        err.to_string().contains("outside the model's folder"),
        "{err}"
    );

    // A link that stays inside is fine.
    std::fs::write(inner.join("real.bin"), &bin).unwrap();
    std::os::unix::fs::symlink(inner.join("real.bin"), inner.join("alias.bin")).unwrap();
    let path = write_model(&inner, "m2.gltf", "alias.bin", &bin);
    assert!(load(&path, &LoadOptions::default()).is_ok());
}

// ------------------------------------------------------------- robustness

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn mutate(rng: &mut Rng, src: &[u8], text: bool) -> Vec<u8> {
    let mut b = src.to_vec();
    match rng.below(4) {
        0 => {
            for _ in 0..1 + rng.below(8) {
                let i = rng.below(b.len());
                b[i] ^= 1 << rng.below(8);
            }
        }
        1 => b.truncate(rng.below(b.len())),
        2 if text => {
            // Replace one number with a hostile one.
            let digits: Vec<usize> = (0..b.len()).filter(|&i| b[i].is_ascii_digit()).collect();
            let at = digits[rng.below(digits.len())];
            let end = (at..b.len())
                .find(|&i| !b[i].is_ascii_digit())
                .unwrap_or(b.len());
            let subst = [
                "0",
                "1",
                "-1",
                "3",
                "255",
                "65535",
                "4294967295",
                "18446744073709551615",
                "99999999999999",
                "1e40",
                "0.5",
            ];
            let s = subst[rng.below(subst.len())];
            b.splice(at..end, s.bytes());
        }
        _ => {
            for _ in 0..1 + rng.below(4) {
                let i = rng.below(b.len());
                b[i] = rng.next() as u8;
            }
        }
    }
    b
}

#[test]
fn mutated_inputs_never_panic() {
    let dir = assets().join("BoxTextured");
    let glb = std::fs::read(dir.join("BoxTextured-glTF-Binary/BoxTextured.glb")).unwrap();
    let gltf = std::fs::read(dir.join("BoxTextured-glTF/BoxTextured.gltf")).unwrap();
    let bin = std::fs::read(dir.join("BoxTextured-glTF/BoxTextured0.bin")).unwrap();
    let png = std::fs::read(dir.join("BoxTextured-glTF/CesiumLogoFlat.png")).unwrap();
    let embedded = std::fs::read(dir.join("BoxTextured-glTF-Embedded/BoxTextured.gltf")).unwrap();
    let opts = LoadOptions::default();
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let (mut ok, mut err) = (0, 0);
    // SEAMSTRESS_FUZZ_CASES raises the count for longer local runs.
    let cases: usize = std::env::var("SEAMSTRESS_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(600);
    for case in 0..cases {
        let mut files = HashMap::new();
        files.insert("BoxTextured0.bin".to_string(), bin.clone());
        files.insert("CesiumLogoFlat.png".to_string(), png.clone());
        let (name, main) = match case % 5 {
            0 => ("BoxTextured.glb", mutate(&mut rng, &glb, false)),
            1 => ("BoxTextured.gltf", mutate(&mut rng, &gltf, true)),
            2 => {
                let m = mutate(&mut rng, &bin, false);
                files.insert("BoxTextured0.bin".to_string(), m);
                ("BoxTextured.gltf", gltf.clone())
            }
            3 => {
                let m = mutate(&mut rng, &png, false);
                files.insert("CesiumLogoFlat.png".to_string(), m);
                ("BoxTextured.gltf", gltf.clone())
            }
            _ => ("BoxTextured.gltf", mutate(&mut rng, &embedded, true)),
        };
        let result = catch_unwind(AssertUnwindSafe(|| {
            load_from_memory(name, &main, &files, &opts)
        }));
        match result {
            Ok(Ok(_)) => ok += 1,
            Ok(Err(e)) => {
                let msg = e.to_string();
                assert!(!msg.contains('\n'), "case {case}: {msg}");
                assert!(msg.starts_with(name), "case {case}: {msg}");
                err += 1;
            }
            Err(_) => panic!(
                "case {case} panicked; input: {:?}",
                String::from_utf8_lossy(&main[..main.len().min(400)])
            ),
        }
    }
    println!("mutations: {ok} loaded, {err} refused");
    assert!(ok > 0 && err > 0);
}

#[test]
fn glb_on_disk_and_parse_errors() {
    let tmp = TempDir::new("glb");
    let path = tmp.0.join("broken.glb");
    std::fs::write(&path, b"glTF\x02\0\0\0\x08\0\0\0").unwrap();
    let err = load(&path, &LoadOptions::default()).unwrap_err();
    assert!(matches!(err.kind, LoadErrorKind::Malformed(_)), "{err}");
    let path = tmp.0.join("broken.gltf");
    std::fs::write(&path, b"{\"asset\": {\"version\": \"2.0\"}, \"meshes\": 5}").unwrap();
    let err = load(&path, &LoadOptions::default()).unwrap_err();
    assert!(err.to_string().contains("invalid glTF JSON"), "{err}");
}
