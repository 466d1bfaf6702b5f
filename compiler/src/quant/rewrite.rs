//! The ONNX rewrite: chosen `Conv` and `MatMul` nodes (constant weights) become `QLinearConv` and
//! `QLinearMatMul` on u8 activations and symmetric i8 weights, with requantisation fused into the
//! integer kernel. A `Relu` that is a node's only consumer folds into its output range; `MaxPool`
//! of a quantised value runs on u8 (max commutes with an increasing map). Float consumers read a
//! `DequantizeLinear` that keeps the original value name, so the rest of the graph is untouched.

use std::collections::{HashMap, HashSet};

use tract_onnx::pb;

use super::candidates::{candidates, floats, quantise_weights, Candidate, Kind};
use crate::{Error, Result};

const FLOAT: i32 = 1;
const UINT8: i32 = 2;
const INT8: i32 = 3;
const INT32: i32 = 6;

/// Quantisation parameters of a u8 tensor: `real = scale * (q - zero_point)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QParams {
    /// Step between two levels.
    pub scale: f32,
    /// The level that stands for 0.
    pub zero_point: u8,
}

impl QParams {
    /// u8 parameters covering `[lo, hi]` (which must hold 0).
    pub fn from_range(lo: f32, hi: f32) -> QParams {
        let scale = (hi - lo) / 255.0;
        if scale.is_nan() || scale <= 0.0 || !scale.is_finite() {
            return QParams { scale: 1.0, zero_point: 0 };
        }
        QParams { scale, zero_point: (-lo / scale).round().clamp(0.0, 255.0) as u8 }
    }

    /// u8 parameters covering `[floor, hi]` whose lowest code stands for `floor` or less (where
    /// rounding the zero point would put it above).
    pub fn from_range_floor(floor: f32, hi: f32) -> QParams {
        let mut p = QParams::from_range(floor, hi);
        if -(p.zero_point as f32) * p.scale > floor && p.zero_point < 255 {
            p.zero_point += 1;
        }
        p
    }
}

/// What the rewrite needs to know about one quantised node.
#[derive(Debug, Clone)]
pub struct NodePlan {
    /// Per-output-channel weight scales instead of one.
    pub per_channel: bool,
}

