//! Depthwise convolutions on u8 data (tract's quantised `Conv` with one group per channel, which
//! `QLinearConv` with `group = C` becomes: MobileNet's 3x3 and 5x5 layers in an int8 plan made
//! with `prl quantize --depthwise`) as [`DepthwiseQConv`].
//!
//! tract runs these as an im2col and an integer matrix product per channel: NanoTrack's twenty
//! depthwise layers took 95 ms of a 107 ms search step that way. Here, on AVX-512 VNNI with
//! VBMI, every output row is a sum over the kernel's rows of `vpdpbusd`s: one `vpermb` makes
//! sixteen words of four consecutive input bytes (a kernel row's taps `4g .. 4g + 4` for sixteen
//! output columns, strided by 2 for stride 2) from one 64-byte load of the padded plane, and
//! `vpdpbusd` multiplies them by that kernel row's four i8 weights (zero past the kernel's
//! width) into sixteen i32 sums; the padding holds the input zero point and `x0·Σw` comes off
//! with the bias, so the sums are exactly `Σ (x − x0)·w`. They are requantised in registers as
//! [`super::PackedQConv`] requantises (tract's rounding). On aarch64 with the dot product
//! (`dwqconv_sdot.rs`) `TBL` makes the words and `SDOT` sums them (the bytes flipped to `x − 128`
//! as i8: no mixed-sign dot product on the Orin's A78AE). Elsewhere the same exact sums come
//! from the float depthwise kernel of every other CPU ([`DepthwiseConv`] on `x − x0` and the
//! integer weights: every product and partial sum is an integer under 2^24, so exact in f32),
//! requantised by the same code: the same bytes on every path. Around it, in NanoTrack's
//! `--depthwise` plans, the byte table tract makes of the hard-swish before it is applied as
//! each plane is padded ([`DepthwiseQConv::reading_table`]), and the dequantisation (with its
//! activation) after it as each plane is made ([`DepthwiseQConv::dequantizing`]).

use std::sync::Arc;

use tract_nnef::internal::*;
use tract_nnef::tract_core::ops::cnn::{Conv, KernelFormat};
use tract_nnef::tract_core::ops::element_wise::ElementWiseOp;
use tract_nnef::tract_core::ops::nn::DataFormat;
use tract_nnef::tract_core::ops::quant::LookupTable;

use super::conv::ConvShape;
use super::dwconv::DepthwiseConv;
#[cfg(target_arch = "x86_64")]
use super::dwqconv_kernel;
#[cfg(target_arch = "aarch64")]
use super::dwqconv_sdot;
use super::qconv::{konst_values, quant_params, requant_scales, sum_bound};
use super::qconv_kernel::{exact_fits, requantise};
use super::quant::DequantizeU8;
use super::{all_ones, output_tensor_written, pads_2d};
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
use super::{par_chunks, serial_if_small, with_bytes, SERIAL_MACS};

/// Output columns a step of the integer kernels makes (16 i32 lanes on AVX-512, four registers
/// of four on NEON).
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
pub(super) const LANES: usize = 16;
/// Bytes past a padded plane's end that a load from its last column may reach (64 on AVX-512,
/// 48 on NEON).
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
pub(super) const SLACK: usize = 64;

/// How a [`DepthwiseQConv`] computes its sums.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Path {
    /// The float depthwise kernel on `x − x0` (exact integer sums): every CPU.
    Float,
    /// `vpermb` + `vpdpbusd`: AVX-512 VNNI with VBMI.
    Vnni,
    /// `TBL` + `SDOT`: aarch64 with the dot product.
    Sdot,
}

impl Path {
    /// The paths this CPU runs ([`crate::isa`]): the float one, and the integer kernel where
    /// there is one (the tests run each).
    #[cfg(test)]
    fn here() -> Vec<Path> {
        match Path::best() {
            Path::Float => vec![Path::Float],
            best => vec![Path::Float, best],
        }
    }

