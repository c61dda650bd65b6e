//! Counts as a person reads them: "1 model", "2 models", "0 textures".

/// `n` and the noun, plural unless `n` is 1. Every noun the command line
/// counts takes an `s`.
pub fn count(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{n} {noun}s")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_is_singular_and_zero_is_not() {
        assert_eq!(count(1, "model"), "1 model");
        assert_eq!(count(0, "model"), "0 models");
        assert_eq!(count(12, "texture"), "12 textures");
    }
}
