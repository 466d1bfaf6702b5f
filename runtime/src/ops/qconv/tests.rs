//! [`PackedQConv`] against the direct integer formula and tract's own quantised `Conv`, on
//! every words path the CPU has; and the tract models other int8 operators' tests compare with.

use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::einsum::EinSum;
use tract_nnef::tract_core::ops::nn::DataFormat;
use tract_nnef::tract_core::tract_linalg::{mmm::RoundingPolicy, Scaler};

use super::super::qconv_kernel::{exact_fits, requant_one};
use super::words::{interleave4, transpose8x8};
use super::*;

/// tract's quantised `Conv` of `s` in `group`s (1, or `s.ci` for a depthwise one) on NCHW
/// (`batch`) or CHW data, wired in a model of its own: i8 weights spread over the bytes, input
/// zero point 117 and scale 0.02, weight zero point 0, output zero point 100; `bias`, the
/// weight scales (one, or one per output channel) and the output scale as given; the input
/// through `table` where given (tract's `LookupTable`). The tests' reference for the
/// operators that replace it.
pub(in crate::ops) fn tract_q_conv(
    s: &ConvShape,
    group: usize,
    batch: bool,
    (bias, w_scale, y_scale): (&[i32], Tensor, f32),
    table: Option<&[u8]>,
) -> TypedModel {
    use tract_nnef::tract_core::ops::cnn::{PaddingSpec, PoolSpec};
    let mut model = TypedModel::default();
    let x_shape: TVec<usize> = if batch { tvec![1, s.ci, s.h, s.w] } else { tvec![s.ci, s.h, s.w] };
    let mut x = model.add_source("x", u8::fact(&x_shape)).unwrap();
    if let Some(t) = table {
        let lut = tract_nnef::tract_core::ops::quant::lookup_table(tract_linalg::routines::lut_u8(t).unwrap());
        x = model.wire_node("lut", lut, &[x]).unwrap()[0];
    }
    let per_group = s.ci / group;
    let w: Vec<i8> = (0..s.co * per_group * s.kh * s.kw).map(|i| ((i * 104729) % 255) as i32 as i8).collect();
    let konst = |name: &str, t: Tensor, model: &mut TypedModel| model.add_const(name, t).unwrap();
    let w = konst("w", Tensor::from_shape(&[s.co, per_group, s.kh, s.kw], &w).unwrap(), &mut model);
    let b = konst("b", Tensor::from_shape(&[s.co], bias).unwrap(), &mut model);
    let scalars = [tensor0(117i32), tensor0(0.02f32), tensor0(0i32), w_scale, tensor0(100i32), tensor0(y_scale)];
    let mut inputs = vec![x, w, b];
    for (i, t) in scalars.into_iter().enumerate() {
        inputs.push(konst(&format!("q{i}"), t, &mut model));
    }
    let pool_spec = PoolSpec {
        data_format: if batch { DataFormat::NCHW } else { DataFormat::CHW },
        kernel_shape: tvec![s.kh, s.kw],
        padding: PaddingSpec::ExplicitOnnxPool(tvec![s.pad[0], s.pad[1]], tvec![s.pad[2], s.pad[3]], false),
        dilations: None,
        strides: Some(tvec![s.stride, s.stride]),
        input_channels: s.ci,
        output_channels: s.co,
    };
    let op = Conv { pool_spec, kernel_fmt: KernelFormat::OIHW, group, q_params: Some(u8::datum_type()) };
    let y = model.wire_node("conv", op, &inputs).unwrap();
    model.select_output_outlets(&y).unwrap();
    model
}

