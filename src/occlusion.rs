//! Lost-and-found sequences made from a real one, for measuring what tells a lost target from a
//! tracked one and whether a tracker finds it again.
//!
//! The made sequence is a moving view (a window of the source frames): the target is covered
//! for a span of frames by a patch of the frame's own background, and the view pans while it
//! is hidden, so the target comes back somewhere else in the picture, as it does when a drone
//! keeps flying while a tree or a building hides what it follows. Ground truth is in the view's
//! coordinates, `NaN` on frames where the target is hidden or out of view (UAV123's convention
//! for an absent target).

use std::path::Path;

use prl_runtime::Frame;

use crate::{load_frame, InputError, Sequence};

/// How a lost-and-found sequence is made from a source sequence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LostAndFound {
    /// First frame (0-based) on which the target is covered.
    pub hide_from: usize,
    /// How many frames it stays covered.
    pub hide_frames: usize,
    /// How far the view moves, in source pixels (x, y), over the hidden frames (it stays
    /// there afterwards).
    pub pan: (i64, i64),
    /// The view's width and height in pixels.
    pub view: (usize, usize),
}

/// Why a lost-and-found sequence could not be made.
#[derive(Debug, thiserror::Error)]
pub enum OcclusionError {
    /// A source frame or file could not be read.
    #[error(transparent)]
    Input(#[from] InputError),
    /// The settings do not fit the source.
    #[error("{0}")]
    Spec(String),
    /// An output could not be written.
    #[error("{path}: cannot write: {msg}")]
    Write {
        /// The file.
        path: String,
        /// What went wrong.
        msg: String,
    },
}

/// Margin around the ground-truth box that the cover also hides (a fraction of the box's side,
/// each way, plus 4 pixels), so that no edge of the target shows.
const COVER_MARGIN: f64 = 0.25;

impl LostAndFound {
    /// The view's top-left corner on source frame `i` (of a `w`x`h` source): centred so that
    /// the views before and after the pan both fit, moving linearly while the target is hidden.
    pub fn view_origin(&self, i: usize, w: usize, h: usize) -> (i64, i64) {
        let (vw, vh) = (self.view.0 as i64, self.view.1 as i64);
        let x0 = (w as i64 - vw - self.pan.0) / 2;
        let y0 = (h as i64 - vh - self.pan.1) / 2;
        let t = if i < self.hide_from {
            0.0
        } else {
            ((i - self.hide_from + 1) as f64 / (self.hide_frames + 1) as f64).min(1.0)
        };
        (x0 + (self.pan.0 as f64 * t).round() as i64, y0 + (self.pan.1 as f64 * t).round() as i64)
    }

    /// Whether the target is covered on frame `i`.
    pub fn hidden(&self, i: usize) -> bool {
        (self.hide_from..self.hide_from + self.hide_frames).contains(&i)
    }

    fn check(&self, w: usize, h: usize, frames: usize) -> Result<(), OcclusionError> {
        let (vw, vh) = self.view;
        let spare = |side: usize, v: usize, pan: i64| side as i64 - v as i64 - pan.abs();
        if vw < 16 || vh < 16 || spare(w, vw, self.pan.0) < 0 || spare(h, vh, self.pan.1) < 0 {
            return Err(OcclusionError::Spec(format!(
                "a {vw}x{vh} view panning by {},{} does not fit in {w}x{h} frames",
                self.pan.0, self.pan.1
            )));
        }
        if self.hide_frames == 0 || self.hide_from == 0 || self.hide_from + self.hide_frames >= frames {
            return Err(OcclusionError::Spec(format!(
                "hiding frames {}..{} needs a visible first frame and a visible frame after (the sequence has {frames})",
                self.hide_from,
                self.hide_from + self.hide_frames
            )));
        }
        Ok(())
    }

