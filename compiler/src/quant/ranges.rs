//! Each activation's u8 parameters from what calibration saw: the method's range, adjusted where
//! the layer's consumer makes part of it useless.

use std::collections::HashMap;

use super::calibrate::Stats;
use super::{Candidate, Method, QParams};

/// Where `HardSwish` (`x·min(max(x + 3, 0), 6)/6`) stops being 0.
const HARD_SWISH_FLOOR: f32 = -3.0;

/// Every observed value's u8 parameters and the range they cover (as the report shows it).
#[derive(Debug)]
pub(super) struct Ranges {
    /// By value name.
    pub params: HashMap<String, QParams>,
    /// By value name: the calibrated range after the adjustments below.
    pub range: HashMap<String, (f32, f32)>,
}

impl Ranges {
    /// `method`'s ranges of every value `stats` observed. Two adjustments, both exact:
    /// - a ReLU after a pool clips below 0 anyway: all 256 levels go to `[0, max]`;
    /// - a `HardSwish` that alone reads a layer's output is 0 at and below -3, so codes for lower
    ///   values are wasted (NanoTrack's stem reaches -95, half its 256 levels): the range starts
    ///   at -3, with the lowest code at or below it so that it still maps to 0.
    pub fn of(stats: &Stats, cands: &[Candidate], method: Method) -> Ranges {
        let mut range: HashMap<String, (f32, f32)> =
            stats.observers.iter().map(|(v, o)| (v.clone(), o.range(method).unwrap_or((0.0, 0.0)))).collect();
        let mut params: HashMap<String, QParams> =
            range.iter().map(|(v, &(lo, hi))| (v.clone(), QParams::from_range(lo, hi))).collect();
        for c in cands {
            let Some(r) = range.get_mut(&c.output) else { continue };
            if c.relu_after_pool {
                r.0 = 0.0;
                params.insert(c.output.clone(), QParams::from_range(0.0, r.1));
            }
            if c.hard_swish_after && r.0 < HARD_SWISH_FLOOR {
                r.0 = HARD_SWISH_FLOOR;
                params.insert(c.output.clone(), QParams::from_range_floor(HARD_SWISH_FLOOR, r.1));
            }
        }
        Ranges { params, range }
    }
}
