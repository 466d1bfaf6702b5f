//! Pooling.

use super::{Attr, Graph, Value};
use crate::Result;

impl Graph {
    /// `MaxPool`, square kernel, no padding.
    pub fn max_pool(&mut self, name: &str, x: &Value, kernel: usize, stride: usize) -> Result<Value> {
        let (k, s) = (kernel as i64, stride as i64);
        self.node(
            "MaxPool",
            name,
            &[x],
            &[("kernel_shape", Attr::Ints(vec![k, k])), ("strides", Attr::Ints(vec![s, s]))],
        )
    }

    /// `AveragePool` with padding counted in the divisor (PyTorch's default `count_include_pad`).
    pub fn avg_pool(&mut self, name: &str, x: &Value, kernel: usize, stride: usize, pad: usize) -> Result<Value> {
        let (k, s, p) = (kernel as i64, stride as i64, pad as i64);
        self.node(
            "AveragePool",
            name,
            &[x],
            &[
                ("kernel_shape", Attr::Ints(vec![k, k])),
                ("strides", Attr::Ints(vec![s, s])),
                ("pads", Attr::Ints(vec![p, p, p, p])),
                ("count_include_pad", Attr::Int(1)),
            ],
        )
    }

    /// `GlobalAveragePool`: [N,C,H,W] -> [N,C,1,1].
    pub fn global_avg_pool(&mut self, name: &str, x: &Value) -> Result<Value> {
        self.node("GlobalAveragePool", name, &[x], &[])
    }
}
