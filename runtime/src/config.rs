//! Tracker settings: which tracker family a plan is for, and every number its loop needs.
//!
//! The loop itself ([`crate::Tracker`]) is one crop + state machine for all families; what
//! differs between them is how the search graph's outputs become boxes and scores
//! ([`Family`]) and a few switches of their official code, which are settings here rather
//! than constants in the loop.

use serde::{Deserialize, Serialize};

/// The Siamese tracker families the runtime can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Family {
    /// PRL-Track (IROS 2024): search outputs `loc` [1,4,N,N] (left, right, top, bottom as
    /// `atanh` offsets), `cls1` [1,2,N,N], `cls2` [1,1,N,N]; the score mixes the softmax of
    /// `cls1` with the raw `cls2` logit.
    PrlTrack,
    /// NanoTrack (v2, HonglinChu/SiamTrackers): search outputs `cls` [1,2,N,N] and `loc`
    /// [1,4,N,N] (left, top, right, bottom distances in crop pixels); the score is the softmax
    /// of `cls`, channel 1.
    Nanotrack,
}

impl Family {
    /// Every family.
    pub const ALL: [Family; 2] = [Family::PrlTrack, Family::Nanotrack];

    /// The name used in manifests and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Family::PrlTrack => "prl-track",
            Family::Nanotrack => "nanotrack",
        }
    }

    /// The family called `name`, if any.
    pub fn parse(name: &str) -> Option<Family> {
        Family::ALL.into_iter().find(|f| f.name() == name)
    }

    /// The search graph's outputs this family decodes, in order, as `(name, channels)`; each
    /// is `[1, channels, score_size, score_size]`.
    pub fn search_outputs(self) -> &'static [(&'static str, usize)] {
        match self {
            Family::PrlTrack => &[("loc", 4), ("cls1", 2), ("cls2", 1)],
            Family::Nanotrack => &[("cls", 2), ("loc", 4)],
        }
    }
}

fn prl_track() -> Family {
    Family::PrlTrack
}
fn one() -> f64 {
    1.0
}
fn prl_grid_origin() -> f64 {
    // The official `generate_anchor`: `stride * i + 63 - TRAIN.SEARCH_SIZE // 2` (287 // 2).
    63.0 - 143.0
}
fn prl_loc_scale() -> f64 {
    // The official `generate_anchor` multiplies the atanh offsets by the literal 143.
    143.0
}
fn prl_ratio_eps() -> f64 {
    1e-5
}
fn yes() -> bool {
    true
}

/// Tracker hyper-parameters. Fields added after the first plan format have serde defaults
/// equal to PRL-Track's, so older PRL-Track plans and settings files still read unchanged.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackerConfig {
    /// Which tracker's decoding and scoring the plan's outputs need.
    #[serde(default = "prl_track")]
    pub family: Family,
    /// Template crop side (`EXEMPLAR_SIZE`).
    pub exemplar_size: usize,
    /// Search crop side (`INSTANCE_SIZE`).
    pub instance_size: usize,
    /// Context added around the target (`CONTEXT_AMOUNT`).
    pub context_amount: f64,
    /// Scale/aspect change penalty (`PENALTY_K`).
    pub penalty_k: f64,
    /// Weight of the cosine window (`WINDOW_INFLUENCE`).
    pub window_influence: f64,
    /// Size update rate (`LR`).
    pub lr: f64,
    /// Weight of the `cls1` score (`w2`; PRL-Track only).
    #[serde(default = "one")]
    pub w2: f64,
    /// Weight of the `cls2` score (`w3`; PRL-Track only).
    #[serde(default = "one")]
    pub w3: f64,
    /// Output stride of the score map in crop pixels.
    pub stride: usize,
    /// Score map side.
    pub score_size: usize,
    /// Offset, in search-crop pixels from the crop centre, of score cell (0, 0): cell (row i,
    /// column j) sits at `(grid_origin + stride * j, grid_origin + stride * i)`. PRL-Track:
    /// `63 - 287 // 2 = -80` (centred on 11 cells); NanoTrack: `-(16 // 2) * 16 = -128` (not
    /// centred: -128..112).
    #[serde(default = "prl_grid_origin")]
    pub grid_origin: f64,
    /// Factor of PRL-Track's `atanh` box offsets (the official code's literal 143; unused by
    /// families whose offsets are pixels).
    #[serde(default = "prl_loc_scale")]
    pub loc_scale: f64,
    /// The `eps` of the official penalty: `change(r) = max(r, 1 / (r + eps))` and aspect ratios
    /// `w / (h + eps)`. PRL-Track: 1e-5; NanoTrack: 0 (none).
    #[serde(default = "prl_ratio_eps")]
    pub ratio_eps: f64,
    /// When the target covers more than half of the frame, search crops keep the template's
    /// window side (PRL-Track's `scaleaa` rule; NanoTrack has none).
    #[serde(default = "yes")]
    pub large_target_keeps_template_size: bool,
    /// What a prediction's state (`tracking`, `uncertain`, `lost`) is decided on. `None` (plans
    /// made before states existed): the family's default ([`TrackerConfig::state_rule`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_signal: Option<StateSignal>,
    /// Confidence (the value of `state_signal`) below which a prediction is `uncertain` rather
    /// than `tracking`. `None`: the family's default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncertain_below: Option<f64>,
    /// Confidence below which the target is `lost`. `None`: the family's default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lost_below: Option<f64>,
    /// Re-detection settings of the long-term mode ([`crate::Tracker::set_long_term`]). `None`:
    /// the defaults ([`TrackerConfig::long_term_rule`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub long_term: Option<LongTermConfig>,
}

