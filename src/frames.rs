//! Decoding frames as OpenCV's `imread(IMREAD_COLOR)` does: JPEG with libjpeg-turbo's decoder
//! (mozjpeg; other decoders differ on ~10% of pixels), everything else with `image`; grey and
//! 16-bit images are converted to 8-bit colour.

use std::path::Path;

use prl_runtime::{Frame, PixelLayout};

use crate::InputError;

/// Read and decode one frame.
pub fn load_frame(path: &Path) -> Result<Frame, InputError> {
    let bad = |msg: String| InputError::new(path, msg);
    let bytes = std::fs::read(path).map_err(|e| bad(format!("cannot read frame: {e}")))?;
    if bytes.starts_with(&[0xff, 0xd8]) {
        let (w, h, rgb) = decode_jpeg(&bytes).map_err(|m| bad(format!("bad JPEG: {m}")))?;
        return Frame::from_raw(w, h, &rgb, PixelLayout::Rgb).map_err(|e| bad(e.to_string()));
    }
    let img = image::load_from_memory(&bytes).map_err(|e| bad(format!("cannot decode image: {e}")))?;
    let rgb = img.to_rgb8();
    if rgb.width() == 0 || rgb.height() == 0 {
        return Err(bad("empty image".into()));
    }
    Ok(Frame::from_rgb_image(&rgb))
}

fn decode_jpeg(bytes: &[u8]) -> Result<(usize, usize, Vec<u8>), String> {
    // mozjpeg reports libjpeg errors by unwinding; turn them into errors.
    std::panic::catch_unwind(|| -> Result<(usize, usize, Vec<u8>), String> {
        let d = mozjpeg::Decompress::new_mem(bytes).map_err(|e| e.to_string())?;
        let mut d = d.rgb().map_err(|e| e.to_string())?;
        let (w, h) = (d.width(), d.height());
        let px: Vec<[u8; 3]> = d.read_scanlines().map_err(|e| e.to_string())?;
        d.finish().map_err(|e| e.to_string())?;
        Ok((w, h, px.into_iter().flatten().collect()))
    })
    .unwrap_or_else(|p| Err(p.downcast_ref::<String>().cloned().unwrap_or_else(|| "decoder failure".into())))
}
