//! The `seamstress` command line: `process` runs the engine on one model
//! or a batch of them, `serve` runs the HTTP service.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};

use seamstress::batch::run::{run_model, BatchOptions, ModelFiles, RunError, Runner, Written};
use seamstress::batch::{self, BatchModel};
use seamstress::bc1::Level;
use seamstress::budget::{self, Limits};
use seamstress::client::retry::RetryParams;
use seamstress::client::{Remote, RemoteParams};
use seamstress::lod::LodRatios;
use seamstress::model::LoadOptions;
use seamstress::pipeline::{
    self, AlphaOption, Container, Format, JobSettings, Method, NoSink, ProcessOptions, Resize,
    Target, DEFAULT_SEAM_TOLERANCE, DEFAULT_SEAM_WEIGHT,
};
use seamstress::plural::count;
use seamstress::seam::erase::Mode;

#[derive(Parser)]
#[command(
    name = "seamstress",
    version,
    about = "Seam erasure for glTF textures",
    after_help = "Logs go to standard error: warnings and errors for `process`, each request \
                  and job for `serve`; -v and -vv log more. SEAMSTRESS_LOG sets what is \
                  logged (e.g. SEAMSTRESS_LOG=debug, or seamstress=debug,tower_http=info); \
                  -v raises its overall level."
)]
struct Cli {
    /// Log format on standard error.
    #[arg(long, global = true, value_enum, default_value = "text")]
    log_format: LogFormat,
    /// Log more on standard error: -v one level more (info for `process`),
    /// -vv two (debug).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

#[derive(Subcommand)]
enum Command {
    /// Erase the seams of every colour texture of one model, or of every
    /// model of files, folders and glob patterns, and encode them to BC1.
    Process(ProcessArgs),
    /// The same batch on a running server: uploads each model, follows its
    /// job, downloads its files into the tree `process` writes.
    Submit(SubmitArgs),
    /// Run the HTTP service: a durable job queue and a worker pool over the engine.
    Serve(Box<seamstress::service::ServeArgs>),
    /// Run workers only, on a cluster's shared job store and files: claims
    /// and runs jobs, serves /metrics and /healthz.
    Worker(Box<seamstress::service::WorkerArgs>),
    /// Show a folder `process` wrote in the browser: the model in 3D, its
    /// texture as input, erased, regular and seam-aware BC1 and with filter
    /// taps discarded, and its seams. Serves on 127.0.0.1 and prints the URL.
    View {
        /// One model's output folder (it holds report.json).
        dir: PathBuf,
        /// The port; 0 takes any free one.
        #[arg(long, default_value_t = 0)]
        port: u16,
    },
    /// One job of a server's worker, in a process of its own.
    #[command(hide = true)]
    RunJob {
        /// The job's scratch folder, as the worker prepared it.
        dir: PathBuf,
    },
}

/// Which models, where their outputs go, and how a batch runs: the same
/// for `process` and `submit`.
#[derive(clap::Args)]
struct BatchArgs {
    /// .glb files, .gltf files with their files beside them, folders
    /// (every model below them) and glob patterns ('assets/**/*.glb').
    /// One model file writes into --out; anything else mirrors the inputs
    /// under --out, a folder per model.
    #[arg(required = true, value_name = "INPUT")]
    inputs: Vec<PathBuf>,
    /// Folder for the outputs (created if missing).
    #[arg(short, long)]
    out: PathBuf,
    /// Models processed at once (a batch; for submit, jobs in flight).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..))]
    jobs: u16,
    /// Go on with the other models after one fails (a batch).
    #[arg(long)]
    keep_going: bool,
    /// Process every model of a batch, also those whose outputs are those
    /// of their unchanged inputs and options.
    #[arg(long)]
    force: bool,
    /// Also write the batch's summary as JSON into this file.
    #[arg(long, value_name = "FILE")]
    summary: Option<PathBuf>,
    /// Print JSON on standard output instead of the summary for a person:
    /// one model's report (as report.json holds it), or a batch's summary.
    #[arg(long, conflicts_with = "quiet")]
    json: bool,
    /// Print nothing but errors.
    #[arg(short, long)]
    quiet: bool,
}

/// What `process` and `submit` print besides errors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Output {
    /// For a person: a few lines per model, or a batch's summary.
    Summary,
    /// The report, or the batch's summary, as JSON on standard output.
    Json,
    /// Errors only.
    Quiet,
}

