//! Frames as the tracker sees them: 8-bit, 3 channels, stored BGR like the official code's
//! OpenCV images.

use crate::{Error, Result};

/// Channel order of a raw interleaved 8-bit buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelLayout {
    /// Blue, green, red (OpenCV's order).
    Bgr,
    /// Red, green, blue (the `image` crate's order).
    Rgb,
}

/// A frame: `height` rows of `width` interleaved BGR pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    width: usize,
    height: usize,
    bgr: Vec<u8>,
}

/// That `len` bytes are exactly a `width` x `height` BGR frame, not empty.
fn check_size(width: usize, height: usize, len: usize) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::Input(format!("empty frame ({width}x{height})")));
    }
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(3));
    if need != Some(len) {
        let need = need.map_or_else(|| "more than usize".to_string(), |n| n.to_string());
        return Err(Error::Input(format!("a {width}x{height} frame needs {need} bytes, got {len}")));
    }
    Ok(())
}

impl Frame {
    /// A frame from a raw interleaved buffer of `width * height * 3` bytes in `layout`.
    pub fn from_raw(width: usize, height: usize, data: &[u8], layout: PixelLayout) -> Result<Self> {
        check_size(width, height, data.len())?;
        let bgr = match layout {
            PixelLayout::Bgr => data.to_vec(),
            PixelLayout::Rgb => data.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect(),
        };
        Ok(Frame { width, height, bgr })
    }

    /// A frame that takes over a BGR buffer of `width * height * 3` bytes (no copy: decoded video
    /// frames).
    pub fn from_bgr(width: usize, height: usize, bgr: Vec<u8>) -> Result<Self> {
        check_size(width, height, bgr.len())?;
        Ok(Frame { width, height, bgr })
    }

    /// A frame from an RGB image of the `image` crate.
    pub fn from_rgb_image(img: &image::RgbImage) -> Self {
        let bgr = img.as_raw().chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect();
        Frame { width: img.width() as usize, height: img.height() as usize, bgr }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Interleaved BGR bytes, row-major.
    pub fn bgr(&self) -> &[u8] {
        &self.bgr
    }

    /// Per-channel mean over the whole frame (B, G, R), in f64 as numpy computes it.
    pub fn channel_mean(&self) -> [f64; 3] {
        let mut sums = [0u64; 3];
        for p in self.bgr.chunks_exact(3) {
            for c in 0..3 {
                sums[c] += p[c] as u64;
            }
        }
        let n = (self.width * self.height) as f64;
        sums.map(|s| s as f64 / n)
    }
}
