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
pub mod job;
pub mod options;
mod progress;

pub use alpha::{AlphaFormat, AlphaOption, AlphaReport};
use alpha::{AlphaMetrics, AlphaPlan};
pub use job::{admit, run_job, JobError, JobInput, JobOutput, JobSettings, JobTimings};
pub use options::{
    Format, Method, OptionPatch, OptionsError, ProcessOptions, DEFAULT_SEAM_TOLERANCE,
    DEFAULT_SEAM_WEIGHT,
};
pub use progress::{NoSink, Progress, Sink, Stop};

use std::collections::BTreeMap;
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::bc1::alpha::{decode_alpha_image, encode_alpha_image, AlphaBlock};
use crate::bc1::alpha_seam_aware::{optimise_alpha, AlphaProblem};
use crate::bc1::dds::{write_dds, DdsHeaderKind, MipLevel};
use crate::bc1::punch::punch_through;
use crate::bc1::seam_aware::{optimise, Problem, SeamAwareOptions};
use crate::bc1::Decoder;
pub use crate::bc1::Target;
use crate::bc1::{self, Block};
use crate::mips;
use crate::model::{find_seams, AlphaUse, Model, SeamSet, Skipped, Texture, TextureBinding};
use crate::picture::{seams_png, SeamPicture};
pub use crate::resize::{Resize, SizeChange};
use crate::seam::charts::{ChartFidelity, Charts, HARM_PSNR_DB};
use crate::seam::classify::{classify, ClassifyOptions, SeamVerdicts};
use crate::seam::erase::{erase, EraseError, EraseOptions, EraseStats, Mode};
use crate::seam::masking::{mask, MaskingOptions};
use crate::seam::metric::seam_points_texel_length;
use crate::seam::padding::pad_left_seams;
use crate::seam::quadrature::QuadPoint;
use crate::seam::system::SolveError;
use crate::seam::{colour_channels, psnr, SeamMetric, TexelClasses, TexelGrid};

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
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
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
}

#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Timings {
    pub load: u64,
    pub seams: u64,
    pub erase: u64,
    pub encode: u64,
    pub seam_aware: u64,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Files {
    pub dds: Option<String>,
    pub erased: String,
    /// `<name>.seams.png`, when pictures were asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seams: Option<String>,
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
    pub files: Files,
    pub timings_ms: Timings,
    pub solver: EraseStats,
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
    let total = model.bindings.len();
    for (k, binding) in model.bindings.iter().enumerate() {
        sink.progress(&Progress {
            stage: "process",
            texture: Some((k, total)),
            fraction: 0.1 + 0.8 * k as f64 / total as f64,
        })
        .map_err(PipelineError::Stopped)?;
        let fitted = crate::resize::fit(binding, opts.resize);
        let binding = fitted.as_ref().map_or(binding, |f| &f.0);
        // The last texture's working set is freed, and this one's would
        // land in its holes or not as the threads happen to interleave.
        crate::heap::release_freed_memory();
        let (mut report, mut out) = process_texture(binding, load_ms, opts)?;
        report.resize = fitted.map(|f| f.1);
        files.append(&mut out);
        warnings.extend(harm_warning(&report, opts));
        warnings.extend(alpha_warning(&report));
        textures.push(report);
    }
    let report = Report {
        input: input_name.to_string(),
        options: *opts,
        textures,
        skipped: model.skipped.clone(),
        warnings,
    };
    Ok(Output { files, report })
}

/// One mip level of one texture, seam-erased.
struct ErasedLevel {
    grid: TexelGrid,
    /// Every seam, as the metric measures them.
    seams: SeamSet,
    /// The seams closed (with every silhouette): what erasure and seam-aware
    /// encoding make agree.
    closed: SeamSet,
    verdicts: SeamVerdicts,
    charts: Charts,
    /// Gutter texels filled from their own chart along the seams left open.
    padded: usize,
    classes: TexelClasses,
    /// The solver's output before rounding (the next mip level is filtered from it).
    float: Texture,
    /// Rounded to the file's bit depth: what the PNG holds and BC1 encodes.
    stored: Texture,
    stats: EraseStats,
    seams_ms: u64,
    erase_ms: u64,
}