/// The long-term mode: pysot's long-term SiamRPN scheme (`SiamRPNLTTracker`), on the plan's
/// confidence rather than the best score, with the larger search region made of search crops
/// of the usual shape, so that it works for heads tied to one search size (NanoTrack's).
/// One rule differs from pysot's, by measurement (docs/lost-target.md): while the region is
/// searched the box moves only to a find at or above `found_above` (pysot moves it to anything
/// at or above its low threshold, which let the box wander off after look-alikes in the
/// background while the target was hidden).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LongTermConfig {
    /// Confidence below which the target counts as lost: the box stays where it was and the
    /// following frames search the larger region (pysot's `CONFIDENCE_LOW`).
    pub lost_below: f64,
    /// Confidence at or above which a find in the larger region is taken: the box moves there
    /// and the search returns to the usual crop (pysot's `CONFIDENCE_HIGH`).
    pub found_above: f64,
    /// Search crops per side of the larger region (odd, 1 to 9): `tiles` x `tiles` crops of the
    /// usual scale around the last position, spaced by the span of the score map, so that their
    /// maps tile one map `tiles` times the usual side (pysot's `LOST_INSTANCE_SIZE` 831 is about
    /// 3.3 times its 255).
    pub tiles: usize,
    /// Weight of the cosine window over the larger region (pysot: 0.001).
    pub window_influence: f64,
}

/// What tells a followed target from a lost one: the value a prediction's state is decided on
/// (its `confidence`; higher is surer).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StateSignal {
    /// The chosen cell's score (the official `best_score`). NanoTrack's stays above 0.9 on many
    /// frames where the target is hidden: a poor signal for it (docs/lost-target.md).
    BestScore,
    /// One minus the mean score of the whole map: near 1 when the map has one sharp peak (the
    /// target), lower when the response spreads over the background, as it does when the
    /// target is hidden or the tracker has drifted off it.
    MapFocus,
}

/// The default state rule (signal, uncertain below, lost below) of every family. NanoTrack's
/// thresholds are calibrated on lost-and-found versions of the shared UAV123 sequences
/// (docs/lost-target.md); PRL-Track's are NanoTrack's, not calibrated (no trained PRL-Track
/// weights are available to this project).
const fn default_state_rule(family: Family) -> (StateSignal, f64, f64) {
    match family {
        Family::PrlTrack | Family::Nanotrack => (StateSignal::MapFocus, 0.93, 0.92),
    }
}

impl Default for TrackerConfig {
    /// PRL-Track's official settings ([`TrackerConfig::prl_track`]).
    fn default() -> Self {
        TrackerConfig::prl_track()
    }
}

