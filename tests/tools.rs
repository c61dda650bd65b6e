//! Which of the outside tools that some tests need are here: as found when
//! the tests were built (which decided what `#[needs]` ignores) and now.
//! Under `SEAMSTRESS_REQUIRE_TOOLS` a missing one fails this test, named
//! with how to install it, besides the tests that need it.

#[path = "needs/src/probe.rs"]
mod probe;

#[test]
fn outside_tools_found_and_missing() {
    let required = std::env::var_os("SEAMSTRESS_REQUIRE_TOOLS").is_some();
    let at_build = needs::found_at_build!();
    let now = probe::found();
    let mut missing = Vec::new();
    let mut stale = false;
    for ((tool, (key, built)), here) in probe::TOOLS.iter().zip(at_build).zip(now) {
        assert_eq!(tool.key, key);
        eprintln!(
            "{:<16} {}",
            tool.key,
            match (built, here) {
                (true, true) => "found".to_string(),
                (false, false) => format!("missing ({}): {}", tool.what, tool.install),
                (true, false) => format!("gone since the build ({}): {}", tool.what, tool.install),
                (false, true) => "found, but missing when the tests were built".to_string(),
            }
        );
        stale |= here && !built && !required;
        if !here {
            missing.push(format!("{} ({}): {}", tool.key, tool.what, tool.install));
        }
    }
    if stale {
        eprintln!(
            "the tests that need a tool installed since they were built stay ignored \
             until it is looked for again: touch tests/needs/build.rs"
        );
    }
    assert!(
        !required || missing.is_empty(),
        "SEAMSTRESS_REQUIRE_TOOLS is set and these are missing:\n{}",
        missing.join("\n")
    );
}
