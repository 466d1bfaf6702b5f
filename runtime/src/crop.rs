//! The official `get_subwindow`: a square crop around a centre, padded with the sequence's
//! channel average, resized to the network's input size, as float NCHW BGR.

use crate::{resize_linear_u8, Frame};

/// Cut the `original_sz`x`original_sz` window centred on `center` out of `frame` (padding outside
/// with `avg`, truncated to u8 as numpy stores it) and resize it to `model_sz`x`model_sz` (no
/// resize when equal). Returns interleaved BGR bytes, `model_sz` rows.
pub fn get_subwindow(frame: &Frame, center: (f64, f64), model_sz: usize, original_sz: usize, avg: [f64; 3]) -> Vec<u8> {
    let sz = original_sz as i64;
    let c = (original_sz as f64 + 1.0) / 2.0;
    let xmin = (center.0 - c + 0.5).floor() as i64;
    let ymin = (center.1 - c + 0.5).floor() as i64;
    let (w, h) = (frame.width() as i64, frame.height() as i64);
    let pad = avg.map(|v| v as u8);
    let src = frame.bgr();
    let mut patch = Vec::with_capacity(original_sz * original_sz * 3);
    for y in ymin..ymin + sz {
        for x in xmin..xmin + sz {
            if (0..w).contains(&x) && (0..h).contains(&y) {
                let at = ((y * w + x) * 3) as usize;
                patch.extend_from_slice(&src[at..at + 3]);
            } else {
                patch.extend_from_slice(&pad);
            }
        }
    }
    if model_sz == original_sz {
        patch
    } else {
        resize_linear_u8(&patch, original_sz, original_sz, 3, model_sz, model_sz)
    }
}

/// Interleaved BGR bytes of a `side`x`side` crop as the network's float NCHW input.
pub fn crop_to_tensor(crop: &[u8], side: usize) -> Vec<f32> {
    let plane = side * side;
    let mut out = vec![0f32; 3 * plane];
    for (i, p) in crop.chunks_exact(3).enumerate() {
        for c in 0..3 {
            out[c * plane + i] = p[c] as f32;
        }
    }
    out
}
