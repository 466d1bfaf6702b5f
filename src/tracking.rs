//! The one tracking loop every command and example uses: frames in, per-frame boxes, scores and
//! stage timings out, with the same checks everywhere (frames of one sequence have one size,
//! errors name the frame).

use std::time::{Duration, Instant};

use prl_runtime::{BBox, Frame, Prediction, TargetState, Tracker};

use crate::{iou, load_frame, read_frame, Damaged, InputError};

/// Where one frame's time went.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameTiming {
    /// Waiting for the frame: reading and decoding it, or, when frames are read ahead on a thread
    /// of their own ([`read_ahead`]), what of that the tracker still had to wait for.
    pub decode: Duration,
    /// Cutting and resizing the crop.
    pub crop: Duration,
    /// The template graph (first frame) or the search graph.
    pub network: Duration,
    /// Decoding the outputs and updating the state.
    pub post: Duration,
}

impl FrameTiming {
    /// The tracker's part of the frame (crop, network, post-processing; decoding excluded).
    pub fn tracking(&self) -> Duration {
        self.crop + self.network + self.post
    }
}

/// What a run over a sequence gave: one entry per frame, the first frame's being the init box
/// (score and confidence 1, `tracking`; pysot writes score 1) and its template step.
#[derive(Debug, Clone, Default)]
pub struct TrackRun {
    /// The target's box per frame.
    pub boxes: Vec<BBox>,
    /// The tracker's score per frame.
    pub scores: Vec<f64>,
    /// The tracker's confidence per frame (what its state is decided on).
    pub confidences: Vec<f64>,
    /// The tracker's state per frame.
    pub states: Vec<TargetState>,
    /// Stage times per frame.
    pub timings: Vec<FrameTiming>,
    /// Wall time of the whole run.
    pub total: Duration,
}

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    /// A frame could not be read.
    #[error(transparent)]
    Frame(#[from] InputError),
    /// The tracker refused a frame or the box.
    #[error("{label}: {source}")]
    Tracker {
        /// The frame (and the target, when there are several).
        label: String,
        /// Which target's tracker (0-based).
        target: usize,
        /// What the runtime said.
        source: prl_runtime::Error,
    },
    /// A frame's size differs from the first frame's.
    #[error("{label}: frame is {got_w}x{got_h}, the first frame {w}x{h}: frames of one sequence must have one size")]
    Size {
        /// The frame.
        label: String,
        /// Its width.
        got_w: usize,
        /// Its height.
        got_h: usize,
        /// The first frame's width.
        w: usize,
        /// The first frame's height.
        h: usize,
    },
    /// The caller's per-frame hook failed (writing a visualisation, say).
    #[error("{0}")]
    Hook(String),
    /// A video source failed.
    #[error(transparent)]
    Video(#[from] crate::video::VideoError),
}

/// Frames of a sequence, by index.
pub trait Frames {
    /// How many.
    fn len(&self) -> usize;
    /// Whether there are none.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Frame `i`, decoded.
    fn frame(&mut self, i: usize) -> Result<Frame, InputError>;
    /// Frame `i`'s name in errors (its file).
    fn label(&self, i: usize) -> String;
}

/// Frame files, decoded as OpenCV does.
impl Frames for &[std::path::PathBuf] {
    fn len(&self) -> usize {
        <[std::path::PathBuf]>::len(self)
    }
    fn frame(&mut self, i: usize) -> Result<Frame, InputError> {
        load_frame(&self[i])
    }
    fn label(&self, i: usize) -> String {
        self[i].display().to_string()
    }
}

/// Frame files, with a rule for damaged ones (a truncated JPEG, say: used with a warning, or an
/// error with [`Damaged::Refuse`]).
pub struct FrameFiles<'a> {
    /// The files, in order.
    pub paths: &'a [std::path::PathBuf],
    /// What to do with a frame the decoder could only partly read.
    pub damaged: Damaged,
}

impl Frames for FrameFiles<'_> {
    fn len(&self) -> usize {
        self.paths.len()
    }
    fn frame(&mut self, i: usize) -> Result<Frame, InputError> {
        read_frame(&self.paths[i], self.damaged)
    }
    fn label(&self, i: usize) -> String {
        self.paths[i].display().to_string()
    }
}

