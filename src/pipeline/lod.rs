//! The job's levels of detail (`lod`): the rewritten model simplified with
//! the seam test, each level measured on the job's own erased texture and
//! DDS, and written into the model (`MSFT_lod`) and, with `lod_files`, as
//! `<name>.lodN.glb` beside it.

use std::borrow::Cow;
use std::collections::HashMap;

use crate::bc1::{dds::read_dds, decode_image};
use crate::lod::closed::ClosedSeams;
use crate::lod::seam_texture::{Allowance, JudgedImage, SampledTexture, TextureJudge};
use crate::lod::{
    self, gltf_lod, LevelIndices, LodError, LodLevel, LodTexture, ModelConstraints,
    DEFAULT_TEXTURE_SIZE, JUDGED_CHORD_TEXELS, LEVEL_MARGIN_DDS, LEVEL_MARGIN_ERASED,
    SEAM_TOLERANCE_TEXELS,
};
use crate::model::load::{ResolveError, Sampling};
use crate::model::{
    find_seams, plan_from_memory, LoadOptions, PlannedTexture, Resolver, SeamSet, Texture,
    UvTriangle,
};
use crate::picture::{seams_png, SeamPicture, Version};
use crate::seam::grid::TexelGrid;
use crate::seam::metric::colour_channels;
use crate::seam::SeamMetric;

use super::level::rgb;
use super::{Format, OutputFile, Report};

/// The job's files first, then the input's: what the rewritten model (and
/// each level) refers to.
struct JobFiles<'a> {
    files: &'a [OutputFile],
    input: &'a dyn Resolver,
}

impl Resolver for JobFiles<'_> {
    fn read(&self, path: &str) -> Result<Cow<'_, [u8]>, ResolveError> {
        match self.files.iter().find(|f| f.name == path) {
            Some(f) => Ok(Cow::Borrowed(&f.bytes)),
            None => self.input.read(path),
        }
    }
}

/// What the levels add to the job.
pub(super) struct Lods {
    /// The rewritten model, now with its levels.
    pub model: Vec<u8>,
    /// The levels' buffer beside a `.gltf`, and `<name>.lodN.glb`.
    pub files: Vec<OutputFile>,
    pub levels: Vec<LodLevel>,
    pub warnings: Vec<String>,
}

/// One processed texture's level-0 images, decoded once for every level.
struct Measured<'a> {
    image: usize,
    /// The texture's name in the job's files (`<name>.seams.png`).
    name: &'a str,
    width: usize,
    height: usize,
    erased: Texture,
    dds: Option<Vec<f32>>,
    /// The erased image as RGB, with `pictures`.
    erased_rgb: Option<Vec<f32>>,
    /// The closed seams of the full mesh, each as its half-edges' UVs.
    closed: &'a [[[[f64; 2]; 2]; 2]],
}

/// The levels of `model` (the rewritten model, named `model_name`);
/// `referring` is the same model referring to its textures as files, the
/// base of each `<name>.lodN.glb` (with `lod_files`).
pub(super) fn add_lods(
    model_name: &str,
    model: &[u8],
    referring: Option<&[u8]>,
    report: &Report,
    files: &[OutputFile],
    input: &dyn Resolver,
) -> Result<Lods, LodError> {
    let ratios = report.options.lod.as_slice();
    let made = make_levels(
        model_name,
        model,
        referring,
        report,
        files,
        input,
        ratios,
        Constrained::Seams,
    )?;
    let (model, beside) = gltf_lod::with_lods(
        model,
        &made.indices,
        ratios,
        &format!("{}.lod.bin", stem(model_name)),
    )?;
    let mut out_files = made.files;
    if let Some((name, bytes)) = beside {
        out_files.insert(0, OutputFile { name, bytes });
    }
    Ok(Lods {
        model,
        files: out_files,
        levels: made.levels,
        warnings: made.warnings,
    })
}

/// Whether the seam test constrains the simplifier.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Constrained {
    /// The job's way: the seam test of `lod`.
    Seams,
    /// meshoptimizer alone, for comparison.
    Plain,
}

/// Levels made and measured.
pub struct MadeLevels {
    /// Level 0 (the full mesh), then one per ratio.
    pub levels: Vec<LodLevel>,
    pub indices: Vec<LevelIndices>,
    /// `<name>.lodN.glb`, where a referring model was given.
    pub files: Vec<OutputFile>,
    pub warnings: Vec<String>,
}

fn stem(model_name: &str) -> &str {
    model_name.rsplit_once('.').map_or(model_name, |(s, _)| s)
}

