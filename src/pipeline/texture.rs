//! One texture of a job, from its level 0 to its last mip level, to its
//! files and its report.
//!
//! Level 0's encoding is the longest chain of the job after the erasure:
//! its seam-aware search is one thread's work. What does not depend on it
//! runs beside it: the erased PNG, the erased texture's figures and every
//! smaller mip level, each level's encoding beside the erasure of the levels
//! below. Every piece computes the same bytes whichever thread runs it, so
//! the files do not depend on the thread count.

use std::time::Instant;

use serde::Serialize;

use super::alpha::{self, AlphaFormat, AlphaPlan, AlphaReport};
use super::bc7_level::{self, Bc7Level};
use super::figures::{Figures, Measured};
use super::file::{regular_file, texture_file, Shipped};
use super::level::{
    encode_level, encode_regular, encode_seam_aware, erase_level, rgb, EncodedLevel, ErasedLevel,
    Rung, TextureMesh,
};
use super::measure::Measure;
use super::view_files;
use super::Container;
use super::{
    AlphaSeamSummary, Files, Format, Metrics, OutputFile, PipelineError, ProcessOptions, SeamShare,
    SeamSummary, TextureReport,
};
use crate::bc1::alpha::decode_alpha_image;
use crate::bc1::dds::MipLevel;
use crate::bc1::{self, Decoder};
use crate::mips;
use crate::model::{Texture, TextureBinding};
use crate::picture::{job_versions, seams_png, SeamPicture};
use crate::resize::SizeChange;
use crate::seam::{colour_channels, SeamMetric};

/// Milliseconds of one texture's stages. The stages on the texture's
/// critical path (all but `beside`'s) follow one another and sum to
/// `total`; `beside` gives the own time of the work that ran beside level
/// 0's encoding.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Timings {
    /// Loading the model (the whole model's, before any texture).
    pub load: u64,
    /// Finding and judging the seams of level 0.
    pub seams: u64,
    /// Erasing level 0's seams.
    pub erase: u64,
    /// Waiting, once erased, for the texture before it to finish (the
    /// next texture's erasure runs beside the last one's encoding).
    pub waited: u64,
    /// Level 0's regular BC1 encoding.
    pub encode: u64,
    /// Level 0's seam-aware search.
    pub seam_aware: u64,
    /// Waiting, after level 0's encoding, for the work beside it to end.
    pub beside_wait: u64,
    /// Decoding level 0's encodings under every decoder, with their figures.
    pub metrics: u64,
    /// Drawing `<name>.seams.png`.
    pub pictures: u64,
    /// Writing the DDS file's bytes.
    pub dds: u64,
    /// The texture from start to end.
    pub total: u64,
    pub beside: BesideTimings,
}

/// The own time of the work that ran beside level 0's encoding.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct BesideTimings {
    /// Writing the erased PNG.
    pub png: u64,
    /// The input's and the erased texture's figures.
    pub metrics: u64,
    /// Erasing and encoding every smaller mip level.
    pub mips: u64,
}

fn ms_since(t: Instant) -> u64 {
    t.elapsed().as_millis() as u64
}

/// A texture whose level 0 is erased: what [`finish_texture`] goes on from.
pub(super) struct Erased<'a> {
    original: &'a TextureBinding,
    /// The texture brought to the size it is processed at, when it was.
    fitted: Option<(TextureBinding, SizeChange)>,
    plan: Option<AlphaPlan>,
    /// The mesh's edges and charts, found once for every level.
    mesh: TextureMesh,
    level0: ErasedLevel,
    started: Instant,
    erased_at: Instant,
}

impl Erased<'_> {
    fn binding(&self) -> &TextureBinding {
        self.fitted.as_ref().map_or(self.original, |f| &f.0)
    }

    /// The model's image this texture is.
    pub(super) fn image(&self) -> usize {
        self.original.image
    }
}

