//! `prl-runtime`: the slim part of the toolchain that ships on the camera. It loads a compiled
//! plan (decluttered NNEF graphs plus a manifest, optimised by tract when loaded), cuts and
//! resizes crops exactly as the official trackers do, and runs their tracking loop: one crop +
//! state machine for every tracker family (PRL-Track, NanoTrack), with the family's decoding
//! and scoring beside it (`family.rs`) and its settings from the plan. Its dependency tree holds no tract-onnx, no protobuf and no command-line parser.
//!
//! ```no_run
//! # fn main() -> Result<(), prl_runtime::Error> {
//! use prl_runtime::{Frame, Plan, Tracker, BBox};
//! let plan = Plan::load("models/prl-track/plan")?;
//! let config = plan.manifest().tracker.clone();
//! let mut tracker = Tracker::new(plan, config);
//! let first = Frame::from_rgb_image(&image::open("000001.png").unwrap().to_rgb8());
//! tracker.init(&first, BBox { x: 110.0, y: 108.0, w: 36.0, h: 24.0 })?;
//! let next = Frame::from_rgb_image(&image::open("000002.png").unwrap().to_rgb8());
//! let prediction = tracker.track(&next)?;
//! println!("{:?} {}", prediction.bbox, prediction.score);
//! # Ok(()) }
//! ```

mod archive;
mod atomic;
mod config;
mod crop;
mod cropper;
mod error;
mod family;
mod fast_conv;
mod frame;
mod isa;
mod manifest;
mod nnef;
mod ops;
mod plan;
mod quantization;
mod quiet;
mod recording;
mod resize;
mod threads;
mod tracker;

pub use archive::{check_graph_archive, parse_work};
pub use atomic::{commit, temporary_path, write_atomically, write_files_atomically};
pub use config::{Family, LongTermConfig, StateSignal, TrackerConfig};
pub use crop::{crop_to_tensor, get_subwindow};
pub use cropper::{Cropper, TemplateCrop};
pub use error::{Error, Result};
pub use fast_conv::{winograd_warning, Winograd};
pub use frame::{Frame, PixelLayout};
pub use isa::{isa, isa_warning, F32Kernel, Isa, Needs, F32_KERNELS};
pub use manifest::{
    GraphInfo, PlanManifest, Preprocessing, SourceFile, TensorInfo, WeightsInfo, PLAN_FORMAT_VERSION, PLAN_MANIFEST,
};
pub use nnef::nnef;
pub use ops::{
    accelerate, accelerate_with, own_operators, Accelerated, Attention, AttnMix, AttnScores, Binary, BroadcastBinary,
    ChannelMaxPool, ConstMatMul, ConvShape, DepthwiseConv, DepthwiseConvHwc, DepthwiseQConv, DepthwiseXCorr,
    DequantizeU8, LayerNormCore, PackedConv, PackedQConv, Permute, PointwiseConv, QuantizeU8, RowSoftmax,
    SqueezeExcite, WinogradConv,
};
pub use plan::{NodeInfo, NodeTime, Plan, SearchOutput, TemplateFeatures};
pub use quantization::{CalibrationInfo, LayerDecision, QuantLayer, QuantizationInfo};
pub use quiet::catch_quietly;
pub use recording::{record, replay, TensorMatch, RECORDING_INDEX};
pub use resize::{resize_linear_u8, resize_linear_u8_rows};
pub use threads::{set_threads, spread, Threads};
pub use tracker::{confidence, BBox, Prediction, StepTimings, TargetState, Tracker};
