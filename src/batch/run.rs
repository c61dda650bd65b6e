//! Runs models into output folders: one model ([`run_model`]) or a whole
//! batch on `jobs` threads ([`run_batch`]), telling an [`Observer`] what
//! happens so that the caller can draw progress.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use super::cache::{self, Stamp, STAMP_NAME};
use super::discover::BatchModel;
use super::summary::{ModelOutcome, Summary};
use crate::model::rewrite::referenced_files;
use crate::model::DirResolver;
use crate::pipeline::job::REPORT_NAME;
use crate::pipeline::{
    self, JobError, JobInput, JobSettings, ProcessOptions, Progress, Sink, Stop,
};

/// Why a model produced no outputs.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The input is at fault (a bad model, over the budget, an `--out`
    /// that cannot be written); the message names it.
    #[error("{0}")]
    BadInput(String),
    /// Something failed that the input cannot fix.
    #[error("{0}")]
    Internal(String),
}

/// What a model's run wrote.
pub struct Written {
    pub report: Vec<u8>,
    /// Output names (relative to the folder) and sizes.
    pub files: Vec<(String, u64)>,
}

/// A model read from disk, with the folder its files are resolved in.
pub struct ModelFiles {
    pub name: String,
    pub main: Vec<u8>,
    pub dir: PathBuf,
    pub files: DirResolver,
}

impl ModelFiles {
    pub fn read(input: &Path) -> Result<ModelFiles, RunError> {
        let name = input.display().to_string();
        let main = std::fs::read(input).map_err(|e| {
            let message = format!("{name}: cannot read it: {e}");
            match e.kind() {
                std::io::ErrorKind::NotFound | std::io::ErrorKind::IsADirectory => {
                    RunError::BadInput(message)
                }
                _ => RunError::Internal(message),
            }
        })?;
        let dir = match input.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let files = DirResolver::new(&dir)
            .map_err(|e| RunError::Internal(format!("cannot open {}: {e}", dir.display())))?;
        Ok(ModelFiles {
            name,
            main,
            dir,
            files,
        })
    }
}

/// Runs `model` (read from `input`) and writes its outputs into `out`.
/// Into the model's own folder, the model and the files it refers to are
/// never overwritten.
pub fn run_model(
    model: &ModelFiles,
    input: &Path,
    out: &Path,
    settings: &JobSettings,
    sink: &mut dyn Sink,
) -> Result<Written, RunError> {
    // Before the work, so that an unusable output folder fails at once.
    let mut staging = Staging::open(out)?;
    let job = JobInput {
        name: &model.name,
        main: &model.main,
        files: &model.files,
    };
    let output = pipeline::run_job(&job, settings, sink).map_err(|e| match e {
        JobError::BadInput(m) | JobError::TooLarge(m) => RunError::BadInput(m),
        e => RunError::Internal(format!("{}: processing failed: {e}", model.name)),
    })?;
    let files = output.files.into_iter().map(|f| (f.name, f.bytes));
    write_outputs(&mut staging, model, input, files)
}