/// The first stage of a texture: brought to size, its level 0's seams
/// judged and erased. The solver's working set is the largest of the job.
pub(super) fn erase_texture<'a>(
    original: &'a TextureBinding,
    opts: &ProcessOptions,
) -> Result<Erased<'a>, PipelineError> {
    let started = Instant::now();
    let fitted = crate::resize::fit(original, opts.resize);
    let b = fitted.as_ref().map_or(original, |f| &f.0);
    let span = tracing::info_span!("texture", image = b.image, name = %b.name);
    let _guard = span.enter();
    let plan = alpha::plan(b, opts.alpha, opts.format);
    let t = Instant::now();
    let mesh = TextureMesh::new(&b.triangles);
    let weld_ms = ms_since(t);
    let mut level0 = erase_level(
        b,
        &mesh,
        &b.texture,
        opts,
        plan.is_some_and(|p| p.erase),
        Rung::Base,
    )?;
    level0.seams_ms += weld_ms;
    tracing::info!(
        seam_edges = level0.seams.seams.len(),
        closed = level0.verdicts.closed_count(),
        unknowns = level0.stats.unknowns,
        erase_ms = level0.erase_ms,
        peak_mb = crate::heap::peak_resident_mb(),
        "seams erased"
    );
    Ok(Erased {
        original,
        fitted,
        plan,
        mesh,
        level0,
        started,
        erased_at: Instant::now(),
    })
}