/// Frames made by a function (generated video), labelled `"<what> frame N"`.
pub struct MadeFrames<F> {
    /// How many.
    pub count: usize,
    /// What they are, for labels.
    pub what: &'static str,
    /// Frame `i`.
    pub make: F,
}

impl<F: FnMut(usize) -> Frame> Frames for MadeFrames<F> {
    fn len(&self) -> usize {
        self.count
    }
    fn frame(&mut self, i: usize) -> Result<Frame, InputError> {
        Ok((self.make)(i))
    }
    fn label(&self, i: usize) -> String {
        format!("{} frame {}", self.what, i + 1)
    }
}

/// Track through `frames` from `init` on the first, each frame decoded while the tracker works
/// on the one before ([`read_ahead`]). `on_frame(i, frame, prediction)` sees every frame and what
/// the tracker said of it as it goes (for drawing, output or progress; the first frame's is the
/// init box, score 1, `tracking`); an error from it stops the run.
pub fn track(
    tracker: &mut Tracker,
    frames: impl Frames + Send,
    init: BBox,
    on_frame: impl FnMut(usize, &Frame, &Prediction) -> Result<(), String>,
) -> Result<TrackRun, TrackError> {
    let n = frames.len();
    read_ahead(frames, |stream| track_stream(tracker, stream, init, n, on_frame))
}

/// Frames that come one after another (a video, a camera, a stream: the length need not be
/// known).
pub trait FrameStream {
    /// The next frame, or `None` at the end.
    fn next_frame(&mut self) -> Result<Option<Frame>, TrackError>;
    /// The frame last given, as errors name it (asked only when there is an error).
    fn label(&self) -> String;
}

/// [`Frames`] one after another, as a [`FrameStream`].
pub fn in_order<F: Frames>(frames: F) -> impl FrameStream {
    InOrder { frames, next: 0 }
}

/// [`Frames`] one after another.
struct InOrder<F> {
    frames: F,
    next: usize,
}

impl<F: Frames> FrameStream for InOrder<F> {
    fn next_frame(&mut self) -> Result<Option<Frame>, TrackError> {
        if self.next == self.frames.len() {
            return Ok(None);
        }
        self.next += 1;
        Ok(Some(self.frames.frame(self.next - 1)?))
    }
    fn label(&self) -> String {
        self.frames.label(self.next.saturating_sub(1))
    }
}

/// [`Frames`] one after another, as [`in_order`] gives them (the same frames, the same errors,
/// the same labels), but each decoded on a thread of its own while the caller works on the one
/// before: one frame ahead, so that decoding leaves the per-frame time when a core is free for
/// it. `body` runs on the calling thread with the stream; the reading thread stops when the
/// stream is dropped or a frame fails, and is joined before this returns.
pub fn read_ahead<F: Frames + Send, R>(frames: F, body: impl FnOnce(ReadAhead) -> R) -> R {
    std::thread::scope(|scope| {
        // A rendezvous channel: the reader decodes frame i + 1 while frame i is tracked, then
        // waits until it is asked for.
        let (tx, rx) = std::sync::mpsc::sync_channel(0);
        let mut frames = frames;
        let n = frames.len();
        scope.spawn(move || {
            for i in 0..n {
                let frame = frames.frame(i);
                let failed = frame.is_err();
                if tx.send((frame, frames.label(i))).is_err() || failed {
                    return;
                }
            }
        });
        body(ReadAhead { rx, label: String::new() })
    })
}

/// The stream [`read_ahead`] gives.
pub struct ReadAhead {
    rx: std::sync::mpsc::Receiver<(Result<Frame, InputError>, String)>,
    label: String,
}

impl FrameStream for ReadAhead {
    fn next_frame(&mut self) -> Result<Option<Frame>, TrackError> {
        // The reader hangs up after the last frame (or, having panicked, early: the scope then
        // passes its panic on).
        let Ok((frame, label)) = self.rx.recv() else { return Ok(None) };
        self.label = label;
        Ok(Some(frame?))
    }
    fn label(&self) -> String {
        self.label.clone()
    }
}

