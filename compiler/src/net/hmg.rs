//! The hierarchical modelling generator (HMG, `grader.vit`): a shared patch embedding of AR, SR1
//! and SR2, fixed sin-cos position embeddings, and two transformer blocks of width 576 whose
//! attention is the hierarchical cross-attention.

use super::layers::{conv_weights, linear, ConvSpec};
use crate::onnx::{ConvOpts, Graph, Value};
use crate::weights::{Init, Scope};
use crate::{Result, Tensor};

const GRID: usize = 11;
const TOKENS: usize = GRID * GRID;
const EMBED: usize = 192;
const WIDTH: usize = 3 * EMBED;
const HEADS: usize = 12;
const MLP: usize = 768;
const DEPTH: usize = 2;

/// The 2-D sin-cos position embedding [grid², dim] of the official code (MAE style): the first
/// half of the channels encodes the column, the second half the row; each half is
/// `[sin(p·ω), cos(p·ω)]` with `ω_i = 1 / 10000^(i / (dim/4))`.
pub fn sincos_pos_embed(dim: usize, grid: usize) -> Tensor {
    let quarter = dim / 4;
    let mut data = Vec::with_capacity(grid * grid * dim);
    for row in 0..grid {
        for col in 0..grid {
            for pos in [col, row] {
                let omega = |i: usize| 1.0 / 10000f64.powf(i as f64 / quarter as f64);
                data.extend((0..quarter).map(|i| (pos as f64 * omega(i)).sin() as f32));
                data.extend((0..quarter).map(|i| (pos as f64 * omega(i)).cos() as f32));
            }
        }
    }
    Tensor::new([1, grid * grid, dim], data)
}

/// The hierarchical cross-attention on `x` [1, N, 3·p·heads] after `qkv`: q, k, v are split in
/// thirds per head (q3, q4, q5 ...), and the output concatenates
/// `softmax(q4·[k3;k4]ᵀ·s)·[v3;v4]`, `softmax(q5·[k3;k5]ᵀ·s)·[v3;v5]`, `softmax(q5·[k4;k5]ᵀ·s)·[v4;v5]`
/// (each head-major), with `s = (3p)^-1/2`. `qkv` is [1, N, 3·3·p·heads].
pub fn hierarchical_attention(
    g: &mut Graph,
    name: &str,
    qkv: &Value,
    tokens: usize,
    heads: usize,
    part: usize,
) -> Result<Value> {
    let (n, h, p) = (tokens as i64, heads as i64, part as i64);
    let head_dim = 3 * part;
    // [N, 3(qkv), H, 3(part), p] -> [3(qkv), 3(part), H, N, p] -> [9, H, N, p]: q3 q4 q5 k3 k4 k5 v3 v4 v5.
    let x = g.reshape(&format!("{name}.split"), qkv, &[n, 3, h, 3, p])?;
    let x = g.transpose(&format!("{name}.heads"), &x, &[1, 3, 2, 0, 4])?;
    let x = g.reshape(&format!("{name}.pieces"), &x, &[9, h, n, p])?;
    let scale = g.constant(&format!("{name}.scale"), &Tensor::full([1], (head_dim as f32).powf(-0.5)))?;
    let mut outs = Vec::new();
    for (i, (q, k1, k2)) in [(1, 0, 1), (2, 0, 2), (2, 1, 2)].into_iter().enumerate() {
        let b = format!("{name}.x{}", i + 3);
        let q = g.gather(&format!("{b}.q"), &x, 0, &[q])?;
        let q = g.reshape(&format!("{b}.q.heads"), &q, &[h, n, p])?;
        // keys: [2, H, N, p] -> [H, p, 2, N] -> [H, p, 2N] (keys concatenated along tokens, transposed)
        let k = g.gather(&format!("{b}.k"), &x, 0, &[3 + k1, 3 + k2])?;
        let k = g.transpose(&format!("{b}.k.t"), &k, &[1, 3, 0, 2])?;
        let k = g.reshape(&format!("{b}.k.cat"), &k, &[h, p, 2 * n])?;
        // values: [2, H, N, p] -> [H, 2, N, p] -> [H, 2N, p]
        let v = g.gather(&format!("{b}.v"), &x, 0, &[6 + k1, 6 + k2])?;
        let v = g.transpose(&format!("{b}.v.t"), &v, &[1, 0, 2, 3])?;
        let v = g.reshape(&format!("{b}.v.cat"), &v, &[h, 2 * n, p])?;
        let a = g.matmul(&format!("{b}.scores"), &q, &k)?;
        let a = g.mul(&format!("{b}.scaled"), &a, &scale)?;
        let a = g.softmax(&format!("{b}.softmax"), &a, -1)?;
        let o = g.matmul(&format!("{b}.mix"), &a, &v)?;
        let o = g.transpose(&format!("{b}.tokens"), &o, &[1, 0, 2])?;
        outs.push(g.reshape(&b, &o, &[1, n, h * p])?);
    }
    g.concat(name, &outs.iter().collect::<Vec<_>>(), 2)
}