/// The rest of a texture after [`erase_texture`]: its encodings, figures,
/// smaller mip levels and files.
pub(super) fn finish_texture(
    erased: Erased<'_>,
    load_ms: u64,
    opts: &ProcessOptions,
) -> Result<(TextureReport, Vec<OutputFile>), PipelineError> {
    let waited = ms_since(erased.erased_at);
    let b = erased.binding();
    let (level0, plan, started) = (&erased.level0, erased.plan, erased.started);
    let tex = &b.texture;
    let span = tracing::info_span!("texture", image = b.image, name = %b.name);
    let _guard = span.enter();
    // Two independent sets of quadrature points (tens of milliseconds each on
    // a 2048² atlas), before either branch below can start.
    let (all, closed) = rayon::join(
        || SeamMetric::new(&level0.grid, &level0.seams),
        || SeamMetric::new(&level0.grid, &level0.closed),
    );
    let measure = Measure {
        all,
        closed,
        alpha_closed: level0
            .alpha
            .as_ref()
            .map(|a| SeamMetric::new(&level0.grid, &a.closed)),
        charts: &level0.charts,
        inside: &level0.classes.inside,
        compared: colour_channels(tex.channels),
    };
    let alphas =
        plan.and_then(|p| Some((p, alpha::channel(tex)?, alpha::channel(&level0.stored)?)));
    let compressed = opts.format.compressed();

    let input_rgb = rgb(tex);
    let erased_rgb = rgb(&level0.stored);
    let figures = Figures {
        name: &b.name,
        tex,
        measure: &measure,
        input_rgb: &input_rgb,
        erased_rgb: &erased_rgb,
    };

    let t = Instant::now();
    let (first, side) = rayon::join(
        || {
            compressed
                .then(|| encode_level0(b, level0, opts, plan.as_ref(), &figures))
                .transpose()
        },
        || Beside::run(&erased, &measure, alphas.as_ref(), opts),
    );
    let (first, side) = (first?, side?);
    let (encode_ms, seam_aware_ms, figured_ms) = first.as_ref().map_or((0, 0, 0), Level0::timings);
    let beside_wait = ms_since(t).saturating_sub(encode_ms + seam_aware_ms + figured_ms);

    let erased_name = format!("{}.erased.png", b.name);
    let mut files = vec![OutputFile {
        name: erased_name.clone(),
        bytes: side.png,
    }];
    let mut report = TextureReport {
        image: b.image,
        name: b.name.clone(),
        width: tex.width,
        height: tex.height,
        resize: erased.fitted.as_ref().map(|f| f.1),
        alpha: side.alpha,
        seam_edges: level0.seams.seams.len(),
        seams: seam_summary(level0, opts),
        input: side.input,
        erased: side.erased,
        bc1: None,
        bc1_seam_aware: None,
        bc1_target: None,
        bc7: None,
        bc7_seam_aware: None,
        files: Files {
            dds: None,
            ktx2: None,
            erased: erased_name,
            seams: None,
            charts: None,
            edges: None,
            regular: None,
            input: None,
        },
        timings_ms: Timings {
            load: load_ms,
            seams: level0.seams_ms,
            erase: level0.erase_ms,
            waited,
            encode: encode_ms,
            seam_aware: seam_aware_ms,
            beside_wait,
            beside: side.timings,
            ..Timings::default()
        },
        solver: level0.stats,
        closed_seams: level0.closed.seams.iter().map(|s| [s.a, s.b]).collect(),
    };

    let mut decoded = None;
    if let Some(first) = first {
        let t = Instant::now();
        let level = match first {
            Level0::Bc1 {
                enc,
                regular,
                shipped,
                ..
            } => {
                report.bc1 = Some(regular.metrics);
                if opts.seam_aware {
                    report.bc1_seam_aware = Some(shipped.metrics);
                    report.bc1_target = Some(opts.decoder);
                }
                if let (Some(r), Some((p, input, erased))) =
                    (report.alpha.as_mut(), alphas.as_ref())
                {
                    let alpha_figures = |regular| {
                        dds_alpha(&enc, p, tex, regular).map(|per| {
                            per.into_iter()
                                .map(|(d, a)| (d.name(), measure.alpha(p, &a, input, Some(erased))))
                                .collect()
                        })
                    };
                    r.regular = alpha_figures(true);
                    r.dds = alpha_figures(false);
                }
                decoded = Some((regular.ideal, shipped.ideal));
                if opts.keep_regular {
                    let level = MipLevel {
                        width: tex.width as u32,
                        height: tex.height as u32,
                        blocks: enc.regular,
                        alpha: enc.alpha_regular,
                    };
                    let (name, bytes) = regular_file(b, level)?;
                    report.files.regular = Some(name.clone());
                    files.push(OutputFile { name, bytes });
                }
                Shipped::Bc1(MipLevel {
                    width: tex.width as u32,
                    height: tex.height as u32,
                    blocks: enc.shipped,
                    alpha: enc.alpha_shipped,
                })
            }
            Level0::Bc7 {
                enc,
                regular,
                shipped,
                ..
            } => {
                report.bc7 = Some(regular.metrics);
                if opts.seam_aware {
                    report.bc7_seam_aware = Some(shipped.metrics);
                }
                if let (Some(r), Some((p, input, erased))) =
                    (report.alpha.as_mut(), alphas.as_ref())
                {
                    if p.format == AlphaFormat::Bc7 {
                        let figures = |a: &[f32]| {
                            let m = measure.alpha(p, a, input, Some(erased));
                            Some([(BC7_DECODING, m)].into_iter().collect())
                        };
                        r.regular = figures(&regular.alpha);
                        r.dds = figures(&shipped.alpha);
                    }
                }
                decoded = Some((regular.ideal, shipped.ideal));
                Shipped::Bc7 {
                    width: tex.width as u32,
                    height: tex.height as u32,
                    blocks: enc.shipped,
                }
            }
        };
        report.timings_ms.metrics = figured_ms + ms_since(t);
        tracing::info!(
            encode_ms,
            seam_aware_ms,
            peak_mb = crate::heap::peak_resident_mb(),
            "level 0 encoded"
        );

        let t = Instant::now();
        let mut levels = vec![level];
        levels.extend(side.smaller);
        let (name, bytes) = texture_file(b, levels, opts)?;
        match opts.container {
            Container::Dds => report.files.dds = Some(name.clone()),
            Container::Ktx2 => report.files.ktx2 = Some(name.clone()),
        }
        files.push(OutputFile { name, bytes });
        report.timings_ms.dds = ms_since(t);
    }
    if opts.keep_regular {
        let name = format!("{}.input.png", b.name);
        let bytes = tex
            .encode_png()
            .map_err(|e| PipelineError::encode(&b.name, e))?;
        files.push(OutputFile {
            name: name.clone(),
            bytes,
        });
        report.files.input = Some(name);
    }
    if opts.pictures {
        let t = Instant::now();
        let (regular, shipped) = decoded
            .as_ref()
            .map_or((&erased_rgb[..], &erased_rgb[..]), |(r, s)| {
                (&r[..], &s[..])
            });
        let picture = SeamPicture {
            grid: &level0.grid,
            versions: job_versions(&input_rgb, &erased_rgb, regular, shipped),
            seams: &level0.seams,
            closed: &level0.verdicts.closed,
            alpha_closed: level0.alpha.as_ref().map(|a| a.verdicts.closed.as_slice()),
        };
        let name = format!("{}.seams.png", b.name);
        files.push(OutputFile {
            name: name.clone(),
            bytes: seams_png(&picture).map_err(|e| PipelineError::encode(&b.name, e))?,
        });
        report.files.seams = Some(name);

        let name = format!("{}.charts.png", b.name);
        let bytes = view_files::charts_png(&level0.grid, &level0.charts)
            .map_err(|e| PipelineError::encode(&b.name, e))?;
        files.push(OutputFile {
            name: name.clone(),
            bytes,
        });
        report.files.charts = Some(name);
        let versions = view_files::Versions {
            input: &input_rgb,
            erased: &erased_rgb,
            regular,
            seam_aware: shipped,
        };
        let bytes = view_files::edges_json(
            &level0.grid,
            &level0.seams,
            &level0.verdicts.closed,
            &level0.verdicts.jump,
            (!opts.erase_all).then_some(opts.seam_tolerance),
            &versions,
        )
        .map_err(|e| PipelineError::encode(&b.name, e))?;
        let name = format!("{}.edges.json", b.name);
        files.push(OutputFile {
            name: name.clone(),
            bytes,
        });
        report.files.edges = Some(name);
        report.timings_ms.pictures = ms_since(t);
    }
    report.timings_ms.total = ms_since(started);
    tracing::debug!(peak_mb = crate::heap::peak_resident_mb(), "texture done");
    Ok((report, files))
}

