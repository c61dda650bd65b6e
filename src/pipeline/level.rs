//! One mip level of one texture through the engine's two stages: seams
//! judged and erased ([`erase_level`]), then encoded regular and seam-aware
//! ([`encode_level`]).

use std::borrow::Cow;
use std::time::Instant;

use rayon::prelude::*;

use super::alpha::{self, AlphaFormat, AlphaPlan};
use super::{ChartHarm, HarmCause, Method, PipelineError, ProcessOptions};
use crate::bc1::alpha::{encode_alpha_image, AlphaBlock};
use crate::bc1::alpha_seam_aware::{optimise_alpha, AlphaProblem};
use crate::bc1::punch::punch_through;
use crate::bc1::seam_aware::{optimise, Problem, SeamAwareOptions};
use crate::bc1::{self, Block};
use crate::model::{MeshEdges, SeamSet, Texture, TextureBinding, UvTriangle};
use crate::seam::charts::{harmed, ChartLabels, Charts, HARM_PSNR_DB};
use crate::seam::classify::{classify, ClassifyOptions, SeamVerdicts};
use crate::seam::erase::{
    erase_within, EraseOptions, EraseStats, Erased, Mode, BAND_MARGIN, MIP_BAND_MARGIN,
};
use crate::seam::masking::{mask, MaskingOptions};
use crate::seam::metric::seam_points_texel_length;
use crate::seam::padding::pad_left_seams;
use crate::seam::quadrature::QuadPoint;
use crate::seam::{colour_channels, TexelClasses, TexelGrid};

/// What every level of a texture reads of its mesh, whatever the level's
/// size: the welded edges, paired, and the triangles' charts. Found once,
/// before level 0; the mip chain would otherwise wait for both at each level.
pub(super) struct TextureMesh {
    pub(super) edges: MeshEdges,
    charts: ChartLabels,
}

impl TextureMesh {
    pub(super) fn new(triangles: &[UvTriangle]) -> Self {
        let (edges, charts) =
            rayon::join(|| MeshEdges::new(triangles), || ChartLabels::new(triangles));
        TextureMesh { edges, charts }
    }
}

/// One mip level of one texture, seam-erased.
pub(super) struct ErasedLevel {
    pub(super) grid: TexelGrid,
    /// Every seam, as the metric measures them.
    pub(super) seams: SeamSet,
    /// The seams closed (with every silhouette): what erasure and seam-aware
    /// encoding make agree.
    pub(super) closed: SeamSet,
    pub(super) verdicts: SeamVerdicts,
    /// Alpha's own verdicts, where they differ from the colour's.
    pub(super) alpha: Option<AlphaSeams>,
    pub(super) charts: Charts,
    /// Gutter texels filled from their own chart along the seams left open.
    pub(super) padded: usize,
    /// Charts whose colour the erasure still repainted under 30 dB.
    pub(super) harm: Vec<ChartHarm>,
    pub(super) classes: TexelClasses,
    /// The solver's output before rounding (the next mip level is filtered from it).
    pub(super) float: Texture,
    /// Rounded to the file's bit depth: what the PNG holds and BC1 encodes.
    pub(super) stored: Texture,
    pub(super) stats: EraseStats,
    pub(super) seams_ms: u64,
    pub(super) erase_ms: u64,
}

/// Which level of the mip chain is erased: how far seams are spared for
/// the charts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Rung {
    /// Level 0, the one the report judges: a chart still repainted after
    /// sparing the middle zone has every seam touching it spared.
    Base,
    /// A smaller level: charts a few texels across are mostly seam band,
    /// and closing any seam moves them; only the middle zone is spared, so
    /// that the agreeing seams stay closed however far the model is seen.
    Mip,
}

