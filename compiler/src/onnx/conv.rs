//! Convolutions.

use super::{Attr, Graph, Value};
use crate::Result;

/// Stride, padding and grouping of a 2-D convolution.
#[derive(Debug, Clone, Copy)]
pub struct ConvOpts {
    /// Stride on both axes.
    pub stride: usize,
    /// Zero padding on every side.
    pub pad: usize,
    /// Number of groups (channels for a depthwise convolution).
    pub group: usize,
}

impl Default for ConvOpts {
    fn default() -> Self {
        ConvOpts { stride: 1, pad: 0, group: 1 }
    }
}

impl ConvOpts {
    /// Stride `s`, no padding.
    pub fn stride(s: usize) -> Self {
        ConvOpts { stride: s, ..Default::default() }
    }
    /// Stride `s`, padding `p`.
    pub fn stride_pad(s: usize, p: usize) -> Self {
        ConvOpts { stride: s, pad: p, group: 1 }
    }
}

impl Graph {
    /// `Conv(x, w[, b])`, NCHW.
    pub fn conv(&mut self, name: &str, x: &Value, w: &Value, b: Option<&Value>, o: ConvOpts) -> Result<Value> {
        let p = o.pad as i64;
        let s = o.stride as i64;
        let attrs = [
            ("strides", Attr::Ints(vec![s, s])),
            ("pads", Attr::Ints(vec![p, p, p, p])),
            ("group", Attr::Int(o.group as i64)),
        ];
        match b {
            Some(b) => self.node("Conv", name, &[x, w, b], &attrs),
            None => self.node("Conv", name, &[x, w], &attrs),
        }
    }

    /// Depthwise cross-correlation of `x` [1,C,H,W] with `kernel` [1,C,k,k] (a graph value, such
    /// as template features): each channel of `x` is correlated with the same channel of `kernel`.
    pub fn depthwise_xcorr(
        &mut self,
        name: &str,
        x: &Value,
        kernel: &Value,
        channels: usize,
        k: usize,
    ) -> Result<Value> {
        let kernel = self.reshape(&format!("{name}.kernel"), kernel, &[channels as i64, 1, k as i64, k as i64])?;
        self.conv(name, x, &kernel, None, ConvOpts { group: channels, ..Default::default() })
    }
}