/// Track through `frames` as they come. `expected` (how many, if known) sizes the results;
/// `on_frame(i, frame, prediction)` sees every frame as it goes.
pub fn track_stream(
    tracker: &mut Tracker,
    frames: impl FrameStream,
    init: BBox,
    expected: usize,
    mut on_frame: impl FnMut(usize, &Frame, &Prediction) -> Result<(), String>,
) -> Result<TrackRun, TrackError> {
    let runs =
        track_targets(std::slice::from_mut(tracker), 1, frames, &[init], expected, |i, f, p| on_frame(i, f, &p[0]))?;
    Ok(runs.into_iter().next().expect("one run per tracker"))
}

/// Several targets through `frames` as they come, one tracker (one state, one box) each,
/// `trackers[k]` starting from `inits[k]` (the trackers may share one plan: [`Plan`] clones are
/// cheap). Each frame is decoded once; the targets' steps are spread over `jobs` threads (each
/// thread takes a contiguous share of the targets). `on_frame(i, frame, predictions)` sees every
/// frame with one prediction per target. One [`TrackRun`] per target; with one target this is
/// [`track_stream`] exactly.
///
/// [`Plan`]: prl_runtime::Plan
pub fn track_targets(
    trackers: &mut [Tracker],
    jobs: usize,
    mut frames: impl FrameStream,
    inits: &[BBox],
    expected: usize,
    mut on_frame: impl FnMut(usize, &Frame, &[Prediction]) -> Result<(), String>,
) -> Result<Vec<TrackRun>, TrackError> {
    if inits.len() != trackers.len() || trackers.is_empty() {
        return Err(TrackError::Hook(format!("{} initial boxes for {} trackers", inits.len(), trackers.len())));
    }
    let start = Instant::now();
    let mut runs: Vec<TrackRun> = (0..trackers.len())
        .map(|_| TrackRun {
            boxes: Vec::with_capacity(expected),
            scores: Vec::with_capacity(expected),
            confidences: Vec::with_capacity(expected),
            states: Vec::with_capacity(expected),
            timings: Vec::with_capacity(expected),
            total: Duration::ZERO,
        })
        .collect();
    let several = trackers.len() > 1;
    let mut size = (0, 0);
    for i in 0.. {
        let t = Instant::now();
        let Some(f) = frames.next_frame()? else { break };
        let decode = t.elapsed();
        if i == 0 {
            size = (f.width(), f.height());
        } else if (f.width(), f.height()) != size {
            let (got_w, got_h) = (f.width(), f.height());
            return Err(TrackError::Size { label: frames.label(), got_w, got_h, w: size.0, h: size.1 });
        }
        let steps = prl_runtime::spread(trackers, jobs, |k, tracker| {
            if i == 0 {
                tracker.init(&f, inits[k])?;
                Ok(Prediction { bbox: inits[k], score: 1.0, confidence: 1.0, state: TargetState::Tracking })
            } else {
                tracker.track(&f)
            }
        });
        let mut predictions = Vec::with_capacity(steps.len());
        for (k, step) in steps.into_iter().enumerate() {
            let p = step.map_err(|source| {
                let label = if several { format!("{} (target {})", frames.label(), k + 1) } else { frames.label() };
                TrackError::Tracker { label, target: k, source }
            })?;
            let run = &mut runs[k];
            run.boxes.push(p.bbox);
            run.scores.push(p.score);
            run.confidences.push(p.confidence);
            run.states.push(p.state);
            let s = trackers[k].last_timings();
            run.timings.push(FrameTiming { decode, crop: s.crop, network: s.network, post: s.post });
            predictions.push(p);
        }
        on_frame(i, &f, &predictions).map_err(TrackError::Hook)?;
    }
    let total = start.elapsed();
    runs.iter_mut().for_each(|r| r.total = total);
    Ok(runs)
}

/// One tracking step of every target on `frame`, spread over `jobs` threads as
/// [`track_targets`] does: each target's prediction, or the first error with its target.
pub fn step_targets(
    trackers: &mut [Tracker],
    jobs: usize,
    frame: &Frame,
) -> Result<Vec<Prediction>, (usize, prl_runtime::Error)> {
    let steps = prl_runtime::spread(trackers, jobs, |_, t| t.track(frame));
    steps.into_iter().enumerate().map(|(k, s)| s.map_err(|e| (k, e))).collect()
}

