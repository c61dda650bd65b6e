//! The seam engine: exact seam metric, seam erasure, and the sampled
//! masking baseline, all on one texel grid.

pub mod assemble;
pub mod charts;
pub mod classify;
pub mod coarse;
pub mod erase;
pub mod far_field;
pub mod grid;
pub mod masking;
pub mod metric;
pub mod multigrid;
pub mod padding;
pub mod quadrature;
pub mod sparse;
pub mod stencil;
pub mod system;
pub mod texels;
pub mod transfer;

pub use grid::TexelGrid;
pub use metric::{colour_channels, psnr, SeamMetric};
pub use texels::TexelClasses;
