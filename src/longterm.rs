//! Long-term tracking figures, as VOT-LT defines them and pysot-toolkit computes them
//! (`toolkit/evaluation/f1_benchmark.py`, `toolkit/utils/statistics.py`): tracking precision,
//! recall and F-score over confidence thresholds, from the per-frame boxes and confidences of a
//! result and a ground truth that marks absent frames (NaN).
//!
//! Pr(t) is the mean overlap over the frames whose confidence is at least t (0 where the target
//! is absent: reporting it there costs precision); Re(t) is the sum of those overlaps over the
//! number of frames where the target is present. Dataset curves are the means of the videos'
//! curves; F = 2 Pr Re / (Pr + Re) on them, and the figures are read at the threshold of the
//! largest F. As in pysot, the first frame's confidence is NaN (it is the init box) and the
//! thresholds are 98 quantiles of every confidence of the dataset, plus -inf and +inf.
//!
//! One difference, stated: the overlap is the exact area ratio of the two boxes clipped to the
//! frame, where the VOT toolkit rasterises them on the pixel grid (the two differ by a fraction
//! of a boundary pixel's share).

/// The confidences `determine_thresholds(scores, 100)[::-1]` of pysot gives: `+inf`, 98
/// quantiles of the non-NaN `scores` from the highest, `-inf`. With fewer than 98 scores pysot
/// indexes out of range; here the quantile indices are clamped to the scores.
pub fn thresholds(scores: &[f64]) -> Vec<f64> {
    const RESOLUTION: usize = 100;
    let mut s: Vec<f64> = scores.iter().copied().filter(|v| !v.is_nan()).collect();
    s.sort_by(f64::total_cmp);
    let mut t = vec![f64::NEG_INFINITY];
    if !s.is_empty() {
        let n = s.len() as f64;
        let delta = (n / (RESOLUTION - 2) as f64).floor();
        let (a, b) = (delta - 1.0, n - delta);
        let steps = (RESOLUTION - 3) as f64;
        for i in 0..RESOLUTION - 2 {
            // np.linspace: the last point is exactly b.
            let x = if i == RESOLUTION - 3 { b } else { a + i as f64 * (b - a) / steps };
            let idx = (x + 0.5).floor().clamp(0.0, n - 1.0) as usize;
            t.push(s[idx]);
        }
    }
    t.push(f64::INFINITY);
    t.reverse();
    t
}

/// Overlap of a predicted and a ground-truth `x,y,w,h` box inside a `width` x `height` frame
/// (both clipped to it); NaN where the ground truth is absent (NaN, or no area), 0 for a
/// prediction with no area in the frame.
pub fn bounded_overlap(pred: [f64; 4], gt: [f64; 4], width: f64, height: f64) -> f64 {
    if gt.iter().any(|v| v.is_nan()) {
        return f64::NAN;
    }
    let clip = |b: [f64; 4]| {
        let (x0, y0) = (b[0].clamp(0.0, width), b[1].clamp(0.0, height));
        let (x1, y1) = ((b[0] + b[2]).clamp(0.0, width), (b[1] + b[3]).clamp(0.0, height));
        [x0, y0, x1, y1]
    };
    let (p, g) = (clip(pred), clip(gt));
    let area = |b: [f64; 4]| (b[2] - b[0]).max(0.0) * (b[3] - b[1]).max(0.0);
    if area(g) <= 0.0 {
        return f64::NAN;
    }
    let inter = area([p[0].max(g[0]), p[1].max(g[1]), p[2].min(g[2]), p[3].min(g[3])]);
    let union = area(p) + area(g) - inter;
    if union > 0.0 && inter.is_finite() {
        inter / union
    } else {
        0.0
    }
}

/// A video's precision and recall at each threshold.
#[derive(Debug, Clone, PartialEq)]
pub struct LtCurves {
    /// Tracking precision per threshold.
    pub precision: Vec<f64>,
    /// Tracking recall per threshold.
    pub recall: Vec<f64>,
}

/// Whether a ground-truth box marks the target present (pysot: not NaN).
pub fn present(gt: [f64; 4]) -> bool {
    !gt[0].is_nan()
}

/// pysot's `calculate_f1` for one video: `confidences[0]` (the init frame) is taken as NaN.
pub fn video_curves(
    gt: &[[f64; 4]],
    pred: &[[f64; 4]],
    confidences: &[f64],
    (width, height): (f64, f64),
    thresholds: &[f64],
) -> Result<LtCurves, String> {
    if pred.len() != gt.len() || confidences.len() != gt.len() {
        return Err(format!(
            "{} boxes and {} confidences for {} ground-truth frames",
            pred.len(),
            confidences.len(),
            gt.len()
        ));
    }
    let n_present = gt.iter().filter(|g| present(**g)).count() as f64;
    // NaN overlaps and NaN confidences count as 0, as in calculate_f1.
    let overlaps: Vec<f64> = gt
        .iter()
        .zip(pred)
        .map(|(g, p)| bounded_overlap(*p, *g, width, height))
        .map(|o| if o.is_nan() { 0.0 } else { o })
        .collect();
    let scores: Vec<f64> =
        confidences.iter().enumerate().map(|(i, &c)| if i == 0 || c.is_nan() { 0.0 } else { c }).collect();
    let (mut precision, mut recall) = (Vec::new(), Vec::new());
    for &t in thresholds {
        let chosen = |s: f64| if t == f64::NEG_INFINITY { s > 0.0 } else { s >= t };
        let (count, sum) = scores
            .iter()
            .zip(&overlaps)
            .filter(|(s, _)| chosen(**s))
            .fold((0usize, 0.0), |(c, sum), (_, o)| (c + 1, sum + o));
        if count == 0 {
            precision.push(1.0);
            recall.push(0.0);
        } else {
            precision.push(sum / count as f64);
            recall.push(sum / n_present);
        }
    }
    Ok(LtCurves { precision, recall })
}