impl BatchArgs {
    fn output(&self) -> Output {
        match (self.json, self.quiet) {
            (true, _) => Output::Json,
            (_, true) => Output::Quiet,
            _ => Output::Summary,
        }
    }
}

#[derive(clap::Args)]
struct ProcessArgs {
    #[command(flatten)]
    batch: BatchArgs,
    #[command(flatten)]
    options: OptionArgs,
    /// Refuse textures wider or taller than this, before decoding them.
    #[arg(long, default_value_t = 16384)]
    max_texture_size: u32,
    /// Refuse (exit 2) a model whose estimated peak memory is above this
    /// (512M, 4G, ...), before decoding it. Default: the memory available
    /// (MemAvailable, or less under a cgroup limit or `ulimit -v`) divided
    /// among the models run at once (--jobs).
    #[arg(long, value_name = "BYTES", value_parser = budget::parse_bytes)]
    max_memory: Option<u64>,
}

/// The job options as flags: each becomes its field of [`ProcessOptions`]
/// (the one definition, with the service's and the report's names) in
/// [`OptionArgs::options`]; a test holds the defaults to the library's.
#[derive(clap::Args)]
struct OptionArgs {
    /// How far from the seams texels may change: local, or global (changes
    /// spread over the charts, for sides painted with a colour offset).
    #[arg(long, value_parser = word::<Mode>, default_value = "local")]
    mode: Mode,
    /// How the two sides of a seam are made to agree: erase (along the whole
    /// seam, integrated exactly) or masking (at sampled points).
    #[arg(long, value_parser = word::<Method>, default_value = "erase")]
    method: Method,
    /// The block compression written for each texture besides the erased
    /// PNG: bc1 (BC3 where alpha blends; `dds` is its older name), bc7, or
    /// png (the erased PNG only).
    #[arg(long, value_parser = word::<Format>, default_value = "bc1")]
    format: Format,
    /// BC1 encoder effort: fast, default or best.
    #[arg(long, value_parser = word::<Level>, default_value = "default")]
    bc1_level: Level,
    /// BC7 encoder effort: fast, default or best.
    #[arg(long, value_parser = word::<Level>, default_value = "default")]
    bc7_level: Level,
    /// The file the blocks go in: dds (referenced from the rewritten model)
    /// or ktx2.
    #[arg(long, value_parser = word::<Container>, default_value = "dds")]
    container: Container,
    /// Supercompress KTX2 files with Zstandard at this level (1-22).
    #[arg(
        long,
        value_name = "LEVEL",
        default_value_t = 0,
        hide_default_value = true
    )]
    zstd: u8,
    /// Store the regular BC1 encoding instead of the seam-aware one.
    #[arg(long)]
    no_seam_aware: bool,
    /// α: how much seam agreement weighs against fidelity in seam-aware BC1.
    #[arg(long, default_value_t = DEFAULT_SEAM_WEIGHT)]
    seam_weight: f64,
    /// Write level 0 only. By default the DDS holds the whole mip chain,
    /// each level erased and encoded on its own.
    #[arg(long, overrides_with = "mips")]
    no_mips: bool,
    /// The default; still accepted from scripts written when the chain had
    /// to be asked for.
    #[arg(long, hide = true, overrides_with = "no_mips")]
    mips: bool,
    /// Write the DX10 header (BC1_UNORM, or BC1_UNORM_SRGB for colour textures).
    #[arg(long)]
    dx10: bool,
    /// Also process occlusion and metallic-roughness textures.
    #[arg(long)]
    extra_maps: bool,
    /// Leave seams whose sides, as their own charts paint them, differ by
    /// more than this many 8-bit levels (RMS along the edge): they are
    /// painted apart on purpose, and closing them would repaint the art.
    #[arg(long, value_name = "LEVELS", default_value_t = DEFAULT_SEAM_TOLERANCE)]
    seam_tolerance: f64,
    /// Close every seam, however differently its sides are painted.
    #[arg(long)]
    erase_all: bool,
    /// The GPU decoders whose palette rounding the seam-aware encoding keeps
    /// the seams closed under: ideal (the float palette), nvidia, amd, or
    /// robust (all three at once: one file for any GPU).
    #[arg(long, value_parser = word::<Target>, default_value = "robust")]
    decoder: Target,
    /// A texture whose sides are not multiples of 4 (which WebGL refuses):
    /// mul4 pads it to the next multiple of 4 and scales the rewritten
    /// model's UVs for it (KHR_texture_transform), or resamples it where
    /// padding cannot be exact (tiling UVs); pow2 resamples to powers of
    /// two; none leaves it.
    #[arg(long, value_parser = word::<Resize>, default_value = "mul4")]
    resize: Resize,
    /// What the DDS keeps of a base colour's alpha: auto (MASK materials:
    /// BC1 with one-bit alpha; BLEND, or alpha below 1 in the image: BC3),
    /// drop (opaque BC1), bc1a or bc3.
    #[arg(long, value_parser = word::<AlphaOption>, default_value = "auto")]
    alpha: AlphaOption,
    /// Also write <name>.seams.png: the seams coloured by what was done to
    /// them, with close-ups of the worst.
    #[arg(long)]
    pictures: bool,
    /// Seam-aware levels of detail: comma-separated ratios of each mesh's
    /// triangles (e.g. 0.5,0.25,0.1), carried by the rewritten model
    /// through MSFT_lod; seams stay closed on every level.
    #[arg(long, value_parser = word::<LodRatios>)]
    lod: Option<LodRatios>,
    /// Also write each level as its own <name>.lodN.glb, sharing the
    /// textures.
    #[arg(long)]
    lod_files: bool,
    /// Also write <name>.regular.dds: level 0's regular BC1 encoding, for
    /// `seamstress view` to show beside the seam-aware one.
    #[arg(long)]
    keep_regular: bool,
}