/// A case that tells tract's two forms of per-channel requantisation scales apart (see
/// [`requant_scales`]): [`tract_q_conv`] of `s` in `group`s with weight scales where `x · k / y`
/// and `(k · x) · (1 / y)` part by a unit in the last place, one per output channel (`equal`:
/// all the same, tract's exact product) and biases whose products with the two round apart;
/// its input the zero point over the first half of every plane (outputs there: the biases
/// requantised), spread bytes below. Checks that tract's optimised plan takes the form its
/// channel count calls for, not the other, and returns the model, the input and tract's bytes.
pub(in crate::ops) fn parting_case(
    s: &ConvShape,
    group: usize,
    batch: bool,
    equal: bool,
) -> (TypedModel, TValue, Vec<u8>) {
    use super::super::qconv_kernel::parting_scales;
    // [`tract_q_conv`]'s input scale and zero points.
    let (x_scale, y_scale, x0, y0) = (0.02f32, 0.0137f32, 117u8, 100u8);
    let co = s.co;
    let (k_scale, bias): (Vec<f32>, Vec<i32>) = match equal {
        false => parting_scales(x_scale, y_scale, false).take(co).unzip(),
        true => parting_scales(x_scale, y_scale, true).take(1).flat_map(|p| std::iter::repeat_n(p, co)).unzip(),
    };
    assert_eq!(k_scale.len(), co, "enough scales where the forms part");
    let model = tract_q_conv(s, group, batch, (&bias, tensor1(&k_scale), y_scale), None);
    let mut bytes: Vec<u8> = (0..s.ci * s.h * s.w).map(|i| ((i * 7919) % 256) as u8).collect();
    for plane in bytes.chunks_exact_mut(s.h * s.w) {
        plane[..s.h / 2 * s.w].fill(x0);
    }
    let shape: Vec<usize> = if batch { vec![1, s.ci, s.h, s.w] } else { vec![s.ci, s.h, s.w] };
    let input = Tensor::from_shape(&shape, &bytes).unwrap().into_tvalue();
    let out = model.clone().into_optimized().unwrap().into_runnable().unwrap().run(tvec![input.clone()]).unwrap();
    // SAFETY: the output is u8 (possibly quantised).
    let want = unsafe { out[0].try_as_plain_ram().unwrap().as_slice_unchecked::<u8>().to_vec() };
    // Row 1, column 1 of each output plane: its window reads the zero point alone.
    let at_zero: Vec<u8> = want.chunks_exact(s.out().0 * s.out().1).map(|p| p[s.out().1 + 1]).collect();
    let by = |f: &dyn Fn(f32) -> f32| -> Vec<u8> {
        k_scale.iter().zip(&bias).map(|(&k, &b)| requant_one(b, f(k), equal, y0)).collect()
    };
    let division = by(&|k| x_scale * k / y_scale);
    let reciprocal = by(&|k| (k * x_scale) * (1.0 / y_scale));
    let (expected, other) = if co < 16 { (division, reciprocal) } else { (reciprocal, division) };
    assert_eq!(at_zero, expected, "{co} channels, equal {equal}: tract's bytes");
    assert_ne!(at_zero, other, "{co} channels, equal {equal}: the forms part");
    (model, input, want)
}

/// The direct integer formula, on `images` NCHW images of `s` (input zero point 7, output
/// zero point 100), requantised by [`requant_one`] with `scale[o]`.
fn direct(s: &ConvShape, input: &[u8], kernel: &[i8], bias: &[i32], (scale, exact): (&[f32], bool)) -> Vec<u8> {
    let (oh, ow) = s.out();
    let mut out = Vec::with_capacity(input.len() / (s.ci * s.h * s.w) * s.co * oh * ow);
    for img in input.chunks_exact(s.ci * s.h * s.w) {
        for o in 0..s.co {
            for y in 0..oh {
                for x in 0..ow {
                    let mut acc = bias[o];
                    for c in 0..s.ci {
                        for i in 0..s.kh {
                            for j in 0..s.kw {
                                let (yy, xx) = (
                                    (s.stride * y + i) as isize - s.pad[0] as isize,
                                    (s.stride * x + j) as isize - s.pad[1] as isize,
                                );
                                if yy < 0 || xx < 0 || yy >= s.h as isize || xx >= s.w as isize {
                                    continue;
                                }
                                let v = img[(c * s.h + yy as usize) * s.w + xx as usize] as i32 - 7;
                                acc += v * kernel[((o * s.ci + c) * s.kh + i) * s.kw + j] as i32;
                            }
                        }
                    }
                    out.push(requant_one(acc, scale[o], exact, 100));
                }
            }
        }
    }
    out
}

