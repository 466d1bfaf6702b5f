//! `.pth` (zip + pickle) and safetensors checkpoints, as `prl build --weights` reads them.
#![no_main]

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = prl_compiler::checkpoint::Checkpoint::from_bytes(std::path::Path::new("fuzz.pth"), data);
});
