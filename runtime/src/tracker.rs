//! The official Siamese tracking loop, to the number: crops, decoding of the score map (per
//! family, [`crate::family`]), scale/aspect penalties, cosine window, smoothing. It is PRL-Track's
//! `PRLTrack` and NanoTrack's `NanoTracker` at once: where their code differs, a setting of
//! [`TrackerConfig`] says which way (grid origin, penalty `eps`, the large-target crop rule).

use std::time::{Duration, Instant};

use crate::{
    Cropper, Error, Frame, LongTermConfig, Plan, Result, SearchOutput, StateSignal, TemplateCrop, TemplateFeatures,
    TrackerConfig,
};

/// An axis-aligned box: top-left corner and size, 0-based float pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BBox {
    /// Left edge.
    pub x: f64,
    /// Top edge.
    pub y: f64,
    /// Width.
    pub w: f64,
    /// Height.
    pub h: f64,
}

impl std::fmt::Display for BBox {
    /// `x,y,w,h`, each number in its shortest exact form (as `--init` takes it).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{},{},{},{}", self.x, self.y, self.w, self.h)
    }
}

/// How sure the tracker is that it still follows the target: its confidence (the plan's
/// [`StateSignal`]) against the thresholds of the plan's settings
/// ([`TrackerConfig::state_rule`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TargetState {
    /// The confidence is at or above `uncertain_below`.
    Tracking,
    /// Below `uncertain_below`, at or above `lost_below`.
    Uncertain,
    /// Below `lost_below` (or NaN): the box is not to be trusted.
    Lost,
}

impl TargetState {
    /// The state of a prediction of confidence `c` under `uncertain_below` and `lost_below`.
    pub fn of(c: f64, uncertain_below: f64, lost_below: f64) -> TargetState {
        if c >= uncertain_below {
            TargetState::Tracking
        } else if c >= lost_below {
            TargetState::Uncertain
        } else {
            TargetState::Lost
        }
    }

    /// `tracking`, `uncertain` or `lost`.
    pub fn name(self) -> &'static str {
        match self {
            TargetState::Tracking => "tracking",
            TargetState::Uncertain => "uncertain",
            TargetState::Lost => "lost",
        }
    }
}

impl std::fmt::Display for TargetState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What the tracker says about a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prediction {
    /// The target's box.
    pub bbox: BBox,
    /// The score of the chosen cell (`best_score` of the official tracker; not a probability).
    pub score: f64,
    /// The value of the plan's [`StateSignal`] the state is decided on (higher is surer).
    pub confidence: f64,
    /// Whether the target is followed.
    pub state: TargetState,
}

/// The confidence of a score map whose chosen cell is `best` under `signal`.
pub fn confidence(signal: StateSignal, score: &[f64], best: usize) -> f64 {
    match signal {
        StateSignal::BestScore => score[best],
        StateSignal::MapFocus => 1.0 - score.iter().sum::<f64>() / score.len() as f64,
    }
}

struct State {
    center: (f64, f64),
    size: (f64, f64),
    /// Long-term mode: the target counts as lost and the larger region is searched.
    redetecting: bool,
    /// The template crop's padding colour and window side, which every search crop reuses.
    template: TemplateCrop,
    features: TemplateFeatures,
}

/// The long-term mode's settings, read once, and the cosine window over its larger region
/// (crop-major: crop 0's cells, then crop 1's...).
struct LongTerm {
    rule: LongTermConfig,
    window: Vec<f64>,
}

/// Where the time of the last `init` or `track` call went.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepTimings {
    /// Cutting and resizing the crop, to the network's input tensor.
    pub crop: Duration,
    /// Running the template or search graph.
    pub network: Duration,
    /// Decoding, penalties, window and state update.
    pub post: Duration,
}

/// A single-target tracker running a [`Plan`].
pub struct Tracker {
    plan: Plan,
    config: TrackerConfig,
    cropper: Cropper,
    window: Vec<f64>,
    /// Long-term mode ([`Tracker::set_long_term`]).
    long_term: Option<LongTerm>,
    /// Threads the long-term mode's region crops are searched on ([`Tracker::set_region_threads`]).
    region_threads: usize,
    state: Option<State>,
    timings: StepTimings,
}