/// Pseudo-random inputs and weights for `s`.
fn data(s: &ConvShape) -> (Vec<u8>, Vec<i8>) {
    let input = (0..2 * s.ci * s.h * s.w).map(|i| ((i * 7919) % 256) as u8).collect();
    let kernel = (0..s.co * s.ci * s.kh * s.kw).map(|i| (((i * 104729) % 255) as i32 - 127) as i8).collect();
    (input, kernel)
}

/// Both kernels (AMX where the CPU has it, VNNI) against [`direct`] on two images of `s`.
fn check(s: ConvShape) {
    if !has_words_path() {
        // The op is only made where VNNI, AVX2 or SDOT may be used: say so, loudly.
        eprintln!(
            "NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's kernels are NOT tested on this machine"
        );
        return;
    }
    let (input, kernel) = data(&s);
    let bias: Vec<i32> = (0..s.co as i32).map(|o| 100 * o - 500).collect();
    let k_scale: Vec<f32> =
        (0..s.co).map(|o| (0.001 + 0.0001 * o as f32) * 9.0 / (s.ci * s.kh * s.kw) as f32).collect();
    let scale = requant_scales(0.02, &k_scale, 0.05, s.co);
    let want = direct(&s, &input, &kernel, &bias, (&scale, false));
    let unsaturated = want.iter().filter(|&&v| v != 0 && v != 255).count();
    assert!(unsaturated > want.len() / 2, "most outputs should not saturate: {unsaturated} of {}", want.len());
    let q = QuantParams { x0: 7, x_scale: 0.02, k_scale, y0: 100, y_scale: 0.05 };
    every_path(&s, &input, &kernel, &bias, q, &want);
}

/// Every path of the op made for `s` (AMX where the CPU has it; VNNI, AVX2 or SDOT words;
/// channels in lanes where packed) gives `want` on the images `input`, on the calling thread
/// and over a pool of eight (the Orin's cores: few channel blocks are cut in runs of rows or
/// tiles, [`super::super::par::parts`]).
fn every_path(s: &ConvShape, input: &[u8], kernel: &[i8], bias: &[i32], q: QuantParams, want: &[u8]) {
    use tract_linalg::multithread::{multithread_tract_scope, Executor};
    let amx = PackedQConv::new(s.clone(), kernel, bias, q, u8::datum_type()).unwrap();
    let vnni = PackedQConv { amx: None, ..amx.clone() };
    // The positions-in-lanes tiles too, where the channels-in-lanes ones were packed.
    let rows = PackedQConv { lanes: None, ..vnni.clone() };
    let images = input.len() / (s.ci * s.h * s.w);
    let x = tract_ndarray::Array4::from_shape_vec((images, s.ci, s.h, s.w), input.to_vec()).unwrap().into_tensor();
    let words = match words_path() {
        Some(WordsPath::Sdot) => "SDOT",
        Some(WordsPath::Avx2) => "AVX2",
        _ => "VNNI",
    };
    let lanes = if vnni.lanes.is_some() { "VNNI in lanes" } else { words };
    let ops = [(&amx, if amx.amx.is_some() { "AMX" } else { lanes }), (&vnni, lanes), (&rows, words)];
    for (threads, e) in [(1, Executor::SingleThread), (8, Executor::multithread(8))] {
        for (op, isa) in ops {
            let out = multithread_tract_scope(e.clone(), || {
                op.eval(&EvalContext::out_of_plan(), tvec![x.clone().into_tvalue()]).unwrap()
            });
            let out = out[0].try_as_plain_ram().unwrap();
            let got = out.as_slice::<u8>().unwrap();
            if let Some(i) = (0..want.len()).find(|&i| got[i] != want[i]) {
                panic!("{isa}, {threads} threads, {s:?}: output {i} is {} instead of {}", got[i], want[i]);
            }
        }
    }
}

