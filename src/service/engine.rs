//! One job's CPU work: the same loader and [`pipeline::run`] as `seamstress
//! process`, plus the rewritten model. Runs on a blocking thread.

use std::collections::BTreeMap;
use std::time::Instant;

use serde_json::value::RawValue;

use crate::budget::{self, Limits, OverBudget};
use crate::model::rewrite::rewrite_model;
use crate::model::{self, LoadError, LoadOptions, Model, Plan};
use crate::pipeline::{self, Output};

use super::job::StageTimings;
use super::options::{process_options, ResolvedOptions};
use super::upload::{base_name, Bundle};

/// Why a job stopped before its end.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    Canceled,
    TimedOut,
    ShuttingDown,
}

#[derive(Debug)]
pub enum EngineError {
    /// The upload is at fault: the loader's one-line message.
    BadInput(String),
    /// Over the job budget (`too_large`).
    TooLarge(String),
    /// The engine failed on a model it accepted.
    Failed(String),
    /// The job's process died without an outcome (`crashed`).
    Crashed(String),
    /// Its results could not be written: the disk is full (`storage_full`).
    StorageFull(String),
    Stopped(Stop),
}

/// Everything a finished job stores.
pub struct Produced {
    /// Output files in a stable order: per texture as the pipeline returns
    /// them, then `report.json`, then the rewritten model and its files.
    pub files: Vec<(String, Vec<u8>)>,
    pub report: Box<RawValue>,
    pub timings: StageTimings,
    pub warnings: Vec<String>,
}

pub const REPORT_NAME: &str = "report.json";

pub fn load_options(opts: &ResolvedOptions, max_texture_size: u32) -> LoadOptions {
    LoadOptions {
        max_texture_size,
        extra_maps: opts.extra_maps,
        ..LoadOptions::default()
    }
}

