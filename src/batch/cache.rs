//! Whether a model's outputs are still those of its inputs.
//!
//! After a model's outputs are written, its output folder gets a stamp:
//! a SHA-256 over the engine's version, the job's settings, the model's
//! bytes and those of every file it refers to, with the outputs' names and
//! sizes. A later run with the same key and the outputs still in place
//! skips the model: an unchanged folder rebuilds in the time it takes to
//! read and hash its files.

use std::path::Path;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::model::rewrite::referenced_files;
use crate::model::Resolver;
use crate::pipeline::ProcessOptions;
use crate::service::config::hex;

/// The stamp's file name in a model's output folder.
pub const STAMP_NAME: &str = "seamstress.stamp.json";

/// What a model's outputs were made from, and what they are.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Stamp {
    pub key: String,
    /// Output file names (relative to the folder) and sizes.
    pub files: Vec<(String, u64)>,
}

/// The cache key of a model under `options` (the limits a job runs under
/// decide whether it runs, not what it writes: they are not part of it).
/// `seamstress submit` sends it as the job's `Idempotency-Key`.
pub fn key(main: &[u8], files: &dyn Resolver, options: &ProcessOptions) -> String {
    let settings = serde_json::Value::Object(options.to_json()).to_string();
    let mut h = Sha256::new();
    let mut part = |bytes: &[u8]| {
        h.update((bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    part(env!("CARGO_PKG_VERSION").as_bytes());
    part(settings.as_bytes());
    part(main);
    // A file that cannot be read now fails the job later; it still keys.
    for uri in referenced_files(main).unwrap_or_default() {
        part(uri.as_bytes());
        match files.read(&uri) {
            Ok(bytes) => part(&bytes),
            Err(_) => part(b""),
        }
    }
    hex(&h.finalize())
}

impl Stamp {
    /// The stamp in `dir`, if it is there and whole.
    pub fn read(dir: &Path) -> Option<Stamp> {
        serde_json::from_slice(&std::fs::read(dir.join(STAMP_NAME)).ok()?).ok()
    }

    /// Whether `dir` holds the outputs of `key`: the stamp says so and
    /// every file it lists is there at its size.
    pub fn fresh(dir: &Path, key: &str) -> bool {
        Stamp::read(dir).is_some_and(|s| {
            s.key == key
                && s.files.iter().all(|(name, size)| {
                    std::fs::metadata(dir.join(name)).is_ok_and(|m| m.len() == *size)
                })
        })
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        serde_json::to_vec_pretty(self).unwrap_or_default()
    }
}