/// Rewrite `graph` in place: every candidate named in `chosen` becomes an integer operator, with
/// activation parameters from `params` (by value name).
pub fn rewrite(
    graph: &mut pb::GraphProto,
    chosen: &HashMap<String, NodePlan>,
    params: &HashMap<String, QParams>,
) -> Result<()> {
    let cands: HashMap<String, Candidate> =
        candidates(graph).into_iter().filter(|c| chosen.contains_key(&c.node)).map(|c| (c.node.clone(), c)).collect();
    let folded: HashSet<String> = cands.values().filter_map(|c| c.relu.clone()).collect();
    let mut inits: HashMap<String, pb::TensorProto> =
        std::mem::take(&mut graph.initializer).into_iter().map(|t| (t.name.clone(), t)).collect();
    let mut new_inits: Vec<pb::TensorProto> = vec![];
    let mut nodes = vec![];
    // Float value name -> (its u8 twin, parameters).
    let mut quantised: HashMap<String, (String, QParams)> = HashMap::new();
    let param = |v: &str, node: &str| {
        params.get(v).copied().ok_or_else(|| Error::Graph {
            graph: graph.name.clone(),
            node: node.into(),
            msg: format!("no calibrated range for `{v}`"),
        })
    };
    // Activations are quantised where they are made, so that data movement between there and
    // the integer operator (reshapes, gathers, ReLU) runs on u8.
    let Placement { roots, path } = placement(&graph.node, &cands, params);
    let quantise = |v: &str, p: QParams, nodes: &mut Vec<pb::NodeProto>, new_inits: &mut Vec<pb::TensorProto>| {
        let q = format!("{v}.u8");
        let (s, z) = scalar_params(new_inits, &q, p);
        nodes.push(node("QuantizeLinear", &q, &[v, &s, &z], &q, vec![]));
        (q, p)
    };
    for input in &graph.input {
        if let Some(&p) = roots.get(&input.name) {
            let q = quantise(&input.name, p, &mut nodes, &mut new_inits);
            quantised.insert(input.name.clone(), q);
        }
    }
    for n in std::mem::take(&mut graph.node) {
        if folded.contains(&n.name) {
            continue;
        }
        if let Some(c) = cands.get(&n.name) {
            let mut operand = |v: &str, nodes: &mut Vec<pb::NodeProto>, new_inits: &mut Vec<pb::TensorProto>| {
                Ok::<_, Error>(match quantised.get(v) {
                    Some(q) => q.clone(),
                    None => {
                        let q = quantise(v, param(v, &n.name)?, nodes, new_inits);
                        quantised.insert(v.to_string(), q.clone());
                        q
                    }
                })
            };
            let (xq, xp) = operand(&c.input, &mut nodes, &mut new_inits)?;
            let yp = param(&c.output, &n.name)?;
            if c.kind == Kind::ActMatMul {
                let (bq, _) = operand(&c.weight, &mut nodes, &mut new_inits)?;
                let yq = format!("{}.u8", c.output);
                let (ys, yz) = scalar_params(&mut new_inits, &yq, yp);
                let (xs, xz, bs, bz) =
                    (format!("{xq}.scale"), format!("{xq}.zero"), format!("{bq}.scale"), format!("{bq}.zero"));
                nodes.push(node("QLinearMatMul", &c.node, &[&xq, &xs, &xz, &bq, &bs, &bz, &ys, &yz], &yq, vec![]));
                nodes.push(node("DequantizeLinear", &format!("{}.f32", c.output), &[&yq, &ys, &yz], &c.output, vec![]));
                quantised.insert(c.output.clone(), (yq, yp));
                continue;
            }
            let (dims, values) = {
                let refs: HashMap<&str, &pb::TensorProto> = inits.iter().map(|(k, v)| (k.as_str(), v)).collect();
                c.weight_values(&refs)
            };
            let wdims: Vec<i64> = dims.iter().map(|&d| d as i64).collect();
            let axis = if c.kind == Kind::Conv { 0 } else { 1 };
            let per_channel = chosen[&c.node].per_channel;
            let (wq, ws) = quantise_weights(&values, &dims, axis, per_channel);
            let wname = format!("{}.i8", c.node);
            new_inits.push(init(&wname, &wdims, INT8, wq.iter().map(|&v| v as u8).collect()));
            let sdims: Vec<i64> = if per_channel { vec![ws.len() as i64] } else { vec![] };
            new_inits.push(init(&format!("{wname}.scale"), &sdims, FLOAT, le(&ws)));
            new_inits.push(init(&format!("{wname}.zero"), &sdims, INT8, vec![0; ws.len()]));
            let yq = format!("{}.u8", c.output);
            let (ys, yz) = scalar_params(&mut new_inits, &yq, yp);
            let (xs, xz) = (format!("{xq}.scale"), format!("{xq}.zero"));
            let (wsn, wzn) = (format!("{wname}.scale"), format!("{wname}.zero"));
            let mut inputs = vec![xq.as_str(), &xs, &xz, &wname, &wsn, &wzn, &ys, &yz];
            let bias_name = format!("{}.i32", c.node);
            if c.kind == Kind::Conv {
                if let Some(b) = n.input.get(2).and_then(|b| inits.get(b)) {
                    let bias: Vec<i32> = floats(b)
                        .iter()
                        .enumerate()
                        .map(|(i, &v)| {
                            let s = xp.scale * ws[if per_channel { i } else { 0 }];
                            (v as f64 / s as f64).round().clamp(i32::MIN as f64, i32::MAX as f64) as i32
                        })
                        .collect();
                    new_inits.push(init(&bias_name, &b.dims, INT32, le(&bias)));
                    inputs.push(&bias_name);
                }
            }
            let op = if c.kind == Kind::Conv { "QLinearConv" } else { "QLinearMatMul" };
            let attrs = if c.kind == Kind::Conv { n.attribute.clone() } else { vec![] };
            nodes.push(node(op, &c.node, &inputs, &yq, attrs));
            nodes.push(node("DequantizeLinear", &format!("{}.f32", c.output), &[&yq, &ys, &yz], &c.output, vec![]));
            quantised.insert(c.output.clone(), (yq, yp));
            continue;
        }
        // Data movement and max pooling commute with an increasing map; ReLU is the identity on
        // a u8 tensor whose zero point is 0 (nothing below 0 is representable).
        // Only on the way to an integer operator, or after one (pools of quantised outputs).
        let wanted = path.contains(&n.output[0]) || matches!(n.op_type.as_str(), "MaxPool" | "Relu");
        let passes = |p: &QParams| wanted && passes_u8(&n.op_type, p);
        if n.output.len() == 1 && quantised.get(&n.input[0]).is_some_and(|(_, p)| passes(p)) {
            if let Some((xq, p)) = quantised.get(&n.input[0]).cloned() {
                let out = n.output[0].clone();
                let yq = if n.op_type == "Relu" {
                    xq
                } else {
                    let yq = format!("{out}.u8");
                    let inputs = std::iter::once(xq).chain(n.input[1..].iter().cloned()).collect();
                    nodes.push(pb::NodeProto { input: inputs, output: vec![yq.clone()], ..n });
                    yq
                };
                let (s, z) = (format!("{yq}.scale"), format!("{yq}.zero"));
                if !new_inits.iter().any(|t| t.name == s) {
                    scalar_params(&mut new_inits, &yq, p);
                }
                nodes.push(node("DequantizeLinear", &format!("{out}.f32"), &[&yq, &s, &z], &out, vec![]));
                quantised.insert(out, (yq, p));
                continue;
            }
        }
        let outs = n.output.clone();
        nodes.push(n);
        for o in outs {
            if let (Some(&p), false) = (roots.get(&o), quantised.contains_key(&o)) {
                let q = quantise(&o, p, &mut nodes, &mut new_inits);
                quantised.insert(o, q);
            }
        }
    }
    let nodes = prune(nodes, graph.output.iter().map(|o| o.name.clone()).collect());
    // Weights of quantised nodes are no longer read in f32.
    let read: HashSet<&str> = nodes.iter().flat_map(|n| n.input.iter().map(String::as_str)).collect();
    inits.retain(|k, _| read.contains(k.as_str()));
    let mut kept: Vec<pb::TensorProto> = inits.into_values().collect();
    kept.sort_by(|a, b| a.name.cmp(&b.name));
    graph.initializer = kept.into_iter().chain(new_inits).collect();
    graph.node = nodes;
    Ok(())
}

