//! The official tracker's crop geometry, without a network: where `init` and `track` cut their
//! windows and how large. [`crate::Tracker`] uses it for every crop; the quantiser uses it to cut
//! calibration crops exactly as tracking does.

use crate::{crop_to_tensor, get_subwindow, BBox, Error, Frame, Result, TrackerConfig};

/// Cuts template and search crops as the official trackers (`PRLTrack`, `NanoTracker`) do.
#[derive(Debug, Clone)]
pub struct Cropper {
    config: TrackerConfig,
}

/// A target's template crop and the quantities `init` keeps from it.
#[derive(Debug, Clone)]
pub struct TemplateCrop {
    /// The template graph's input, float NCHW BGR `[1, 3, exemplar_size, exemplar_size]`.
    pub z: Vec<f32>,
    /// The target's centre, `x + (w - 1) / 2`.
    pub center: (f64, f64),
    /// The target's width and height.
    pub size: (f64, f64),
    /// Side of the square window cut (rounded half to even, as numpy does).
    pub s_z: f64,
    /// The frame's per-channel mean, which pads every crop of the sequence.
    pub channel_average: [f64; 3],
}

pub(crate) fn round_half_even(v: f64) -> f64 {
    v.round_ties_even()
}

impl Cropper {
    /// Crops for the tracker settings `config`.
    pub fn new(config: &TrackerConfig) -> Self {
        Cropper { config: config.clone() }
    }

    /// The side of the context window around a target of `size`.
    fn context_size(&self, size: (f64, f64)) -> f64 {
        let ctx = self.config.context_amount * (size.0 + size.1);
        ((size.0 + ctx) * (size.1 + ctx)).sqrt()
    }

    /// The template crop for a target in `bbox` (x, y, w, h) on `frame`, cut as the official
    /// `init` cuts it. A box with no finite position, no positive size, outside the frame or
    /// larger than the frame is an [`Error::InitBox`]: the last rule bounds every crop of the
    /// track (the loop clips the size to the frame after each step) to about 3.1 times the
    /// frame's longer side, so no box can ask for an unbounded allocation.
    pub fn template(&self, frame: &Frame, bbox: BBox) -> Result<TemplateCrop> {
        let refuse = |problem: String| Err(Error::InitBox { bbox, problem });
        let ok = |v: f64| v.is_finite();
        if !(ok(bbox.x) && ok(bbox.y) && ok(bbox.w) && ok(bbox.h)) {
            return refuse("every number must be finite".into());
        }
        if bbox.w <= 0.0 || bbox.h <= 0.0 {
            return refuse("its width and height must be positive".into());
        }
        let (fw, fh) = (frame.width() as f64, frame.height() as f64);
        if bbox.x + bbox.w <= 0.0 || bbox.y + bbox.h <= 0.0 || bbox.x >= fw || bbox.y >= fh {
            return refuse(format!("lies outside the {fw}x{fh} frame"));
        }
        if bbox.w > fw || bbox.h > fh {
            return refuse(format!("is larger than the {fw}x{fh} frame"));
        }
        let center = (bbox.x + (bbox.w - 1.0) / 2.0, bbox.y + (bbox.h - 1.0) / 2.0);
        let size = (bbox.w, bbox.h);
        let context = self.context_size(size);
        if context < 1.0 {
            return refuse("is too small: its context crop is under one pixel".into());
        }
        let s_z = round_half_even(context);
        let channel_average = frame.channel_mean();
        let side = self.config.exemplar_size;
        let z = crop_to_tensor(&get_subwindow(frame, center, side, s_z as usize, channel_average), side);
        Ok(TemplateCrop { z, center, size, s_z, channel_average })
    }

    /// `s_z` of a search crop: the context size of a target of `size`, or, where the settings
    /// keep PRL-Track's rule, the template's when the target covers more than half of the
    /// `width`x`height` frame.
    pub fn search_context(&self, size: (f64, f64), width: usize, height: usize, template: &TemplateCrop) -> f64 {
        if self.config.large_target_keeps_template_size && size.0 * size.1 > 0.5 * (width * height) as f64 {
            template.s_z
        } else {
            self.context_size(size)
        }
    }

    /// The search crop the official `track` cuts on `frame` when its target is at `center` with
    /// `size`, for a sequence whose template crop was `template` (its padding colour and, for
    /// targets over half the frame, its window side). Float NCHW BGR
    /// `[1, 3, instance_size, instance_size]`.
    pub fn search(&self, frame: &Frame, center: (f64, f64), size: (f64, f64), template: &TemplateCrop) -> Vec<f32> {
        let (crop, side) = self.search_window(frame, center, size, template);
        crop_to_tensor(&crop, side)
    }

    /// [`Self::search`] as the search graph's input tensor (no intermediate buffer).
    pub(crate) fn search_input(
        &self,
        frame: &Frame,
        center: (f64, f64),
        size: (f64, f64),
        template: &TemplateCrop,
    ) -> Result<tract_nnef::prelude::Tensor> {
        let (crop, side) = self.search_window(frame, center, size, template);
        crate::crop::crop_to_input(&crop, side)
    }

    /// The search crop's BGR bytes and side (the official geometry, before conversion).
    fn search_window(
        &self,
        frame: &Frame,
        center: (f64, f64),
        size: (f64, f64),
        template: &TemplateCrop,
    ) -> (Vec<u8>, usize) {
        let s_z = self.search_context(size, frame.width(), frame.height(), template);
        let side = self.config.instance_size;
        let s_x = s_z * (side as f64 / self.config.exemplar_size as f64);
        (get_subwindow(frame, center, side, round_half_even(s_x) as usize, template.channel_average), side)
    }
}