/// Writes a model's output files through `staging` into its folder. Into
/// the model's own folder, the model and the files it refers to are never
/// overwritten.
pub(crate) fn write_outputs(
    staging: &mut Staging,
    model: &ModelFiles,
    input: &Path,
    outputs: impl Iterator<Item = (String, Vec<u8>)>,
) -> Result<Written, RunError> {
    let same_folder = match (staging.out.canonicalize(), model.dir.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    let mut originals = referenced_files(&model.main).unwrap_or_default();
    originals.extend(input.file_name().map(|n| n.to_string_lossy().into_owned()));
    let mut files = Vec::new();
    let mut report = Vec::new();
    for (name, bytes) in outputs {
        if name == REPORT_NAME {
            report.clone_from(&bytes);
        }
        if same_folder && originals.contains(&name) {
            tracing::warn!(file = %name, "not written: --out is the model's folder and holds it");
            continue;
        }
        staging.write(&name, &bytes)?;
        files.push((name, bytes.len() as u64));
    }
    staging.publish()?;
    Ok(Written { report, files })
}

/// Where a batch's models run: here ([`JobSettings`]: the pipeline in this
/// process) or on a server (`seamstress submit`'s client).
pub trait Runner: Sync {
    /// The options the outputs are made with (part of the cache key).
    fn options(&self) -> &ProcessOptions;
    /// Runs `model` (read from `input`) into `out`; `key` is its cache key.
    fn run(
        &self,
        model: &ModelFiles,
        input: &Path,
        out: &Path,
        key: &str,
        sink: &mut dyn Sink,
    ) -> Result<Written, RunError>;
}

impl Runner for JobSettings {
    fn options(&self) -> &ProcessOptions {
        &self.process
    }

    fn run(
        &self,
        model: &ModelFiles,
        input: &Path,
        out: &Path,
        _key: &str,
        sink: &mut dyn Sink,
    ) -> Result<Written, RunError> {
        run_model(model, input, out, self, sink)
    }
}

/// What a batch's caller hears: calls come from the worker threads.
pub trait Observer: Sync {
    /// Model `index` starts (or is looked up in the cache).
    fn started(&self, index: usize, model: &BatchModel);
    /// Model `index` is at `at`.
    fn progress(&self, index: usize, model: &BatchModel, at: &Progress<'_>);
    /// Model `index` is done, however it ended.
    fn finished(&self, index: usize, outcome: &ModelOutcome);
}

/// How a batch runs.
#[derive(Clone, Debug)]
pub struct BatchOptions {
    pub out: PathBuf,
    /// Models at once.
    pub jobs: usize,
    /// Go on after a model fails.
    pub keep_going: bool,
    /// Run every model, even those whose outputs are up to date.
    pub force: bool,
}

/// Runs every model of `models` into its folder under `opts.out`.
pub fn run_batch(
    models: &[BatchModel],
    runner: &dyn Runner,
    opts: &BatchOptions,
    observer: &dyn Observer,
) -> Summary {
    let started = Instant::now();
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let outcomes = Mutex::new(Vec::new());
    // The cache key covers everything that shapes the outputs.
    std::thread::scope(|s| {
        for _ in 0..opts.jobs.clamp(1, models.len().max(1)) {
            s.spawn(|| loop {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(m) = models.get(i) else { break };
                observer.started(i, m);
                let outcome = one(m, i, runner, opts, observer);
                let failed = matches!(outcome.status, "bad_input" | "failed");
                if failed && !opts.keep_going {
                    stop.store(true, Ordering::Relaxed);
                }
                observer.finished(i, &outcome);
                outcomes
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push((i, outcome));
            });
        }
    });
    let mut outcomes = outcomes.into_inner().unwrap_or_else(|e| e.into_inner());
    outcomes.sort_by_key(|(i, _)| *i);
    Summary::new(
        outcomes.into_iter().map(|(_, o)| o).collect(),
        models.len(),
        started.elapsed().as_secs_f64(),
    )
}

/// One model of a batch: from the cache, or run and stamped.
fn one(
    m: &BatchModel,
    index: usize,
    runner: &dyn Runner,
    opts: &BatchOptions,
    observer: &dyn Observer,
) -> ModelOutcome {
    let t = Instant::now();
    let out = opts.out.join(&m.out);
    let outcome = |status, error: Option<String>| ModelOutcome {
        model: m.path.display().to_string(),
        out: out.display().to_string(),
        status,
        error,
        textures: 0,
        seams: Default::default(),
        seconds: t.elapsed().as_secs_f64(),
    };
    let failed = |e: RunError| match e {
        RunError::BadInput(msg) => outcome("bad_input", Some(msg)),
        RunError::Internal(msg) => outcome("failed", Some(msg)),
    };
    let files = match ModelFiles::read(&m.path) {
        Ok(f) => f,
        Err(e) => return failed(e),
    };
    let key = cache::key(&files.main, &files.files, runner.options());
    if !opts.force && Stamp::fresh(&out, &key) {
        let report = std::fs::read(out.join(REPORT_NAME)).unwrap_or_default();
        return outcome("cached", None).with_report(&report);
    }
    let mut sink = |at: &Progress<'_>| -> Result<(), Stop> {
        observer.progress(index, m, at);
        Ok(())
    };
    match runner.run(&files, &m.path, &out, &key, &mut sink) {
        Ok(w) => {
            let stamp = Stamp {
                key,
                files: w.files,
            };
            if let Err(e) = write_atomic(&out.join(STAMP_NAME), &stamp.to_bytes()) {
                // The outputs stand; the next run redoes the model.
                tracing::warn!(folder = %out.display(), error = %e, "cache stamp not written");
            }
            outcome("processed", None).with_report(&w.report)
        }
        Err(e) => failed(e),
    }
}

fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    let mut f = std::fs::File::create(&tmp)?;
    f.write_all(bytes)?;
    f.sync_all()?;
    std::fs::rename(&tmp, path)
}

