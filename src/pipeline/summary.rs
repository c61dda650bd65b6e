//! One model's report as the few lines a person reads after `seamstress
//! process`: what was closed, by how much, and what was written. The
//! report itself stays the record (`report.json`, or `--json`).

use std::fmt::Write as _;
use std::path::Path;

use serde::Deserialize;

use crate::plural::count;

/// The report fields the summary reads; the rest are ignored.
#[derive(Deserialize)]
struct ReportView {
    input: String,
    textures: Vec<TextureView>,
    skipped: Vec<serde::de::IgnoredAny>,
    warnings: Vec<String>,
}

#[derive(Deserialize)]
struct TextureView {
    name: String,
    width: usize,
    height: usize,
    seam_edges: usize,
    seams: SeamsView,
    input: MetricsView,
    erased: MetricsView,
    bc1: Option<MetricsView>,
    bc1_seam_aware: Option<MetricsView>,
    #[serde(default)]
    bc7: Option<MetricsView>,
    #[serde(default)]
    bc7_seam_aware: Option<MetricsView>,
    #[serde(default)]
    files: FilesView,
}

#[derive(Default, Deserialize)]
struct FilesView {
    #[serde(default)]
    ktx2: Option<String>,
}

#[derive(Deserialize)]
struct SeamsView {
    closed: ShareView,
    left: ShareView,
}

#[derive(Deserialize)]
struct ShareView {
    edges: usize,
    length_share: f64,
}

#[derive(Deserialize)]
struct MetricsView {
    seam_rms_closed: Option<f64>,
}

/// How many file names the last line lists before it only counts them.
const LISTED_FILES: usize = 6;

/// The summary of a model's `report` (its JSON bytes), whose `files` were
/// written into `out`: a line for the model, one per texture, one for the
/// files.
pub fn model_summary(
    report: &[u8],
    out: &Path,
    files: &[String],
) -> Result<String, serde_json::Error> {
    let r: ReportView = serde_json::from_slice(report)?;
    let mut s = format!("{}: {}", r.input, count(r.textures.len(), "texture"));
    if !r.skipped.is_empty() {
        let _ = write!(s, ", {} skipped", r.skipped.len());
    }
    if !r.warnings.is_empty() {
        let _ = write!(
            s,
            ", {} (in report.json)",
            count(r.warnings.len(), "warning")
        );
    }
    s.push('\n');
    for t in &r.textures {
        let _ = writeln!(s, "  {}", texture_line(t));
    }
    let mut names = files.iter().take(LISTED_FILES).cloned().collect::<Vec<_>>();
    if files.len() > LISTED_FILES {
        names.push(format!("and {} more", files.len() - LISTED_FILES));
    }
    let _ = writeln!(
        s,
        "wrote {} to {}: {}",
        count(files.len(), "file"),
        out.display(),
        names.join(", ")
    );
    Ok(s)
}

/// `243 of 270 seams closed (93% of the seam length), 27 left as painted
/// (7%); seam_rms over the closed seams 7.53 → 0.91 in the DDS`.
fn texture_line(t: &TextureView) -> String {
    let mut s = format!("{} {}×{}: ", t.name, t.width, t.height);
    let (closed, left) = (&t.seams.closed, &t.seams.left);
    if t.seam_edges == 0 {
        s.push_str("no seams");
        return s;
    }
    let seams = count(t.seam_edges, "seam");
    if left.edges == 0 {
        let _ = write!(s, "all {seams} closed");
    } else if closed.edges == 0 {
        let _ = write!(s, "{seams}, all left as painted");
        return s;
    } else {
        let _ = write!(
            s,
            "{} of {seams} closed ({} of the seam length), {} left as painted ({})",
            closed.edges,
            percent(closed.length_share),
            left.edges,
            percent(left.length_share)
        );
    }
    // What a renderer samples: the DDS or KTX2 file when there is one,
    // else the PNG.
    let file = if t.files.ktx2.is_some() {
        "in the KTX2"
    } else {
        "in the DDS"
    };
    let encoded = [&t.bc1_seam_aware, &t.bc1, &t.bc7_seam_aware, &t.bc7]
        .into_iter()
        .find_map(Option::as_ref);
    let (after, held) = match encoded {
        Some(m) => (m, file),
        None => (&t.erased, "in the erased PNG"),
    };
    if let (Some(before), Some(after)) = (t.input.seam_rms_closed, after.seam_rms_closed) {
        let _ = write!(
            s,
            "; seam_rms over the closed seams {before:.2} → {after:.2} {held}"
        );
    }
    s
}

/// A share as a whole percentage; a small share does not read as none.
fn percent(share: f64) -> String {
    let p = share * 100.0;
    if p > 0.0 && p < 0.5 {
        "<1%".into()
    } else {
        format!("{p:.0}%")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(closed: usize, left: usize, after: &str) -> String {
        format!(
            r#"{{"name":"t","width":8,"height":4,"seam_edges":{},
                "seams":{{"closed":{{"edges":{closed},"length_share":0.9257}},
                          "left":{{"edges":{left},"length_share":0.0743}}}},
                "input":{{"seam_rms_closed":7.525}},"erased":{{"seam_rms_closed":0.2}},
                "bc1":null,"bc1_seam_aware":{after}}}"#,
            closed + left
        )
    }

    fn summary(textures: &[String], skipped: usize, warnings: usize) -> String {
        let report = format!(
            r#"{{"input":"m.glb","textures":[{}],"skipped":[{}],"warnings":[{}]}}"#,
            textures.join(","),
            vec!["{}"; skipped].join(","),
            vec!["\"w\""; warnings].join(",")
        );
        let files = ["m.glb".to_string(), "report.json".to_string()];
        model_summary(report.as_bytes(), Path::new("out"), &files).unwrap()
    }

    #[test]
    fn closed_seams_before_and_after() {
        let s = summary(&[texture(243, 27, r#"{"seam_rms_closed":0.9071}"#)], 0, 0);
        assert_eq!(
            s,
            "m.glb: 1 texture\n  t 8×4: 243 of 270 seams closed (93% of the seam length), \
             27 left as painted (7%); seam_rms over the closed seams 7.53 → 0.91 in the DDS\n\
             wrote 2 files to out: m.glb, report.json\n"
        );
    }

    #[test]
    fn counts_and_versions_read_right() {
        let s = summary(&[texture(3, 0, "null"), texture(0, 1, "null")], 1, 1);
        assert!(
            s.starts_with("m.glb: 2 textures, 1 skipped, 1 warning (in report.json)\n"),
            "{s}"
        );
        assert!(
            s.contains(
                "all 3 seams closed; seam_rms over the closed seams 7.53 → 0.20 in the erased PNG"
            ),
            "{s}"
        );
        assert!(s.contains("1 seam, all left as painted\n"), "{s}");
        assert_eq!(percent(0.001), "<1%");
        assert_eq!(percent(0.0), "0%");
    }
}