impl OptionArgs {
    fn options(&self) -> ProcessOptions {
        ProcessOptions {
            mode: self.mode,
            method: self.method,
            format: self.format,
            bc1_level: self.bc1_level,
            bc7_level: self.bc7_level,
            container: self.container,
            zstd: self.zstd,
            seam_aware: !self.no_seam_aware,
            seam_weight: self.seam_weight,
            // The two flags override each other: the last one given holds.
            mips: self.mips || !self.no_mips,
            dx10: self.dx10,
            extra_maps: self.extra_maps,
            seam_tolerance: self.seam_tolerance,
            erase_all: self.erase_all,
            decoder: self.decoder,
            resize: self.resize,
            alpha: self.alpha,
            pictures: self.pictures,
            lod: self.lod.unwrap_or_default(),
            lod_files: self.lod_files,
            keep_regular: self.keep_regular,
        }
    }
}

#[derive(clap::Args)]
struct SubmitArgs {
    #[command(flatten)]
    batch: BatchArgs,
    #[command(flatten)]
    options: OptionArgs,
    /// The server: http://HOST:PORT.
    #[arg(long, value_name = "URL")]
    server: String,
    /// How long a request waits for a server that is unreachable or busy
    /// (503, 429), retrying with backoff, before its model fails (30s, 10m).
    #[arg(
        long,
        value_name = "DURATION",
        default_value = "10m",
        value_parser = seamstress::service::config::parse_duration
    )]
    give_up_after: std::time::Duration,
    /// The bearer token, if the server asks for one.
    #[arg(long, env = "SEAMSTRESS_TOKEN", hide_env_values = true)]
    token: Option<String>,
}

#[global_allocator]
static ALLOC: seamstress::heap::HugePageAlloc = seamstress::heap::HugePageAlloc;

fn main() -> ExitCode {
    seamstress::heap::retain_freed_memory();
    let cli = Cli::parse();
    let format = cli.log_format;
    init_logging(
        format,
        &log_filter(&cli, std::env::var("SEAMSTRESS_LOG").ok()),
    );
    match cli.command {
        Command::Process(args) => match process(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(Failure::BadInput(msg)) => fail(format, 2, &msg),
            Err(Failure::Internal(e)) => fail(format, 1, &format!("{e:#}")),
        },
        Command::Submit(args) => match submit(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(Failure::BadInput(msg)) => fail(format, 2, &msg),
            Err(Failure::Internal(e)) => fail(format, 1, &format!("{e:#}")),
        },
        Command::RunJob { dir } => match seamstress::service::run_job(&dir) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => fail(format, 1, &format!("{}: {e}", dir.display())),
        },
        Command::View { dir, port } => match view(&dir, port) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => fail(format, 1, &e.to_string()),
        },
        Command::Serve(args) => match seamstress::service::serve(*args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => fail(format, if e.is_usage() { 2 } else { 1 }, &e.to_string()),
        },
        Command::Worker(args) => match seamstress::service::work(*args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => fail(format, if e.is_usage() { 2 } else { 1 }, &e.to_string()),
        },
    }
}

