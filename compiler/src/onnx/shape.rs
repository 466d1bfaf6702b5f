//! Shape manipulation: reshape, transpose, concat, slice, gather.

use super::{Attr, Graph, Value};
use crate::Result;

impl Graph {
    /// `Reshape` to a fixed shape (one `-1` allowed).
    pub fn reshape(&mut self, name: &str, x: &Value, shape: &[i64]) -> Result<Value> {
        let s = self.constant_i64(&format!("{name}.shape"), &[shape.len()], shape)?;
        self.node("Reshape", name, &[x, &s], &[])
    }
    /// `Transpose` with permutation `perm`.
    pub fn transpose(&mut self, name: &str, x: &Value, perm: &[i64]) -> Result<Value> {
        self.node("Transpose", name, &[x], &[("perm", Attr::Ints(perm.to_vec()))])
    }
    /// `Concat` along `axis`.
    pub fn concat(&mut self, name: &str, xs: &[&Value], axis: i64) -> Result<Value> {
        self.node("Concat", name, xs, &[("axis", Attr::Int(axis))])
    }
    /// `Slice`: `x[start..end]` along `axis`.
    pub fn slice(&mut self, name: &str, x: &Value, axis: i64, start: i64, end: i64) -> Result<Value> {
        let starts = self.constant_i64(&format!("{name}.starts"), &[1], &[start])?;
        let ends = self.constant_i64(&format!("{name}.ends"), &[1], &[end])?;
        let axes = self.constant_i64(&format!("{name}.axes"), &[1], &[axis])?;
        self.node("Slice", name, &[x, &starts, &ends, &axes], &[])
    }
    /// `Gather` of constant `indices` along `axis`.
    pub fn gather(&mut self, name: &str, x: &Value, axis: i64, indices: &[i64]) -> Result<Value> {
        let idx = self.constant_i64(&format!("{name}.indices"), &[indices.len()], indices)?;
        self.node("Gather", name, &[x, &idx], &[("axis", Attr::Int(axis))])
    }
    /// `Gather` along `axis` with constant `indices` of shape `shape` (any rank).
    pub fn gather_nd_indices(
        &mut self,
        name: &str,
        x: &Value,
        axis: i64,
        shape: &[usize],
        indices: &[i64],
    ) -> Result<Value> {
        let idx = self.constant_i64(&format!("{name}.indices"), shape, indices)?;
        self.node("Gather", name, &[x, &idx], &[("axis", Attr::Int(axis))])
    }
}
