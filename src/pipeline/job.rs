//! The whole job, the library's one entry point: a model and its files in;
//! every texture's files, `report.json` and the model rewritten to use the
//! DDS files out. The CLI and the service both call [`run_job`] and add
//! nothing to it but where the bytes come from and go to.

use std::collections::BTreeMap;
use std::time::Instant;

use crate::budget::{self, Limits};
use crate::lod::LodLevel;
use crate::model::rewrite::{
    referenced_files, rewrite_model, rewrite_model_referring, Replacement,
};
use crate::model::{self, LoadError, LoadOptions, Plan, Resolver};

use super::lod::add_lods;
use super::progress::{Progress, Sink, Stop};
use super::{run_reporting, OutputFile, PipelineError, ProcessOptions, Report};

/// The name of the report among a job's files.
pub const REPORT_NAME: &str = "report.json";

/// A model to process: its file and what its URIs refer to.
pub struct JobInput<'a> {
    /// The model's file name (a path for the CLI): the report's `input`,
    /// errors' subject, and (its last component) the rewritten model's name.
    pub name: &'a str,
    pub main: &'a [u8],
    pub files: &'a dyn Resolver,
}

/// Everything a job is told.
#[derive(Clone, Debug)]
pub struct JobSettings {
    pub process: ProcessOptions,
    /// The loader's limits (its `extra_maps` is the job option's).
    pub load: LoadOptions,
    pub limits: Limits,
}

/// Milliseconds per stage of the job.
#[derive(Clone, Copy, Debug, Default)]
pub struct JobTimings {
    pub load: u64,
    pub process: u64,
    pub rewrite: u64,
}

/// A finished job.
pub struct JobOutput {
    /// In a stable order: per texture as the pipeline makes them, then
    /// `report.json`, then the rewritten model and the files beside it.
    pub files: Vec<OutputFile>,
    pub report: Report,
    /// The report's warnings and any about the rewritten model.
    pub warnings: Vec<String>,
    pub timings: JobTimings,
}

/// Why a job ended without its files.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The input is at fault (one line naming the file).
    #[error("{0}")]
    BadInput(String),
    /// Over the budget: the quantity, its value and the limit.
    #[error("{0}")]
    TooLarge(String),
    /// The engine failed on a model it accepted, or the machine did.
    #[error("{0}")]
    Failed(String),
    #[error("stopped: {0:?}")]
    Stopped(Stop),
}

impl From<LoadError> for JobError {
    fn from(e: LoadError) -> Self {
        if e.is_bad_input() {
            JobError::BadInput(e.to_string())
        } else {
            JobError::Failed(e.to_string())
        }
    }
}

/// Reads and checks everything of the input but its texels, and holds the
/// job to its budget: what [`run_job`] does before any large allocation,
/// and what a service checks an upload with before queueing it.
pub fn admit(input: &JobInput<'_>, settings: &JobSettings) -> Result<Plan, JobError> {
    // Which maps load is a job option; the limits are the caller's.
    let load = LoadOptions {
        extra_maps: settings.process.extra_maps,
        ..settings.load.clone()
    };
    let plan = model::plan_from_memory(input.name, input.main, input.files, &load)?;
    let need = budget::need(&plan, &settings.process);
    budget::check(&need, &settings.limits)
        .map_err(|over| JobError::TooLarge(format!("{}: {over}", plan.file())))?;
    Ok(plan)
}

/// Runs the whole job; `sink` hears its progress and may stop it.
pub fn run_job(
    input: &JobInput<'_>,
    settings: &JobSettings,
    sink: &mut dyn Sink,
) -> Result<JobOutput, JobError> {
    let at = |stage, fraction| Progress {
        stage,
        texture: None,
        fraction,
    };
    sink.progress(&at("load", 0.0)).map_err(JobError::Stopped)?;
    let t = Instant::now();
    let model = admit(input, settings)?.decode()?;
    let mut timings = JobTimings {
        load: t.elapsed().as_millis() as u64,
        ..JobTimings::default()
    };

    let t = Instant::now();
    let out = run_reporting(
        &model,
        base_name(input.name),
        timings.load,
        &settings.process,
        sink,
    )
    .map_err(|e| match e {
        PipelineError::Stopped(stop) => JobError::Stopped(stop),
        e => JobError::Failed(e.to_string()),
    })?;
    // Every texture the model binds was skipped by the solver: nothing of
    // use would come out, and the model is at fault (its UVs), so the job
    // fails as bad input rather than succeed empty.
    if !model.bindings.is_empty() && out.report.textures.is_empty() && !out.unsolvable.is_empty() {
        return Err(JobError::BadInput(format!(
            "{}: no texture can be processed: {}",
            input.name,
            out.unsolvable.join("; ")
        )));
    }
    timings.process = t.elapsed().as_millis() as u64;
    drop(model);

    sink.progress(&at("rewrite", 0.9))
        .map_err(JobError::Stopped)?;
    let t = Instant::now();
    let mut files = out.files;
    let mut report = out.report;
    // The report goes before the model, but the levels of detail made
    // with the model add to it: its place is held until then.
    let report_at = files.len();
    files.push(OutputFile {
        name: REPORT_NAME.to_string(),
        bytes: Vec::new(),
    });
    let mut warnings = report.warnings.clone();
    if let Some((levels, lod_warnings)) = rewritten_model(input, &report, &mut files, &mut warnings)
    {
        report.lods = levels;
        report.warnings.extend(lod_warnings.iter().cloned());
        warnings.extend(lod_warnings);
    }
    let mut json = serde_json::to_vec_pretty(&report)
        .map_err(|e| JobError::Failed(format!("cannot serialise the report: {e}")))?;
    json.push(b'\n');
    files[report_at].bytes = json;
    timings.rewrite = t.elapsed().as_millis() as u64;
    Ok(JobOutput {
        files,
        report,
        warnings,
        timings,
    })
}

