//! Calibration crops for the int8 quantiser: what the network really sees while tracking. Each
//! sequence's template comes from its first ground-truth box, cut as `init` cuts it; its search
//! crops come from frames spread over the sequence, cut by the runtime's own crop code around the
//! ground truth moved and rescaled by the kind of error tracking makes.

use std::path::PathBuf;

use prl_compiler::{Calibration, Tensor};
use prl_runtime::{CalibrationInfo, Cropper, TrackerConfig};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::{init_box_from_groundtruth, load_frame, InputError, Sequence};

/// Standard deviation of the crop centre's offset, as a share of the target's width and height.
pub const POSITION_JITTER: f64 = 0.1;
/// Standard deviation of the log of the target size's scale factor.
pub const SCALE_JITTER: f64 = 0.1;

/// Which crops to cut.
#[derive(Debug, Clone)]
pub struct CalibrationSpec {
    /// Sequence folders (OTB/UAV123 layout, with ground truth).
    pub sequences: Vec<PathBuf>,
    /// Search crops per sequence, from frames spread evenly after the first.
    pub frames_per_sequence: usize,
    /// Templates per sequence: the first frame's, as tracking uses, and more from frames spread
    /// over the sequence, so that ranges cover targets that look otherwise (the search crops of
    /// a sequence take them in turn). 1 gives exactly what tracking sees.
    pub templates_per_sequence: usize,
    /// Seed of the jitter.
    pub seed: u64,
    /// Take the frames half-way between those a calibration with the same count takes: crops
    /// held out from calibration, for measuring.
    pub held_out: bool,
}

/// `n` frames after the first, evenly spread over `1..len` (shifted half a step when
/// `held_out`, so that they fall between the calibration frames).
fn spread(len: usize, n: usize, held_out: bool) -> Vec<usize> {
    let avail = len.saturating_sub(1);
    if n >= avail {
        return (1..len).collect();
    }
    let half = if held_out { avail / (2 * n) } else { 0 };
    (0..n).map(|i| 1 + i * avail / n + half).collect()
}

/// Cut the calibration crops of `spec` with the tracker settings `config`. `progress(done,
/// total)` is called after each frame.
pub fn calibration_crops(
    spec: &CalibrationSpec,
    config: &TrackerConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Calibration, InputError> {
    let cropper = Cropper::new(config);
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let normal = Normal::new(0.0, 1.0).expect("unit normal");
    let mut calib = Calibration::default();
    let total = spec.sequences.len() * spec.frames_per_sequence;
    let mut names = vec![];
    for dir in &spec.sequences {
        let seq = Sequence::open(dir)?;
        let gt = seq.groundtruth().ok_or_else(|| InputError::new(dir, "no ground truth to calibrate along"))?;
        let gt_file = dir.join("groundtruth_rect.txt");
        let first = load_frame(&seq.frames[0])?;
        let template = cropper
            .template(&first, init_box_from_groundtruth(gt[0]))
            .map_err(|e| InputError::new(&gt_file, format!("first box: {e}")))?;
        let side = config.exemplar_size;
        let first_template = calib.templates.len();
        calib.templates.push(Tensor::new([1, 3, side, side], template.z.clone()));
        for k in spread(seq.frames.len(), spec.templates_per_sequence.saturating_sub(1), false) {
            let b = gt[k];
            if b.iter().all(|v| v.is_finite()) && b[2] > 0.0 && b[3] > 0.0 {
                let frame = load_frame(&seq.frames[k])?;
                let z = cropper
                    .template(&frame, init_box_from_groundtruth(b))
                    .map_err(|e| InputError::new(&gt_file, format!("box {}: {e}", k + 1)))?;
                calib.templates.push(Tensor::new([1, 3, side, side], z.z));
            }
        }
        let templates = calib.templates.len() - first_template;
        for (j, i) in spread(seq.frames.len(), spec.frames_per_sequence, spec.held_out).into_iter().enumerate() {
            let t = first_template + j % templates;
            let [x, y, w, h] = gt[i];
            progress(calib.searches.len(), total);
            if !(x.is_finite() && y.is_finite() && w > 0.0 && h > 0.0) {
                continue; // the target is absent: tracking would not be looking at it either
            }
            let frame = load_frame(&seq.frames[i])?;
            let scale = (SCALE_JITTER * normal.sample(&mut rng)).exp();
            let center = (
                x + w / 2.0 + POSITION_JITTER * w * normal.sample(&mut rng),
                y + h / 2.0 + POSITION_JITTER * h * normal.sample(&mut rng),
            );
            let x = cropper.search(&frame, center, (w * scale, h * scale), &template);
            calib.searches.push((t, Tensor::new([1, 3, config.instance_size, config.instance_size], x)));
        }
        names.push(seq.name.clone());
    }
    progress(total, total);
    calib.info =
        CalibrationInfo {
            sequences: names,
            sampling: format!(
            "{} template(s) per sequence (its first ground-truth box, then boxes spread over it); {} search crops per \
             sequence from frames spread evenly after the first, taking the templates in turn, centred on the ground \
             truth moved by N(0, {POSITION_JITTER}) of its size and scaled by exp(N(0, {SCALE_JITTER})), seed {}",
            spec.templates_per_sequence.max(1), spec.frames_per_sequence, spec.seed
        ),
            ..Default::default()
        };
    Ok(calib)
}

#[cfg(test)]
mod tests {
    #[test]
    fn frames_are_spread_after_the_first() {
        assert_eq!(super::spread(11, 5, false), vec![1, 3, 5, 7, 9]);
        assert_eq!(super::spread(11, 5, true), vec![2, 4, 6, 8, 10]);
        assert_eq!(super::spread(4, 10, false), vec![1, 2, 3]);
        assert_eq!(super::spread(1, 3, false), Vec::<usize>::new());
    }
}