/// The levels of a job's rewritten model (`model`, before any levels were
/// added to it) at `ratios`, each measured on the job's erased texture and
/// DDS (`report`, `files`): what `lod` does, and, `Plain`, what
/// meshoptimizer alone would do, for comparison.
#[allow(clippy::too_many_arguments)]
pub fn make_levels(
    model_name: &str,
    model: &[u8],
    referring: Option<&[u8]>,
    report: &Report,
    files: &[OutputFile],
    input: &dyn Resolver,
    ratios: &[f64],
    constrained: Constrained,
) -> Result<MadeLevels, LodError> {
    let resolver = JobFiles { files, input };
    let meshes = gltf_lod::read_meshes(model, &resolver)?;
    let mut warnings: Vec<String> = meshes
        .iter()
        .filter_map(|m| m.kept_whole.as_ref())
        .map(|why| format!("lod: {why}: kept whole in every level"))
        .collect();
    for w in &warnings {
        tracing::warn!(warning = %w, "mesh not simplified");
    }
    let size = report
        .textures
        .iter()
        .map(|t| t.width.max(t.height) as f64)
        .fold(0.0, f64::max);
    let size = if size > 0.0 {
        size
    } else {
        DEFAULT_TEXTURE_SIZE
    };
    let measured = measured_textures(report, files);
    let (found, samplings) = texture_seams(model_name, model, &resolver, report, &measured)?;
    let chains: Vec<Option<ClosedSeams>> = found
        .iter()
        .zip(&measured)
        .map(|(found, m)| {
            found
                .as_ref()
                .map(|(seams, _, triangles)| ClosedSeams::new(seams, triangles, m.closed))
        })
        .collect();
    let measure = |bytes: &[u8], level: usize| {
        level_seams(
            model_name, bytes, &resolver, report, &measured, &chains, level,
        )
    };
    let (full_textures, _) = measure(model, 0)?;
    let judges = texture_judges(&measured, &found, &chains, &full_textures, &samplings);
    let constraints = match constrained {
        Constrained::Seams => ModelConstraints::Seams {
            tolerance: SEAM_TOLERANCE_TEXELS / size,
            most: JUDGED_CHORD_TEXELS / size,
            judges: &judges,
        },
        Constrained::Plain => ModelConstraints::Plain,
    };
    let geometry = lod::simplify_model(&meshes, ratios, &constraints);
    let full = lod::full_triangles(&meshes);
    for (k, g) in geometry.iter().enumerate() {
        // Short of the ratio by half again: the seams stopped the
        // simplifier, which the caller should know.
        let wanted = full as f64 * ratios[k];
        if constrained == Constrained::Seams && g.triangles as f64 > 1.5 * wanted.max(1.0) {
            warnings.push(format!(
                "lod {}: {} triangles for a ratio of {} ({wanted:.0}): the seam constraints \
                 stop the simplifier there",
                k + 1,
                g.triangles,
                ratios[k]
            ));
        }
        if g.unsettled > 0 {
            warnings.push(format!(
                "lod {}: {} primitive(s) stopped early: their seams would not settle",
                k + 1,
                g.unsettled
            ));
        }
    }

    let stem = stem(model_name);
    let mut levels = Vec::with_capacity(ratios.len() + 1);
    levels.push(level_row(
        0,
        1.0,
        full,
        0.0,
        (0.0, 0.0),
        (0, 0),
        full_textures,
        None,
    ));
    let mut out_files = Vec::new();
    for (k, g) in geometry.iter().enumerate() {
        let glb = gltf_lod::level_glb(model, &g.indices)?;
        let (textures, pictures) = measure(&glb, k + 1)?;
        out_files.extend(pictures);
        let file = match referring {
            Some(base) => {
                let name = format!("{stem}.lod{}.glb", k + 1);
                let bytes = gltf_lod::level_glb(base, &g.indices)?;
                out_files.push(OutputFile {
                    name: name.clone(),
                    bytes,
                });
                Some(name)
            }
            None => None,
        };
        levels.push(level_row(
            k + 1,
            ratios[k],
            g.triangles,
            g.error,
            (g.hausdorff, g.hausdorff_plain),
            (g.seam_vertices, g.seam_locked),
            textures,
            file,
        ));
        tracing::info!(
            level = k + 1,
            ratio = ratios[k],
            triangles = g.triangles,
            hausdorff = g.hausdorff,
            "level of detail made"
        );
    }
    Ok(MadeLevels {
        levels,
        indices: geometry.into_iter().map(|g| g.indices).collect(),
        files: out_files,
        warnings,
    })
}