    /// The fastest path here.
    fn best() -> Path {
        let isa = crate::isa();
        if cfg!(target_arch = "x86_64") && isa.vnni && isa.vbmi {
            Path::Vnni
        } else if cfg!(target_arch = "aarch64") && isa.dotprod {
            Path::Sdot
        } else {
            Path::Float
        }
    }
}

/// `y[n,c,oy,ox] = sat_u8(round((Σ_{i,j} (pad(x)[n,c,s·oy+i,s·ox+j] − x0)·w[c,i,j] + bias[c]) ·
/// scale[c]) + y0)`, `pad` with the zero point `x0`, stride `s` 1 or 2: a depthwise
/// convolution of u8 data with constant i8 weights (zero point 0) and i32 bias.
#[derive(Clone)]
pub struct DepthwiseQConv {
    /// `ci == co` channels; the kernel is `kh` x `kw`.
    shape: ConvShape,
    /// The data has a batch axis (NCHW); else it is CHW (tract drops a batch axis of 1).
    batch: bool,
    /// Per channel, `kh · groups` words: kernel row `i`'s taps `4g .. 4g + 4` as four i8 (zero
    /// past the kernel's width), `groups = ⌈kw / 4⌉`.
    words: Arc<Vec<i32>>,
    /// Per channel `bias − x0·Σw`: what the VNNI path's sums of raw bytes need added.
    offset: Arc<Vec<i32>>,
    /// Per channel `Σw`: the SDOT path's sums of `x − 128` need `128·Σw` more.
    wsum: Arc<Vec<i32>>,
    /// Per channel: what the portable path's sums of `x − x0` need added.
    bias: Arc<Vec<i32>>,
    /// Per channel `x_scale · w_scale / y_scale`, as tract computes it
    /// ([`super::qconv::requant_scales`]).
    scale: Arc<Vec<f32>>,
    /// One scale for every channel: tract's exact fixed-point product
    /// ([`super::qconv_kernel::requant_one`]).
    exact: bool,
    x0: u8,
    y0: u8,
    /// The output's datum type (u8 with its quantisation parameters).
    out_dt: DatumType,
    /// The portable path: the float kernel on `x − x0` with the integer weights, bias 0.
    float: DepthwiseConv,
    /// A byte table the input goes through first ([`Self::reading_table`]).
    table: Option<Arc<[u8; 256]>>,
    /// The output is f32, each plane dequantised by this (and its activation) as it is made
    /// ([`Self::dequantizing`]).
    dequant: Option<DequantizeU8>,
}

impl std::fmt::Debug for DepthwiseQConv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DepthwiseQConv({:?})", self.shape)
    }
}

impl PartialEq for DepthwiseQConv {
    fn eq(&self, other: &Self) -> bool {
        self.shape == other.shape
            && self.batch == other.batch
            && self.words == other.words
            && self.offset == other.offset
            && self.wsum == other.wsum
            && self.bias == other.bias
            && super::same_bits(&self.scale, &other.scale)
            && (self.exact, self.x0, self.y0, self.out_dt) == (other.exact, other.x0, other.y0, other.out_dt)
            && self.table == other.table
            && self.dequant == other.dequant
    }
}

impl Eq for DepthwiseQConv {}

