//! Editing third-party ONNX models: renaming values, fixing input shapes, asking tract for the
//! output shapes, and joining a backbone and a head into one graph.

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};

use prost::Message;
use tract_onnx::pb;
use tract_onnx::prelude::{Framework, InferenceModelExt};

use crate::onnx::value_info;
use crate::{Error, Result};

/// An ONNX model read from a file, with the file's name for errors.
#[derive(Debug, Clone)]
pub(crate) struct Onnx {
    path: PathBuf,
    model: pb::ModelProto,
}

fn graph_err(path: &Path, msg: impl Into<String>) -> Error {
    Error::format(path, msg)
}

fn dims(v: &pb::ValueInfoProto) -> Option<Vec<Option<usize>>> {
    use pb::tensor_shape_proto::dimension::Value;
    let Some(pb::type_proto::Value::TensorType(t)) = v.r#type.as_ref()?.value.as_ref() else { return None };
    let shape = t.shape.as_ref()?;
    Some(
        shape
            .dim
            .iter()
            .map(|d| match d.value {
                Some(Value::DimValue(n)) if n > 0 => Some(n as usize),
                _ => None,
            })
            .collect(),
    )
}

/// A declared shape with every dimension known.
fn concrete(v: &pb::ValueInfoProto) -> Option<Vec<usize>> {
    dims(v)?.into_iter().collect()
}

/// NaN values in an f32 tensor's data (`None` for other types).
fn nan_count(t: &pb::TensorProto) -> Option<usize> {
    const FLOAT: i32 = 1;
    if t.data_type != FLOAT {
        return None;
    }
    let raw = t.raw_data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
    Some(raw.chain(t.float_data.iter().copied()).filter(|v| v.is_nan()).count())
}

impl Onnx {
    /// Decode `file` as an ONNX model with a graph of nodes.
    pub fn decode(file: &super::OnnxFile) -> Result<Onnx> {
        let path = file.path.clone();
        let model = pb::ModelProto::decode(file.bytes.as_slice())
            .map_err(|e| graph_err(&path, format!("not an ONNX model (truncated or corrupt?): {e}")))?;
        let Some(g) = model.graph.as_ref() else { return Err(graph_err(&path, "ONNX model without a graph")) };
        if g.node.is_empty() || g.output.is_empty() {
            return Err(graph_err(&path, "ONNX graph without nodes or outputs (truncated?)"));
        }
        if let Some(n) = g.node.iter().find(|n| n.attribute.iter().any(|a| a.g.is_some() || !a.graphs.is_empty())) {
            return Err(graph_err(&path, format!("node `{}` ({}) holds a subgraph; not supported", n.name, n.op_type)));
        }
        // A graph's inputs, outputs and initializers have names (an empty name is an absent
        // optional value to a node; fuzzing found an importer panicking on an unnamed input).
        let named = g.input.iter().map(|v| ("input", &v.name)).chain(g.output.iter().map(|v| ("output", &v.name)));
        let mut named = named.chain(g.initializer.iter().map(|t| ("initializer", &t.name)));
        if let Some((what, _)) = named.find(|(_, n)| n.is_empty()) {
            return Err(graph_err(&path, format!("a graph {what} has an empty name")));
        }
        // Every value has one name and one maker: graph inputs, initializers and node outputs
        // are distinct (an input listed twice, or a value two nodes make, cannot be renamed or
        // wired unambiguously), and so are the graph's outputs. An initializer may also be
        // listed as an input (ONNX's overridable constant); that is not a second maker.
        let mut makers: HashSet<&str> = HashSet::new();
        let inits: HashSet<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
        let inputs = g.input.iter().map(|v| v.name.as_str()).filter(|n| !inits.contains(n));
        let outputs = g.node.iter().flat_map(|n| n.output.iter().map(String::as_str)).filter(|n| !n.is_empty());
        if let Some(dup) =
            inputs.chain(g.initializer.iter().map(|t| t.name.as_str())).chain(outputs).find(|n| !makers.insert(n))
        {
            return Err(graph_err(
                &path,
                format!(
                    "value `{dup}` is made twice (listed twice as an input or initializer, or the output of two nodes)"
                ),
            ));
        }
        // Every graph output is listed once and is a value the graph makes (tract indexes
        // them unchecked).
        let mut seen = HashSet::new();
        for o in &g.output {
            if !seen.insert(o.name.as_str()) {
                return Err(graph_err(&path, format!("graph output `{}` is listed twice", o.name)));
            }
            if !makers.contains(o.name.as_str()) {
                return Err(graph_err(&path, format!("graph output `{}` is made by no node", o.name)));
            }
        }
        // A NaN weight makes every output NaN: a corrupt or diverged model, refused by name.
        // (Infinities pass: exporters use them for open clip bounds and masks.)
        let constants = g.node.iter().filter(|n| n.op_type == "Constant").flat_map(|n| n.attribute.iter());
        let tensors = g.initializer.iter().chain(constants.filter_map(|a| a.t.as_ref()));
        if let Some((name, count)) = tensors.filter_map(|t| nan_count(t).map(|c| (&t.name, c))).find(|(_, c)| *c > 0) {
            return Err(graph_err(&path, format!("weight `{name}` holds {count} NaN values (a corrupt model?)")));
        }
        Ok(Onnx { path, model })
    }

