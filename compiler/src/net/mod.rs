//! The PRL-Track network as two fixed-shape ONNX graphs, written to read like the paper:
//! backbone, depthwise cross-correlations, regulators (AR, SR), HMG, heads.

mod backbone;
mod heads;
mod hmg;
mod layers;
mod regulators;
mod variant;

pub use hmg::{hierarchical_attention, sincos_pos_embed};
pub use regulators::{lip2d, nearest_indices, upsample_nearest};
pub use variant::Variant;

use crate::onnx::Graph;
use crate::weights::Weights;
use crate::Result;

/// Template (exemplar) crop side.
pub const TEMPLATE_SIZE: usize = 127;
/// Search (instance) crop side.
pub const SEARCH_SIZE: usize = 287;

/// A named tensor of fixed shape at a graph boundary or a stage of the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TensorSpec {
    /// Value name in the graphs (and key in golden files).
    pub name: &'static str,
    /// Shape, batch first.
    pub shape: &'static [usize],
}

const fn t(name: &'static str, shape: &'static [usize]) -> TensorSpec {
    TensorSpec { name, shape }
}

/// Template graph input.
pub const TEMPLATE_INPUT: TensorSpec = t("z", &[1, 3, TEMPLATE_SIZE, TEMPLATE_SIZE]);
/// Backbone layers 1..5 of the template (values of the template graph, golden keys).
pub const TEMPLATE_FEATURES: [TensorSpec; 5] = [
    t("zf1", &[1, 96, 29, 29]),
    t("zf2", &[1, 256, 12, 12]),
    t("zf3", &[1, 384, 10, 10]),
    t("zf4", &[1, 384, 8, 8]),
    t("zf5", &[1, 256, 6, 6]),
];
/// Template graph outputs, which are the search graph's inputs after `x`.
pub const TEMPLATE_OUTPUTS: [TensorSpec; 5] = TEMPLATE_FEATURES;
/// Search graph image input.
pub const SEARCH_INPUT: TensorSpec = t("x", &[1, 3, SEARCH_SIZE, SEARCH_SIZE]);
/// Search graph outputs.
pub const SEARCH_OUTPUTS: [TensorSpec; 3] =
    [t("loc", &[1, 4, 11, 11]), t("cls1", &[1, 2, 11, 11]), t("cls2", &[1, 1, 11, 11])];
/// Intermediate stages of the search graph, in execution order (named values, verifiable).
pub const SEARCH_STAGES: [TensorSpec; 14] = [
    t("xf1", &[1, 96, 69, 69]),
    t("xf2", &[1, 256, 32, 32]),
    t("xf3", &[1, 384, 30, 30]),
    t("xf4", &[1, 384, 28, 28]),
    t("xf5", &[1, 256, 26, 26]),
    t("s1", &[1, 96, 41, 41]),
    t("s2", &[1, 256, 21, 21]),
    t("s3", &[1, 384, 21, 21]),
    t("s4", &[1, 384, 21, 21]),
    t("s5", &[1, 256, 21, 21]),
    t("ar", &[1, 192, 11, 11]),
    t("sr1", &[1, 192, 11, 11]),
    t("sr2", &[1, 192, 11, 11]),
    t("hmg", &[1, 192, 11, 11]),
];

/// The search graph's inputs, in order: `x`, then the template graph's outputs.
pub fn search_inputs() -> Vec<TensorSpec> {
    std::iter::once(SEARCH_INPUT).chain(TEMPLATE_OUTPUTS).collect()
}

/// The two graphs of the network.
pub struct Network {
    /// `z` -> `zf1..zf5`.
    pub template: Graph,
    /// `x`, `zf1..zf5` -> `loc`, `cls1`, `cls2`.
    pub search: Graph,
}

/// Build both graphs from `weights` (keys as in the official checkpoint).
pub fn build_network(weights: &Weights) -> Result<Network> {
    build_variant(weights, Variant::Full)
}

/// Build both graphs of an ablation variant (the template graph is the same for all).
pub fn build_variant(weights: &Weights, variant: Variant) -> Result<Network> {
    Ok(Network { template: template_graph(weights)?, search: search_variant(weights, variant)? })
}

/// The template branch: the backbone on the exemplar crop.
pub fn template_graph(weights: &Weights) -> Result<Graph> {
    let w = weights.root();
    let mut g = Graph::new("prl_track_template");
    let z = g.input(TEMPLATE_INPUT.name, TEMPLATE_INPUT.shape)?;
    let feats = backbone::backbone(&mut g, &w.pp("backbone"), &z, "zf")?;
    for (f, spec) in feats.iter().zip(TEMPLATE_OUTPUTS) {
        g.output(f, spec.shape)?;
    }
    Ok(g)
}

/// The search branch: backbone on the search crop, cross-correlations with the template
/// features, AR, SR1, SR2, HMG and heads.
pub fn search_graph(weights: &Weights) -> Result<Graph> {
    search_variant(weights, Variant::Full)
}

/// The search branch of an ablation variant (see [`Variant`]).
pub fn search_variant(weights: &Weights, variant: Variant) -> Result<Graph> {
    let w = weights.root();
    let mut g = Graph::new("prl_track_search");
    let x = g.input(SEARCH_INPUT.name, SEARCH_INPUT.shape)?;
    let zf = TEMPLATE_OUTPUTS.iter().map(|s| g.input(s.name, s.shape)).collect::<Result<Vec<_>>>()?;
    let xf = backbone::backbone(&mut g, &w.pp("backbone"), &x, "xf")?;
    // The five correlations as the official code writes them: depthwise convolutions whose
    // kernels are the template features (tract runs them as `prl_runtime::DepthwiseXCorr`).
    let s = (0..5)
        .map(|i| {
            let spec = TEMPLATE_FEATURES[i];
            g.depthwise_xcorr(&format!("s{}", i + 1), &xf[i], &zf[i], spec.shape[1], spec.shape[2])
        })
        .collect::<Result<Vec<_>>>()?;
    let gw = w.pp("grader");
    let ar = if variant.ar() {
        regulators::appearance_regulator(&mut g, &gw.pp("ar"), "ar", &s[2], &s[0], &s[1])?
    } else {
        variant::stand_in(&mut g, "ar", &s[2], 384)?
    };
    let (sr1, sr2) = if variant.sr() {
        let sr1 = regulators::semantic_regulator(&mut g, &gw.pp("sr1"), "sr1", &s[3], 384, &ar, 30.0)?;
        let sr2 = regulators::semantic_regulator(&mut g, &gw.pp("sr2"), "sr2", &s[4], 256, &sr1, 15.0)?;
        (sr1, sr2)
    } else {
        (variant::stand_in(&mut g, "sr1", &s[3], 384)?, variant::stand_in(&mut g, "sr2", &s[4], 256)?)
    };
    let h = match variant {
        Variant::Baseline => sr2, // the heads on the last correlation map, through its stand-in
        _ => hmg::hmg(&mut g, &gw.pp("vit"), "hmg", [&ar, &sr1, &sr2])?,
    };
    let outs = heads::heads(&mut g, &gw, &h)?;
    for (o, spec) in outs.iter().zip(SEARCH_OUTPUTS) {
        g.output(o, spec.shape)?;
    }
    Ok(g)
}
