//! What an int8 plan's manifest says about its quantisation: method, calibration data, each
//! layer's decision and ranges. Written by the compiler's quantiser; the runtime only carries it.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// How a plan's search graph was quantised.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct QuantizationInfo {
    /// Activation range method (`minmax`, `percentile`, `entropy`).
    pub method: String,
    /// Per-channel weight scales setting (`auto`, `on`, `off`).
    pub per_channel: String,
    /// The calibration data.
    pub calibration: CalibrationInfo,
    /// Every candidate layer of the search graph, in graph order.
    pub layers: Vec<QuantLayer>,
    /// Each u8 tensor of the graph: value name -> the real range its 256 levels cover.
    pub ranges: BTreeMap<String, (f32, f32)>,
}

/// Where the calibration crops came from.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
pub struct CalibrationInfo {
    /// Sequence names (folders).
    pub sequences: Vec<String>,
    /// Template crops (one per sequence's first frame).
    pub template_crops: usize,
    /// Search crops.
    pub search_crops: usize,
    /// How frames were sampled and crops jittered.
    pub sampling: String,
}

/// Why a layer is or is not integer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LayerDecision {
    /// Runs as an integer operator.
    Int8,
    /// Kept in f32 because the user named it.
    KeptByUser,
    /// Kept in f32 as one of the most sensitive layers (the budget).
    KeptSensitive,
    /// Kept in f32: too little work to pay for its quantise/dequantise.
    TooSmall,
    /// Kept in f32: too few output channels for tract's int8 convolution to pay (its eager
    /// im2col and zero-point column sums cost per input element, the kernel saves per MAC).
    FewChannels,
    /// Kept in f32: a product of two activations, quantised only on request (`--act-matmul`):
    /// both sides are quantised every frame and tract computes zero-point sums of both, which
    /// measured no faster than f32 for `s1` and slower for attention.
    ActivationProduct,
}

impl LayerDecision {
    /// A short phrase for reports.
    pub fn describe(self) -> &'static str {
        match self {
            LayerDecision::Int8 => "int8",
            LayerDecision::KeptByUser => "fp32 (--keep-fp32)",
            LayerDecision::KeptSensitive => "fp32 (sensitive, --budget)",
            LayerDecision::TooSmall => "fp32 (too small to pay)",
            LayerDecision::FewChannels => "fp32 (too few channels)",
            LayerDecision::ActivationProduct => "fp32 (act x act, --act-matmul)",
        }
    }
}

/// One quantisable layer: a `Conv` or `MatMul` with constant weights, or a `MatMul` of two
/// activations.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct QuantLayer {
    /// Node name in the search graph.
    pub node: String,
    /// `conv`, `matmul` (constant weights) or `act-matmul` (a product of two activations).
    pub op: String,
    /// Multiply-adds per run.
    pub macs: u64,
    /// What was decided.
    pub decision: LayerDecision,
    /// One weight scale per output channel (else one per tensor).
    pub per_channel: bool,
    /// Relative error of the weights after symmetric i8 quantisation.
    pub weight_error: f64,
    /// Calibrated range of its input.
    pub input_range: (f32, f32),
    /// Calibrated range of its output (after a folded ReLU).
    pub output_range: (f32, f32),
    /// Relative error of each search output (PRL-Track: loc, cls1, cls2; NanoTrack: cls, loc)
    /// with this layer alone quantised (sensitivity pass).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensitivity: Option<Vec<f64>>,
}
