//! The lane tiles against their portable forms, on every path the CPU has.

#[cfg(target_arch = "x86_64")]
use super::x86::transpose;
use super::*;
use crate::isa::F32Kernel;

#[test]
#[cfg(target_arch = "x86_64")]
fn transposes_sixteen_rows() {
    if !crate::isa().avx512 {
        eprintln!("NOTE: no AVX-512 here (or PRL_ISA caps it): the 16 x 16 transpose is NOT tested here");
        return;
    }
    use std::arch::x86_64::*;
    let m: Vec<f32> = (0..256).map(|i| i as f32).collect();
    // SAFETY: the CPU has AVX-512F (checked above); every load and store is 16 of the 256.
    unsafe {
        let mut r: [__m512; 16] = std::array::from_fn(|i| _mm512_loadu_ps(m.as_ptr().add(16 * i)));
        transpose(&mut r);
        let mut out = vec![0f32; 256];
        for (i, r) in r.iter().enumerate() {
            _mm512_storeu_ps(out.as_mut_ptr().add(16 * i), *r);
        }
        for i in 0..16 {
            for j in 0..16 {
                assert_eq!(out[i * 16 + j], m[j * 16 + i], "({i}, {j})");
            }
        }
    }
}

/// The compact tiles (AVX2's of one register, AVX-512's of two and three, where the CPU
/// has them) give the bits of the portable compact tiles and of the wide ones (every path
/// sums in tap order, one rounding per multiply-add), and the convolution's sums: partial
/// channel blocks, several tap passes, maps smaller than a tile.
#[test]
fn compact_tiles_equal_the_portable_and_the_wide_ones() {
    if !matches!(crate::isa::f32_kernel(), F32Kernel::Avx2Fma | F32Kernel::Avx512) {
        println!("NOTE: no AVX2 here (or PRL_ISA caps it): the compact tiles run their portable form only");
    } else if crate::isa::f32_kernel() != F32Kernel::Avx512 {
        println!("NOTE: no AVX-512 here (or PRL_ISA caps it): the compact tiles of 2 and 3 registers run their portable form only");
    }
    for (ci, h, w, k, co) in
        [(30, 11, 23, 3, 40), (40, 12, 12, 3, 16), (7, 5, 6, 5, 48), (3, 4, 4, 3, 33), (20, 9, 9, 3, 96)]
    {
        let l = Layout::dense(ci, h, w, k);
        let taps = l.taps.len();
        let padded: Vec<f32> = (0..ci * h * w + 64).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
        let weight: Vec<f32> = (0..co * taps).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let live: Vec<usize> = (0..taps).collect();
        let bias: Vec<f32> = (0..co).map(|o| o as f32 / 8.0).collect();
        let plane = l.oh * l.ow;
        for (v, px) in [(1, COMPACT_P), (2, 10), (2, 9), (3, 8)] {
            let pack = LanePack::with_tile(&weight, taps, &live, co, Tile { v, px, compact: true });
            let oc = pack.channels();
            assert!(pack.compact() && px == pack.positions());
            let mut got = vec![0f32; co * plane];
            pack.run_compact(&l, &padded, &bias, Activation::NONE, &mut got);
            let (tiles_n, wide_n) = (plane.div_ceil(px), l.positions().div_ceil(px));
            for b in 0..co.div_ceil(oc) {
                let block = pack.block(b);
                let mut sums = vec![0f32; tiles_n * oc * px];
                compact_tiles(&l, oc, px, &padded, block, 0, &mut sums);
                let mut wide = vec![0f32; wide_n * oc * px];
                tiles(&l, oc, px, &padded, block, 0, &mut wide);
                for (s, at) in outputs(&l, &wide, oc, px, 0) {
                    for (r, s) in s.iter().enumerate().take(co - b * oc) {
                        let o = b * oc + r;
                        let want = s + bias[o];
                        assert!(
                            sums[at * oc + r] + bias[o] == want,
                            "{co} channels, {v}x{px}: compact and wide sums differ"
                        );
                        assert!(
                            got[o * plane + at] == want,
                            "{co} channels, {v}x{px}: output {o} at {at}: dispatched differs"
                        );
                    }
                }
            }
            // With an activation: applied to every output, as the wide tiles' callers do.
            let act = Activation { lo: -1.0, hi: 2.0, hard_swish: true };
            let mut with_act = vec![0f32; co * plane];
            pack.run_compact(&l, &padded, &bias, act, &mut with_act);
            let mut want = got.clone();
            act.apply_all(&mut want);
            assert!(with_act == want, "{co} channels, {v}x{px}: the activation differs");
            for o in [0, co - 1] {
                for at in [0, plane - 1] {
                    let (y, x) = (at / l.ow, at % l.ow);
                    let mut acc = bias[o] as f64;
                    for (tap, &t) in l.taps.iter().enumerate() {
                        acc += padded[y * l.wp + x + t] as f64 * weight[o * taps + tap] as f64;
                    }
                    let g = got[o * plane + at] as f64;
                    assert!((g - acc).abs() < 1e-3, "{co} channels, output {o} at {at}: {g} against {acc}");
                }
            }
        }
    }
}

