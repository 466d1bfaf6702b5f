//! Frame decoding: JPEG through libjpeg-turbo (mozjpeg), PNG/BMP/WebP through `image`.
#![no_main]

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok((frame, _damage)) = prl_track::decode_frame_bytes(std::path::Path::new("fuzz.jpg"), data) {
        let _ = frame.channel_mean();
    }
});