fn erase_level(
    b: &TextureBinding,
    tex: &Texture,
    opts: &ProcessOptions,
    erase_alpha: bool,
) -> Result<ErasedLevel, PipelineError> {
    let grid = TexelGrid {
        width: tex.width,
        height: tex.height,
        wrap_s: b.wrap_s,
        wrap_t: b.wrap_t,
    };
    let compared = colour_channels(tex.channels);
    let t = Instant::now();
    let seams = find_seams(&b.triangles, tex.width, tex.height);
    let charts = Charts::new(&grid, &b.triangles);
    let mut verdicts = if opts.erase_all {
        SeamVerdicts::all_closed(&seams)
    } else {
        classify(
            &grid,
            &tex.data,
            tex.channels,
            compared,
            &seams,
            &charts,
            &ClassifyOptions {
                tolerance: opts.seam_tolerance,
                remove_chart_offsets: opts.mode == Mode::Global,
            },
        )
    };
    let seams_ms = t.elapsed().as_millis() as u64;

    let t = Instant::now();
    let mut solved = solve(b, &grid, tex, &seams, &verdicts.closed, &charts, opts)?;
    if !opts.erase_all {
        // The middle zone closes only where that repaints no chart.
        let harmed = charts.harmed(&solved.data, &tex.data, tex.channels, compared);
        let spared = verdicts.spare(&seams, &charts, &harmed);
        if spared > 0 {
            tracing::debug!(spared, "seams left to spare their charts");
            solved = solve(b, &grid, tex, &seams, &verdicts.closed, &charts, opts)?;
        }
    }
    if !erase_alpha {
        alpha::restore(&mut solved.data, tex);
    }
    let like = |data| Texture {
        width: tex.width,
        height: tex.height,
        channels: tex.channels,
        data,
        encoding: tex.encoding,
    };
    let stored = like(quantized(&solved.data, tex.encoding.max_value()));
    let float = like(solved.data);
    Ok(ErasedLevel {
        grid,
        seams,
        closed: solved.closed,
        verdicts,
        charts,
        padded: solved.padded,
        classes: solved.classes,
        float,
        stored,
        stats: solved.stats,
        seams_ms,
        erase_ms: t.elapsed().as_millis() as u64,
    })
}

/// One erasure of a level with the seams `closed` selects.
struct Solved {
    closed: SeamSet,
    classes: TexelClasses,
    padded: usize,
    data: Vec<f32>,
    stats: EraseStats,
}

/// Pads the gutter along the seams left, then makes the closed seams agree.
fn solve(
    b: &TextureBinding,
    grid: &TexelGrid,
    tex: &Texture,
    seams: &SeamSet,
    closed: &[bool],
    charts: &Charts,
    opts: &ProcessOptions,
) -> Result<Solved, PipelineError> {
    let selected = seams.select(closed);
    let mut input = tex.data.clone();
    let padded = pad_left_seams(grid, &mut input, tex.channels, seams, closed, charts);
    let classes = TexelClasses::new(grid, &b.triangles, &selected);
    let (data, stats) = match opts.method {
        Method::Erase => erase(
            grid,
            &input,
            tex.channels,
            &selected,
            &classes,
            &EraseOptions::new(opts.mode),
        )
        .map_err(|source| PipelineError::Erase {
            name: b.name.clone(),
            source,
        })?,
        Method::Masking => {
            let out = mask(
                grid,
                &input,
                tex.channels,
                &selected,
                &classes,
                &MaskingOptions::default(),
            )
            .map_err(|source| PipelineError::Solve {
                name: b.name.clone(),
                source,
            })?;
            (out, EraseStats::default())
        }
    };
    Ok(Solved {
        closed: selected,
        classes,
        padded,
        data,
        stats,
    })
}

/// Rounds to what the output file stores, so every metric describes the file.
fn quantized(data: &[f32], max_value: u32) -> Vec<f32> {
    let levels = max_value as f32;
    data.par_iter()
        .map(|v| {
            let x = v.clamp(0.0, 1.0) * levels;
            // `f32::round` is a library call on baseline x86-64 (a fifth of
            // this loop's time). For x ≥ 0, adding ½ in f64 is exact, so
            // truncating rounds half away from zero as it does.
            (f64::from(x) + 0.5) as u32 as f32 / levels
        })
        .collect()
}

/// RGB view of a texture: grey is replicated, alpha dropped (BC1 is opaque).
fn rgb(t: &Texture) -> Vec<f32> {
    let ch = t.channels;
    t.data
        .chunks(ch)
        .flat_map(|c| {
            if ch < 3 {
                [c[0]; 3]
            } else {
                [c[0], c[1], c[2]]
            }
        })
        .collect()
}