/// The last component of a model's name.
fn base_name(name: &str) -> &str {
    name.rsplit(['/', '\\']).next().unwrap_or(name)
}

/// Adds the model rewritten to use the DDS files (`MSFT_texture_dds`), with
/// the erased PNGs as the fallback images, and for a `.gltf` the files it
/// still refers to, when the report lists DDS or KTX2 files (a model with
/// KTX2 files refers to the erased PNGs alone). What stands in the way
/// is a warning, not a failure: the DDS files are the job's point.
/// With `lod`, the model carries its levels of detail: their figures and
/// warnings are returned.
fn rewritten_model(
    input: &JobInput<'_>,
    report: &Report,
    files: &mut Vec<OutputFile>,
    warnings: &mut Vec<String>,
) -> Option<(Vec<LodLevel>, Vec<String>)> {
    let bytes_of = |name: &str| files.iter().find(|f| f.name == name).map(|f| &f.bytes[..]);
    let mut images = BTreeMap::new();
    for t in &report.textures {
        if t.files.dds.is_none() && t.files.ktx2.is_none() {
            continue;
        }
        let dds = t
            .files
            .dds
            .as_deref()
            .and_then(|name| Some((name, bytes_of(name)?)));
        if let Some(fallback) = bytes_of(&t.files.erased) {
            images.insert(
                t.image,
                Replacement {
                    dds,
                    fallback_name: &t.files.erased,
                    fallback,
                    uv_scale: t.resize.and_then(|r| r.uv_scale),
                },
            );
        }
    }
    if images.is_empty() {
        return None;
    }
    let mut bytes = match rewrite_model(input.main, &images) {
        Ok(b) => b,
        Err(e) => {
            warnings.push(format!("no rewritten model: {e}"));
            return None;
        }
    };
    let referring = (report.options.lod_files && !report.options.lod.is_empty())
        .then(|| rewrite_model_referring(input.main, &images).ok())
        .flatten();
    drop(images);
    let mut lods = None;
    let mut lod_files = Vec::new();
    if !report.options.lod.is_empty() {
        let name = base_name(input.name);
        match add_lods(
            name,
            &bytes,
            referring.as_deref(),
            report,
            files,
            input.files,
        ) {
            Ok(l) => {
                bytes = l.model;
                lod_files = l.files;
                lods = Some((l.levels, l.warnings));
            }
            Err(e) => warnings.push(format!("no levels of detail: {e}")),
        }
    }
    let taken = |name: &str| files.iter().chain(&lod_files).any(|f| f.name == name);
    // The files the rewritten model refers to that the job did not make.
    let beside: Vec<String> = match referenced_files(&bytes) {
        Ok(list) => list.into_iter().filter(|n| !taken(n)).collect(),
        Err(e) => {
            warnings.push(format!("no rewritten model: {e}"));
            return None;
        }
    };
    let model_name = base_name(input.name).to_string();
    if taken(&model_name) {
        warnings.push(format!(
            "no rewritten model: the model's name {model_name:?} is the name of an output"
        ));
        return None;
    }
    let mut copied = Vec::with_capacity(beside.len());
    for name in beside {
        match input.files.read(&name) {
            Ok(data) => copied.push(OutputFile {
                name,
                bytes: data.into_owned(),
            }),
            Err(e) => {
                warnings.push(format!("no rewritten model: cannot read {name:?}: {e}"));
                return None;
            }
        }
    }
    files.push(OutputFile {
        name: model_name,
        bytes,
    });
    files.extend(lod_files);
    files.extend(copied);
    lods
}
