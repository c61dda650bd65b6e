//! What a file that is not glTF is, told from its first bytes.
//!
//! A newcomer who gives an OBJ or an FBX file should learn that, not that
//! its "glTF JSON" is invalid at line 1. Only bytes that cannot be glTF
//! (neither the GLB magic nor a JSON object) are looked at, so a model the
//! loader would take is never refused here.

use std::fmt;

/// A format recognised by its first bytes that is not a glTF model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Foreign {
    Obj,
    Fbx,
    Collada,
    Ply,
    Stl,
    Png,
    Jpeg,
    Zip,
    /// Nothing recognised: neither GLB nor JSON.
    Unknown,
}

/// How many bytes are looked at: enough for a header and the first lines.
const WINDOW: usize = 4096;

/// OBJ statements a file's first lines are made of.
const OBJ_KEYWORDS: &[&str] = &[
    "v", "vt", "vn", "vp", "f", "l", "p", "o", "g", "s", "mtllib", "usemtl",
];

impl Foreign {
    /// `None` when `bytes` may be glTF: they start with the GLB magic or,
    /// past a byte-order mark and white space, with a JSON object.
    pub fn sniff(bytes: &[u8]) -> Option<Foreign> {
        let text = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        let text = &text[text.iter().take_while(|b| b.is_ascii_whitespace()).count()..];
        if bytes.starts_with(b"glTF") || text.starts_with(b"{") {
            return None;
        }
        let head = &bytes[..bytes.len().min(WINDOW)];
        let found = if head.starts_with(b"Kaydara FBX Binary") || head.starts_with(b"; FBX") {
            Foreign::Fbx
        } else if head.starts_with(b"\x89PNG\r\n\x1a\n") {
            Foreign::Png
        } else if head.starts_with(b"\xFF\xD8\xFF") {
            Foreign::Jpeg
        } else if head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06") {
            Foreign::Zip
        } else if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
            Foreign::Ply
        } else if is_word(text, b"solid") {
            Foreign::Stl
        } else if text.starts_with(b"<?xml") && contains(head, b"<COLLADA") {
            Foreign::Collada
        } else if is_obj(head, bytes.len() <= WINDOW) {
            Foreign::Obj
        } else {
            Foreign::Unknown
        };
        Some(found)
    }

    fn what(self) -> &'static str {
        match self {
            Foreign::Obj => "a Wavefront OBJ file",
            Foreign::Fbx => "an FBX file",
            Foreign::Collada => "a COLLADA file",
            Foreign::Ply => "a PLY file",
            Foreign::Stl => "an STL file",
            Foreign::Png => "a PNG image",
            Foreign::Jpeg => "a JPEG image",
            Foreign::Zip => "a zip archive",
            Foreign::Unknown => "neither GLB (which starts with \"glTF\") nor glTF JSON",
        }
    }
}

impl fmt::Display for Foreign {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let what = self.what();
        match self {
            Foreign::Png | Foreign::Jpeg => write!(
                f,
                "{what}, not a model; give the .gltf or .glb that uses it"
            ),
            Foreign::Zip => write!(
                f,
                "{what}, not glTF; unpack it and give the .gltf or .glb inside"
            ),
            Foreign::Unknown => write!(f, "not a glTF model: {what}"),
            _ => write!(
                f,
                "{what}, not glTF; convert it to glTF (.gltf or .glb) first"
            ),
        }
    }
}

/// `text` starts with `word` followed by white space or its end.
fn is_word(text: &[u8], word: &[u8]) -> bool {
    text.strip_prefix(word)
        .is_some_and(|rest| rest.first().is_none_or(u8::is_ascii_whitespace))
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

/// Every complete line of `head` is blank, a comment or an OBJ statement,
/// and one at least is a statement. `whole` says `head` is the whole file,
/// so that its last line is complete too.
fn is_obj(head: &[u8], whole: bool) -> bool {
    let Ok(text) = std::str::from_utf8(head) else {
        return false;
    };
    let complete = if whole {
        text
    } else {
        text.rfind('\n').map_or("", |end| &text[..end])
    };
    let mut statements = 0;
    for line in complete.lines().map(str::trim).filter(|l| !l.is_empty()) {
        if line.starts_with('#') {
            continue;
        }
        let keyword = line.split_whitespace().next().unwrap_or("");
        if !OBJ_KEYWORDS.contains(&keyword) {
            return false;
        }
        statements += 1;
    }
    statements > 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn foreign_formats_are_named() {
        let obj = b"# Blender OBJ\nmtllib cube.mtl\no Cube\nv 1 1 -1\nvt 0 0\nf 1/1 2/2 3/3\n";
        assert_eq!(Foreign::sniff(obj), Some(Foreign::Obj));
        assert_eq!(
            Foreign::sniff(b"Kaydara FBX Binary  \0\x1a\0"),
            Some(Foreign::Fbx)
        );
        assert_eq!(
            Foreign::sniff(b"; FBX 7.4.0 project file"),
            Some(Foreign::Fbx)
        );
        assert_eq!(Foreign::sniff(b"\x89PNG\r\n\x1a\n...."), Some(Foreign::Png));
        assert_eq!(Foreign::sniff(b"\xFF\xD8\xFF\xE0"), Some(Foreign::Jpeg));
        assert_eq!(Foreign::sniff(b"PK\x03\x04rest"), Some(Foreign::Zip));
        assert_eq!(
            Foreign::sniff(b"ply\nformat ascii 1.0\n"),
            Some(Foreign::Ply)
        );
        assert_eq!(Foreign::sniff(b"solid cube\n facet"), Some(Foreign::Stl));
        let dae = b"<?xml version=\"1.0\"?>\n<COLLADA xmlns=\"x\">";
        assert_eq!(Foreign::sniff(dae), Some(Foreign::Collada));
        assert_eq!(Foreign::sniff(b"hello there"), Some(Foreign::Unknown));
        assert_eq!(Foreign::sniff(b""), Some(Foreign::Unknown));
        let message = Foreign::Obj.to_string();
        assert!(
            message.starts_with("a Wavefront OBJ file, not glTF"),
            "{message}"
        );
    }

    #[test]
    fn what_may_be_gltf_is_left_to_the_loader() {
        assert_eq!(Foreign::sniff(b"glTF\x02\0\0\0"), None);
        assert_eq!(Foreign::sniff(b"{\"asset\":{}}"), None);
        assert_eq!(Foreign::sniff(b"\xEF\xBB\xBF \n {}"), None);
        // A text that merely starts like OBJ is not taken for one.
        assert_eq!(
            Foreign::sniff(b"v 1 2 3\nsomething else\n"),
            Some(Foreign::Unknown)
        );
        assert_eq!(
            Foreign::sniff(b"# only a comment\n"),
            Some(Foreign::Unknown)
        );
    }

    #[test]
    fn a_line_cut_by_the_window_does_not_count() {
        let mut obj = b"o big\n".to_vec();
        while obj.len() < WINDOW + 100 {
            obj.extend_from_slice(b"v 0.123456 0.654321 0.111111\n");
        }
        assert_eq!(Foreign::sniff(&obj), Some(Foreign::Obj));
    }
}
