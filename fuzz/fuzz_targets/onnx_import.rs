//! `prl import nanotrack`: a third-party backbone and head ONNX pair. The input is the
//! backbone's length (4 bytes, little-endian), the backbone, then the head; both are mutated
//! (seeds: the smallest pair that fits the contract, and the shipped files).
#![no_main]

use std::path::PathBuf;

use prl_compiler::import::{import, nanotrack, FamilyImport, OnnxFile, Parts};

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((len, rest)) = data.split_first_chunk::<4>() else { return };
    let len = (u32::from_le_bytes(*len) as usize).min(rest.len());
    let (backbone, head) = rest.split_at(len);
    let file = |name: &str, bytes: &[u8]| OnnxFile { path: PathBuf::from(name), bytes: bytes.to_vec() };
    let parts = Parts::BackboneHead { backbone: file("fuzz_backbone.onnx", backbone), head: file("fuzz_head.onnx", head) };
    let family = FamilyImport {
        model: nanotrack::MODEL.into(),
        tracker: prl_runtime::TrackerConfig::nanotrack(),
        config: None,
    };
    let _ = import(&parts, &family);
});
