//! One job's CPU work: [`pipeline::run_job`], as `seamstress process` runs
//! it, over an upload; and the check an upload gets before it is queued.

use serde_json::value::RawValue;

use crate::budget::Limits;
use crate::model::LoadOptions;
use crate::pipeline::{self, JobError, JobInput, JobSettings, ProcessOptions, Progress};

use super::job::{Progress as JobProgress, StageTimings};
use super::upload::Bundle;

pub use crate::pipeline::Stop;

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

/// What a job over `bundle` is told.
fn settings(opts: &ProcessOptions, max_texture_size: u32, limits: &Limits) -> JobSettings {
    JobSettings {
        process: *opts,
        load: LoadOptions {
            max_texture_size,
            ..LoadOptions::default()
        },
        limits: *limits,
    }
}

fn input(bundle: &Bundle) -> JobInput<'_> {
    JobInput {
        name: &bundle.main_name,
        main: &bundle.main,
        files: &bundle.files,
    }
}

/// Checks an upload as the job will, short of decoding the pixels
/// (containers, JSON, schema, buffers, accessors, URIs, every image's
/// header against the size limit), and holds the job to its budget.
pub fn validate(
    bundle: &Bundle,
    opts: &ProcessOptions,
    max_texture_size: u32,
    limits: &Limits,
) -> Result<(), JobError> {
    pipeline::admit(&input(bundle), &settings(opts, max_texture_size, limits)).map(drop)
}

/// Runs one job: [`pipeline::run_job`] over the upload. `checkpoint` is
/// called between stages and textures with the job's progress; an `Err`
/// from it stops the job there.
pub fn run(
    bundle: &Bundle,
    opts: &ProcessOptions,
    max_texture_size: u32,
    limits: &Limits,
    checkpoint: &mut dyn FnMut(&JobProgress) -> Result<(), Stop>,
) -> Result<Produced, EngineError> {
    let settings = settings(opts, max_texture_size, limits);
    let mut sink = |at: &Progress<'_>| checkpoint(&JobProgress::of(at));
    let out = pipeline::run_job(&input(bundle), &settings, &mut sink).map_err(|e| match e {
        JobError::BadInput(m) => EngineError::BadInput(m),
        JobError::TooLarge(m) => EngineError::TooLarge(m),
        JobError::Failed(m) => EngineError::Failed(m),
        JobError::Stopped(stop) => EngineError::Stopped(stop),
    })?;
    let report = serde_json::to_string(&out.report)
        .ok()
        .and_then(|text| RawValue::from_string(text).ok())
        .ok_or_else(|| EngineError::Failed("cannot serialise the report".into()))?;
    Ok(Produced {
        files: out.files.into_iter().map(|f| (f.name, f.bytes)).collect(),
        report,
        timings: StageTimings {
            load: Some(out.timings.load),
            process: Some(out.timings.process),
            rewrite: Some(out.timings.rewrite),
            ..StageTimings::default()
        },
        warnings: out.warnings,
    })
}
