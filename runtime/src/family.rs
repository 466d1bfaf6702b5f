//! What differs between tracker families: how the search graph's outputs become a box and a
//! score per cell of the score map. Everything else (crops, penalties, window, state update)
//! is the one loop in [`crate::Tracker`].

use crate::{Error, Family, Result, SearchOutput, TrackerConfig};

/// Boxes `[cx, cy, w, h]` in search-crop pixels relative to the crop centre, and scores, one per
/// cell (row-major over the score map), as the family's official code computes them.
pub(crate) type Decoded = (Vec<[f64; 4]>, Vec<f64>);

/// Decode `out` for `cfg.family`, after checking that its tensors fit the score map.
pub(crate) fn decode(cfg: &TrackerConfig, out: &SearchOutput) -> Result<Decoded> {
    let cells = cfg.score_size * cfg.score_size;
    let expected = cfg.family.search_outputs();
    let fits = out.outputs.len() == expected.len()
        && out.outputs.iter().zip(expected).all(|(t, (_, channels))| t.len() == channels * cells);
    if !fits {
        let got: Vec<String> = out.outputs.iter().map(|t| t.len().to_string()).collect();
        let want: Vec<String> = expected.iter().map(|(n, c)| format!("{n} {}", c * cells)).collect();
        return Err(Error::Input(format!(
            "search outputs of {} values do not fit {}'s {}x{} score map (expected {})",
            got.join("/"),
            cfg.family.name(),
            cfg.score_size,
            cfg.score_size,
            want.join(", ")
        )));
    }
    let o = &out.outputs;
    Ok(match cfg.family {
        Family::PrlTrack => prl_track(cfg, &o[0], &o[1], &o[2]),
        Family::Nanotrack => nanotrack(cfg, &o[0], &o[1]),
    })
}

/// `softmax([c0, c1])[1]` in float32, as torch computes it.
fn softmax1(c0: f32, c1: f32) -> f32 {
    let m = c0.max(c1);
    let (e0, e1) = ((c0 - m).exp(), (c1 - m).exp());
    e1 / (e0 + e1)
}

/// The official `PRLTrack.generate_anchor` and score lines.
fn prl_track(cfg: &TrackerConfig, loc: &[f32], cls1: &[f32], cls2: &[f32]) -> Decoded {
    let n = cfg.score_size;
    let cells = n * n;
    let scale = cfg.loc_scale as f32;
    // dcon: values <= -1 become -0.99, >= 1 become 0.99 (others, even beyond ±0.99, stay); atanh
    // in float32 as numpy computes it on the float32 map.
    let dcon = |v: f32| -> f32 {
        let v = if v <= -1.0 {
            -0.99f32
        } else if v >= 1.0 {
            0.99f32
        } else {
            v
        };
        ((1.0 + v).ln() - (1.0 - v).ln()) / 2.0 * scale
    };
    let mut pred = Vec::with_capacity(cells);
    let mut score = Vec::with_capacity(cells);
    for i in 0..cells {
        let (row, col) = (i / n, i % n);
        let ax = (cfg.stride * col) as f64 + cfg.grid_origin;
        let ay = (cfg.stride * row) as f64 + cfg.grid_origin;
        // Sizes are float32 sums, as numpy adds the float32 map.
        let d: [f32; 4] = std::array::from_fn(|k| dcon(loc[k * cells + i]));
        let (w, h) = ((d[0] + d[1]) as f64, (d[2] + d[3]) as f64);
        let (wh, hh) = (((d[0] + d[1]) / 2.0) as f64, ((d[2] + d[3]) / 2.0) as f64);
        pred.push([ax - d[0] as f64 + wh, ay - d[2] as f64 + hh, w, h]);
        // Scores in float32 too: softmax(cls1)[1] * w2 plus the raw cls2 logit * w3, halved.
        let s1 = softmax1(cls1[i], cls1[cells + i]);
        score.push(((s1 * cfg.w2 as f32 + cls2[i] * cfg.w3 as f32) / 2.0) as f64);
    }
    (pred, score)
}

/// The official `NanoTracker._convert_bbox` (points, then `corner2center`) and
/// `_convert_score`, in float32 as numpy and torch compute them.
fn nanotrack(cfg: &TrackerConfig, cls: &[f32], loc: &[f32]) -> Decoded {
    let n = cfg.score_size;
    let cells = n * n;
    let mut pred = Vec::with_capacity(cells);
    let mut score = Vec::with_capacity(cells);
    for i in 0..cells {
        let (row, col) = (i / n, i % n);
        let px = (cfg.grid_origin + (cfg.stride * col) as f64) as f32;
        let py = (cfg.grid_origin + (cfg.stride * row) as f64) as f32;
        let [l, t, r, b]: [f32; 4] = std::array::from_fn(|k| loc[k * cells + i]);
        let (x1, y1, x2, y2) = (px - l, py - t, px + r, py + b);
        let c = [(x1 + x2) * 0.5, (y1 + y2) * 0.5, x2 - x1, y2 - y1];
        pred.push(c.map(f64::from));
        score.push(softmax1(cls[i], cls[cells + i]) as f64);
    }
    (pred, score)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn out(v: Vec<Vec<f32>>) -> SearchOutput {
        SearchOutput { outputs: v }
    }

    #[test]
    fn prl_centre_cell_with_zero_regression() {
        let cfg = TrackerConfig::prl_track();
        let cells = 121;
        let (pred, score) =
            decode(&cfg, &out(vec![vec![0.0; 4 * cells], vec![0.0; 2 * cells], vec![0.4; cells]])).unwrap();
        // Centre cell (5,5): anchor 16*5 + 63 - 143 = 0; zero sizes.
        assert_eq!(pred[60], [0.0, 0.0, 0.0, 0.0]);
        assert_eq!(pred[0][..2], [-80.0, -80.0]);
        assert_eq!(score[0], ((0.5f32 + 0.4f32) / 2.0) as f64);
    }

    #[test]
    fn nanotrack_points_are_not_centred() {
        let cfg = TrackerConfig::nanotrack();
        let cells = 256;
        // l, t, r, b = 10, 20, 30, 40 everywhere; cls favours channel 1.
        let mut loc = vec![0.0; 4 * cells];
        for (k, v) in [10.0, 20.0, 30.0, 40.0].into_iter().enumerate() {
            loc[k * cells..(k + 1) * cells].fill(v);
        }
        let mut cls = vec![0.0; 2 * cells];
        cls[cells..].fill(2.0);
        let (pred, score) = decode(&cfg, &out(vec![cls, loc])).unwrap();
        // Cell (0, 0) at (-128, -128); box x1 = -138, x2 = -98 -> cx -118, w 40; y1 -148, y2 -88.
        assert_eq!(pred[0], [-118.0, -118.0, 40.0, 60.0]);
        // Cell (15, 15) at (112, 112).
        assert_eq!(pred[255][..2], [122.0, 122.0]);
        assert!((score[7] - 1.0 / (1.0 + (-2.0f64).exp())).abs() < 1e-6);
    }

    #[test]
    fn outputs_that_do_not_fit_are_errors() {
        let cfg = TrackerConfig::nanotrack();
        let e = decode(&cfg, &out(vec![vec![0.0; 2 * 121], vec![0.0; 4 * 121]])).unwrap_err();
        assert!(e.to_string().contains("16x16"), "{e}");
    }
}
