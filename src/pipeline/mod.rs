//! The pipeline: [`run_job`] (in `job.rs`) takes a model file and its files
//! to every output, the rewritten model included; [`run`] takes a loaded
//! model through each texture's stages to its files and report.
//!
//! model → seams → erase → encode (regular, then seam-aware) → DDS.
//!
//! The pipeline never touches the file system for its outputs: it returns
//! named byte buffers, which the CLI writes into a folder and the service
//! into its file store, so both serve identical bytes.

pub mod alpha;
mod bc7_level;
mod figures;
mod file;
pub mod job;
mod level;
pub mod lod;
mod measure;
pub mod options;
mod progress;
pub mod summary;
mod texture;
mod view_files;

pub use alpha::{AlphaFormat, AlphaOption, AlphaReport};
pub use job::{admit, run_job, JobError, JobInput, JobOutput, JobSettings, JobTimings};
pub use options::{
    Container, Format, Method, OptionPatch, OptionsError, ProcessOptions, DEFAULT_SEAM_TOLERANCE,
    DEFAULT_SEAM_WEIGHT,
};
pub use progress::{NoSink, Progress, Sink, Stop};
use texture::{erase_texture, finish_texture, Erased};
pub use texture::{BesideTimings, Timings};

use std::collections::BTreeMap;

use serde::Serialize;

pub use crate::bc1::Target;
use crate::model::{Model, Skipped};
pub use crate::resize::{Resize, SizeChange};
use crate::seam::charts::HARM_PSNR_DB;
use crate::seam::erase::{EraseError, EraseStats};
use crate::seam::system::SolveError;

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("texture {name}: {source}")]
    Erase {
        name: String,
        #[source]
        source: EraseError,
    },
    #[error("texture {name}: {source}")]
    Solve {
        name: String,
        #[source]
        source: SolveError,
    },
    #[error("texture {name}: cannot encode: {message}")]
    Encode { name: String, message: String },
    #[error("stopped: {0:?}")]
    Stopped(Stop),
}

impl PipelineError {
    /// A texture's file or encoding could not be made.
    fn encode(name: &str, e: impl std::fmt::Display) -> Self {
        PipelineError::Encode {
            name: name.to_string(),
            message: e.to_string(),
        }
    }
}

/// Seam and fidelity figures for one version of a texture.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Metrics {
    /// Length-weighted RMS seam difference over every seam, in 8-bit levels
    /// (`null` without seams).
    pub seam_rms: Option<f64>,
    /// The same over the seams that were closed (`null` when none was).
    pub seam_rms_closed: Option<f64>,
    /// RGB PSNR over inside texels against the input (`null` for the input itself, or if identical).
    pub psnr: Option<f64>,
    /// The lowest PSNR of any UV chart against the input (`null` for the
    /// input, or when no chart changed): one repainted chart shows here
    /// when the texture's PSNR averages it away.
    pub worst_chart_psnr: Option<f64>,
    /// How many UV charts fall under 30 dB against the input.
    pub charts_under_30db: Option<usize>,
    /// For BC1 encodings: the figures as each GPU decoder rounds the
    /// palette (the fields above are the `ideal` decoder's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decoders: Option<BTreeMap<&'static str, DecoderMetrics>>,
}

/// A BC1 encoding's figures under one decoder.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct DecoderMetrics {
    pub seam_rms: Option<f64>,
    pub seam_rms_closed: Option<f64>,
    /// Against the input, as [`Metrics::psnr`].
    pub psnr: Option<f64>,
    /// Against the erased texture, the one BC1 was given: the encoding's own cost.
    pub encoding_psnr: Option<f64>,
}

/// How many seam edges, and what share of the seams' 3D length.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SeamShare {
    pub edges: usize,
    pub length_share: f64,
}

