//! Which nodes can become integer operators, and their weights in i8.

use std::collections::{HashMap, HashSet};

use tract_onnx::pb;

const FLOAT: i32 = 1;

/// Which integer operator a candidate becomes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `Conv` -> `QLinearConv`.
    Conv,
    /// `MatMul` with a constant right-hand side -> `QLinearMatMul`.
    MatMul,
    /// `MatMul` of two activations (HMG's attention products) -> `QLinearMatMul` with both
    /// sides quantised at run time.
    ActMatMul,
}

/// A node the quantiser can turn into an integer operator.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The node's name (stable: it is what `--keep-fp32` names).
    pub node: String,
    /// What it becomes.
    pub kind: Kind,
    /// Its activation input.
    pub input: String,
    /// The value its quantised output stands for: its own output, or that of the `Relu` (or
    /// `Clip` from 0) folded into it.
    pub output: String,
    /// The folded `Relu` node, if any, or `Clip` node with a lower bound of 0 (ReLU6: its output
    /// range starts at 0 and ends at most at the upper bound, so its u8 form is the layer's own
    /// output saturated at the ends of that range).
    pub relu: Option<String>,
    /// A `Relu` follows after a `MaxPool` (AlexNet's conv, BN, pool, ReLU): the output's range
    /// starts at 0, and pool and ReLU then run on u8.
    pub relu_after_pool: bool,
    /// The output's only consumer is a `HardSwish`, which is 0 at and below -3 (MobileNetV3's
    /// layers): the output's u8 range need not reach below that.
    pub hard_swish_after: bool,
    /// The weight initializer (for [`Kind::ActMatMul`], the right-hand activation).
    pub weight: String,
    /// The graph multiplies by the weight's transpose (a linear layer's `Transpose` of a
    /// PyTorch `[out, in]` weight).
    pub transposed: bool,
    /// A depthwise convolution (one group per channel, weights `[c, 1, kh, kw]`).
    pub depthwise: bool,
}

impl Candidate {
    /// The weight as the operator uses it: dims and row-major values.
    pub fn weight_values(&self, inits: &HashMap<&str, &pb::TensorProto>) -> (Vec<usize>, Vec<f32>) {
        let w = inits[self.weight.as_str()];
        let dims: Vec<usize> = w.dims.iter().map(|&d| d as usize).collect();
        let v = floats(w);
        if !self.transposed {
            return (dims, v);
        }
        let (r, c) = (dims[0], dims[1]);
        let t = (0..r * c).map(|i| v[(i % r) * c + i / r]).collect();
        (vec![c, r], t)
    }
}