/// Whether `op` can run on the u8 twin of its first input (parameters `p`) unchanged.
fn passes_u8(op: &str, p: &QParams) -> bool {
    matches!(op, "MaxPool" | "Reshape" | "Transpose" | "Gather") || (op == "Relu" && p.zero_point == 0)
}

/// Where activations are quantised, and which values then travel in u8.
struct Placement {
    /// Values quantised where they are made (a graph input, at the start), with parameters.
    roots: HashMap<String, QParams>,
    /// Values between a root and an integer operator's input: made on u8 by data movement.
    path: HashSet<String>,
}

/// For each integer operator's activation input, walk back through data movement (reshapes,
/// transposes, gathers, ReLU) to the value that feeds it: quantising there lets the movement
/// run on u8, a quarter of the bytes. Max pooling is not walked through: quantising after it
/// touches a quarter of the values.
fn placement(
    nodes: &[pb::NodeProto],
    cands: &HashMap<String, Candidate>,
    params: &HashMap<String, QParams>,
) -> Placement {
    let producer: HashMap<&str, &pb::NodeProto> =
        nodes.iter().flat_map(|n| n.output.iter().map(move |o| (o.as_str(), n))).collect();
    let outputs: HashSet<&str> = cands.values().map(|c| c.output.as_str()).collect();
    let mut plan = Placement { roots: HashMap::new(), path: HashSet::new() };
    for c in cands.values() {
        let inputs = if c.kind == Kind::ActMatMul { vec![&c.input, &c.weight] } else { vec![&c.input] };
        for v in inputs {
            let Some(&p) = params.get(v) else { continue };
            let mut at = v.as_str();
            while let Some(n) = producer
                .get(at)
                .filter(|n| n.op_type != "MaxPool" && passes_u8(&n.op_type, &p) && !outputs.contains(at))
            {
                plan.path.insert(at.to_string());
                at = n.input[0].as_str();
            }
            // A value an integer operator makes is u8 already.
            if !outputs.contains(at) {
                plan.roots.insert(at.to_string(), p);
            }
        }
    }
    plan
}

