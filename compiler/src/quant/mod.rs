//! Post-training int8 quantisation of the search graph.
//!
//! 1. Calibrate: run the fp32 template graph on each calibration template crop and the fp32
//!    search graph on each calibration search crop, observing every tensor an integer operator
//!    would read or write ([`Observer`]).
//! 2. Choose: every `Conv`/`MatMul` with constant weights and enough work (at least
//!    [`QuantizeOptions::min_macs`] multiply-adds) is a layer; weights are symmetric i8, per
//!    tensor or per output channel; activations are u8 with the range the [`Method`] picks.
//! 3. Optionally rank layers by sensitivity (each quantised alone, error of loc/cls1/cls2 over
//!    calibration crops) and keep the most sensitive in f32 (`budget`), plus any named ones.
//! 4. Rewrite the ONNX graph ([`rewrite`]) into `QLinearConv`/`QLinearMatMul`, which tract runs
//!    on its integer kernels with requantisation fused.
//!
//! The template graph runs once per target and stays fp32.

mod calibrate;
mod candidates;
mod observer;
mod ranges;
mod rewrite;

use std::collections::{BTreeMap, HashMap};

use prost::Message;
use sha2::{Digest, Sha256};
use tract_onnx::pb;

pub use calibrate::Calibration;
pub use candidates::{candidates, quantise_weights, Candidate, Kind};
pub use observer::{Method, Observer, PERCENTILE};
use ranges::Ranges;
pub use rewrite::QParams;

use prl_runtime::{CalibrationInfo, LayerDecision, QuantLayer, QuantizationInfo};

use crate::checkpoint::hex;
use crate::{relative_error, BuiltModel, Error, Result};

/// Whether weights get one scale per output channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PerChannel {
    /// Per channel where one scale per tensor loses more than 2% of the weight (relative
    /// error) and per channel at least halves that: per-channel requantisation runs as separate
    /// f32 operators in tract (layer 2: about 10% slower), and a weight error under 2% costs less
    /// than the activations' quantisation already does.
    Auto,
    /// Always per channel.
    On,
    /// Always one scale per weight tensor.
    Off,
}

impl PerChannel {
    /// Every setting.
    pub const ALL: [PerChannel; 3] = [PerChannel::Auto, PerChannel::On, PerChannel::Off];

    /// The name used on the command line and in manifests.
    pub fn name(self) -> &'static str {
        match self {
            PerChannel::Auto => "auto",
            PerChannel::On => "on",
            PerChannel::Off => "off",
        }
    }

    /// The setting called `name`, if any.
    pub fn parse(name: &str) -> Option<PerChannel> {
        PerChannel::ALL.into_iter().find(|p| p.name() == name)
    }
}

/// What the quantiser does.
#[derive(Debug, Clone)]
pub struct QuantizeOptions {
    /// How activation ranges are chosen.
    pub method: Method,
    /// Per-channel weight scales.
    pub per_channel: PerChannel,
    /// Layers (node names) kept in f32.
    pub keep_fp32: Vec<String>,
    /// Keep this many of the most sensitive layers in f32 (runs the sensitivity pass).
    pub budget: Option<usize>,
    /// Layers with fewer multiply-adds stay f32: the quantise/dequantise around them would cost
    /// more than the integer kernel saves.
    pub min_macs: u64,
    /// Convolutions with fewer output channels stay f32. Where the runtime's `PackedQConv`
    /// runs them (AVX-512 VNNI, aarch64's dot product; stride 1 or 2) 64 is enough: PRL-Track's
    /// layer 1 (96 channels, three input channels) is about 2x faster in int8 there. tract's own int8
    /// convolution, used elsewhere, pays an eager im2col and zero-point sums per input element,
    /// which only more channels amortise (layer 1 about 2x slower in int8 than in f32 on it).
    pub min_out_channels: usize,
    /// Also quantise products of two activations (HMG's attention).
    pub act_matmul: bool,
    /// Also quantise depthwise convolutions (MobileNet's; one group per channel), whatever
    /// their multiply-adds (few per byte they move: what int8 saves there is memory and the
    /// dequantisation of their input, not arithmetic).
    pub depthwise: bool,
    /// Calibration crops the sensitivity pass measures on.
    pub sensitivity_crops: usize,
}

impl Default for QuantizeOptions {
    fn default() -> Self {
        QuantizeOptions {
            method: Method::MinMax,
            per_channel: PerChannel::Auto,
            keep_fp32: vec![],
            budget: None,
            min_macs: 4_000_000,
            min_out_channels: 64,
            act_matmul: false,
            depthwise: false,
            sensitivity_crops: 8,
        }
    }
}

