//! `prl compile`: load each ONNX graph with tract, fix its input facts, declutter it, and save
//! it as NNEF (`.nnef.tar`) beside a plan manifest. tract cannot serialise optimised models, so a
//! plan holds decluttered graphs and the runtime optimises them when it loads them.

use std::path::Path;

use prl_runtime::{GraphInfo, PlanManifest, QuantizationInfo, TrackerConfig, PLAN_FORMAT_VERSION, PLAN_MANIFEST};
use sha2::{Digest, Sha256};
use tract_onnx::prelude::{self as tp, Datum as _, Framework, InferenceFact, InferenceModelExt};

use crate::artefacts::write_graph_dir;
use crate::checkpoint::hex;
use crate::{BuiltModel, Error, Result};

/// The tract release plans are written with (pinned in Cargo.toml).
pub const TRACT_VERSION: &str = "0.23.9";

/// A compiled plan in memory.
#[derive(Debug, Clone)]
pub struct CompiledPlan {
    /// What `plan.json` says.
    pub manifest: PlanManifest,
    /// `template.nnef.tar` bytes.
    pub template: Vec<u8>,
    /// `search.nnef.tar` bytes.
    pub search: Vec<u8>,
}

/// Compile a built model into a plan (fp32) carrying the tracker settings `tracker`.
pub fn compile(model: &BuiltModel, tracker: &TrackerConfig) -> Result<CompiledPlan> {
    compile_with(model, tracker, None)
}

/// Compile a model whose search graph [`crate::quantize`] rewrote into an int8 plan; the
/// manifest records `quantization`.
pub fn compile_int8(
    model: &BuiltModel,
    tracker: &TrackerConfig,
    quantization: QuantizationInfo,
) -> Result<CompiledPlan> {
    compile_with(model, tracker, Some(quantization))
}

fn compile_with(
    model: &BuiltModel,
    tracker: &TrackerConfig,
    quantization: Option<QuantizationInfo>,
) -> Result<CompiledPlan> {
    let template = to_nnef(&model.template, &model.manifest.template, "template graph")?;
    let search = to_nnef(&model.search, &model.manifest.search, "search graph")?;
    let info = |g: &GraphInfo, file: &str, bytes: &[u8]| GraphInfo {
        file: file.into(),
        sha256: hex(&Sha256::digest(bytes)),
        ..g.clone()
    };
    let manifest = PlanManifest {
        format_version: PLAN_FORMAT_VERSION,
        model: model.manifest.model.clone(),
        precision: if quantization.is_some() { "int8" } else { "fp32" }.into(),
        tool: format!("prl-compiler {}", env!("CARGO_PKG_VERSION")),
        tract_version: TRACT_VERSION.into(),
        weights: model.manifest.weights.clone(),
        template: info(&model.manifest.template, "template.nnef.tar", &template),
        search: info(&model.manifest.search, "search.nnef.tar", &search),
        preprocessing: model.manifest.preprocessing.clone(),
        tracker: tracker.clone(),
        variant: model.manifest.variant.clone(),
        optimizer_knobs: optimizer_knobs(),
        quantization,
    };
    Ok(CompiledPlan { manifest, template, search })
}

/// tract knobs a plan is optimised under. tract's direct spatial convolution measured 1.6-1.9x
/// slower here than im2col and a matrix product for layer 1 (docs/performance.md); the runtime
/// runs layer 1 as its own `PackedConv`, and the knob keeps tract's fallback on the faster path.
pub(crate) fn optimizer_knobs() -> std::collections::BTreeMap<String, String> {
    [("TRACT_DISABLE_DIRECT_SPATIAL".to_string(), "true".to_string())].into()
}

impl CompiledPlan {
    /// Write the plan directory `dir` (atomically, file by file).
    pub fn write(&self, dir: &Path) -> Result<()> {
        let m = &self.manifest;
        write_graph_dir(dir, PLAN_MANIFEST, m, [(&m.template.file, &self.template), (&m.search.file, &self.search)])
    }
}

/// Decluttered NNEF of one ONNX graph, as a tar archive (tract's standard operators: the
/// runtime's own ones are put in when a plan is loaded, see `prl_runtime::accelerate`).
fn to_nnef(onnx: &[u8], info: &GraphInfo, context: &str) -> Result<Vec<u8>> {
    let err = |e: tp::TractError| Error::tract(context, format!("{e:#}").replace('\n', " "));
    let mut model = tract_onnx::onnx().model_for_read(&mut &*onnx).map_err(err)?;
    for (i, t) in info.inputs.iter().enumerate() {
        model.set_input_fact(i, InferenceFact::dt_shape(f32::datum_type(), &t.shape)).map_err(err)?;
    }
    let model = model.into_typed().and_then(|m| m.into_decluttered()).map_err(err)?;
    prl_runtime::nnef().write_to_tar(&model, Vec::new()).map_err(err)
}
