//! The appearance-aware regulator (AR, `grader.ar`) and the semantic-aware regulators
//! (SR, `grader.sr1`, `grader.sr2`), with LIP pooling and nearest upsampling.

use super::layers::{conv, conv_bn, squeeze_excite, ConvSpec};
use crate::onnx::{ConvOpts, Graph, Value};
use crate::weights::Scope;
use crate::{Result, Tensor};

/// Width of the regulators' outputs.
pub const WIDTH: usize = 192;

/// LIP pooling with the input as its own logit:
/// `avgpool3s2p1(x * exp(x)) / (avgpool3s2p1(exp(x)) + 1e-8)`, padding counted in the average.
pub fn lip2d(g: &mut Graph, name: &str, x: &Value) -> Result<Value> {
    let e = g.exp(&format!("{name}.exp"), x)?;
    let xe = g.mul(&format!("{name}.weighted"), x, &e)?;
    let num = g.avg_pool(&format!("{name}.num"), &xe, 3, 2, 1)?;
    let den = g.avg_pool(&format!("{name}.den"), &e, 3, 2, 1)?;
    let eps = g.constant(&format!("{name}.eps"), &Tensor::full([1], 1e-8))?;
    let den = g.add(&format!("{name}.den_eps"), &den, &eps)?;
    g.div(name, &num, &den)
}

/// Source index of each destination index for PyTorch's `F.interpolate(mode="nearest")`:
/// `min(floor(dst * (src / dst_size)), src - 1)`, the scale computed in f32 as PyTorch does.
pub fn nearest_indices(src: usize, dst: usize) -> Vec<i64> {
    let scale = src as f32 / dst as f32;
    (0..dst).map(|d| ((d as f32 * scale).floor() as i64).min(src as i64 - 1)).collect()
}

/// Nearest upsampling of an NCHW value from `src`x`src` to `dst`x`dst` (two constant gathers).
pub fn upsample_nearest(g: &mut Graph, name: &str, x: &Value, src: usize, dst: usize) -> Result<Value> {
    let idx = nearest_indices(src, dst);
    let rows = g.gather(&format!("{name}.rows"), x, 2, &idx)?;
    g.gather(name, &rows, 3, &idx)
}

/// AR on `s3`, gated by `s1` (through LIP) and `s2`: [1,192,11,11], named `name`.
pub(crate) fn appearance_regulator(
    g: &mut Graph,
    w: &Scope,
    name: &str,
    s3: &Value,
    s1: &Value,
    s2: &Value,
) -> Result<Value> {
    let n = |s: &str| format!("{name}.{s}");
    let one = |conv, cin| ConvSpec { conv, cin, cout: 1, k: 1, opts: ConvOpts::default(), bias: true, gain: 1.0 };
    let g1 = conv_bn(g, &n("conv1"), s1, &one(w.pp("conv1"), 96), &w.pp("bn"), 200.0)?;
    let g1 = lip2d(g, &n("lip"), &g1)?;
    let g2 = conv(g, &n("conv2"), s2, &one(w.pp("conv2"), 256))?;
    let cat = g.concat(&n("concat"), &[&g1, &g2], 1)?;
    let g12 = conv(g, &n("conv_concat"), &cat, &one(w.pp("conv_concat"), 2))?;
    let g12 = g.relu(&n("relu"), &g12)?;
    let gating = g.mul(&n("gating"), s3, &g12)?;
    let x = g.add(&n("gated"), s3, &gating)?;
    let spec = ConvSpec {
        conv: w.pp("conv").pp(0),
        cin: 384,
        cout: WIDTH,
        k: 3,
        opts: ConvOpts::stride_pad(2, 1),
        bias: false,
        gain: 1.0,
    };
    let x = conv_bn(g, &n("conv"), &x, &spec, &w.pp("conv").pp(1), 1000.0)?;
    let x = g.relu(&n("conv.relu"), &x)?;
    squeeze_excite(g, name, &x, &w.pp("se"), WIDTH)
}

/// SR on `x` ([1,cin,21,21]) guided by `t` ([1,192,11,11]): [1,192,11,11], named `name`.
pub(crate) fn semantic_regulator(
    g: &mut Graph,
    w: &Scope,
    name: &str,
    x: &Value,
    cin: usize,
    t: &Value,
    act_scale: f32,
) -> Result<Value> {
    let n = |s: &str| format!("{name}.{s}");
    // The official code upsamples `t` (192 channels) to 21x21, then applies the 1x1 `conv1`
    // (192 -> 1). A 1x1 convolution commutes with nearest upsampling (each output is the same
    // sum over the same input pixel's channels), so the convolution runs first on the 11x11
    // map and only its one channel is upsampled: the same values, 3.6x fewer multiply-adds and
    // 1/192 of the gathers (192-channel gathers ran on one thread, 0.15 ms of a step).
    let spec =
        ConvSpec { conv: w.pp("conv1"), cin: WIDTH, cout: 1, k: 1, opts: ConvOpts::default(), bias: true, gain: 1.0 };
    let t = conv(g, &n("conv1"), t, &spec)?;
    let t = upsample_nearest(g, &n("upsample"), &t, 11, 21)?;
    let special = g.mul(&n("special"), x, &t)?;
    let x = g.add(&n("gated"), x, &special)?;
    let spec = ConvSpec {
        conv: w.pp("conv2").pp(0),
        cin,
        cout: WIDTH,
        k: 3,
        opts: ConvOpts::stride_pad(2, 1),
        bias: false,
        gain: 1.0,
    };
    let x = conv_bn(g, &n("conv2"), &x, &spec, &w.pp("conv2").pp(1), act_scale)?;
    let x = g.relu(&n("conv2.relu"), &x)?;
    squeeze_excite(g, name, &x, &w.pp("se"), WIDTH)
}
