//! One-pass evaluation (OPE) exactly as pysot-toolkit computes it (`toolkit/utils/statistics.py`,
//! `toolkit/evaluation/ope_benchmark.py` of the official repository), quirks included:
//!
//! - success: IoU of `x,y,w,h` boxes without the +1 convention, clamped to [0, 1]; a frame whose
//!   ground-truth w or h is not > 0 (or NaN) gets IoU -1, a miss at every threshold; thresholds
//!   `np.arange(0, 1.05, 0.05)`, a frame counts when `iou > t`; the AUC is the mean over the 21
//!   thresholds;
//! - precision: centres `x + (w-1)/2`, `y + (h-1)/2`; a frame whose ground-truth centre has a
//!   coordinate not > 0 (or NaN) gets distance -1, which counts as a **hit** at every threshold
//!   (pysot's quirk, kept so that the numbers equal the published ones); thresholds 0..=50 px,
//!   `dist <= t`, reported at 20 px;
//! - normalised precision: the same on centres divided by the ground-truth w,h (+1e-16),
//!   thresholds 0..=0.5 by 0.01, reported at 0.2;
//! - every rate is divided by the number of ground-truth frames; NaN in a result is a miss;
//!   dataset figures are unweighted means over videos.

/// Overlap thresholds of the success plot (`np.arange(0, 1.05, 0.05)`: 21 values).
pub fn success_thresholds() -> Vec<f64> {
    (0..21).map(|i| i as f64 * 0.05).collect()
}

/// Pixel thresholds of the precision plot (0..=50).
pub fn precision_thresholds() -> Vec<f64> {
    (0..=50).map(f64::from).collect()
}

/// Thresholds of the normalised precision plot (`np.arange(0, 51, 1) / 100`).
pub fn norm_precision_thresholds() -> Vec<f64> {
    (0..=50).map(|i| f64::from(i) / 100.0).collect()
}

/// Index of the reported point of the precision curves (20 px; 0.2 normalised).
pub const PRECISION_INDEX: usize = 20;

/// One video's OPE curves.
#[derive(Debug, Clone, PartialEq)]
pub struct Curves {
    /// Success rate at each of [`success_thresholds`].
    pub success: Vec<f64>,
    /// Precision at each of [`precision_thresholds`].
    pub precision: Vec<f64>,
    /// Normalised precision at each of [`norm_precision_thresholds`].
    pub norm_precision: Vec<f64>,
}

impl Curves {
    /// Success AUC: the mean of the success curve.
    pub fn auc(&self) -> f64 {
        mean(&self.success)
    }
    /// Precision at 20 px.
    pub fn precision_at_20(&self) -> f64 {
        self.precision[PRECISION_INDEX]
    }
    /// Normalised precision at 0.2.
    pub fn norm_precision_at_02(&self) -> f64 {
        self.norm_precision[PRECISION_INDEX]
    }
}

/// numpy's `maximum` / `minimum`: NaN if either side is NaN.
fn nan_max(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() {
        f64::NAN
    } else {
        a.max(b)
    }
}
fn nan_min(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() {
        f64::NAN
    } else {
        a.min(b)
    }
}

/// pysot's `overlap_ratio` of one pair of `x,y,w,h` boxes (NaN propagates).
pub fn overlap_ratio(a: [f64; 4], b: [f64; 4]) -> f64 {
    let left = nan_max(a[0], b[0]);
    let right = nan_min(a[0] + a[2], b[0] + b[2]);
    let top = nan_max(a[1], b[1]);
    let bottom = nan_min(a[1] + a[3], b[1] + b[3]);
    let intersect = nan_max(0.0, right - left) * nan_max(0.0, bottom - top);
    let union = a[2] * a[3] + b[2] * b[3] - intersect;
    nan_max(nan_min(1.0, intersect / union), 0.0)
}