/// Four rows' bytes interleaved into words, flipped or not, with lengths around the vector
/// paths' sixteen: the scalar formula's words.
#[test]
fn interleaving_four_rows_gives_each_position_s_word() {
    for n in [0, 5, 16, 31, 48, 117] {
        let rows: Vec<Vec<u8>> = (0..4).map(|c| (0..n).map(|x| (x * 37 + c * 101 + 7) as u8).collect()).collect();
        for flip in [0u32, 0x8080_8080] {
            let mut got = vec![0u32; n];
            interleave4([&rows[0], &rows[1], &rows[2], &rows[3]], &mut got, flip);
            for (x, &w) in got.iter().enumerate() {
                let want = u32::from_ne_bytes([rows[0][x], rows[1][x], rows[2][x], rows[3][x]]) ^ flip;
                assert_eq!(w, want, "n {n}, flip {flip:x}, position {x}");
            }
        }
    }
}

/// With one scale for every output channel, every path rounds the exact product, as tract's
/// `Scaler`: on an image at the input's zero point each channel's sum is its bias, chosen
/// where the f32 product rounds the other way; the other image is the usual one.
#[test]
fn one_scale_rounds_the_exact_product_on_every_path() {
    // HMG `proj`'s scales, the weights' 32 times smaller: more sums in range, more ties (10).
    exact_product_on_every_path(0.0069588, 0.0007929764 / 32.0, 0.0028860883);
}

/// The same with a scale above 1 (tract's fixed point then shifts by less than 31; such
/// scales come where the output's calibrated range is narrow, as `--method percentile`
/// makes NanoTrack's first pointwise layer). There no f32 product of an integer below 2^24
/// lands on a half that the exact one misses (the exact one is a multiple of 2^-23 times
/// the scale's exponent, which is at least the f32 product's half unit), so the biases span
/// the output range instead of rounding apart.
#[test]
fn one_scale_above_one_rounds_the_exact_product_on_every_path() {
    exact_product_on_every_path(1.0, 1.37, 1.0);
}

fn exact_product_on_every_path(x_scale: f32, w_scale: f32, y_scale: f32) {
    if !has_words_path() {
        eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's exact requantisation is NOT tested on this machine");
        return;
    }
    let scale = x_scale * w_scale / y_scale;
    assert!(exact_fits(scale, 1 << 16), "{scale}");
    let ties = super::super::qconv_kernel::tie_sums(scale);
    assert!(scale >= 1.0 || ties.len() >= 8, "the case needs sums that round apart: {}", ties.len());
    for s in [
        // AMX (where the CPU has it) and channels in lanes (VNNI), a partial group of four.
        ConvShape { ci: 6, h: 9, w: 21, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 },
        // A 1x1 layer without padding (rows requantised where they lie), 48 outputs.
        ConvShape { ci: 8, h: 9, w: 13, co: 48, kh: 1, kw: 1, pad: [0; 4], stride: 1 },
        // Stride 2, a partial block of 8 outputs.
        ConvShape { ci: 7, h: 12, w: 15, co: 11, kh: 3, kw: 4, pad: [1, 2, 0, 1], stride: 2 },
    ] {
        let (mut input, kernel) = data(&s);
        input[s.ci * s.h * s.w..].fill(7);
        let bias: Vec<i32> = match scale >= 1.0 {
            true => (0..s.co).map(|o| (o as i32 * 13) % 141 - 70).collect(),
            false => (0..s.co).map(|o| ties[(o * 7) % ties.len()]).collect(),
        };
        let one = vec![scale; s.co];
        let want = direct(&s, &input, &kernel, &bias, (&one, true));
        let zero_point_image = &want[s.out().0 * s.out().1 * s.co..];
        if scale >= 1.0 {
            assert!(zero_point_image.iter().all(|&y| (1..255).contains(&y)), "{s:?}: outputs in range");
        } else {
            let f32_product = direct(&s, &input, &kernel, &bias, (&one, false));
            let apart = want.iter().zip(&f32_product).filter(|(a, b)| a != b).count();
            assert!(
                apart >= s.out().0 * s.out().1 * s.co,
                "{s:?}: every output at the zero point rounds apart: {apart}"
            );
        }
        let q = QuantParams { x0: 7, x_scale, k_scale: vec![w_scale], y0: 100, y_scale };
        every_path(&s, &input, &kernel, &bias, q, &want);
    }
}