/// The nodes of `model`'s graph that can become integer operators (depthwise convolutions
/// among them: [`Candidate::depthwise`]).
pub fn candidates(graph: &pb::GraphProto) -> Vec<Candidate> {
    let inits: HashMap<&str, &pb::TensorProto> = graph.initializer.iter().map(|t| (t.name.as_str(), t)).collect();
    let outputs: HashSet<&str> = graph.output.iter().map(|o| o.name.as_str()).collect();
    let mut consumers: HashMap<&str, Vec<&pb::NodeProto>> = HashMap::new();
    for n in &graph.node {
        for i in &n.input {
            consumers.entry(i.as_str()).or_default().push(n);
        }
    }
    // Transposes of 2-D initializers (linear layers): output name -> initializer.
    let transposes: HashMap<&str, &pb::TensorProto> = graph
        .node
        .iter()
        .filter(|n| n.op_type == "Transpose" && ints(n, "perm") == [1, 0])
        .filter_map(|n| Some((n.output[0].as_str(), *inits.get(n.input[0].as_str())?)))
        .collect();
    let sole = |v: &str, op: &str| match consumers.get(v).map(Vec::as_slice) {
        Some([c]) if c.op_type == op && !outputs.contains(v) => Some(*c),
        _ => None,
    };
    let mut found = vec![];
    for n in &graph.node {
        let Some(wname) = n.input.get(1) else { continue };
        let (w, transposed) = match (inits.get(wname.as_str()), transposes.get(wname.as_str())) {
            (Some(w), _) => (*w, false),
            (None, Some(w)) if n.op_type == "MatMul" => (*w, true),
            (None, None) if n.op_type == "MatMul" => {
                found.push(Candidate {
                    node: n.name.clone(),
                    kind: Kind::ActMatMul,
                    input: n.input[0].clone(),
                    output: n.output[0].clone(),
                    relu: None,
                    relu_after_pool: false,
                    hard_swish_after: false,
                    weight: wname.clone(),
                    transposed: false,
                    depthwise: false,
                });
                continue;
            }
            _ => continue,
        };
        let depthwise = w.dims.len() == 4 && w.dims[1] == 1 && group(n) > 1 && group(n) == w.dims[0];
        let kind = match n.op_type.as_str() {
            "Conv" if (group(n) == 1 || depthwise) && w.dims.len() == 4 => Kind::Conv,
            "MatMul" if w.dims.len() == 2 => Kind::MatMul,
            _ => continue,
        };
        if w.data_type != FLOAT {
            continue;
        }
        let out = n.output[0].as_str();
        let relu = sole(out, "Relu").or_else(|| sole(out, "Clip").filter(|c| clips_from_zero(c, &inits)));
        let relu_after_pool =
            relu.is_none() && sole(out, "MaxPool").is_some_and(|p| sole(&p.output[0], "Relu").is_some());
        found.push(Candidate {
            node: n.name.clone(),
            kind,
            input: n.input[0].clone(),
            output: relu.map_or(out, |r| r.output[0].as_str()).to_string(),
            relu: relu.map(|r| r.name.clone()),
            relu_after_pool,
            hard_swish_after: relu.is_none() && sole(out, "HardSwish").is_some(),
            weight: w.name.clone(),
            transposed,
            depthwise,
        });
    }
    found
}

/// Whether a `Clip` node's lower bound is 0 and its upper one above 0 (or absent): bounds as
/// inputs (opset 11 and later) from initializers, or as attributes (before).
fn clips_from_zero(n: &pb::NodeProto, inits: &HashMap<&str, &pb::TensorProto>) -> bool {
    let bound = |i: usize, attr: &str| match n.input.get(i).filter(|v| !v.is_empty()) {
        Some(v) => inits.get(v.as_str()).and_then(|t| floats(t).first().copied()).map(Some),
        None => Some(n.attribute.iter().find(|a| a.name == attr).map(|a| a.f)),
    };
    match (bound(1, "min"), bound(2, "max")) {
        (Some(Some(lo)), Some(hi)) => lo == 0.0 && hi.is_none_or(|h| h > 0.0),
        _ => false,
    }
}

fn ints(n: &pb::NodeProto, name: &str) -> Vec<i64> {
    n.attribute.iter().find(|a| a.name == name).map_or(vec![], |a| a.ints.clone())
}

fn group(n: &pb::NodeProto) -> i64 {
    n.attribute.iter().find(|a| a.name == "group").map_or(1, |a| a.i)
}

/// f32 values of an initializer.
pub fn floats(t: &pb::TensorProto) -> Vec<f32> {
    if t.raw_data.is_empty() {
        t.float_data.clone()
    } else {
        t.raw_data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
    }
}

