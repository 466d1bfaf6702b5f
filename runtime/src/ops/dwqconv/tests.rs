//! [`super::DepthwiseQConv`] against tract's integer convolution: every kernel path, the
//! hard-swish table before it, the dequantisation after it, per-channel scales.

use super::*;

/// tract's quantised depthwise `Conv` of `s` on `batch` (NCHW) or CHW data, with input zero
/// point 117, output zero point 100, and per-channel weight scales (`one_scale`: the same
/// for every channel), wired in a model of its own, its input through `table` where given
/// (tract's `LookupTable`).
fn tract_model(s: &ConvShape, batch: bool, one_scale: bool, table: Option<&[u8]>) -> TypedModel {
    let c = s.ci;
    let bias: Vec<i32> = (0..c as i32).map(|o| 300 * o - 2000).collect();
    let taps = (s.kh * s.kw) as f32;
    let w_scale: Vec<f32> = (0..c).map(|o| if one_scale { 0.4 } else { 0.2 + 0.05 * o as f32 }).collect();
    let w_scale: Vec<f32> = w_scale.iter().map(|v| v / (taps.sqrt() * 127.0)).collect();
    let w_scale = if one_scale { tensor0(w_scale[0]) } else { tensor1(&w_scale) };
    super::super::qconv::tract_q_conv(s, c, batch, (&bias, w_scale, 0.01), table)
}

/// The tests' u8 input for `s`: NCHW (`batch`) or CHW bytes spread over 0..=255.
fn input_for(s: &ConvShape, batch: bool) -> TValue {
    let x_shape: Vec<usize> = if batch { vec![1, s.ci, s.h, s.w] } else { vec![s.ci, s.h, s.w] };
    let bytes: Vec<u8> = (0..s.ci * s.h * s.w).map(|i| ((i * 7919) % 256) as u8).collect();
    Tensor::from_shape(&x_shape, &bytes).unwrap().into_tvalue()
}

/// `model` run by tract alone as a plan runs it: decluttered and optimised (its requantisation
/// scales are then those of [`requant_scales`]; its unoptimised eval computes them otherwise).
fn tract_run(model: &TypedModel, input: &TValue) -> TVec<TValue> {
    model.clone().into_optimized().unwrap().into_runnable().unwrap().run(tvec![input.clone()]).unwrap()
}

/// The bytes of a u8 (possibly quantised) tensor.
fn bytes_of(t: &Tensor) -> Vec<u8> {
    // SAFETY: the tests' outputs are u8, possibly with quantisation parameters.
    unsafe { t.try_as_plain_ram().unwrap().as_slice_unchecked::<u8>().to_vec() }
}

/// Every path (VNNI where the CPU has it, the float kernel's sums everywhere) gives tract's
/// own bytes: 3x3 and 5x5 kernels, stride 1 and 2, maps of 16 columns and of widths that
/// leave part-filled blocks, per-channel scales and one (tract's exact product), NCHW and
/// CHW, one layer in channel groups.
#[test]
fn every_path_gives_tract_s_bytes() {
    let shape = |c, h, w, k: usize, stride| ConvShape { ci: c, h, w, co: c, kh: k, kw: k, pad: [k / 2; 4], stride };
    let cases = [
        (shape(6, 16, 16, 3, 1), true, false),
        (shape(5, 33, 65, 3, 2), true, true),
        (shape(4, 13, 27, 5, 1), false, false),
        (shape(3, 16, 16, 5, 2), true, false),
        (ConvShape { ci: 3, h: 10, w: 7, co: 3, kh: 3, kw: 3, pad: [0, 1, 2, 0], stride: 2 }, false, true),
        // Over SERIAL_MACS: channels in groups (on the pool, when there is one).
        (shape(24, 64, 64, 5, 1), true, false),
    ];
    if Path::here() == [Path::Float] {
        eprintln!("NOTE: no AVX-512 VNNI with VBMI or aarch64 dot product here (or PRL_ISA caps it): DepthwiseQConv's integer kernels are NOT tested here, only the float kernel's exact sums");
    }
    for (s, batch, one_scale) in cases {
        let model = tract_model(&s, batch, one_scale, None);
        let input = input_for(&s, batch);
        let want = bytes_of(&tract_run(&model, &input)[0]);
        let spread: std::collections::HashSet<u8> = want.iter().copied().collect();
        assert!(
            spread.len() > (want.len() / 5).min(50),
            "{s:?}: the outputs should spread over the bytes: {}",
            spread.len()
        );
        let node = model.node(model.output_outlets().unwrap()[0].node);
        let op = depthwise_q(&model, node).unwrap().expect("a DepthwiseQConv");
        assert_eq!(op.exact, one_scale);
        for path in Path::here() {
            let got = op.run(&EvalContext::out_of_plan(), input.clone(), path).unwrap();
            assert_eq!(got.shape(), model.output_fact(0).unwrap().shape.as_concrete().unwrap());
            let got = bytes_of(&got);
            assert!(got == want, "{s:?}, {path:?}: other bytes");
        }
        // And put in by `accelerate`, as a plan gets it.
        let mut fast = model.clone();
        assert_eq!(crate::ops::accelerate(&mut fast).unwrap().int8_convolutions, 1, "{s:?}");
        let got = bytes_of(&fast.into_runnable().unwrap().run(tvec![input]).unwrap()[0]);
        assert!(got == want, "{s:?}: other bytes in the accelerated model");
    }
}

