//! Building blocks shared by the modules: convolutions with BatchNorm folded in, linear layers,
//! squeeze-and-excitation.

use crate::onnx::{ConvOpts, Graph, Value};
use crate::weights::{Init, Scope};
use crate::{Result, Tensor};

/// BatchNorm epsilon (PyTorch's default).
const BN_EPS: f64 = 1e-5;

/// A convolution as the checkpoint stores it: `conv` names its scope (`weight`, maybe `bias`).
pub(crate) struct ConvSpec<'a> {
    pub conv: Scope<'a>,
    pub cin: usize,
    pub cout: usize,
    pub k: usize,
    pub opts: ConvOpts,
    pub bias: bool,
    /// Gain of the random initialisation (ignored with a checkpoint).
    pub gain: f32,
}

impl ConvSpec<'_> {
    fn weight(&self) -> Result<Tensor> {
        let fan_in = self.cin / self.opts.group * self.k * self.k;
        let shape = [self.cout, self.cin / self.opts.group, self.k, self.k];
        self.conv.get("weight", &shape, Init::Fan { fan_in, gain: self.gain })
    }

    fn bias(&self, mean: f32) -> Result<Option<Tensor>> {
        self.bias.then(|| self.conv.get("bias", &[self.cout], Init::Normal { mean, std: 0.01 })).transpose()
    }
}

/// `conv(x)` with its own weights.
pub(crate) fn conv(g: &mut Graph, name: &str, x: &Value, spec: &ConvSpec) -> Result<Value> {
    conv_with_bias_init(g, name, x, spec, 0.0)
}

/// `conv(x)` whose random bias centres on `bias_mean`.
pub(crate) fn conv_with_bias_init(
    g: &mut Graph,
    name: &str,
    x: &Value,
    spec: &ConvSpec,
    bias_mean: f32,
) -> Result<Value> {
    let (w, b) = conv_weights(g, spec, bias_mean)?;
    g.conv(name, x, &w, b.as_ref(), spec.opts)
}

/// The convolution's weight and bias as initializers, for a convolution applied more than once.
pub(crate) fn conv_weights(g: &mut Graph, spec: &ConvSpec, bias_mean: f32) -> Result<(Value, Option<Value>)> {
    let w = g.constant(&spec.conv.key("weight"), &spec.weight()?)?;
    let b = match spec.bias(bias_mean)? {
        Some(b) => Some(g.constant(&spec.conv.key("bias"), &b)?),
        None => None,
    };
    Ok((w, b))
}

/// `bn(conv(x))` with the BatchNorm (scope `bn`) folded into the convolution's weights, in f64.
/// `act_scale` is the rough size of the convolution's output, used only by random weights to
/// give the BatchNorm statistics that keep activations in range.
pub(crate) fn conv_bn(
    g: &mut Graph,
    name: &str,
    x: &Value,
    spec: &ConvSpec,
    bn: &Scope,
    act_scale: f32,
) -> Result<Value> {
    let (w, b) = folded_conv_bn(g, spec, bn, act_scale)?;
    g.conv(name, x, &w, Some(&b), spec.opts)
}

/// The convolution's weights and bias with the BatchNorm folded in (f64 arithmetic), as
/// initializers named `<conv key>+<bn prefix>`.
fn folded_conv_bn(g: &mut Graph, spec: &ConvSpec, bn: &Scope, act_scale: f32) -> Result<(Value, Value)> {
    let c = spec.cout;
    let gamma = bn.get("weight", &[c], Init::Uniform { lo: 0.8, hi: 1.2 })?;
    let beta = bn.get("bias", &[c], Init::Normal { mean: 0.0, std: 0.1 })?;
    let mean = bn.get("running_mean", &[c], Init::Normal { mean: 0.0, std: 0.1 * act_scale })?;
    let s2 = act_scale * act_scale;
    let var = bn.get("running_var", &[c], Init::Uniform { lo: 0.8 * s2, hi: 1.2 * s2 })?;
    let mut w = spec.weight()?;
    let b = spec.bias(0.0)?;
    let per_out = w.len() / c;
    let mut bias = vec![0f32; c];
    for (o, bias) in bias.iter_mut().enumerate() {
        let inv = gamma.data[o] as f64 / (var.data[o] as f64 + BN_EPS).sqrt();
        for v in &mut w.data[o * per_out..(o + 1) * per_out] {
            *v = (*v as f64 * inv) as f32;
        }
        let b0 = b.as_ref().map_or(0.0, |b| b.data[o] as f64);
        *bias = ((b0 - mean.data[o] as f64) * inv + beta.data[o] as f64) as f32;
    }
    let folded = format!("+{}", bn.key("").trim_end_matches('.'));
    let w = g.constant(&(spec.conv.key("weight") + &folded), &w)?;
    let b = g.constant(&(spec.conv.key("bias") + &folded), &Tensor::new([c], bias))?;
    Ok((w, b))
}

/// A PyTorch `nn.Linear` (`weight` [out, in], optional `bias`) on the last axis of `x`, from
/// `cin` to `cout` features.
pub(crate) fn linear(
    g: &mut Graph,
    name: &str,
    x: &Value,
    w: &Scope,
    [cin, cout]: [usize; 2],
    bias: bool,
    gain: f32,
) -> Result<Value> {
    let wt = g.constant(&w.key("weight"), &w.get("weight", &[cout, cin], Init::Fan { fan_in: cin, gain })?)?;
    let b = if bias {
        Some(g.constant(&w.key("bias"), &w.get("bias", &[cout], Init::Normal { mean: 0.0, std: 0.02 })?)?)
    } else {
        None
    };
    g.linear(name, x, &wt, b.as_ref())
}

/// Squeeze-and-excitation (`SELayer`, reduction 16, no biases): `x * sigmoid(fc2(relu(fc1(avg(x)))))`.
pub(crate) fn squeeze_excite(g: &mut Graph, name: &str, x: &Value, se: &Scope, c: usize) -> Result<Value> {
    let fc = se.pp("fc");
    let r = c / 16;
    let y = g.global_avg_pool(&format!("{name}.se.pool"), x)?;
    let y = g.reshape(&format!("{name}.se.flat"), &y, &[1, c as i64])?;
    let y = linear(g, &format!("{name}.se.fc1"), &y, &fc.pp(0), [c, r], false, 1.0)?;
    let y = g.relu(&format!("{name}.se.relu"), &y)?;
    let y = linear(g, &format!("{name}.se.fc2"), &y, &fc.pp(2), [r, c], false, 1.0)?;
    let y = g.sigmoid(&format!("{name}.se.sigmoid"), &y)?;
    let y = g.reshape(&format!("{name}.se.gate"), &y, &[1, c as i64, 1, 1])?;
    g.mul(name, x, &y)
}