/// Level 0 encoded, with both encodings' figures.
enum Level0 {
    Bc1 {
        enc: EncodedLevel,
        regular: Measured,
        shipped: Measured,
        /// The seam-aware search's time, with the regular figures beside it.
        searched_ms: u64,
        /// The shipped encoding's figures' time.
        figured_ms: u64,
    },
    Bc7 {
        enc: Bc7Level,
        regular: Measured,
        shipped: Measured,
        searched_ms: u64,
        figured_ms: u64,
    },
}

impl Level0 {
    /// The regular encoding's, the seam-aware search's and the shipped
    /// figures' milliseconds.
    fn timings(&self) -> (u64, u64, u64) {
        match self {
            Level0::Bc1 {
                enc,
                searched_ms,
                figured_ms,
                ..
            } => (enc.encode_ms, *searched_ms, *figured_ms),
            Level0::Bc7 {
                enc,
                searched_ms,
                figured_ms,
                ..
            } => (enc.encode_ms, *searched_ms, *figured_ms),
        }
    }
}

/// Level 0's regular encoding, then its seam-aware search with the regular
/// encoding's figures beside it (they need nothing of the search), then the
/// shipped encoding's figures: all on this side of the join, so that they
/// run while the mip chain beside them still does.
fn encode_level0(
    b: &TextureBinding,
    level0: &ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
    figures: &Figures<'_>,
) -> Result<Level0, PipelineError> {
    if opts.format == Format::Bc7 {
        let (regular, encode_ms) = bc7_level::encode_regular(b, level0, opts, plan)?;
        let t = Instant::now();
        let (shipped, regular_figures) = rayon::join(
            || bc7_level::encode_seam_aware(b, level0, &regular, opts, plan),
            || figures.of_bc7(&regular),
        );
        let ((shipped, seam_aware_ms), regular_figures) = (shipped?, regular_figures?);
        let searched_ms = ms_since(t);
        let t = Instant::now();
        let shipped_figures = figures.of_bc7(&shipped)?;
        return Ok(Level0::Bc7 {
            searched_ms,
            figured_ms: ms_since(t),
            enc: Bc7Level {
                shipped,
                encode_ms,
                seam_aware_ms,
            },
            regular: regular_figures,
            shipped: shipped_figures,
        });
    }
    let regular = encode_regular(b, level0, opts, plan)?;
    let t = Instant::now();
    let (shipped, regular_figures) = rayon::join(
        || encode_seam_aware(b, level0, &regular, opts, plan),
        || figures.of(&regular.blocks, regular.clear.as_deref()),
    );
    let (shipped, regular_figures) = (shipped?, regular_figures?);
    let searched_ms = ms_since(t);
    let t = Instant::now();
    let enc = EncodedLevel::new(regular, shipped);
    let shipped_figures = figures.of_changed(
        &enc.regular,
        &regular_figures,
        &enc.shipped,
        enc.clear.as_deref(),
    )?;
    Ok(Level0::Bc1 {
        searched_ms,
        figured_ms: ms_since(t),
        enc,
        regular: regular_figures,
        shipped: shipped_figures,
    })
}