/// A run's private folder inside its output folder (removed when dropped):
/// files are written and synced there, then renamed into place one by one,
/// so a reader never sees half a file and concurrent runs never clash.
pub(crate) struct Staging {
    out: PathBuf,
    dir: PathBuf,
    names: Vec<String>,
}

impl Staging {
    /// A staging folder in `out`; an `out` that cannot be written is the
    /// caller's input at fault.
    pub(crate) fn open(out: &Path) -> Result<Staging, RunError> {
        Staging::create(out).map_err(|e| {
            RunError::BadInput(format!("--out {}: cannot write there: {e}", out.display()))
        })
    }

    fn create(out: &Path) -> std::io::Result<Staging> {
        std::fs::create_dir_all(out)?;
        remove_abandoned(out);
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let dir = out.join(format!(
            ".seamstress-{}-{nanos:08x}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        std::fs::create_dir(&dir)?;
        Ok(Staging {
            out: out.to_path_buf(),
            dir,
            names: Vec::new(),
        })
    }

    fn write(&mut self, name: &str, bytes: &[u8]) -> Result<(), RunError> {
        let path = self.dir.join(name);
        let io = |what: &str, p: &Path, e: std::io::Error| {
            RunError::Internal(format!("cannot {what} {}: {e}", p.display()))
        };
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| io("create", parent, e))?;
        }
        let mut f = std::fs::File::create(&path).map_err(|e| io("create", &path, e))?;
        f.write_all(bytes)
            .and_then(|_| f.sync_all())
            .map_err(|e| io("write", &path, e))?;
        self.names.push(name.to_string());
        Ok(())
    }

    fn publish(&self) -> Result<(), RunError> {
        for name in &self.names {
            let to = self.out.join(name);
            let io = |e: std::io::Error| {
                RunError::Internal(format!("cannot write {}: {e}", to.display()))
            };
            if let Some(parent) = to.parent() {
                std::fs::create_dir_all(parent).map_err(io)?;
            }
            std::fs::rename(self.dir.join(name), &to).map_err(io)?;
        }
        Ok(())
    }
}

/// Removes the staging folders in `out` of runs whose process is gone (a
/// batch killed mid-write leaves its folder behind; a live run's is kept).
fn remove_abandoned(out: &Path) {
    let Ok(entries) = std::fs::read_dir(out) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let pid = name
            .to_str()
            .and_then(|n| n.strip_prefix(".seamstress-"))
            .and_then(|rest| rest.split('-').next())
            .and_then(|pid| pid.parse::<libc::pid_t>().ok());
        if pid.is_some_and(|pid| !process_alive(pid)) {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

fn process_alive(pid: libc::pid_t) -> bool {
    // SAFETY: signal 0 sends nothing; it only asks whether `pid` exists.
    let r = unsafe { libc::kill(pid, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() != Some(libc::ESRCH)
}

impl Drop for Staging {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
