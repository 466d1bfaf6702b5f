//! `prl import nanotrack`: a third-party backbone or head ONNX (the other one as shipped).
//! The first byte says which file the rest replaces.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use prl_compiler::import::{import, nanotrack, FamilyImport, OnnxFile, Parts};

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

fn shipped() -> &'static (OnnxFile, OnnxFile) {
    static FILES: OnceLock<(OnnxFile, OnnxFile)> = OnceLock::new();
    FILES.get_or_init(|| {
        let dir = prl_fuzz::shared().join("models/nanotrack-v2");
        let read = |n: &str| OnnxFile::read(&dir.join(n)).expect("the shipped NanoTrack files");
        (read("nanotrack_backbone_sim.onnx"), read("nanotrack_head_sim.onnx"))
    })
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((&which, bytes)) = data.split_first() else { return };
    let (backbone, head) = shipped().clone();
    let fuzzed = |name: &str| OnnxFile { path: PathBuf::from(name), bytes: bytes.to_vec() };
    let parts = if which % 2 == 0 {
        Parts::BackboneHead { backbone: fuzzed("fuzz_backbone.onnx"), head }
    } else {
        Parts::BackboneHead { backbone, head: fuzzed("fuzz_head.onnx") }
    };
    let family = FamilyImport {
        model: nanotrack::MODEL.into(),
        tracker: prl_runtime::TrackerConfig::nanotrack(),
        config: None,
    };
    let _ = import(&parts, &family);
});