pub(super) fn erase_level(
    b: &TextureBinding,
    mesh: &TextureMesh,
    tex: &Texture,
    opts: &ProcessOptions,
    erase_alpha: bool,
    rung: Rung,
) -> Result<ErasedLevel, PipelineError> {
    let grid = TexelGrid {
        width: tex.width,
        height: tex.height,
        wrap_s: b.wrap_s,
        wrap_t: b.wrap_t,
    };
    let compared = colour_channels(tex.channels);
    let t = Instant::now();
    let seams = mesh.edges.seams(tex.width, tex.height);
    let charts = Charts::labelled(&grid, &b.triangles, &mesh.charts);
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
            &judging(opts),
        )
    };
    let seams_ms = t.elapsed().as_millis() as u64;

    let t = Instant::now();
    let (mut solved, harm) = judged_solve(
        b,
        &grid,
        (&tex.data, tex.channels, compared),
        &seams,
        &mut verdicts,
        &charts,
        (opts, rung),
    )?;
    let alpha_group = if erase_alpha && !opts.erase_all {
        alpha_apart(
            b,
            &grid,
            tex,
            &seams,
            &verdicts,
            &charts,
            (opts, rung),
            &mut solved.data,
        )?
    } else {
        None
    };
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
        alpha: alpha_group,
        charts,
        padded: solved.padded,
        harm,
        classes: solved.classes,
        float,
        stored,
        stats: solved.stats,
        seams_ms,
        erase_ms: t.elapsed().as_millis() as u64,
    })
}

/// Alpha judged on its own where its sides are painted apart while the
/// colour's agree, or the other way round.
pub(super) struct AlphaSeams {
    pub(super) verdicts: SeamVerdicts,
    /// The alpha seams closed, for the alpha figures and the seam-aware
    /// alpha search.
    pub(super) closed: SeamSet,
    pub(super) padded: usize,
    /// Charts whose alpha the erasure still repainted.
    pub(super) harm: Vec<ChartHarm>,
}

/// The solve for `verdicts`, then, unless every seam is to close, the
/// middle zone's edges whose closing repainted a chart spared and the
/// solve made again without them; where a chart is still repainted, every
/// edge touching it is spared, whatever its jump, and the solve made once
/// more. `data` is (texels, channels, channels compared).
#[allow(clippy::too_many_arguments)]
fn judged_solve(
    b: &TextureBinding,
    grid: &TexelGrid,
    (data, channels, compared): (&[f32], usize, usize),
    seams: &SeamSet,
    verdicts: &mut SeamVerdicts,
    charts: &Charts,
    (opts, rung): (&ProcessOptions, Rung),
) -> Result<(Solved, Vec<ChartHarm>), PipelineError> {
    // Each solve after the first starts from the band the one before ended
    // with: sparing seams leaves the rest's band as it was.
    let run = |closed: &[bool], prior: Option<&Solved>| {
        let prior = prior.and_then(|p| p.band.as_deref());
        solve(
            b,
            grid,
            data,
            channels,
            seams,
            closed,
            charts,
            (opts, rung),
            prior,
        )
    };
    let psnr = |solved: &Solved| charts.psnr_per_chart(&solved.data, data, channels, compared);
    let mut solved = run(&verdicts.closed, None)?;
    let mut per_chart = psnr(&solved);
    if !opts.erase_all {
        // The middle zone closes only where that repaints no chart.
        let spared = verdicts.spare(seams, charts, &harmed(&per_chart));
        if spared > 0 {
            tracing::debug!(spared, "seams left to spare their charts");
            solved = run(&verdicts.closed, Some(&solved))?;
            per_chart = psnr(&solved);
        }
        let still = harmed(&per_chart);
        if rung == Rung::Base && still.contains(&true) {
            let spared = verdicts.spare_touching(grid, seams, charts, &still);
            if spared > 0 {
                tracing::debug!(spared, "seams of every zone left to spare their charts");
                solved = run(&verdicts.closed, Some(&solved))?;
                per_chart = psnr(&solved);
            }
        }
    }
    let harm = chart_harm(charts, &b.triangles, per_chart, HarmCause::of(opts));
    Ok((solved, harm))
}

