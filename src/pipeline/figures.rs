//! Level 0's encodings decoded and measured: under every decoder, each
//! encoding's seam agreement and PSNRs.
//!
//! The seam-aware encoding differs from the regular one only in the blocks
//! under the seams (Fox: 4 048 of 262 144), so its figures are the regular
//! encoding's corrected there: the squared errors the PSNRs are made of
//! lose those blocks' regular terms and gain their new ones, and the seam
//! terms are summed again from the blocks under the seams alone. Measured
//! over the whole image instead, the figures of the second encoding took
//! three decodings of the whole texture and a dozen passes over it. Under
//! the GPU decoders even the first encoding is measured block by block, as
//! each block is decoded, with no decoded image of its own.

use std::collections::BTreeMap;

use super::bc7_level;
use super::measure::Measure;
use super::{DecoderMetrics, Metrics, PipelineError};
use crate::bc1::{self, Block, Decoder};
use crate::bc7;
use crate::model::Texture;
use crate::seam::charts::ChartSse;
use crate::seam::metric::{in_chunks, Sse};

/// Block rows per parallel task of [`Figures::of_blocks`].
const BLOCK_ROWS_PER_TASK: usize = 16;

/// Level 0's encodings decoded and measured.
pub(super) struct Figures<'a> {
    pub(super) name: &'a str,
    pub(super) tex: &'a Texture,
    pub(super) measure: &'a Measure<'a>,
    pub(super) input_rgb: &'a [f32],
    pub(super) erased_rgb: &'a [f32],
}

/// One encoding's figures, and its ideal decoding (for the pictures).
pub(super) struct Measured {
    pub(super) metrics: Metrics,
    pub(super) ideal: Vec<f32>,
    /// A BC7 encoding's decoded alpha (empty for BC1).
    pub(super) alpha: Vec<f32>,
    /// What a BC1 encoding's PSNRs were summed from (`None` for BC7).
    sums: Option<Sums>,
}

/// A BC1 encoding's squared errors: per decoder ([`Decoder::ALL`] order)
/// against the input and the erased texture over the inside texels, and
/// the ideal decoding's per chart against the input.
#[derive(Clone)]
struct Sums {
    input: [Sse; 3],
    erased: [Sse; 3],
    charts: ChartSse,
}

