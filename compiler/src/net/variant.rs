//! The ablation variants of the paper's Table II, for their latency: which of AR, SR (SR1 and
//! SR2) and the fine representation learning (FLP: the HMG transformer) the search graph keeps.
//!
//! A module left out is replaced by the least that keeps the shapes: a 3x3 stride-2 convolution
//! (192 channels, ReLU) from the correlation map the module would have read, so the heads still
//! see [1,192,11,11]. Without FLP the heads read the last regulator's output. Modules that exist
//! in the checkpoint keep its weights; the stand-in convolutions are seeded random (they have no
//! trained weights anywhere), so a variant is for timing, not for tracking.

use serde::{Deserialize, Serialize};

use super::layers::{conv, ConvSpec};
use crate::onnx::{ConvOpts, Graph, Value};
use crate::weights::Weights;
use crate::Result;

/// Which modules the search graph holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Variant {
    /// PRL-Track as published: AR, SR1, SR2, HMG, heads.
    #[default]
    Full,
    /// Backbone, correlations and heads only.
    Baseline,
    /// Baseline + the fine representation learning (HMG).
    Flp,
    /// Baseline + AR + HMG.
    ArFlp,
    /// Baseline + SR1/SR2 + HMG.
    SrFlp,
}

impl Variant {
    /// Every variant, in the order of the paper's table.
    pub const ALL: [Variant; 5] = [Variant::Baseline, Variant::Flp, Variant::ArFlp, Variant::SrFlp, Variant::Full];

    /// Name on the command line and in manifests.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::Baseline => "baseline",
            Variant::Flp => "flp",
            Variant::ArFlp => "ar-flp",
            Variant::SrFlp => "sr-flp",
        }
    }

    /// The variant called `name`.
    pub fn parse(name: &str) -> Option<Variant> {
        Variant::ALL.into_iter().find(|v| v.name() == name)
    }

    /// Whether the search graph keeps the appearance-aware regulator.
    pub fn ar(self) -> bool {
        matches!(self, Variant::Full | Variant::ArFlp)
    }
    /// Whether it keeps the two semantic-aware regulators.
    pub fn sr(self) -> bool {
        matches!(self, Variant::Full | Variant::SrFlp)
    }
    /// Whether it keeps the fine representation learning (HMG).
    pub fn flp(self) -> bool {
        self != Variant::Baseline
    }
}

/// Seed of the stand-in convolutions' weights.
const STAND_IN_SEED: u64 = 0x5eed;

/// A 3x3 stride-2 convolution `cin` -> 192 with ReLU on `x` ([1,cin,21,21] -> [1,192,11,11]),
/// named `name`, standing in for a module the variant leaves out.
pub(crate) fn stand_in(g: &mut Graph, name: &str, x: &Value, cin: usize) -> Result<Value> {
    let weights = Weights::random(STAND_IN_SEED);
    let w = weights.root();
    let spec = ConvSpec {
        conv: w.pp("stand_in").pp(name),
        cin,
        cout: super::regulators::WIDTH,
        k: 3,
        opts: ConvOpts::stride_pad(2, 1),
        bias: true,
        gain: 2f32.sqrt(),
    };
    let y = conv(g, &format!("{name}.conv"), x, &spec)?;
    g.relu(name, &y)
}
