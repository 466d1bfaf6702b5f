//! Box overlap, as the OPE toolkit measures it.

/// IoU of two `x,y,w,h` boxes, without the +1 pixel convention, clamped to [0, 1].
pub fn iou(a: [f64; 4], b: [f64; 4]) -> f64 {
    let ix = (a[0] + a[2]).min(b[0] + b[2]) - a[0].max(b[0]);
    let iy = (a[1] + a[3]).min(b[1] + b[3]) - a[1].max(b[1]);
    let inter = ix.max(0.0) * iy.max(0.0);
    let union = a[2] * a[3] + b[2] * b[3] - inter;
    if union > 0.0 {
        (inter / union).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::iou;

    #[test]
    fn overlaps() {
        assert_eq!(iou([0., 0., 10., 10.], [0., 0., 10., 10.]), 1.0);
        assert_eq!(iou([0., 0., 10., 10.], [5., 0., 10., 10.]), 50.0 / 150.0);
        assert_eq!(iou([0., 0., 10., 10.], [20., 20., 5., 5.]), 0.0);
    }
}
