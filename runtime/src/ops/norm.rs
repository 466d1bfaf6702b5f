//! HMG's layer norms without their affine part: `(x − mean) / sqrt(mean((x − mean)²) + eps)`
//! over one axis, as [`LayerNormCore`].
//!
//! tract declutters ONNX `LayerNormalization` into a sum, a scaling, a broadcast subtraction and
//! its `RmsNorm`, and folds the scale and bias into the next linear layer. With the tokens moved
//! to the last axis, the normalised axis (576 channels) is strided, and the four ops took 1.3 ms
//! a norm on [576, 121] (HMG has four). Here the columns go in groups of 16: one pass over the
//! rows sums a group, one sums its squared deviations and one writes it: 0.039 ms a norm on one
//! thread, against 0.042 with whole rows a pass (Intel Xeon VM, 2026-12-06). Splitting the
//! groups over two threads made it slower there (0.05 -> 0.08 ms).

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::binary::TypedBinOp;
use tract_nnef::tract_core::ops::math::{Mul, Sub};
use tract_nnef::tract_core::ops::nn::{Reduce, Reducer, RmsNorm};

/// `y = (x − m) / sqrt(v + eps)` with `m` the mean and `v` the mean square of `x − m` along
/// `axis` (tract's `RmsNorm` of the centred input).
#[derive(Debug, Clone, PartialEq)]
pub struct LayerNormCore {
    /// The normalised axis.
    pub axis: usize,
    /// Added to the mean square.
    pub eps: f32,
}

impl Eq for LayerNormCore {}

impl Op for LayerNormCore {
    fn name(&self) -> StaticName {
        "LayerNormCore".into()
    }
    op_as_typed_op!();
}

impl EvalOp for LayerNormCore {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let shape = input.shape().to_vec();
        ensure!(self.axis < shape.len(), "LayerNormCore: axis {} of {:?}", self.axis, shape);
        let (len, inner) = (shape[self.axis], shape[self.axis + 1..].iter().product::<usize>());
        let mut out = input.into_tensor();
        {
            let mut plain = out.try_as_plain_ram_mut()?;
            let data = plain.as_slice_mut::<f32>()?;
            if len * inner > 0 {
                for block in data.chunks_exact_mut(len * inner) {
                    for g in 0..inner.div_ceil(COLS) {
                        self.normalise(block, len, inner, g * COLS);
                    }
                }
            }
        }
        Ok(tvec!(out.into_tvalue()))
    }
}

/// Columns normalised together: their sums stay in registers over the rows.
const COLS: usize = 16;

impl LayerNormCore {
    /// Normalise the columns `c0..c0 + COLS` (fewer at the end) of `block` (`[len][inner]`)
    /// along its first axis, in place.
    fn normalise(&self, block: &mut [f32], len: usize, inner: usize, c0: usize) {
        match inner - c0 {
            // The constant lets the compiler keep the sums in registers.
            cols if cols >= COLS => self.columns(block, len, inner, c0..c0 + COLS),
            cols => self.columns(block, len, inner, c0..c0 + cols),
        }
    }

    /// [`LayerNormCore::normalise`] of the columns `cols` (at most [`COLS`]): each column's sum
    /// over the rows in order, its mean, the sum of squared deviations in order, and
    /// `(x − mean) · scale`.
    #[inline(always)]
    fn columns(&self, block: &mut [f32], len: usize, inner: usize, cols: std::ops::Range<usize>) {
        let recip = 1.0 / len as f32;
        let mut mean = [0f32; COLS];
        for row in block.chunks_exact(inner) {
            mean.iter_mut().zip(&row[cols.clone()]).for_each(|(m, &v)| *m += v);
        }
        mean.iter_mut().for_each(|m| *m *= recip);
        let mut square = [0f32; COLS];
        for row in block.chunks_exact(inner) {
            for ((s, &v), &m) in square.iter_mut().zip(&row[cols.clone()]).zip(&mean) {
                *s += (v - m) * (v - m);
            }
        }
        let scale = square.map(|s| 1.0 / (s / len as f32 + self.eps).sqrt());
        for row in block.chunks_exact_mut(inner) {
            for ((v, &m), &k) in row[cols.clone()].iter_mut().zip(&mean).zip(&scale) {
                *v = (*v - m) * k;
            }
        }
    }
}

impl TypedOp for LayerNormCore {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(inputs[0].without_value()))
    }
    as_op!();
}

