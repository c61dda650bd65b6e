//! The `seamstress` command line: `process` runs the engine on one model.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};

use seamstress::bc1::Level;
use seamstress::budget::{self, Limits};
use seamstress::model::rewrite::referenced_files;
use seamstress::model::{DirResolver, LoadOptions};
use seamstress::pipeline::job::REPORT_NAME;
use seamstress::pipeline::{
    self, AlphaOption, Format, JobError, JobInput, JobSettings, Method, NoSink, ProcessOptions,
    Resize, Target, DEFAULT_SEAM_TOLERANCE, DEFAULT_SEAM_WEIGHT,
};
use seamstress::seam::erase::Mode;

#[derive(Parser)]
#[command(
    name = "seamstress",
    version,
    about = "Seam erasure for glTF textures",
    after_help = "Logs go to standard error: warnings and errors for `process`, each request \
                  and job for `serve`. SEAMSTRESS_LOG sets what is logged (e.g. \
                  SEAMSTRESS_LOG=debug, or seamstress=debug,tower_http=info)."
)]
struct Cli {
    /// Log format on standard error.
    #[arg(long, global = true, value_enum, default_value = "text")]
    log_format: LogFormat,
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
    /// Erase the seams of every colour texture of a model and encode it to BC1.
    Process(ProcessArgs),
    /// Run the HTTP service: a durable job queue and a worker pool over the engine.
    Serve(Box<seamstress::service::ServeArgs>),
    /// One job of a server's worker, in a process of its own.
    #[command(hide = true)]
    RunJob {
        /// The job's scratch folder, as the worker prepared it.
        dir: PathBuf,
    },
}

#[derive(clap::Args)]
struct ProcessArgs {
    /// A .glb, or a .gltf with its files beside it.
    input: PathBuf,
    /// Folder for the outputs (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// How far from the seams texels may change: local, or global (changes
    /// spread over the charts, for sides painted with a colour offset).
    #[arg(long, value_parser = word::<Mode>, default_value = "local")]
    mode: Mode,
    /// How the two sides of a seam are made to agree: erase (along the whole
    /// seam, integrated exactly) or masking (at sampled points).
    #[arg(long, value_parser = word::<Method>, default_value = "erase")]
    method: Method,
    /// The files written for each texture: dds (a BC1 DDS and the erased
    /// PNG) or png (the erased PNG only).
    #[arg(long, value_parser = word::<Format>, default_value = "dds")]
    format: Format,
    /// BC1 encoder effort: fast, default or best.
    #[arg(long, value_parser = word::<Level>, default_value = "default")]
    bc1_level: Level,
    /// Store the regular BC1 encoding instead of the seam-aware one.
    #[arg(long)]
    no_seam_aware: bool,
    /// α: how much seam agreement weighs against fidelity in seam-aware BC1.
    #[arg(long, default_value_t = DEFAULT_SEAM_WEIGHT)]
    seam_weight: f64,
    /// Write the full mip chain, each level erased and encoded on its own.
    #[arg(long)]
    mips: bool,
    /// Write the DX10 header (BC1_UNORM, or BC1_UNORM_SRGB for colour textures).
    #[arg(long)]
    dx10: bool,
    /// Refuse textures wider or taller than this, before decoding them.
    #[arg(long, default_value_t = 16384)]
    max_texture_size: u32,
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
    /// Refuse (exit 2) a model whose estimated peak memory is above this
    /// (512M, 4G, ...), before decoding it. Default: the memory this
    /// process may use (the machine's, or less under `ulimit -v` or a
    /// container's limit).
    #[arg(long, value_name = "BYTES", value_parser = budget::parse_bytes)]
    max_memory: Option<u64>,
}

fn main() -> ExitCode {
    seamstress::heap::retain_freed_memory();
    let cli = Cli::parse();
    // A one-shot command stays quiet; a service logs every request and job.
    let default_level = match cli.command {
        Command::Process(_) | Command::RunJob { .. } => "warn",
        Command::Serve(_) => "info",
    };
    let format = cli.log_format;
    init_logging(format, default_level);
    match cli.command {
        Command::Process(args) => match process(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(Failure::BadInput(msg)) => fail(format, 2, &msg),
            Err(Failure::Internal(e)) => fail(format, 1, &format!("{e:#}")),
        },
        Command::RunJob { dir } => match seamstress::service::run_job(&dir) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => fail(format, 1, &format!("{}: {e}", dir.display())),
        },
        Command::Serve(args) => match seamstress::service::serve(*args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => fail(format, if e.is_usage() { 2 } else { 1 }, &e.to_string()),
        },
    }
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

