//! pysot dataset JSON files (`{video: {img_names, gt_rect, init_rect, attr}}`).
#![no_main]

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let root = std::path::Path::new("/nonexistent-dataset");
    if let Ok(d) = prl_track::parse_pysot_json(root, &root.join("fuzz.json"), &text) {
        let _ = d.attributes();
    }
});