    fn graph(&self) -> &pb::GraphProto {
        self.model.graph.as_ref().expect("checked at decode")
    }

    fn graph_mut(&mut self) -> &mut pb::GraphProto {
        self.model.graph.as_mut().expect("checked at decode")
    }

    /// Positions in `graph.input` of the real inputs (not initializers listed as inputs).
    fn input_slots(&self) -> Vec<usize> {
        let g = self.graph();
        let inits: HashSet<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
        (0..g.input.len()).filter(|&i| !inits.contains(g.input[i].name.as_str())).collect()
    }

    fn input(&self, i: usize) -> &pb::ValueInfoProto {
        &self.graph().input[self.input_slots()[i]]
    }

    fn describe(values: &[&pb::ValueInfoProto]) -> String {
        let one = |v: &&pb::ValueInfoProto| match dims(v) {
            Some(d) => {
                let d: Vec<String> = d.iter().map(|x| x.map_or("?".into(), |n| n.to_string())).collect();
                format!("`{}` [{}]", v.name, d.join(", "))
            }
            None => format!("`{}`", v.name),
        };
        values.iter().map(one).collect::<Vec<_>>().join(", ")
    }

    /// Check the number of real inputs and of outputs; `hint` says what the role expects.
    pub fn expect_io(&self, inputs: usize, outputs: usize, hint: &str) -> Result<()> {
        let ins: Vec<&pb::ValueInfoProto> = self.input_slots().into_iter().map(|i| &self.graph().input[i]).collect();
        let outs: Vec<&pb::ValueInfoProto> = self.graph().output.iter().collect();
        if ins.len() == inputs && outs.len() == outputs {
            return Ok(());
        }
        let guess = match (ins.len(), inputs) {
            (2, 1) => " (is it the head?)",
            (1, 2) => " (is it the backbone?)",
            _ => "",
        };
        let hint = if hint.is_empty() { String::new() } else { format!(": {hint}") };
        Err(graph_err(
            &self.path,
            format!(
                "{} input(s) ({}) and {} output(s) ({}), expected {inputs} and {outputs}{hint}{guess}",
                ins.len(),
                Self::describe(&ins),
                outs.len(),
                Self::describe(&outs)
            ),
        ))
    }

    /// The single input must be an image: rank 4 with 3 channels where declared.
    pub fn expect_image_input(&self) -> Result<()> {
        let v = self.input(0);
        match dims(v) {
            Some(d) if d.len() == 4 && d[1].is_none_or(|c| c == 3) => Ok(()),
            Some(d) => Err(graph_err(
                &self.path,
                format!(
                    "input `{}` has rank {} {}; a backbone takes an image [1, 3, H, W]",
                    v.name,
                    d.len(),
                    Self::describe(&[v])
                ),
            )),
            None => Ok(()),
        }
    }

    /// Whether any node, graph input, output or initializer names `name`.
    fn names_value(&self, name: &str) -> bool {
        let g = self.graph();
        g.node.iter().flat_map(|n| n.input.iter().chain(&n.output)).any(|s| s == name)
            || g.input.iter().chain(&g.output).chain(&g.value_info).any(|v| v.name == name)
            || g.initializer.iter().any(|t| t.name == name)
    }

