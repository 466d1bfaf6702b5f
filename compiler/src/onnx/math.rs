//! Element-wise maths, activations, softmax and matrix products.

use super::{Attr, Graph, Value};
use crate::Result;

impl Graph {
    /// `a + b` (broadcasting).
    pub fn add(&mut self, name: &str, a: &Value, b: &Value) -> Result<Value> {
        self.node("Add", name, &[a, b], &[])
    }
    /// `a * b` (broadcasting).
    pub fn mul(&mut self, name: &str, a: &Value, b: &Value) -> Result<Value> {
        self.node("Mul", name, &[a, b], &[])
    }
    /// `a / b` (broadcasting).
    pub fn div(&mut self, name: &str, a: &Value, b: &Value) -> Result<Value> {
        self.node("Div", name, &[a, b], &[])
    }
    /// `max(x, 0)`.
    pub fn relu(&mut self, name: &str, x: &Value) -> Result<Value> {
        self.node("Relu", name, &[x], &[])
    }
    /// `1 / (1 + exp(-x))`.
    pub fn sigmoid(&mut self, name: &str, x: &Value) -> Result<Value> {
        self.node("Sigmoid", name, &[x], &[])
    }
    /// `exp(x)`.
    pub fn exp(&mut self, name: &str, x: &Value) -> Result<Value> {
        self.node("Exp", name, &[x], &[])
    }
    /// Exact GELU, `x/2 * (1 + erf(x/√2))` (opset 20 `Gelu`, `approximate = "none"`).
    pub fn gelu(&mut self, name: &str, x: &Value) -> Result<Value> {
        self.node("Gelu", name, &[x], &[("approximate", Attr::Str("none".into()))])
    }
    /// Softmax along `axis`.
    pub fn softmax(&mut self, name: &str, x: &Value, axis: i64) -> Result<Value> {
        self.node("Softmax", name, &[x], &[("axis", Attr::Int(axis))])
    }
    /// Batched matrix product.
    pub fn matmul(&mut self, name: &str, a: &Value, b: &Value) -> Result<Value> {
        self.node("MatMul", name, &[a, b], &[])
    }
    /// A linear layer as PyTorch stores it: `x · wᵀ (+ b)`, `w` of shape [out, in].
    pub fn linear(&mut self, name: &str, x: &Value, w: &Value, b: Option<&Value>) -> Result<Value> {
        let wt = self.transpose(&format!("{name}.weight_t"), w, &[1, 0])?;
        match b {
            Some(b) => {
                let y = self.matmul(&format!("{name}.matmul"), x, &wt)?;
                self.add(name, &y, b)
            }
            None => self.matmul(name, x, &wt),
        }
    }
}