    /// The view of source frame `i` (its ground truth `gt`): the frame with the target covered
    /// when hidden, cut to the view, and the box in view coordinates (`NaN` when hidden, when
    /// the source has none, or when the box's centre is outside the view; else clipped to it).
    pub fn make_frame(&self, i: usize, src: &Frame, gt: [f64; 4]) -> (Frame, [f64; 4]) {
        let (w, h) = (src.width(), src.height());
        let mut bgr = src.bgr().to_vec();
        if self.hidden(i) && gt.iter().all(|v| v.is_finite()) {
            cover(&mut bgr, w, h, gt);
        }
        let (ox, oy) = self.view_origin(i, w, h);
        let (vw, vh) = self.view;
        let mut view = Vec::with_capacity(vw * vh * 3);
        for y in 0..vh {
            let at = ((oy as usize + y) * w + ox as usize) * 3;
            view.extend_from_slice(&bgr[at..at + vw * 3]);
        }
        let frame = Frame::from_bgr(vw, vh, view).expect("the view's size matches its pixels");
        let nan = [f64::NAN; 4];
        if self.hidden(i) || gt.iter().any(|v| !v.is_finite()) {
            return (frame, nan);
        }
        let (x, y) = (gt[0] - ox as f64, gt[1] - oy as f64);
        let (cx, cy) = (x + gt[2] / 2.0, y + gt[3] / 2.0);
        if !(0.0..vw as f64).contains(&cx) || !(0.0..vh as f64).contains(&cy) {
            return (frame, nan);
        }
        let (x0, y0) = (x.max(0.0), y.max(0.0));
        let (x1, y1) = ((x + gt[2]).min(vw as f64), (y + gt[3]).min(vh as f64));
        (frame, [x0, y0, x1 - x0, y1 - y0])
    }

