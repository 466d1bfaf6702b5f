//! The AlexNet backbone with BatchNorm (`backbone.layer1..5`), BatchNorm folded into the convs.

use super::layers::{conv_bn, ConvSpec};
use crate::onnx::{ConvOpts, Graph, Value};
use crate::weights::Scope;
use crate::Result;

/// Channel counts of the five layers.
pub const CHANNELS: [usize; 5] = [96, 256, 384, 384, 256];

/// Run layers 1..5 on `input` (BGR, 0..255); the outputs are named `{prefix}1`..`{prefix}5`.
/// Layer 1 is the official 11x11 stride-2 convolution (the runtime's `PackedConv` runs it on
/// the input's four phases, which is the space-to-depth form with no padding taps).
pub(crate) fn backbone(g: &mut Graph, w: &Scope, input: &Value, prefix: &str) -> Result<Vec<Value>> {
    // (kernel, stride, max-pool after, ReLU, random-init activation scale)
    let layers = [
        (11, 2, true, true, 200.0),
        (5, 1, true, true, 2.0),
        (3, 1, false, true, 1.0),
        (3, 1, false, true, 1.0),
        (3, 1, false, false, 1.0),
    ];
    let mut outs = Vec::new();
    let mut x = input.clone();
    let mut cin = 3;
    for (i, &(k, stride, pool, relu, scale)) in layers.iter().enumerate() {
        let l = w.pp(format!("layer{}", i + 1));
        let name = format!("backbone.layer{}", i + 1);
        let out = format!("{prefix}{}", i + 1);
        let spec = ConvSpec {
            conv: l.pp(0),
            cin,
            cout: CHANNELS[i],
            k,
            opts: ConvOpts::stride(stride),
            bias: true,
            gain: 1.0,
        };
        let conv_name = if !pool && !relu { out.clone() } else { format!("{name}.conv") };
        x = conv_bn(g, &conv_name, &x, &spec, &l.pp(1), scale)?;
        if pool {
            x = g.max_pool(&format!("{name}.maxpool"), &x, 3, 2)?;
        }
        if relu {
            x = g.relu(&out, &x)?;
        }
        outs.push(x.clone());
        cin = CHANNELS[i];
    }
    Ok(outs)
}