/// What was done with the seams: which were closed and which left as painted.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SeamSummary {
    /// The jump (8-bit levels) up to which seams were closed; `null` with
    /// `erase_all`, which closes every seam.
    pub tolerance: Option<f64>,
    pub closed: SeamShare,
    pub left: SeamShare,
    /// Of the seams left, those whose sides differ by more than 16 levels but
    /// within the tolerance: left because closing them repainted a chart
    /// under 30 dB.
    pub spared: usize,
    /// Gutter texels along the seams left, filled from their own chart.
    pub padded_texels: usize,
    /// UV charts the erasure still changed under 30 dB, after sparing every
    /// seam that touches them; empty when none.
    pub repainted: Vec<ChartHarm>,
    /// For an erased alpha judged apart from the colour (its sides painted
    /// apart where the colour's agree, or the other way round): the same
    /// for alpha. Absent where alpha follows the colour's seams.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alpha: Option<AlphaSeamSummary>,
}

/// [`SeamSummary`]'s figures for alpha judged on its own.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AlphaSeamSummary {
    pub closed: SeamShare,
    pub left: SeamShare,
    pub spared: usize,
    pub padded_texels: usize,
    pub repainted: Vec<ChartHarm>,
}

/// A UV chart the erasure changed under [`HARM_PSNR_DB`]: which, how much,
/// and why sparing seams did not keep it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ChartHarm {
    /// The chart's number, in the order its first triangle comes in the model.
    pub chart: u32,
    pub texels: usize,
    /// PSNR of the chart's texels against the input, in dB.
    pub psnr: f64,
    /// The chart's UV bounds, to find it in the atlas.
    pub uv_min: [f64; 2],
    pub uv_max: [f64; 2],
    pub cause: HarmCause,
}

/// Why a chart was repainted although the job spares seams to keep charts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum HarmCause {
    /// `--erase-all` closes every seam and spares none.
    EraseAll,
    /// Global mode spreads the colour offset between charts over whole
    /// charts, which is what it is for.
    GlobalOffsets,
    /// Every seam touching the chart was left apart; the erasure of the
    /// seams near it, which spreads beyond their footprints, still reached it.
    NearbySeams,
}

impl HarmCause {
    fn of(opts: &ProcessOptions) -> HarmCause {
        if opts.erase_all {
            HarmCause::EraseAll
        } else if opts.mode == crate::seam::erase::Mode::Global {
            HarmCause::GlobalOffsets
        } else {
            HarmCause::NearbySeams
        }
    }