/// The dispatched tiles give the portable tiles' bits, for both tile shapes, with a
/// partial last block and several tap chunks.
#[test]
fn dispatched_tiles_equal_the_portable_ones() {
    if crate::isa::f32_kernel() != F32Kernel::Avx512 {
        println!("NOTE: no AVX-512 here (or PRL_ISA caps it): PackedConv's channels-in-lanes AVX-512 tiles are not tested here");
    }
    let (ci, h, w, k) = (30, 11, 23, 3);
    let l = Layout::dense(ci, h, w, k);
    let padded: Vec<f32> = (0..ci * h * w + 64).map(|i| ((i * 7919 % 1000) as f32) / 500.0 - 1.0).collect();
    for co in [40, 96] {
        let taps = l.taps.len();
        let weight: Vec<f32> = (0..co * taps).map(|i| ((i * 104729 % 997) as f32) / 498.0 - 1.0).collect();
        let live: Vec<usize> = (0..taps).collect();
        let v = LanePack::registers_for(co).unwrap();
        let pack = LanePack::with_tile(&weight, taps, &live, co, Tile::wide(v));
        let bias: Vec<f32> = (0..co).map(|o| o as f32 / 8.0).collect();
        let mut got = vec![0f32; co * l.oh * l.ow];
        pack.run(&l, &padded, &bias, Activation::NONE, &mut got);
        let (oc, px) = (pack.channels(), pack.positions());
        let tiles_n = l.positions().div_ceil(px);
        let mut want = vec![0f32; co * l.oh * l.ow];
        for b in 0..co.div_ceil(oc) {
            let mut sums = vec![0f32; tiles_n * oc * px];
            tiles(&l, oc, px, &padded, &pack.values()[b * taps * oc..(b + 1) * taps * oc], 0, &mut sums);
            for (i, s) in sums.chunks_exact(oc).enumerate() {
                let (y, x) = (i / l.wp, i % l.wp);
                if i >= l.positions() || x >= l.ow {
                    continue;
                }
                for (r, s) in s.iter().enumerate().take(co - b * oc) {
                    want[(b * oc + r) * l.oh * l.ow + y * l.ow + x] = s + bias[b * oc + r];
                }
            }
        }
        assert!(got == want, "{co} channels: the dispatched tiles differ from the portable ones");
        // With an activation: applied to every output as it is written.
        let act = Activation { lo: -1.0, hi: 2.0, hard_swish: true };
        let mut with_act = vec![0f32; co * l.oh * l.ow];
        pack.run(&l, &padded, &bias, act, &mut with_act);
        act.apply_all(&mut want);
        assert!(with_act == want, "{co} channels: the activation differs");
        // And the sums are the convolution's (f64 reference).
        for o in [0, co - 1] {
            for (y, x) in [(0, 0), (l.oh - 1, l.ow - 1), (3, 7)] {
                let mut acc = bias[o] as f64;
                for (tap, &t) in l.taps.iter().enumerate() {
                    acc += padded[y * l.wp + x + t] as f64 * weight[o * taps + tap] as f64;
                }
                let g = got[o * l.oh * l.ow + y * l.ow + x];
                assert!((g as f64 - acc).abs() < 1e-3, "{co} channels, output {o} at ({y}, {x}): {g} against {acc}");
            }
        }
    }
}