impl TrackerConfig {
    /// PRL-Track's official settings (`experiments/config.yaml`).
    pub fn prl_track() -> Self {
        TrackerConfig {
            family: Family::PrlTrack,
            exemplar_size: 127,
            instance_size: 287,
            context_amount: 0.5,
            penalty_k: 0.08,
            window_influence: 0.42,
            lr: 0.30,
            w2: 1.0,
            w3: 1.0,
            stride: 16,
            score_size: 11,
            grid_origin: prl_grid_origin(),
            loc_scale: prl_loc_scale(),
            ratio_eps: prl_ratio_eps(),
            large_target_keeps_template_size: true,
            state_signal: Some(default_state_rule(Family::PrlTrack).0),
            uncertain_below: Some(default_state_rule(Family::PrlTrack).1),
            lost_below: Some(default_state_rule(Family::PrlTrack).2),
            long_term: None,
        }
    }

    /// NanoTrack v2's official settings (`models/config/configv2.yaml`).
    pub fn nanotrack() -> Self {
        TrackerConfig {
            family: Family::Nanotrack,
            exemplar_size: 127,
            instance_size: 255,
            context_amount: 0.5,
            penalty_k: 0.150,
            window_influence: 0.490,
            lr: 0.385,
            w2: 1.0,
            w3: 1.0,
            stride: 16,
            score_size: 16,
            grid_origin: -((16 / 2) as f64) * 16.0,
            loc_scale: 1.0,
            ratio_eps: 0.0,
            large_target_keeps_template_size: false,
            state_signal: Some(default_state_rule(Family::Nanotrack).0),
            uncertain_below: Some(default_state_rule(Family::Nanotrack).1),
            lost_below: Some(default_state_rule(Family::Nanotrack).2),
            long_term: None,
        }
    }

    /// The family's default settings.
    pub fn for_family(family: Family) -> Self {
        match family {
            Family::PrlTrack => TrackerConfig::prl_track(),
            Family::Nanotrack => TrackerConfig::nanotrack(),
        }
    }

    /// What a prediction's state is decided on, and the confidences below which it is
    /// `uncertain` and `lost`: the settings', or the family's defaults where a plan predates them.
    pub fn state_rule(&self) -> (StateSignal, f64, f64) {
        let (s, u, l) = default_state_rule(self.family);
        (self.state_signal.unwrap_or(s), self.uncertain_below.unwrap_or(u), self.lost_below.unwrap_or(l))
    }

    /// The long-term mode's settings: the plan's, else the family's defaults (both families:
    /// lost below 0.90, found at 0.94, 3 x 3 crops, pysot's window influence 0.001; calibrated
    /// for NanoTrack's map-focus confidence in docs/lost-target.md, not for PRL-Track).
    pub fn long_term_rule(&self) -> LongTermConfig {
        self.long_term.clone().unwrap_or(match self.family {
            Family::PrlTrack | Family::Nanotrack => {
                LongTermConfig { lost_below: 0.90, found_above: 0.94, tiles: 3, window_influence: 0.001 }
            }
        })
    }

    /// Settings that cannot run (zero or absurd sizes, non-finite numbers), as a message.
    pub fn check(&self) -> Result<(), String> {
        let sizes = [self.exemplar_size, self.instance_size, self.stride, self.score_size];
        if sizes.iter().any(|&s| s == 0 || s > 4096) {
            return Err(format!(
                "tracker sizes must be between 1 and 4096: exemplar {}, instance {}, stride {}, score map {}",
                self.exemplar_size, self.instance_size, self.stride, self.score_size
            ));
        }
        let reals = [
            self.context_amount,
            self.penalty_k,
            self.window_influence,
            self.lr,
            self.w2,
            self.w3,
            self.grid_origin,
            self.loc_scale,
            self.ratio_eps,
        ];
        if reals.iter().any(|v| !v.is_finite()) {
            return Err("tracker settings must be finite numbers".into());
        }
        let (_, u, l) = self.state_rule();
        if !(l.is_finite() && u.is_finite() && l <= u) {
            return Err(format!("lost_below ({l}) must be a number at most uncertain_below ({u})"));
        }
        let lt = self.long_term_rule();
        if !(lt.lost_below.is_finite() && lt.found_above.is_finite() && lt.lost_below <= lt.found_above) {
            return Err(format!(
                "long_term.lost_below ({}) must be a number at most long_term.found_above ({})",
                lt.lost_below, lt.found_above
            ));
        }
        if lt.tiles.is_multiple_of(2) || lt.tiles > 9 || !lt.window_influence.is_finite() {
            return Err(format!(
                "long_term.tiles must be odd and at most 9 (got {}), long_term.window_influence finite",
                lt.tiles
            ));
        }
        Ok(())
    }
}