/// The [`LayerNormCore`] and its input for an f32 `RmsNorm` node whose input is
/// `x − sum(x, axis) · (1/len)`, the form tract declutters `LayerNormalization` into.
pub(crate) fn layer_norm(model: &TypedModel, node: &TypedNode) -> TractResult<Option<(LayerNormCore, OutletId)>> {
    let Some(rms) = node.op_as::<RmsNorm>() else { return Ok(None) };
    let producer = |o: OutletId| model.node(o.node);
    let bin = |n: &TypedNode, f: fn(&TypedBinOp) -> bool| n.op_as::<TypedBinOp>().is_some_and(f);
    let sub = producer(node.inputs[0]);
    if !bin(sub, |b| b.0.is::<Sub>()) || model.outlet_fact(node.inputs[0])?.datum_type != f32::datum_type() {
        return Ok(None);
    }
    let (x, mean) = (sub.inputs[0], producer(sub.inputs[1]));
    if !bin(mean, |b| b.0.is::<Mul>()) {
        return Ok(None);
    }
    let len = model.outlet_fact(x)?.shape[rms.axis].to_usize()?;
    let mut sum = false;
    let mut recip = false;
    for &i in &mean.inputs {
        let n = producer(i);
        if let Some(r) = n.op_as::<Reduce>() {
            sum |= r.reducer == Reducer::Sum && r.axes.as_slice() == [rms.axis] && n.inputs[0] == x;
        } else if let Some(k) = &model.outlet_fact(i)?.konst {
            recip |= k.len() == 1 && k.cast_to_scalar::<f32>()? == 1.0 / len as f32;
        }
    }
    if !(sum && recip) {
        return Ok(None);
    }
    Ok(Some((LayerNormCore { axis: rms.axis, eps: rms.eps.cast_to_scalar::<f32>()? }, x)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalises_along_a_strided_and_a_last_axis() {
        let (len, inner) = (7, 5);
        let x: Vec<f32> = (0..2 * len * inner).map(|i| ((i * 37 % 23) as f32) * 0.5 - 3.0).collect();
        for axis in [1, 2] {
            let shape = if axis == 1 { [2, len, inner] } else { [2, inner, len] };
            let t = tract_ndarray::Array3::from_shape_vec(shape, x.clone()).unwrap().into_tensor();
            let op = LayerNormCore { axis, eps: 1e-6 };
            let out = op.eval(&EvalContext::out_of_plan(), tvec![t.clone().into_tvalue()]).unwrap();
            let (out, t) = (out[0].to_plain_array_view::<f32>().unwrap(), t.to_plain_array_view::<f32>().unwrap());
            for lane in t.lanes(tract_ndarray::Axis(axis)).into_iter().zip(out.lanes(tract_ndarray::Axis(axis))) {
                let (xs, ys) = lane;
                let m = xs.iter().map(|&v| v as f64).sum::<f64>() / xs.len() as f64;
                let v = xs.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / xs.len() as f64;
                for (&x, &y) in xs.iter().zip(ys) {
                    let want = (x as f64 - m) / (v + 1e-6).sqrt();
                    assert!((y as f64 - want).abs() < 1e-5, "axis {axis}: {y} vs {want}");
                }
            }
        }
    }

    #[test]
    fn column_groups_give_the_row_loops_bits() {
        // HMG's shape: 576 channels normalised, 121 tokens (seven groups of 16 and one of 9).
        let (len, inner) = (576, 121);
        let x: Vec<f32> = (0..len * inner).map(|i| ((i * 7919 % 1009) as f32).sin() * 3.0 + 0.25).collect();
        let op = LayerNormCore { axis: 0, eps: 1e-5 };
        let t = tract_ndarray::Array2::from_shape_vec([len, inner], x.clone()).unwrap().into_tensor();
        let out = op.eval(&EvalContext::out_of_plan(), tvec![t.into_tvalue()]).unwrap();
        let out = out[0].to_plain_array_view::<f32>().unwrap();
        // The plain form: whole rows, one pass each.
        let mut mean = vec![0f32; inner];
        x.chunks(inner).for_each(|row| mean.iter_mut().zip(row).for_each(|(m, &v)| *m += v));
        mean.iter_mut().for_each(|m| *m *= 1.0 / len as f32);
        let mut square = vec![0f32; inner];
        for row in x.chunks(inner) {
            square.iter_mut().zip(row).zip(&mean).for_each(|((s, &v), &m)| *s += (v - m) * (v - m));
        }
        let scale: Vec<f32> = square.iter().map(|&s| 1.0 / (s / len as f32 + 1e-5).sqrt()).collect();
        for (i, (&y, &v)) in out.iter().zip(&x).enumerate() {
            let c = i % inner;
            assert_eq!(y.to_bits(), ((v - mean[c]) * scale[c]).to_bits(), "value {i}");
        }
    }
}
