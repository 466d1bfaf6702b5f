//! A small fluent ONNX graph builder (protobuf via `prost`): graphs, value handles,
//! initializers and node constructors grouped by op family, one file each.

mod builder;
mod conv;
mod math;
mod norm;
mod pool;
mod shape;

pub(crate) use builder::value_info;
pub use builder::{Attr, Graph, Value, OPSET};
pub use conv::ConvOpts;