/// A level encoded: the blocks the DDS holds, and the regular encoding's.
struct EncodedLevel {
    regular: Vec<Block>,
    shipped: Vec<Block>,
    /// BC3's alpha blocks (empty for BC1).
    alpha_regular: Vec<AlphaBlock>,
    alpha_shipped: Vec<AlphaBlock>,
    /// For BC1 with one-bit alpha: the texels encoded transparent.
    clear: Option<Vec<bool>>,
    encode_ms: u64,
    seam_aware_ms: u64,
}

fn encode_level(
    b: &TextureBinding,
    level: &ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<EncodedLevel, PipelineError> {
    let encode_err = |message: String| PipelineError::Encode {
        name: b.name.clone(),
        message,
    };
    let (w, h) = (level.grid.width, level.grid.height);
    let target = rgb(&level.stored);
    let values = plan.and_then(|_| alpha::channel(&level.stored));
    let format = plan.map(|p| p.format);
    let clear = match (plan, &values) {
        (Some(p), Some(a)) if p.format == AlphaFormat::Bc1a => {
            Some(alpha::transparent(a, p.cutoff.unwrap_or(0.5)))
        }
        _ => None,
    };
    let t = Instant::now();
    let mut regular = bc1::encode_image_for(&target, w, h, 3, opts.bc1_level, opts.decoder)
        .map_err(|e| encode_err(e.to_string()))?;
    if let Some(clear) = &clear {
        punch_through(&mut regular, &target, clear, w, h, opts.decoder);
    }
    let alpha_regular = match (format, &values) {
        (Some(AlphaFormat::Bc3), Some(a)) => encode_alpha_image(a, w, h, opts.decoder),
        _ => Vec::new(),
    };
    let encode_ms = t.elapsed().as_millis() as u64;
    let t = Instant::now();
    let mut shipped = regular.clone();
    let mut alpha_shipped = alpha_regular.clone();
    if opts.seam_aware && !level.closed.seams.is_empty() {
        let points = seam_points_texel_length(&level.grid, &level.closed);
        let sa_opts = SeamAwareOptions {
            alpha: opts.seam_weight,
            target: opts.decoder,
            ..SeamAwareOptions::default()
        };
        let kept;
        let colour_points = match &clear {
            Some(clear) => {
                kept = away_from_punched_blocks(&points, clear, w, h);
                &kept
            }
            None => &points,
        };
        let problem = Problem {
            width: w,
            height: h,
            target: &target,
            channels: 3,
            inside: &level.classes.inside,
            points: colour_points,
        };
        let stats =
            optimise(&problem, &mut shipped, &sa_opts).map_err(|source| PipelineError::Solve {
                name: b.name.clone(),
                source,
            })?;
        stats.log("colour");
        if let (Some(a), Some(true)) = (&values, plan.map(|p| p.erase)) {
            let problem = AlphaProblem {
                width: w,
                height: h,
                target: a,
                inside: &level.classes.inside,
                points: &points,
            };
            optimise_alpha(&problem, &mut alpha_shipped, &sa_opts).log("alpha");
        }
    }
    Ok(EncodedLevel {
        regular,
        shipped,
        alpha_regular,
        alpha_shipped,
        clear,
        encode_ms,
        seam_aware_ms: t.elapsed().as_millis() as u64,
    })
}

/// The seam points none of whose taps fall in a block holding a
/// transparent texel. Those blocks are in three-colour mode, which the
/// seam-aware search does not model: they keep the regular encoding.
fn away_from_punched_blocks(
    points: &[QuadPoint],
    clear: &[bool],
    w: usize,
    h: usize,
) -> Vec<QuadPoint> {
    let bw = w.div_ceil(4);
    let mut punched = vec![false; bw * h.div_ceil(4)];
    for (t, _) in clear.iter().enumerate().filter(|(_, c)| **c) {
        punched[(t / w / 4) * bw + (t % w) / 4] = true;
    }
    points
        .iter()
        .filter(|q| {
            q.taps
                .iter()
                .all(|&(t, _)| !punched[(t as usize / w / 4) * bw + (t as usize % w) / 4])
        })
        .cloned()
        .collect()
}

/// The metric over every seam and over the closed ones, and the fidelity
/// figures, for one texture's level 0.
struct Measure<'a> {
    all: SeamMetric,
    closed: SeamMetric,
    charts: &'a Charts,
    inside: &'a [bool],
    compared: usize,
}