    /// Make the lost-and-found version of the sequence in `src_dir` (frames and ground truth)
    /// in `out_dir`: `img/000001.png`... (lossless) and `groundtruth_rect.txt`. Files are
    /// written to temporary names and renamed, so an interrupted run leaves no half-written
    /// frame under a final name. Returns how many frames were written.
    pub fn make(&self, src_dir: &Path, out_dir: &Path) -> Result<usize, OcclusionError> {
        let seq = Sequence::open(src_dir)?;
        let gt = seq.groundtruth().ok_or_else(|| {
            OcclusionError::Spec(format!("{}: no groundtruth_rect.txt: the target's box is needed", src_dir.display()))
        })?;
        let first = load_frame(&seq.frames[0])?;
        self.check(first.width(), first.height(), seq.frames.len())?;
        let img = out_dir.join("img");
        let werr = |p: &Path, e: &dyn std::fmt::Display| OcclusionError::Write {
            path: p.display().to_string(),
            msg: e.to_string(),
        };
        std::fs::create_dir_all(&img).map_err(|e| werr(&img, &e))?;
        let mut text = String::new();
        for (i, path) in seq.frames.iter().enumerate() {
            let src = if i == 0 { first.clone() } else { load_frame(path)? };
            if (src.width(), src.height()) != (first.width(), first.height()) {
                return Err(OcclusionError::Spec(format!(
                    "{}: frame size differs from the first frame's",
                    path.display()
                )));
            }
            let (frame, b) = self.make_frame(i, &src, gt[i]);
            let name = img.join(format!("{:06}.png", i + 1));
            let tmp = img.join(format!(".{:06}.png.tmp", i + 1));
            let image = frame.to_rgb_image();
            image.save_with_format(&tmp, image::ImageFormat::Png).map_err(|e| werr(&tmp, &e))?;
            std::fs::rename(&tmp, &name).map_err(|e| werr(&name, &e))?;
            text.push_str(&if b[0].is_nan() {
                "NaN,NaN,NaN,NaN\n".to_string()
            } else {
                format!("{},{},{},{}\n", b[0], b[1], b[2], b[3])
            });
        }
        let gt_path = out_dir.join("groundtruth_rect.txt");
        let tmp = out_dir.join(".groundtruth_rect.txt.tmp");
        std::fs::write(&tmp, text).map_err(|e| werr(&tmp, &e))?;
        std::fs::rename(&tmp, &gt_path).map_err(|e| werr(&gt_path, &e))?;
        Ok(seq.frames.len())
    }
}

/// Cover box `b` (with [`COVER_MARGIN`]) of a `w`x`h` BGR image by the same-sized patch beside
/// it (left or right, else above or below, whichever lies wholly in the frame and clear of the
/// cover), or by the frame's mean colour when none does.
fn cover(bgr: &mut [u8], w: usize, h: usize, b: [f64; 4]) {
    let mx = b[2] * COVER_MARGIN + 4.0;
    let my = b[3] * COVER_MARGIN + 4.0;
    let clip = |v: f64, hi: usize| v.round().clamp(0.0, hi as f64) as usize;
    let (x0, x1) = (clip(b[0] - mx, w), clip(b[0] + b[2] + mx, w));
    let (y0, y1) = (clip(b[1] - my, h), clip(b[1] + b[3] + my, h));
    let (cw, ch) = (x1 - x0, y1 - y0);
    if cw == 0 || ch == 0 {
        return;
    }
    let (cw_i, ch_i) = (cw as i64, ch as i64);
    let fits = |(dx, dy): (i64, i64)| {
        let (sx, sy) = (x0 as i64 + dx, y0 as i64 + dy);
        sx >= 0 && sy >= 0 && sx + cw_i <= w as i64 && sy + ch_i <= h as i64
    };
    let from = [(-cw_i, 0), (cw_i, 0), (0, -ch_i), (0, ch_i)].into_iter().find(|&d| fits(d));
    match from {
        Some((dx, dy)) => {
            for y in 0..ch {
                let dst = ((y0 + y) * w + x0) * 3;
                let src = (((y0 + y) as i64 + dy) as usize * w + (x0 as i64 + dx) as usize) * 3;
                bgr.copy_within(src..src + cw * 3, dst);
            }
        }
        None => {
            let n = (w * h) as f64;
            let mean: Vec<u8> = (0..3)
                .map(|c| (bgr.iter().skip(c).step_by(3).map(|&v| v as f64).sum::<f64>() / n).round() as u8)
                .collect();
            for y in y0..y1 {
                for p in bgr[(y * w + x0) * 3..(y * w + x1) * 3].chunks_exact_mut(3) {
                    p.copy_from_slice(&mean);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> LostAndFound {
        LostAndFound { hide_from: 5, hide_frames: 4, pan: (40, -20), view: (60, 40) }
    }

    #[test]
    fn the_view_pans_while_hidden_and_stays() {
        let s = spec();
        let (w, h) = (120, 80);
        assert_eq!(s.view_origin(0, w, h), (10, 30));
        assert_eq!(s.view_origin(4, w, h), (10, 30));
        assert_eq!(s.view_origin(6, w, h), (26, 22));
        assert_eq!(s.view_origin(9, w, h), (50, 10));
        assert_eq!(s.view_origin(30, w, h), (50, 10));
        assert!(s.check(w, h, 20).is_ok());
        assert!(s.check(w, h, 9).is_err(), "no visible frame after the hidden ones");
        assert!(s.check(90, h, 20).is_err(), "the pan does not fit");
    }

    #[test]
    fn hidden_frames_show_background_and_have_no_box() {
        let s = spec();
        let (w, h) = (120, 80);
        // A grey ramp background with a white target at (60, 40) 10x8.
        let mut bgr: Vec<u8> = (0..w * h).flat_map(|i| [(i % w) as u8; 3]).collect();
        for y in 40..48 {
            for x in 60..70 {
                bgr[(y * w + x) * 3..(y * w + x) * 3 + 3].fill(255);
            }
        }
        let src = Frame::from_bgr(w, h, bgr).unwrap();
        let gt = [60.0, 40.0, 10.0, 8.0];
        let (f, b) = s.make_frame(0, &src, gt);
        assert_eq!((f.width(), f.height()), (60, 40));
        assert_eq!(b, [50.0, 10.0, 10.0, 8.0]);
        assert!(f.bgr().contains(&255));
        let (f, b) = s.make_frame(5, &src, gt);
        assert!(b.iter().all(|v| v.is_nan()));
        assert!(!f.bgr().contains(&255), "the target shows through its cover");
        // After the pan the target is back, 40 px to the left and 20 px lower in the view.
        let (_, b) = s.make_frame(9, &src, gt);
        assert_eq!(b, [10.0, 30.0, 10.0, 8.0]);
        // Out of the view: no box.
        let (_, b) = s.make_frame(9, &src, [5.0, 40.0, 10.0, 8.0]);
        assert!(b[0].is_nan());
    }
}