/// A tracker's long-term figures on a dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct LtSummary {
    /// The thresholds, from the highest.
    pub thresholds: Vec<f64>,
    /// Mean precision over videos per threshold.
    pub precision: Vec<f64>,
    /// Mean recall over videos per threshold.
    pub recall: Vec<f64>,
    /// F-score per threshold (from the mean curves).
    pub f_score: Vec<f64>,
    /// Index of the threshold of the largest F (numpy's argmax: the first NaN if any).
    pub best: usize,
}

impl LtSummary {
    /// Precision, recall and F at the best threshold, and that threshold.
    pub fn at_best(&self) -> (f64, f64, f64, f64) {
        let i = self.best;
        (self.precision[i], self.recall[i], self.f_score[i], self.thresholds[i])
    }
}

/// pysot's `show_result` figures from the videos' curves (all made on `thresholds`).
pub fn summarise(thresholds: Vec<f64>, videos: &[LtCurves]) -> LtSummary {
    let avg = |f: fn(&LtCurves) -> &Vec<f64>| -> Vec<f64> {
        (0..thresholds.len()).map(|i| crate::ope::mean(&videos.iter().map(|c| f(c)[i]).collect::<Vec<_>>())).collect()
    };
    let precision = avg(|c| &c.precision);
    let recall = avg(|c| &c.recall);
    let f_score: Vec<f64> = precision.iter().zip(&recall).map(|(p, r)| 2.0 * p * r / (p + r)).collect();
    let best = match f_score.iter().position(|f| f.is_nan()) {
        Some(i) => i,
        None => (0..f_score.len()).fold(0, |b, i| if f_score[i] > f_score[b] { i } else { b }),
    };
    LtSummary { thresholds, precision, recall, f_score, best }
}

/// The confidences file written beside a result file `<video>.txt`: `<video>_confidence.value`
/// (VOT-LT's name), one value per frame.
pub fn confidence_path(results: &std::path::Path) -> std::path::PathBuf {
    let stem = results.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    results.with_file_name(format!("{stem}_confidence.value"))
}

/// Parse a confidences file: one number per line (`nan` allowed), `frames` of them.
pub fn parse_confidences(text: &str, frames: usize) -> Result<Vec<f64>, String> {
    let v: Vec<f64> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .enumerate()
        .map(|(i, l)| l.trim().parse::<f64>().map_err(|_| format!("line {}: `{}` is not a number", i + 1, l.trim())))
        .collect::<Result<_, _>>()?;
    if v.len() != frames {
        return Err(format!("{} confidences for {frames} frames", v.len()));
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thresholds_are_pysots_quantiles() {
        // 196 scores 0, 1, ..., 195: delta = 2, indices round(linspace(1, 194, 98)).
        let s: Vec<f64> = (0..196).rev().map(f64::from).collect();
        let t = thresholds(&s);
        assert_eq!(t.len(), 100);
        assert_eq!((t[0], t[99]), (f64::INFINITY, f64::NEG_INFINITY));
        assert_eq!((t[98], t[1]), (1.0, 194.0));
        // linspace(1, 194, 98)[1] = 1 + 193/97 = 2.9897...: rounds to 3.
        assert_eq!(t[97], 3.0);
        assert!(thresholds(&[f64::NAN, 0.5]).iter().all(|v| !v.is_nan()));
    }

    #[test]
    fn precision_recall_as_calculate_f1() {
        let gt = [[0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 10.0], [f64::NAN; 4], [0.0, 0.0, 10.0, 10.0]];
        let pred = [[0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 5.0], [50.0, 50.0, 10.0, 10.0], [30.0, 30.0, 5.0, 5.0]];
        let conf = [1.0, 0.9, 0.2, 0.5];
        let t = [f64::INFINITY, 0.9, 0.5, 0.1, f64::NEG_INFINITY];
        let c = video_curves(&gt, &pred, &conf, (100.0, 100.0), &t).unwrap();
        // inf: nothing chosen. 0.9: frame 1 (0.5). 0.5: frames 1, 3 (0.5, 0). 0.1 and -inf: 1, 2, 3.
        assert_eq!(c.precision, vec![1.0, 0.5, 0.25, 0.5 / 3.0, 0.5 / 3.0]);
        assert_eq!(c.recall, vec![0.0, 0.5 / 3.0, 0.5 / 3.0, 0.5 / 3.0, 0.5 / 3.0]);
        let s = summarise(t.to_vec(), &[c]);
        assert_eq!(s.best, 1);
        assert!((s.at_best().2 - 2.0 * 0.5 * (0.5 / 3.0) / (0.5 + 0.5 / 3.0)).abs() < 1e-15);
    }

    #[test]
    fn overlap_is_clipped_to_the_frame() {
        // Half of the prediction lies outside a 10x10 frame: clipped, it equals the truth.
        assert_eq!(bounded_overlap([5.0, 0.0, 10.0, 10.0], [5.0, 0.0, 5.0, 10.0], 10.0, 10.0), 1.0);
        assert!(bounded_overlap([0.0; 4], [f64::NAN; 4], 10.0, 10.0).is_nan());
        assert_eq!(bounded_overlap([20.0, 20.0, 5.0, 5.0], [0.0, 0.0, 5.0, 5.0], 10.0, 10.0), 0.0);
    }
}
