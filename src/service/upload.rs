//! An upload as one blob: the model file and the files its URIs name.

use std::collections::BTreeMap;

use sha2::{Digest, Sha256};

use crate::model::sniff::Foreign;
use crate::pipeline::ProcessOptions;

/// A `.glb` or `.gltf` with the files beside it, keyed by the relative
/// paths its URIs use.
#[derive(Clone, Debug, PartialEq)]
pub struct Bundle {
    pub main_name: String,
    pub main: Vec<u8>,
    pub files: BTreeMap<String, Vec<u8>>,
}

const MAGIC: &[u8] = b"seamstress-bundle-1\n";

impl Bundle {
    pub fn is_glb(&self) -> bool {
        self.main.starts_with(b"glTF")
    }

    pub fn total_bytes(&self) -> u64 {
        (self.main.len() + self.files.values().map(Vec::len).sum::<usize>()) as u64
    }

    /// Length-prefixed names and contents, model first then files in name
    /// order: equal uploads encode to equal bytes, whatever their framing.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.total_bytes() as usize + 256);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(1 + self.files.len() as u64).to_le_bytes());
        let mut entry = |name: &str, data: &[u8]| {
            out.extend_from_slice(&(name.len() as u64).to_le_bytes());
            out.extend_from_slice(name.as_bytes());
            out.extend_from_slice(&(data.len() as u64).to_le_bytes());
            out.extend_from_slice(data);
        };
        entry(&self.main_name, &self.main);
        for (name, data) in &self.files {
            entry(name, data);
        }
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Bundle, String> {
        let rest = bytes.strip_prefix(MAGIC).ok_or("not an upload bundle")?;
        let mut cur = Cursor(rest);
        let count = cur.len()?;
        let mut entries = Vec::new();
        for _ in 0..count {
            let name_len = cur.len()?;
            let name = String::from_utf8(cur.take(name_len)?.to_vec())
                .map_err(|_| "file name is not UTF-8".to_string())?;
            let data_len = cur.len()?;
            entries.push((name, cur.take(data_len)?.to_vec()));
        }
        let mut entries = entries.into_iter();
        let (main_name, main) = entries.next().ok_or("empty upload bundle")?;
        Ok(Bundle {
            main_name,
            main,
            files: entries.collect(),
        })
    }

    /// The result-cache key: equal owner, options and upload give equal
    /// outputs, so a second job can reuse the first one's files.
    pub fn key(&self, owner: &str, options: &ProcessOptions) -> String {
        let mut h = Sha256::new();
        h.update(b"seamstress-job-1\0");
        h.update((owner.len() as u64).to_le_bytes());
        h.update(owner.as_bytes());
        let opts = serde_json::to_vec(options).unwrap_or_default();
        h.update((opts.len() as u64).to_le_bytes());
        h.update(&opts);
        h.update(self.encode());
        super::config::hex(&h.finalize())
    }
}

struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        if self.0.len() < n {
            return Err("truncated upload bundle".into());
        }
        let (head, tail) = self.0.split_at(n);
        self.0 = tail;
        Ok(head)
    }

    fn len(&mut self) -> Result<usize, String> {
        let mut a = [0u8; 8];
        a.copy_from_slice(self.take(8)?);
        usize::try_from(u64::from_le_bytes(a)).map_err(|_| "oversized entry".to_string())
    }
}

/// Checks a raw upload's bytes against its declared media type: a `.gltf`
/// sent as `model/gltf-binary` would otherwise be refused for what a GLB
/// parser makes of it (a missing `.bin`, say), not for its label.
/// `application/octet-stream` declares neither and takes both.
pub fn check_media_type(media: &str, body: &[u8]) -> Result<(), String> {
    let glb = body.starts_with(b"glTF");
    let json = !glb && Foreign::sniff(body).is_none();
    match media {
        "model/gltf-binary" if json => {
            Err("the body is glTF JSON, not GLB: send it as model/gltf+json".into())
        }
        "model/gltf+json" if glb => {
            Err("the body is GLB, not glTF JSON: send it as model/gltf-binary".into())
        }
        _ => Ok(()),
    }
}

/// A file name from a client, as a relative `/`-separated path that cannot
/// leave the upload: no empty, `.` or `..` parts, no backslashes, colons or
/// control characters, at most 255 bytes.
pub fn safe_name(name: &str) -> Option<String> {
    let name = name.trim();
    if name.is_empty() || name.len() > 255 || name.starts_with('/') {
        return None;
    }
    let ok = name.split('/').all(|part| {
        !part.is_empty()
            && part != "."
            && part != ".."
            && !part
                .chars()
                .any(|c| c.is_control() || matches!(c, '\\' | ':'))
    });
    ok.then(|| name.to_string())
}

/// The last component of a safe name.
pub fn base_name(name: &str) -> &str {
    name.rsplit('/').next().unwrap_or(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bundles_round_trip() {
        let b = Bundle {
            main_name: "m.gltf".into(),
            main: b"{}".to_vec(),
            files: BTreeMap::from([
                ("a.bin".to_string(), vec![1, 2, 3]),
                ("tex/b.png".to_string(), vec![]),
            ]),
        };
        let bytes = b.encode();
        assert_eq!(Bundle::decode(&bytes).unwrap(), b);
        assert!(Bundle::decode(&bytes[..bytes.len() - 1]).is_err());
        assert!(Bundle::decode(b"nonsense").is_err());
    }

    #[test]
    fn media_types_must_fit_the_bytes() {
        let json = b" {\"asset\":{\"version\":\"2.0\"}}";
        let glb = b"glTF\x02\0\0\0";
        let err = check_media_type("model/gltf-binary", json).unwrap_err();
        assert!(err.contains("glTF JSON, not GLB"), "{err}");
        let err = check_media_type("model/gltf+json", glb).unwrap_err();
        assert!(err.contains("GLB, not glTF JSON"), "{err}");
        assert!(check_media_type("model/gltf-binary", glb).is_ok());
        assert!(check_media_type("model/gltf+json", json).is_ok());
        assert!(check_media_type("application/octet-stream", json).is_ok());
        // Neither: the loader names what it is.
        assert!(check_media_type("model/gltf-binary", b"v 0 0 0\nf 1 1 1\n").is_ok());
    }

    #[test]
    fn names_stay_inside() {
        assert_eq!(safe_name("a/b.png").as_deref(), Some("a/b.png"));
        for bad in ["", "/etc/passwd", "../x", "a/../b", "a//b", "c:\\x", "a\nb"] {
            assert!(safe_name(bad).is_none(), "{bad:?}");
        }
    }
}