/// Drop nodes nothing reads (dequantisations no float operator needs, transposes of weights
/// now stored as i8).
fn prune(nodes: Vec<pb::NodeProto>, outputs: HashSet<String>) -> Vec<pb::NodeProto> {
    let mut live = outputs;
    let mut kept: Vec<pb::NodeProto> = vec![];
    for n in nodes.into_iter().rev() {
        if n.output.iter().any(|o| live.contains(o)) {
            live.extend(n.input.iter().cloned());
            kept.push(n);
        }
    }
    kept.reverse();
    kept
}

/// Scalar scale and zero-point initializers `<name>.scale`, `<name>.zero`.
fn scalar_params(inits: &mut Vec<pb::TensorProto>, name: &str, p: QParams) -> (String, String) {
    let (s, z) = (format!("{name}.scale"), format!("{name}.zero"));
    inits.push(init(&s, &[], FLOAT, le(&[p.scale])));
    inits.push(init(&z, &[], UINT8, vec![p.zero_point]));
    (s, z)
}

fn le<T: Copy + ToLe>(v: &[T]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le()).collect()
}

trait ToLe {
    fn to_le(self) -> [u8; 4];
}
impl ToLe for f32 {
    fn to_le(self) -> [u8; 4] {
        self.to_le_bytes()
    }
}
impl ToLe for i32 {
    fn to_le(self) -> [u8; 4] {
        self.to_le_bytes()
    }
}

fn init(name: &str, dims: &[i64], data_type: i32, raw_data: Vec<u8>) -> pb::TensorProto {
    pb::TensorProto { name: name.into(), dims: dims.to_vec(), data_type, raw_data, ..Default::default() }
}

fn node(op: &str, name: &str, inputs: &[&str], output: &str, attribute: Vec<pb::AttributeProto>) -> pb::NodeProto {
    pb::NodeProto {
        name: name.into(),
        op_type: op.into(),
        input: inputs.iter().map(|s| s.to_string()).collect(),
        output: vec![output.into()],
        attribute,
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn qparams_keep_zero_exact() {
        let p = QParams::from_range(0.0, 255.0);
        assert_eq!((p.scale, p.zero_point), (1.0, 0));
        let p = QParams::from_range(-1.0, 3.0);
        assert_eq!(p.zero_point, 64);
        assert_eq!(QParams::from_range(0.0, 0.0).scale, 1.0);
    }

    #[test]
    fn a_floor_stays_at_or_above_the_lowest_code() {
        // [-3, 10]: 3/(13/255) = 58.8 rounds to 59, whose code stands for -3.008: kept.
        // [-3, 9.2]: 3/(12.2/255) = 62.7 rounds to 63 (-3.014): kept. [-3, 16.5]:
        // 3/(19.5/255) = 39.23 rounds down to 39 (-2.98), above -3: one code more.
        for hi in [10.0, 9.2, 16.5, 83.758, 0.5] {
            let p = QParams::from_range_floor(-3.0, hi);
            let lowest = -(p.zero_point as f32) * p.scale;
            assert!(lowest <= -3.0 && lowest > -3.0 - p.scale, "[-3, {hi}]: lowest code {lowest}");
        }
        assert_eq!(QParams::from_range_floor(-3.0, 16.5).zero_point, 40);
    }
}
