//! The page's files, embedded, each with its media type.

/// The job page; it finds the job's URL from its own path.
pub const JOB_PAGE: &str = include_str!("../../assets/view/job.html");
/// The job list.
pub const LIST_PAGE: &str = include_str!("../../assets/view/list.html");

/// An embedded file.
#[derive(Clone, Copy, Debug)]
pub struct Asset {
    pub content_type: &'static str,
    pub bytes: &'static [u8],
}

const JS: &str = "text/javascript; charset=utf-8";
const TEXT: &str = "text/plain; charset=utf-8";

macro_rules! embedded {
    ($($path:literal => $type:expr),* $(,)?) => {
        &[$(($path, Asset {
            content_type: $type,
            bytes: include_bytes!(concat!("../../assets/view/", $path)),
        })),*]
    };
}

/// Every file under `/v1/view/assets/`, by its path there.
const ASSETS: &[(&str, Asset)] = embedded! {
    "view.js" => JS,
    "list.js" => JS,
    "auth.js" => JS,
    "view.css" => "text/css; charset=utf-8",
    "three/build/three.module.js" => JS,
    "three/build/three.core.js" => JS,
    "three/examples/jsm/loaders/GLTFLoader.js" => JS,
    "three/examples/jsm/loaders/DDSLoader.js" => JS,
    "three/examples/jsm/utils/BufferGeometryUtils.js" => JS,
    "three/examples/jsm/utils/SkeletonUtils.js" => JS,
    "three/LICENSE" => TEXT,
    "three/README.md" => TEXT,
};

/// The embedded file at `path`, if there is one.
pub fn asset(path: &str) -> Option<Asset> {
    ASSETS.iter().find(|(p, _)| *p == path).map(|(_, a)| *a)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pages_import_only_embedded_files() {
        // Every module the pages load by absolute path is served.
        for page in [
            JOB_PAGE,
            LIST_PAGE,
            std::str::from_utf8(asset("view.js").unwrap().bytes).unwrap(),
        ] {
            for (i, _) in page.match_indices("/v1/view/assets/") {
                let rest = &page[i + "/v1/view/assets/".len()..];
                let end = rest.find(['"', '\'']).unwrap();
                let path = &rest[..end];
                if !path.ends_with('/') {
                    assert!(asset(path).is_some(), "{path} is not embedded");
                }
            }
        }
        assert!(asset("../Cargo.toml").is_none());
    }
}
