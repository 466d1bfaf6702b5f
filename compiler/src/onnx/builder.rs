//! The graph, its values and its initializers.

use std::collections::HashSet;

use prost::Message;
use tract_onnx::pb;

use crate::{Error, Result, Tensor};

/// ONNX opset the graphs are written against (GroupNormalization's per-channel affine needs 21).
pub const OPSET: i64 = 21;
const IR_VERSION: i64 = 10;
const FLOAT: i32 = 1;
const INT64: i32 = 7;

/// A handle on a value (tensor) of the graph under construction: its name.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Value(String);

impl Value {
    /// The value's name in the graph.
    pub fn name(&self) -> &str {
        &self.0
    }
}

/// A node attribute.
#[derive(Debug, Clone)]
pub enum Attr {
    /// One integer.
    Int(i64),
    /// A list of integers.
    Ints(Vec<i64>),
    /// One float.
    Float(f32),
    /// A string.
    Str(String),
}

/// An ONNX graph under construction.
pub struct Graph {
    name: String,
    nodes: Vec<pb::NodeProto>,
    initializers: Vec<pb::TensorProto>,
    inputs: Vec<pb::ValueInfoProto>,
    outputs: Vec<pb::ValueInfoProto>,
    values: HashSet<String>,
}

/// A float value of `shape` (no shape when `None`: left for inference).
pub(crate) fn value_info(name: &str, shape: Option<&[usize]>) -> pb::ValueInfoProto {
    use pb::tensor_shape_proto::{dimension, Dimension};
    let shape = shape.map(|s| pb::TensorShapeProto {
        dim: s
            .iter()
            .map(|&d| Dimension { value: Some(dimension::Value::DimValue(d as i64)), ..Default::default() })
            .collect(),
    });
    let tensor = pb::type_proto::Tensor { elem_type: FLOAT, shape };
    pb::ValueInfoProto {
        name: name.to_string(),
        r#type: Some(pb::TypeProto { value: Some(pb::type_proto::Value::TensorType(tensor)), ..Default::default() }),
        ..Default::default()
    }
}

impl Graph {
    /// An empty graph.
    pub fn new(name: impl Into<String>) -> Self {
        Graph {
            name: name.into(),
            nodes: vec![],
            initializers: vec![],
            inputs: vec![],
            outputs: vec![],
            values: HashSet::new(),
        }
    }

    /// The graph's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    fn error(&self, node: &str, msg: impl Into<String>) -> Error {
        Error::Graph { graph: self.name.clone(), node: node.into(), msg: msg.into() }
    }

    fn claim(&mut self, name: &str) -> Result<Value> {
        if !self.values.insert(name.to_string()) {
            return Err(self.error(name, "a value of this name already exists"));
        }
        Ok(Value(name.to_string()))
    }

    /// A graph input of fixed shape (f32).
    pub fn input(&mut self, name: &str, shape: &[usize]) -> Result<Value> {
        let v = self.claim(name)?;
        self.inputs.push(value_info(name, Some(shape)));
        Ok(v)
    }

    /// Mark `value` as a graph output of the given shape.
    pub fn output(&mut self, value: &Value, shape: &[usize]) -> Result<()> {
        if !self.values.contains(&value.0) {
            return Err(self.error(&value.0, "output of an unknown value"));
        }
        self.outputs.push(value_info(&value.0, Some(shape)));
        Ok(())
    }

    /// An f32 initializer (a weight keeps its checkpoint key as name).
    pub fn constant(&mut self, name: &str, t: &Tensor) -> Result<Value> {
        let v = self.claim(name)?;
        self.initializers.push(pb::TensorProto {
            name: name.to_string(),
            dims: t.shape.iter().map(|&d| d as i64).collect(),
            data_type: FLOAT,
            raw_data: t.data.iter().flat_map(|x| x.to_le_bytes()).collect(),
            ..Default::default()
        });
        Ok(v)
    }

    /// An i64 initializer (shapes, indices, slice bounds).
    pub fn constant_i64(&mut self, name: &str, shape: &[usize], data: &[i64]) -> Result<Value> {
        if shape.iter().product::<usize>() != data.len() {
            return Err(self.error(name, format!("shape {shape:?} for {} values", data.len())));
        }
        let v = self.claim(name)?;
        self.initializers.push(pb::TensorProto {
            name: name.to_string(),
            dims: shape.iter().map(|&d| d as i64).collect(),
            data_type: INT64,
            raw_data: data.iter().flat_map(|x| x.to_le_bytes()).collect(),
            ..Default::default()
        });
        Ok(v)
    }

    /// A node of `op` named `name`, whose single output value is also called `name`.
    pub fn node(&mut self, op: &str, name: &str, inputs: &[&Value], attrs: &[(&str, Attr)]) -> Result<Value> {
        for i in inputs {
            if !self.values.contains(&i.0) {
                return Err(self.error(name, format!("{op} reads unknown value `{}`", i.0)));
            }
        }
        let out = self.claim(name)?;
        let attribute = attrs.iter().map(|(n, a)| attribute(n, a)).collect();
        self.nodes.push(pb::NodeProto {
            name: name.to_string(),
            op_type: op.to_string(),
            input: inputs.iter().map(|v| v.0.clone()).collect(),
            output: vec![name.to_string()],
            attribute,
            ..Default::default()
        });
        Ok(out)
    }

    /// Number of nodes so far.
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// The finished model.
    pub fn to_model(&self, doc: &str) -> pb::ModelProto {
        pb::ModelProto {
            ir_version: IR_VERSION,
            opset_import: vec![pb::OperatorSetIdProto { domain: String::new(), version: OPSET }],
            producer_name: "prl-compiler".into(),
            producer_version: env!("CARGO_PKG_VERSION").into(),
            doc_string: doc.into(),
            graph: Some(pb::GraphProto {
                name: self.name.clone(),
                node: self.nodes.clone(),
                initializer: self.initializers.clone(),
                input: self.inputs.clone(),
                output: self.outputs.clone(),
                ..Default::default()
            }),
            ..Default::default()
        }
    }

    /// The finished model as ONNX protobuf bytes.
    pub fn encode(&self, doc: &str) -> Vec<u8> {
        self.to_model(doc).encode_to_vec()
    }
}

fn attribute(name: &str, a: &Attr) -> pb::AttributeProto {
    use pb::attribute_proto::AttributeType as T;
    let mut p = pb::AttributeProto { name: name.to_string(), ..Default::default() };
    match a {
        Attr::Int(i) => (p.i, p.r#type) = (*i, T::Int as i32),
        Attr::Ints(v) => (p.ints, p.r#type) = (v.clone(), T::Ints as i32),
        Attr::Float(f) => (p.f, p.r#type) = (*f, T::Float as i32),
        Attr::Str(s) => (p.s, p.r#type) = (s.as_bytes().to_vec(), T::String as i32),
    }
    p
}