#[allow(clippy::too_many_arguments)]
fn level_row(
    level: usize,
    ratio: f64,
    triangles: usize,
    error: f64,
    (hausdorff, hausdorff_plain): (f64, f64),
    (seam_vertices, seam_vertices_locked): (usize, usize),
    textures: Vec<LodTexture>,
    file: Option<String>,
) -> LodLevel {
    let worst = |f: fn(&LodTexture) -> Option<f64>| textures.iter().filter_map(f).reduce(f64::max);
    LodLevel {
        level,
        ratio,
        triangles,
        seam_edges: textures.iter().map(|t| t.seam_edges).sum(),
        seam_rms_erased: worst(|t| t.seam_rms_erased),
        seam_rms_dds: worst(|t| t.seam_rms_dds),
        seam_rms_closed_erased: worst(|t| t.seam_rms_closed_erased),
        seam_rms_closed_dds: worst(|t| t.seam_rms_closed_dds),
        simplifier_error: error,
        hausdorff,
        hausdorff_plain,
        seam_vertices,
        seam_vertices_locked,
        file,
        textures,
    }
}

/// Each processed texture's erased image and its DDS (BC1) decoded.
fn measured_textures<'a>(report: &'a Report, files: &[OutputFile]) -> Vec<Measured<'a>> {
    let bytes_of = |name: &str| files.iter().find(|f| f.name == name).map(|f| &f.bytes[..]);
    let mut out = Vec::new();
    for t in &report.textures {
        let Some(erased) = bytes_of(&t.files.erased) else {
            continue;
        };
        let Ok(erased) = Texture::decode(erased, u32::MAX) else {
            continue;
        };
        let dds = (report.options.format == Format::Bc1)
            .then(|| t.files.dds.as_deref().and_then(bytes_of))
            .flatten()
            .and_then(|b| read_dds(b).ok())
            .and_then(|d| {
                let l = d.levels.into_iter().next()?;
                decode_image(&l.blocks, l.width as usize, l.height as usize).ok()
            });
        let erased_rgb = report.options.pictures.then(|| rgb(&erased).into_owned());
        out.push(Measured {
            image: t.image,
            name: &t.name,
            width: t.width,
            height: t.height,
            erased,
            dds,
            erased_rgb,
            closed: &t.closed_seams,
        });
    }
    out
}

/// One texture's seams on one level's mesh, its grid, and the triangles
/// the seams were found in.
type FoundSeams = (SeamSet, TexelGrid, Vec<UvTriangle>);

/// Each measured texture's seams on the mesh of `bytes` (`None` where the
/// model no longer samples it); and which primitive samples which image.
fn texture_seams(
    name: &str,
    bytes: &[u8],
    files: &dyn Resolver,
    report: &Report,
    measured: &[Measured],
) -> Result<(Vec<Option<FoundSeams>>, Vec<Sampling>), LodError> {
    let opts = LoadOptions {
        extra_maps: report.options.extra_maps,
        ..LoadOptions::default()
    };
    let plan =
        plan_from_memory(name, bytes, files, &opts).map_err(|e| LodError::Model(e.to_string()))?;
    let samplings = plan.samplings;
    let mut planned: Vec<Option<PlannedTexture>> = plan.textures.into_iter().map(Some).collect();
    let found = measured
        .iter()
        .map(|m| {
            let pt = planned
                .iter_mut()
                .find(|p| p.as_ref().is_some_and(|p| p.image == m.image))?
                .take()?;
            let grid = TexelGrid {
                width: m.width,
                height: m.height,
                wrap_s: pt.wrap_s,
                wrap_t: pt.wrap_t,
            };
            let seams = find_seams(&pt.triangles, m.width, m.height);
            Some((seams, grid, pt.triangles))
        })
        .collect();
    Ok((found, samplings))
}

