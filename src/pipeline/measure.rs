//! The figures of one texture's level 0: seam agreement over every seam and
//! over the closed ones, PSNR inside the charts and per chart, per decoder.

use super::alpha::{self, AlphaMetrics, AlphaPlan};
use super::{DecoderMetrics, Metrics};
use crate::model::AlphaUse;
use crate::seam::charts::{ChartFidelity, Charts};
use crate::seam::metric::{squared_error, Sse};
use crate::seam::{psnr, SeamMetric};

/// The metric over every seam and over the closed ones, and the fidelity
/// figures, for one texture's level 0.
pub(super) struct Measure<'a> {
    pub(super) all: SeamMetric,
    pub(super) closed: SeamMetric,
    /// Over the seams closed for alpha, where alpha was judged apart from
    /// the colour; else the colour's.
    pub(super) alpha_closed: Option<SeamMetric>,
    pub(super) charts: &'a Charts,
    pub(super) inside: &'a [bool],
    pub(super) compared: usize,
}

impl Measure<'_> {
    pub(super) fn input(&self, data: &[f32], channels: usize) -> Metrics {
        Metrics {
            seam_rms: self.all.seam_rms(data, channels, self.compared),
            seam_rms_closed: self.closed.seam_rms(data, channels, self.compared),
            psnr: None,
            worst_chart_psnr: None,
            charts_under_30db: None,
            decoders: None,
        }
    }

    /// An encoding's figures under one decoder, from its decoding: the
    /// seam terms and the two PSNRs side by side; with the squared errors
    /// the PSNRs come from (against the input, against the erased texture).
    pub(super) fn decoder(
        &self,
        data: &[f32],
        input: &[f32],
        erased: &[f32],
    ) -> (DecoderMetrics, [Sse; 2]) {
        let ((seam_rms, seam_rms_closed), (against_input, against_erased)) = rayon::join(
            || {
                (
                    self.all.seam_rms(data, 3, self.compared),
                    self.closed.seam_rms(data, 3, self.compared),
                )
            },
            || {
                (
                    squared_error(data, input, 3, self.compared, self.inside),
                    squared_error(data, erased, 3, self.compared, self.inside),
                )
            },
        );
        let figures = DecoderMetrics {
            seam_rms,
            seam_rms_closed,
            psnr: against_input.psnr(),
            encoding_psnr: against_erased.psnr(),
        };
        (figures, [against_input, against_erased])
    }

    /// Alpha figures of `alpha` (one value per texel) against `input`'s
    /// (and, for an encoding, against the `erased` alpha it encoded).
    pub(super) fn alpha(
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
        let charts = self.charts.fidelity(alpha, input, 1, 1);
        // A chart whose alpha did not change has no figure: the input's own
        // alpha, and alpha left as painted, show none.
        let changed = charts.worst_psnr.is_some();
        AlphaMetrics {
            worst_chart_psnr: charts.worst_psnr,
            charts_under_30db: changed.then_some(charts.under_threshold),
            seam_rms: self.all.seam_rms(alpha, 1, 1),
            seam_rms_closed: self
                .alpha_closed
                .as_ref()
                .unwrap_or(&self.closed)
                .seam_rms(alpha, 1, 1),
            psnr: psnr(alpha, input, 1, 1, self.inside),
            encoding_psnr: erased.and_then(|e| psnr(alpha, e, 1, 1, self.inside)),
            opacity_changes: mask.map(|c| alpha::opacity_changes(input, alpha, c, self.inside)),
        }
    }

    pub(super) fn against(&self, data: &[f32], channels: usize, reference: &[f32]) -> Metrics {
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