/// What runs beside level 0's encoding, and what it made.
struct Beside {
    png: Vec<u8>,
    input: Metrics,
    erased: Metrics,
    alpha: Option<AlphaReport>,
    /// Mip levels 1 and smaller, encoded (empty without `mips` or a
    /// compressed format).
    smaller: Vec<Shipped>,
    timings: BesideTimings,
}

impl Beside {
    fn run(
        texture: &Erased<'_>,
        measure: &Measure<'_>,
        alphas: Option<&(AlphaPlan, Vec<f32>, Vec<f32>)>,
        opts: &ProcessOptions,
    ) -> Result<Beside, PipelineError> {
        let (b, level0) = (texture.binding(), &texture.level0);
        let (mesh, plan) = (&texture.mesh, texture.plan.as_ref());
        let tex = &b.texture;
        // The mip chain is the longest of these: it starts first.
        let (smaller, (png, input, erased, alpha, png_ms, metrics_ms)) = rayon::join(
            || {
                let t = Instant::now();
                let smaller = if opts.mips && opts.format.compressed() {
                    let count = mips::chain_len(tex.width, tex.height);
                    smaller_levels(b, mesh, &level0.float, 1, count, opts, plan)
                } else {
                    Ok(Vec::new())
                };
                (smaller, ms_since(t))
            },
            || {
                let t = Instant::now();
                let png = level0.stored.encode_png();
                let png_ms = ms_since(t);
                let t = Instant::now();
                let input = measure.input(&tex.data, tex.channels);
                let erased = measure.against(&level0.stored.data, tex.channels, &tex.data);
                let alpha = alphas.map(|(p, input, erased)| AlphaReport {
                    format: p.format,
                    material: p.material,
                    erased_seams: p.erase,
                    input: measure.alpha(p, input, input, None),
                    erased: measure.alpha(p, erased, input, None),
                    regular: None,
                    dds: None,
                });
                (png, input, erased, alpha, png_ms, ms_since(t))
            },
        );
        let (smaller, mips_ms) = smaller;
        Ok(Beside {
            png: png.map_err(|e| PipelineError::encode(&b.name, e))?,
            input,
            erased,
            alpha,
            smaller: smaller?,
            timings: BesideTimings {
                png: png_ms,
                metrics: metrics_ms,
                mips: mips_ms,
            },
        })
    }
}