/// `seamstress view`: serves the folder until Ctrl-C; the URL goes to
/// standard output, for a person or a script to open.
fn view(dir: &Path, port: u16) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(seamstress::view::serve_folder(dir, port, |url| {
        println!("{url}");
        let _ = std::io::stdout().flush();
    }))?;
    Ok(())
}

/// Ends the program with `status`, saying why on standard error: one line,
/// and with `--log-format json` a JSON line like every other.
fn fail(format: LogFormat, status: u8, message: &str) -> ExitCode {
    match format {
        LogFormat::Text => eprintln!("error: {message}"),
        LogFormat::Json => tracing::error!(status, error = message, "exiting"),
    }
    ExitCode::from(status)
}

/// An option's word, as the HTTP options and the report spell it: the
/// options are defined once, in the library, with their serde names.
fn word<T: serde::de::DeserializeOwned>(s: &str) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string())).map_err(|e| e.to_string())
}

/// Log levels from quietest to loudest.
const LEVELS: [&str; 5] = ["error", "warn", "info", "debug", "trace"];

/// The log filter: the command's level (a one-shot command warns, a service
/// logs every request and job), raised by -v and lowered to errors by -q,
/// with SEAMSTRESS_LOG's directives. Without a flag, SEAMSTRESS_LOG alone
/// decides when set; with one, the louder of its overall level and the
/// flag's holds, and its per-target directives stay.
fn log_filter(cli: &Cli, env: Option<String>) -> String {
    let (default, quiet) = match &cli.command {
        Command::Process(a) => (1, a.batch.quiet),
        Command::Submit(a) => (1, a.batch.quiet),
        Command::RunJob { .. } => (1, false),
        Command::View { .. } => (1, false),
        Command::Serve(_) | Command::Worker(_) => (2, false),
    };
    // As before the flags: a SEAMSTRESS_LOG that does not parse is ignored.
    let env =
        env.filter(|e| !e.trim().is_empty() && tracing_subscriber::EnvFilter::try_new(e).is_ok());
    if cli.verbose == 0 && !quiet {
        if let Some(env) = env {
            return env;
        }
    }
    let flag = if quiet {
        0
    } else {
        (default + usize::from(cli.verbose)).min(LEVELS.len() - 1)
    };
    let mut overall = flag;
    let mut targeted = Vec::new();
    for directive in env.iter().flat_map(|e| e.split(',')).map(str::trim) {
        match LEVELS
            .iter()
            .position(|l| directive.eq_ignore_ascii_case(l))
        {
            Some(level) if !quiet => overall = overall.max(level),
            Some(_) => {}
            None if !directive.is_empty() => targeted.push(directive),
            None => {}
        }
    }
    std::iter::once(LEVELS[overall])
        .chain(targeted)
        .collect::<Vec<_>>()
        .join(",")
}

fn init_logging(format: LogFormat, filter: &str) {
    let filter = tracing_subscriber::EnvFilter::new(filter);
    // Colours only for a person at a terminal, never into files or pipes.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(ansi)
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Text => builder.init(),
        LogFormat::Json => builder.json().init(),
    }
}

enum Failure {
    /// Exit status 2: the input is at fault; one line that names it.
    BadInput(String),
    /// Exit status 1: something failed that the input cannot fix.
    Internal(anyhow::Error),
}

impl From<anyhow::Error> for Failure {
    fn from(e: anyhow::Error) -> Self {
        Failure::Internal(e)
    }
}

/// The options, checked, and the models of the inputs, with `--out`
/// checked before any work so that an unusable one fails at once.
fn prepare(
    batch: &BatchArgs,
    flags: &OptionArgs,
) -> Result<(ProcessOptions, Vec<BatchModel>), Failure> {
    let options = flags.options();
    options
        .validate()
        .map_err(|e| Failure::BadInput(format!("--{}", e.to_string().replace('_', "-"))))?;
    if batch.out.exists() && !batch.out.is_dir() {
        return Err(Failure::BadInput(format!(
            "--out {}: exists and is not a folder",
            batch.out.display()
        )));
    }
    let models = batch::discover(&batch.inputs).map_err(|e| Failure::BadInput(e.to_string()))?;
    Ok((options, models))
}

