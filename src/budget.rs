//! What a job will cost, known from its [`Plan`] before any texel exists.
//!
//! A small file can ask for a great deal: a PNG of 65 KB may announce
//! 8192² texels; one UV coordinate of 1e6 makes a seam cross millions of
//! texel cells, each a quadrature piece, and a triangle spanning thousands of
//! texture periods is rasterised over all of them. So before a job decodes
//! anything, the quantities that drive its memory and time are counted from
//! the image headers and the triangles' UVs (a pass over the edges and
//! triangles, no texel touched), and the job is refused when one is over
//! its limit, with the quantity, its value and the limit named.
//!
//! The memory estimate is a linear model over those quantities whose
//! coefficients were measured (peak resident memory of the default job on
//! every shared model; `cargo bench --bench erase -- budget` prints both):
//! the decoded inputs of every texture are held through the job, and a
//! texture is erased beside the encoding of the one before it.

use std::fmt;

use crate::model::{MeshEdges, Plan, PlannedTexture, UvTriangle};
use crate::pipeline::ProcessOptions;
use crate::seam::grid::TexelGrid;
use crate::seam::quadrature::Segment;

/// Quadrature points per seam piece: three Gauss points for the difference
/// and three for the C1 term.
const POINTS_PER_PIECE: u64 = 6;

// The memory model, fitted to the peak resident memory of `seamstress
// process` running the default job on every shared model (`cargo bench
// --bench erase -- budget` prints both, with the quantities below): blub,
// Fox, CesiumMan, Duck, BoxTextured, cube_gradient_1024 and _128,
// WaterBottle, TextureTransformTest, 12 runs each on a two-core machine.
// A job keeps the pages it frees (`heap`), so its peak lies above the
// memory in use by the holes freed blocks leave, and one model's peak
// varies by up to 8% from run to run (blocks freed and made again by
// threads in whatever order they run). The estimate lies above the peak
// of every model whose peak is its erase (blub 1.22, Fox 1.19, WaterBottle
// 1.32 of the highest of three runs) and below those of the smallest ones,
// where the process itself weighs most (Duck 0.84, cube_gradient_128 0.77).
//
// The peak falls in one of two stages of the texture worked on, and the
// estimate takes the larger:
//
// * the erase (every model with seams but BoxTextured): per texel its
//   copies and conversions (padded input, solution, texel classes, charts,
//   distances, band numbering); per seam quadrature point its taps and the
//   system entries it adds; and the band of unknowns along the seams, whose
//   systems and multigrid levels hold most of the memory. The band is as
//   long as the seams and reaches as far as a seam's jump must spread,
//   which depends on the texels, but is 8–11% of the texture's side on
//   every shared model but BoxTextured (2%): so points × side stands for
//   it. Points alone cannot: blub and Fox, both 2048² with 98 100 and
//   168 228 points, hold 0.74 and 1.78 million unknowns.
// * the encoding (BoxTextured, whose band is small for its seams, and
//   TextureTransformTest, which has no seams and is not solved): the RGB
//   images the BC1 figures compare and their decodes, and the seam-aware
//   search's terms per quadrature point.
//
// On top of either, the process itself (code, libraries, thread stacks, the
// parsed model) and every texture's decoded input and output files, held
// until the job ends (WaterBottle, with four textures, alone measures it:
// more than the f32 input and the files, the fit's 14.6 B per channel-texel
// also covers what else a texture keeps).
//
// The coefficients were chosen to keep every run's est/peak inside
// [1/1.2, 1.25] (|peak − est| ≤ 20% of est) with the largest margin for
// the worst one, not by least squares: a linear programme maximises t with
// est ≤ 1.25·(1 − t)·min and est ≥ (1 + t)·max/1.2 over each model's runs,
// the stage that peaks taken for the lower bound and both stages for the
// upper. Every one of the 108 runs is at least 3.8% inside the band; blub,
// Fox and BoxTextured are nearest its top, CesiumMan, cube_gradient_1024,
// cube_gradient_128 and TextureTransformTest its bottom.