    /// Rename a value everywhere it appears. A value the model already calls `new` is renamed
    /// out of the way first (fuzzing found a backbone with a weight named `z`, which the input
    /// renamed `z` then became).
    fn rename_value(&mut self, old: &str, new: &str) {
        if old == new {
            return;
        }
        if self.names_value(new) {
            let free = (1..).map(|k| format!("{new}_{k}")).find(|n| !self.names_value(n)).expect("a free name");
            self.rename_value(new, &free);
        }
        let g = self.graph_mut();
        let swap = |s: &mut String| {
            if s == old {
                *s = new.to_string();
            }
        };
        for n in &mut g.node {
            n.input.iter_mut().chain(n.output.iter_mut()).for_each(swap);
        }
        g.input.iter_mut().chain(&mut g.output).chain(&mut g.value_info).for_each(|v| swap(&mut v.name));
        g.initializer.iter_mut().for_each(|t| swap(&mut t.name));
    }

    /// Rename the real input `i`.
    pub fn rename_input(&mut self, i: usize, name: &str) {
        let old = self.input(i).name.clone();
        self.rename_value(&old, name);
    }

    /// Rename the first real input to `input` and the outputs, in order, to `outputs`.
    pub fn rename_io(&mut self, input: &str, outputs: &[&str]) {
        self.rename_input(0, input);
        let olds: Vec<String> = self.graph().output.iter().map(|o| o.name.clone()).collect();
        for (old, new) in olds.iter().zip(outputs) {
            self.rename_value(old, new);
        }
    }

    /// Fix the real input `i` to `shape` (float).
    pub fn set_input_shape(&mut self, i: usize, shape: &[usize]) {
        let slot = self.input_slots()[i];
        let g = self.graph_mut();
        g.input[slot] = value_info(&g.input[slot].name, Some(shape));
    }

    /// Declare the outputs' shapes.
    pub fn set_output_shapes(&mut self, shapes: &[Vec<usize>]) {
        for (o, s) in self.graph_mut().output.iter_mut().zip(shapes) {
            *o = value_info(&o.name, Some(s));
        }
    }

    /// The outputs' shapes as tract infers them from the inputs' (the model's own declared
    /// intermediate and output shapes are dropped first: they were made for other input sizes).
    /// `what` says at which input sizes, for errors.
    pub fn infer_output_shapes(&mut self, file: &Path, what: &str) -> Result<Vec<Vec<usize>>> {
        let g = self.graph_mut();
        g.value_info.clear();
        for o in &mut g.output {
            *o = value_info(&o.name, None);
        }
        let err = |e: tract_onnx::prelude::TractError| {
            graph_err(file, format!("tract cannot run it {what}: {}", format!("{e:#}").replace('\n', " ")))
        };
        // tract's ONNX translation can panic on malformed graphs it does not check (found by
        // fuzzing: a stride of 0 divides by zero in its shape inference): a panic is a one-line
        // error naming the file, not an abort or a panic message.
        let typed = prl_runtime::catch_quietly(|| {
            let mut model = tract_onnx::onnx().model_for_proto_model(&self.model)?;
            if let Some((node, shape)) = crate::shapes::first_unfixed_shape(&mut model) {
                let msg =
                    format!("node {node:?}: output shape {shape} is not fixed {what} (shapes that do not broadcast?)");
                return Ok(Err(graph_err(file, msg)));
            }
            model.into_typed().map(Ok)
        });
        let model =
            typed.ok_or_else(|| graph_err(file, format!("tract cannot read it {what}: its graph is malformed")))?;
        let model = model.map_err(err)??;
        model
            .output_outlets()
            .map_err(err)?
            .iter()
            .map(|&o| {
                let fact = model.outlet_fact(o).map_err(err)?;
                let shape = fact.shape.as_concrete().map(<[usize]>::to_vec);
                shape.ok_or_else(|| graph_err(file, format!("output shape {:?} is not fixed {what}", fact.shape)))
            })
            .collect()
    }

    /// Which of a head's two inputs take the template and the search features, from their
    /// declared shapes (in order when undeclared).
    pub fn feature_inputs(&self, zf: &[usize], xf: &[usize]) -> Result<(usize, usize)> {
        let (a, b) = (concrete(self.input(0)), concrete(self.input(1)));
        let is = |v: &Option<Vec<usize>>, s: &[usize]| v.as_deref() == Some(s);
        match (&a, &b) {
            (None, None) => Ok((0, 1)),
            _ if is(&a, zf) && (b.is_none() || is(&b, xf)) => Ok((0, 1)),
            _ if is(&b, zf) && (a.is_none() || is(&a, xf)) => Ok((1, 0)),
            _ => Err(graph_err(
                &self.path,
                format!(
                    "inputs {} do not take the backbone's features: template {zf:?}, search {xf:?}",
                    Self::describe(&[self.input(0), self.input(1)])
                ),
            )),
        }
    }