/// HMG on the three regulator outputs; returns [1,192,11,11] named `name`.
pub(crate) fn hmg(g: &mut Graph, w: &Scope, name: &str, feats: [&Value; 3]) -> Result<Value> {
    let n = |s: &str| format!("{name}.{s}");
    let proj = ConvSpec {
        conv: w.pp("patch_embed").pp("proj"),
        cin: EMBED,
        cout: EMBED,
        k: 1,
        opts: ConvOpts::default(),
        bias: true,
        gain: 1.0,
    };
    let (pw, pb) = conv_weights(g, &proj, 0.0)?;
    let mut tokens = Vec::new();
    for (i, f) in feats.into_iter().enumerate() {
        let t = g.conv(&n(&format!("patch_embed{}", i + 1)), f, &pw, pb.as_ref(), proj.opts)?;
        let t = g.reshape(&n(&format!("patch_embed{}.flat", i + 1)), &t, &[1, EMBED as i64, TOKENS as i64])?;
        let t = g.transpose(&n(&format!("patch_embed{}.tokens", i + 1)), &t, &[0, 2, 1])?;
        let key = format!("pos_embed{}", i + 1);
        let pe = w.get(&key, &[1, TOKENS, EMBED], Init::Fixed(sincos_pos_embed(EMBED, GRID)))?;
        let pe = g.constant(&w.key(&key), &pe)?;
        tokens.push(g.add(&n(&format!("embed{}", i + 1)), &t, &pe)?);
    }
    let mut x = g.concat(&n("tokens"), &tokens.iter().collect::<Vec<_>>(), 2)?;
    for b in 0..DEPTH {
        let bw = w.pp("blocks").pp(b);
        let bn = |s: &str| n(&format!("blocks.{b}.{s}"));
        let h = layer_norm(g, &bn("norm1"), &x, &bw.pp("norm1"))?;
        let qkv = linear(g, &bn("attn.qkv"), &h, &bw.pp("attn").pp("qkv"), [WIDTH, 3 * WIDTH], true, 1.0)?;
        let a = hierarchical_attention(g, &bn("attn.cross"), &qkv, TOKENS, HEADS, WIDTH / HEADS / 3)?;
        let a = linear(g, &bn("attn.proj"), &a, &bw.pp("attn").pp("proj"), [WIDTH, WIDTH], true, 0.5)?;
        x = g.add(&bn("attn.residual"), &x, &a)?;
        let h = layer_norm(g, &bn("norm2"), &x, &bw.pp("norm2"))?;
        let h = linear(g, &bn("mlp.fc1"), &h, &bw.pp("mlp").pp("fc1"), [WIDTH, MLP], true, 1.0)?;
        let h = g.gelu(&bn("mlp.gelu"), &h)?;
        let h = linear(g, &bn("mlp.fc2"), &h, &bw.pp("mlp").pp("fc2"), [MLP, WIDTH], true, 0.5)?;
        x = g.add(&bn("mlp.residual"), &x, &h)?;
    }
    // Keep the x5 third, back to NCHW.
    let x5 = g.slice(&n("x5"), &x, 2, 2 * EMBED as i64, WIDTH as i64)?;
    let x5 = g.transpose(&n("x5.channels"), &x5, &[0, 2, 1])?;
    g.reshape(name, &x5, &[1, EMBED as i64, GRID as i64, GRID as i64])
}

fn layer_norm(g: &mut Graph, name: &str, x: &Value, w: &Scope) -> Result<Value> {
    let s = g.constant(&w.key("weight"), &w.get("weight", &[WIDTH], Init::Uniform { lo: 0.9, hi: 1.1 })?)?;
    let b = g.constant(&w.key("bias"), &w.get("bias", &[WIDTH], Init::Normal { mean: 0.0, std: 0.02 })?)?;
    g.layer_norm(name, x, &s, &b, 1e-6)
}