#[test]
fn equals_the_integer_formula_with_zero_points_and_padding() {
    // 6 input channels (a partial group of four), 11 outputs (a partial block), padding 1;
    // padding reads real zeros (the input zero point 7).
    check(ConvShape { ci: 6, h: 9, w: 37, co: 11, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 1 });
    // Two 64-channel steps (the second partial), a 32-output block and a partial one, a
    // 5x5 kernel without padding, wide rows that end inside a block.
    check(ConvShape { ci: 70, h: 14, w: 19, co: 40, kh: 5, kw: 5, pad: [0; 4], stride: 1 });
    check(ConvShape { ci: 128, h: 6, w: 6, co: 32, kh: 1, kw: 1, pad: [0, 2, 1, 0], stride: 1 });
    // A 1x1 layer without padding as NanoTrack's: 117 positions (not a multiple of 16),
    // 48 outputs in lanes.
    check(ConvShape { ci: 24, h: 9, w: 13, co: 48, kh: 1, kw: 1, pad: [0; 4], stride: 1 });
    // 96 outputs: two blocks of 48 channels in lanes (on VNNI), 600 tap groups in 5 passes.
    check(ConvShape { ci: 96, h: 9, w: 12, co: 96, kh: 5, kw: 5, pad: [2, 2, 2, 2], stride: 1 });
}

/// Per-channel scales as tract's plan has them ([`requant_scales`]: `x · k / y` with 12
/// output channels, `(k · x) · (1 / y)` with 20), on layers where the two forms give other
/// bytes ([`parting_case`]; weight scales one per channel, and all equal: tract's exact
/// product): the `PackedQConv` that `accelerate` makes gives tract's bytes.
#[test]
fn per_channel_scales_are_tract_s_to_the_last_bit() {
    if !has_words_path() {
        eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's per-channel scales are NOT tested on this machine");
        return;
    }
    for co in [12, 20] {
        let s = ConvShape { ci: 8, h: 10, w: 13, co, kh: 3, kw: 3, pad: [1; 4], stride: 1 };
        for exact in [false, true] {
            let (model, input, want) = parting_case(&s, 1, true, exact);
            let mut fast = model;
            assert_eq!(crate::ops::accelerate(&mut fast).unwrap().int8_convolutions, 1, "{s:?}");
            let out = fast.into_runnable().unwrap().run(tvec![input]).unwrap().remove(0);
            // SAFETY: the output is u8 (possibly quantised).
            let got = unsafe { out.try_as_plain_ram().unwrap().as_slice_unchecked::<u8>().to_vec() };
            assert!(got == want, "{co} channels, exact {exact}: other bytes");
        }
    }
}