/// Python's `min(a, b)`: `a` unless `b < a` (so a NaN `a` stays, a NaN `b` is ignored).
fn py_min(a: f64, b: f64) -> f64 {
    if b < a {
        b
    } else {
        a
    }
}

/// Python's `max(a, b)`: `a` unless `b > a`.
fn py_max(a: f64, b: f64) -> f64 {
    if b > a {
        b
    } else {
        a
    }
}

/// `np.hanning(n)`.
fn hanning(n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![1.0];
    }
    (0..n).map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / (n - 1) as f64).cos()).collect()
}

/// `np.argmax`: the first NaN if there is one, else the first maximum.
fn argmax(v: &[f64]) -> usize {
    if let Some(i) = v.iter().position(|x| x.is_nan()) {
        return i;
    }
    let mut best = 0;
    for (i, &x) in v.iter().enumerate() {
        if x > v[best] {
            best = i;
        }
    }
    best
}

impl Tracker {
    /// A tracker running `plan` with `config` (usually `plan.manifest().tracker`).
    pub fn new(plan: Plan, config: TrackerConfig) -> Self {
        let h = hanning(config.score_size);
        let window = h.iter().flat_map(|a| h.iter().map(move |b| a * b)).collect();
        let cropper = Cropper::new(&config);
        let timings = StepTimings::default();
        Tracker { plan, cropper, config, window, long_term: None, region_threads: 1, state: None, timings }
    }

    /// Threads the long-term mode searches its region's crops on. 1 (the default): one after
    /// another on the calling thread, the network on the threads of [`crate::set_threads`];
    /// `n` > 1: `n` threads side by side, each running its share of the crops with the network
    /// on its own thread (the crops are independent: on small networks this scales better).
    pub fn set_region_threads(&mut self, n: usize) {
        self.region_threads = n.max(1);
    }

    /// Turn the long-term mode on or off (off: the official short-term tracker, to the number).
    /// On, it is pysot's long-term scheme (`SiamRPNLTTracker`) on the plan's confidence: when the
    /// confidence falls below `long_term.lost_below` the box stays where it was and the
    /// following frames search a region of `tiles` x `tiles` search crops around it, with the
    /// cosine window almost off, until the confidence reaches `long_term.found_above`.
    pub fn set_long_term(&mut self, on: bool) {
        self.long_term = on.then(|| {
            let rule = self.config.long_term_rule();
            let (k, n) = (rule.tiles, self.config.score_size);
            let h = hanning(k * n);
            let at = |tile: usize, cell: usize| h[tile * n + cell];
            let window = (0..k * k)
                .flat_map(|t| (0..n * n).map(move |c| (t, c)))
                .map(|(t, c)| at(t / k, c / n) * at(t % k, c % n))
                .collect();
            LongTerm { rule, window }
        });
        if let Some(st) = self.state.as_mut() {
            st.redetecting = false;
        }
    }

    /// Whether the long-term mode is searching its larger region (the target counted as lost).
    pub fn redetecting(&self) -> bool {
        self.state.as_ref().is_some_and(|s| s.redetecting)
    }

    /// Where the time of the last `init` or `track` went.
    pub fn last_timings(&self) -> StepTimings {
        self.timings
    }

    /// The plan being run.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The current target's template features (`None` before `init`).
    pub fn features(&self) -> Option<&TemplateFeatures> {
        self.state.as_ref().map(|s| &s.features)
    }

    /// The template graph's input for a target in `bbox` on `frame`, exactly as [`Tracker::init`]
    /// cuts it (float NCHW BGR, `[1, 3, exemplar_size, exemplar_size]`).
    pub fn exemplar_crop(&self, frame: &Frame, bbox: BBox) -> Result<Vec<f32>> {
        Ok(self.cropper.template(frame, bbox)?.z)
    }

