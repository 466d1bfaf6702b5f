//! Float convolutions of stride 1 or 2 with constant weights as [`PackedConv`], a direct
//! convolution whose weights are packed once, when the plan is loaded ([`super::conv_kernel`]).
//! With stride 2 the padded input is stored as its four phases (even/odd rows x columns), so
//! that each tap again reads consecutive positions: the same kernel, and no extra work.
//!
//! tract runs these convolutions as an im2col and a matrix product with the whole reduction
//! (`k` = 2400 for backbone layer 2) in one pass, which here reached 25-60 GFLOP/s on one core
//! against about 100 for ONNX Runtime. The direct form reads every tap's inputs in place, with
//! no im2col buffer and no packing of the activations.

use std::ops::Range;
use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::nn::DataFormat;

use super::act::{output_fact, reshape_output, Activation, Tail};
use super::conv_kernel::{channel_block, Layout, MAX_PX, ROWS};
use super::conv_lanes::LanePack;
use super::par::{par_runs, parts, SyncPtr};
use super::scratch::lend;
use super::{all_ones, output_tensor_written, pads_2d, par_chunks, same_bits, serial_if_small};

mod shape;
#[cfg(test)]
mod tests;

pub use shape::ConvShape;

/// `out[n,o,y,x] = bias[o] + Σ_{c,i,j} pad(input)[n,c,y+i,x+j]·weight[o,c,i,j]`, stride 1, with
/// the weights packed `[o / 8][(c,i,j)][o % 8]` when the op is made (taps `(c,i,j)` whose
/// weights are all zero left out), or, on AVX-512 for 32 channels or more, packed for tiles
/// with the channels in the vector lanes ([`super::conv_lanes`]).
#[derive(Clone)]
pub struct PackedConv {
    shape: ConvShape,
    layout: Arc<Layout>,
    weights: Arc<Vec<f32>>,
    lanes: Option<Arc<LanePack>>,
    bias: Arc<Vec<f32>>,
    /// Applied to the output as it is written (the graph's activation after the convolution).
    act: Activation,
    /// The padded input's positions the channels' padding does not write
    /// ([`super::with_padded`]).
    borders: Arc<Vec<(usize, usize)>>,
    /// The output's shape where the fused nodes end in another shape than `[n, co, oh, ow]`.
    reshape: Option<TVec<usize>>,
}

impl std::fmt::Debug for PackedConv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PackedConv({:?})", self.shape)
    }
}

impl PartialEq for PackedConv {
    fn eq(&self, other: &Self) -> bool {
        fn lanes(c: &PackedConv) -> &[f32] {
            c.lanes.as_ref().map(|l| l.values()).unwrap_or_default()
        }
        self.shape == other.shape
            && same_bits(&self.weights, &other.weights)
            && same_bits(lanes(self), lanes(other))
            && same_bits(&self.bias, &other.bias)
            && self.act == other.act
            && self.reshape == other.reshape
    }
}

impl Eq for PackedConv {}

impl PackedConv {
    /// Pack OIHW `weight` ([co, ci, kh, kw], row-major) and `bias` (one value or `co`).
    pub fn new(shape: ConvShape, weight: &[f32], bias: &[f32]) -> TractResult<PackedConv> {
        let taps = shape.ci * shape.kh * shape.kw;
        ensure!(weight.len() == shape.co * taps, "PackedConv: {} weights for {shape:?}", weight.len());
        ensure!(bias.len() == 1 || bias.len() == shape.co, "PackedConv: {} bias values for {shape:?}", bias.len());
        // Taps whose weight is zero for every output (the padding of a space-to-depth kernel)
        // are left out: with finite inputs they add exact zeros.
        let mut nonzero = vec![false; taps];
        for w in weight.chunks_exact(taps) {
            nonzero.iter_mut().zip(w).for_each(|(n, &v)| *n |= v != 0.0);
        }
        let live: Vec<usize> = (0..taps).filter(|&t| nonzero[t]).collect();
        let blocks = shape.co.div_ceil(ROWS);
        let lanes = LanePack::new(weight, taps, &live, &shape).map(Arc::new);
        // Written in order, block by block: the block's rows are read as 8 streams (not at all
        // where the lanes' packing serves).
        let mut packed = Vec::new();
        if lanes.is_none() {
            packed.reserve(blocks * live.len() * ROWS);
            for rows in weight.chunks(ROWS * taps) {
                for &t in &live {
                    packed.extend((0..ROWS).map(|r| rows.get(r * taps + t).copied().unwrap_or(0.0)));
                }
            }
        }
        let bias: Vec<f32> =
            (0..blocks * ROWS).map(|o| if bias.len() == 1 { bias[0] } else { *bias.get(o).unwrap_or(&0.0) }).collect();
        let (_, wq) = shape.phase();
        let (oh, ow) = shape.out();
        let offsets = shape.tap_offsets(shape.ci);
        let layout = Layout { taps: live.iter().map(|&t| offsets[t]).collect(), wp: wq, oh, ow };
        let (weights, bias) = (Arc::new(packed), Arc::new(bias));
        let plane_in = shape.stride * shape.stride * shape.phase().0 * wq;
        let zeros = vec![0.0; shape.h * shape.w];
        let borders = Arc::new(super::unwritten_runs(Self::padded_len(&shape), |buf| {
            for plane in buf.chunks_exact_mut(plane_in).take(shape.ci) {
                shape.pad_plane(&zeros, plane);
            }
        }));
        let layout = Arc::new(layout);
        Ok(PackedConv { shape, layout, weights, lanes, bias, act: Activation::NONE, borders, reshape: None })
    }

