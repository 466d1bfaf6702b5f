//! `prl-compiler`: turns a PRL-Track checkpoint (official PyTorch `.pth`, `.safetensors`, or
//! seeded random weights) into the network as two fixed-shape ONNX graphs (template and search),
//! runs them with tract, and checks them against tensors exported from the official
//! implementation; [`import`] brings third-party Siamese trackers (NanoTrack) from their ONNX
//! files into the same two-graph form.
//!
//! Layout: [`checkpoint`] reads weights without Python; [`Weights`] looks them up by scoped
//! prefix so names equal checkpoint keys; [`onnx`] is a generic graph builder; [`net`] is the
//! network; [`OnnxRunner`] runs a graph with tract; [`build_model`] makes model directories,
//! [`compile`] turns them into plans for `prl-runtime`, and [`verify`] compares every stage with
//! golden tensors.

mod artefacts;
pub mod checkpoint;
mod engine;
mod error;
pub mod import;
pub mod net;
pub mod onnx;
mod plan;
pub mod quant;
mod shapes;
mod tensor;
mod verify;
mod weights;

pub use artefacts::{
    build_model, build_model_variant, preprocessing, BuiltModel, Manifest, WeightsSource, MODEL_MANIFEST,
};
pub use engine::{NetworkRunner, OnnxRunner};
pub use error::{Error, Result};
pub use import::{nanotrack::import_nanotrack, FamilyImport, OnnxFile, Parts};
pub use plan::{compile, compile_int8, rebuild_model, CompiledPlan, TRACT_VERSION};
pub use quant::{quantize, Calibration, Method, PerChannel, QuantizeOptions};
pub use tensor::{relative_error, Tensor};
pub use verify::{read_golden, verify, StageReport, VerifyReport};
pub use weights::{Init, Scope, Weights};
