//! What the integration tests share: the outside tools some of them compare
//! against, and a running server. (Each test file uses some of it.)
#![allow(dead_code)]

pub mod server;

use std::process::{Command, Stdio};

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

/// The OpenAPI contract tester.
pub const SCHEMATHESIS: Tool = Tool {
    name: "schemathesis",
    probe: &["schemathesis", "--version"],
    install: "python3 -m pip install schemathesis",
};

pub struct Tool {
    name: &'static str,
    probe: &'static [&'static str],
    install: &'static str,
}

impl Tool {
    /// Whether the tool runs here. Without it a test says so on stderr and
    /// passes, so that `cargo test` works on a machine with only Rust; with
    /// `SEAMSTRESS_REQUIRE_TOOLS` set, a missing tool fails the test.
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
