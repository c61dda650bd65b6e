//! Looks for the outside tools once, when the tests are built, so that
//! `#[needs]` can mark a test ignored (and `cargo test` count and name it)
//! rather than let it pass without running.
//!
//! Cargo runs this again only when the environment the answers depend on
//! changes; a tool installed without such a change is found after
//! `touch tests/needs/build.rs` (`tests/tools.rs` says so when it sees one).

#[path = "src/probe.rs"]
mod probe;

/// Set (as `.ci/run` does, after installing the tools) to make a missing
/// outside tool fail the tests that need it: nothing is ignored then.
const REQUIRE: &str = "SEAMSTRESS_REQUIRE_TOOLS";

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=src/probe.rs");
    println!("cargo::rerun-if-env-changed={REQUIRE}");
    for var in probe::ENV {
        println!("cargo::rerun-if-env-changed={var}");
    }
    let required = std::env::var_os(REQUIRE).is_some();
    let found = if required {
        vec![true; probe::TOOLS.len()]
    } else {
        probe::found()
    };
    let out = std::path::PathBuf::from(std::env::var_os("OUT_DIR").unwrap()).join("found.rs");
    std::fs::write(
        out,
        format!("const FOUND: [bool; {}] = {found:?};\n", found.len()),
    )
    .unwrap();
}