impl DepthwiseQConv {
    /// The convolution of `shape` (`ci == co`, stride 1 or 2) with i8 `kernel` `[c, 1, kh, kw]`,
    /// i32 `bias` (one per channel), input zero point `x0`, per-channel `scale`s (`x_scale ·
    /// w_scale / y_scale`), output zero point `y0` and datum type `out_dt`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        shape: ConvShape,
        batch: bool,
        kernel: &[i8],
        bias: &[i32],
        (x0, scale, y0): (u8, &[f32], u8),
        out_dt: DatumType,
    ) -> TractResult<DepthwiseQConv> {
        let (c, kh, kw) = (shape.ci, shape.kh, shape.kw);
        ensure!(shape.co == c && matches!(shape.stride, 1 | 2), "DepthwiseQConv: shape {shape:?}");
        ensure!(
            kernel.len() == c * kh * kw && bias.len() == c && scale.len() == c,
            "DepthwiseQConv: parameters for {shape:?}"
        );
        let groups = kw.div_ceil(4);
        let mut words = vec![0i32; c * kh * groups];
        let mut offset = vec![0i32; c];
        let mut wsum = vec![0i32; c];
        for ch in 0..c {
            let taps = &kernel[ch * kh * kw..(ch + 1) * kh * kw];
            for i in 0..kh {
                for g in 0..groups {
                    let mut b = [0u8; 4];
                    for (t, b) in b.iter_mut().enumerate().take(kw.saturating_sub(4 * g)) {
                        *b = taps[i * kw + 4 * g + t] as u8;
                    }
                    words[(ch * kh + i) * groups + g] = i32::from_le_bytes(b);
                }
            }
            let sum: i32 = taps.iter().map(|&w| w as i32).sum();
            offset[ch] = bias[ch] - x0 as i32 * sum;
            wsum[ch] = sum;
        }
        let exact = scale.iter().all(|v| v.to_bits() == scale[0].to_bits());
        let weights: Vec<f32> = kernel.iter().map(|&w| w as f32).collect();
        let float =
            DepthwiseConv::new(shape.clone(), batch, &weights, &[0.0])?.reading(DequantizeU8::new(1.0, x0 as i32));
        Ok(DepthwiseQConv {
            shape,
            batch,
            words: Arc::new(words),
            offset: Arc::new(offset),
            wsum: Arc::new(wsum),
            bias: Arc::new(bias.to_vec()),
            scale: Arc::new(scale.to_vec()),
            exact,
            x0,
            y0,
            out_dt,
            float,
            table: None,
            dequant: None,
        })
    }

    /// The convolution followed by `dequant`: each output plane dequantised (with the
    /// dequantiser's activation) while it is in the thread's cache, the values `dequant` would
    /// have written from the bytes. MobileNet's depthwise layers with a hard-swish and a
    /// squeeze-excitation after them (NanoTrack's blocks 4 to 8) feed f32 operators.
    pub(crate) fn dequantizing(self, dequant: DequantizeU8) -> DepthwiseQConv {
        DepthwiseQConv { dequant: Some(dequant), ..self }
    }

    /// The convolution of `table` applied to the input's bytes, reading the bytes before it:
    /// the table is applied as each plane is copied into the padded one. tract makes such a
    /// table of a dequantisation, an element-wise function and a quantisation (MobileNet's
    /// hard-swish between an integer pointwise layer and a depthwise one), and ran it as a
    /// pass of its own (NanoTrack: four, 0.07 ms a step on one thread).
    pub(crate) fn reading_table(self, table: [u8; 256]) -> DepthwiseQConv {
        DepthwiseQConv { table: Some(Arc::new(table)), ..self }
    }

    /// The padded plane's rows and row length (no phases: the byte permutes and lookups take
    /// every second byte for stride 2), with [`SLACK`] bytes after it.
    #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
    fn padded_len(&self) -> usize {
        let (hp, wp) = self.shape.padded();
        hp * wp + SLACK
    }

    /// Channel `ch` of one image on `path` (VNNI or SDOT): `src` (`[h, w]` bytes) into `dst`
    /// (`[oh, ow]`), with `pad` ([`Self::padded_len`] bytes whose borders hold the path's
    /// padding, [`Self::padding`]).
    #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
    fn channel(&self, path: Path, ch: usize, src: &[u8], pad: &mut [u8], dst: &mut [u8]) {
        let s = &self.shape;
        let per = s.kh * s.kw.div_ceil(4);
        let words = &self.words[ch * per..(ch + 1) * per];
        let (oh, ow) = s.out();
        assert!(
            src.len() == s.h * s.w && pad.len() >= self.padded_len() && dst.len() == oh * ow,
            "planes of the shape"
        );
        assert!(path == Path::best(), "{path:?} runs here");
        match path {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: the CPU has AVX-512F, BW, VL, VNNI and VBMI ([`Path::best`], asserted);
            // `src`, `pad` (the padded plane and its slack) and `dst` are the planes of the
            // shape (asserted).
            Path::Vnni => unsafe {
                match &self.table {
                    None => dwqconv_kernel::copy_rows::<false>(s, src, pad, &[0; 256]),
                    Some(t) => dwqconv_kernel::copy_rows::<true>(s, src, pad, t),
                }
                let q = (self.offset[ch], self.scale[ch], self.exact, self.y0);
                dwqconv_kernel::plane(s, pad, words, q, dst)
            },
            #[cfg(target_arch = "aarch64")]
            Path::Sdot => {
                dwqconv_sdot::copy_rows(s, src, pad, self.table.as_deref());
                let q = (self.offset[ch] + 128 * self.wsum[ch], self.scale[ch], self.exact, self.y0);
                // SAFETY: the CPU has the dot product ([`Path::best`], asserted); `pad` (the
                // padded plane and its slack) and `dst` are the planes of the shape (asserted).
                unsafe { dwqconv_sdot::plane(s, pad, words, q, dst) }
            }
            _ => unreachable!("{path:?} is not an integer kernel of this architecture"),
        }
    }

    /// The byte a path's padded plane holds outside the input: `x0`, flipped to `x0 − 128` on
    /// SDOT (its planes hold `x − 128` as i8).
    #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
    fn padding(&self, path: Path) -> u8 {
        if path == Path::Sdot {
            self.x0 ^ 0x80
        } else {
            self.x0
        }
    }
}