/// The charts `psnr` puts under [`HARM_PSNR_DB`], worst first, with where
/// they lie and why sparing could not keep them.
fn chart_harm(
    charts: &Charts,
    triangles: &[UvTriangle],
    psnr: Vec<Option<f64>>,
    cause: HarmCause,
) -> Vec<ChartHarm> {
    let under = |p: &Option<f64>| p.is_some_and(|p| p < HARM_PSNR_DB);
    if !psnr.iter().any(under) {
        return Vec::new();
    }
    let extents = charts.extents(triangles);
    let mut out: Vec<ChartHarm> = psnr
        .iter()
        .zip(&extents)
        .enumerate()
        .filter(|(_, (p, _))| under(p))
        .map(|(chart, (p, e))| ChartHarm {
            chart: chart as u32,
            texels: e.texels,
            psnr: p.unwrap_or(f64::INFINITY),
            uv_min: e.uv_min,
            uv_max: e.uv_max,
            cause,
        })
        .collect();
    out.sort_by(|a, b| a.psnr.total_cmp(&b.psnr).then(a.chart.cmp(&b.chart)));
    out
}

/// Judges the alpha of a texture whose alpha is erased by the same rule as
/// its colour, each side as its own chart paints it. Where the verdicts
/// differ from the colour's, alpha is solved on its own over its own closed
/// seams, and written into `solved`; where they agree, the joint solve
/// already did just that, and `None` says so.
#[allow(clippy::too_many_arguments)]
fn alpha_apart(
    b: &TextureBinding,
    grid: &TexelGrid,
    tex: &Texture,
    seams: &SeamSet,
    colour: &SeamVerdicts,
    charts: &Charts,
    (opts, rung): (&ProcessOptions, Rung),
    solved: &mut [f32],
) -> Result<Option<AlphaSeams>, PipelineError> {
    let Some(plane) = alpha::channel(tex) else {
        return Ok(None);
    };
    let mut verdicts = classify(grid, &plane, 1, 1, seams, charts, &judging(opts));
    if verdicts.closed == colour.closed {
        return Ok(None);
    }
    let (alone, harm) = judged_solve(
        b,
        grid,
        (&plane, 1, 1),
        seams,
        &mut verdicts,
        charts,
        (opts, rung),
    )?;
    let c = tex.channels;
    for (px, a) in solved.chunks_mut(c).zip(&alone.data) {
        px[c - 1] = *a;
    }
    tracing::debug!(
        alpha_closed = verdicts.closed_count(),
        colour_closed = colour.closed_count(),
        "alpha seams judged apart from the colour's"
    );
    Ok(Some(AlphaSeams {
        verdicts,
        closed: alone.closed,
        padded: alone.padded,
        harm,
    }))
}

/// How seams are judged, colour and alpha alike.
fn judging(opts: &ProcessOptions) -> ClassifyOptions {
    ClassifyOptions {
        tolerance: opts.seam_tolerance,
        remove_chart_offsets: opts.mode == Mode::Global,
    }
}

/// One erasure of a level with the seams `closed` selects.
struct Solved {
    closed: SeamSet,
    classes: TexelClasses,
    padded: usize,
    data: Vec<f32>,
    stats: EraseStats,
    /// The erasure's last band (see [`erase_within`]).
    band: Option<Vec<bool>>,
}