impl Measure<'_> {
    fn input(&self, data: &[f32], channels: usize) -> Metrics {
        Metrics {
            seam_rms: self.all.seam_rms(data, channels, self.compared),
            seam_rms_closed: self.closed.seam_rms(data, channels, self.compared),
            psnr: None,
            worst_chart_psnr: None,
            charts_under_30db: None,
            decoders: None,
        }
    }

    /// An encoding's figures under every decoder; `decode` decodes it with one.
    fn per_decoder(
        &self,
        decode: impl Fn(Decoder) -> Result<Vec<f32>, PipelineError>,
        input: &[f32],
        erased: &[f32],
    ) -> Result<BTreeMap<&'static str, DecoderMetrics>, PipelineError> {
        let mut out = BTreeMap::new();
        for d in Decoder::ALL {
            let data = decode(d)?;
            out.insert(
                d.name(),
                DecoderMetrics {
                    seam_rms: self.all.seam_rms(&data, 3, self.compared),
                    seam_rms_closed: self.closed.seam_rms(&data, 3, self.compared),
                    psnr: psnr(&data, input, 3, self.compared, self.inside),
                    encoding_psnr: psnr(&data, erased, 3, self.compared, self.inside),
                },
            );
        }
        Ok(out)
    }

    /// Alpha figures of `alpha` (one value per texel) against `input`'s
    /// (and, for an encoding, against the `erased` alpha it encoded).
    fn alpha(
        &self,
        plan: &AlphaPlan,
        alpha: &[f32],
        input: &[f32],
        erased: Option<&[f32]>,
    ) -> AlphaMetrics {
        let mask = match (plan.material, plan.cutoff) {
            (AlphaUse::Mask { .. }, Some(c)) => Some(c),
            _ => None,
        };
        AlphaMetrics {
            seam_rms: self.all.seam_rms(alpha, 1, 1),
            seam_rms_closed: self.closed.seam_rms(alpha, 1, 1),
            psnr: psnr(alpha, input, 1, 1, self.inside),
            encoding_psnr: erased.and_then(|e| psnr(alpha, e, 1, 1, self.inside)),
            opacity_changes: mask.map(|c| alpha::opacity_changes(input, alpha, c, self.inside)),
        }
    }

    fn against(&self, data: &[f32], channels: usize, reference: &[f32]) -> Metrics {
        let ChartFidelity {
            worst_psnr,
            under_threshold,
            ..
        } = self
            .charts
            .fidelity(data, reference, channels, self.compared);
        Metrics {
            psnr: psnr(data, reference, channels, self.compared, self.inside),
            worst_chart_psnr: worst_psnr,
            charts_under_30db: Some(under_threshold),
            ..self.input(data, channels)
        }
    }
}

fn seam_summary(level: &ErasedLevel, opts: &ProcessOptions) -> SeamSummary {
    let total = level.seams.total_length();
    let share = |closed: bool| {
        let picked = level
            .seams
            .seams
            .iter()
            .zip(&level.verdicts.closed)
            .filter(|(_, c)| **c == closed);
        let (edges, length) = picked.fold((0, 0.0), |(n, l), (s, _)| (n + 1, l + s.length));
        SeamShare {
            edges,
            length_share: if total > 0.0 { length / total } else { 0.0 },
        }
    };
    SeamSummary {
        tolerance: (!opts.erase_all).then_some(opts.seam_tolerance),
        closed: share(true),
        left: share(false),
        spared: level.verdicts.spared,
        padded_texels: level.padded,
    }
}