impl Op for DepthwiseQConv {
    fn name(&self) -> StaticName {
        "DepthwiseQConv".into()
    }

    fn info(&self) -> TractResult<Vec<String>> {
        let s = &self.shape;
        let path = match Path::best() {
            Path::Vnni => "AVX-512 VNNI",
            Path::Sdot => "aarch64 SDOT",
            Path::Float => "the float kernel's exact sums",
        };
        let scale = if self.exact { "one scale, exact product" } else { "per-channel scales" };
        let table = if self.table.is_some() { ", input through a byte table" } else { "" };
        let out = if self.dequant.is_some() { ", output dequantised" } else { "" };
        Ok(vec![format!(
            "{}x{} kernel, stride {}, {} channels, pad {:?}, u8 x i8 on {path}, {scale}{table}{out}",
            s.kh, s.kw, s.stride, s.ci, s.pad
        )])
    }

    op_as_typed_op!();
}

impl EvalOp for DepthwiseQConv {
    op_out_of_plan!();

    fn eval(&self, ctx: &EvalContext, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        let input = args_1!(inputs);
        Ok(tvec!(self.run(ctx, input, Path::best())?.into_tvalue()))
    }
}

impl DepthwiseQConv {
    /// The output for `input` on `path`.
    fn run(&self, ctx: &EvalContext, input: TValue, path: Path) -> TractResult<Tensor> {
        let s = &self.shape;
        let (n, c, h, w) = match (self.batch, input.shape()) {
            (true, &[n, c, h, w]) => (n, c, h, w),
            (false, &[c, h, w]) => (1, c, h, w),
            _ => bail!("DepthwiseQConv: input {:?} for {s:?}", input.shape()),
        };
        ensure!((c, h, w) == (s.ci, s.h, s.w), "DepthwiseQConv: input {:?} for {s:?}", input.shape());
        ensure!(input.datum_type().unquantized() == u8::datum_type(), "DepthwiseQConv: input is not u8");
        let (oh, ow) = s.out();
        let shape: TVec<usize> = if self.batch { tvec![n, c, oh, ow] } else { tvec![c, oh, ow] };
        let plane = oh * ow;
        if path != Path::Float {
            return self.run_words(&input, &shape, path);
        }
        // The float kernel's sums (exact integers), requantised plane by plane.
        let input = match &self.table {
            None => input,
            Some(t) => {
                let mut looked = input.into_tensor();
                // SAFETY: u8 storage (checked above); every byte replaced by its entry.
                unsafe { looked.try_as_plain_ram_mut()?.as_slice_mut_unchecked::<u8>() }
                    .iter_mut()
                    .for_each(|b| *b = t[*b as usize]);
                looked.into_tvalue()
            }
        };
        let sums = self.float.eval(ctx, tvec![input])?.remove(0);
        let sums = sums.try_as_plain_ram()?;
        let sums = sums.as_slice::<f32>()?;
        // SAFETY: every plane of the output is requantised whole.
        let mut out = unsafe {
            output_tensor_written(&shape, |out: &mut [u8]| {
                let mut ints = vec![0i32; plane];
                for (p, (o, f)) in out.chunks_exact_mut(plane).zip(sums.chunks_exact(plane)).enumerate() {
                    ints.iter_mut().zip(f).for_each(|(i, &f)| *i = f as i32);
                    requantise(&ints, self.bias[p % c], self.scale[p % c], self.exact, self.y0, o);
                }
                Ok(())
            })?
        };
        if let Some(dq) = &self.dequant {
            let bytes = out.try_as_plain_ram()?;
            // SAFETY: u8 storage, just written.
            let bytes = unsafe { bytes.as_slice_unchecked::<u8>() };
            // SAFETY: the whole output is dequantised.
            return unsafe {
                output_tensor_written(&shape, |values: &mut [f32]| {
                    dq.apply(bytes, values);
                    Ok(())
                })
            };
        }
        // SAFETY: same storage type (u8), the output fact's quantisation parameters.
        unsafe { out.set_datum_type(self.out_dt) };
        Ok(out)
    }

