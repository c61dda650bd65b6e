//! What the integration tests share: the outside tools some of them compare
//! against, and a running server. (Each test file uses some of it.)
#![allow(dead_code)]

pub mod cluster;
pub mod server;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use base64::Engine as _;
use serde_json::Value;

/// Set (as `.ci/run` does, after installing the tools) to make a missing
/// outside tool fail the tests that need it instead of skipping them.
const REQUIRE: &str = "SEAMSTRESS_REQUIRE_TOOLS";

/// Python with the modules the independent evaluator
/// (`../shared/tools/seam_eval.py`) and the Pillow DDS check import.
pub const PYTHON: Tool = Tool {
    name: "python3 with numpy, pillow and pygltflib",
    probe: &["python3", "-c", "import numpy, PIL, pygltflib"],
    install: "python3 -m pip install numpy pillow pygltflib",
};

/// texture2ddecoder, a second BC1/BC3 decoder besides Pillow's.
pub const TEXTURE2DDECODER: Tool = Tool {
    name: "python3 with texture2ddecoder and pillow",
    probe: &["python3", "-c", "import texture2ddecoder, PIL"],
    install: "python3 -m pip install texture2ddecoder pillow",
};

/// Headless Chromium (WebGL on SwiftShader), for three.js renders.
pub const CHROMIUM: Tool = Tool {
    name: "chromium",
    probe: &["chromium", "--version"],
    install: "apt-get install chromium",
};

/// The OpenAPI contract tester.
pub const SCHEMATHESIS: Tool = Tool {
    name: "schemathesis",
    probe: &["schemathesis", "--version"],
    install: "python3 -m pip install schemathesis",
};

/// The Khronos glTF validator (npm `gltf-validator`, on NODE_PATH) under node.
pub const GLTF_VALIDATOR: Tool = Tool {
    name: "node with the npm package gltf-validator (on NODE_PATH)",
    probe: &["node", "-e", "require('gltf-validator')"],
    install: "npm install --prefix DIR gltf-validator && export NODE_PATH=DIR/node_modules",
};

pub struct Tool {
    name: &'static str,
    probe: &'static [&'static str],
    install: &'static str,
}

impl Tool {
    /// Whether the tool runs here. A test that needs it throughout is
    /// marked `#[needs(...)]`, ignored where the tool was missing when the
    /// tests were built; this check covers a tool gone since, and the
    /// checks that a test makes only where the tool is (they say so on
    /// stderr and pass). With `SEAMSTRESS_REQUIRE_TOOLS` set, a missing
    /// tool fails the test.
    pub fn available(&self) -> bool {
        let runs = Command::new(self.probe[0])
            .args(&self.probe[1..])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !runs {
            assert!(
                std::env::var_os(REQUIRE).is_none(),
                "{} is missing and {REQUIRE} is set; install it: {}",
                self.name,
                self.install
            );
            eprintln!(
                "skipped: {} is missing (install it: {})",
                self.name, self.install
            );
        }
        runs
    }
}

