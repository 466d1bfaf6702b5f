//! Depthwise cross-correlation in the form tract runs fastest for large kernels: the template
//! side becomes a Toeplitz matrix once per target (template graph), the search side a gather of
//! overlapping row windows, and the correlation one batched matrix product per frame.
//!
//! For channel `c`, `out[c,i,j] = Σ_{u,v} x[c,i+u,j+v]·z[c,u,v]`. With
//! `R[c,i,(u,col)] = x[c,i+u,col]` and `T[c,(u,col),j] = z[c,u,col-j]` (0 outside the kernel),
//! `out[c] = R[c]·T[c]`. `T` is a gather of `z`'s values: exact.

use crate::onnx::{Graph, Value};
use crate::{Result, Tensor};

/// `T` [C, k·w, w−k+1] of a template feature `z` [1,C,k,k] for search features of width `w`: a
/// gather of `z`'s values (a zero appended to each channel fills the places outside the kernel).
pub fn toeplitz_kernel(g: &mut Graph, name: &str, z: &Value, c: usize, k: usize, w: usize) -> Result<Value> {
    let out = w - k + 1;
    let zero = (k * k) as i64; // index of the zero appended to each channel
    let at = |u: usize, col: usize, j: usize| if col >= j && col - j < k { (u * k + col - j) as i64 } else { zero };
    let idx: Vec<i64> = (0..k).flat_map(|u| (0..w).flat_map(move |col| (0..out).map(move |j| at(u, col, j)))).collect();
    let flat = g.reshape(&format!("{name}.flat"), z, &[c as i64, (k * k) as i64])?;
    let zeros = g.constant(&format!("{name}.zeros"), &Tensor::full([c, 1], 0.0))?;
    let padded = g.concat(&format!("{name}.padded"), &[&flat, &zeros], 1)?;
    g.gather_nd_indices(name, &padded, 1, &[k * w, out], &idx)
}

/// The correlation of `x` [1,C,h,w] with a kernel given as [`toeplitz_kernel`]'s `T`:
/// [1, C, h−k+1, w−k+1], named `name`.
pub fn toeplitz_xcorr(
    g: &mut Graph,
    name: &str,
    x: &Value,
    t: &Value,
    c: usize,
    k: usize,
    h: usize,
    w: usize,
) -> Result<Value> {
    let (oh, ow) = (h - k + 1, w - k + 1);
    let idx: Vec<i64> = (0..oh).flat_map(|i| (0..k).map(move |u| (i + u) as i64)).collect();
    let x = g.reshape(&format!("{name}.planes"), x, &[c as i64, h as i64, w as i64])?;
    let r = g.gather(&format!("{name}.windows"), &x, 1, &idx)?;
    let r = g.reshape(&format!("{name}.rows"), &r, &[c as i64, oh as i64, (k * w) as i64])?;
    let o = g.matmul(&format!("{name}.matmul"), &r, t)?;
    g.reshape(name, &o, &[1, c as i64, oh as i64, ow as i64])
}