    /// For each of the family's outputs `(name, channels)`, the index of the model output that
    /// is it: the one with that many channels where declared and unambiguous, else by position.
    pub fn order_outputs(&self, wanted: &[(&str, usize)]) -> Result<Vec<usize>> {
        let outs = &self.graph().output;
        let channels: Vec<Option<usize>> =
            outs.iter().map(|o| dims(o).and_then(|d| d.get(1).copied().flatten())).collect();
        let by_channels: Option<Vec<usize>> = wanted
            .iter()
            .map(|(_, c)| {
                let hits: Vec<usize> = (0..outs.len()).filter(|&i| channels[i] == Some(*c)).collect();
                (hits.len() == 1).then(|| hits[0])
            })
            .collect();
        match by_channels {
            Some(order) if order.iter().collect::<HashSet<_>>().len() == order.len() => Ok(order),
            _ if channels.iter().all(Option::is_none) => Ok((0..wanted.len()).collect()),
            _ => {
                let want: Vec<String> = wanted.iter().map(|(n, c)| format!("{n} ({c} channels)")).collect();
                let outs: Vec<&pb::ValueInfoProto> = outs.iter().collect();
                Err(graph_err(&self.path, format!("outputs {} are not {}", Self::describe(&outs), want.join(" and "))))
            }
        }
    }

    /// Put the outputs in `order`.
    pub fn reorder_outputs(&mut self, order: &[usize]) {
        let g = self.graph_mut();
        g.output = order.iter().map(|&i| g.output[i].clone()).collect();
    }

    /// The model as protobuf bytes, with `doc` as its doc string.
    pub fn encode(&self, doc: &str) -> Vec<u8> {
        let mut m = self.model.clone();
        m.doc_string = doc.into();
        m.producer_name = "prl-compiler import".into();
        m.producer_version = env!("CARGO_PKG_VERSION").into();
        m.encode_to_vec()
    }

    /// Every value and node name prefixed with `prefix/`, except those `keep` maps to a name.
    fn prefixed(&self, prefix: &str, keep: &BTreeMap<String, String>) -> pb::GraphProto {
        let name = |v: &str| -> String {
            if v.is_empty() {
                return String::new(); // an absent optional input
            }
            match keep.get(v) {
                Some(n) => n.clone(),
                None if v.starts_with('/') => format!("{prefix}{v}"),
                None => format!("{prefix}/{v}"),
            }
        };
        let mut g = self.graph().clone();
        for (k, n) in g.node.iter_mut().enumerate() {
            n.input.iter_mut().chain(n.output.iter_mut()).for_each(|v| *v = name(v));
            n.name = if n.name.is_empty() { format!("{prefix}/{}_{k}", n.op_type) } else { name(&n.name) };
        }
        g.initializer.iter_mut().for_each(|t| t.name = name(&t.name));
        g.input.iter_mut().chain(&mut g.output).for_each(|v| v.name = name(&v.name));
        g.value_info.clear();
        g
    }
}

/// Opsets of both models, one version per domain; differing versions are an error.
fn opsets(a: &Onnx, b: &Onnx) -> Result<Vec<pb::OperatorSetIdProto>> {
    let mut by_domain: BTreeMap<String, i64> = BTreeMap::new();
    for o in &a.model.opset_import {
        by_domain.insert(o.domain.clone(), o.version);
    }
    for o in &b.model.opset_import {
        match by_domain.get(&o.domain) {
            Some(&v) if v != o.version => {
                return Err(graph_err(
                    &b.path,
                    format!(
                        "opset {} of domain `{}`, but {} uses opset {v}: the two parts must share one opset",
                        o.version,
                        o.domain,
                        a.path.display()
                    ),
                ))
            }
            _ => drop(by_domain.insert(o.domain.clone(), o.version)),
        }
    }
    Ok(by_domain.into_iter().map(|(domain, version)| pb::OperatorSetIdProto { domain, version }).collect())
}

