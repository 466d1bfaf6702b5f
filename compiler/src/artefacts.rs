//! `prl build`: the two ONNX graphs and a JSON manifest in a model directory, written atomically.

use std::path::{Path, PathBuf};

use prl_runtime::{GraphInfo, Preprocessing, TensorInfo, WeightsInfo};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::checkpoint::{hex, Checkpoint};
use crate::net::{self, TensorSpec};
use crate::{Error, Result, Weights};

fn tensor_info(s: &TensorSpec) -> TensorInfo {
    TensorInfo { name: s.name.into(), shape: s.shape.to_vec() }
}

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
    /// The ablation variant, when not the published network (`baseline`, `flp`, `ar-flp`,
    /// `sr-flp`): for latency studies only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub variant: Option<String>,
    /// The tracker family and settings the model needs (imported models carry them; PRL-Track
    /// models built from a checkpoint take `models/prl-track/tracker.toml` at compile time).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tracker: Option<prl_runtime::TrackerConfig>,
}

/// A built model in memory: the two ONNX graphs and their manifest.
#[derive(Debug, Clone)]
pub struct BuiltModel {
    /// What `manifest.json` says.
    pub manifest: Manifest,
    /// `template.onnx` bytes.
    pub template: Vec<u8>,
    /// `search.onnx` bytes.
    pub search: Vec<u8>,
    /// Checkpoint keys the network does not use.
    pub unused_keys: Vec<String>,
}

/// File name of a model directory's manifest.
pub const MODEL_MANIFEST: &str = "manifest.json";

/// Build the network from `source` into ONNX graphs and their manifest.
pub fn build_model(source: &WeightsSource) -> Result<BuiltModel> {
    build_model_variant(source, net::Variant::Full)
}

/// Build an ablation variant of the network (see [`net::Variant`]).
pub fn build_model_variant(source: &WeightsSource, variant: net::Variant) -> Result<BuiltModel> {
    let weights = source.load()?;
    let network = net::build_variant(&weights, variant)?;
    let weights_info = match (weights.checkpoint(), weights.seed()) {
        (Some(c), _) => WeightsInfo {
            kind: "checkpoint".into(),
            path: Some(c.path.display().to_string()),
            sha256: Some(c.sha256.clone()),
            seed: None,
            files: vec![],
            note: "weights converted from the checkpoint".into(),
        },
        (None, seed) => WeightsInfo {
            kind: "random".into(),
            path: None,
            sha256: None,
            seed,
            files: vec![],
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
        template: info(
            "template.onnx",
            &template,
            vec![tensor_info(&net::TEMPLATE_INPUT)],
            net::TEMPLATE_OUTPUTS.iter().map(tensor_info).collect(),
        ),
        search: info(
            "search.onnx",
            &search,
            net::search_inputs().iter().map(tensor_info).collect(),
            net::SEARCH_OUTPUTS.iter().map(tensor_info).collect(),
        ),
        preprocessing: preprocessing(),
        variant: (variant != net::Variant::Full).then(|| variant.name().to_string()),
        tracker: None,
    };
    Ok(BuiltModel { manifest, template, search, unused_keys: weights.unused_keys() })
}

/// The graphs' input contract.
pub fn preprocessing() -> Preprocessing {
    Preprocessing {
        channels: "BGR".into(),
        range: "0..255 (float32 of uint8 pixels)".into(),
        normalisation: "none".into(),
        layout: "NCHW, batch 1".into(),
        template_size: net::TEMPLATE_SIZE,
        search_size: net::SEARCH_SIZE,
        crop: "official get_subwindow: square crop around the target, padded with the first frame's per-channel \
               mean, resized with OpenCV INTER_LINEAR on uint8"
            .into(),
    }
}

impl BuiltModel {
    /// Write `template.onnx`, `search.onnx` and `manifest.json` into `dir` (atomically).
    pub fn write(&self, dir: &Path) -> Result<()> {
        let m = &self.manifest;
        write_graph_dir(dir, MODEL_MANIFEST, m, [(&m.template.file, &self.template), (&m.search.file, &self.search)])
    }

    /// Read a model directory written by [`BuiltModel::write`], checking each graph's SHA-256.
    pub fn read(dir: &Path) -> Result<BuiltModel> {
        let mpath = dir.join(MODEL_MANIFEST);
        let bytes = std::fs::read(&mpath).map_err(|e| Error::io(&mpath, e))?;
        let manifest: Manifest =
            serde_json::from_slice(&bytes).map_err(|e| Error::format(&mpath, format!("not a model manifest: {e}")))?;
        if manifest.format_version != FORMAT_VERSION {
            return Err(Error::format(
                &mpath,
                format!("model format {}, expected {FORMAT_VERSION}", manifest.format_version),
            ));
        }
        let read = |g: &GraphInfo| -> Result<Vec<u8>> {
            let p = dir.join(&g.file);
            let b = std::fs::read(&p).map_err(|e| Error::io(&p, e))?;
            let digest = hex(&Sha256::digest(&b));
            if digest != g.sha256 {
                return Err(Error::format(&p, format!("sha256 {digest} does not match the manifest's {}", g.sha256)));
            }
            Ok(b)
        };
        let (template, search) = (read(&manifest.template)?, read(&manifest.search)?);
        Ok(BuiltModel { manifest, template, search, unused_keys: vec![] })
    }
}

/// Write a directory of two graph files and the JSON manifest describing them.
pub(crate) fn write_graph_dir(
    dir: &Path,
    manifest_name: &str,
    manifest: &impl Serialize,
    graphs: [(&str, &[u8]); 2],
) -> Result<()> {
    let json = serde_json::to_vec_pretty(manifest).map_err(|e| Error::Other(e.to_string()))?;
    // Committed by the manifest: a reader finds the old directory, no manifest, or the new one.
    prl_runtime::write_files_atomically(dir, &[graphs[0], graphs[1], (manifest_name, &json)], manifest_name).map_err(
        |e| match e {
            prl_runtime::Error::Io { path, err } => Error::Io { path, err },
            other => Error::Other(other.to_string()),
        },
    )
}
