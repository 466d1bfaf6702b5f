//! Tracker settings.

/// Tracker hyper-parameters of the official PRL-Track configuration.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackerConfig {
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
    /// Weight of the `cls1` score (`w2`).
    pub w2: f64,
    /// Weight of the `cls2` score (`w3`).
    pub w3: f64,
    /// Output stride of the score map in crop pixels.
    pub stride: usize,
    /// Score map side.
    pub score_size: usize,
}

impl Default for TrackerConfig {
    /// The official settings (`experiments/config.yaml`).
    fn default() -> Self {
        TrackerConfig {
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
        }
    }
}