/// The warning an unattended run must not miss: charts repainted below
/// [`HARM_PSNR_DB`] by erasure or by the encoding the DDS holds.
fn harm_warning(t: &TextureReport, opts: &ProcessOptions) -> Option<String> {
    let versions = [
        ("erased texture", Some(&t.erased)),
        ("DDS", t.bc1_seam_aware.as_ref()),
    ];
    let (what, m) = versions
        .into_iter()
        .filter_map(|(what, m)| Some((what, m?)))
        .find(|(_, m)| m.charts_under_30db.unwrap_or(0) > 0)?;
    let (charts, psnr) = (m.charts_under_30db?, m.worst_chart_psnr?);
    tracing::warn!(
        texture = %t.name,
        version = what,
        charts_under_30db = charts,
        worst_chart_psnr = psnr,
        "UV charts changed below 30 dB"
    );
    let why = if opts.erase_all {
        "; --erase-all closes seams whose sides are painted apart"
    } else {
        ""
    };
    Some(format!(
        "texture {}: {charts} UV chart(s) under {HARM_PSNR_DB} dB in the {what} \
         (worst {psnr:.1} dB){why}",
        t.name
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

fn process_texture(
    b: &TextureBinding,
    load_ms: u64,
    opts: &ProcessOptions,
) -> Result<(TextureReport, Vec<OutputFile>), PipelineError> {
    let tex = &b.texture;
    let span = tracing::info_span!("texture", image = b.image, name = %b.name);
    let _guard = span.enter();
    let encode_err = |message: String| PipelineError::Encode {
        name: b.name.clone(),
        message,
    };

    let plan = alpha::plan(b, opts.alpha);
    let level0 = erase_level(b, tex, opts, plan.is_some_and(|p| p.erase))?;
    // The solver's working set is freed now and the encoder's has another
    // shape: given back rather than left as holes, the process's peak
    // follows the memory in use (see `heap`).
    crate::heap::release_freed_memory();
    tracing::info!(
        seam_edges = level0.seams.seams.len(),
        closed = level0.verdicts.closed_count(),
        unknowns = level0.stats.unknowns,
        erase_ms = level0.erase_ms,
        peak_mb = crate::heap::peak_resident_mb(),
        "seams erased"
    );
    let measure = Measure {
        all: SeamMetric::new(&level0.grid, &level0.seams),
        closed: SeamMetric::new(&level0.grid, &level0.closed),
        charts: &level0.charts,
        inside: &level0.classes.inside,
        compared: colour_channels(tex.channels),
    };

    let mut files = Vec::new();
    let erased_name = format!("{}.erased.png", b.name);
    let png = level0
        .stored
        .encode_png()
        .map_err(|e| encode_err(e.to_string()))?;
    files.push(OutputFile {
        name: erased_name.clone(),
        bytes: png,
    });

    let mut report = TextureReport {
        image: b.image,
        name: b.name.clone(),
        width: tex.width,
        height: tex.height,
        resize: None,
        alpha: None,
        seam_edges: level0.seams.seams.len(),
        seams: seam_summary(&level0, opts),
        input: measure.input(&tex.data, tex.channels),
        erased: measure.against(&level0.stored.data, tex.channels, &tex.data),
        bc1: None,
        bc1_seam_aware: None,
        bc1_target: None,
        files: Files {
            dds: None,
            erased: erased_name,
            seams: None,
        },
        timings_ms: Timings {
            load: load_ms,
            seams: level0.seams_ms,
            erase: level0.erase_ms,
            encode: 0,
            seam_aware: 0,
        },
        solver: level0.stats,
    };

    let input_rgb = rgb(tex);
    let erased_rgb = rgb(&level0.stored);
    let alphas =
        plan.and_then(|p| Some((p, alpha::channel(tex)?, alpha::channel(&level0.stored)?)));
    report.alpha = alphas.as_ref().map(|(p, input, erased)| AlphaReport {
        format: p.format,
        material: p.material,
        erased_seams: p.erase,
        input: measure.alpha(p, input, input, None),
        erased: measure.alpha(p, erased, input, None),
        regular: None,
        dds: None,
    });
    let mut decoded = None;
    if opts.format == Format::Dds {
        let enc = encode_level(b, &level0, opts, plan.as_ref())?;
        // As after the erase: the decodes and mip levels that follow are
        // shaped unlike the encoder's blocks.
        crate::heap::release_freed_memory();
        // Under a transparent texel of a one-bit-alpha DDS no colour is
        // shown: the colour figures take the erased texture's there.
        let decode = |blocks: &[Block], d: Decoder| {
            let mut rgb = bc1::decode_image_with(blocks, tex.width, tex.height, d)
                .map_err(|e| encode_err(e.to_string()))?;
            if let Some(clear) = &enc.clear {
                for (t, _) in clear.iter().enumerate().filter(|(_, c)| **c) {
                    rgb[t * 3..t * 3 + 3].copy_from_slice(&erased_rgb[t * 3..t * 3 + 3]);
                }
            }
            Ok(rgb)
        };
        let regular = decode(&enc.regular, Decoder::Ideal)?;
        let shipped = decode(&enc.shipped, Decoder::Ideal)?;
        let mut bc1 = measure.against(&regular, 3, &input_rgb);
        bc1.decoders =
            Some(measure.per_decoder(|d| decode(&enc.regular, d), &input_rgb, &erased_rgb)?);
        report.bc1 = Some(bc1);
        if opts.seam_aware {
            let mut sa = measure.against(&shipped, 3, &input_rgb);
            sa.decoders =
                Some(measure.per_decoder(|d| decode(&enc.shipped, d), &input_rgb, &erased_rgb)?);
            report.bc1_seam_aware = Some(sa);
            report.bc1_target = Some(opts.decoder);
        }
        if let (Some(r), Some((p, input, erased))) = (report.alpha.as_mut(), alphas.as_ref()) {
            let figures = |regular| {
                dds_alpha(&enc, p, tex, regular).map(|per| {
                    per.into_iter()
                        .map(|(d, a)| (d.name(), measure.alpha(p, &a, input, Some(erased))))
                        .collect()
                })
            };
            r.regular = figures(true);
            r.dds = figures(false);
        }
        report.timings_ms.encode = enc.encode_ms;
        report.timings_ms.seam_aware = enc.seam_aware_ms;
        tracing::info!(
            encode_ms = enc.encode_ms,
            seam_aware_ms = enc.seam_aware_ms,
            peak_mb = crate::heap::peak_resident_mb(),
            "level 0 encoded"
        );
        let dds_name = format!("{}.dds", b.name);
        files.push(OutputFile {
            name: dds_name.clone(),
            bytes: write_levels(b, &level0, enc, opts, plan.as_ref())?,
        });
        report.files.dds = Some(dds_name);
        decoded = Some((regular, shipped));
    }
    if opts.pictures {
        let (regular, shipped) = decoded
            .as_ref()
            .map_or((&erased_rgb, &erased_rgb), |(r, s)| (r, s));
        let picture = SeamPicture {
            grid: &level0.grid,
            input: &input_rgb,
            erased: &erased_rgb,
            bc1: regular,
            seam_aware: shipped,
            seams: &level0.seams,
            closed: &level0.verdicts.closed,
        };
        let name = format!("{}.seams.png", b.name);
        files.push(OutputFile {
            name: name.clone(),
            bytes: seams_png(&picture).map_err(|e| encode_err(e.to_string()))?,
        });
        report.files.seams = Some(name);
    }
    tracing::debug!(peak_mb = crate::heap::peak_resident_mb(), "texture done");
    Ok((report, files))
}

/// The DDS's level-0 alpha under each decoder, when it holds alpha.
/// `regular`: of the regular encoding rather than the shipped one.
fn dds_alpha(
    enc: &EncodedLevel,
    plan: &AlphaPlan,
    tex: &Texture,
    regular: bool,
) -> Option<Vec<(Decoder, Vec<f32>)>> {
    let (w, h) = (tex.width, tex.height);
    let (colour, alpha) = if regular {
        (&enc.regular, &enc.alpha_regular)
    } else {
        (&enc.shipped, &enc.alpha_shipped)
    };
    let per = |d: Decoder| match plan.format {
        AlphaFormat::Bc3 => Some(decode_alpha_image(alpha, w, h, d)),
        AlphaFormat::Bc1a => Some(bc1::punch::punch_alpha(colour, w, h)),
        AlphaFormat::Dropped => None,
    };
    Decoder::ALL
        .into_iter()
        .map(|d| Some((d, per(d)?)))
        .collect()
}

/// The DDS: level 0 as encoded, then (with `mips`) every smaller level
/// filtered from the one above, erased and encoded on its own.
fn write_levels(
    b: &TextureBinding,
    level0: &ErasedLevel,
    enc0: EncodedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<Vec<u8>, PipelineError> {
    let tex = &b.texture;
    let mut levels = vec![MipLevel {
        width: tex.width as u32,
        height: tex.height as u32,
        blocks: enc0.shipped,
        alpha: enc0.alpha_shipped,
    }];
    if opts.mips {
        let mut above = level0.float.clone();
        for k in 1..mips::chain_len(tex.width, tex.height) {
            let filtered = mips::downsample(&above, b.wrap_s, b.wrap_t);
            let level = erase_level(b, &filtered, opts, plan.is_some_and(|p| p.erase))?;
            let enc = encode_level(b, &level, opts, plan)?;
            tracing::debug!(level = k, width = level.grid.width, "mip level encoded");
            levels.push(MipLevel {
                width: level.grid.width as u32,
                height: level.grid.height as u32,
                blocks: enc.shipped,
                alpha: enc.alpha_shipped,
            });
            above = level.float;
        }
    }
    let header = if opts.dx10 {
        DdsHeaderKind::Dx10 { srgb: b.srgb }
    } else {
        DdsHeaderKind::Legacy
    };
    write_dds(&levels, header).map_err(|e| PipelineError::Encode {
        name: b.name.clone(),
        message: e.to_string(),
    })
}
