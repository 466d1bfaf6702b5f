//! [`super::WinogradConv`] against the direct convolution, its kernel transform, and the
//! forms' exactness.

use super::*;
use crate::ops::conv::direct;

#[test]
fn equals_the_direct_sum() {
    // Odd and even output sizes (a last tile half outside), one-sided and no padding, a
    // partial channel block; values of both signs, as after a convolution. 3x3 and 5x5.
    for (s, tolerance) in [
        (ConvShape { ci: 32, h: 17, w: 19, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, 2e-6),
        (ConvShape { ci: 48, h: 20, w: 20, co: 36, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, 2e-6),
        (ConvShape { ci: 33, h: 7, w: 60, co: 32, kh: 3, kw: 3, pad: [0, 1, 2, 0], stride: 1 }, 2e-6),
        (ConvShape { ci: 64, h: 18, w: 18, co: 64, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, 2e-6),
        (ConvShape { ci: 32, h: 15, w: 18, co: 44, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 }, 1e-5),
        (ConvShape { ci: 40, h: 21, w: 21, co: 32, kh: 5, kw: 5, pad: [0; 4], stride: 1 }, 1e-5),
        (ConvShape { ci: 32, h: 12, w: 33, co: 32, kh: 5, kw: 5, pad: [1, 0, 0, 2], stride: 1 }, 1e-5),
    ] {
        let r = s.kh;
        let n_in = s.ci * s.h * s.w;
        let input: Vec<f32> = (0..2 * n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        let weight: Vec<f32> = (0..s.co * s.ci * r * r).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let bias: Vec<f32> = (0..s.co).map(|o| o as f32 / 4.0).collect();
        let op = WinogradConv::new(s.clone(), &weight, &bias).unwrap();
        let x = tract_ndarray::Array4::from_shape_vec((2, s.ci, s.h, s.w), input.clone()).unwrap();
        let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
        let out = out[0].try_as_plain_ram().unwrap();
        let out = out.as_slice::<f32>().unwrap();
        let per_image = out.len() / 2;
        for (n, got) in out.chunks_exact(per_image).enumerate() {
            let want = direct(&s, 1, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
            let range = want.iter().fold(0f32, |m, v| m.max(v.abs()));
            let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            // A reordered f32 sum of 300-1000 terms through the transforms: a few units of
            // the last place of the range (more for 5x5's larger coefficients), nowhere
            // near a wrong tap or tile (off by the range itself).
            assert!(worst <= tolerance * range, "{s:?} image {n}: off by {worst} of {range}");
        }
    }
}

#[test]
fn transforms_a_kernel_as_g_g_gt() {
    // A kernel of ones: G·1·Gᵀ is the outer product of G's row sums.
    for f in [&F2_3, &F2_5] {
        let mut u = vec![0f32; f.alpha * f.alpha];
        transform_kernel(f, &vec![1.0; f.r * f.r], &mut u);
        let sums: Vec<f64> = f.g.chunks_exact(f.r).map(|row| row.iter().sum()).collect();
        for a in 0..f.alpha {
            for b in 0..f.alpha {
                assert_eq!(u[a * f.alpha + b], (sums[a] * sums[b]) as f32, "{f:?} ({a}, {b})");
            }
        }
    }
}

#[test]
fn forms_interpolate_exactly() {
    // Aᵀ[(Gg) ⊙ (Bᵀd)] is the 1-D correlation of d with g, for every unit d and g (in f64:
    // the matrices themselves, not their rounding).
    for f in [&F2_3, &F2_5] {
        let (r, al) = (f.r, f.alpha);
        for gi in 0..r {
            for di in 0..al {
                let gg: Vec<f64> = (0..al).map(|a| f.g[a * r + gi]).collect();
                let bd: Vec<f64> = (0..al).map(|a| f.bt[a * al + di] as f64).collect();
                for l in 0..2 {
                    let got: f64 = (0..al).map(|a| f.at[l * al + a] as f64 * gg[a] * bd[a]).sum();
                    // y[l] = Σ_k d[l + k]·g[k]: 1 where di = l + gi.
                    let want = if di == l + gi { 1.0 } else { 0.0 };
                    assert!((got - want).abs() < 1e-12, "{f:?}: g {gi}, d {di}, y {l}: {got}");
                }
            }
        }
    }
}