/// Quantise `model`'s search graph on `calib`. `progress(stage, done, total)` reports each step.
pub fn quantize(
    model: &BuiltModel,
    calib: &Calibration,
    opts: &QuantizeOptions,
    progress: &mut dyn FnMut(&str, usize, usize),
) -> Result<(BuiltModel, QuantizationInfo)> {
    let mut onnx =
        pb::ModelProto::decode(model.search.as_slice()).map_err(|e| Error::Other(format!("search graph: {e}")))?;
    let graph = onnx.graph.as_mut().ok_or_else(|| Error::Other("search graph: no graph".into()))?;
    if graph.node.iter().any(|n| n.op_type.starts_with("QLinear")) {
        return Err(Error::Quantize("the model is already quantised (its search graph has QLinear operators)".into()));
    }
    let cands: Vec<Candidate> = candidates(graph).into_iter().filter(|c| opts.depthwise || !c.depthwise).collect();
    for name in &opts.keep_fp32 {
        if !cands.iter().any(|c| &c.node == name) {
            let names: Vec<&str> = cands.iter().map(|c| c.node.as_str()).collect();
            return Err(Error::Quantize(format!(
                "--keep-fp32 `{name}` is not a quantisable layer; they are: {}",
                names.join(", ")
            )));
        }
    }
    let stats = calibrate::observe(model, graph, &cands, calib, progress)?;
    let inits: HashMap<&str, &pb::TensorProto> = graph.initializer.iter().map(|t| (t.name.as_str(), t)).collect();
    let ranges = Ranges::of(&stats, &cands, opts.method);
    let mut layers = vec![];
    for c in &cands {
        let (weight_error, per_channel, macs) = if c.kind == Kind::ActMatMul {
            let k = *stats.shapes[&c.input].last().expect("a matrix");
            (0.0, false, stats.shapes[&c.output].iter().product::<usize>() as u64 * k as u64)
        } else {
            let (dims, values) = c.weight_values(&inits);
            let axis = if c.kind == Kind::Conv { 0 } else { 1 };
            let err = |pc| {
                let (q, s) = quantise_weights(&values, &dims, axis, pc);
                let inner: usize = dims[axis + 1..].iter().product();
                let deq: Vec<f32> = q
                    .iter()
                    .enumerate()
                    .map(|(i, &v)| v as f32 * s[if pc { (i / inner) % dims[axis] } else { 0 }])
                    .collect();
                relative_error(&deq, &values).0
            };
            let (e_tensor, e_channel) = (err(false), err(true));
            let per_channel = match opts.per_channel {
                PerChannel::On => true,
                PerChannel::Off => false,
                // A depthwise layer's channels are filters of their own (one input channel each),
                // whose ranges differ widely: one scale for all of them costs accuracy.
                PerChannel::Auto => c.depthwise || (e_tensor > 0.02 && e_tensor > 2.0 * e_channel),
            };
            let k: usize = if c.kind == Kind::Conv { dims[1..].iter().product() } else { dims[0] };
            let macs = stats.shapes[&c.output].iter().product::<usize>() as u64 * k as u64;
            (if per_channel { e_channel } else { e_tensor }, per_channel, macs)
        };
        let out_channels = (c.kind == Kind::Conv).then(|| stats.shapes[&c.output][1]);
        let decision = if opts.keep_fp32.contains(&c.node) {
            LayerDecision::KeptByUser
        } else if macs < opts.min_macs && !c.depthwise {
            LayerDecision::TooSmall
        } else if out_channels.is_some_and(|n| n < opts.min_out_channels) {
            LayerDecision::FewChannels
        } else if c.kind == Kind::ActMatMul && !opts.act_matmul {
            LayerDecision::ActivationProduct
        } else {
            LayerDecision::Int8
        };
        layers.push(QuantLayer {
            node: c.node.clone(),
            op: match c.kind {
                Kind::Conv if c.depthwise => "dwconv",
                Kind::Conv => "conv",
                Kind::MatMul => "matmul",
                Kind::ActMatMul => "act-matmul",
            }
            .into(),
            macs,
            decision,
            per_channel,
            weight_error,
            input_range: ranges.range[&c.input],
            output_range: ranges.range[&c.output],
            sensitivity: None,
        });
    }
    let params = ranges.params;
    let template = onnx.clone();
    if let Some(budget) = opts.budget {
        sensitivity(&template, model, calib, &params, &mut layers, opts.sensitivity_crops, progress)?;
        let mut ranked: Vec<usize> = (0..layers.len()).filter(|&i| layers[i].decision == LayerDecision::Int8).collect();
        let score = |l: &QuantLayer| l.sensitivity.as_ref().map_or(0.0, |s| s.iter().cloned().fold(0.0, f64::max));
        ranked.sort_by(|&a, &b| score(&layers[b]).total_cmp(&score(&layers[a])));
        for &i in ranked.iter().take(budget) {
            layers[i].decision = LayerDecision::KeptSensitive;
        }
    }
    if !layers.iter().any(|l| l.decision == LayerDecision::Int8) {
        let small =
            layers.iter().filter(|l| matches!(l.decision, LayerDecision::TooSmall | LayerDecision::FewChannels));
        return Err(Error::Quantize(format!(
            "no layer would be int8: of {} candidates, {} are under the thresholds (min-macs {}, min-out-channels {}) \
             and the others are kept f32; lower the thresholds for a small network (NanoTrack: --min-macs 1000000 \
             --min-out-channels 16) or keep fewer layers",
            layers.len(),
            small.count(),
            opts.min_macs,
            opts.min_out_channels
        )));
    }
    let chosen = chosen_layers(&layers, None);
    let mut onnx = template;
    rewrite::rewrite(onnx.graph.as_mut().expect("checked above"), &chosen, &params)?;
    let bytes = onnx.encode_to_vec();
    let mut out = model.clone();
    out.manifest.search.sha256 = hex(&Sha256::digest(&bytes));
    out.search = bytes;
    let ranges = quantised_values(&onnx, &params);
    let report = QuantizationInfo {
        method: opts.method.name().into(),
        per_channel: opts.per_channel.name().into(),
        calibration: CalibrationInfo {
            template_crops: calib.templates.len(),
            search_crops: calib.searches.len(),
            ..calib.info.clone()
        },
        layers,
        ranges,
    };
    Ok((out, report))
}