    /// [`EvalOp::eval`] on an integer kernel (`path`, VNNI or SDOT): channels in groups of
    /// about `SERIAL_MACS / 8` multiply-adds over tract's threads, each group with one padded
    /// plane (its borders [`Self::padding`]).
    #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
    fn run_words(&self, input: &Tensor, shape: &[usize], path: Path) -> TractResult<Tensor> {
        let s = &self.shape;
        let c = s.ci;
        let input = input.try_as_plain_ram()?;
        // SAFETY: the datum type is u8, possibly with quantisation parameters (checked).
        let input = unsafe { input.as_slice_unchecked::<u8>() };
        let (oh, ow) = s.out();
        let (plane, in_plane) = (oh * ow, s.h * s.w);
        let images = input.len() / (c * in_plane);
        let macs = plane * s.kh * s.kw;
        let group = (SERIAL_MACS / 8 / macs.max(1)).clamp(1, images * c);
        let src = |p: usize| &input[p * in_plane..(p + 1) * in_plane];
        // SAFETY (both): every plane of every group is written whole.
        serial_if_small(images * c * macs, || match &self.dequant {
            None => unsafe {
                let mut out = output_tensor_written(shape, |out: &mut [u8]| {
                    par_chunks(out, group * plane, |g, dst| {
                        with_bytes(self.padded_len(), |pad| {
                            // The borders read x0; the rows are copied in for each channel.
                            pad.fill(self.padding(path));
                            for (k, d) in dst.chunks_exact_mut(plane).enumerate() {
                                let p = g * group + k;
                                self.channel(path, p % c, src(p), pad, d);
                            }
                        })
                    });
                    Ok(())
                })?;
                // SAFETY: same storage type (u8), the output fact's quantisation parameters.
                out.set_datum_type(self.out_dt);
                Ok(out)
            },
            Some(dq) => unsafe {
                output_tensor_written(shape, |out: &mut [f32]| {
                    par_chunks(out, group * plane, |g, dst| {
                        with_bytes(self.padded_len() + plane, |buf| {
                            let (pad, bytes) = buf.split_at_mut(self.padded_len());
                            pad.fill(self.padding(path));
                            for (k, d) in dst.chunks_exact_mut(plane).enumerate() {
                                let p = g * group + k;
                                self.channel(path, p % c, src(p), pad, bytes);
                                dq.apply(bytes, d);
                            }
                        })
                    });
                    Ok(())
                })
            },
        })
    }

