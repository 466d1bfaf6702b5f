//! Normalisations.

use super::{Attr, Graph, Value};
use crate::Result;

impl Graph {
    /// `LayerNormalization` over the last axis.
    pub fn layer_norm(&mut self, name: &str, x: &Value, scale: &Value, bias: &Value, eps: f32) -> Result<Value> {
        self.node(
            "LayerNormalization",
            name,
            &[x, scale, bias],
            &[("axis", Attr::Int(-1)), ("epsilon", Attr::Float(eps))],
        )
    }

    /// `GroupNormalization` (opset 21: per-channel scale and bias, like PyTorch's GroupNorm).
    pub fn group_norm(
        &mut self,
        name: &str,
        x: &Value,
        groups: usize,
        scale: &Value,
        bias: &Value,
        eps: f32,
    ) -> Result<Value> {
        self.node(
            "GroupNormalization",
            name,
            &[x, scale, bias],
            &[("num_groups", Attr::Int(groups as i64)), ("epsilon", Attr::Float(eps))],
        )
    }
}