fn init_logging(format: LogFormat, default_level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("SEAMSTRESS_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
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

fn process(args: &ProcessArgs) -> Result<(), Failure> {
    if !(args.seam_weight.is_finite() && args.seam_weight >= 0.0) {
        return Err(Failure::BadInput(format!(
            "--seam-weight must be a non-negative number, not {}",
            args.seam_weight
        )));
    }
    if !(args.seam_tolerance.is_finite() && args.seam_tolerance >= 0.0) {
        return Err(Failure::BadInput(format!(
            "--seam-tolerance must be a non-negative number of levels, not {}",
            args.seam_tolerance
        )));
    }
    // Before the work, so that an unusable --out fails at once.
    if args.out.exists() && !args.out.is_dir() {
        return Err(Failure::BadInput(format!(
            "--out {}: exists and is not a folder",
            args.out.display()
        )));
    }
    // Every file is written into a folder of this run's own, then renamed
    // into place: runs sharing an --out never see each other's halves.
    let mut staging = Staging::create(&args.out).map_err(|e| {
        Failure::BadInput(format!(
            "--out {}: cannot write there: {e}",
            args.out.display()
        ))
    })?;

    let load_opts = LoadOptions {
        max_texture_size: args.max_texture_size,
        extra_maps: args.extra_maps,
        ..LoadOptions::default()
    };
    let opts = ProcessOptions {
        mode: args.mode,
        method: args.method,
        format: args.format,
        bc1_level: args.bc1_level,
        seam_aware: !args.no_seam_aware,
        seam_weight: args.seam_weight,
        mips: args.mips,
        dx10: args.dx10,
        seam_tolerance: args.seam_tolerance,
        erase_all: args.erase_all,
        pictures: args.pictures,
        decoder: args.decoder,
        resize: args.resize,
        alpha: args.alpha,
    };
    let limits = Limits {
        max_memory: args.max_memory.unwrap_or_else(budget::usable_memory),
    };
    let name = args.input.display().to_string();
    let main = std::fs::read(&args.input).map_err(|e| {
        let message = format!("{name}: cannot read it: {e}");
        match e.kind() {
            std::io::ErrorKind::NotFound | std::io::ErrorKind::IsADirectory => {
                Failure::BadInput(message)
            }
            _ => Failure::Internal(anyhow::anyhow!(message)),
        }
    })?;
    let dir = match args.input.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let files = DirResolver::new(dir).with_context(|| format!("cannot open {}", dir.display()))?;
    let input = JobInput {
        name: &name,
        main: &main,
        files: &files,
    };
    let settings = JobSettings {
        process: opts,
        load: load_opts,
        limits,
    };
    let output = pipeline::run_job(&input, &settings, &mut NoSink).map_err(|e| match e {
        JobError::BadInput(m) | JobError::TooLarge(m) => Failure::BadInput(m),
        e => Failure::Internal(anyhow::anyhow!("processing failed: {e}")),
    })?;

    // Written into the model's own folder, the rewritten model and its
    // files would replace the originals: those are left as they are.
    let same_folder = match (args.out.canonicalize(), dir.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    let mut originals = referenced_files(&main).unwrap_or_default();
    originals.extend(
        args.input
            .file_name()
            .map(|n| n.to_string_lossy().into_owned()),
    );
    for f in &output.files {
        if same_folder && originals.contains(&f.name) {
            tracing::warn!(file = %f.name, "not written: --out is the model's folder and holds it");
            continue;
        }
        staging.write(&f.name, &f.bytes)?;
    }
    staging.publish()?;
    let report = output
        .files
        .iter()
        .find(|f| f.name == REPORT_NAME)
        .map_or(&[][..], |f| &f.bytes[..]);
    std::io::stdout()
        .write_all(report)
        .context("cannot write to standard output")?;
    Ok(())
}

/// A run's private folder inside `--out` (removed when dropped): files are
/// written and synced there, then renamed into `--out` one by one, so a
/// reader never sees half a file and concurrent runs never clash.
struct Staging {
    out: PathBuf,
    dir: PathBuf,
    names: Vec<String>,
}

impl Staging {
    fn create(out: &Path) -> std::io::Result<Staging> {
        std::fs::create_dir_all(out)?;
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let dir = out.join(format!(".seamstress-{}-{nanos:08x}", std::process::id()));
        std::fs::create_dir(&dir)?;
        Ok(Staging {
            out: out.to_path_buf(),
            dir,
            names: Vec::new(),
        })
    }

    fn write(&mut self, name: &str, bytes: &[u8]) -> anyhow::Result<()> {
        let path = self.dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        let mut f = std::fs::File::create(&path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        f.write_all(bytes)
            .and_then(|_| f.sync_all())
            .with_context(|| format!("cannot write {}", path.display()))?;
        self.names.push(name.to_string());
        Ok(())
    }

    fn publish(&self) -> anyhow::Result<()> {
        for name in &self.names {
            let to = self.out.join(name);
            if let Some(parent) = to.parent() {
                std::fs::create_dir_all(parent)
                    .with_context(|| format!("cannot create {}", parent.display()))?;
            }
            std::fs::rename(self.dir.join(name), &to)
                .with_context(|| format!("cannot write {}", to.display()))?;
        }
        Ok(())
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