impl Figures<'_> {
    /// Under a texel of a one-bit-alpha DDS encoded transparent (`clear`)
    /// no colour is shown: the colour figures take the erased texture's there.
    fn decode(
        &self,
        blocks: &[Block],
        clear: Option<&[bool]>,
        d: Decoder,
    ) -> Result<Vec<f32>, PipelineError> {
        let mut rgb = bc1::decode_image_with(blocks, self.tex.width, self.tex.height, d)
            .map_err(|e| PipelineError::encode(self.name, e))?;
        if let Some(clear) = clear {
            for (t, _) in clear.iter().enumerate().filter(|(_, c)| **c) {
                rgb[t * 3..t * 3 + 3].copy_from_slice(&self.erased_rgb[t * 3..t * 3 + 3]);
            }
        }
        Ok(rgb)
    }

    /// The figures of an encoding of level 0. Only the ideal decoding is
    /// made whole (the pictures show it); the others are measured block by
    /// block ([`Figures::of_blocks`]): at 8192² each decoding is 768 MiB.
    pub(super) fn of(
        &self,
        blocks: &[Block],
        clear: Option<&[bool]>,
    ) -> Result<Measured, PipelineError> {
        let m = self.measure;
        let ideal = self.decode(blocks, clear, Decoder::Ideal)?;
        let (charts, ideal_figures) = rayon::join(
            || {
                m.charts
                    .squared_errors(&ideal, self.input_rgb, 3, m.compared)
            },
            || m.decoder(&ideal, self.input_rgb, self.erased_rgb),
        );
        let (w, h) = (self.tex.width, self.tex.height);
        let tapped = TappedBlocks::new(m, blocks, bc1::block_dims(w, h).0, w);
        let per: Vec<(DecoderMetrics, [Sse; 2])> = Decoder::ALL
            .into_iter()
            .map(|d| {
                if d == Decoder::Ideal {
                    ideal_figures
                } else {
                    self.of_blocks(blocks, clear, d, &tapped)
                }
            })
            .collect();
        let sums = Sums {
            input: std::array::from_fn(|d| per[d].1[0]),
            erased: std::array::from_fn(|d| per[d].1[1]),
            charts,
        };
        let per = per.into_iter().map(|(figures, _)| figures).collect();
        Ok(Measured {
            metrics: metrics(per, &sums.charts),
            ideal,
            alpha: Vec::new(),
            sums: Some(sums),
        })
    }

    /// An encoding's figures under decoder `d`, decoded block by block
    /// rather than into an image of its own: the squared errors summed as
    /// each block is decoded, the seam terms from the blocks under the
    /// seams.
    fn of_blocks(
        &self,
        blocks: &[Block],
        clear: Option<&[bool]>,
        d: Decoder,
        tapped: &TappedBlocks<'_>,
    ) -> (DecoderMetrics, [Sse; 2]) {
        let m = self.measure;
        let (w, h) = (self.tex.width, self.tex.height);
        let (bw, bh) = bc1::block_dims(w, h);
        let shown = |t: usize| clear.is_none_or(|c| !c[t]);
        let parts = in_chunks(bh, BLOCK_ROWS_PER_TASK, |rows| {
            let (mut input, mut erased) = (Sse::default(), Sse::default());
            let first = rows.start * bw;
            for (b, block) in (first..).zip(&blocks[first..rows.end * bw]) {
                let decoded = block.decode_with(d);
                for (k, texel) in decoded.iter().enumerate() {
                    let Some(t) = bc1::block_texel((w, h), bw, b, k) else {
                        continue;
                    };
                    if !m.inside[t] {
                        continue;
                    }
                    for (c, &decoded) in texel.iter().enumerate().take(m.compared) {
                        let v = if shown(t) {
                            f64::from(decoded)
                        } else {
                            f64::from(self.erased_rgb[t * 3 + c])
                        };
                        input.sum += (v - f64::from(self.input_rgb[t * 3 + c])).powi(2);
                        erased.sum += (v - f64::from(self.erased_rgb[t * 3 + c])).powi(2);
                    }
                    input.values += m.compared;
                    erased.values += m.compared;
                }
            }
            (input, erased)
        });
        let (mut input, mut erased) = (Sse::default(), Sse::default());
        for (i, e) in parts {
            (input.sum, input.values) = (input.sum + i.sum, input.values + i.values);
            (erased.sum, erased.values) = (erased.sum + e.sum, erased.values + e.values);
        }
        let (seam_rms, seam_rms_closed) = self.seam_terms(tapped, clear, d);
        let figures = DecoderMetrics {
            seam_rms,
            seam_rms_closed,
            psnr: input.psnr(),
            encoding_psnr: erased.psnr(),
        };
        (figures, [input, erased])
    }

    /// The seam metric over every seam and over the closed ones, of the
    /// encoding `tapped` reads, under decoder `d`.
    fn seam_terms(
        &self,
        tapped: &TappedBlocks<'_>,
        clear: Option<&[bool]>,
        d: Decoder,
    ) -> (Option<f64>, Option<f64>) {
        let m = self.measure;
        let decoded = tapped.decode(d);
        let value = |t: usize, c: usize| {
            if clear.is_none_or(|c| !c[t]) {
                decoded[tapped.slot(t)][tapped.texel_in_block(t)][c]
            } else {
                self.erased_rgb[t * 3 + c]
            }
        };
        (
            m.all.seam_rms_with(m.compared, value),
            m.closed.seam_rms_with(m.compared, value),
        )
    }

    /// The figures of `blocks`, an encoding that differs from `regular`'s
    /// (`regular_blocks`) in a few blocks, as [`Figures::of`] gives them but
    /// for the order of the sums.
    pub(super) fn of_changed(
        &self,
        regular_blocks: &[Block],
        regular: &Measured,
        blocks: &[Block],
        clear: Option<&[bool]>,
    ) -> Result<Measured, PipelineError> {
        let Some(sums) = regular.sums.as_ref() else {
            return self.of(blocks, clear);
        };
        let m = self.measure;
        let (w, h) = (self.tex.width, self.tex.height);
        let bw = bc1::block_dims(w, h).0;
        let shown = |t: usize| clear.is_none_or(|c| !c[t]);
        let changed: Vec<usize> = (0..blocks.len())
            .filter(|&b| blocks[b] != regular_blocks[b])
            .collect();
        let mut ideal = regular.ideal.clone();
        let mut sums = sums.clone();
        for (di, d) in Decoder::ALL.into_iter().enumerate() {
            for &b in &changed {
                let (old, new) = (regular_blocks[b].decode_with(d), blocks[b].decode_with(d));
                for k in 0..16 {
                    let Some(t) = bc1::block_texel((w, h), bw, b, k) else {
                        continue;
                    };
                    if !shown(t) {
                        continue;
                    }
                    let change = |reference: &[f32]| -> f64 {
                        (0..m.compared)
                            .map(|c| {
                                let r = f64::from(reference[t * 3 + c]);
                                (f64::from(new[k][c]) - r).powi(2)
                                    - (f64::from(old[k][c]) - r).powi(2)
                            })
                            .sum()
                    };
                    if m.inside[t] {
                        sums.input[di].sum += change(self.input_rgb);
                        sums.erased[di].sum += change(self.erased_rgb);
                    }
                    if d == Decoder::Ideal {
                        let chart = m.charts.of_texel[t];
                        if chart != crate::seam::charts::Charts::NONE {
                            sums.charts.sum[chart as usize] += change(self.input_rgb);
                        }
                        ideal[t * 3..t * 3 + 3].copy_from_slice(&new[k]);
                    }
                }
            }
        }
        let tapped = TappedBlocks::new(m, blocks, bw, w);
        let per = Decoder::ALL
            .into_iter()
            .enumerate()
            .map(|(di, d)| {
                let (all, closed) = if d == Decoder::Ideal {
                    (
                        m.all.seam_rms(&ideal, 3, m.compared),
                        m.closed.seam_rms(&ideal, 3, m.compared),
                    )
                } else {
                    self.seam_terms(&tapped, clear, d)
                };
                DecoderMetrics {
                    seam_rms: all,
                    seam_rms_closed: closed,
                    psnr: sums.input[di].psnr(),
                    encoding_psnr: sums.erased[di].psnr(),
                }
            })
            .collect();
        Ok(Measured {
            metrics: metrics(per, &sums.charts),
            ideal,
            alpha: Vec::new(),
            sums: Some(sums),
        })
    }

    /// The figures of a BC7 encoding of level 0: one decoding, exact.
    pub(super) fn of_bc7(&self, blocks: &[bc7::Block]) -> Result<Measured, PipelineError> {
        let (rgb, alpha) = bc7_level::decode(self.name, blocks, self.tex.width, self.tex.height)?;
        let metrics = self.measure.against(&rgb, 3, self.input_rgb);
        Ok(Measured {
            metrics,
            ideal: rgb,
            alpha,
            sums: None,
        })
    }
}

