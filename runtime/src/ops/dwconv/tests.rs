//! [`super::DepthwiseConv`]'s row kernel paths and the operator against the direct sum.

use super::*;

fn direct(s: &ConvShape, input: &[f32], weight: &[f32], bias: &[f32]) -> Vec<f32> {
    super::super::conv::direct(s, s.ci, input, weight, bias)
}

use kernel::Rows;

/// Every row kernel this CPU can run, by name.
fn paths() -> Vec<(&'static str, Rows)> {
    #[allow(unused_mut)]
    let mut v: Vec<(&'static str, Rows)> = vec![("generic", kernel::rows_generic::<false>)];
    #[cfg(target_arch = "aarch64")]
    v.push(("neon", kernel::rows_neon));
    #[cfg(target_arch = "x86_64")]
    {
        if super::super::avx2_fma() {
            // SAFETY (of the call through this pointer): AVX2 and FMA are present.
            v.push(("avx2", |a, b, c, d, e, f, g| unsafe { kernel::rows_avx2(a, b, c, d, e, f, g) }));
        } else {
            eprintln!("NOTE: no AVX2+FMA here (or PRL_ISA caps it): DepthwiseConv's AVX2 path is not tested here");
        }
        if super::super::avx512_fma() {
            // SAFETY (of the call through this pointer): AVX-512F, AVX2 and FMA are present.
            v.push(("avx512", |a, b, c, d, e, f, g| unsafe { kernel::rows_avx512(a, b, c, d, e, f, g) }));
        } else {
            eprintln!("NOTE: no AVX-512 here (or PRL_ISA caps it): DepthwiseConv's AVX-512 path is not tested here");
        }
    }
    v
}

#[test]
fn every_path_equals_the_direct_sum() {
    for s in [
        ConvShape { ci: 3, h: 9, w: 7, co: 3, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
        ConvShape { ci: 4, h: 37, w: 70, co: 4, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
        ConvShape { ci: 5, h: 33, w: 65, co: 5, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 },
        ConvShape { ci: 2, h: 16, w: 16, co: 2, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 2 },
        ConvShape { ci: 3, h: 10, w: 13, co: 3, kh: 4, kw: 3, pad: [0, 1, 2, 0], stride: 2 },
        // 8 columns (an 8-column block), 27 (two 16-column blocks, one part-filled).
        ConvShape { ci: 3, h: 8, w: 8, co: 3, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
        ConvShape { ci: 2, h: 9, w: 27, co: 2, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
        // 16 columns, 13 rows: four at a time, then one.
        ConvShape { ci: 2, h: 13, w: 16, co: 2, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
        // Over SERIAL_MACS: channels in groups (on the pool, when there is one).
        ConvShape { ci: 16, h: 64, w: 64, co: 16, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
    ] {
        let n_in = s.ci * s.h * s.w;
        let input: Vec<f32> = (0..2 * n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        let weight: Vec<f32> = (0..s.ci * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let bias: Vec<f32> = (0..s.ci).map(|o| o as f32 / 4.0).collect();
        let op = DepthwiseConv::new(s.clone(), true, &weight, &bias).unwrap();
        let (oh, ow) = s.out();
        for (name, path) in paths() {
            for n in 0..2 {
                let want = direct(&s, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
                let mut got = vec![0f32; s.ci * oh * ow];
                let mut scratch = op.scratch();
                let taps = s.kh * s.kw;
                for (c, dst) in got.chunks_exact_mut(oh * ow).enumerate() {
                    let src = &input[n * n_in + c * s.h * s.w..][..s.h * s.w];
                    op.channel(c, src, dst, &mut scratch);
                    // The same channel through the path under test.
                    let ws = &weight[c * taps..(c + 1) * taps];
                    path(&scratch, s.phase().1, &op.offsets, ws, bias[c], dst, ow);
                }
                let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-4, "{name} {s:?} image {n}: off by {worst}");
            }
        }
        // And the operator as tract runs it.
        let x = tract_ndarray::Array4::from_shape_vec((2, s.ci, s.h, s.w), input.clone()).unwrap();
        let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
        let out = out[0].try_as_plain_ram().unwrap();
        let out = out.as_slice::<f32>().unwrap();
        for n in 0..2 {
            let want = direct(&s, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
            let got = &out[n * want.len()..(n + 1) * want.len()];
            let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-4, "op {s:?} image {n}: off by {worst}");
        }
    }
}

/// The u8 tests' layers: stride 1 on the calling thread, stride 2, and stride 1 in channel
/// groups (over the pool where there is one).
fn u8_shapes() -> [ConvShape; 3] {
    [
        ConvShape { ci: 3, h: 9, w: 7, co: 3, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
        ConvShape { ci: 5, h: 33, w: 65, co: 5, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 },
        ConvShape { ci: 16, h: 64, w: 64, co: 16, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 },
    ]
}

/// Reading u8 data through a dequantiser (and its activation) gives, bit for bit, the
/// convolution of what the dequantiser writes: stride 1 and 2, one layer on the calling
/// thread and one in channel groups.
#[test]
fn reading_u8_equals_the_convolution_of_the_dequantised_input() {
    let relu6 = Activation { lo: 0.0, hi: 6.0, hard_swish: false };
    let hard_swish = Activation { hard_swish: true, ..Activation::NONE };
    for (s, act) in u8_shapes().into_iter().zip([relu6, hard_swish, hard_swish]) {
        let n_in = s.ci * s.h * s.w;
        let bytes: Vec<u8> = (0..n_in).map(|i| (i * 7919 % 251) as u8).collect();
        let weight: Vec<f32> = (0..s.ci * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let bias: Vec<f32> = (0..s.ci).map(|o| o as f32 / 4.0).collect();
        let dq = DequantizeU8::new(0.0473, 117).with_act(act);
        let mut dequantised = vec![0f32; n_in];
        dq.apply(&bytes, &mut dequantised);
        assert!(dequantised.iter().any(|&v| v > 0.0) && dequantised.iter().any(|&v| v <= 0.0));
        let op = DepthwiseConv::new(s.clone(), true, &weight, &bias).unwrap();
        let reading = op.clone().reading(dq);
        let run = |op: &DepthwiseConv, x: Tensor| {
            let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tvalue()]).unwrap();
            out[0].try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec()
        };
        let dims = (1, s.ci, s.h, s.w);
        let want = run(&op, tract_ndarray::Array4::from_shape_vec(dims, dequantised).unwrap().into_tensor());
        let got = run(&reading, tract_ndarray::Array4::from_shape_vec(dims, bytes).unwrap().into_tensor());
        assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "{s:?}");
    }
}

/// Writing u8 through a quantiser gives, byte for byte, what the quantiser makes of the
/// f32 output (activation included): stride 1 and 2, f32 input and u8 read through a
/// dequantiser, on the calling thread and over a pool of two.
#[test]
fn writing_u8_equals_the_quantised_output() {
    use tract_linalg::multithread::{multithread_tract_scope, Executor};
    let hard_swish = Activation { hard_swish: true, ..Activation::NONE };
    for (s, reads) in u8_shapes().into_iter().zip([false, true, false]) {
        let n_in = s.ci * s.h * s.w;
        let weight: Vec<f32> = (0..s.ci * s.kh * s.kw).map(|i| ((i * 104729 % 997) as f32) / 998.0 - 0.5).collect();
        let bias: Vec<f32> = (0..s.ci).map(|o| o as f32 / 8.0 - 0.3).collect();
        let op = DepthwiseConv { act: hard_swish, ..DepthwiseConv::new(s.clone(), true, &weight, &bias).unwrap() };
        let (op, x) = if reads {
            let bytes: Vec<u8> = (0..n_in).map(|i| (i * 7919 % 251) as u8).collect();
            let op = op.reading(DequantizeU8::new(0.0173, 117));
            (op, tract_ndarray::Array4::from_shape_vec((1, s.ci, s.h, s.w), bytes).unwrap().into_tensor())
        } else {
            let values: Vec<f32> = (0..n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
            (op, tract_ndarray::Array4::from_shape_vec((1, s.ci, s.h, s.w), values).unwrap().into_tensor())
        };
        let q = QuantizeU8::new(1.0 / 0.013, 21);
        let writing = op.clone().writing(q.clone());
        let run = |op: &DepthwiseConv, e: Executor| {
            multithread_tract_scope(e, || op.eval(&EvalContext::out_of_plan(), tvec![x.clone().into_tvalue()]).unwrap())
        };
        let values = run(&op, Executor::SingleThread);
        let values = values[0].try_as_plain_ram().unwrap();
        let values = values.as_slice::<f32>().unwrap();
        let mut want = vec![0u8; values.len()];
        q.apply(values, &mut want);
        let distinct = want.iter().collect::<std::collections::HashSet<_>>().len();
        assert!(distinct > 10 && want.contains(&0), "{s:?}: {distinct} distinct bytes");
        for e in [Executor::SingleThread, Executor::multithread(2)] {
            let got = run(&writing, e);
            assert_eq!(got[0].datum_type(), u8::datum_type());
            let got = got[0].try_as_plain_ram().unwrap();
            // SAFETY: the output is u8.
            let got = unsafe { got.as_slice_unchecked::<u8>() };
            assert!(got == want.as_slice(), "{s:?}: other bytes");
        }
    }
}
