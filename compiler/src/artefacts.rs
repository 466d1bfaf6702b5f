//! `prl build`: the two ONNX graphs and a JSON manifest in a model directory, written atomically.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::checkpoint::{hex, Checkpoint};
use crate::net::{self, TensorSpec};
use crate::{Error, Result, Weights};

/// Version of the model directory layout and manifest.
pub const FORMAT_VERSION: u32 = 1;

/// Where the weights come from.
#[derive(Debug, Clone)]
pub enum WeightsSource {
    /// A `.pth` or `.safetensors` file.
    Checkpoint(PathBuf),
    /// Seeded random weights.
    Random(u64),
}

impl WeightsSource {
    /// Load the weights.
    pub fn load(&self) -> Result<Weights> {
        Ok(match self {
            WeightsSource::Checkpoint(p) => Weights::from_checkpoint(Checkpoint::load(p)?),
            WeightsSource::Random(seed) => Weights::random(*seed),
        })
    }
}

/// What `build` needs.
#[derive(Debug, Clone)]
pub struct BuildOptions {
    /// The weights.
    pub source: WeightsSource,
    /// Output directory (created if needed).
    pub out: PathBuf,
}

/// A named tensor in the manifest.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TensorInfo {
    /// Value name.
    pub name: String,
    /// Fixed shape.
    pub shape: Vec<usize>,
}

impl From<&TensorSpec> for TensorInfo {
    fn from(s: &TensorSpec) -> Self {
        TensorInfo { name: s.name.into(), shape: s.shape.to_vec() }
    }
}

/// One emitted graph.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GraphInfo {
    /// File name inside the model directory.
    pub file: String,
    /// SHA-256 of the file.
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
    #[serde(skip_serializing_if = "Option::is_none")]
    pub path: Option<String>,
    /// Checkpoint SHA-256.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
    /// Random seed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// A plain statement for people reading the manifest.
    pub note: String,
}

/// What a model directory holds (`manifest.json`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Manifest {
    /// [`FORMAT_VERSION`].
    pub format_version: u32,
    /// The network.
    pub model: String,
    /// The tool that wrote it.
    pub tool: String,
    /// ONNX opset of the graphs.
    pub opset: i64,
    /// The weights.
    pub weights: WeightsInfo,
    /// Template graph.
    pub template: GraphInfo,
    /// Search graph.
    pub search: GraphInfo,
    /// How input crops must be prepared.
    pub preprocessing: Preprocessing,
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

/// What `build` did.
#[derive(Debug)]
pub struct BuildReport {
    /// The manifest written.
    pub manifest: Manifest,
    /// Where.
    pub out: PathBuf,
    /// Checkpoint keys the network does not use.
    pub unused_keys: Vec<String>,
}

/// Build the network from `opts.source` and write `template.onnx`, `search.onnx` and
/// `manifest.json` into `opts.out`. Files are written to temporaries and renamed at the end.
pub fn build(opts: &BuildOptions) -> Result<BuildReport> {
    let weights = opts.source.load()?;
    let network = net::build_network(&weights)?;
    let weights_info = match (weights.checkpoint(), weights.seed()) {
        (Some(c), _) => WeightsInfo {
            kind: "checkpoint".into(),
            path: Some(c.path.display().to_string()),
            sha256: Some(c.sha256.clone()),
            seed: None,
            note: "weights converted from the checkpoint".into(),
        },
        (None, seed) => WeightsInfo {
            kind: "random".into(),
            path: None,
            sha256: None,
            seed,
            note: "RANDOM WEIGHTS: not a trained model; its boxes mean nothing".into(),
        },
    };
    let doc = format!("PRL-Track ({}), built by prl-compiler {}", weights_info.note, env!("CARGO_PKG_VERSION"));
    let template = network.template.encode(&doc);
    let search = network.search.encode(&doc);
    let info = |file: &str, bytes: &[u8], inputs: Vec<TensorInfo>, outputs: Vec<TensorInfo>| GraphInfo {
        file: file.into(),
        sha256: hex(&Sha256::digest(bytes)),
        inputs,
        outputs,
    };
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "prl-track".into(),
        tool: format!("prl-compiler {}", env!("CARGO_PKG_VERSION")),
        opset: crate::onnx::OPSET,
        weights: weights_info,
        template: info("template.onnx", &template, vec![(&net::TEMPLATE_INPUT).into()], net::TEMPLATE_FEATURES.iter().map(Into::into).collect()),
        search: info(
            "search.onnx",
            &search,
            std::iter::once(&net::SEARCH_INPUT).chain(&net::TEMPLATE_FEATURES).map(Into::into).collect(),
            net::SEARCH_OUTPUTS.iter().map(Into::into).collect(),
        ),
        preprocessing: Preprocessing {
            channels: "BGR".into(),
            range: "0..255 (float32 of uint8 pixels)".into(),
            normalisation: "none".into(),
            layout: "NCHW, batch 1".into(),
            template_size: net::TEMPLATE_SIZE,
            search_size: net::SEARCH_SIZE,
            crop: "official get_subwindow: square crop around the target, padded with the first frame's per-channel mean, resized with OpenCV INTER_LINEAR on uint8".into(),
        },
    };
    let json = serde_json::to_vec_pretty(&manifest).map_err(|e| Error::Other(e.to_string()))?;
    write_all_atomically(
        &opts.out,
        &[("template.onnx", &template), ("search.onnx", &search), ("manifest.json", &json)],
    )?;
    Ok(BuildReport { manifest, out: opts.out.clone(), unused_keys: weights.unused_keys() })
}

/// Write every file to a temporary beside it, then rename them all: a failure leaves no
/// half-written file under its final name.
pub(crate) fn write_all_atomically(dir: &Path, files: &[(&str, &[u8])]) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let tmp = |name: &str| dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let written: Result<()> = files
        .iter()
        .try_for_each(|(name, bytes)| std::fs::write(tmp(name), bytes).map_err(|e| Error::io(dir.join(name), e)));
    if let Err(e) = written {
        files.iter().for_each(|(name, _)| drop(std::fs::remove_file(tmp(name))));
        return Err(e);
    }
    for (name, _) in files {
        std::fs::rename(tmp(name), dir.join(name)).map_err(|e| Error::io(dir.join(name), e))?;
    }
    Ok(())
}