    /// The length of the padded input: every channel's plane (its phases with stride 2), with
    /// room past the end for a tile of positions and a row.
    fn padded_len(s: &ConvShape) -> usize {
        let (hq, wq) = s.phase();
        s.ci * s.stride * s.stride * hq * wq + MAX_PX + wq
    }

    /// The convolution followed by the nodes of `tail` ([`super::act::tail`]).
    pub(crate) fn fused(self, tail: &Tail) -> TractResult<PackedConv> {
        ensure!(tail.bias.is_none(), "PackedConv: a convolution has its own bias");
        Ok(PackedConv { act: tail.act, reshape: tail.reshaped(), ..self })
    }

    /// The convolution's shape.
    pub fn shape(&self) -> &ConvShape {
        &self.shape
    }

    /// Channel block `b`'s packed weights and bias.
    fn block(&self, b: usize) -> (&[f32], &[f32; ROWS]) {
        let taps = self.layout.taps.len();
        let bias = self.bias[b * ROWS..(b + 1) * ROWS].try_into().expect("ROWS values");
        (&self.weights[b * taps * ROWS..(b + 1) * taps * ROWS], bias)
    }

    /// [`channel_block`] over every channel block with its output rows cut in `parts` runs, on
    /// tract's threads, where whole blocks would leave threads idle ([`parts`]). A run's rows
    /// are those of a layout that starts at its first row (the padded input read from that row
    /// on), summed into the thread's buffer and copied into the block's planes. A position's
    /// sum does not depend on the tile it falls in, so the outputs are those of whole blocks,
    /// bit for bit.
    fn blocks_in_parts(&self, padded: &[f32], parts: usize, out: &mut [f32]) {
        thread_local! {
            static RUN: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let Layout { wp, oh, ow, .. } = *self.layout;
        let (co, plane) = (self.shape.co, oh * ow);
        assert_eq!(out.len(), co * plane);
        let dst = SyncPtr(out.as_mut_ptr());
        par_runs(co.div_ceil(ROWS), parts, oh, |b, Range { start: y0, end: y1 }| {
            let rows = ROWS.min(co - b * ROWS);
            let run = Layout { taps: self.layout.taps.clone(), wp, oh: y1 - y0, ow };
            let n = (y1 - y0) * ow;
            let (weights, bias) = self.block(b);
            lend(&RUN, rows * n, |sums: &mut [f32]| {
                channel_block(&run, &padded[y0 * wp..], weights, bias, self.act, sums);
                for (r, sums) in sums.chunks_exact(n).enumerate() {
                    // SAFETY: rows `y0 .. y1` of channel `b·ROWS + r < co`'s plane, within `out`
                    // (asserted); no other item writes them.
                    let d = unsafe { std::slice::from_raw_parts_mut(dst.at((b * ROWS + r) * plane + y0 * ow), n) };
                    d.copy_from_slice(sums);
                }
            });
        });
    }
}

impl Op for PackedConv {
    fn name(&self) -> StaticName {
        "PackedConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let s = &self.shape;
        let (kh, kw, ci, co, taps) = (s.kh, s.kw, s.ci, s.co, self.layout.taps.len());
        let tile = match &self.lanes {
            Some(l) if l.compact() => {
                format!("compact tiles of {} channels by {} output positions", l.channels(), l.positions())
            }
            Some(l) => format!("tiles of {} channels in lanes", l.channels()),
            None => format!("tiles of {ROWS} channels"),
        };
        Ok(vec![format!(
            "{kh}x{kw} kernel, stride {}, {ci} -> {co} channels, pad {:?}, {taps} taps, {tile}, activation {}",
            s.stride,
            s.pad,
            self.act.describe()
        )])
    }

