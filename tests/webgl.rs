//! Rewritten models as a browser shows them: headless Chromium renders them
//! with three.js (vendored in `assets/view/three/`) through WebGL on
//! SwiftShader, and `tests/webgl/render.html` reports whether the textures
//! came from the DDS files (`MSFT_texture_dds`) rather than the PNG fallback,
//! and whether the model shows its texture's colours rather than black.
//! `tests/webgl/ktx2.html` renders models with their BC7 KTX2 files as
//! three.js's `KTX2Loader` reads them, against the render from the erased
//! PNGs.

use std::fs::File;
use std::net::{TcpListener, TcpStream};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
use needs::needs;

/// How long one page may take, loading included; a render takes about 3 s.
const PAGE_TIMEOUT: Duration = Duration::from_secs(60);

/// A scratch folder, removed on drop.
struct Scratch(PathBuf);

impl Scratch {
    /// `tag` tells apart the tests of this file, which run at once.
    fn new(tag: &str) -> Scratch {
        let dir =
            std::env::temp_dir().join(format!("seamstress-webgl-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Scratch(dir)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `python3 -m http.server` on a free loopback port, killed on drop (so on
/// a failed assertion too). Module scripts and the loaders' fetches need
/// http: Chromium refuses them from file:// pages.
struct Server {
    child: Child,
    port: u16,
}

impl Server {
    fn start(root: &Path, log: &Path) -> Server {
        // The port is free when asked for but could be taken before python
        // binds it; python then exits, and another port is tried.
        for _ in 0..5 {
            let port = TcpListener::bind(("127.0.0.1", 0))
                .unwrap()
                .local_addr()
                .unwrap()
                .port();
            let child = Command::new("python3")
                .args(["-m", "http.server", &port.to_string()])
                .args(["--bind", "127.0.0.1", "--directory"])
                .arg(root)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(File::create(log).unwrap())
                .spawn()
                .expect("python3 starts");
            let mut server = Server { child, port };
            let deadline = Instant::now() + Duration::from_secs(20);
            while Instant::now() < deadline {
                if server.child.try_wait().unwrap().is_some() {
                    break;
                }
                if TcpStream::connect(("127.0.0.1", port)).is_ok() {
                    return server;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            server.stop();
        }
        panic!(
            "python3 -m http.server did not start: {}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
    }

    fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop();
    }
}

fn asset(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets")
        .join(rel)
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// Runs `seamstress process` on the asset `rel` into `out`.
fn process(rel: &str, out: &Path, extra: &[&str]) {
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("process")
        .arg(asset(rel))
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .expect("seamstress runs");
    assert!(
        o.status.success(),
        "seamstress process {rel} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// What `render.html` wrote into `<pre id="result">`, from the DOM that
/// `--dump-dom` prints.
fn result_json(dom: &str) -> Option<Value> {
    let start = dom.find("<pre id=\"result\">")? + "<pre id=\"result\">".len();
    let end = start + dom[start..].find("</pre>")?;
    // The serialised DOM escapes these in text; `&amp;` goes last so that
    // an escaped `&lt;` is not unescaped twice.
    let text = dom[start..end]
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&nbsp;", "\u{a0}")
        .replace("&amp;", "&");
    serde_json::from_str(&text).ok()
}

/// Loads `PAGE?model=MODEL` in headless Chromium and returns the page's
/// result, or panics with what Chromium said.
fn render(port: u16, page: &str, model: &str, scratch: &Path, tag: &str) -> Value {
    let url = format!("http://127.0.0.1:{port}/{page}?model={model}");
    let stdout_path = scratch.join(format!("{tag}.dom.html"));
    let stderr_path = scratch.join(format!("{tag}.chromium.log"));
    let mut child = Command::new("chromium")
        .args([
            "--headless=new",
            // Chromium's sandbox does not start as root, which CI runs as.
            "--no-sandbox",
            // Debian's launcher adds this only when /dev/shm is small, and
            // its check misreads some mount tables.
            "--disable-dev-shm-usage",
            // WebGL on the CPU: no GPU here or in CI. SwiftShader offers
            // WEBGL_compressed_texture_s3tc.
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--enable-logging=stderr",
            // Virtual time waits for the page's fetches and then runs out at
            // once: the DOM is dumped as soon as the page is idle.
            "--virtual-time-budget=30000",
        ])
        .arg(format!(
            "--user-data-dir={}",
            scratch.join(format!("{tag}.profile")).display()
        ))
        .args(["--dump-dom", &url])
        .stdin(Stdio::null())
        .stdout(File::create(&stdout_path).unwrap())
        .stderr(File::create(&stderr_path).unwrap())
        // Its own process group, so that a hung browser is killed with its
        // helper processes.
        .process_group(0)
        .spawn()
        .expect("chromium starts");
    let deadline = Instant::now() + PAGE_TIMEOUT;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            // SAFETY: signals only the process group started above.
            unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
            let _ = child.wait();
            panic!(
                "chromium took over {PAGE_TIMEOUT:?} on {url}; its log:\n{}",
                std::fs::read_to_string(&stderr_path).unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let dom = std::fs::read_to_string(&stdout_path).unwrap();
    match result_json(&dom) {
        Some(v) if status.success() => v,
        _ => panic!(
            "no result from {url} (chromium {status}); the DOM:\n{dom}\nits log:\n{}",
            std::fs::read_to_string(&stderr_path).unwrap_or_default()
        ),
    }
}

/// The folder the pages are served from, in `scratch`: the pages, and
/// three.js beside them.
fn www(scratch: &Scratch) -> PathBuf {
    let root = scratch.0.join("www");
    copy_dir(
        &PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/webgl"),
        &root,
    );
    // three.js lives with the view page, which serves it.
    copy_dir(
        &PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/view/three"),
        &root.join("three"),
    );
    root
}

struct Case {
    tag: &'static str,
    asset: &'static str,
    extra: &'static [&'static str],
    /// At least this share of the canvas shows the model: the camera found
    /// it. Half of what was measured.
    min_covered: f64,
}

const CASES: &[Case] = &[
    Case {
        tag: "box",
        asset: "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
        extra: &["--no-mips"],
        min_covered: 0.25,
    },
    Case {
        tag: "fox",
        asset: "Fox/Fox.gltf",
        extra: &[],
        min_covered: 0.05,
    },
    // DDSLoader's path for a mip chain (the default) whose levels are not
    // all multiples of 4 (212, 106, 53, ...).
    Case {
        tag: "box_mips",
        asset: "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
        extra: &[],
        min_covered: 0.25,
    },
    // The DDS embedded in the GLB's binary chunk, reached through a
    // bufferView instead of a file.
    Case {
        tag: "box_glb",
        asset: "BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb",
        extra: &[],
        min_covered: 0.25,
    },
];

/// Of the model's pixels, the share brighter than black. Every case
/// measured 1.0 (the fox 0.998: its dark paws); with the DDS blocks zeroed
/// (a black texture) it is 0, as the scene has ambient light only.
const MIN_NONBLACK: f64 = 0.5;

#[needs(chromium, python)]
#[test]
fn dds_textures_render_in_webgl() {
    if !common::CHROMIUM.available() || !common::PYTHON.available() {
        return;
    }
    let scratch = Scratch::new("dds");
    let root = www(&scratch);
    for case in CASES {
        process(case.asset, &root.join(case.tag), case.extra);
    }
    let server = Server::start(&root, &scratch.0.join("http.log"));

    let mut failures = Vec::new();
    for case in CASES {
        let name = Path::new(case.asset).file_name().unwrap().to_str().unwrap();
        let model = format!("{}/{name}", case.tag);
        let started = Instant::now();
        let r = render(server.port, "render.html", &model, &scratch.0, case.tag);
        eprintln!("{model}: {r} ({:.1?})", started.elapsed());

        let mut fail = |what: String| failures.push(format!("{model}: {what}; result {r}"));
        if r["s3tc"] != Value::Bool(true) {
            fail("WebGL lacks WEBGL_compressed_texture_s3tc".into());
        }
        let errors = r["errors"].as_array().map_or(0, Vec::len);
        if errors != 0 {
            fail(format!("{errors} errors on the page"));
        }
        let maps = r["maps"].as_u64().unwrap_or(0);
        let compressed = r["compressed_textures"].as_u64().unwrap_or(0);
        // A texture from the PNG fallback is a plain Texture, not a
        // CompressedTexture.
        if maps == 0 || compressed != maps {
            fail(format!(
                "{compressed} of {maps} base colour maps came from the DDS"
            ));
        }
        let covered = r["covered"].as_f64().unwrap_or(0.0);
        if covered < case.min_covered {
            fail(format!(
                "the model covers {covered:.3} of the canvas, under {}",
                case.min_covered
            ));
        }
        let nonblack = r["nonblack"].as_f64().unwrap_or(0.0);
        if nonblack < MIN_NONBLACK {
            fail(format!(
                "{nonblack:.3} of its pixels are not black, under {MIN_NONBLACK}"
            ));
        }
    }
    drop(server);
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

struct Ktx2Case {
    tag: &'static str,
    asset: &'static str,
    extra: &'static [&'static str],
    /// The KTX2 header's `supercompressionScheme`: 0 none, 2 Zstandard.
    supercompression: u32,
    /// As in `Case`: half of what was measured.
    min_covered: f64,
}

const KTX2_CASES: &[Ktx2Case] = &[
    // Every mip level, the default; 212, 106, 53, ...: levels past the
    // second are not multiples of 4.
    Ktx2Case {
        tag: "box_ktx2",
        asset: "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
        extra: &["--format", "bc7", "--container", "ktx2"],
        supercompression: 0,
        min_covered: 0.25,
    },
    // Zstandard, which KTX2Loader inflates with the WebAssembly decoder
    // embedded in `zstddec.module.js`; the image is a data URI in the glTF.
    Ktx2Case {
        tag: "duck_ktx2",
        asset: "Duck/Duck.gltf",
        extra: &["--format", "bc7", "--container", "ktx2", "--zstd", "19"],
        supercompression: 2,
        min_covered: 0.12,
    },
];

/// `VK_FORMAT_BC7_SRGB_BLOCK`: a base colour texture's format in the KTX2.
const VK_FORMAT_BC7_SRGB_BLOCK: u32 = 146;

/// With level 0 alone on both, the render from the KTX2 against the one
/// from the erased PNG: the mean absolute difference per channel, in 0-255
/// levels, and the share of the model's pixels off by more than 16 in some
/// channel. Measured 0.06 and 0 on both models (BC7's own error).
const MAX_LEVEL0_DIFF: f64 = 0.5;
const MAX_LEVEL0_FAR: f64 = 0.01;
/// The same with the mip chains, the KTX2's (each level filtered, erased
/// and encoded on its own) against the one the GPU makes from the PNG,
/// which filters odd sizes otherwise. Measured 2.3 and 0.074 (the box's
/// lettering), 0.5 and 0.006 (the duck). With the KTX2 upside down they
/// are 48 and 0.60, 18 and 0.18.
const MAX_MIPMAPPED_DIFF: f64 = 5.0;
const MAX_MIPMAPPED_FAR: f64 = 0.15;
/// The model without its texture must differ from the PNG render by this
/// much for the comparisons to tell anything; measured 75 and 99.
const MIN_UNTEXTURED_DIFF: f64 = 20.0;

/// A mean colour from the page, as `(r, g, b)` to one decimal.
fn rgb(v: &Value) -> String {
    let c: Vec<String> = v
        .as_array()
        .map(|a| {
            a.iter()
                .map(|c| format!("{:.1}", c.as_f64().unwrap_or(f64::NAN)))
                .collect()
        })
        .unwrap_or_default();
    format!("({})", c.join(", "))
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap())
}

/// BC7 KTX2 files as three.js's `KTX2Loader` shows them: `ktx2.html` swaps
/// each base colour map of the model for the KTX2 file the report names
/// for its image, and the render must match the one from the erased PNGs.
#[needs(chromium, python)]
#[test]
fn bc7_ktx2_textures_render_through_ktx2loader() {
    if !common::CHROMIUM.available() || !common::PYTHON.available() {
        return;
    }
    let scratch = Scratch::new("ktx2");
    let root = www(&scratch);
    for case in KTX2_CASES {
        process(case.asset, &root.join(case.tag), case.extra);
    }
    let server = Server::start(&root, &scratch.0.join("http.log"));

    let mut failures = Vec::new();
    for case in KTX2_CASES {
        let dir = root.join(case.tag);
        let name = Path::new(case.asset).file_name().unwrap().to_str().unwrap();
        let model = format!("{}/{name}", case.tag);

        // The files as written: BC7 sRGB, supercompressed as asked; their
        // level counts, to hold the page's textures to.
        let report: Value =
            serde_json::from_slice(&std::fs::read(dir.join("report.json")).unwrap()).unwrap();
        let mut levels = std::collections::HashMap::new();
        for t in report["textures"].as_array().unwrap() {
            let file = t["files"]["ktx2"]
                .as_str()
                .expect("files.ktx2 in the report");
            assert_eq!(t["files"]["dds"], Value::Null, "{model}: {t}");
            let bytes = std::fs::read(dir.join(file)).unwrap();
            assert_eq!(
                u32_at(&bytes, 12),
                VK_FORMAT_BC7_SRGB_BLOCK,
                "{model}: {file}"
            );
            assert_eq!(u32_at(&bytes, 44), case.supercompression, "{model}: {file}");
            levels.insert(file.to_string(), u64::from(u32_at(&bytes, 40)));
        }

        let started = Instant::now();
        let r = render(server.port, "ktx2.html", &model, &scratch.0, case.tag);
        let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
        let vs = &r["vs_png"];
        eprintln!(
            "{model}: EXT_texture_compression_bptc {}, WEBGL_compressed_texture_s3tc {}, \
             WEBGL_compressed_texture_s3tc_srgb {}; mean colour PNG {}, KTX2 {}, \
             untextured {}; against the PNG render: KTX2 level 0 {:.2} ({:.3} far), \
             KTX2 mipmapped {:.2} ({:.3} far), untextured {:.1} ({:.3} far) ({:.1?})",
            r["bptc"],
            r["s3tc"],
            r["s3tc_srgb"],
            rgb(&r["mean"]["png"]),
            rgb(&r["mean"]["ktx2"]),
            rgb(&r["mean"]["untextured"]),
            f(&vs["ktx2_level0"]["diff"]),
            f(&vs["ktx2_level0"]["far"]),
            f(&vs["ktx2"]["diff"]),
            f(&vs["ktx2"]["far"]),
            f(&vs["untextured"]["diff"]),
            f(&vs["untextured"]["far"]),
            started.elapsed()
        );
        eprintln!("{model}: {r}");

        let mut fail = |what: String| failures.push(format!("{model}: {what}; result {r}"));
        // Without it WebGL has no BC7 format to upload the KTX2 files as.
        if r["bptc"] != Value::Bool(true) {
            fail("WebGL lacks EXT_texture_compression_bptc".into());
        }
        let errors = r["errors"].as_array().map_or(0, Vec::len);
        if errors != 0 {
            fail(format!("{errors} errors on the page"));
        }
        let maps = r["maps"].as_u64().unwrap_or(0);
        let ktx2_maps = r["ktx2_maps"].as_array().cloned().unwrap_or_default();
        if maps == 0 || ktx2_maps.len() as u64 != maps {
            fail(format!(
                "{} of {maps} base colour maps came from KTX2 files",
                ktx2_maps.len()
            ));
        }
        for t in &ktx2_maps {
            let file = t["file"].as_str().unwrap_or_default();
            if t["compressed"] != Value::Bool(true)
                || t["format"] != "RGBA_BPTC"
                || t["color_space"] != "srgb"
            {
                fail(format!(
                    "{file} is not an sRGB BC7 CompressedTexture in three.js: {t}"
                ));
            }
            if t["levels"].as_u64() != levels.get(file).copied() {
                fail(format!(
                    "{file} has {} levels in three.js, {:?} in the file",
                    t["levels"],
                    levels.get(file)
                ));
            }
        }
        let covered = f(&r["covered"]);
        if covered.is_nan() || covered < case.min_covered {
            fail(format!(
                "the model covers {covered:.3} of the canvas, under {}",
                case.min_covered
            ));
        }
        let nonblack = f(&r["nonblack"]);
        if nonblack.is_nan() || nonblack < MIN_NONBLACK {
            fail(format!(
                "{nonblack:.3} of its pixels are not black, under {MIN_NONBLACK}"
            ));
        }
        for (key, max_diff, max_far) in [
            ("ktx2_level0", MAX_LEVEL0_DIFF, MAX_LEVEL0_FAR),
            ("ktx2", MAX_MIPMAPPED_DIFF, MAX_MIPMAPPED_FAR),
        ] {
            let (diff, far) = (f(&vs[key]["diff"]), f(&vs[key]["far"]));
            // NaN (no figure) fails too.
            if diff.is_nan() || far.is_nan() || diff > max_diff || far > max_far {
                fail(format!(
                    "the {key} render differs from the PNG one by {diff:.2} levels \
                     ({far:.3} of the pixels by over 16), over {max_diff} ({max_far})"
                ));
            }
        }
        let untextured = f(&vs["untextured"]["diff"]);
        if untextured.is_nan() || untextured < MIN_UNTEXTURED_DIFF {
            fail(format!(
                "without its texture the model differs by {untextured:.1} levels only, \
                 under {MIN_UNTEXTURED_DIFF}: the comparison tells nothing"
            ));
        }
    }
    drop(server);
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