/// A byte table before the convolution (tract's `LookupTable`, as it makes of a hard-swish
/// between two integer layers) is read by the convolution, which gives, on every path,
/// tract's bytes; the table's node goes.
#[test]
fn a_table_before_it_is_applied_as_planes_are_padded() {
    let table: Vec<u8> = (0..256).map(|i| ((i * i) / 255 + (i % 7)).min(255) as u8).collect();
    for (s, batch) in [
        (ConvShape { ci: 6, h: 16, w: 16, co: 6, kh: 3, kw: 3, pad: [1; 4], stride: 1 }, false),
        (ConvShape { ci: 5, h: 33, w: 70, co: 5, kh: 5, kw: 5, pad: [2; 4], stride: 2 }, true),
    ] {
        let model = tract_model(&s, batch, false, Some(&table));
        let input = input_for(&s, batch);
        let want = bytes_of(&tract_run(&model, &input)[0]);
        let node = model.node(model.output_outlets().unwrap()[0].node);
        let op = depthwise_q(&model, node).unwrap().expect("a DepthwiseQConv");
        let (op, x) = past_table(&model, node.inputs[0], op);
        assert!(op.table.is_some() && x.node == 0, "the table read, the source its input");
        for path in Path::here() {
            let got = op.run(&EvalContext::out_of_plan(), input.clone(), path).unwrap();
            let got = bytes_of(&got);
            assert!(got == want, "{s:?}, {path:?}: other bytes");
        }
        let mut fast = model.clone();
        crate::ops::accelerate(&mut fast).unwrap();
        assert!(fast.nodes().iter().all(|n| n.name != "lut"), "the table's node is gone");
        let got = bytes_of(&fast.into_runnable().unwrap().run(tvec![input]).unwrap()[0]);
        assert!(got == want, "{s:?}: other bytes in the accelerated model");
    }
}

/// A dequantisation with a hard-swish after the convolution (MobileNet's blocks with a
/// squeeze-excitation) is written by it: tract's f32 values on every path, the dequantiser
/// and the activation's nodes gone.
#[test]
fn a_dequantisation_after_it_is_written_by_it() {
    use tract_nnef::tract_core::ops::nn::hard_swish;
    use tract_nnef::tract_core::ops::quant::DequantizeLinearF32;
    for (s, batch) in [
        (ConvShape { ci: 6, h: 16, w: 16, co: 6, kh: 5, kw: 5, pad: [2; 4], stride: 1 }, false),
        (ConvShape { ci: 24, h: 64, w: 64, co: 24, kh: 3, kw: 3, pad: [1; 4], stride: 2 }, true),
    ] {
        let mut model = tract_model(&s, batch, false, None);
        let y = model.output_outlets().unwrap()[0];
        let dq = DequantizeLinearF32 { scale: 0.05, zero_point: 100 };
        let y = model.wire_node("dequant", dq, &[y]).unwrap();
        let y = model.wire_node("hswish", hard_swish(), &y).unwrap();
        model.select_output_outlets(&y).unwrap();
        let input = input_for(&s, batch);
        let want = tract_run(&model, &input).remove(0);
        let want: Vec<u32> =
            want.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().iter().map(|v| v.to_bits()).collect();
        let conv = model.node_by_name("conv").unwrap();
        let op = depthwise_q(&model, conv).unwrap().expect("a DepthwiseQConv");
        let (dq, chain) = dequantized_after(&model, conv).unwrap().expect("the dequantiser after it");
        assert_eq!(chain.len(), 2, "the dequantiser and the hard-swish");
        let op = op.dequantizing(dq);
        for path in Path::here() {
            let got = op.run(&EvalContext::out_of_plan(), input.clone(), path).unwrap();
            let got: Vec<u32> =
                got.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().iter().map(|v| v.to_bits()).collect();
            assert!(got == want, "{s:?}, {path:?}: other values");
        }
        let mut fast = model.clone();
        crate::ops::accelerate(&mut fast).unwrap();
        assert_eq!(fast.nodes().len(), 2, "the source and the convolution: {fast}");
        let got = fast.into_runnable().unwrap().run(tvec![input]).unwrap().remove(0);
        let got: Vec<u32> =
            got.try_as_plain_ram().unwrap().as_slice::<f32>().unwrap().iter().map(|v| v.to_bits()).collect();
        assert!(got == want, "{s:?}: other values in the accelerated model");
    }
}

/// Per-channel scales as tract's plan has them ([`requant_scales`]: `x · k / y` with 12
/// channels, `(k · x) · (1 / y)` with 20), on layers where the two forms give other bytes
/// ([`super::super::qconv::parting_case`]; weight scales one per channel, and all equal:
/// tract's exact product): every path gives tract's bytes.
#[test]
fn per_channel_scales_are_tract_s_to_the_last_bit() {
    for c in [12, 20] {
        let s = ConvShape { ci: c, h: 16, w: 21, co: c, kh: 3, kw: 3, pad: [1; 4], stride: 1 };
        for equal in [false, true] {
            let (model, input, want) = super::super::qconv::parting_case(&s, c, false, equal);
            let node = model.node(model.output_outlets().unwrap()[0].node);
            let op = depthwise_q(&model, node).unwrap().expect("a DepthwiseQConv");
            assert_eq!(op.exact, equal);
            for path in Path::here() {
                let got = bytes_of(&op.run(&EvalContext::out_of_plan(), input.clone(), path).unwrap());
                assert!(got == want, "{c} channels, equal {equal}, {path:?}: other bytes");
            }
        }
    }
}
