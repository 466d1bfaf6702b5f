//! The builder's non-trivial ops, run with tract on small hand-computed cases.

use prl_compiler::net::{hierarchical_attention, lip2d, nearest_indices, upsample_nearest, TensorSpec};
use prl_compiler::onnx::Graph;
use prl_compiler::{OnnxRunner, Tensor};

/// Build a one-input graph with `f`, run it on `x`, return its output.
fn run(
    shape: &'static [usize],
    out_shape: &[usize],
    x: Vec<f32>,
    f: impl FnOnce(&mut Graph, &prl_compiler::onnx::Value) -> prl_compiler::onnx::Value,
) -> Tensor {
    let mut g = Graph::new("test");
    let input = g.input("x", shape).unwrap();
    let y = f(&mut g, &input);
    g.output(&y, out_shape).unwrap();
    let spec = TensorSpec { name: "x", shape };
    let r = OnnxRunner::new(&g.encode("test"), "test graph", &[spec], None).unwrap();
    let out = r.run(&[&Tensor::new(shape.to_vec(), x)]).unwrap().remove(0);
    assert_eq!(out.shape, out_shape);
    out
}

fn close(a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= 1e-5 * y.abs().max(1.0), "{a:?} vs {b:?}");
    }
}

#[test]
fn lip_pooling_by_hand() {
    // x[0,0] = ln 2 (so exp = 2), x[1,1] = 1, zeros elsewhere; 3x3 window, stride 2, pad 1,
    // padding counted in both averages (the 1/9 cancels). Output (0,0) sees cells
    // (0,0),(0,1),(1,0),(1,1): (2·ln2 + 1·e) / (2 + 1 + 1 + e).
    let (a, b) = (2f32.ln(), 1f32);
    let x = vec![a, 0., 0., 0., b, 0., 0., 0., 0.];
    let out = run(&[1, 1, 3, 3], &[1, 1, 2, 2], x, |g, x| lip2d(g, "lip", x).unwrap());
    let e = b.exp();
    // Each other output sees x[1,1] and three zeros: (1·e) / (3 + e).
    let side = (b * e) / (3.0 + e);
    close(&out.data, &[(2.0 * a + b * e) / (4.0 + e), side, side, side]);
}

#[test]
fn nearest_indices_follow_pytorch() {
    assert_eq!(nearest_indices(2, 3), [0, 0, 1]);
    assert_eq!(nearest_indices(2, 4), [0, 0, 1, 1]);
    let exact: Vec<i64> = (0..21).map(|d| d * 11 / 21).collect();
    assert_eq!(nearest_indices(11, 21), exact);
}

#[test]
fn nearest_upsampling_by_hand() {
    let out =
        run(&[1, 1, 2, 2], &[1, 1, 3, 3], vec![1., 2., 3., 4.], |g, x| upsample_nearest(g, "up", x, 2, 3).unwrap());
    assert_eq!(out.data, [1., 1., 2., 1., 1., 2., 3., 3., 4.]);
}

/// One token, one head, parts of width 1: qkv = [q3 q4 q5 k3 k4 k5 v3 v4 v5].
#[test]
fn hierarchical_attention_by_hand() {
    let qkv = vec![0., 2., 0., 0., 1., 0., 1., 2., 3.];
    let out = run(&[1, 1, 9], &[1, 1, 3], qkv, |g, x| hierarchical_attention(g, "attn", x, 1, 1, 1).unwrap());
    let s = 3f32.powf(-0.5);
    // x3: q4=2 against [k3=0, k4=1] -> weights ∝ [1, e^{2s}] on [v3=1, v4=2].
    let e = (2.0 * s).exp();
    // x4, x5: q5=0 -> uniform: (v3+v5)/2, (v4+v5)/2.
    close(&out.data, &[(1.0 + 2.0 * e) / (1.0 + e), 2.0, 2.5]);
}

/// Two tokens, q = 0: every query attends uniformly over the two concatenated key sets.
#[test]
fn hierarchical_attention_concatenates_keys_over_tokens() {
    let mut qkv = vec![0f32; 18];
    qkv[6..9].copy_from_slice(&[1., 2., 3.]);
    qkv[15..18].copy_from_slice(&[5., 6., 7.]);
    let out = run(&[1, 2, 9], &[1, 2, 3], qkv, |g, x| hierarchical_attention(g, "attn", x, 2, 1, 1).unwrap());
    close(&out.data, &[3.5, 4.0, 4.5, 3.5, 4.0, 4.5]);
}