/// The process itself.
const BASE_BYTES: f64 = 10.5 * 1048576.0;
/// Bytes per texel and channel of every texture (level 0; a third more
/// with mips).
const HELD_BYTES_PER_CHANNEL_TEXEL: f64 = 14.6;
/// The erase of the texture worked on: bytes per texel (level 0)…
const ERASE_BYTES_PER_TEXEL: f64 = 24.0;
/// …per seam quadrature point…
const ERASE_BYTES_PER_POINT: f64 = 846.0;
/// …and per seam quadrature point and texel of the texture's side (the
/// band along the seams).
const ERASE_BYTES_PER_POINT_SIDE: f64 = 0.902;
/// Its encoding: bytes per texel. The level's float and stored copies, the
/// input's and the erased texture's RGB, the PNG's bytes and two decodings
/// of an encoding at a time (the figures of the regular encoding run beside
/// the seam-aware search): `cube_gradient_1024`, whose band is small,
/// peaks here at 126–132 MiB…
const ENCODE_BYTES_PER_TEXEL: f64 = 60.0;
/// …and per seam quadrature point (the seam-aware search's terms).
const ENCODE_BYTES_PER_POINT: f64 = 730.0;
/// An encoding beside the next texture's erase, per texel (its points as
/// above): not all of it is held when the erase peaks. WaterBottle, two
/// 2048² textures, peaks at 724–746 MiB, 139 MiB over its erase alone.
const BESIDE_BYTES_PER_TEXEL: f64 = 30.0;

/// Triangles' bounding boxes may cover this many times a texture's texels
/// (over all levels) before the job is refused: the shared models cover
/// 1.5–12×, Duck with its UVs tiled 10 × 10 times 290×; one whose UVs span
/// thousands of periods is refused in milliseconds instead of rasterised
/// for minutes.
pub const MAX_COVERAGE: u64 = 1024;

/// Quadrature points allowed per texel: seams crossing this many cells per
/// texel of the texture (over all levels) wrap around it many times over.
pub const MAX_POINTS_PER_TEXEL: u64 = 16;

/// What a job needs, summed over its textures and (with mips) levels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Need {
    /// Texels of every level of every texture.
    pub texels: u64,
    /// Seam quadrature points over every level, with the silhouettes'
    /// pieces counted alike (for [`MAX_POINTS_PER_TEXEL`]; the memory
    /// estimate takes the seams' alone).
    pub quadrature_points: u64,
    /// Texel cells the triangles are rasterised over (bounding boxes,
    /// clipped as the rasteriser clips them), every level.
    pub covered_texels: u64,
    /// Estimated peak memory, bytes.
    pub memory_bytes: u64,
}

/// The limits a job is held to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Peak memory one job may use, bytes.
    pub max_memory: u64,
}

/// A job over its budget: which quantity, how much, and the limit.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{quantity} {value} is over the limit of {limit}{why}")]
pub struct OverBudget {
    pub quantity: &'static str,
    pub value: String,
    pub limit: String,
    /// What usually causes it, with a leading separator, or empty.
    pub why: &'static str,
}

/// The quantities the memory estimate is linear in, as [`need`] counts them.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Terms {
    /// Texels times channels held through the job: every texture's level 0,
    /// a third more with mips.
    pub held_channel_texels: f64,
    /// Level-0 texels of the texture worked on at the peak (the one whose
    /// working set is largest).
    pub work_texels: u64,
    /// That texture's level-0 seam quadrature points.
    pub work_points: u64,
    /// Level-0 texels and seam points of the texture whose encoding runs
    /// beside that one's erase (the one before it; 0 for none).
    pub beside_texels: u64,
    pub beside_points: u64,
}

impl Terms {
    /// The estimated peak memory, bytes (saturating: a hostile plan
    /// estimates at `u64::MAX`).
    pub fn memory_bytes(&self) -> u64 {
        (BASE_BYTES + HELD_BYTES_PER_CHANNEL_TEXEL * self.held_channel_texels + stage_bytes(self))
            as u64
    }
}

/// The working sets at the peak: the texture worked on, and the encoding
/// of the one before beside its erase.
fn stage_bytes(t: &Terms) -> f64 {
    let beside = if t.beside_texels > 0 {
        BESIDE_BYTES_PER_TEXEL * t.beside_texels as f64
            + ENCODE_BYTES_PER_POINT * t.beside_points as f64
    } else {
        0.0
    };
    work_bytes(t) + beside
}

