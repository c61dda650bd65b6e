//! Seam-aware BC7.
