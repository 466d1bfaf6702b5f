//! The manifests that describe built models and compiled plans (shared with the compiler).

use serde::{Deserialize, Serialize};

use crate::{TrackerConfig, Winograd};

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
    /// `checkpoint`, `random`, or `onnx` (a third-party model imported by `prl import`).
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
    /// The source files of an imported model (`kind: onnx`), each with its role and SHA-256,
    /// so that the model can be imported again from them and checked.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub files: Vec<SourceFile>,
    /// A plain statement for people reading the manifest.
    pub note: String,
}

/// One source file of an imported model.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SourceFile {
    /// What it is (`backbone`, `head`, `config`).
    pub role: String,
    /// Path as given.
    pub path: String,
    /// SHA-256, hex.
    pub sha256: String,
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
    /// The network (`prl-track`, `nanotrack-v2`, ...); the tracker family is `tracker.family`.
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
    /// The convolutions the runtime runs as Winograd's fast algorithm (`prl compile
    /// --winograd`; absent: none). `PRL_WINOGRAD` overrides it when the plan is loaded.
    #[serde(default, skip_serializing_if = "Winograd::is_off")]
    pub winograd: Winograd,
    /// How the search graph was quantised (int8 plans only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quantization: Option<crate::QuantizationInfo>,
}

impl PlanManifest {
    /// Whether the tracker settings fit the graphs: the template graph takes one
    /// `[1, 3, exemplar, exemplar]` crop, the search graph a `[1, 3, instance, instance]` crop
    /// followed by exactly the template graph's outputs, and its outputs are the family's, each
    /// `[1, channels, score_size, score_size]`. A message saying what disagrees otherwise.
    pub fn check(&self) -> Result<(), String> {
        let t = &self.tracker;
        t.check()?;
        let crop = |g: &GraphInfo, side: usize, what: &str| match g.inputs.first() {
            Some(i) if i.shape == [1, 3, side, side] => Ok(()),
            Some(i) => Err(format!(
                "{} input `{}` is {:?}, but the tracker settings cut {what} crops of {side}x{side}",
                g.file, i.name, i.shape
            )),
            None => Err(format!("{} has no input", g.file)),
        };
        crop(&self.template, t.exemplar_size, "template")?;
        crop(&self.search, t.instance_size, "search")?;
        let features = &self.search.inputs[1..];
        if features.len() != self.template.outputs.len()
            || features.iter().zip(&self.template.outputs).any(|(a, b)| a.shape != b.shape)
        {
            return Err(format!(
                "{} takes template features {:?}, but {} gives {:?}",
                self.search.file,
                features.iter().map(|f| &f.shape).collect::<Vec<_>>(),
                self.template.file,
                self.template.outputs.iter().map(|f| &f.shape).collect::<Vec<_>>()
            ));
        }
        let expected = t.family.search_outputs();
        let n = t.score_size;
        let fits = self.search.outputs.len() == expected.len()
            && self.search.outputs.iter().zip(expected).all(|(o, (_, c))| o.shape == [1, *c, n, n]);
        if !fits {
            let want: Vec<String> = expected.iter().map(|(name, c)| format!("{name} [1, {c}, {n}, {n}]")).collect();
            let got: Vec<String> = self.search.outputs.iter().map(|o| format!("{} {:?}", o.name, o.shape)).collect();
            return Err(format!(
                "{} outputs {}, but a {} tracker with a {n}x{n} score map needs {}",
                self.search.file,
                got.join(", "),
                t.family.name(),
                want.join(", ")
            ));
        }
        Ok(())
    }
}
