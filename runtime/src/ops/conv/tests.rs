//! [`super::PackedConv`] against the direct sum, and the padding's row helpers.

use super::shape::deinterleave;
use super::*;

#[test]
fn deinterleaves_rows_of_every_length() {
    // Whole blocks of 32 (AVX-512 where the CPU has it), the pairs after them, an odd end.
    for len in 0..100usize {
        let row: Vec<f32> = (0..len).map(|i| i as f32).collect();
        let (mut even, mut odd) = (vec![-1.0; len.div_ceil(2)], vec![-1.0; len / 2]);
        deinterleave(&row, &mut even, &mut odd);
        assert!(even.iter().enumerate().all(|(i, &v)| v == (2 * i) as f32), "even, {len}");
        assert!(odd.iter().enumerate().all(|(i, &v)| v == (2 * i + 1) as f32), "odd, {len}");
    }
}

#[test]
fn pads_a_plane_for_stride_1() {
    // Every row length from 1 to 99 (whole steps of 16 or 8, and the rests: masked on
    // AVX-512, a step ending at the row's end or value by value on AVX2); the padding
    // stays untouched.
    for w in 1..100usize {
        for (h, pad) in [(5, [1, 1, 1, 1]), (3, [0, 2, 1, 0]), (4, [2, 0, 0, 3])] {
            let s = ConvShape { ci: 1, h, w, co: 1, kh: 3, kw: 3, pad, stride: 1 };
            let (hq, wq) = s.phase();
            let src: Vec<f32> = (0..h * w).map(|i| i as f32).collect();
            let mut got = vec![-1.0f32; hq * wq + 8];
            s.pad_plane(&src, &mut got);
            let mut want = vec![-1.0f32; got.len()];
            for y in 0..h {
                for x in 0..w {
                    want[(y + pad[0]) * wq + x + pad[1]] = src[y * w + x];
                }
            }
            assert_eq!(got, want, "w {w}, h {h}, pad {pad:?}");
        }
    }
}

#[test]
fn pads_a_plane_for_stride_2_as_its_phases() {
    // Every row length from 1 to 99 (whole blocks of 32 on AVX-512 and masked rests), both
    // column paddings' parities, odd and even row counts; the padding stays untouched.
    for w in 1..100usize {
        for (h, pad) in [(5, [1, 1, 1, 1]), (4, [2, 2, 2, 2]), (3, [0, 1, 2, 0]), (6, [1, 0, 0, 3])] {
            let s = ConvShape { ci: 1, h, w, co: 1, kh: 3, kw: 3, pad, stride: 2 };
            let (hq, wq) = s.phase();
            let src: Vec<f32> = (0..h * w).map(|i| i as f32).collect();
            let mut got = vec![-1.0f32; 4 * hq * wq + 8];
            s.pad_plane(&src, &mut got);
            // Padded (yp, xp) goes to phase (yp % 2, xp % 2), at (yp / 2, xp / 2).
            let mut want = vec![-1.0f32; got.len()];
            for y in 0..h {
                for x in 0..w {
                    let (yp, xp) = (y + pad[0], x + pad[1]);
                    want[((yp % 2) * 2 + xp % 2) * hq * wq + (yp / 2) * wq + xp / 2] = src[y * w + x];
                }
            }
            assert_eq!(got, want, "w {w}, h {h}, pad {pad:?}");
        }
    }
}

