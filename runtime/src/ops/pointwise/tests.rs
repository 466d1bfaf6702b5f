//! [`super::PointwiseConv`]'s kernel paths against the direct sum, and which graphs it takes.

use super::*;
use crate::ops::attention::tests::values;
use tract_nnef::tract_core::ops::binary::TypedBinOp;
use tract_nnef::tract_core::ops::einsum::EinSum;
use tract_nnef::tract_core::ops::math::{add, max, min};
use tract_nnef::tract_core::ops::nn::hard_swish;

/// Every tile path the CPU can run, against sums in f64, for each kind of activation.
#[test]
fn every_kernel_path_equals_the_direct_sum() {
    let (k, ldx) = (37, NB + 5);
    let panel = values(k * MR, 3);
    let x = values(k * ldx, 1);
    let bias: [f32; MR] = std::array::from_fn(|r| r as f32 * 0.5 - 1.0);
    let acts = [
        Activation::NONE,
        Activation { lo: 0.0, hi: 6.0, hard_swish: false },
        Activation { hard_swish: true, ..Activation::NONE },
    ];
    for act in acts {
        let want: Vec<Vec<f64>> = (0..MR)
            .map(|r| {
                (0..NB)
                    .map(|j| {
                        let s: f64 = (0..k).map(|i| panel[i * MR + r] as f64 * x[i * ldx + j] as f64).sum();
                        act.apply((s + bias[r] as f64) as f32) as f64
                    })
                    .collect()
            })
            .collect();
        type Path = unsafe fn(&[f32], &[f32], usize, [f32; MR], Activation, *mut f32, usize, usize);
        #[allow(unused_mut)] // only x86 adds paths
        let mut paths: Vec<(&str, Path)> = vec![
            ("dispatched", tile),
            ("generic fused", tile_generic::<true>),
            ("generic plain", tile_generic::<false>),
        ];
        #[cfg(target_arch = "x86_64")]
        {
            if super::super::avx2_fma() {
                paths.push(("avx2+fma", tile_fma));
            } else {
                eprintln!("NOTE: no AVX2+FMA here (or PRL_ISA caps it): PointwiseConv's AVX2 path is not tested here");
            }
            if super::super::avx512_fma() {
                paths.push(("avx512", tile_avx512));
            } else {
                eprintln!(
                    "NOTE: no AVX-512 here (or PRL_ISA caps it): PointwiseConv's AVX-512 path is not tested here"
                );
            }
        }
        for (name, path) in paths {
            // Rows past `rows` must stay untouched.
            let mut out = [[f32::NAN; NB]; MR];
            // SAFETY: the local tile holds MR rows of NB; the paths run only where the CPU
            // has their features (checked above).
            unsafe { path(&panel, &x, ldx, bias, act, out.as_mut_ptr().cast(), NB, MR - 1) };
            for r in 0..MR {
                for j in 0..NB {
                    let (g, w) = (out[r][j], want[r][j]);
                    if r == MR - 1 {
                        assert!(g.is_nan(), "{name}: row {r} written");
                    } else {
                        assert!((g as f64 - w).abs() <= 1e-4 * w.abs().max(1.0), "{name} {act:?}: {r},{j}: {g} vs {w}");
                    }
                }
            }
        }
    }
}

/// A model of one 1x1 convolution as tract declutters it (`mk,kn->mn`, then the bias and
/// what `tail` adds), run by tract and after [`accelerate`](super::super::accelerate).
fn check(m: usize, k: usize, h: usize, w: usize, tail: impl Fn(&mut TypedModel, OutletId) -> OutletId, fused: usize) {
    check_expr("mk,kn->mn", [m, k], [k, h * w], tail, fused)
}

/// As [`check`], for the product `expr` of a constant of shape `w` and the data `x`.
fn check_expr(
    expr: &str,
    w: [usize; 2],
    x: [usize; 2],
    tail: impl Fn(&mut TypedModel, OutletId) -> OutletId,
    fused: usize,
) {
    let mut model = TypedModel::default();
    let xs = model.add_source("x", f32::fact(x)).unwrap();
    let wt = model.add_const("w", Tensor::from_shape(&w, &values(w[0] * w[1], 3)).unwrap()).unwrap();
    let y = model.wire_node("product", EinSum::new(expr.parse().unwrap(), f32::datum_type()), &[wt, xs]);
    let y = tail(&mut model, y.unwrap()[0]);
    model.select_output_outlets(&[y]).unwrap();
    let input = Tensor::from_shape(&x, &values(x[0] * x[1], 1)).unwrap();
    let want = model.clone().into_runnable().unwrap().run(tvec![input.clone().into_tvalue()]).unwrap();
    let nodes = model.nodes().len();
    let done = super::super::accelerate(&mut model).unwrap();
    assert_eq!(done.pointwise, 1);
    // The product's constant and the fused nodes (with their constants) are gone.
    assert_eq!(nodes - model.nodes().len(), fused, "nodes removed");
    let got = model.into_runnable().unwrap().run(tvec![input.into_tvalue()]).unwrap();
    assert_eq!(got[0].shape(), want[0].shape());
    let (got, want) = (got[0].try_as_plain_ram().unwrap(), want[0].try_as_plain_ram().unwrap());
    let (got, want) = (got.as_slice::<f32>().unwrap(), want.as_slice::<f32>().unwrap());
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((g - w).abs() <= 1e-4 * w.abs().max(1.0), "element {i}: {g} vs {w}");
    }
}