/// One search graph: `x` through the backbone into the head's search input `s_in`, the input
/// `zf` into its template input `t_in`; the head's outputs, in `order`, named `outputs`. Values
/// and nodes are prefixed `backbone/` and `head/` so the two never collide.
pub(crate) fn join(
    backbone: &Onnx,
    head: &Onnx,
    t_in: usize,
    s_in: usize,
    order: &[usize],
    outputs: &[String],
) -> Result<Onnx> {
    let b_out = backbone.graph().output[0].name.clone();
    let features = format!("backbone/{}", b_out.trim_start_matches('/'));
    let b_keep: BTreeMap<String, String> =
        [(backbone.input(0).name.clone(), "x".to_string()), (b_out, features.clone())].into();
    let mut h_keep: BTreeMap<String, String> =
        [(head.input(t_in).name.clone(), "zf".to_string()), (head.input(s_in).name.clone(), features)].into();
    for (&i, name) in order.iter().zip(outputs) {
        h_keep.insert(head.graph().output[i].name.clone(), name.clone());
    }
    let (b, h) = (backbone.prefixed("backbone", &b_keep), head.prefixed("head", &h_keep));
    let inits: HashSet<&str> = b.initializer.iter().chain(&h.initializer).map(|t| t.name.as_str()).collect();
    let real = |g: &pb::GraphProto| -> Vec<pb::ValueInfoProto> {
        g.input.iter().filter(|v| !inits.contains(v.name.as_str())).cloned().collect()
    };
    let x = real(&b).into_iter().find(|v| v.name == "x").expect("renamed above");
    let zf = real(&h).into_iter().find(|v| v.name == "zf").expect("renamed above");
    let graph = pb::GraphProto {
        name: "search".into(),
        node: b.node.iter().chain(&h.node).cloned().collect(),
        initializer: b.initializer.iter().chain(&h.initializer).cloned().collect(),
        input: vec![x, zf],
        output: order.iter().map(|&i| h.output[i].clone()).collect(),
        ..Default::default()
    };
    let model = pb::ModelProto {
        ir_version: backbone.model.ir_version.max(head.model.ir_version).max(4),
        opset_import: opsets(backbone, head)?,
        graph: Some(graph),
        ..Default::default()
    };
    Ok(Onnx { path: head.path.clone(), model })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::onnx::Graph;
    use crate::Tensor;

    #[test]
    fn renaming_to_a_name_the_model_uses_moves_that_value_out_of_the_way() {
        // Fuzzing found a backbone whose weight is named `z`, the name the template graph's
        // input takes: the renamed input was taken for the weight and no input was left.
        let mut g = Graph::new("tiny");
        let x = g.input("input", &[1, 3, 8, 8]).unwrap();
        let w = g.constant("z", &Tensor::new([2, 3, 1, 1], vec![1.0; 6])).unwrap();
        let y = g.node("Conv", "conv", &[&x, &w], &[]).unwrap();
        g.output(&y, &[1, 2, 8, 8]).unwrap();
        let file = super::super::OnnxFile { path: "tiny.onnx".into(), bytes: g.encode("test") };
        let mut m = Onnx::decode(&file).unwrap();
        m.rename_io("z", &["zf"]);
        m.set_input_shape(0, &[1, 3, 4, 4]);
        assert_eq!(m.input(0).name, "z");
        assert_eq!(m.graph().initializer[0].name, "z_1");
        assert_eq!(m.graph().node[0].input, ["z", "z_1"]);
        assert_eq!(m.infer_output_shapes(Path::new("tiny.onnx"), "").unwrap(), [vec![1, 2, 4, 4]]);
    }

    #[test]
    fn an_unnamed_graph_input_is_refused() {
        // Fuzzing found the join of backbone and head panicking on a head input named "".
        let mut g = Graph::new("tiny");
        let x = g.input("input", &[1, 3, 8, 8]).unwrap();
        let y = g.node("Relu", "relu", &[&x], &[]).unwrap();
        g.output(&y, &[1, 3, 8, 8]).unwrap();
        let mut model = g.to_model("test");
        model.graph.as_mut().unwrap().input[0].name.clear();
        let file = super::super::OnnxFile { path: "unnamed.onnx".into(), bytes: model.encode_to_vec() };
        let e = Onnx::decode(&file).unwrap_err().to_string();
        assert_eq!(e, "unnamed.onnx: a graph input has an empty name");
    }

    #[test]
    fn shapes_that_do_not_broadcast_are_refused_at_the_node_before_they_grow() {
        let file = super::super::OnnxFile { path: "wide.onnx".into(), bytes: crate::shapes::tests::unbroadcastable(5) };
        let mut m = Onnx::decode(&file).unwrap();
        let e = m.infer_output_shapes(Path::new("wide.onnx"), "here").unwrap_err().to_string();
        assert!(e.starts_with("wide.onnx: node \"mismatch\": output shape 1,2,16,broadcast("), "{e}");
        assert!(e.ends_with("is not fixed here (shapes that do not broadcast?)"), "{e}");
    }
}