    op_as_typed_op!();
}

impl EvalOp for PackedConv {
    op_out_of_plan!();

    fn eval(&self, _ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        let s = &self.shape;
        let (n, ci, h, w) = (s.batch_of("PackedConv", input.shape())?, s.ci, s.h, s.w);
        let input = input.try_as_plain_ram()?;
        let input = input.as_slice::<f32>()?;
        let (oh, ow) = s.out();
        let (hq, wq) = s.phase();
        let plane = oh * ow;
        let phases = s.stride * s.stride;
        let fill = |out: &mut [f32]| {
            super::with_padded(Self::padded_len(s), &self.borders, |padded| {
                for (src, dst) in input.chunks_exact(ci * h * w).zip(out.chunks_exact_mut(s.co * plane)) {
                    // The channels padded over the threads (one after another the other threads
                    // waited: 1.8 MB of input for the search graph's second layer).
                    let plane_in = phases * hq * wq;
                    par_chunks(&mut padded[..ci * plane_in], plane_in, |c, dst| {
                        s.pad_plane(&src[c * h * w..(c + 1) * h * w], dst)
                    });
                    match &self.lanes {
                        Some(lanes) if lanes.compact() => {
                            lanes.run_compact(&self.layout, padded, &self.bias, self.act, dst);
                            continue;
                        }
                        Some(lanes) => {
                            lanes.run(&self.layout, padded, &self.bias, self.act, dst);
                            continue;
                        }
                        None => {}
                    }
                    let parts = parts(s.co.div_ceil(ROWS), 1, oh);
                    if parts > 1 {
                        self.blocks_in_parts(padded, parts, dst);
                        continue;
                    }
                    par_chunks(dst, ROWS * plane, |b, out| {
                        let (weights, bias) = self.block(b);
                        channel_block(&self.layout, padded, weights, bias, self.act, out);
                    });
                }
                Ok(())
            })
        };
        let macs = [n, s.co, plane, ci, s.kh, s.kw].iter().fold(1usize, |a, &b| a.saturating_mul(b));
        // SAFETY: every output is written: the tiles cover every position of every row, each
        // channel block (or lanes' block) writes all its channels.
        let out = serial_if_small(macs, || unsafe { output_tensor_written(&[n, s.co, oh, ow], fill) })?;
        Ok(tvec!(reshape_output(out, self.reshape.as_ref())?.into_tvalue()))
    }
}

impl TypedOp for PackedConv {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        Ok(tvec!(output_fact(self.reshape.as_ref(), || self.shape.output_fact(&inputs[0].shape[0]))))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let (oh, ow) = self.shape.out();
        let s = &self.shape;
        let macs = s.co * oh * ow * self.layout.taps.len();
        Ok(tvec!((Cost::FMA(f32::datum_type()), inputs[0].shape[0].clone() * macs)))
    }

    as_op!();
}

/// A float 2-D convolution with constant OIHW weights and bias, explicit padding, dilation 1
/// and stride 1 or 2: what the runtime's convolutions take over from tract.
pub(crate) struct ConstConv<'a> {
    /// tract's operator (groups, channels, data format).
    pub conv: &'a Conv,
    /// The data input's shape.
    pub input: &'a [usize],
    /// Zero padding: top, left, bottom, right.
    pub pad: [usize; 4],
    /// Stride, the same along rows and columns.
    pub stride: usize,
    /// Kernel rows and columns.
    pub kernel: (usize, usize),
    /// The weights and bias, row-major.
    pub weight: &'a [f32],
    pub bias: &'a [f32],
}