fn encode_bytes(texels: u64, points: u64) -> f64 {
    ENCODE_BYTES_PER_TEXEL * texels as f64 + ENCODE_BYTES_PER_POINT * points as f64
}

/// The working set of the texture `t` describes: the larger of its erase
/// (none without seams: such a texture is not solved) and its encoding.
fn work_bytes(t: &Terms) -> f64 {
    let (texels, points) = (t.work_texels as f64, t.work_points as f64);
    let erase = if t.work_points > 0 {
        ERASE_BYTES_PER_TEXEL * texels
            + (ERASE_BYTES_PER_POINT + ERASE_BYTES_PER_POINT_SIDE * texels.sqrt()) * points
    } else {
        0.0
    };
    erase.max(encode_bytes(t.work_texels, t.work_points))
}

/// Counts what `plan` will cost under `opts`.
pub fn need(plan: &Plan, opts: &ProcessOptions) -> Need {
    need_and_terms(plan, opts).0
}

/// [`need`], and the terms its memory estimate is made of.
pub fn need_and_terms(plan: &Plan, opts: &ProcessOptions) -> (Need, Terms) {
    let mut total = Need::default();
    let mut terms = Terms::default();
    // The texture before this one: its encoding runs beside this one's
    // erase (`pipeline::run_reporting`).
    let mut before: Option<(u64, u64)> = None;
    for t in &plan.textures {
        let (one, level0) = texture_need(t, opts.mips);
        let channels = f64::from(t.header.channels);
        let mut held = level0.texels as f64 * channels;
        if opts.mips {
            held *= 4.0 / 3.0;
        }
        terms.held_channel_texels += held;
        let alone = Terms {
            work_texels: level0.texels,
            work_points: level0.seam_points,
            ..Terms::default()
        };
        let mut beside = alone;
        if let Some((texels, points)) = before {
            (beside.beside_texels, beside.beside_points) = (texels, points);
        }
        for this in [alone, beside] {
            if stage_bytes(&this) > stage_bytes(&terms) {
                (terms.work_texels, terms.work_points) = (this.work_texels, this.work_points);
                (terms.beside_texels, terms.beside_points) =
                    (this.beside_texels, this.beside_points);
            }
        }
        before = Some((level0.texels, level0.seam_points));
        total.texels = total.texels.saturating_add(one.texels);
        total.quadrature_points = total
            .quadrature_points
            .saturating_add(one.quadrature_points);
        total.covered_texels = total.covered_texels.saturating_add(one.covered_texels);
    }
    total.memory_bytes = terms.memory_bytes();
    (total, terms)
}

/// Refuses a job whose need is over `limits`, or whose seams or triangles
/// wrap around its textures far more often than any real model does.
pub fn check(need: &Need, limits: &Limits) -> Result<(), OverBudget> {
    if need.covered_texels > need.texels.saturating_mul(MAX_COVERAGE) {
        return Err(OverBudget {
            quantity: "texels covered by triangles",
            value: need.covered_texels.to_string(),
            limit: need.texels.saturating_mul(MAX_COVERAGE).to_string(),
            why: " (1024 times the textures' texels: UVs span too many texture periods)",
        });
    }
    let points_limit = need.texels.saturating_mul(MAX_POINTS_PER_TEXEL);
    if need.quadrature_points > points_limit {
        return Err(OverBudget {
            quantity: "seam quadrature points",
            value: need.quadrature_points.to_string(),
            limit: points_limit.to_string(),
            why: " (16 per texel: seams span too many texture periods)",
        });
    }
    if need.memory_bytes > limits.max_memory {
        return Err(OverBudget {
            quantity: "estimated memory",
            value: Bytes(need.memory_bytes).to_string(),
            limit: Bytes(limits.max_memory).to_string(),
            why: " (see --max-memory)",
        });
    }
    Ok(())
}

/// Level 0 of a texture as the memory estimate sees it.
#[derive(Clone, Copy)]
struct Level0 {
    texels: u64,
    /// Quadrature points of its seams alone: silhouettes make none.
    seam_points: u64,
}

