//! OpenCV's `resize(INTER_LINEAR)` on 8-bit images, bit for bit (as opencv-python computes it):
//! half-pixel centres, 11-bit fixed-point coefficients rounded half to even, horizontal pass into
//! i32 row buffers, vertical pass with OpenCV's SIMD rounding.

const COEF_SCALE: f32 = 2048.0;

/// Per destination index: the two source indices and their fixed-point weights.
struct Taps {
    idx: Vec<[usize; 2]>,
    w: Vec<[i32; 2]>,
}

fn round_half_even(v: f32) -> i32 {
    v.round_ties_even() as i32
}

/// Coefficients along one axis. `clamp_weights` is OpenCV's horizontal rule (weights forced to
/// (1, 0) past the borders); the vertical rule keeps fractional weights and clamps only indices.
fn taps(src: usize, dst: usize, clamp_weights: bool) -> Taps {
    let scale = 1.0 / (dst as f64 / src as f64);
    let last = src as i64 - 1;
    let mut idx = Vec::with_capacity(dst);
    let mut w = Vec::with_capacity(dst);
    for d in 0..dst {
        let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
        let mut s = f.floor() as i64;
        let mut f = f - s as f32;
        if clamp_weights {
            if s < 0 {
                f = 0.0;
                s = 0;
            }
            if s >= last {
                f = 0.0;
                s = last;
            }
        }
        let i0 = s.clamp(0, last) as usize;
        let i1 = (s + 1).clamp(0, last) as usize;
        idx.push([i0, i1]);
        w.push([round_half_even((1.0 - f) * COEF_SCALE), round_half_even(f * COEF_SCALE)]);
    }
    Taps { idx, w }
}

/// Resize an interleaved 8-bit image of `channels` channels from `sw`x`sh` to `dw`x`dh` exactly
/// as `cv2.resize(img, (dw, dh))` does.
pub fn resize_linear_u8(src: &[u8], sw: usize, sh: usize, channels: usize, dw: usize, dh: usize) -> Vec<u8> {
    assert_eq!(src.len(), sw * sh * channels, "source buffer size");
    let row_len = sw * channels;
    resize_linear_u8_rows(sw, sh, channels, dw, dh, |y, row| row.copy_from_slice(&src[y * row_len..(y + 1) * row_len]))
}