fn process(args: &ProcessArgs) -> Result<(), Failure> {
    let (options, models) = prepare(&args.batch, &args.options)?;
    let settings = JobSettings {
        process: options,
        load: LoadOptions {
            max_texture_size: args.max_texture_size,
            ..LoadOptions::default()
        },
        limits: Limits {
            // As `serve` shares it among its workers: every model of a
            // batch may be at its peak at once.
            max_memory: args.max_memory.unwrap_or_else(|| {
                budget::memory_per_job(usize::from(args.batch.jobs).min(models.len()))
            }),
        },
    };
    match &models[..] {
        [one] if one.out.as_os_str().is_empty() => {
            let model = ModelFiles::read(&one.path)?;
            let written = run_model(&model, &one.path, &args.batch.out, &settings, &mut NoSink)?;
            print_model(&written, &args.batch)
        }
        _ => run_batch(&args.batch, &models, &settings),
    }
}

/// One model's outcome on standard output, as `--json` and `-q` ask.
fn print_model(written: &Written, args: &BatchArgs) -> Result<(), Failure> {
    let text = match args.output() {
        Output::Quiet => return Ok(()),
        Output::Json => written.report.clone(),
        Output::Summary => {
            let names: Vec<String> = written.files.iter().map(|(n, _)| n.clone()).collect();
            pipeline::summary::model_summary(&written.report, &args.out, &names)
                .context("the report cannot be summarised")?
                .into_bytes()
        }
    };
    std::io::stdout()
        .write_all(&text)
        .context("cannot write to standard output")?;
    Ok(())
}

fn submit(args: &SubmitArgs) -> Result<(), Failure> {
    let (options, models) = prepare(&args.batch, &args.options)?;
    let params = RemoteParams {
        server: args.server.clone(),
        token: args.token.clone(),
        retry: RetryParams {
            give_up_after: args.give_up_after,
            ..RetryParams::default()
        },
        poll: std::time::Duration::from_millis(250),
    };
    let remote = Remote::new(params, options)?;
    run_batch(&args.batch, &models, &remote)
}

impl From<RunError> for Failure {
    fn from(e: RunError) -> Self {
        match e {
            RunError::BadInput(m) => Failure::BadInput(m),
            RunError::Internal(m) => Failure::Internal(anyhow::anyhow!(m)),
        }
    }
}

/// A batch: a progress bar on a terminal (plain lines otherwise), the
/// summary at the end; exit status 1 if a model failed inside, else 2 if
/// one was bad input.
fn run_batch(args: &BatchArgs, models: &[BatchModel], runner: &dyn Runner) -> Result<(), Failure> {
    let opts = BatchOptions {
        out: args.out.clone(),
        jobs: usize::from(args.jobs),
        keep_going: args.keep_going,
        force: args.force,
    };
    let output = args.output();
    let progress = BatchProgress::new(models.len(), output == Output::Quiet);
    let summary = batch::run::run_batch(models, runner, &opts, &progress);
    progress.bar.finish_and_clear();
    let json = serde_json::to_vec_pretty(&summary).context("summary")?;
    match output {
        Output::Quiet => eprint!("{}", error_lines(&summary)),
        Output::Summary => eprint!("{}", summary.text()),
        Output::Json => {
            eprint!("{}", summary.text());
            let mut out = std::io::stdout();
            out.write_all(&json)
                .and_then(|()| out.write_all(b"\n"))
                .context("cannot write to standard output")?;
        }
    }
    if let Some(path) = &args.summary {
        std::fs::write(path, json)
            .with_context(|| format!("cannot write the summary to {}", path.display()))?;
    }
    let of_models = |n: usize| format!("{n} of {}", count(summary.models, "model"));
    if summary.failed > 0 {
        return Err(Failure::Internal(anyhow::anyhow!(
            "{} failed",
            of_models(summary.failed)
        )));
    }
    if summary.bad_input > 0 {
        let verb = if summary.bad_input == 1 { "is" } else { "are" };
        return Err(Failure::BadInput(format!(
            "{} {verb} bad input",
            of_models(summary.bad_input)
        )));
    }
    Ok(())
}

/// The models that did not succeed, a line each: all `-q` prints of a batch.
fn error_lines(summary: &batch::Summary) -> String {
    let mut lines = String::new();
    for o in &summary.outcomes {
        if let Some(e) = &o.error {
            lines.push_str(&format!("{} {}: {e}\n", o.status, o.model));
        }
    }
    lines
}