/// Why an upload is refused before it is queued.
#[derive(Debug, thiserror::Error)]
pub enum Rejection {
    #[error(transparent)]
    Load(#[from] LoadError),
    /// Over the job budget: `too_large`.
    #[error("{file}: {over}")]
    TooLarge { file: String, over: OverBudget },
}

/// Checks an upload the way loading does, short of decoding the pixels
/// (containers, JSON, schema, buffers, accessors, URIs, every image's
/// header against the size limit), and holds the job to its budget.
pub fn validate(
    bundle: &Bundle,
    opts: &ResolvedOptions,
    max_texture_size: u32,
    limits: &Limits,
) -> Result<Plan, Rejection> {
    let plan = model::plan_from_memory(
        &bundle.main_name,
        &bundle.main,
        &bundle.files,
        &load_options(opts, max_texture_size),
    )?;
    let need = budget::need(&plan, &process_options(opts));
    budget::check(&need, limits).map_err(|over| Rejection::TooLarge {
        file: plan.file().to_string(),
        over,
    })?;
    Ok(plan)
}

/// Runs one job. `checkpoint` is called between stages with the stage and
/// the fraction done; an `Err` from it stops the job there.
pub fn run(
    bundle: &Bundle,
    opts: &ResolvedOptions,
    max_texture_size: u32,
    limits: &Limits,
    checkpoint: &mut dyn FnMut(&str, f64) -> Result<(), Stop>,
) -> Result<Produced, EngineError> {
    let mut timings = StageTimings::default();
    checkpoint("load", 0.0).map_err(EngineError::Stopped)?;
    let t = Instant::now();
    let load_failed = |e: LoadError| {
        if e.is_bad_input() {
            EngineError::BadInput(e.to_string())
        } else {
            EngineError::Failed(e.to_string())
        }
    };
    // The upload was held to the budget when it came; the limit may have
    // been lowered since (a restart with other settings).
    let plan = match validate(bundle, opts, max_texture_size, limits) {
        Ok(plan) => plan,
        Err(Rejection::Load(e)) => return Err(load_failed(e)),
        Err(e @ Rejection::TooLarge { .. }) => return Err(EngineError::TooLarge(e.to_string())),
    };
    let mut model = plan.decode().map_err(load_failed)?;
    let load_ms = t.elapsed().as_millis() as u64;
    timings.load = Some(load_ms);

    let t = Instant::now();
    let output = process(&mut model, bundle, load_ms, opts, checkpoint)?;
    timings.process = Some(t.elapsed().as_millis() as u64);

    checkpoint("rewrite", 0.9).map_err(EngineError::Stopped)?;
    let t = Instant::now();
    let mut files: Vec<(String, Vec<u8>)> = output
        .files
        .into_iter()
        .map(|f| (f.name, f.bytes))
        .collect();
    let mut report_bytes = serde_json::to_vec_pretty(&output.report)
        .map_err(|e| EngineError::Failed(format!("cannot serialise the report: {e}")))?;
    report_bytes.push(b'\n');
    let report = serde_json::to_string(&output.report)
        .ok()
        .and_then(|text| RawValue::from_string(text).ok())
        .ok_or_else(|| EngineError::Failed("cannot serialise the report".into()))?;
    files.push((REPORT_NAME.to_string(), report_bytes));
    let dds: BTreeMap<usize, String> = output
        .report
        .textures
        .iter()
        .filter_map(|t| Some((t.image, t.files.dds.clone()?)))
        .collect();
    let mut warnings = output.report.warnings.clone();
    rewritten_model(bundle, &dds, &mut files, &mut warnings);
    timings.rewrite = Some(t.elapsed().as_millis() as u64);
    Ok(Produced {
        files,
        report,
        timings,
        warnings,
    })
}

/// The pipeline, one texture at a time so that progress is reported and a
/// cancellation or the time limit is honoured between textures. Each call
/// gets the model with one binding; the textures are independent, so the
/// files and report entries are those of a single call over all of them.
fn process(
    model: &mut Model,
    bundle: &Bundle,
    load_ms: u64,
    opts: &ResolvedOptions,
    checkpoint: &mut dyn FnMut(&str, f64) -> Result<(), Stop>,
) -> Result<Output, EngineError> {
    let popts = process_options(opts);
    let failed = |e: pipeline::PipelineError| EngineError::Failed(e.to_string());
    let bindings = std::mem::take(&mut model.bindings);
    let total = bindings.len();
    if total == 0 {
        return pipeline::run(model, &bundle.main_name, load_ms, &popts).map_err(failed);
    }
    let mut merged: Option<Output> = None;
    for (k, binding) in bindings.into_iter().enumerate() {
        checkpoint("process", 0.1 + 0.8 * k as f64 / total as f64).map_err(EngineError::Stopped)?;
        let mut one = model.clone();
        one.bindings = vec![binding];
        let out = pipeline::run(&one, &bundle.main_name, load_ms, &popts).map_err(failed)?;
        match &mut merged {
            None => merged = Some(out),
            Some(m) => {
                m.files.extend(out.files);
                m.report.textures.extend(out.report.textures);
                m.report.warnings.extend(out.report.warnings);
            }
        }
    }
    merged.ok_or_else(|| EngineError::Failed("no output".into()))
}

/// Adds the model rewritten to use the DDS files (and, for a `.gltf`, the
/// uploaded files it refers to), when the report lists DDS files.
fn rewritten_model(
    bundle: &Bundle,
    dds: &BTreeMap<usize, String>,
    files: &mut Vec<(String, Vec<u8>)>,
    warnings: &mut Vec<String>,
) {
    if dds.is_empty() {
        return;
    }
    let model_name = base_name(&bundle.main_name).to_string();
    let taken = |name: &str| files.iter().any(|(n, _)| n == name);
    if let Some(clash) = std::iter::once(model_name.as_str())
        .chain(bundle.files.keys().map(String::as_str))
        .find(|n| taken(n))
    {
        warnings.push(format!(
            "no rewritten model: the upload's file {clash:?} has the name of an output"
        ));
        return;
    }
    match rewrite_model(&bundle.main, dds) {
        Ok(bytes) => {
            files.push((model_name, bytes));
            for (name, data) in &bundle.files {
                files.push((name.clone(), data.clone()));
            }
        }
        Err(e) => warnings.push(format!("no rewritten model: {e}")),
    }
}