fn konst(model: &mut TypedModel, name: &str, shape: &[usize], v: Vec<f32>) -> OutletId {
    model.add_const(name, Tensor::from_shape(shape, &v).unwrap()).unwrap()
}

fn bin(model: &mut TypedModel, name: &str, op: TypedBinOp, a: OutletId, b: OutletId) -> OutletId {
    model.wire_node(name, op, &[a, b]).unwrap()[0]
}

#[test]
fn fuses_the_bias_and_activation_of_a_1x1_convolution() {
    // m not a multiple of the panel, n of the tile (a short last block).
    let bias_relu6 = |m: usize| {
        move |model: &mut TypedModel, y: OutletId| {
            let b = konst(model, "b", &[m, 1], values(m, 5));
            let y = bin(model, "bias", add(), y, b);
            let lo = konst(model, "lo", &[1, 1], vec![0.0]);
            let y = bin(model, "max", max(), y, lo);
            let hi = konst(model, "hi", &[1, 1], vec![6.0]);
            bin(model, "min", min(), y, hi)
        }
    };
    check(20, 24, 10, 10, bias_relu6(20), 7);
    check(72, 16, 16, 16, bias_relu6(72), 7);
    // The bias, a reshape to the image, hard-swish (tract's order in NanoTrack).
    check(
        13,
        40,
        8,
        8,
        |model: &mut TypedModel, y: OutletId| {
            let b = konst(model, "b", &[13, 1], values(13, 5));
            let y = bin(model, "bias", add(), y, b);
            let y = model.wire_node("image", AxisOp::Reshape(1, tvec![64.into()], tvec![8.into(), 8.into()]), &[y]);
            model.wire_node("hs", hard_swish(), &y.unwrap()).unwrap()[0]
        },
        5,
    );
    // No bias; a reshape alone at the end stays tract's.
    check(
        8,
        8,
        4,
        16,
        |model: &mut TypedModel, y: OutletId| {
            model.wire_node("image", AxisOp::Reshape(1, tvec![64.into()], tvec![4.into(), 16.into()]), &[y]).unwrap()[0]
        },
        1,
    );
}

#[test]
fn takes_a_product_with_one_output_channel_or_one_input_channel() {
    // PRL-Track's gating convolutions (96 or 192 channels to one): tract makes the product's
    // output positions-first, `[n][1]`, which is the same values in the same order.
    let bias = |model: &mut TypedModel, y: OutletId| {
        let b = konst(model, "b", &[1, 1], vec![-0.5]);
        bin(model, "bias", add(), y, b)
    };
    check_expr("mk,kn->nm", [1, 96], [96, 41 * 41], bias, 3);
    check(1, 40, 9, 9, bias, 3);
    // Two single-channel maps to one (`ar`'s concatenation): one channel in, one out.
    check_expr("mk,kn->mn", [1, 1], [1, 21 * 21], bias, 3);
}

#[test]
fn stops_where_a_value_is_used_twice_or_the_bias_is_not_per_channel() {
    // The biased value also feeds another node: the bias is fused, the clamp is not.
    check(
        12,
        16,
        8,
        8,
        |model: &mut TypedModel, y: OutletId| {
            let b = konst(model, "b", &[12, 1], values(12, 5));
            let y = bin(model, "bias", add(), y, b);
            let lo = konst(model, "lo", &[1, 1], vec![0.0]);
            let r = bin(model, "relu", max(), y, lo);
            bin(model, "sum", add(), y, r)
        },
        3,
    );
    // A bias per position is not a convolution's: only the product is replaced.
    check(
        12,
        16,
        8,
        8,
        |model: &mut TypedModel, y: OutletId| {
            let b = konst(model, "b", &[1, 64], values(64, 5));
            bin(model, "bias", add(), y, b)
        },
        1,
    );
}
