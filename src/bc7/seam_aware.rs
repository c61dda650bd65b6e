//! Seam-aware BC7 (interface placeholder for local builds only).
use crate::bc1::seam_aware::{SeamAwareOptions, SeamAwareStats};
use crate::seam::quadrature::QuadPoint;
use crate::seam::system::SolveError;
pub struct Problem<'a> {
    pub width: usize,
    pub height: usize,
    pub target: &'a [f32],
    pub inside: &'a [bool],
    pub points: &'a [QuadPoint],
    pub alpha_points: Option<&'a [QuadPoint]>,
}
pub fn optimise(
    _p: &Problem,
    _b: &mut [super::Block],
    _o: &SeamAwareOptions,
) -> Result<SeamAwareStats, SolveError> {
    Ok(SeamAwareStats::default())
}