/// The layers to rewrite: those decided int8, or only `only` when given.
fn chosen_layers(layers: &[QuantLayer], only: Option<&str>) -> HashMap<String, rewrite::NodePlan> {
    layers
        .iter()
        .filter(|l| match only {
            Some(n) => l.node == n,
            None => l.decision == LayerDecision::Int8,
        })
        .map(|l| (l.node.clone(), rewrite::NodePlan { per_channel: l.per_channel }))
        .collect()
}

/// The (min, max) each u8 tensor of the rewritten graph stands for.
fn quantised_values(onnx: &pb::ModelProto, params: &HashMap<String, QParams>) -> BTreeMap<String, (f32, f32)> {
    let graph = onnx.graph.as_ref().expect("a graph");
    graph
        .node
        .iter()
        .filter(|n| n.op_type == "DequantizeLinear" || n.op_type == "QuantizeLinear")
        .filter_map(|n| {
            let v = if n.op_type == "QuantizeLinear" { &n.input[0] } else { &n.output[0] };
            let p = params.get(v)?;
            let lo = p.scale * -(p.zero_point as f32);
            Some((v.clone(), (lo, lo + 255.0 * p.scale)))
        })
        .collect()
}

/// Quantise each int8-eligible layer alone and measure each search output against fp32.
fn sensitivity(
    onnx: &pb::ModelProto,
    model: &BuiltModel,
    calib: &Calibration,
    params: &HashMap<String, QParams>,
    layers: &mut [QuantLayer],
    crops: usize,
    progress: &mut dyn FnMut(&str, usize, usize),
) -> Result<()> {
    let samples = calibrate::Samples::spread(model, calib, crops)?;
    let reference = samples.run(model, &model.search)?;
    let todo: Vec<usize> = (0..layers.len()).filter(|&i| layers[i].decision == LayerDecision::Int8).collect();
    for (done, &i) in todo.iter().enumerate() {
        progress("sensitivity", done, todo.len());
        let mut one = onnx.clone();
        let chosen = chosen_layers(layers, Some(&layers[i].node));
        rewrite::rewrite(one.graph.as_mut().expect("a graph"), &chosen, params)?;
        let outs = samples.run(model, &one.encode_to_vec())?;
        let mut err = vec![0f64; reference.first().map_or(0, Vec::len)];
        for (o, r) in outs.iter().zip(&reference) {
            for (k, e) in err.iter_mut().enumerate() {
                *e += relative_error(&o[k].data, &r[k].data).0 / samples.len() as f64;
            }
        }
        layers[i].sensitivity = Some(err);
    }
    progress("sensitivity", todo.len(), todo.len());
    Ok(())
}
