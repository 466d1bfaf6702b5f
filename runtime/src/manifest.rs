//! The manifests that describe built models and compiled plans (shared with the compiler).

use serde::{Deserialize, Serialize};

use crate::TrackerConfig;

/// Version of the plan layout this runtime reads.
pub const PLAN_FORMAT_VERSION: u32 = 1;
/// File name of a plan's manifest inside the plan directory.
pub const PLAN_MANIFEST: &str = "plan.json";

/// A named tensor of fixed shape.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TensorInfo {
    /// Value name.
    pub name: String,
    /// Fixed shape.
    pub shape: Vec<usize>,
}

/// One graph file.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GraphInfo {
    /// File name inside the model or plan directory.
    pub file: String,
    /// SHA-256 of the file, hex.
    pub sha256: String,
    /// Inputs, in order.
    pub inputs: Vec<TensorInfo>,
    /// Outputs, in order.
    pub outputs: Vec<TensorInfo>,
}

/// Provenance of the weights.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct WeightsInfo {
    /// `checkpoint` or `random`.
    pub kind: String,
    /// Checkpoint path as given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<String>,
    /// Checkpoint SHA-256.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
    /// Random seed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// A plain statement for people reading the manifest.
    pub note: String,
}

/// The preprocessing contract of the graphs' image inputs.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Preprocessing {
    /// Channel order.
    pub channels: String,
    /// Value range.
    pub range: String,
    /// Normalisation applied before the network.
    pub normalisation: String,
    /// Tensor layout.
    pub layout: String,
    /// Template crop side.
    pub template_size: usize,
    /// Search crop side.
    pub search_size: usize,
    /// How crops are cut and resized.
    pub crop: String,
}

/// `plan.json`: what a compiled plan holds.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PlanManifest {
    /// [`PLAN_FORMAT_VERSION`].
    pub format_version: u32,
    /// The network (`prl-track`).
    pub model: String,
    /// `fp32` (or `int8` for quantised plans).
    pub precision: String,
    /// The tool that compiled it.
    pub tool: String,
    /// tract version the graphs were written with.
    pub tract_version: String,
    /// The weights.
    pub weights: WeightsInfo,
    /// Template graph (decluttered NNEF).
    pub template: GraphInfo,
    /// Search graph (decluttered NNEF).
    pub search: GraphInfo,
    /// How input crops must be prepared.
    pub preprocessing: Preprocessing,
    /// Tracker settings.
    pub tracker: TrackerConfig,
    /// The ablation variant of the network, when not the published one (`baseline`, `flp`,
    /// `ar-flp`, `sr-flp`): such plans are for latency studies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub variant: Option<String>,
    /// tract knobs (`TRACT_*` names, scopable ones only) in force while the runtime optimises
    /// the graphs: kernel choices the compiler measured and made for this plan.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub optimizer_knobs: std::collections::BTreeMap<String, String>,
    /// How the search graph was quantised (int8 plans only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quantization: Option<crate::QuantizationInfo>,
}