/// An encoding's figures from its figures under each decoder
/// ([`Decoder::ALL`] order; the first fields are the ideal decoder's) and
/// its ideal decoding's per-chart errors.
fn metrics(per: Vec<DecoderMetrics>, charts: &ChartSse) -> Metrics {
    let ideal = per[0];
    let fidelity = charts.fidelity();
    Metrics {
        seam_rms: ideal.seam_rms,
        seam_rms_closed: ideal.seam_rms_closed,
        psnr: ideal.psnr,
        worst_chart_psnr: fidelity.worst_psnr,
        charts_under_30db: Some(fidelity.under_threshold),
        decoders: Some(
            Decoder::ALL
                .iter()
                .zip(per)
                .map(|(d, figures)| (d.name(), figures))
                .collect::<BTreeMap<_, _>>(),
        ),
    }
}

/// The blocks that the seam metrics' taps read, each with its place in a
/// list of their decodings.
struct TappedBlocks<'a> {
    blocks: &'a [Block],
    bw: usize,
    width: usize,
    /// Per block of the texture, its place among `list` (`u32::MAX` if none).
    slot: Vec<u32>,
    list: Vec<usize>,
}

impl<'a> TappedBlocks<'a> {
    fn new(m: &Measure<'_>, blocks: &'a [Block], bw: usize, width: usize) -> Self {
        let mut slot = vec![u32::MAX; blocks.len()];
        let mut list = Vec::new();
        for q in m.all.points.iter().chain(&m.closed.points) {
            for &(t, _) in &q.taps {
                let t = t as usize;
                let b = (t / width / 4) * bw + (t % width) / 4;
                if slot[b] == u32::MAX {
                    slot[b] = list.len() as u32;
                    list.push(b);
                }
            }
        }
        TappedBlocks {
            blocks,
            bw,
            width,
            slot,
            list,
        }
    }

    fn decode(&self, d: Decoder) -> Vec<[[f32; 3]; 16]> {
        self.list
            .iter()
            .map(|&b| self.blocks[b].decode_with(d))
            .collect()
    }

    /// Texel `t`'s place in its block.
    fn texel_in_block(&self, t: usize) -> usize {
        (t / self.width) % 4 * 4 + t % 4
    }

    /// The place of texel `t`'s block among the decodings.
    fn slot(&self, t: usize) -> usize {
        let b = (t / self.width / 4) * self.bw + (t % self.width) / 4;
        self.slot[b] as usize
    }
}
