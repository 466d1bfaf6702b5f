//! Annotation and result files (`x,y,w,h` per line) and `--init` boxes.
#![no_main]

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(boxes) = prl_track::parse_boxes_text(std::path::Path::new("fuzz.txt"), &text) {
        // Results against ground truth, as `prl eval` scores them.
        let half = boxes.len() / 2;
        let _ = prl_track::ope::evaluate(&boxes[..half], &boxes[half..half * 2]);
    }
    let _ = prl_track::parse_box(&text);
});