/// One texture's quantities over the levels the job makes of it
/// (`memory_bytes` left at zero), and those of its level 0.
fn texture_need(t: &PlannedTexture, mips: bool) -> (Need, Level0) {
    let (mut w, mut h) = (t.header.width as usize, t.header.height as usize);
    let mut need = Need::default();
    let mut level0 = None;
    // Welded once: only which half-edges differ depends on the level's size.
    let edges = MeshEdges::new(&t.triangles);
    loop {
        let (seam_points, silhouette_points) = quadrature_points(t, &edges, w, h);
        let level = Need {
            texels: (w * h) as u64,
            covered_texels: covered(&t.triangles, w, h),
            quadrature_points: seam_points.saturating_add(silhouette_points),
            memory_bytes: 0,
        };
        need.texels = need.texels.saturating_add(level.texels);
        need.covered_texels = need.covered_texels.saturating_add(level.covered_texels);
        need.quadrature_points = need
            .quadrature_points
            .saturating_add(level.quadrature_points);
        let first = *level0.get_or_insert(Level0 {
            texels: level.texels,
            seam_points,
        });
        if !mips || (w == 1 && h == 1) {
            return (need, first);
        }
        (w, h) = ((w / 2).max(1), (h / 2).max(1));
    }
}

/// Cells the rasteriser visits: each triangle's texel bounding box, clipped
/// to twice the texture per side as `seam::texels` clips it.
fn covered(triangles: &[UvTriangle], w: usize, h: usize) -> u64 {
    let span = |a: f64, b: f64, c: f64, n: usize| -> u64 {
        let (lo, hi) = (a.min(b).min(c) * n as f64, a.max(b).max(c) * n as f64);
        let cells = (hi.ceil() - lo.floor() + 1.0).max(1.0);
        (cells.min(2.0 * n as f64 + 1.0)) as u64
    };
    triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.uvs;
            span(a[0], b[0], c[0], w).saturating_mul(span(a[1], b[1], c[1], h))
        })
        .fold(0u64, u64::saturating_add)
}

/// Quadrature points of the seams and of the silhouettes at one level:
/// one piece per cell crossing of either side, six points a piece. (The
/// erasure makes points of the seams alone; a silhouette's pieces are the
/// cells it marks, counted alike against [`MAX_POINTS_PER_TEXEL`].)
fn quadrature_points(t: &PlannedTexture, edges: &MeshEdges, w: usize, h: usize) -> (u64, u64) {
    let grid = TexelGrid {
        width: w,
        height: h,
        wrap_s: t.wrap_s,
        wrap_t: t.wrap_t,
    };
    let seams = edges.seams(w, h);
    let pieces = |uv: [[f64; 2]; 2]| crossings(Segment::from_uv(&grid, uv));
    let seam_pieces = seams
        .seams
        .iter()
        .map(|s| 1u64.saturating_add(pieces(s.a)).saturating_add(pieces(s.b)))
        .fold(0u64, u64::saturating_add);
    let silhouette_pieces = seams
        .silhouettes
        .iter()
        .map(|s| 1u64.saturating_add(pieces(s.uv)))
        .fold(0u64, u64::saturating_add);
    (
        seam_pieces.saturating_mul(POINTS_PER_PIECE),
        silhouette_pieces.saturating_mul(POINTS_PER_PIECE),
    )
}

/// Integer x or y lines a segment crosses.
fn crossings(s: Segment) -> u64 {
    (0..2)
        .map(|axis| {
            let (a, b) = (s.start[axis], s.end[axis]);
            let (lo, hi) = (a.min(b), a.max(b));
            // Integers k with lo < k < hi; saturating casts keep 1e300 finite.
            (hi.ceil() - lo.floor() - 1.0).max(0.0) as u64
        })
        .fold(0u64, u64::saturating_add)
}

/// Bytes as people read them: "3.1 GiB".
pub struct Bytes(pub u64);

impl fmt::Display for Bytes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
        let mut v = self.0 as f64;
        let mut unit = 0;
        while v >= 1024.0 && unit + 1 < UNITS.len() {
            v /= 1024.0;
            unit += 1;
        }
        if unit == 0 {
            write!(f, "{} B", self.0)
        } else {
            write!(f, "{v:.1} {}", UNITS[unit])
        }
    }
}