#[test]
fn equals_the_direct_sum_with_padding_and_a_partial_channel_block() {
    // 11 output channels: one whole block of 8 and a partial one; 3 taps chunks of 128 for
    // the 300-tap layer; outputs of 1 to 2 tiles.
    // The last: every third tap's weights are zero for all outputs (left out when packed).
    for (s, zero_taps, wide_on_avx512) in [
        (ConvShape { ci: 3, h: 9, w: 7, co: 11, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
        (ConvShape { ci: 12, h: 14, w: 14, co: 8, kh: 5, kw: 5, pad: [0; 4], stride: 1 }, false, false),
        (ConvShape { ci: 5, h: 6, w: 40, co: 3, kh: 2, kw: 4, pad: [0, 2, 1, 0], stride: 1 }, false, false),
        (ConvShape { ci: 4, h: 12, w: 12, co: 9, kh: 6, kw: 6, pad: [0; 4], stride: 1 }, true, false),
        // Stride 2 (the regulators' 3x3 convolutions: odd and even sizes, one-sided padding).
        (ConvShape { ci: 6, h: 21, w: 21, co: 10, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 }, false, false),
        (ConvShape { ci: 3, h: 10, w: 13, co: 9, kh: 4, kw: 3, pad: [0, 1, 2, 0], stride: 2 }, false, false),
        // One column, no odd run; one column padded on the left, no even one.
        (ConvShape { ci: 2, h: 7, w: 1, co: 3, kh: 3, kw: 1, pad: [1, 0, 1, 0], stride: 2 }, false, false),
        (ConvShape { ci: 2, h: 7, w: 1, co: 3, kh: 3, kw: 2, pad: [1, 1, 1, 0], stride: 2 }, false, false),
        // 32 channels or more: on AVX-512 the channels-in-lanes tiles, on these small maps
        // the compact ones (32 x 10 with a partial block; 48 x 8, stride 2; zero taps left
        // out).
        (ConvShape { ci: 7, h: 15, w: 17, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
        (ConvShape { ci: 3, h: 23, w: 21, co: 96, kh: 5, kw: 5, pad: [0, 1, 0, 1], stride: 2 }, false, false),
        (ConvShape { ci: 9, h: 8, w: 8, co: 48, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, true, false),
        // A map wide enough that the wide tiles (3 and 2 registers) compute fewer values
        // than the compact ones on AVX-512 (2 of 62 columns dropped a row).
        (ConvShape { ci: 3, h: 22, w: 62, co: 48, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, false, true),
        (ConvShape { ci: 3, h: 22, w: 62, co: 40, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, false, true),
        // Small maps of 16 input channels or more: on AVX2 the compact tiles (a partial
        // block of 16 channels; stride 2; a map smaller than a tile).
        (ConvShape { ci: 16, h: 8, w: 8, co: 24, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
        (ConvShape { ci: 20, h: 11, w: 9, co: 32, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 }, false, false),
        (ConvShape { ci: 16, h: 4, w: 4, co: 16, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, true, false),
        // And on AVX-512 those of 32 channels by 10 positions (a partial block) and of 48
        // by 8 (zero taps left out).
        (ConvShape { ci: 24, h: 9, w: 9, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 }, false, false),
        (ConvShape { ci: 16, h: 7, w: 7, co: 48, kh: 3, kw: 3, pad: [0; 4], stride: 1 }, true, false),
    ] {
        let n_in = s.ci * s.h * s.w;
        let taps = s.ci * s.kh * s.kw;
        let input: Vec<f32> = (0..2 * n_in).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        let weight: Vec<f32> = (0..s.co * taps)
            .map(|i| if zero_taps && i % taps % 3 == 0 { 0.0 } else { ((i * 104729 % 997) as f32) / 498.0 - 1.0 })
            .collect();
        let bias: Vec<f32> = (0..s.co).map(|o| o as f32 / 4.0).collect();
        let op = PackedConv::new(s.clone(), &weight, &bias).unwrap();
        assert_eq!(op.layout.taps.len(), if zero_taps { taps - taps.div_ceil(3) } else { taps });
        let compact = op.lanes.as_ref().is_some_and(|l| l.compact());
        match crate::isa::f32_kernel() {
            crate::isa::F32Kernel::Avx2Fma => assert_eq!(compact, s.ci >= 16, "{s:?}: compact tiles {compact}"),
            crate::isa::F32Kernel::Avx512 => {
                assert_eq!(compact, s.co >= 32 && !wide_on_avx512, "{s:?}: compact tiles {compact}")
            }
            _ => assert!(!compact, "{s:?}: compact tiles without AVX2"),
        }
        let x = tract_ndarray::Array4::from_shape_vec((2, s.ci, s.h, s.w), input.clone()).unwrap();
        let out = op.eval(&EvalContext::out_of_plan(), tvec![x.into_tensor().into_tvalue()]).unwrap();
        let out = out[0].try_as_plain_ram().unwrap();
        let out = out.as_slice::<f32>().unwrap();
        let per_image = out.len() / 2;
        for (n, got) in out.chunks_exact(per_image).enumerate() {
            let want = direct(&s, 1, &input[n * n_in..(n + 1) * n_in], &weight, &bias);
            let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(worst < 1e-4, "{s:?} image {n}: off by {worst}");
        }
    }
}

/// Over pools of 2, 3 and 8 threads, where few channel blocks are cut in runs of output rows
/// (or of tiles, [`super::super::par::parts`]), the outputs are those of one thread, bit for
/// bit: backbone layer 1's form (12 blocks of 8 channels, 8 threads), one block (2 threads),
/// three (2 and 8), stride 1 and 2, runs of one row.
#[test]
fn runs_of_rows_over_threads_give_one_thread_s_outputs() {
    use tract_linalg::multithread::{multithread_tract_scope, Executor};
    for s in [
        ConvShape { ci: 3, h: 35, w: 33, co: 96, kh: 11, kw: 11, pad: [0; 4], stride: 2 },
        ConvShape { ci: 4, h: 9, w: 30, co: 8, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
        ConvShape { ci: 5, h: 20, w: 17, co: 24, kh: 3, kw: 3, pad: [1, 0, 1, 2], stride: 2 },
        ConvShape { ci: 2, h: 4, w: 9, co: 3, kh: 3, kw: 3, pad: [0; 4], stride: 1 },
    ] {
        let taps = s.ci * s.kh * s.kw;
        let input: Vec<f32> = (0..s.ci * s.h * s.w).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        let weight: Vec<f32> = (0..s.co * taps).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let bias: Vec<f32> = (0..s.co).map(|o| o as f32 / 4.0).collect();
        let op = PackedConv::new(s.clone(), &weight, &bias).unwrap();
        let x = tract_ndarray::Array4::from_shape_vec((1, s.ci, s.h, s.w), input.clone()).unwrap().into_tensor();
        let run = |e: Executor| {
            let out =
                multithread_tract_scope(e, || op.eval(&EvalContext::out_of_plan(), tvec![x.clone().into_tvalue()]));
            out.unwrap()[0].try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().to_vec()
        };
        let one = run(Executor::SingleThread);
        let want = direct(&s, 1, &input, &weight, &bias);
        let worst = one.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{s:?}: off by {worst}");
        for threads in [2, 3, 8] {
            let got = run(Executor::multithread(threads));
            let same = got.iter().zip(&one).all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "{s:?}: {threads} threads give other outputs than one");
        }
    }
}
