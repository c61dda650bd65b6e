//! What a batch did: printed at its end, and written as JSON with
//! `--summary FILE`.

use serde::Serialize;

use crate::plural::count;

/// One model's result.
#[derive(Clone, Debug, Serialize)]
pub struct ModelOutcome {
    pub model: String,
    /// Its output folder.
    pub out: String,
    /// `processed`, `cached` (its outputs were already those of its
    /// inputs), `bad_input` or `failed`.
    pub status: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    pub textures: usize,
    #[serde(flatten)]
    pub seams: SeamFigures,
    pub seconds: f64,
}

/// What became of the seams: of a model (means over its textures), or of
/// a batch (means over its models). The closed seams come first: they are
/// what a run sets out to fix, while the figures over all seams include
/// those left as painted on purpose, which can rise where the encoding
/// moves a painted edge.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct SeamFigures {
    /// Seam edges closed, and left as painted, over the textures.
    pub seams_closed: usize,
    pub seams_left: usize,
    /// The report's `seam_rms_closed` of the input, and of what the
    /// outputs hold (the DDS, or the erased PNG without one).
    pub seam_rms_closed_before: Option<f64>,
    pub seam_rms_closed_after: Option<f64>,
    /// The report's `seam_rms`, over every seam, the same way.
    pub seam_rms_all_seams_before: Option<f64>,
    pub seam_rms_all_seams_after: Option<f64>,
}

/// The mean of the values present, `None` without any.
fn mean(values: impl Iterator<Item = Option<f64>>) -> Option<f64> {
    let v: Vec<f64> = values.flatten().collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

impl SeamFigures {
    /// The figures of a report's textures.
    fn of_textures(textures: &[serde_json::Value]) -> SeamFigures {
        let edges = |which: &str| {
            let count = |t: &serde_json::Value| t["seams"][which]["edges"].as_u64();
            textures.iter().filter_map(count).sum::<u64>() as usize
        };
        // What a renderer samples: the block-compressed file when there is
        // one, else the PNG.
        let held = |t: &serde_json::Value, key: &str| {
            ["bc1_seam_aware", "bc1", "bc7_seam_aware", "bc7", "erased"]
                .iter()
                .find_map(|version| t[*version][key].as_f64())
        };
        let input = |key: &str| mean(textures.iter().map(|t| t["input"][key].as_f64()));
        let output = |key: &str| mean(textures.iter().map(|t| held(t, key)));
        SeamFigures {
            seams_closed: edges("closed"),
            seams_left: edges("left"),
            seam_rms_closed_before: input("seam_rms_closed"),
            seam_rms_closed_after: output("seam_rms_closed"),
            seam_rms_all_seams_before: input("seam_rms"),
            seam_rms_all_seams_after: output("seam_rms"),
        }
    }

    /// The figures of a batch's models.
    fn of_models(outcomes: &[ModelOutcome]) -> SeamFigures {
        let over =
            |pick: fn(&SeamFigures) -> Option<f64>| mean(outcomes.iter().map(|o| pick(&o.seams)));
        SeamFigures {
            seams_closed: outcomes.iter().map(|o| o.seams.seams_closed).sum(),
            seams_left: outcomes.iter().map(|o| o.seams.seams_left).sum(),
            seam_rms_closed_before: over(|s| s.seam_rms_closed_before),
            seam_rms_closed_after: over(|s| s.seam_rms_closed_after),
            seam_rms_all_seams_before: over(|s| s.seam_rms_all_seams_before),
            seam_rms_all_seams_after: over(|s| s.seam_rms_all_seams_after),
        }
    }
}

impl ModelOutcome {
    /// The seam figures and texture count from a model's `report.json`.
    pub fn with_report(mut self, report: &[u8]) -> Self {
        let Ok(r) = serde_json::from_slice::<serde_json::Value>(report) else {
            return self;
        };
        let textures = r["textures"].as_array().cloned().unwrap_or_default();
        self.textures = textures.len();
        self.seams = SeamFigures::of_textures(&textures);
        self
    }
}

/// The whole batch.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Summary {
    pub models: usize,
    pub processed: usize,
    pub cached: usize,
    pub bad_input: usize,
    pub failed: usize,
    /// Models not started because an earlier one failed (no `--keep-going`).
    pub not_run: usize,
    pub textures: usize,
    /// Means over the models that have each figure; the seam counts are
    /// sums.
    #[serde(flatten)]
    pub seams: SeamFigures,
    pub seconds: f64,
    pub outcomes: Vec<ModelOutcome>,
}

impl Summary {
    pub fn new(outcomes: Vec<ModelOutcome>, total: usize, seconds: f64) -> Summary {
        let count = |s: &str| outcomes.iter().filter(|o| o.status == s).count();
        Summary {
            models: total,
            processed: count("processed"),
            cached: count("cached"),
            bad_input: count("bad_input"),
            failed: count("failed"),
            not_run: total - outcomes.len(),
            textures: outcomes.iter().map(|o| o.textures).sum(),
            seams: SeamFigures::of_models(&outcomes),
            seconds,
            outcomes,
        }
    }

    /// The lines a person reads at the end of a batch: the counts, then
    /// the closed seams before and after, then the figures over all seams.
    pub fn text(&self) -> String {
        let mut s = format!(
            "{}: {} processed, {} from the cache, {} bad input, {} failed{} — {}, {:.1} s\n",
            count(self.models, "model"),
            self.processed,
            self.cached,
            self.bad_input,
            self.failed,
            if self.not_run > 0 {
                format!(", {} not run", self.not_run)
            } else {
                String::new()
            },
            count(self.textures, "texture"),
            self.seconds
        );
        s.push_str(&self.seam_lines());
        for o in &self.outcomes {
            let Some(e) = &o.error else { continue };
            // Most messages name the model already.
            if e.contains(&o.model) {
                s.push_str(&format!("{}: {e}\n", o.status));
            } else {
                s.push_str(&format!("{} {}: {e}\n", o.status, o.model));
            }
        }
        s
    }

    /// `seam_rms over the closed seams: 7.220 → 0.390 (1 model; 1234
    /// seams closed, 56 left as painted)`, then the same over all seams.
    fn seam_lines(&self) -> String {
        let f = &self.seams;
        let mut s = String::new();
        if let (Some(b), Some(a)) = (f.seam_rms_closed_before, f.seam_rms_closed_after) {
            let models = self
                .outcomes
                .iter()
                .filter(|o| o.seams.seam_rms_closed_after.is_some())
                .count();
            let over = if models == 1 {
                "1 model".to_string()
            } else {
                format!("mean over {models} models")
            };
            s.push_str(&format!(
                "seam_rms over the closed seams: {b:.3} → {a:.3} ({over}; {} closed, {} left as painted)\n",
                count(f.seams_closed, "seam"),
                f.seams_left
            ));
        } else if f.seams_closed + f.seams_left > 0 {
            s.push_str(&format!(
                "no seam closed: {} left as painted\n",
                count(f.seams_left, "seam")
            ));
        }
        if let (Some(b), Some(a)) = (f.seam_rms_all_seams_before, f.seam_rms_all_seams_after) {
            if f.seams_left > 0 {
                s.push_str(&format!(
                    "seam_rms over all seams, those left as painted included: {b:.3} → {a:.3}\n"
                ));
            }
        }
        s
    }
}