/// The quantised `EinSum` tract makes of a 1x1 convolution (HMG's patch embeddings) becomes
/// a [`PackedQConv`] giving tract's own bytes; other einsums stay.
#[test]
fn the_einsum_of_a_pointwise_convolution_gives_tract_s_bytes() {
    let run = |expr: &str, x_shape: &[usize], w_shape: &[usize], made: usize| {
        // The product form (`akm,kn->mn`) has its channels second to last and the weights
        // `K x N` or `N x K`; the convolutions' have them third to last and `N x K`.
        let product = expr.ends_with("->mn") || expr.ends_with("->anm");
        let ci = match (product, expr.starts_with("mk") || expr.starts_with("HWI")) {
            (_, true) => x_shape[x_shape.len() - 1],
            (true, false) => x_shape[x_shape.len() - 2],
            _ => x_shape[x_shape.len() - 3],
        };
        let co = if product && expr.contains(",kn,") { w_shape[1] } else { w_shape[0] };
        let mut model = TypedModel::default();
        let x = model.add_source("x", u8::fact(x_shape)).unwrap();
        let w: Vec<i8> = (0..w_shape.iter().product()).map(|i: usize| ((i * 104729) % 255) as i32 as i8).collect();
        let konst = |name: &str, t: Tensor, model: &mut TypedModel| model.add_const(name, t).unwrap();
        let w = konst("w", Tensor::from_shape(w_shape, &w).unwrap(), &mut model);
        let bias: Vec<i32> = (0..co as i32).map(|o| 300 * o - 2000).collect();
        let b = konst("b", Tensor::from_shape(&[co], &bias).unwrap(), &mut model);
        let scalars = [
            tensor0(3i32),
            tensor0(0.02f32),
            tensor0(0i32),
            tensor0(0.2f32 / ((ci as f32).sqrt() * 127.0)),
            tensor0(100i32),
            tensor0(0.01f32),
        ];
        let mut inputs = vec![x, w, b];
        for (i, t) in scalars.into_iter().enumerate() {
            inputs.push(konst(&format!("q{i}"), t, &mut model));
        }
        let op = EinSum::newq(expr.parse().unwrap(), i32::datum_type(), u8::datum_type());
        let y = model.wire_node("embed", op, &inputs).unwrap();
        model.select_output_outlets(&y).unwrap();
        let n: usize = x_shape.iter().product();
        let input = Tensor::from_shape(x_shape, &(0..n).map(|i| ((i * 7919) % 256) as u8).collect::<Vec<_>>());
        let input = input.unwrap().into_tvalue();
        let reference = model.clone();
        let done = crate::ops::accelerate(&mut model).unwrap();
        assert_eq!(done.int8_convolutions, made, "{expr}");
        if made == 0 {
            return;
        }
        let want = reference.into_runnable().unwrap().run(tvec![input.clone()]).unwrap();
        let got = model.into_runnable().unwrap().run(tvec![input]).unwrap();
        let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
        // SAFETY: both outputs are u8 (possibly quantised).
        let (got, want) = unsafe { (got.as_slice_unchecked::<u8>(), want.as_slice_unchecked::<u8>()) };
        let spread: std::collections::HashSet<u8> = want.iter().copied().collect();
        assert!(spread.len() > 50, "{expr}: the outputs should spread over the bytes: {}", spread.len());
        assert_eq!(got, want, "{expr}");
    };
    if !has_words_path() {
        eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): the pointwise einsum stays with tract and is NOT tested as a PackedQConv here");
        return;
    }
    // HMG's form (192 channels, 11x11 tokens) with other letters, and 40 outputs (32-channel tiles).
    run("aicd,bi,b,,,,,,->abcd", &[1, 192, 11, 11], &[192, 192], 1);
    run("NIHW,OI,O,,,,,,->NOHW", &[1, 24, 5, 7], &[40, 24], 1);
    // NanoTrack's forms: the batch axis dropped (CHW), and dropped on the way out.
    run("IHW,OI,O,,,,,,->OHW", &[24, 32, 32], &[88, 24], 1);
    run("NIHW,OI,O,,,,,,->OHW", &[1, 16, 24, 20], &[16, 16], 1);
    // Channels last on either side or both (NanoTrack's pointwise layers on aarch64, where
    // tract moves the depthwise layers' channels last), on every words path.
    run("HWI,OI,O,,,,,,->OHW", &[6, 7, 36], &[20, 36], 1);
    run("IHW,OI,O,,,,,,->HWO", &[36, 6, 7], &[20, 36], 1);
    run("HWI,OI,O,,,,,,->HWO", &[9, 13, 39], &[88, 39], 1);
    // Not a pointwise convolution (the weights' axes the other way round): left alone.
    run("NIHW,IO,O,,,,,,->NOHW", &[1, 24, 5, 7], &[24, 40], 0);
    run("IHW,IO,O,,,,,,->OHW", &[24, 5, 7], &[24, 40], 0);
    // HMG's linear layers (`akm,kn->mn`, tokens out last), made where `products_here`
    // says; and without the leading axis.
    let made = usize::from(products_here());
    if made == 0 {
        eprintln!("NOTE: the product form of PackedQConv is made on the AVX2, SDOT and VNNI words paths, on VNNI's where tract's AMX kernels do not take the products (TRACT_CPU_ISA=-amx-int8 reaches it): NOT tested here");
    }
    run("akm,kn,n,,,,,,->mn", &[1, 48, 121], &[48, 72], made);
    run("km,nk,n,,,,,,->mn", &[36, 37], &[20, 36], made);
    // Tokens first in, channels first out, a new leading axis (HMG's `proj` and `fc2`).
    run("mk,kn,n,,,,,,->anm", &[121, 40], &[40, 24], made);
    // Tokens first in and out, input channels that are not whole words, output channels
    // that are not whole blocks of 8, positions that are not whole tiles.
    run("mk,kn,n,,,,,,->mn", &[70, 39], &[39, 20], made);
}