    /// Start tracking the target in `bbox` (x, y, w, h) on `frame`.
    pub fn init(&mut self, frame: &Frame, bbox: BBox) -> Result<()> {
        let t0 = Instant::now();
        let template = self.cropper.template(frame, bbox)?;
        let t1 = Instant::now();
        let features = self.plan.template(&template.z)?;
        self.timings = StepTimings { crop: t1 - t0, network: t1.elapsed(), post: Duration::ZERO };
        self.state =
            Some(State { center: template.center, size: template.size, redetecting: false, template, features });
        Ok(())
    }

    /// Locate the target in the next frame.
    pub fn track(&mut self, frame: &Frame) -> Result<Prediction> {
        if self.redetecting() {
            return self.redetect(frame);
        }
        let t0 = Instant::now();
        let st = self.tracked()?;
        let x = self.cropper.search_input(frame, st.center, st.size, &st.template)?;
        let t1 = Instant::now();
        let out = self.plan.search_input(x, &st.features)?;
        let t2 = Instant::now();
        let prediction = self.update(frame.width(), frame.height(), &out)?;
        self.timings = StepTimings { crop: t1 - t0, network: t2 - t1, post: t2.elapsed() };
        Ok(prediction)
    }

    /// The long-term mode's step while the target is lost: every crop of the larger region,
    /// each through the search graph, then one decision over all their cells.
    fn redetect(&mut self, frame: &Frame) -> Result<Prediction> {
        let st = self.state.as_ref().expect("redetecting implies init");
        let cfg = &self.config;
        let k = self.long_term.as_ref().expect("redetecting implies the long-term mode").rule.tiles as f64;
        let scale_z = cfg.exemplar_size as f64
            / self.cropper.search_context(st.size, frame.width(), frame.height(), &st.template);
        let span = (cfg.score_size * cfg.stride) as f64;
        let t0 = Instant::now();
        let (mut crops, mut offsets) = (Vec::new(), Vec::new());
        for i in 0..(k * k) as usize {
            // Crop (row, col)'s centre, in search-crop pixels from the target's, then in frame pixels.
            let (row, col) = ((i / k as usize) as f64, (i % k as usize) as f64);
            let offset = ((col - (k - 1.0) / 2.0) * span, (row - (k - 1.0) / 2.0) * span);
            let center = (st.center.0 + offset.0 / scale_z, st.center.1 + offset.1 / scale_z);
            crops.push(self.cropper.search(frame, center, st.size, &st.template));
            offsets.push(offset);
        }
        let t1 = Instant::now();
        let (plan, zf, one) = (&self.plan, &st.features, crate::Threads::new(1));
        // With region threads: side by side, each crop's network on one thread; else one after
        // another, the network on set_threads' threads.
        let outs: Vec<SearchOutput> = if self.region_threads > 1 {
            crate::spread(&mut crops, self.region_threads, |_, x| one.run(|| plan.search(x, zf)))
        } else {
            crops.iter().map(|x| plan.search(x, zf)).collect()
        }
        .into_iter()
        .collect::<Result<_>>()?;
        let (crop, network) = (t1 - t0, t1.elapsed());
        let t2 = Instant::now();
        let tiles: Vec<(&SearchOutput, (f64, f64))> = outs.iter().zip(offsets).collect();
        let prediction = self.decide(frame.width(), frame.height(), &tiles)?;
        self.timings = StepTimings { crop, network, post: t2.elapsed() };
        Ok(prediction)
    }

    /// The search graph's input for `frame` around the current target, as the official
    /// `track` cuts it (float NCHW BGR).
    pub fn search_crop(&self, frame: &Frame) -> Result<Vec<f32>> {
        let st = self.tracked()?;
        Ok(self.cropper.search(frame, st.center, st.size, &st.template))
    }

    /// The target's state, or the error for tracking before `init`.
    fn tracked(&self) -> Result<&State> {
        self.state.as_ref().ok_or_else(|| Error::Input("track called before init".into()))
    }

    /// The cell of the score map `update` would pick for `out` from the current state (the
    /// argmax of the penalised, windowed score), without changing the state: for comparing two
    /// networks' outputs on the same crop.
    pub fn best_cell(&self, frame_w: usize, frame_h: usize, out: &SearchOutput) -> Result<usize> {
        Ok(argmax(&self.cells(frame_w, frame_h, &[(out, (0.0, 0.0))])?.pscore))
    }