/// Duck with its TEXCOORD_0 scaled by `scale` and shifted: REPEAT tiles the
/// texture `scale` times along each axis.
pub fn tiled_duck(scale: f32, dir: &Path) -> PathBuf {
    let shared = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets");
    let text = std::fs::read_to_string(shared.join("Duck/Duck.gltf")).unwrap();
    let mut g: Value = serde_json::from_str(&text).unwrap();
    let uri = g["buffers"][0]["uri"].as_str().unwrap().to_string();
    let (head, data) = uri.split_once(',').unwrap();
    let mut buf = base64::engine::general_purpose::STANDARD
        .decode(data)
        .unwrap();
    let acc_index = g["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]
        .as_u64()
        .unwrap() as usize;
    let acc = g["accessors"][acc_index].clone();
    let view = &g["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let start = view["byteOffset"].as_u64().unwrap_or(0) as usize
        + acc["byteOffset"].as_u64().unwrap_or(0) as usize;
    let stride = view["byteStride"].as_u64().unwrap_or(8) as usize;
    for i in 0..acc["count"].as_u64().unwrap() as usize {
        for c in 0..2 {
            let o = start + i * stride + 4 * c;
            let v = f32::from_le_bytes(buf[o..o + 4].try_into().unwrap());
            buf[o..o + 4].copy_from_slice(&(v * scale - 1.4).to_le_bytes());
        }
    }
    let acc = g["accessors"][acc_index].as_object_mut().unwrap();
    acc.remove("min");
    acc.remove("max");
    g["buffers"][0]["uri"] = Value::String(format!(
        "{head},{}",
        base64::engine::general_purpose::STANDARD.encode(&buf)
    ));
    let path = dir.join(format!("duck_tiled_{scale}.gltf"));
    std::fs::write(&path, serde_json::to_vec(&g).unwrap()).unwrap();
    path
}

/// CRC-32 as PNG chunks use it, of a chunk's type and data.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

/// Runs `cmd`'s process under an address-space limit of `bytes`.
pub fn limit_address_space(cmd: &mut Command, bytes: u64) {
    use std::os::unix::process::CommandExt;
    // SAFETY: setrlimit is async-signal-safe and touches only the child.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// The independent evaluator (`../shared/tools/seam_eval.py`) on `model`,
/// read with `image` where given, with options of its own (`--texture`,
/// `--decoder`, `--agree`, ...); needs [`PYTHON`].
pub fn seam_eval(model: &Path, image: Option<&Path>, options: &[&str]) -> Value {
    let mut cmd = Command::new("python3");
    cmd.arg(shared_assets().join("../tools/seam_eval.py"))
        .arg(model);
    if let Some(i) = image {
        cmd.arg(i);
    }
    cmd.args(options);
    let o = cmd.output().expect("python3 runs");
    assert!(
        o.status.success(),
        "seam_eval.py failed on {}: {}",
        model.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("seam_eval prints JSON")
}

/// The Khronos validator's verdict on a model written by `process` (needs
/// [`GLTF_VALIDATOR`]).
pub fn gltf_validate(model: &Path) -> Value {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/tools/gltf_validate.js");
    let o = Command::new("node")
        .arg(script)
        .arg(model)
        .output()
        .expect("node runs");
    assert!(
        o.status.success(),
        "the validator failed on {}: {}",
        model.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("the validator prints JSON")
}

/// Runs `seamstress process MODEL --out OUT EXTRA...`, which must succeed,
/// and returns its `report.json`.
pub fn process_report(model: &Path, out: &Path, extra: &[&str]) -> Value {
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("process")
        .arg(model)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .expect("seamstress runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
}

/// The shared assets folder.
pub fn shared_assets() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets")
}

pub fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let dest = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_tree(&p, &dest);
        } else {
            std::fs::copy(&p, &dest).unwrap();
        }
    }
}

/// Every shared model but the negative ones, and one of those: a GLB whose
/// mesh needs Draco.
pub fn farm_folder(dir: &Path) -> (PathBuf, usize) {
    farm_folder_without(dir, &[])
}

/// [`farm_folder`] without the shared folders named in `skip`.
pub fn farm_folder_without(dir: &Path, skip: &[&str]) -> (PathBuf, usize) {
    let input = dir.join("in");
    for e in std::fs::read_dir(shared_assets()).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap();
        if p.is_dir() && name != "negative" && !skip.iter().any(|s| name == *s) {
            copy_tree(&p, &input.join(p.file_name().unwrap()));
        }
    }
    std::fs::copy(
        shared_assets().join("negative/BoxTextured_draco.glb"),
        input.join("draco.glb"),
    )
    .unwrap();
    let mut models = 0;
    let mut dirs = vec![input.clone()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "glb" || x == "gltf") {
                models += 1;
            }
        }
    }
    (input, models)
}

/// A report without what differs from run to run (the time each stage
/// took) or with the caller (the input's name).
pub fn report_without_timings(bytes: &[u8]) -> Value {
    let mut v: Value = serde_json::from_slice(bytes).expect("a JSON report");
    for t in v["textures"].as_array_mut().into_iter().flatten() {
        if let Some(t) = t.as_object_mut() {
            t.remove("timings_ms");
        }
    }
    if let Some(v) = v.as_object_mut() {
        v.remove("input");
    }
    v
}