/// `node` of `model` as a [`ConstConv`], if it is one.
pub(crate) fn const_conv<'a>(model: &'a TypedModel, node: &'a TypedNode) -> TractResult<Option<ConstConv<'a>>> {
    let Some(conv) = node.op_as::<Conv>() else { return Ok(None) };
    let facts = model.node_input_facts(node.id)?;
    let ps = &conv.pool_spec;
    let Some(pad) = pads_2d(&ps.padding) else { return Ok(None) };
    let plain = conv.q_params.is_none()
        && conv.kernel_fmt == KernelFormat::OIHW
        && ps.kernel_shape.len() == 2
        && all_ones(&ps.dilations)
        && facts.len() == 3
        && facts.iter().all(|f| f.datum_type == f32::datum_type());
    if !plain {
        return Ok(None);
    }
    let stride = match ps.strides.as_deref() {
        None | Some([1, 1]) => 1,
        Some([2, 2]) => 2,
        _ => return Ok(None),
    };
    let (Some(weight), Some(bias)) = (&facts[1].konst, &facts[2].konst) else { return Ok(None) };
    let Some(input) = facts[0].shape.as_concrete() else { return Ok(None) };
    let (weight, bias) = (weight.try_as_plain_ram()?, bias.try_as_plain_ram()?);
    let kernel = (ps.kernel_shape[0], ps.kernel_shape[1]);
    let (weight, bias) = (weight.as_slice::<f32>()?, bias.as_slice::<f32>()?);
    Ok(Some(ConstConv { conv, input, pad, stride, kernel, weight, bias }))
}

/// A convolution's shape, OIHW weights and bias.
pub(crate) type PlainConv<'a> = (ConvShape, &'a [f32], &'a [f32]);

/// The shape, OIHW weights and bias of `node` of `model` if it is a [`ConstConv`] with one
/// group, NCHW, and a kernel larger than 1x1: what [`PackedConv`] and
/// [`super::winograd::WinogradConv`] take.
pub(crate) fn plain_conv<'a>(model: &'a TypedModel, node: &'a TypedNode) -> TractResult<Option<PlainConv<'a>>> {
    let Some(c) = const_conv(model, node)? else { return Ok(None) };
    let ps = &c.conv.pool_spec;
    let (kh, kw) = c.kernel;
    let (&[_, ci, h, w], 1, DataFormat::NCHW) = (c.input, c.conv.group, ps.data_format) else { return Ok(None) };
    if kh * kw == 1 {
        return Ok(None);
    }
    let shape = ConvShape { ci, h, w, co: ps.output_channels, kh, kw, pad: c.pad, stride: c.stride };
    Ok(Some((shape, c.weight, c.bias)))
}

/// The [`PackedConv`] for `node` of `model` if it is a [`plain_conv`].
pub(crate) fn packed(model: &TypedModel, node: &TypedNode) -> TractResult<Option<PackedConv>> {
    let Some((shape, weight, bias)) = plain_conv(model, node)? else { return Ok(None) };
    Ok(Some(PackedConv::new(shape, weight, bias)?))
}

/// A direct f64 sum of a convolution of `groups` groups (OIHW weights, `[co, ci / groups, kh,
/// kw]`): the reference the kernels are tested against.
#[cfg(test)]
pub(crate) fn direct(s: &ConvShape, groups: usize, input: &[f32], weight: &[f32], bias: &[f32]) -> Vec<f32> {
    let (oh, ow) = s.out();
    let (cig, cog) = (s.ci / groups, s.co / groups);
    let at = |c: usize, y: usize, x: usize| -> f64 {
        let (y, x) = (y as isize - s.pad[0] as isize, x as isize - s.pad[1] as isize);
        if y < 0 || x < 0 || y >= s.h as isize || x >= s.w as isize {
            0.0
        } else {
            input[(c * s.h + y as usize) * s.w + x as usize] as f64
        }
    };
    let mut out = vec![];
    for o in 0..s.co {
        for y in 0..oh {
            for x in 0..ow {
                let mut acc = bias[o] as f64;
                for c in 0..cig {
                    for i in 0..s.kh {
                        for j in 0..s.kw {
                            acc += at((o / cog) * cig + c, y * s.stride + i, x * s.stride + j)
                                * weight[((o * cig + c) * s.kh + i) * s.kw + j] as f64;
                        }
                    }
                }
                out.push(acc as f32);
            }
        }
    }
    out
}
