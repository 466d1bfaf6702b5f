//! The heads (`grader.convloc`, `grader.convcls`, `grader.cls1`, `grader.cls2`): three
//! conv3x3 + GroupNorm(32) + ReLU stages per branch, then the output convolutions.

use super::layers::{conv, conv_with_bias_init, ConvSpec};
use crate::onnx::{ConvOpts, Graph, Value};
use crate::weights::{Init, Scope};
use crate::Result;

const C: usize = 192;
const GROUPS: usize = 32;

fn tower(g: &mut Graph, w: &Scope, name: &str, x: &Value) -> Result<Value> {
    let mut x = x.clone();
    for (c, n) in [(0, 1), (3, 4), (6, 7)] {
        let spec =
            ConvSpec { conv: w.pp(c), cin: C, cout: C, k: 3, opts: ConvOpts::stride_pad(1, 1), bias: true, gain: 1.0 };
        x = conv(g, &format!("{name}.{c}"), &x, &spec)?;
        let gn = w.pp(n);
        let s = g.constant(&gn.key("weight"), &gn.get("weight", &[C], Init::Uniform { lo: 0.8, hi: 1.2 })?)?;
        let b = g.constant(&gn.key("bias"), &gn.get("bias", &[C], Init::Normal { mean: 0.0, std: 0.1 })?)?;
        x = g.group_norm(&format!("{name}.{n}"), &x, GROUPS, &s, &b, 1e-5)?;
        x = g.relu(&format!("{name}.{}", n + 1), &x)?;
    }
    Ok(x)
}

/// `loc` [1,4,11,11], `cls1` [1,2,11,11], `cls2` [1,1,11,11] from the HMG output.
pub(crate) fn heads(g: &mut Graph, w: &Scope, x: &Value) -> Result<[Value; 3]> {
    let out =
        |conv, cout, gain| ConvSpec { conv, cin: C, cout, k: 3, opts: ConvOpts::stride_pad(1, 1), bias: true, gain };
    let l = tower(g, &w.pp("convloc"), "grader.convloc", x)?;
    // Random weights: small regression outputs centred so that boxes come out plausible.
    let loc = conv_with_bias_init(g, "loc", &l, &out(w.pp("convloc").pp(9), 4, 0.05), 0.3)?;
    let c = tower(g, &w.pp("convcls"), "grader.convcls", x)?;
    let cls1 = conv(g, "cls1", &c, &out(w.pp("cls1"), 2, 0.2))?;
    let cls2 = conv(g, "cls2", &c, &out(w.pp("cls2"), 1, 0.2))?;
    Ok([loc, cls1, cls2])
}