    /// Decoded boxes, scores, penalties and penalised scores of every cell of the search outputs
    /// `tiles`, each with its crop's centre offset from the target's in search-crop pixels
    /// (one output at offset 0: the official step).
    fn cells(&self, frame_w: usize, frame_h: usize, tiles: &[(&SearchOutput, (f64, f64))]) -> Result<Cells> {
        let cfg = &self.config;
        let st = self.state.as_ref().ok_or_else(|| Error::Input("update called before init".into()))?;
        let scale_z = cfg.exemplar_size as f64 / self.cropper.search_context(st.size, frame_w, frame_h, &st.template);
        // Each crop's cells, its boxes moved by its offset (none for the official step's one
        // crop, decoded straight into place), crop after crop. `tiles` is never empty.
        let shift = |boxes: &mut [[f64; 4]], (dx, dy): (f64, f64)| {
            if (dx, dy) != (0.0, 0.0) {
                boxes.iter_mut().for_each(|b| (b[0], b[1]) = (b[0] + dx, b[1] + dy));
            }
        };
        let (mut pred, mut score) = crate::family::decode(cfg, tiles[0].0)?;
        shift(&mut pred, tiles[0].1);
        for &(out, offset) in &tiles[1..] {
            let (mut p, s) = crate::family::decode(cfg, out)?;
            shift(&mut p, offset);
            pred.extend(p);
            score.extend(s);
        }
        let (window, influence) = match (&self.long_term, tiles.len()) {
            (Some(lt), n) if n > 1 => (lt.window.as_slice(), lt.rule.window_influence),
            _ => (self.window.as_slice(), cfg.window_influence),
        };

        let sz = |w: f64, h: f64| {
            let pad = (w + h) * 0.5;
            ((w + pad) * (h + pad)).sqrt()
        };
        let (tw, th) = (st.size.0 * scale_z, st.size.1 * scale_z);
        let eps = cfg.ratio_eps;
        let n = pred.len();
        let mut penalty = Vec::with_capacity(n);
        let mut pscore = Vec::with_capacity(n);
        for i in 0..n {
            let [_, _, pw, ph] = pred[i];
            let s_c = change(sz(pw, ph) / sz(tw, th), eps);
            let r_c = change((st.size.0 / (st.size.1 + eps)) / (pw / (ph + eps)), eps);
            let p = (-(r_c * s_c - 1.0) * cfg.penalty_k).exp();
            penalty.push(p);
            pscore.push(p * score[i] * (1.0 - influence) + window[i] * influence);
        }
        Ok(Cells { pred, score, penalty, pscore, scale_z })
    }

    /// The official post-processing of one search output for a frame of `frame_w`x`frame_h`:
    /// decode the grid, apply the scale/aspect penalties and the cosine window, pick the best
    /// cell, smooth and clip the target, and return it. [`Tracker::track`] is crop, network,
    /// then this; it is public for benchmarks and for callers that run the network themselves.
    pub fn update(&mut self, frame_w: usize, frame_h: usize, out: &SearchOutput) -> Result<Prediction> {
        self.decide(frame_w, frame_h, &[(out, (0.0, 0.0))])
    }