/// Parses "512M", "4G", "4GiB", "1.5g" or a plain number of bytes.
pub fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let value: f64 = num
        .parse()
        .map_err(|_| format!("{s:?} is not an amount of memory (e.g. 512M, 4G)"))?;
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" | "kib" => 1 << 10,
        "m" | "mb" | "mib" => 1 << 20,
        "g" | "gb" | "gib" => 1 << 30,
        "t" | "tb" | "tib" => 1 << 40,
        _ => return Err(format!("{s:?}: unknown unit (use K, M, G or T)")),
    };
    let bytes = value * scale as f64;
    if !bytes.is_finite() || bytes < 1.0 || bytes > u64::MAX as f64 {
        return Err(format!("{s:?} is not a usable amount of memory"));
    }
    Ok(bytes as u64)
}

/// The memory this process may really use, read when it is called: what
/// the kernel counts as available (`MemAvailable`: free memory and what it
/// can reclaim without swapping, so less what every other process holds),
/// or less within a container's or a service's cgroup limit, or under an
/// address-space limit (`ulimit -v`).
pub fn usable_memory() -> u64 {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok();
    let cgroups = std::fs::read_to_string("/proc/self/cgroup")
        .map(|text| cgroup_rooms(&text))
        .unwrap_or_default();
    usable(meminfo.as_deref(), &cgroups, address_space_limit())
}

/// The default budget of each of `jobs` jobs run at once: the usable
/// memory shared out, since every one of them may be at its peak together.
/// `process --jobs` and `serve --workers` both take it.
pub fn memory_per_job(jobs: usize) -> u64 {
    usable_memory() / jobs.max(1) as u64
}

/// [`usable_memory`] from what it reads: `/proc/meminfo`'s text, the room
/// left under each cgroup limit above this process, and the address-space
/// limit. Nothing known is no limit.
fn usable(meminfo: Option<&str>, cgroups: &[u64], address_space: Option<u64>) -> u64 {
    let mut limit = meminfo.and_then(available_memory).unwrap_or(u64::MAX);
    for &room in cgroups {
        limit = limit.min(room);
    }
    if let Some(rl) = address_space {
        // Address space is not resident memory: code, thread stacks and
        // allocator reservations take some that is never touched.
        limit = limit.min(rl / 4 * 3);
    }
    limit
}

/// `MemAvailable` from `/proc/meminfo`'s text; `MemTotal` on kernels
/// before 3.14, which do not estimate it.
fn available_memory(meminfo: &str) -> Option<u64> {
    let field = |name: &str| {
        meminfo.lines().find_map(|l| {
            let kb = l.strip_prefix(name)?.strip_prefix(':')?;
            kb.trim().strip_suffix("kB")?.trim().parse::<u64>().ok()
        })
    };
    field("MemAvailable")
        .or_else(|| field("MemTotal"))
        .map(|kb| kb.saturating_mul(1024))
}

/// One cgroup's memory files, version 2's names or version 1's.
const CGROUP_FILES: [(&str, [&str; 3]); 2] = [
    // The hierarchy's mount, its limit, its usage, and its statistics.
    (
        "/sys/fs/cgroup",
        ["memory.max", "memory.current", "memory.stat"],
    ),
    (
        "/sys/fs/cgroup/memory",
        [
            "memory.limit_in_bytes",
            "memory.usage_in_bytes",
            "memory.stat",
        ],
    ),
];

/// The room under every memory limit of the cgroups holding this process
/// (its own and each one above it, whose limits hold it too), in both
/// hierarchies; `proc_self_cgroup` is `/proc/self/cgroup`'s text.
fn cgroup_rooms(proc_self_cgroup: &str) -> Vec<u64> {
    let (v2, v1) = cgroup_paths(proc_self_cgroup);
    let mut rooms = Vec::new();
    for (path, (mount, [max, current, stat])) in [v2, v1].into_iter().zip(CGROUP_FILES) {
        let Some(path) = path else { continue };
        let mut dir = std::path::PathBuf::from(mount);
        // Outside its cgroup namespace's root a process sees `..` in its
        // path, and in a container's namespace a path the container's mount
        // does not show: the mount is the nearest cgroup known then.
        if !path.split('/').any(|c| c == "..") {
            dir.extend(path.split('/').filter(|c| !c.is_empty()));
        }
        let dirs = dir
            .ancestors()
            .take_while(|d| d.starts_with(mount))
            .filter(|d| d.is_dir());
        for d in dirs {
            let read = |name: &str| std::fs::read_to_string(d.join(name)).ok();
            if let (Some(max), Some(current)) = (read(max), read(current)) {
                rooms.extend(cgroup_room(&max, &current, read(stat).as_deref()));
            }
        }
    }
    rooms
}