/// With one scale, the einsums made `PackedQConv`s (a 1x1 convolution; a product, on the
/// AVX2 words path) requantise as tract's kernels: at HMG `proj`'s scales, a sum of 48902 is
/// 93.5 as an f32 product and just under it exactly.
#[test]
fn one_scale_rounds_as_tract_s_kernels() {
    if !has_words_path() {
        eprintln!("NOTE: no AVX-512 VNNI, AVX2 or aarch64 dot product here (or PRL_ISA caps it): PackedQConv's rounding is NOT compared with tract's here");
        return;
    }
    // HMG `proj`'s scales, with a sum that rounds apart in f32; and a scale above 1 (the
    // fixed point shifts by less than 31), which tract's kernels served alone until
    // 2026-12-05 (NanoTrack's first pointwise layer with `--method percentile`).
    let (x_scale, w_scale, y_scale) = (0.0069588f32, 0.0007929764f32, 0.0028860883f32);
    let scale = x_scale * w_scale / y_scale;
    let exact = 48902 * Scaler::new(scale, RoundingPolicy::Even);
    assert_ne!((48902.0 * scale).round_ties_even() as i32, exact, "the case must tell the two roundings apart");
    let cases = [((x_scale, w_scale, y_scale), [48902i32, -48902, 48901, 1000]), ((0.5, 2.74, 1.0), [41, -57, 3, 90])];
    for ((x_scale, w_scale, y_scale), biases) in cases {
        rounds_as_tract_s_kernels(x_scale, w_scale, y_scale, biases);
    }
}