/// A batch's progress: a bar with models done, the current stage and the
/// ETA when standard error is a terminal, a line per model otherwise.
struct BatchProgress {
    bar: indicatif::ProgressBar,
    /// A line per finished model (standard error is no terminal).
    lines: bool,
    total: usize,
    done: std::sync::atomic::AtomicUsize,
}

impl BatchProgress {
    /// `quiet`: neither bar nor lines.
    fn new(total: usize, quiet: bool) -> Self {
        let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
        let bar = if terminal && !quiet {
            let bar = indicatif::ProgressBar::new(total as u64);
            let noun = if total == 1 { "model" } else { "models" };
            bar.set_style(
                indicatif::ProgressStyle::with_template(&format!(
                    "{{bar:30}} {{pos}}/{{len}} {noun}, ETA {{eta}} {{wide_msg}}"
                ))
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
            bar
        } else {
            indicatif::ProgressBar::hidden()
        };
        BatchProgress {
            bar,
            lines: !terminal && !quiet,
            total,
            done: std::sync::atomic::AtomicUsize::new(0),
        }
    }
}

impl batch::run::Observer for BatchProgress {
    fn started(&self, _: usize, model: &BatchModel) {
        self.bar.set_message(model.path.display().to_string());
    }

    fn progress(&self, _: usize, model: &BatchModel, at: &pipeline::Progress<'_>) {
        let texture = at
            .texture
            .map(|(i, n)| format!(" texture {}/{n}", i + 1))
            .unwrap_or_default();
        self.bar
            .set_message(format!("{}: {}{texture}", model.path.display(), at.stage));
    }

    fn finished(&self, _: usize, outcome: &batch::ModelOutcome) {
        self.bar.inc(1);
        if self.lines {
            let n = self.done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            eprintln!(
                "[{n}/{}] {} {} ({:.1} s)",
                self.total, outcome.status, outcome.model, outcome.seconds
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flag_defaults_are_the_librarys() {
        let cli = Cli::try_parse_from(["seamstress", "process", "m.glb", "--out", "o"]).unwrap();
        let Command::Process(args) = cli.command else {
            unreachable!("parsed as process")
        };
        assert_eq!(args.options.options(), ProcessOptions::default());
    }

    #[test]
    fn flags_raise_and_lower_the_log_level_over_seamstress_log() {
        let filter = |argv: &[&str], env: Option<&str>| {
            let cli = Cli::try_parse_from(argv).unwrap();
            log_filter(&cli, env.map(str::to_string))
        };
        let process = ["seamstress", "process", "m.glb", "-o", "o"];
        fn with<'a>(flags: &[&'a str]) -> Vec<&'a str> {
            [&["seamstress", "process", "m.glb", "-o", "o"][..], flags].concat()
        }
        assert_eq!(filter(&process, None), "warn");
        assert_eq!(filter(&with(&["-v"]), None), "info");
        assert_eq!(filter(&with(&["-vv"]), None), "debug");
        assert_eq!(filter(&with(&["-q"]), None), "error");
        assert_eq!(filter(&["seamstress", "-v", "serve"], None), "debug");
        // SEAMSTRESS_LOG alone decides without a flag; -v raises its
        // overall level and keeps its targets; one that does not parse is
        // ignored, as it always was.
        let env = Some("tower_http=debug,error");
        assert_eq!(filter(&process, env), "tower_http=debug,error");
        assert_eq!(filter(&with(&["-v"]), env), "info,tower_http=debug");
        assert_eq!(filter(&with(&["-v"]), Some("trace")), "trace");
        assert_eq!(filter(&process, Some("=nonsense=")), "warn");
    }

    #[test]
    fn mips_are_on_unless_no_mips_comes_last() {
        let mips = |flags: &[&str]| {
            let argv = ["seamstress", "process", "m.glb", "--out", "o"];
            let cli = Cli::try_parse_from(argv.iter().chain(flags)).unwrap();
            let Command::Process(args) = cli.command else {
                unreachable!("parsed as process")
            };
            args.options.options().mips
        };
        assert!(mips(&[]));
        assert!(mips(&["--mips"]));
        assert!(!mips(&["--no-mips"]));
        assert!(!mips(&["--mips", "--no-mips"]));
        assert!(mips(&["--no-mips", "--mips"]));
    }
}
