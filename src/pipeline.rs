//! One job: a loaded model in, output files and a report out.
//!
//! model → seams → erase → encode (regular, then seam-aware) → DDS.
//!
//! The pipeline never touches the file system for its outputs: it returns
//! named byte buffers, which the CLI writes into a folder and the service
//! into its file store, so both serve identical bytes.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::bc1::dds::{write_dds, DdsHeaderKind, MipLevel};
use crate::bc1::seam_aware::{optimise, Problem, SeamAwareOptions};
use crate::bc1::{self, Block, Level};
use crate::mips;
use crate::model::{find_seams, Model, SeamSet, Skipped, Texture, TextureBinding};
use crate::seam::erase::{erase, EraseError, EraseOptions, EraseStats, Mode};
use crate::seam::masking::{mask, MaskingOptions};
use crate::seam::metric::seam_points_texel_length;
use crate::seam::system::SolveError;
use crate::seam::{colour_channels, psnr, SeamMetric, TexelClasses, TexelGrid};

/// How seams are removed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Both sides agree along the whole seam, integrated exactly
    // (SPEC §4).
    #[default]
    Erase,
    /// Both sides agree at points sampled along the seams
    // (the seeds' baseline, a simpler least-squares).
    Masking,
}

/// What `process` writes for each texture besides the erased PNG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Format {
    /// A BC1 DDS file and the erased PNG.
    #[default]
    Dds,
    /// The erased PNG only.
    Png,
}

pub use crate::bc1::seam_aware::DEFAULT_ALPHA as DEFAULT_SEAM_WEIGHT;

#[derive(Clone, Copy, Debug)]
pub struct ProcessOptions {
    pub mode: Mode,
    pub method: Method,
    pub format: Format,
    pub bc1_level: Level,
    pub seam_aware: bool,
    pub seam_weight: f64,
    pub mips: bool,
    pub dx10: bool,
}

impl Default for ProcessOptions {
    fn default() -> Self {
        ProcessOptions {
            mode: Mode::Local,
            method: Method::Erase,
            format: Format::Dds,
            bc1_level: Level::Default,
            seam_aware: true,
            seam_weight: DEFAULT_SEAM_WEIGHT,
            mips: false,
            dx10: false,
        }
    }
}

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
}

/// Seam and fidelity figures for one version of a texture.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Metrics {
    /// Length-weighted RMS seam difference in 8-bit levels (`null` without seams).
    pub seam_rms: Option<f64>,
    /// RGB PSNR over inside texels against the input (`null` for the input itself, or if identical).
    pub psnr: Option<f64>,
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
}

#[derive(Clone, Debug, Serialize)]
pub struct TextureReport {
    pub image: usize,
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub seam_edges: usize,
    pub input: Metrics,
    pub erased: Metrics,
    /// The regular BC1 encoding of the erased texture (mip level 0).
    pub bc1: Option<Metrics>,
    /// What the DDS holds (mip level 0), when seam-aware encoding is on.
    pub bc1_seam_aware: Option<Metrics>,
    pub files: Files,
    pub timings_ms: Timings,
    pub solver: EraseStats,
}

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub input: String,
    pub textures: Vec<TextureReport>,
    pub skipped: Vec<Skipped>,
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
    let mut files = Vec::new();
    let mut textures = Vec::new();
    for binding in &model.bindings {
        let (report, mut out) = process_texture(binding, load_ms, opts)?;
        files.append(&mut out);
        textures.push(report);
    }
    let report = Report {
        input: input_name.to_string(),
        textures,
        skipped: model.skipped.clone(),
    };
    Ok(Output { files, report })
}

