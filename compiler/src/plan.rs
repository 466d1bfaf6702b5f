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
        winograd: Default::default(),
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
    crate::shapes::ensure_fixed_shapes(&mut model).map_err(err)?;
    let model = model.into_typed().and_then(|m| m.into_decluttered()).map_err(err)?;
    prl_runtime::nnef().write_to_tar(&model, Vec::new()).map_err(err)
}

/// The fp32 model a plan was compiled from, made again from the sources its manifest records
/// (a checkpoint, a seed, or the ONNX files of an imported model), each checked by SHA-256.
/// `path` names the manifest in errors.
pub fn rebuild_model(m: &PlanManifest, path: &Path) -> Result<BuiltModel> {
    let w = &m.weights;
    let bad = |msg: String| Error::format(path, msg);
    // The sources are recorded as they were named to `prl import` / `prl compile`: a relative
    // name only resolves from the directory that command ran in.
    for f in w.files.iter().map(|f| f.path.as_str()).chain(w.path.as_deref()) {
        if !Path::new(f).exists() {
            return Err(bad(format!(
                "the source file the plan was compiled from, `{f}`, is not found{}; quantise with --model DIR instead",
                if Path::new(f).is_relative() {
                    " from this directory (run from the one it was compiled in)"
                } else {
                    ""
                }
            )));
        }
    }
    let model = match (w.kind.as_str(), &w.path, w.seed) {
        ("onnx", _, _) => {
            let file = |role: &str| w.files.iter().find(|f| f.role == role).map(|f| Path::new(&f.path));
            let (Some(backbone), Some(head)) = (file("backbone"), file("head")) else {
                return Err(bad("the manifest does not name the imported model's backbone and head files".into()));
            };
            match m.tracker.family {
                prl_runtime::Family::Nanotrack => crate::import_nanotrack(backbone, head, file("config"))?,
                f => return Err(bad(format!("imported models of family {} cannot be rebuilt", f.name()))),
            }
        }
        ("checkpoint", Some(p), _) => {
            let source = crate::WeightsSource::Checkpoint(p.into());
            let variant = match &m.variant {
                Some(v) => crate::net::Variant::parse(v).ok_or_else(|| bad(format!("unknown variant `{v}`")))?,
                None => crate::net::Variant::Full,
            };
            crate::build_model_variant(&source, variant)?
        }
        ("random", _, Some(seed)) => crate::build_model(&crate::WeightsSource::Random(seed))?,
        _ => return Err(bad("the manifest does not say where its weights came from".into())),
    };
    let (now, then) = (&model.manifest.weights, w);
    let changed = now.sha256 != then.sha256
        || now.files.iter().zip(&then.files).any(|(a, b)| a.sha256 != b.sha256)
        || model.manifest.search.inputs != m.search.inputs;
    if changed {
        return Err(bad(format!(
            "the source files the plan was compiled from have changed since (SHA-256 differs): {}",
            then.files.iter().map(|f| f.path.as_str()).chain(then.path.as_deref()).collect::<Vec<_>>().join(", ")
        )));
    }
    Ok(model)
}