fn rounds_as_tract_s_kernels(x_scale: f32, w_scale: f32, y_scale: f32, biases: [i32; 4]) {
    let scale = x_scale * w_scale / y_scale;
    let exact = biases[0] * Scaler::new(scale, RoundingPolicy::Even);
    let products = products_here();
    if !products {
        eprintln!("NOTE: the product form of PackedQConv is made on the AVX2, SDOT and VNNI words paths, on VNNI's where tract's AMX kernels do not take the products (TRACT_CPU_ISA=-amx-int8 reaches it): its rounding is NOT tested here");
    }
    let forms: [(&str, &[usize], bool); 2] =
        [("NIHW,OI,O,,,,,,->NOHW", &[1, 4, 3, 1], true), ("mk,kn,n,,,,,,->anm", &[3, 4], products)];
    for (expr, x_shape, made) in forms {
        if !made {
            continue;
        }
        let mut model = TypedModel::default();
        // Inputs at their zero point: every sum is its bias.
        let x = model.add_source("x", u8::fact(x_shape)).unwrap();
        let mut konst = |name: &str, t: Tensor| model.add_const(name, t).unwrap();
        let w = konst("w", Tensor::from_shape(&[4, 4], &[1i8; 16]).unwrap());
        let b = konst("b", Tensor::from_shape(&[4], &biases).unwrap());
        let mut inputs = vec![x, w, b];
        for (i, t) in
            [tensor0(5i32), tensor0(x_scale), tensor0(0i32), tensor0(w_scale), tensor0(128i32), tensor0(y_scale)]
                .into_iter()
                .enumerate()
        {
            inputs.push(konst(&format!("q{i}"), t));
        }
        let op = EinSum::newq(expr.parse().unwrap(), i32::datum_type(), u8::datum_type());
        let y = model.wire_node("proj", op, &inputs).unwrap();
        model.select_output_outlets(&y).unwrap();
        let input = Tensor::from_shape(x_shape, &[5u8; 12]).unwrap().into_tvalue();
        let reference = model.clone().into_optimized().unwrap();
        assert_eq!(crate::ops::accelerate(&mut model).unwrap().int8_convolutions, 1, "{expr}, scale {scale}");
        let want = reference.into_runnable().unwrap().run(tvec![input.clone()]).unwrap();
        let got = model.into_runnable().unwrap().run(tvec![input]).unwrap();
        let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
        // SAFETY: both outputs are u8 (possibly quantised).
        let (got, want) = unsafe { (got.as_slice_unchecked::<u8>(), want.as_slice_unchecked::<u8>()) };
        assert_eq!(got, want, "{expr}, scale {scale}");
        assert_eq!(got[0] as i32, 128 + exact, "{expr}, scale {scale}");
    }
}

#[test]
fn a_product_s_transpose_puts_each_position_s_channels_in_a_row() {
    let square: [u64; 8] = std::array::from_fn(|i| u64::from_le_bytes(std::array::from_fn(|j| (16 * i + j) as u8)));
    let t = transpose8x8(square);
    for (i, row) in t.iter().enumerate() {
        assert_eq!(row.to_le_bytes(), std::array::from_fn(|j| (16 * j + i) as u8), "row {i}");
    }
    // 21 channels of 45 positions; the blocks from position 32 (13 rows: one square and
    // five rows of bytes) and from 0 (32 rows).
    let (co, m) = (21, 45);
    let planes: Vec<u8> = (0..co * m).map(|i| (i * 7 % 251) as u8).collect();
    for (first, n) in [(0, 32), (32, 13)] {
        let mut rows = vec![0u8; n * co];
        transpose_block(&planes, m, first, &mut rows);
        for (r, row) in rows.chunks_exact(co).enumerate() {
            for (o, &v) in row.iter().enumerate() {
                assert_eq!(v, planes[o * m + first + r], "position {}, channel {o}", first + r);
            }
        }
    }
}

#[test]
fn stride_two_equals_the_integer_formula() {
    // Backbone layer 1's form: three channels (one word, a zero fourth weight), an 11x11
    // kernel, 96 outputs (channels in lanes on VNNI), odd and even padded sizes.
    check(ConvShape { ci: 3, h: 31, w: 29, co: 96, kh: 11, kw: 11, pad: [0; 4], stride: 2 });
    // Padding on odd and even sides, a partial 8-channel block, two groups of four.
    check(ConvShape { ci: 7, h: 12, w: 15, co: 11, kh: 3, kw: 4, pad: [1, 2, 0, 1], stride: 2 });
    check(ConvShape { ci: 16, h: 10, w: 10, co: 40, kh: 3, kw: 3, pad: [1, 1, 1, 1], stride: 2 });
}