/// Symmetric i8 weights: per output channel (`axis` of the weight) or one scale for all.
pub fn quantise_weights(w: &[f32], dims: &[usize], axis: usize, per_channel: bool) -> (Vec<i8>, Vec<f32>) {
    let channels = dims[axis];
    let inner: usize = dims[axis + 1..].iter().product();
    let channel = |i: usize| (i / inner) % channels;
    let mut absmax = vec![0f32; if per_channel { channels } else { 1 }];
    for (i, &v) in w.iter().enumerate() {
        let c = if per_channel { channel(i) } else { 0 };
        absmax[c] = absmax[c].max(v.abs());
    }
    let scales: Vec<f32> = absmax.iter().map(|&m| if m > 0.0 { m / 127.0 } else { 1.0 }).collect();
    let q = w
        .iter()
        .enumerate()
        .map(|(i, &v)| (v / scales[if per_channel { channel(i) } else { 0 }]).round().clamp(-127.0, 127.0) as i8)
        .collect();
    (q, scales)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_per_channel_use_each_channels_range() {
        let w = [1.0, -0.5, 0.005, 0.02];
        let (q, s) = quantise_weights(&w, &[2, 2], 0, true);
        assert_eq!(q, vec![127, -64, 32, 127]);
        assert_eq!(s, vec![1.0 / 127.0, 0.02 / 127.0]);
        let (q, s) = quantise_weights(&w, &[2, 2], 0, false);
        assert_eq!(q, vec![127, -64, 1, 3]);
        assert_eq!(s.len(), 1);
        // MatMul weights [K, N] are per column.
        let (_, s) = quantise_weights(&w, &[2, 2], 1, true);
        assert_eq!(s, vec![1.0 / 127.0, 0.5 / 127.0]);
    }

    #[test]
    fn a_hard_swish_read_only_by_itself_is_marked() {
        let node = |op: &str, name: &str, inputs: &[&str]| pb::NodeProto {
            op_type: op.into(),
            name: name.into(),
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: vec![format!("{name}_out")],
            ..Default::default()
        };
        let w = pb::TensorProto {
            name: "w".into(),
            dims: vec![2, 2, 1, 1],
            data_type: FLOAT,
            float_data: vec![1.0; 4],
            ..Default::default()
        };
        let graph = pb::GraphProto {
            node: vec![
                node("Conv", "a", &["x", "w"]),
                node("HardSwish", "a_hs", &["a_out"]),
                node("Conv", "b", &["a_hs_out", "w"]),
                node("HardSwish", "b_hs", &["b_out"]),
                node("Add", "b_add", &["b_out", "b_hs_out"]),
            ],
            initializer: vec![w],
            ..Default::default()
        };
        let found = candidates(&graph);
        let marked: Vec<(&str, bool)> = found.iter().map(|c| (c.node.as_str(), c.hard_swish_after)).collect();
        // b's output is also read raw by the Add: its values below -3 matter there.
        assert_eq!(marked, [("a", true), ("b", false)]);
    }

    #[test]
    fn a_clip_from_zero_folds_like_a_relu() {
        let scalar = |name: &str, v: f32| pb::TensorProto {
            name: name.into(),
            data_type: FLOAT,
            raw_data: v.to_le_bytes().to_vec(),
            ..Default::default()
        };
        let (zero, six, minus) = (scalar("zero", 0.0), scalar("six", 6.0), scalar("minus", -1.0));
        let inits: HashMap<&str, &pb::TensorProto> = [("zero", &zero), ("six", &six), ("minus", &minus)].into();
        let clip = |inputs: &[&str], attribute: Vec<pb::AttributeProto>| pb::NodeProto {
            op_type: "Clip".into(),
            input: inputs.iter().map(|s| s.to_string()).collect(),
            attribute,
            ..Default::default()
        };
        let attr = |name: &str, f: f32| pb::AttributeProto { name: name.into(), f, ..Default::default() };
        // ReLU6 and a clip from zero with no upper bound, as inputs or (before opset 11) attributes.
        assert!(clips_from_zero(&clip(&["x", "zero", "six"], vec![]), &inits));
        assert!(clips_from_zero(&clip(&["x", "zero"], vec![]), &inits));
        assert!(clips_from_zero(&clip(&["x", "zero", ""], vec![]), &inits));
        assert!(clips_from_zero(&clip(&["x"], vec![attr("min", 0.0), attr("max", 6.0)]), &inits));
        // Not from zero, no lower bound, or bounds the graph computes: not folded.
        assert!(!clips_from_zero(&clip(&["x", "minus", "six"], vec![]), &inits));
        assert!(!clips_from_zero(&clip(&["x", "", "six"], vec![]), &inits));
        assert!(!clips_from_zero(&clip(&["x", "computed", "six"], vec![]), &inits));
        assert!(!clips_from_zero(&clip(&["x", "zero", "minus"], vec![]), &inits));
    }
}