/// Per primitive (mesh, primitive), the texture test of its chords: on
/// every measured texture it samples, the erased image and the DDS, each
/// allowed the margin a level may add to the full mesh's seam RMS.
fn texture_judges<'a>(
    measured: &'a [Measured],
    found: &[Option<FoundSeams>],
    chains: &'a [Option<ClosedSeams>],
    full: &[LodTexture],
    samplings: &[Sampling],
) -> HashMap<(usize, usize), TextureJudge<'a>> {
    let mut judges: HashMap<(usize, usize), TextureJudge<'a>> = HashMap::new();
    for s in samplings {
        let Some(k) = measured.iter().position(|m| m.image == s.image) else {
            continue;
        };
        let (m, Some((_, grid, _)), Some(closed)) = (&measured[k], &found[k], &chains[k]) else {
            continue;
        };
        let Some(figures) = full.iter().find(|t| t.image == s.image) else {
            continue;
        };
        let channels = m.erased.channels;
        let compared = colour_channels(channels);
        let mut images = vec![JudgedImage {
            data: &m.erased.data,
            channels,
            compared,
            allowance: Allowance::new(
                figures.seam_rms_closed_erased,
                figures.seam_rms_erased,
                LEVEL_MARGIN_ERASED,
            ),
        }];
        if let Some(dds) = &m.dds {
            images.push(JudgedImage {
                data: dds,
                channels: 3,
                compared: compared.min(3),
                allowance: Allowance::new(
                    figures.seam_rms_closed_dds,
                    figures.seam_rms_dds,
                    LEVEL_MARGIN_DDS,
                ),
            });
        }
        judges
            .entry((s.mesh, s.primitive))
            .or_insert_with(|| TextureJudge {
                textures: Vec::new(),
            })
            .textures
            .push(SampledTexture {
                grid: *grid,
                sampling: *s,
                images,
                closed,
            });
    }
    judges
}

/// The seam figures of every processed texture on the mesh of `bytes`
/// (level `level`); `chains` holds each texture's full-mesh seams with
/// their verdicts. With `pictures`, below level 0 (the job's own picture
/// shows that), each texture's `<name>.lodN.seams.png` too.
fn level_seams(
    name: &str,
    bytes: &[u8],
    files: &dyn Resolver,
    report: &Report,
    measured: &[Measured],
    chains: &[Option<ClosedSeams>],
    level: usize,
) -> Result<(Vec<LodTexture>, Vec<OutputFile>), LodError> {
    let (found, _) = texture_seams(name, bytes, files, report, measured)?;
    let mut out = Vec::new();
    let mut pictures = Vec::new();
    for ((m, found), chains) in measured.iter().zip(found).zip(chains) {
        let Some((seams, grid, triangles)) = found else {
            continue;
        };
        let verdicts = match chains {
            Some(c) => c.classify(&seams, &triangles),
            None => vec![true; seams.seams.len()],
        };
        let closed = seams.select(&verdicts);
        let picture = match &m.erased_rgb {
            Some(erased) if level > 0 => {
                let file = level_picture(m, erased, &grid, &seams, &verdicts, level)?;
                let name = file.name.clone();
                pictures.push(file);
                Some(name)
            }
            _ => None,
        };
        let channels = m.erased.channels;
        let compared = colour_channels(channels);
        let rms = |metric: &SeamMetric| {
            (
                metric.seam_rms(&m.erased.data, channels, compared),
                m.dds
                    .as_ref()
                    .and_then(|d| metric.seam_rms(d, 3, compared.min(3))),
            )
        };
        let (seam_rms_erased, seam_rms_dds) = rms(&SeamMetric::new(&grid, &seams));
        let (seam_rms_closed_erased, seam_rms_closed_dds) = rms(&SeamMetric::new(&grid, &closed));
        out.push(LodTexture {
            image: m.image,
            seam_edges: seams.seams.len(),
            seam_rms_erased,
            seam_rms_dds,
            seam_rms_closed_erased,
            seam_rms_closed_dds,
            seams_picture: picture,
        });
    }
    Ok((out, pictures))
}

/// `<name>.lodN.seams.png`: the level's seams over the texture, lit by what
/// the DDS leaves of them, with close-ups of the worst closed ones in the
/// erased texture and the DDS (the same texture serves every level; what
/// changes is where the seams run).
fn level_picture(
    m: &Measured,
    erased: &[f32],
    grid: &TexelGrid,
    seams: &SeamSet,
    closed: &[bool],
    level: usize,
) -> Result<OutputFile, LodError> {
    let mut versions = vec![Version {
        name: "ERASED",
        data: erased,
    }];
    if let Some(dds) = &m.dds {
        versions.push(Version {
            name: "SEAM-AWARE BC1",
            data: dds,
        });
    }
    let bytes = seams_png(&SeamPicture {
        grid,
        versions,
        seams,
        closed,
        alpha_closed: None,
    })?;
    Ok(OutputFile {
        name: format!("{}.lod{level}.seams.png", m.name),
        bytes,
    })
}