/// Pads the gutter along the seams left, then makes the closed seams agree,
/// over `channels` interleaved channels of `data`, starting from the band
/// `prior` where given.
#[allow(clippy::too_many_arguments)]
fn solve(
    b: &TextureBinding,
    grid: &TexelGrid,
    data: &[f32],
    channels: usize,
    seams: &SeamSet,
    closed: &[bool],
    charts: &Charts,
    (opts, rung): (&ProcessOptions, Rung),
    prior: Option<&[bool]>,
) -> Result<Solved, PipelineError> {
    let selected = seams.select(closed);
    // Only the gutter along the seams left is padded: with every seam closed
    // the texture is read as it is, without a copy (48 MiB at 2048²).
    let (input, padded) = match closed.iter().all(|&c| c) {
        true => (Cow::Borrowed(data), 0),
        false => {
            let mut input = crate::heap::copied(data);
            let padded = pad_left_seams(grid, &mut input, channels, seams, closed, charts);
            (Cow::Owned(input), padded)
        }
    };
    let classes = TexelClasses::with_inside(grid, charts.inside(), &selected);
    let erased = match opts.method {
        Method::Erase => erase_within(
            grid,
            &input,
            channels,
            &selected,
            &classes,
            &EraseOptions {
                band_margin: match rung {
                    Rung::Base => BAND_MARGIN,
                    Rung::Mip => MIP_BAND_MARGIN,
                },
                ..EraseOptions::new(opts.mode)
            },
            prior,
        )
        .map_err(|source| PipelineError::Erase {
            name: b.name.clone(),
            source,
        })?,
        Method::Masking => {
            let out = mask(
                grid,
                &input,
                channels,
                &selected,
                &classes,
                &MaskingOptions::default(),
            )
            .map_err(|source| PipelineError::Solve {
                name: b.name.clone(),
                source,
            })?;
            Erased {
                data: out,
                stats: EraseStats::default(),
                band: None,
            }
        }
    };
    Ok(Solved {
        closed: selected,
        classes,
        padded,
        data: erased.data,
        stats: erased.stats,
        band: erased.band,
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

/// RGB view of a texture: grey is replicated, alpha dropped (BC1 is
/// opaque). An RGB texture is its own view: no copy of a 2048² image
/// (48 MB, and its page faults) on the way to every encoding and figure.
pub(super) fn rgb(t: &Texture) -> Cow<'_, [f32]> {
    let ch = t.channels;
    if ch == 3 {
        return Cow::Borrowed(&t.data);
    }
    Cow::Owned(
        t.data
            .par_chunks(ch)
            .flat_map_iter(|c| {
                if ch < 3 {
                    [c[0]; 3]
                } else {
                    [c[0], c[1], c[2]]
                }
            })
            .collect(),
    )
}

/// A level encoded: the blocks the DDS holds, and the regular encoding's.
pub(super) struct EncodedLevel {
    pub(super) regular: Vec<Block>,
    pub(super) shipped: Vec<Block>,
    /// BC3's alpha blocks (empty for BC1).
    pub(super) alpha_regular: Vec<AlphaBlock>,
    pub(super) alpha_shipped: Vec<AlphaBlock>,
    /// For BC1 with one-bit alpha: the texels encoded transparent.
    pub(super) clear: Option<Vec<bool>>,
    pub(super) encode_ms: u64,
    pub(super) seam_aware_ms: u64,
}

/// Encodes a level: regular BC1, then the seam-aware search from it.
pub(super) fn encode_level(
    b: &TextureBinding,
    level: &ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<EncodedLevel, PipelineError> {
    let regular = encode_regular(b, level, opts, plan)?;
    let shipped = encode_seam_aware(b, level, &regular, opts, plan)?;
    Ok(EncodedLevel::new(regular, shipped))
}

/// A level's regular encoding, and what the seam-aware search starts from.
pub(super) struct Regular<'a> {
    pub(super) blocks: Vec<Block>,
    /// BC3's alpha blocks (empty for BC1).
    pub(super) alpha: Vec<AlphaBlock>,
    /// For BC1 with one-bit alpha: the texels encoded transparent.
    pub(super) clear: Option<Vec<bool>>,
    /// The level's RGB, and its alpha when the DDS keeps alpha.
    rgb: Cow<'a, [f32]>,
    alpha_values: Option<Vec<f32>>,
    pub(super) ms: u64,
}

/// The seam-aware encoding of a level.
pub(super) struct SeamAware {
    pub(super) blocks: Vec<Block>,
    pub(super) alpha: Vec<AlphaBlock>,
    pub(super) ms: u64,
}

impl EncodedLevel {
    pub(super) fn new(regular: Regular, shipped: SeamAware) -> Self {
        EncodedLevel {
            regular: regular.blocks,
            shipped: shipped.blocks,
            alpha_regular: regular.alpha,
            alpha_shipped: shipped.alpha,
            clear: regular.clear,
            encode_ms: regular.ms,
            seam_aware_ms: shipped.ms,
        }
    }
}

pub(super) fn encode_regular<'a>(
    b: &TextureBinding,
    level: &'a ErasedLevel,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<Regular<'a>, PipelineError> {
    let (w, h) = (level.grid.width, level.grid.height);
    let t = Instant::now();
    let rgb = rgb(&level.stored);
    let alpha_values = plan.and_then(|_| alpha::channel(&level.stored));
    let clear = match (plan, &alpha_values) {
        (Some(p), Some(a)) if p.format == AlphaFormat::Bc1a => {
            Some(alpha::transparent(a, p.cutoff.unwrap_or(0.5)))
        }
        _ => None,
    };
    let mut blocks = bc1::encode_image_for(&rgb, w, h, 3, opts.bc1_level, opts.decoder)
        .map_err(|e| PipelineError::encode(&b.name, e))?;
    if let Some(clear) = &clear {
        punch_through(&mut blocks, &rgb, clear, w, h, opts.decoder);
    }
    let alpha = match (plan.map(|p| p.format), &alpha_values) {
        (Some(AlphaFormat::Bc3), Some(a)) => encode_alpha_image(a, w, h, opts.decoder),
        _ => Vec::new(),
    };
    Ok(Regular {
        blocks,
        alpha,
        clear,
        rgb,
        alpha_values,
        ms: t.elapsed().as_millis() as u64,
    })
}

/// The seam-aware search from the regular encoding (a copy of it when
/// seam-aware encoding is off or no seam is closed).
pub(super) fn encode_seam_aware(
    b: &TextureBinding,
    level: &ErasedLevel,
    regular: &Regular,
    opts: &ProcessOptions,
    plan: Option<&AlphaPlan>,
) -> Result<SeamAware, PipelineError> {
    let (w, h) = (level.grid.width, level.grid.height);
    let t = Instant::now();
    let mut shipped = regular.blocks.clone();
    let mut alpha_shipped = regular.alpha.clone();
    if opts.seam_aware && !level.closed.seams.is_empty() {
        let points = seam_points_texel_length(&level.grid, &level.closed);
        let sa_opts = SeamAwareOptions {
            alpha: opts.seam_weight,
            target: opts.decoder,
            ..SeamAwareOptions::default()
        };
        let kept;
        let colour_points = match &regular.clear {
            Some(clear) => {
                kept = away_from_punched_blocks(&points, clear, w, h);
                &kept
            }
            None => &points,
        };
        let problem = Problem {
            width: w,
            height: h,
            target: &regular.rgb,
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
        if let (Some(a), Some(true)) = (&regular.alpha_values, plan.map(|p| p.erase)) {
            // Alpha keeps closed the seams closed for it, which differ
            // from the colour's where its sides are painted apart.
            let alpha_points = level
                .alpha
                .as_ref()
                .map(|g| seam_points_texel_length(&level.grid, &g.closed));
            let problem = AlphaProblem {
                width: w,
                height: h,
                target: a,
                inside: &level.classes.inside,
                points: alpha_points.as_ref().unwrap_or(&points),
            };
            optimise_alpha(&problem, &mut alpha_shipped, &sa_opts).log("alpha");
        }
    }
    Ok(SeamAware {
        blocks: shipped,
        alpha: alpha_shipped,
        ms: t.elapsed().as_millis() as u64,
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