    /// No integer kernel elsewhere ([`Path::best`] is the float one).
    #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
    fn run_words(&self, _: &Tensor, _: &[usize], path: Path) -> TractResult<Tensor> {
        bail!("DepthwiseQConv: no {path:?} kernel on this architecture")
    }
}

impl TypedOp for DepthwiseQConv {
    fn output_facts(&self, inputs: &[&TypedFact]) -> TractResult<TVec<TypedFact>> {
        let (oh, ow) = self.shape.out();
        let (c, oh, ow): (TDim, TDim, TDim) = (self.shape.co.into(), oh.into(), ow.into());
        let shape: TVec<TDim> =
            if self.batch { tvec![inputs[0].shape[0].clone(), c, oh, ow] } else { tvec![c, oh, ow] };
        let dt = if self.dequant.is_some() { f32::datum_type() } else { self.out_dt };
        Ok(tvec!(dt.fact(shape)))
    }

    fn cost(&self, inputs: &[&TypedFact]) -> TractResult<TVec<(Cost, TDim)>> {
        let (oh, ow) = self.shape.out();
        let s = &self.shape;
        let n = if self.batch { inputs[0].shape[0].clone() } else { 1.into() };
        Ok(tvec!((Cost::FMA(i32::datum_type()), n * (s.co * oh * ow * s.kh * s.kw))))
    }

    as_op!();
}

/// `op` reading the input of the u8 `LookupTable` that makes `x` (its input, past a plain
/// cast), where nothing else reads that table ([`DepthwiseQConv::reading_table`]), with the
/// input it then reads; else `op` and `x`.
pub(crate) fn past_table(model: &TypedModel, x: OutletId, op: DepthwiseQConv) -> (DepthwiseQConv, OutletId) {
    let prev = model.node(x.node);
    let table = prev
        .op_as::<ElementWiseOp>()
        .and_then(|e| e.0.downcast_ref::<LookupTable>())
        .filter(|_| super::act::sole_consumer(model, prev).is_some())
        .and_then(|l| <[u8; 256]>::try_from(l.table.table()).ok());
    match table {
        Some(t) if model.outlet_fact(prev.inputs[0]).is_ok_and(|f| f.datum_type.unquantized() == u8::datum_type()) => {
            (op.reading_table(t), prev.inputs[0])
        }
        _ => (op, x),
    }
}

/// The dequantisation (tract's, with the activation after it) that alone reads `node`'s output
/// (past a plain cast), and the nodes it stands for: the convolution can write its values
/// ([`DepthwiseQConv::dequantizing`]).
pub(crate) fn dequantized_after(
    model: &TypedModel,
    node: &TypedNode,
) -> TractResult<Option<(DequantizeU8, Vec<usize>)>> {
    use tract_nnef::tract_core::ops::cast::Cast;
    let Some(mut next) = super::act::sole_consumer(model, node) else { return Ok(None) };
    let mut chain = vec![];
    // Only a cast that adds or drops quantisation parameters (one between two quantised types
    // rescales the bytes).
    let from = node.outputs[0].fact.datum_type;
    let plain = |to: DatumType| to.unquantized() == from.unquantized() && !(from.is_quantized() && to.is_quantized());
    if next.op_as::<Cast>().is_some_and(|c| plain(c.to)) {
        chain.push(next.id);
        let Some(after) = super::act::sole_consumer(model, next) else { return Ok(None) };
        next = after;
    }
    let Some(dq) = super::quant::dequantize_u8(model, next)? else { return Ok(None) };
    let shape = next.outputs[0].fact.shape.as_concrete().unwrap_or_default();
    Ok(Some(match super::act::tail(model, next, None)?.and_then(|t| Some((dq.fused(&t, shape)?, t.chain))) {
        Some((fused, c)) => {
            chain.extend(c);
            (fused, chain)
        }
        None => {
            chain.push(next.id);
            (dq, chain)
        }
    }))
}