    /// The reason, as a warning gives it.
    fn says(self) -> &'static str {
        match self {
            HarmCause::EraseAll => "--erase-all closes every seam, whatever it costs the charts",
            HarmCause::GlobalOffsets => {
                "global mode spreads the colour offsets between charts over whole charts"
            }
            HarmCause::NearbySeams => {
                "every seam touching it was left apart, and the erasure of the seams near it \
                 still reaches it"
            }
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Files {
    pub dds: Option<String>,
    /// `<name>.ktx2`, with `container` `ktx2` (then `dds` is null).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ktx2: Option<String>,
    pub erased: String,
    /// `<name>.seams.png`, when pictures were asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seams: Option<String>,
    /// `<name>.charts.png`, with pictures: each texel's chart, for a
    /// renderer that discards the filter taps outside a fragment's chart.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub charts: Option<String>,
    /// `<name>.edges.json`, with pictures: every seam edge with its verdict
    /// and residuals, for the view page to find and draw the seams.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub edges: Option<String>,
    /// `<name>.regular.dds`, with `keep_regular`: level 0's regular BC1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub regular: Option<String>,
    /// `<name>.input.png`, with `keep_regular`: the input texture as it
    /// was processed (after `resize`), for the view page to compare with.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub input: Option<String>,
}

#[derive(Clone, Debug, Serialize)]
pub struct TextureReport {
    pub image: usize,
    pub name: String,
    /// The size processed and written (after `resize`).
    pub width: usize,
    pub height: usize,
    /// How the texture was brought to that size, when it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resize: Option<SizeChange>,
    /// What became of the alpha channel, when the texture has one in use.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alpha: Option<AlphaReport>,
    pub seam_edges: usize,
    pub seams: SeamSummary,
    pub input: Metrics,
    pub erased: Metrics,
    /// The regular BC1 encoding of the erased texture (mip level 0).
    pub bc1: Option<Metrics>,
    /// What the DDS holds (mip level 0), when seam-aware encoding is on.
    pub bc1_seam_aware: Option<Metrics>,
    /// The decoders the DDS's seam-aware encoding was made for.
    pub bc1_target: Option<Target>,
    /// With `format` `bc7`: the regular BC7 encoding of the erased texture
    /// (mip level 0). BC7 decodes exactly, the same on every GPU.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bc7: Option<Metrics>,
    /// What the file holds (mip level 0), when seam-aware encoding is on.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bc7_seam_aware: Option<Metrics>,
    pub files: Files,
    pub timings_ms: Timings,
    pub solver: EraseStats,
    /// The closed seam edges, each as its two half-edges' UV endpoints:
    /// what the levels of detail measure their own seams against.
    #[serde(skip)]
    pub closed_seams: Vec<[[[f64; 2]; 2]; 2]>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub input: String,
    /// Every option the job ran with.
    pub options: ProcessOptions,
    pub textures: Vec<TextureReport>,
    pub skipped: Vec<Skipped>,
    /// What an unattended run should not miss: a UV chart repainted below
    /// 30 dB, say. Each line names its texture.
    pub warnings: Vec<String>,
    /// With `lod`: the full mesh (level 0) and each level of detail,
    /// measured on the erased texture and the DDS.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub lods: Vec<crate::lod::LodLevel>,
}

/// A named output file.
#[derive(Clone, Debug)]
pub struct OutputFile {
    pub name: String,
    pub bytes: Vec<u8>,
}

pub struct Output {
    pub files: Vec<OutputFile>,
    pub report: Report,
    /// The textures skipped because the seam solver could not take them
    /// through, each as the warning that names it.
    pub unsolvable: Vec<String>,
}

/// Runs the seam engine over every texture of `model`.
///
/// `input_name` is what the report calls the model; `load_ms` is how long
/// loading took (the caller loads, so that it alone touches the file system).
pub fn run(
    model: &Model,
    input_name: &str,
    load_ms: u64,
    opts: &ProcessOptions,
) -> Result<Output, PipelineError> {
    run_reporting(model, input_name, load_ms, opts, &mut NoSink)
}

/// [`run`], telling `sink` before each texture (textures span fractions
/// 0.1 to 0.9 of the job) and stopping when it says so.
pub fn run_reporting(
    model: &Model,
    input_name: &str,
    load_ms: u64,
    opts: &ProcessOptions,
    sink: &mut dyn Sink,
) -> Result<Output, PipelineError> {
    let mut files = Vec::new();
    let mut textures = Vec::new();
    let mut warnings = Vec::new();
    let mut skipped = model.skipped.clone();
    let mut unsolved = Vec::new();
    let total = model.bindings.len();
    // A texture's outcome, under the number of its image.
    type Done = (
        usize,
        Result<(TextureReport, Vec<OutputFile>), PipelineError>,
    );
    let mut finish = |done: Option<Done>| {
        match done {
            None => {}
            Some((_, Ok((report, mut out)))) => {
                files.append(&mut out);
                warnings.extend(harm_warnings(&report, opts));
                warnings.extend(alpha_warning(&report));
                textures.push(report);
            }
            Some((image, Err(e))) => {
                let (skip, warning) = unsolvable(image, e)?;
                skipped.push(skip);
                unsolved.push(warning.clone());
                warnings.push(warning);
            }
        }
        Ok::<_, PipelineError>(())
    };
    // Each texture's erasure runs beside the encoding of the one before:
    // the two stages leave each other's single-thread stretches a core,
    // and only one solver's working set, the job's largest, is held at once.
    let mut last: Option<Erased<'_>> = None;
    for (k, binding) in model.bindings.iter().enumerate() {
        sink.progress(&Progress {
            stage: "process",
            texture: Some((k, total)),
            fraction: 0.1 + 0.8 * k as f64 / total as f64,
        })
        .map_err(PipelineError::Stopped)?;
        let (erased, done) = rayon::join(
            || erase_texture(binding, opts),
            || {
                last.take()
                    .map(|e| (e.image(), finish_texture(e, load_ms, opts)))
            },
        );
        finish(done)?;
        last = match erased {
            Ok(e) => Some(e),
            Err(e) => {
                finish(Some((binding.image, Err(e))))?;
                None
            }
        };
    }
    finish(last.map(|e| (e.image(), finish_texture(e, load_ms, opts))))?;
    let report = Report {
        input: input_name.to_string(),
        options: *opts,
        textures,
        skipped,
        warnings,
        lods: Vec::new(),
    };
    Ok(Output {
        files,
        report,
        unsolvable: unsolved,
    })
}

/// A texture whose seam system the solver cannot take through (one the
/// loader accepted, but whose UVs make a degenerate system, such as
/// TEXCOORD_0 reading the normals): skipped with a warning, as a texture
/// the loader does not take is, so that its image is left as it was and
/// the job's other textures are still made. Any other error is the job's.
fn unsolvable(image: usize, e: PipelineError) -> Result<(Skipped, String), PipelineError> {
    let (name, why) = match &e {
        PipelineError::Erase { name, source } => (name, source.to_string()),
        PipelineError::Solve { name, source } => (name, source.to_string()),
        _ => return Err(e),
    };
    tracing::warn!(
        texture = %name,
        image,
        error = %why,
        "texture skipped: the solver cannot proceed"
    );
    Ok((
        Skipped {
            image: Some(image),
            mesh: None,
            primitive: None,
            reason: format!("the seam solver cannot proceed: {why}"),
        },
        format!(
            "texture {name}: skipped, the seam solver cannot proceed ({why}); \
             its image is left as it was"
        ),
    ))
}

/// Below this PSNR against the input, over the texels inside the UV
/// charts, erasure has changed a texture (or its alpha) more than a few
/// corrections near the seams do: real art whose seams agree keeps 44–49 dB
/// (Fox, Duck, the controller), so a figure under 40 is many corrections
/// adding up, or sides forced together that were painted apart.
const CHANGE_PSNR_DB: f64 = 40.0;

/// Every change beyond what the job promises, one line each with the
/// texture's name and figure: charts repainted below [`HARM_PSNR_DB`],
/// and the inside texels or the alpha changed below [`CHANGE_PSNR_DB`].
fn harm_warnings(t: &TextureReport, opts: &ProcessOptions) -> Vec<String> {
    let why = if opts.erase_all {
        "; --erase-all closes seams whose sides are painted apart"
    } else {
        ""
    };
    let dds = t.bc1_seam_aware.as_ref();
    let versions = [
        (
            "erased texture",
            t.erased.charts_under_30db,
            t.erased.worst_chart_psnr,
        ),
        (
            "DDS",
            dds.and_then(|m| m.charts_under_30db),
            dds.and_then(|m| m.worst_chart_psnr),
        ),
    ];
    let mut out: Vec<String> = repainted_warning(t, "", &t.seams.repainted)
        .or_else(|| chart_warning(t, "", versions, why))
        .into_iter()
        .collect();
    if let Some(psnr) = t.erased.psnr.filter(|&p| p < CHANGE_PSNR_DB) {
        tracing::warn!(texture = %t.name, psnr, "texture changed below 40 dB");
        out.push(format!(
            "texture {}: erasure changed the texels inside its UV charts to {psnr:.1} dB \
             against the input (under {CHANGE_PSNR_DB} dB){why}",
            t.name
        ));
    }
    if let Some(a) = &t.alpha {
        // The DDS's alpha as the ideal decoder reads it.
        let dds = a.dds.as_ref().and_then(|d| d.get("ideal"));
        let versions = [
            (
                "erased texture",
                a.erased.charts_under_30db,
                a.erased.worst_chart_psnr,
            ),
            (
                "DDS",
                dds.and_then(|m| m.charts_under_30db),
                dds.and_then(|m| m.worst_chart_psnr),
            ),
        ];
        let named = t.seams.alpha.as_ref().map_or(&[][..], |a| &a.repainted[..]);
        out.extend(
            repainted_warning(t, "the alpha of ", named)
                .or_else(|| chart_warning(t, "the alpha of ", versions, why)),
        );
    }
    let alpha = t.alpha.as_ref().filter(|a| a.erased_seams);
    if let Some(psnr) = alpha
        .and_then(|a| a.erased.psnr)
        .filter(|&p| p < CHANGE_PSNR_DB)
    {
        tracing::warn!(texture = %t.name, psnr, "alpha changed below 40 dB");
        out.push(format!(
            "texture {}: erasure changed its alpha inside the UV charts to {psnr:.1} dB \
             against the input (under {CHANGE_PSNR_DB} dB){why}",
            t.name
        ));
    }
    out
}

/// The first of `versions` (name, charts under [`HARM_PSNR_DB`], worst
/// chart PSNR) with a chart under it, as a warning; `of` says which
/// channels (`""` for colour, `"the alpha of "`).
fn chart_warning(
    t: &TextureReport,
    of: &str,
    versions: [(&str, Option<usize>, Option<f64>); 2],
    why: &str,
) -> Option<String> {
    let (what, charts, psnr) = versions
        .into_iter()
        .find_map(|(what, n, worst)| Some((what, n.filter(|&n| n > 0)?, worst?)))?;
    tracing::warn!(
        texture = %t.name,
        channels = if of.is_empty() { "colour" } else { "alpha" },
        version = what,
        charts_under_30db = charts,
        worst_chart_psnr = psnr,
        "UV charts changed below 30 dB"
    );
    Some(format!(
        "texture {}: {of}{charts} UV chart(s) under {HARM_PSNR_DB} dB in the {what} \
         (worst {psnr:.1} dB){why}",
        t.name
    ))
}

/// At most this many charts are named in one warning; the report's
/// `seams.repainted` lists them all.
const NAMED_CHARTS: usize = 4;

/// The charts the erasure repainted, by name, figure and cause, as one
/// warning; `of` says which channels (`""` for colour, `"the alpha of "`).
fn repainted_warning(t: &TextureReport, of: &str, charts: &[ChartHarm]) -> Option<String> {
    let worst = charts.first()?;
    for c in charts {
        tracing::warn!(
            texture = %t.name,
            channels = if of.is_empty() { "colour" } else { "alpha" },
            chart = c.chart,
            texels = c.texels,
            psnr = c.psnr,
            cause = ?c.cause,
            "UV chart repainted below 30 dB"
        );
    }
    let named: Vec<String> = charts
        .iter()
        .take(NAMED_CHARTS)
        .map(|c| {
            format!(
                "chart {} ({} texels, UV {:.3}-{:.3} x {:.3}-{:.3}) at {:.1} dB",
                c.chart, c.texels, c.uv_min[0], c.uv_max[0], c.uv_min[1], c.uv_max[1], c.psnr
            )
        })
        .collect();
    let more = match charts.len().saturating_sub(NAMED_CHARTS) {
        0 => String::new(),
        n => format!(" and {n} more (seams.repainted lists them)"),
    };
    Some(format!(
        "texture {}: erasure changed {of}{} UV chart(s) under {HARM_PSNR_DB} dB against the \
         input: {}{more}; {}",
        t.name,
        charts.len(),
        named.join(", "),
        worst.cause.says()
    ))
}

/// The warning for alpha in use that the DDS does not keep (`--alpha drop`).
fn alpha_warning(t: &TextureReport) -> Option<String> {
    let a = t
        .alpha
        .as_ref()
        .filter(|a| a.format == AlphaFormat::Dropped)?;
    tracing::warn!(texture = %t.name, material = ?a.material, "alpha dropped");
    Some(format!(
        "texture {}: its alpha is in use but the DDS is opaque BC1 (--alpha drop)",
        t.name
    ))
}