impl TrackRun {
    /// Mean IoU with `groundtruth` over the frames whose truth has a positive size.
    pub fn mean_iou(&self, groundtruth: &[[f64; 4]]) -> Option<f64> {
        let ious: Vec<f64> = (self.boxes.iter().zip(groundtruth))
            .filter(|(_, g)| g[2] > 0.0 && g[3] > 0.0)
            .map(|(b, g)| iou([b.x, b.y, b.w, b.h], *g))
            .collect();
        (!ious.is_empty()).then(|| ious.iter().sum::<f64>() / ious.len() as f64)
    }

    /// The boxes as `[x, y, w, h]`.
    pub fn xywh(&self) -> Vec<[f64; 4]> {
        self.boxes.iter().map(|b| [b.x, b.y, b.w, b.h]).collect()
    }

    /// Results in pysot's format: one `x,y,w,h` line per frame.
    pub fn results_text(&self) -> String {
        self.boxes.iter().map(|b| format!("{},{},{},{}\n", b.x, b.y, b.w, b.h)).collect()
    }

    /// The per-frame confidences, one a line: the `<video>_confidence.value` file written beside
    /// a result file, which `prl eval`'s long-term figures read ([`crate::longterm`]).
    pub fn confidence_text(&self) -> String {
        self.confidences.iter().map(|c| format!("{c}\n")).collect()
    }

    /// Median of one stage over the frames after the first (the tracking steps), in ms.
    pub fn median_ms(&self, stage: impl Fn(&FrameTiming) -> Duration) -> f64 {
        let mut ms: Vec<f64> = self.timings.iter().skip(1).map(|t| stage(t).as_secs_f64() * 1e3).collect();
        if ms.is_empty() {
            return 0.0;
        }
        ms.sort_by(f64::total_cmp);
        ms[ms.len() / 2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frames 0, 1, ... whose first pixel is their index; frame `bad` fails.
    struct Numbered {
        count: usize,
        bad: usize,
    }

    impl Frames for Numbered {
        fn len(&self) -> usize {
            self.count
        }
        fn frame(&mut self, i: usize) -> Result<Frame, InputError> {
            if i == self.bad {
                return Err(InputError::new(std::path::Path::new(&self.label(i)), "cut short"));
            }
            Ok(Frame::from_bgr(2, 1, vec![i as u8, 0, 0, 0, 0, 0]).unwrap())
        }
        fn label(&self, i: usize) -> String {
            format!("frame{i}.jpg")
        }
    }

    /// What a stream gives until it ends or fails: the frames' first pixels, and the error with
    /// the stream's label at that point.
    fn drain(mut s: impl FrameStream) -> (Vec<u8>, Option<(String, String)>) {
        let mut got = vec![];
        loop {
            match s.next_frame() {
                Ok(Some(f)) => got.push(f.bgr()[0]),
                Ok(None) => return (got, None),
                Err(e) => return (got, Some((e.to_string(), s.label()))),
            }
        }
    }

    #[test]
    fn read_ahead_gives_what_in_order_gives() {
        for (count, bad) in [(5, usize::MAX), (5, 3), (5, 0), (0, usize::MAX)] {
            let plain = drain(in_order(Numbered { count, bad }));
            let ahead = read_ahead(Numbered { count, bad }, drain);
            assert_eq!(plain, ahead, "{count} frames, frame {bad} failing");
        }
        let (got, err) = read_ahead(Numbered { count: 5, bad: 3 }, drain);
        assert_eq!(got, [0, 1, 2]);
        let (msg, label) = err.unwrap();
        assert!(msg.contains("frame3.jpg") && msg.contains("cut short"), "{msg}");
        assert_eq!(label, "frame3.jpg");
    }

    #[test]
    fn read_ahead_stops_when_the_stream_is_dropped() {
        // The body takes one frame of a thousand and returns: the reader must not run on (or
        // block) once the stream is gone.
        let first = read_ahead(Numbered { count: 1000, bad: usize::MAX }, |mut s| s.next_frame().unwrap().unwrap());
        assert_eq!(first.bgr()[0], 0);
    }
}