    /// [`Tracker::update`] over the outputs of one or more crops ([`Tracker::cells`]), with the
    /// long-term mode's rules when it is on.
    fn decide(&mut self, frame_w: usize, frame_h: usize, tiles: &[(&SearchOutput, (f64, f64))]) -> Result<Prediction> {
        let cfg = &self.config;
        let Cells { pred, score, penalty, pscore, scale_z } = self.cells(frame_w, frame_h, tiles)?;
        let st = self.state.as_ref().expect("cells checked init");
        let (fw, fh) = (frame_w as f64, frame_h as f64);
        let best = argmax(&pscore);
        // The confidence is read on the map of the crop the best cell is in.
        let n = score.len() / tiles.len();
        let (tile, cell) = (best / n, best % n);
        let (signal, uncertain_below, lost_below) = cfg.state_rule();
        let confidence = confidence(signal, &score[tile * n..(tile + 1) * n], cell);
        let state = TargetState::of(confidence, uncertain_below, lost_below);
        if let Some(LongTerm { rule: lt, .. }) = &self.long_term {
            // pysot's long-term rule: below the low threshold the box stays, and the larger
            // region is searched until a find reaches the high one (only then does the box
            // move: LongTermConfig).
            let bar = if st.redetecting { lt.found_above } else { lt.lost_below };
            let keep = confidence.is_nan() || confidence < bar;
            let st = self.state.as_mut().expect("initialised");
            st.redetecting = keep;
            if keep {
                let (c, s) = (st.center, st.size);
                let bbox = BBox { x: c.0 - s.0 / 2.0, y: c.1 - s.1 / 2.0, w: s.0, h: s.1 };
                // The box kept is no find: lost, whatever the confidence of the map searched.
                return Ok(Prediction { bbox, score: score[best], confidence, state: TargetState::Lost });
            }
        }
        let st = self.state.as_ref().expect("initialised");
        let b = pred[best].map(|v| v / scale_z);
        let lr = penalty[best] * score[best] * cfg.lr;
        let cx = b[0] + st.center.0;
        let cy = b[1] + st.center.1;
        let width = st.size.0 * (1.0 - lr) + b[2] * lr;
        let height = st.size.1 * (1.0 - lr) + b[3] * lr;
        let cx = py_max(0.0, py_min(cx, fw));
        let cy = py_max(0.0, py_min(cy, fh));
        let width = py_max(10.0, py_min(width, fw));
        let height = py_max(10.0, py_min(height, fh));
        let st = self.state.as_mut().expect("initialised");
        st.center = (cx, cy);
        st.size = (width, height);
        Ok(Prediction {
            bbox: BBox { x: cx - width / 2.0, y: cy - height / 2.0, w: width, h: height },
            score: score[best],
            confidence,
            state,
        })
    }
}

/// Every cell's decoded box, score, penalty and penalised score, and the crop's scale.
struct Cells {
    pred: Vec<[f64; 4]>,
    score: Vec<f64>,
    penalty: Vec<f64>,
    pscore: Vec<f64>,
    scale_z: f64,
}

/// `np.maximum(r, 1/(r+eps))` (PRL-Track: eps 1e-5; NanoTrack: `1/r`, eps 0): NaN propagates.
fn change(r: f64, eps: f64) -> f64 {
    let other = 1.0 / (r + eps);
    if r.is_nan() || other.is_nan() {
        f64::NAN
    } else {
        r.max(other)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numpy_semantics() {
        assert_eq!(argmax(&[1.0, 3.0, 3.0, 2.0]), 1);
        assert_eq!(argmax(&[1.0, f64::NAN, 5.0, f64::NAN]), 1);
        assert_eq!(py_max(10.0, py_min(f64::NAN, 100.0)), 10.0);
        let h = hanning(11);
        assert!((h[5] - 1.0).abs() < 1e-15 && h[0] == 0.0 && (h[1] - 0.0954915028125263).abs() < 1e-12);
        assert!(change(f64::NAN, 1e-5).is_nan());
        assert_eq!(change(0.5, 1e-5), 1.0 / 0.50001);
        assert_eq!(change(0.5, 0.0), 2.0);
    }

    #[test]
    fn states_from_confidence() {
        assert_eq!(TargetState::of(0.93, 0.93, 0.92), TargetState::Tracking);
        assert_eq!(TargetState::of(0.925, 0.93, 0.92), TargetState::Uncertain);
        assert_eq!(TargetState::of(0.92, 0.93, 0.92), TargetState::Uncertain);
        assert_eq!(TargetState::of(0.9, 0.93, 0.92), TargetState::Lost);
        assert_eq!(TargetState::of(f64::NAN, 0.93, 0.92), TargetState::Lost);
        let map = [0.1, 0.9, 0.2, 0.0];
        assert_eq!(confidence(StateSignal::BestScore, &map, 1), 0.9);
        assert!((confidence(StateSignal::MapFocus, &map, 1) - 0.7).abs() < 1e-12);
        assert!(confidence(StateSignal::MapFocus, &[0.5, f64::NAN], 0).is_nan());
    }
}
