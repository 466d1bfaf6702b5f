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

/// That `len` bytes are exactly a `width` x `height` BGR frame, not empty, its sides within
/// u32 (an image's).
fn check_size(width: usize, height: usize, len: usize) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::Input(format!("empty frame ({width}x{height})")));
    }
    if u32::try_from(width).is_err() || u32::try_from(height).is_err() {
        return Err(Error::Input(format!("a {width}x{height} frame: sides over {}", u32::MAX)));
    }
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(3));
    if need != Some(len) {
        let need = need.map_or_else(|| "more than usize".to_string(), |n| n.to_string());
        return Err(Error::Input(format!("a {width}x{height} frame needs {need} bytes, got {len}")));
    }
    Ok(())
}

/// Interleaved pixels of three bytes with the first and third swapped (BGR <-> RGB).
fn swap_red_blue(data: &[u8]) -> Vec<u8> {
    data.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect()
}

impl Frame {
    /// A frame from a raw interleaved buffer of `width * height * 3` bytes in `layout`.
    pub fn from_raw(width: usize, height: usize, data: &[u8], layout: PixelLayout) -> Result<Self> {
        check_size(width, height, data.len())?;
        let bgr = match layout {
            PixelLayout::Bgr => data.to_vec(),
            PixelLayout::Rgb => swap_red_blue(data),
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
        Frame { width: img.width() as usize, height: img.height() as usize, bgr: swap_red_blue(img.as_raw()) }
    }

    /// The frame as an RGB image of the `image` crate (to draw on or save).
    pub fn to_rgb_image(&self) -> image::RgbImage {
        let (w, h) = (self.width as u32, self.height as u32);
        // A frame's sides fit in u32 and its buffer is `width · height · 3` bytes
        // ([`check_size`] where it is made), so the image takes it.
        image::RgbImage::from_raw(w, h, swap_red_blue(&self.bgr)).expect("a frame's buffer fits its size")
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

    /// Per-channel mean over the whole frame (B, G, R), in f64 as numpy computes it (the
    /// integer sums are exact in f64, so the order of summation does not matter).
    pub fn channel_mean(&self) -> [f64; 3] {
        let sums = channel_sums(&self.bgr);
        let n = (self.width * self.height) as f64;
        sums.map(|s| s as f64 / n)
    }
}

/// Bytes a step of [`channel_sums`]: 16 whole pixels in 48 `u16` lanes (lane `i` holds channel
/// `i % 3`), which the compiler vectorises.
const SUM_STEP: usize = 48;
/// Steps between the lanes' flushes into `u64`: 257 x 255 = `u16::MAX`.
const SUM_FLUSH: usize = 257;

/// Exact per-channel sums of interleaved 3-channel bytes. A loop over pixels, one channel at a
/// time, took 0.9 ms of a 1280x720 frame (as long as NanoTrack's template network); this about
/// 0.3 (AMD EPYC Zen 3, `perf` against the step's other work).
fn channel_sums(bytes: &[u8]) -> [u64; 3] {
    let mut sums = [0u64; 3];
    let blocks = bytes.chunks_exact(SUM_STEP * SUM_FLUSH);
    let tail = blocks.remainder();
    for block in blocks {
        add_lanes(&mut sums, &step_sums(block));
    }
    add_lanes(&mut sums, &step_sums(tail));
    for p in tail[tail.len() / SUM_STEP * SUM_STEP..].chunks_exact(3) {
        for c in 0..3 {
            sums[c] += u64::from(p[c]);
        }
    }
    sums
}

/// The lanes' sums over the whole steps of `bytes` (at most [`SUM_FLUSH`] of them).
fn step_sums(bytes: &[u8]) -> [u16; SUM_STEP] {
    debug_assert!(bytes.len() / SUM_STEP <= SUM_FLUSH);
    let mut lanes = [0u16; SUM_STEP];
    for chunk in bytes.chunks_exact(SUM_STEP) {
        let chunk: &[u8; SUM_STEP] = chunk.try_into().expect("steps of SUM_STEP bytes");
        for i in 0..SUM_STEP {
            lanes[i] += u16::from(chunk[i]);
        }
    }
    lanes
}

/// Fold a step's lanes into the channels' sums.
fn add_lanes(sums: &mut [u64; 3], lanes: &[u16; SUM_STEP]) {
    for (i, l) in lanes.iter().enumerate() {
        sums[i % 3] += u64::from(*l);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain per-pixel sums.
    fn plain(bytes: &[u8]) -> [u64; 3] {
        let mut sums = [0u64; 3];
        for p in bytes.chunks_exact(3) {
            for c in 0..3 {
                sums[c] += u64::from(p[c]);
            }
        }
        sums
    }

    #[test]
    fn channel_sums_equal_the_plain_sums() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 24) as u8
        };
        // Short frames (the tail alone), a few steps, and more than one flush block.
        for pixels in [1, 5, 16, 17, 1000, SUM_STEP * SUM_FLUSH / 3 + 7, 1280 * 720] {
            let bytes: Vec<u8> = (0..pixels * 3).map(|_| next()).collect();
            assert_eq!(channel_sums(&bytes), plain(&bytes), "{pixels} pixels");
        }
        // Every byte 255: the lanes at their largest before a flush.
        let full = vec![255u8; 3 * (SUM_STEP * SUM_FLUSH / 3 * 2 + 1)];
        assert_eq!(channel_sums(&full), plain(&full));
        let f = Frame::from_bgr(2, 1, vec![1, 2, 3, 4, 5, 6]).unwrap();
        assert_eq!(f.channel_mean(), [2.5, 3.5, 4.5]);
    }

    #[test]
    fn rgb_images_round_trip_and_sizes_are_checked() {
        let f = Frame::from_bgr(2, 1, vec![1, 2, 3, 4, 5, 6]).unwrap();
        let img = f.to_rgb_image();
        assert_eq!((img.width(), img.height(), img.as_raw().as_slice()), (2, 1, &[3u8, 2, 1, 6, 5, 4][..]));
        assert_eq!(Frame::from_rgb_image(&img), f);
        assert_eq!(Frame::from_raw(2, 1, img.as_raw(), PixelLayout::Rgb).unwrap(), f);
        assert!(Frame::from_bgr(2, 1, vec![0; 5]).is_err());
        assert!(Frame::from_bgr(0, 1, vec![]).is_err());
        let wide = u32::MAX as usize + 1;
        let err = check_size(wide, 1, wide * 3).unwrap_err().to_string();
        assert!(err.contains("sides over"), "{err}");
    }
}
