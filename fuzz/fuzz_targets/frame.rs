//! Frame decoding: JPEG through libjpeg-turbo (mozjpeg), PNG/BMP/WebP through `image`.
#![no_main]

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

/// Frames declaring more pixels are only read for their header: decoding is linear in the
/// declared size (a 100-byte JPEG declaring 520 x 49744 fills 26 million grey pixels in 0.6 s; a
/// 169-byte WebP declaring 819 x 3075 decodes in 0.15 s), which libFuzzer's 1 s limit reports as
/// a hang whenever the machine is busy. So, as libjpeg-turbo's own OSS-Fuzz harness does, the
/// pixel decoders are fuzzed on frames up to 1 M pixels (the 1280 x 720 frames trackers read are
/// 0.92 M). Larger declared sizes up to the runtime's limit decode in the same code;
/// `tests/track_cli.rs` checks the limit itself.
const MAX_FUZZED_PIXELS: usize = 1 << 20;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let path = std::path::Path::new("fuzz.jpg");
    match prl_track::frame_size(path, data) {
        Ok((w, h)) if w * h <= MAX_FUZZED_PIXELS => {}
        _ => return,
    }
    if let Ok((frame, _damage)) = prl_track::decode_frame_bytes(path, data) {
        let _ = frame.channel_mean();
    }
});