/// [`resize_linear_u8`] of an image that is never materialised: `fill_row(y, row)` writes source
/// row `y` (`sw * channels` bytes) when the resize needs it. Only the rows the output samples
/// are asked for (at most two per output row), so memory is one source row, not the image.
pub fn resize_linear_u8_rows(
    sw: usize,
    sh: usize,
    channels: usize,
    dw: usize,
    dh: usize,
    mut fill_row: impl FnMut(usize, &mut [u8]),
) -> Vec<u8> {
    let tx = taps(sw, dw, true);
    let ty = taps(sh, dh, false);
    let row_len = dw * channels;
    // Per output value of a row (column, channel): its two source offsets and weights.
    let (offs, ws): (Vec<[usize; 2]>, Vec<[i32; 2]>) = tx
        .idx
        .iter()
        .zip(&tx.w)
        .flat_map(|(i, w)| (0..channels).map(move |c| ([i[0] * channels + c, i[1] * channels + c], *w)))
        .unzip();
    let mut src_row = vec![0u8; sw * channels];
    // Horizontal pass for one source row, cached since consecutive output rows share rows.
    let mut hrow = |y: usize, out: &mut [i32]| {
        fill_row(y, &mut src_row);
        for ((o, off), w) in out.iter_mut().zip(&offs).zip(&ws) {
            *o = src_row[off[0]] as i32 * w[0] + src_row[off[1]] as i32 * w[1];
        }
    };
    let mut cache: [(usize, Vec<i32>); 2] = [(usize::MAX, vec![0; row_len]), (usize::MAX, vec![0; row_len])];
    let mut out = vec![0u8; dh * row_len];
    for ((iy, wy), dst) in ty.idx.iter().zip(&ty.w).zip(out.chunks_exact_mut(row_len.max(1))) {
        if cache[0].0 != iy[0] {
            if cache[1].0 == iy[0] {
                cache.swap(0, 1);
            } else {
                hrow(iy[0], &mut cache[0].1);
                cache[0].0 = iy[0];
            }
        }
        if cache[1].0 != iy[1] {
            hrow(iy[1], &mut cache[1].1);
            cache[1].0 = iy[1];
        }
        let (r0, r1) = (&cache[0].1, &cache[1].1);
        // Vertical pass (vectorised by the compiler: shifts, adds and a clamp on i32 lanes).
        for ((d, &a), &b) in dst.iter_mut().zip(r0).zip(r1) {
            let v = ((wy[0] * (a >> 4)) >> 16) + ((wy[1] * (b >> 4)) >> 16);
            *d = ((v + 2) >> 2).clamp(0, 255) as u8;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The straightforward form (one value at a time): what the fast one must equal.
    fn reference(src: &[u8], sw: usize, sh: usize, channels: usize, dw: usize, dh: usize) -> Vec<u8> {
        assert_eq!(src.len(), sw * sh * channels, "source buffer size");
        let tx = taps(sw, dw, true);
        let ty = taps(sh, dh, false);
        let row_len = dw * channels;
        // Horizontal pass for one source row, cached since consecutive output rows share rows.
        let hrow = |y: usize, out: &mut Vec<i32>| {
            out.clear();
            let row = &src[y * sw * channels..(y + 1) * sw * channels];
            for (i, wt) in tx.idx.iter().zip(&tx.w) {
                for c in 0..channels {
                    out.push(row[i[0] * channels + c] as i32 * wt[0] + row[i[1] * channels + c] as i32 * wt[1]);
                }
            }
        };
        let mut cache: [(usize, Vec<i32>); 2] = [(usize::MAX, Vec::new()), (usize::MAX, Vec::new())];
        let mut out = Vec::with_capacity(dh * row_len);
        for (iy, wy) in ty.idx.iter().zip(&ty.w) {
            if cache[0].0 != iy[0] {
                if cache[1].0 == iy[0] {
                    cache.swap(0, 1);
                } else {
                    hrow(iy[0], &mut cache[0].1);
                    cache[0].0 = iy[0];
                }
            }
            if cache[1].0 != iy[1] {
                hrow(iy[1], &mut cache[1].1);
                cache[1].0 = iy[1];
            }
            let (r0, r1) = (&cache[0].1, &cache[1].1);
            for x in 0..row_len {
                let v = ((wy[0] * (r0[x] >> 4)) >> 16) + ((wy[1] * (r1[x] >> 4)) >> 16);
                out.push(((v + 2) >> 2).clamp(0, 255) as u8);
            }
        }
        out
    }

    #[test]
    fn equals_the_straightforward_form() {
        for (sw, sh, c, dw, dh) in
            [(300, 290, 3, 255, 255), (611, 589, 3, 127, 127), (97, 53, 3, 287, 287), (40, 30, 1, 17, 61)]
        {
            let src: Vec<u8> = (0..sw * sh * c).map(|i| ((i * 7919 + i / 13) % 256) as u8).collect();
            assert_eq!(
                resize_linear_u8(&src, sw, sh, c, dw, dh),
                reference(&src, sw, sh, c, dw, dh),
                "{sw}x{sh} -> {dw}x{dh}"
            );
        }
    }

    #[test]
    fn identity_size_copies() {
        let src: Vec<u8> = (0..4 * 3 * 3).map(|i| (i * 7) as u8).collect();
        assert_eq!(resize_linear_u8(&src, 4, 3, 3, 4, 3), src);
    }

    #[test]
    fn upscale_of_a_constant_is_constant() {
        let src = vec![200u8; 5 * 5 * 3];
        assert!(resize_linear_u8(&src, 5, 5, 3, 9, 9).iter().all(|&v| v == 200));
    }
}
