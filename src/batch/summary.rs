//! What a batch did: printed at its end, and written as JSON with
//! `--summary FILE`.

use serde::Serialize;

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
    /// Mean over its textures of `seam_rms` of the input and of what the
    /// outputs hold (the DDS, or the erased PNG without one).
    pub seam_rms_before: Option<f64>,
    pub seam_rms_after: Option<f64>,
    pub seconds: f64,
}

impl ModelOutcome {
    /// The seam figures and texture count from a model's `report.json`.
    pub fn with_report(mut self, report: &[u8]) -> Self {
        let Ok(r) = serde_json::from_slice::<serde_json::Value>(report) else {
            return self;
        };
        let textures = r["textures"].as_array().cloned().unwrap_or_default();
        self.textures = textures.len();
        let mean = |pick: &dyn Fn(&serde_json::Value) -> Option<f64>| {
            let v: Vec<f64> = textures.iter().filter_map(pick).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        self.seam_rms_before = mean(&|t| t["input"]["seam_rms"].as_f64());
        self.seam_rms_after = mean(&|t| {
            t["bc1_seam_aware"]["seam_rms"]
                .as_f64()
                .or_else(|| t["bc1"]["seam_rms"].as_f64())
                .or_else(|| t["erased"]["seam_rms"].as_f64())
        });
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
    pub seam_rms_before: Option<f64>,
    pub seam_rms_after: Option<f64>,
    pub seconds: f64,
    pub outcomes: Vec<ModelOutcome>,
}

impl Summary {
    pub fn new(outcomes: Vec<ModelOutcome>, total: usize, seconds: f64) -> Summary {
        let count = |s: &str| outcomes.iter().filter(|o| o.status == s).count();
        let mean = |pick: fn(&ModelOutcome) -> Option<f64>| {
            let v: Vec<f64> = outcomes.iter().filter_map(pick).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        Summary {
            models: total,
            processed: count("processed"),
            cached: count("cached"),
            bad_input: count("bad_input"),
            failed: count("failed"),
            not_run: total - outcomes.len(),
            textures: outcomes.iter().map(|o| o.textures).sum(),
            seam_rms_before: mean(|o| o.seam_rms_before),
            seam_rms_after: mean(|o| o.seam_rms_after),
            seconds,
            outcomes,
        }
    }

    /// The lines a person reads at the end of a batch.
    pub fn text(&self) -> String {
        let mut s = format!(
            "{} models: {} processed, {} from the cache, {} bad input, {} failed{} — {} textures, {:.1} s\n",
            self.models,
            self.processed,
            self.cached,
            self.bad_input,
            self.failed,
            if self.not_run > 0 {
                format!(", {} not run", self.not_run)
            } else {
                String::new()
            },
            self.textures,
            self.seconds
        );
        if let (Some(b), Some(a)) = (self.seam_rms_before, self.seam_rms_after) {
            s.push_str(&format!(
                "seam_rms (mean over models): {b:.3} before, {a:.3} after\n"
            ));
        }
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
}