/// Mip levels `k` to `count − 1`, each filtered from the erased (unrounded)
/// level above, erased and encoded on its own. A level's encoding runs
/// beside the erasure of the levels below it, which does not need it.
fn smaller_levels(
    b: &TextureBinding,
    mesh: &TextureMesh,
    above: &Texture,
    k: usize,
    count: usize,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<Vec<Shipped>, PipelineError> {
    if k >= count {
        return Ok(Vec::new());
    }
    let filtered = mips::downsample(above, b.wrap_s, b.wrap_t);
    let level = erase_level(
        b,
        mesh,
        &filtered,
        opts,
        plan.is_some_and(|p| p.erase),
        Rung::Mip,
    )?;
    drop(filtered);
    // The chain of erasures is the longer path: this thread goes on down it,
    // and the level's encoding waits to be taken by a thread that is free
    // (the other way round, the next level's erasure waited for this one's
    // seam-aware search whenever level 0's encoding held the other thread).
    let (below, enc) = rayon::join(
        || smaller_levels(b, mesh, &level.float, k + 1, count, opts, plan),
        || encode_mip(b, &level, opts, plan),
    );
    let ((shipped, encode_ms, seam_aware_ms), mut below) = (enc?, below?);
    tracing::debug!(
        level = k,
        width = level.grid.width,
        seams_ms = level.seams_ms,
        erase_ms = level.erase_ms,
        encode_ms,
        seam_aware_ms,
        "mip level encoded"
    );
    let mut out = vec![shipped];
    out.append(&mut below);
    Ok(out)
}

/// A mip level encoded in the job's format: its blocks, and the regular
/// encoding's and the seam-aware search's milliseconds.
fn encode_mip(
    b: &TextureBinding,
    level: &ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<(Shipped, u64, u64), PipelineError> {
    let (width, height) = (level.grid.width as u32, level.grid.height as u32);
    if opts.format == Format::Bc7 {
        let enc = bc7_level::encode_level(b, level, opts, plan)?;
        let shipped = Shipped::Bc7 {
            width,
            height,
            blocks: enc.shipped,
        };
        return Ok((shipped, enc.encode_ms, enc.seam_aware_ms));
    }
    let enc = encode_level(b, level, opts, plan)?;
    let shipped = Shipped::Bc1(MipLevel {
        width,
        height,
        blocks: enc.shipped,
        alpha: enc.alpha_shipped,
    });
    Ok((shipped, enc.encode_ms, enc.seam_aware_ms))
}

/// The key of a BC7 encoding's alpha figures: one decoding, exact on
/// every GPU, where BC1's alpha has one per decoder.
const BC7_DECODING: &str = "exact";

fn seam_summary(level: &ErasedLevel, opts: &ProcessOptions) -> SeamSummary {
    let total = level.seams.total_length();
    let share = |verdicts: &[bool], closed: bool| {
        let picked = level
            .seams
            .seams
            .iter()
            .zip(verdicts)
            .filter(|(_, c)| **c == closed);
        let (edges, length) = picked.fold((0, 0.0), |(n, l), (s, _)| (n + 1, l + s.length));
        SeamShare {
            edges,
            length_share: if total > 0.0 { length / total } else { 0.0 },
        }
    };
    let closed = &level.verdicts.closed;
    SeamSummary {
        tolerance: (!opts.erase_all).then_some(opts.seam_tolerance),
        closed: share(closed, true),
        left: share(closed, false),
        spared: level.verdicts.spared,
        padded_texels: level.padded,
        repainted: level.harm.clone(),
        alpha: level.alpha.as_ref().map(|a| AlphaSeamSummary {
            closed: share(&a.verdicts.closed, true),
            left: share(&a.verdicts.closed, false),
            spared: a.verdicts.spared,
            padded_texels: a.padded,
            repainted: a.harm.clone(),
        }),
    }
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
        AlphaFormat::Dropped | AlphaFormat::Bc7 => None,
    };
    Decoder::ALL
        .into_iter()
        .map(|d| Some((d, per(d)?)))
        .collect()
}