/// From `/proc/self/cgroup`'s text, the process's cgroup in the version 2
/// hierarchy (`0::PATH`) and in version 1's memory hierarchy
/// (`N:...memory...:PATH`).
fn cgroup_paths(text: &str) -> (Option<&str>, Option<&str>) {
    let (mut v2, mut v1) = (None, None);
    for line in text.lines() {
        let mut parts = line.splitn(3, ':');
        let (Some(id), Some(controllers), Some(path)) = (parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        if id == "0" && controllers.is_empty() {
            v2 = Some(path);
        } else if controllers.split(',').any(|c| c == "memory") {
            v1 = Some(path);
        }
    }
    (v2, v1)
}

/// The room left under one cgroup's limit: the limit less what its
/// processes use, counting the page cache it could drop (`inactive_file`)
/// as room, as the kernel does before it reclaims anything else. `None`
/// without a limit (`max`, or version 1's near-2⁶³ "unlimited").
fn cgroup_room(max: &str, current: &str, stat: Option<&str>) -> Option<u64> {
    let limit = max.trim().parse::<u64>().ok().filter(|&v| v < 1 << 60)?;
    let used = current.trim().parse::<u64>().ok()?;
    let stat_field = |name: &str| {
        stat?.lines().find_map(|l| {
            let (key, value) = l.split_once(' ')?;
            (key == name).then(|| value.trim().parse::<u64>().ok())?
        })
    };
    // Version 1 counts the hierarchy's page cache in `total_inactive_file`
    // (its usage is the hierarchy's too), version 2 in `inactive_file`.
    let reclaimable = stat_field("total_inactive_file")
        .or_else(|| stat_field("inactive_file"))
        .unwrap_or(0);
    Some(limit.saturating_sub(used.saturating_sub(reclaimable)))
}

fn address_space_limit() -> Option<u64> {
    let mut rl = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes into the struct we own and reads nothing else.
    let ok = unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut rl) } == 0;
    (ok && rl.rlim_cur != libc::RLIM_INFINITY).then_some(rl.rlim_cur)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crossings_count_integer_lines_strictly_inside() {
        let s = |a: [f64; 2], b: [f64; 2]| Segment { start: a, end: b };
        assert_eq!(crossings(s([0.5, 0.5], [0.7, 0.9])), 0);
        assert_eq!(crossings(s([0.5, 0.5], [3.5, 0.5])), 3);
        assert_eq!(crossings(s([1.0, 0.5], [3.0, 0.5])), 1);
        assert_eq!(crossings(s([-2.5, -1.5], [2.5, 1.5])), 5 + 3);
        assert_eq!(crossings(s([-1e300, 0.0], [1e300, 0.0])), u64::MAX);
    }

    #[test]
    fn bytes_parse_and_print() {
        assert_eq!(parse_bytes("512M"), Ok(512 << 20));
        assert_eq!(parse_bytes("4G"), Ok(4 << 30));
        assert_eq!(parse_bytes("1.5GiB"), Ok(3 << 29));
        assert_eq!(parse_bytes("1000"), Ok(1000));
        assert!(parse_bytes("lots").is_err());
        assert!(parse_bytes("4X").is_err());
        assert!(parse_bytes("0").is_err());
        assert_eq!(Bytes(3 << 29).to_string(), "1.5 GiB");
        assert_eq!(Bytes(12).to_string(), "12 B");
    }

    #[test]
    fn the_estimate_is_the_process_and_the_terms() {
        let nothing = Terms::default();
        assert_eq!(nothing.memory_bytes(), BASE_BYTES as u64);
        // A 2048² RGB texture with blub's seams: 533 MiB (measured 515–522).
        let rgb = Terms {
            held_channel_texels: 3.0 * 4194304.0,
            work_texels: 4194304,
            work_points: 98100,
            ..Terms::default()
        };
        assert_eq!(rgb.memory_bytes() >> 20, 533);
        // Without seams it is not solved, only encoded.
        let seamless = Terms {
            work_points: 0,
            ..rgb
        };
        assert!(seamless.memory_bytes() < rgb.memory_bytes());
        // Longer seams, and the same seams on a larger texture, cost more.
        let longer = Terms {
            work_points: 2 * 98100,
            ..rgb
        };
        assert!(longer.memory_bytes() > rgb.memory_bytes());
        // Erased beside another texture's encoding: both working sets.
        let beside = Terms {
            beside_texels: 4194304,
            beside_points: 98100,
            ..rgb
        };
        assert!(beside.memory_bytes() > rgb.memory_bytes());
        let hostile = Terms {
            work_texels: u64::MAX,
            ..rgb
        };
        assert_eq!(hostile.memory_bytes(), u64::MAX);
    }

    #[test]
    fn usable_memory_is_positive() {
        assert!(usable_memory() > 0);
        assert!(memory_per_job(0) > 0);
    }

    const MEMINFO: &str = "MemTotal:       24683772 kB\n\
                           MemFree:        20000000 kB\n\
                           MemAvailable:    4194304 kB\n\
                           Buffers:          123456 kB\n";

    #[test]
    fn the_memory_available_is_what_others_leave_not_the_total() {
        assert_eq!(available_memory(MEMINFO), Some(4 << 30));
        // Kernels before 3.14 give only the total.
        assert_eq!(
            available_memory("MemTotal: 2097152 kB\nMemFree: 1 kB\n"),
            Some(2 << 30)
        );
        assert_eq!(available_memory("MemAvailableX: 5 kB\n"), None);
        assert_eq!(available_memory(""), None);
        assert_eq!(usable(Some(MEMINFO), &[], None), 4 << 30);
        assert_eq!(usable(None, &[], None), u64::MAX);
    }

    #[test]
    fn the_tightest_of_meminfo_cgroups_and_address_space_wins() {
        assert_eq!(usable(Some(MEMINFO), &[3 << 30, 5 << 30], None), 3 << 30);
        assert_eq!(usable(Some(MEMINFO), &[3 << 30], Some(2 << 30)), 3 << 29);
        assert_eq!(usable(None, &[], Some(8 << 30)), 6 << 30);
    }

    #[test]
    fn a_cgroup_leaves_its_limit_less_what_it_cannot_reclaim() {
        let stat = "anon 1073741824\nfile 2147483648\ninactive_file 536870912\n";
        // 4 GiB limit, 3 GiB charged of which 0.5 GiB droppable page cache.
        assert_eq!(
            cgroup_room("4294967296\n", "3221225472\n", Some(stat)),
            Some(3 << 29)
        );
        assert_eq!(
            cgroup_room("4294967296\n", "3221225472\n", None),
            Some(1 << 30)
        );
        // Over its limit (the kernel is reclaiming): no room.
        assert_eq!(cgroup_room("1000\n", "5000\n", None), Some(0));
        // Version 1 names the hierarchy's cache total_inactive_file.
        let v1 = "inactive_file 1\ntotal_inactive_file 1000\n";
        assert_eq!(cgroup_room("10000", "3000", Some(v1)), Some(8000));
        // No limit.
        assert_eq!(cgroup_room("max\n", "3221225472\n", Some(stat)), None);
        assert_eq!(
            cgroup_room("9223372036854771712\n", "5967872\n", None),
            None
        );
        assert_eq!(cgroup_room("", "1", None), None);
    }

    #[test]
    fn the_cgroups_of_this_process_are_read_from_proc() {
        let v1 = "9:name=systemd:/\n4:memory:/process_api/de3a\n0::/\n";
        assert_eq!(cgroup_paths(v1), (Some("/"), Some("/process_api/de3a")));
        let joined = "5:cpu,memory:/docker/abc\n";
        assert_eq!(cgroup_paths(joined), (None, Some("/docker/abc")));
        let v2 = "0::/system.slice/seamstress.service\n";
        assert_eq!(
            cgroup_paths(v2),
            (Some("/system.slice/seamstress.service"), None)
        );
        assert_eq!(cgroup_paths("garbage"), (None, None));
    }
}