/// One mip level of one texture, seam-erased.
struct ErasedLevel {
    grid: TexelGrid,
    seams: SeamSet,
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
) -> Result<ErasedLevel, PipelineError> {
    let grid = TexelGrid {
        width: tex.width,
        height: tex.height,
        wrap_s: b.wrap_s,
        wrap_t: b.wrap_t,
    };
    let t = Instant::now();
    let seams = find_seams(&b.triangles, tex.width, tex.height);
    let classes = TexelClasses::new(&grid, &b.triangles, &seams);
    let seams_ms = t.elapsed().as_millis() as u64;

    let t = Instant::now();
    let (data, stats) = match opts.method {
        Method::Erase => erase(
            &grid,
            &tex.data,
            tex.channels,
            &seams,
            &classes,
            &EraseOptions::new(opts.mode),
        )
        .map_err(|source| PipelineError::Erase {
            name: b.name.clone(),
            source,
        })?,
        Method::Masking => {
            let out = mask(
                &grid,
                &tex.data,
                tex.channels,
                &seams,
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
    let like = |data| Texture {
        width: tex.width,
        height: tex.height,
        channels: tex.channels,
        data,
        encoding: tex.encoding,
    };
    let stored = like(quantized(&data, tex.encoding.max_value()));
    let float = like(data);
    Ok(ErasedLevel {
        grid,
        seams,
        classes,
        float,
        stored,
        stats,
        seams_ms,
        erase_ms: t.elapsed().as_millis() as u64,
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
    encode_ms: u64,
    seam_aware_ms: u64,
}

fn encode_level(
    b: &TextureBinding,
    level: &ErasedLevel,
    opts: &ProcessOptions,
) -> Result<EncodedLevel, PipelineError> {
    let encode_err = |message: String| PipelineError::Encode {
        name: b.name.clone(),
        message,
    };
    let (w, h) = (level.grid.width, level.grid.height);
    let target = rgb(&level.stored);
    let t = Instant::now();
    let regular = bc1::encode_image(&target, w, h, 3, opts.bc1_level)
        .map_err(|e| encode_err(e.to_string()))?;
    let encode_ms = t.elapsed().as_millis() as u64;
    let t = Instant::now();
    let mut shipped = regular.clone();
    if opts.seam_aware && !level.seams.seams.is_empty() {
        let points = seam_points_texel_length(&level.grid, &level.seams);
        let problem = Problem {
            width: w,
            height: h,
            target: &target,
            channels: 3,
            inside: &level.classes.inside,
            points: &points,
        };
        let sa_opts = SeamAwareOptions {
            alpha: opts.seam_weight,
            ..SeamAwareOptions::default()
        };
        let stats =
            optimise(&problem, &mut shipped, &sa_opts).map_err(|source| PipelineError::Solve {
                name: b.name.clone(),
                source,
            })?;
        tracing::debug!(
            blocks = stats.blocks,
            sweeps = stats.sweeps,
            energy_regular = stats.energy_regular,
            energy_final = stats.energy_final,
            "seam-aware encoding"
        );
    }
    Ok(EncodedLevel {
        regular,
        shipped,
        encode_ms,
        seam_aware_ms: t.elapsed().as_millis() as u64,
    })
}

fn process_texture(
    b: &TextureBinding,
    load_ms: u64,
    opts: &ProcessOptions,
) -> Result<(TextureReport, Vec<OutputFile>), PipelineError> {
    let tex = &b.texture;
    let span = tracing::info_span!("texture", image = b.image, name = %b.name);
    let _guard = span.enter();

    let level0 = erase_level(b, tex, opts)?;
    tracing::info!(
        seam_edges = level0.seams.seams.len(),
        unknowns = level0.stats.unknowns,
        erase_ms = level0.erase_ms,
        "seams erased"
    );
    let metric = SeamMetric::new(&level0.grid, &level0.seams);
    let compared = colour_channels(tex.channels);
    let inside = &level0.classes.inside;
    let measure = |data: &[f32], channels: usize, reference: &[f32]| Metrics {
        seam_rms: metric.seam_rms(data, channels, compared),
        psnr: psnr(data, reference, channels, compared, inside),
    };

    let mut files = Vec::new();
    let erased_name = format!("{}.erased.png", b.name);
    let png = level0
        .stored
        .encode_png()
        .map_err(|e| PipelineError::Encode {
            name: b.name.clone(),
            message: e.to_string(),
        })?;
    files.push(OutputFile {
        name: erased_name.clone(),
        bytes: png,
    });

    let mut report = TextureReport {
        image: b.image,
        name: b.name.clone(),
        width: tex.width,
        height: tex.height,
        seam_edges: level0.seams.seams.len(),
        input: Metrics {
            seam_rms: metric.seam_rms(&tex.data, tex.channels, compared),
            psnr: None,
        },
        erased: measure(&level0.stored.data, tex.channels, &tex.data),
        bc1: None,
        bc1_seam_aware: None,
        files: Files {
            dds: None,
            erased: erased_name,
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

    if opts.format == Format::Dds {
        let input_rgb = rgb(tex);
        let enc = encode_level(b, &level0, opts)?;
        let decode = |blocks: &[Block]| {
            bc1::decode_image(blocks, tex.width, tex.height).map_err(|e| PipelineError::Encode {
                name: b.name.clone(),
                message: e.to_string(),
            })
        };
        report.bc1 = Some(measure(&decode(&enc.regular)?, 3, &input_rgb));
        if opts.seam_aware {
            report.bc1_seam_aware = Some(measure(&decode(&enc.shipped)?, 3, &input_rgb));
        }
        report.timings_ms.encode = enc.encode_ms;
        report.timings_ms.seam_aware = enc.seam_aware_ms;
        tracing::info!(
            encode_ms = enc.encode_ms,
            seam_aware_ms = enc.seam_aware_ms,
            "level 0 encoded"
        );

        let mut levels = vec![MipLevel {
            width: tex.width as u32,
            height: tex.height as u32,
            blocks: enc.shipped,
        }];
        if opts.mips {
            let mut above = level0.float;
            for k in 1..mips::chain_len(tex.width, tex.height) {
                let filtered = mips::downsample(&above, b.wrap_s, b.wrap_t);
                let level = erase_level(b, &filtered, opts)?;
                let enc = encode_level(b, &level, opts)?;
                tracing::debug!(level = k, width = level.grid.width, "mip level encoded");
                levels.push(MipLevel {
                    width: level.grid.width as u32,
                    height: level.grid.height as u32,
                    blocks: enc.shipped,
                });
                above = level.float;
            }
        }
        let header = if opts.dx10 {
            DdsHeaderKind::Dx10 { srgb: b.srgb }
        } else {
            DdsHeaderKind::Legacy
        };
        let dds = write_dds(&levels, header).map_err(|e| PipelineError::Encode {
            name: b.name.clone(),
            message: e.to_string(),
        })?;
        let dds_name = format!("{}.dds", b.name);
        files.push(OutputFile {
            name: dds_name.clone(),
            bytes: dds,
        });
        report.files.dds = Some(dds_name);
    }
    Ok((report, files))
}