/// The [`DepthwiseQConv`] for `node` if it is tract's quantised `Conv` with one group per
/// channel (OIHW weights `[c, 1, kh, kw]`, NCHW or CHW data, stride 1 or 2, no dilation), u8
/// input and output, constant i8 weights of zero point 0, an i32 bias and constant
/// quantisation parameters.
pub(crate) fn depthwise_q(model: &TypedModel, node: &TypedNode) -> TractResult<Option<DepthwiseQConv>> {
    if !super::own_int8_operators() {
        return Ok(None);
    }
    let Some(conv) = node.op_as::<Conv>() else { return Ok(None) };
    let facts = model.node_input_facts(node.id)?;
    let ps = &conv.pool_spec;
    let plain = conv.q_params.is_some()
        && conv.kernel_fmt == KernelFormat::OIHW
        && ps.kernel_shape.len() == 2
        && all_ones(&ps.dilations)
        && facts.len() == 9
        && node.outputs[0].fact.datum_type.unquantized() == u8::datum_type()
        && facts[0].datum_type.unquantized() == u8::datum_type()
        && facts[1].datum_type.unquantized() == i8::datum_type();
    if !plain {
        return Ok(None);
    }
    let Some(input) = facts[0].shape.as_concrete() else { return Ok(None) };
    let (batch, c, h, w) = match (ps.data_format, input) {
        (DataFormat::NCHW, &[_, c, h, w]) => (true, c, h, w),
        (DataFormat::CHW, &[c, h, w]) => (false, c, h, w),
        _ => return Ok(None),
    };
    if !(conv.group > 1 && conv.group == c && ps.output_channels == c) {
        return Ok(None);
    }
    let stride = match ps.strides.as_deref() {
        None | Some([1, 1]) => 1,
        Some([2, 2]) => 2,
        _ => return Ok(None),
    };
    let Some(pad) = pads_2d(&ps.padding) else { return Ok(None) };
    let (kh, kw) = (ps.kernel_shape[0], ps.kernel_shape[1]);
    let shape = ConvShape { ci: c, h, w, co: c, kh, kw, pad, stride };
    if shape.padded().0 < kh || shape.padded().1 < kw {
        return Ok(None);
    }
    let (Some(kernel), Some(bias)) = (&facts[1].konst, konst_values::<i32>(facts[2], c)?) else { return Ok(None) };
    let Some(q) = quant_params(&facts, c)? else { return Ok(None) };
    if kernel.len() != c * kh * kw {
        return Ok(None);
    }
    let kernel = kernel.try_as_plain_ram()?;
    // SAFETY: the kernel's datum type is i8, possibly with quantisation parameters (checked).
    let kernel = unsafe { kernel.as_slice_unchecked::<i8>() };
    let scale = requant_scales(q.x_scale, &q.k_scale, q.y_scale, c);
    let op = DepthwiseQConv::new(shape, batch, kernel, &bias, (q.x0, &scale, q.y0), node.outputs[0].fact.datum_type)?;
    // tract's exact product is only ours within these bounds (see [`exact_fits`]).
    if op.exact && !exact_fits(scale[0], sum_bound(kernel, &bias, kh * kw)) {
        return Ok(None);
    }
    Ok(Some(op))
}

#[cfg(test)]
mod tests;