/// Per-frame IoU as pysot's `success_overlap` sees it (-1 where the ground truth has no size).
pub fn frame_overlaps(gt: &[[f64; 4]], result: &[[f64; 4]]) -> Vec<f64> {
    gt.iter().zip(result).map(|(g, r)| if g[2] > 0.0 && g[3] > 0.0 { overlap_ratio(*g, *r) } else { -1.0 }).collect()
}

fn center(b: [f64; 4]) -> [f64; 2] {
    [b[0] + (b[2] - 1.0) / 2.0, b[1] + (b[3] - 1.0) / 2.0]
}

/// pysot's `success_error`: the share of frames with `dist <= t` for each threshold, distances
/// -1 where the ground-truth centre is not > 0 on both axes.
fn success_error(gt: &[[f64; 2]], result: &[[f64; 2]], thresholds: &[f64], n_frame: usize) -> Vec<f64> {
    let dist: Vec<f64> = gt
        .iter()
        .zip(result)
        .map(|(g, r)| {
            if g[0] > 0.0 && g[1] > 0.0 {
                let (dx, dy) = (g[0] - r[0], g[1] - r[1]);
                (dx * dx + dy * dy).sqrt()
            } else {
                -1.0
            }
        })
        .collect();
    thresholds.iter().map(|&t| dist.iter().filter(|&&d| d <= t).count() as f64 / n_frame as f64).collect()
}

/// The OPE curves of one video: `result` must hold one box per ground-truth frame.
pub fn evaluate(gt: &[[f64; 4]], result: &[[f64; 4]]) -> Result<Curves, String> {
    if result.len() != gt.len() {
        return Err(format!("{} result boxes for {} ground-truth frames", result.len(), gt.len()));
    }
    let n = gt.len().max(1);
    let iou = frame_overlaps(gt, result);
    let success =
        success_thresholds().iter().map(|&t| iou.iter().filter(|&&v| v > t).count() as f64 / n as f64).collect();
    let gc: Vec<[f64; 2]> = gt.iter().map(|b| center(*b)).collect();
    let rc: Vec<[f64; 2]> = result.iter().map(|b| center(*b)).collect();
    let precision = success_error(&gc, &rc, &precision_thresholds(), n);
    let norm = |c: &[[f64; 2]]| -> Vec<[f64; 2]> {
        c.iter().zip(gt).map(|(c, g)| [c[0] / (g[2] + 1e-16), c[1] / (g[3] + 1e-16)]).collect()
    };
    let norm_precision = success_error(&norm(&gc), &norm(&rc), &norm_precision_thresholds(), n);
    Ok(Curves { success, precision, norm_precision })
}

/// The mean of `v` (0 for an empty slice).
pub fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// A tracker's dataset figures: unweighted means over videos, as `show_result` prints them.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Mean success curve over videos.
    pub success: Vec<f64>,
    /// Mean precision curve over videos.
    pub precision: Vec<f64>,
    /// Mean normalised precision curve over videos.
    pub norm_precision: Vec<f64>,
    /// Success AUC (the mean of every video's success curve).
    pub auc: f64,
    /// Mean precision at 20 px.
    pub precision_at_20: f64,
    /// Mean normalised precision at 0.2.
    pub norm_precision_at_02: f64,
}

/// Average the curves of several videos.
pub fn summarise<'a>(videos: impl IntoIterator<Item = &'a Curves>) -> Summary {
    let videos: Vec<&Curves> = videos.into_iter().collect();
    let avg = |f: fn(&Curves) -> &Vec<f64>, len: usize| -> Vec<f64> {
        (0..len).map(|i| mean(&videos.iter().map(|c| f(c)[i]).collect::<Vec<_>>())).collect()
    };
    let success = avg(|c| &c.success, 21);
    let precision = avg(|c| &c.precision, 51);
    let norm_precision = avg(|c| &c.norm_precision, 51);
    Summary {
        auc: mean(&success),
        precision_at_20: precision[PRECISION_INDEX],
        norm_precision_at_02: norm_precision[PRECISION_INDEX],
        success,
        precision,
        norm_precision,
    }
}