/// Several heads and tokens against a direct transcription of the official `Attention.forward`.
#[test]
fn hierarchical_attention_matches_a_direct_implementation() {
    let (n, h, p) = (3usize, 2usize, 2usize);
    let d = 3 * p; // head dim
    let c = h * d; // width
    let qkv: Vec<f32> = (0..n * 3 * c).map(|i| ((i * 37 % 23) as f32 - 11.0) / 7.0).collect();
    // qkv[t, which, head, part, j]
    let at = |t: usize, which: usize, head: usize, part: usize, j: usize| {
        qkv[t * 3 * c + which * c + head * d + part * p + j]
    };
    let mut expected = vec![0f32; n * 3 * h * p];
    for (o, (qp, k1, k2)) in [(1, 0, 1), (2, 0, 2), (2, 1, 2)].into_iter().enumerate() {
        for head in 0..h {
            for t in 0..n {
                let keys: Vec<(usize, usize)> = [k1, k2].iter().flat_map(|&k| (0..n).map(move |u| (k, u))).collect();
                let scores: Vec<f32> = keys
                    .iter()
                    .map(|&(k, u)| {
                        (0..p).map(|j| at(t, 0, head, qp, j) * at(u, 1, head, k, j)).sum::<f32>()
                            * (d as f32).powf(-0.5)
                    })
                    .collect();
                let m = scores.iter().cloned().fold(f32::MIN, f32::max);
                let z: f32 = scores.iter().map(|s| (s - m).exp()).sum();
                for j in 0..p {
                    let v: f32 =
                        keys.iter().zip(&scores).map(|(&(k, u), s)| (s - m).exp() / z * at(u, 2, head, k, j)).sum();
                    expected[t * 3 * h * p + o * h * p + head * p + j] = v;
                }
            }
        }
    }
    let shape: &'static [usize] = Box::leak(vec![1, n, 3 * c].into_boxed_slice());
    let out =
        run(shape, &[1, n, 3 * h * p], qkv.clone(), |g, x| hierarchical_attention(g, "attn", x, n, h, p).unwrap());
    close(&out.data, &expected);
}

#[test]
fn builder_errors_name_the_node() {
    let mut g = Graph::new("g");
    let x = g.input("x", &[1]).unwrap();
    g.relu("r", &x).unwrap();
    let err = g.relu("r", &x).unwrap_err().to_string();
    assert!(err.contains("graph `g`, node `r`"), "{err}");
    let mut other = Graph::new("h");
    let y = other.input("y", &[1]).unwrap();
    let err = g.add("sum", &x, &y).unwrap_err().to_string();
    assert!(err.contains("node `sum`") && err.contains("unknown value `y`"), "{err}");
}

/// The correlation with the template as kernel (run by `prl_runtime::DepthwiseXCorr`) equals
/// tract's own depthwise convolution with the same kernel as a constant, and a sum by hand; the
/// 75-wide input gives two strips of output columns (64 + 9).
#[test]
fn depthwise_correlation_equals_tract_convolution() {
    use prl_compiler::onnx::ConvOpts;
    let (c, k, h, w) = (3usize, 3usize, 6usize, 75usize);
    let xv: Vec<f32> = (0..c * h * w).map(|i| ((i * 13 % 17) as f32 - 8.0) / 3.0).collect();
    let zv: Vec<f32> = (0..c * k * k).map(|i| ((i * 7 % 11) as f32 - 5.0) / 2.0).collect();
    let mut g = Graph::new("xcorr");
    let x = g.input("x", &[1, c, h, w]).unwrap();
    let z = g.input("z", &[1, c, k, k]).unwrap();
    let ours = g.depthwise_xcorr("ours", &x, &z, c, k).unwrap();
    let kernel = g.constant("kernel", &Tensor::new(vec![c, 1, k, k], zv.clone())).unwrap();
    let tract = g.conv("tract", &x, &kernel, None, ConvOpts { group: c, ..Default::default() }).unwrap();
    let out = [1, c, h - k + 1, w - k + 1];
    g.output(&ours, &out).unwrap();
    g.output(&tract, &out).unwrap();
    let xs: &'static [usize] = &[1, 3, 6, 75];
    let zs: &'static [usize] = &[1, 3, 3, 3];
    let specs = [TensorSpec { name: "x", shape: xs }, TensorSpec { name: "z", shape: zs }];
    let r = OnnxRunner::new(&g.encode("xcorr"), "xcorr", &specs, None).unwrap();
    let outs = r.run(&[&Tensor::new(xs.to_vec(), xv.clone()), &Tensor::new(zs.to_vec(), zv.clone())]).unwrap();
    // By hand for one cell: channel 1, output (2, 70) (in the second strip).
    let by_hand: f32 = (0..k)
        .flat_map(|u| (0..k).map(move |v| (u, v)))
        .map(|(u, v)| xv[(h + 2 + u) * w + 70 + v] * zv[k * k + u * k + v])
        .sum();
    let at = (h - k + 1) * (w - k + 1) + 2 * (w - k + 1) + 70;
    close(&[outs[0].data[at]], &[by_hand]);
    close(&outs[0].data, &outs[1].data);
}
