//! `prl track`: run a plan over a frame sequence.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use prl_runtime::{set_threads, BBox, Frame, Plan, Prediction, Tracker};
use prl_track::tracking::{self, Frames, TrackRun};
use prl_track::{init_box_from_groundtruth, Damaged, InputError, Sequence};

use prl_track::longterm;

use super::{write_atomically, write_results};

#[derive(Args)]
pub struct TrackArgs {
    /// Plan directory written by `prl compile`.
    #[arg(long, default_value = "models/prl-track/plan")]
    plan: PathBuf,
    /// OTB/UAV123-style sequence folder (`img/`, `groundtruth_rect.txt`); init from its first box
    /// (a folder with one `groundtruth_rect.<N>.txt` per target, as OTB's `Jogging`, tracks them all).
    #[arg(long, value_name = "DIR", required_unless_present_any = ["frames", "video"], conflicts_with_all = ["frames", "video"])]
    sequence: Option<PathBuf>,
    /// A bare folder of frames (needs --init or --targets).
    #[arg(long, value_name = "DIR", conflicts_with = "video")]
    frames: Option<PathBuf>,
    /// A video file, a camera device (`/dev/video0`) or a stream URL (`rtsp://...`), decoded by
    /// FFmpeg (needs --init or --targets; install: `sudo apt-get install ffmpeg`).
    #[arg(long, value_name = "SRC")]
    video: Option<String>,
    /// With --video: always track the newest frame, dropping the ones that came while the tracker
    /// was busy (cameras, streams); the default tracks every frame in order (files).
    #[arg(long, requires = "video")]
    live: bool,
    /// With --video: the frame number (from 0) that --init is on; earlier frames are skipped.
    #[arg(long, value_name = "N", default_value_t = 0, requires = "video")]
    init_frame: usize,
    /// With --video: write the video with the boxes drawn to FILE (through FFmpeg; the codec is
    /// its default for the extension: `.mp4`, `.mkv`, `.avi` ...).
    #[arg(long, value_name = "FILE", requires = "video")]
    vis_video: Option<PathBuf>,
    /// Write one JSON object per frame on standard output (frame number, box, score, confidence,
    /// state; with --video the time too), and everything else on standard error.
    #[arg(long)]
    jsonl: bool,
    /// Long-term mode: when the confidence falls below the plan's `long_term.lost_below`, keep
    /// the last box and search a larger region (tiles x tiles search crops) until the target is
    /// found again (pysot's long-term scheme; docs/lost-target.md).
    #[arg(long)]
    long_term: bool,
    /// Initial box `x,y,w,h` in the first frame (0-based pixels). Repeat it to track several
    /// targets at once, on one plan (target 1 is the first --init).
    #[arg(long, value_name = "X,Y,W,H", value_parser = parse_init, allow_hyphen_values = true)]
    init: Vec<InitArg>,
    /// A file of initial boxes, one `x,y,w,h` line per target (after those of --init): several
    /// targets from a file, for a frame folder, a sequence or a video.
    #[arg(long, value_name = "FILE")]
    targets: Option<PathBuf>,
    /// Write one `x,y,w,h` line per frame here (pysot format; first line the init box); with
    /// --live, `frame,x,y,w,h` lines (the frame number first: frames were dropped). With several
    /// targets, one file each: `NAME_1.txt`, `NAME_2.txt`...
    #[arg(long, value_name = "FILE")]
    results: Option<PathBuf>,
    /// Write each frame with its box drawn (ground truth too, when known) into this folder.
    #[arg(long, value_name = "DIR")]
    vis: Option<PathBuf>,
    /// Threads (default: all cores). With several targets, the targets are spread over them
    /// (one thread per target while there are fewer targets than threads).
    #[arg(long)]
    threads: Option<usize>,
    /// Track only the first N frames.
    #[arg(long, value_name = "N")]
    max_frames: Option<usize>,
    /// Stop at a damaged frame (a truncated or corrupt JPEG) instead of tracking it with a
    /// warning, as OpenCV would decode it.
    #[arg(long)]
    strict: bool,
    /// Decode each frame on the tracking thread when it is needed, not one frame ahead on a
    /// thread of its own while the tracker works (the default: decoding then costs the per-frame
    /// time only what a busy machine cannot overlap); for timing each stage alone.
    #[arg(long, conflicts_with = "video")]
    no_read_ahead: bool,
    /// Write the run's summary (FPS, stage medians, mean IoU, peak memory) here as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

/// `--init` as parsed and as typed (errors quote the box the way the user wrote it).
#[derive(Clone)]
struct InitArg {
    b: [f64; 4],
    text: String,
}

impl InitArg {
    fn bbox(&self) -> BBox {
        BBox { x: self.b[0], y: self.b[1], w: self.b[2], h: self.b[3] }
    }
}

fn parse_init(s: &str) -> Result<InitArg, String> {
    Ok(InitArg { b: prl_track::parse_box(s)?, text: s.trim().to_string() })
}

/// Where a target's first ground-truth box comes from, quoted as its `file` has it
/// (`.../groundtruth_rect.txt line 1 (1e9,0,5,5)`).
fn first_box_as_written(file: &Path, parsed: [f64; 4]) -> String {
    let line = std::fs::read_to_string(file).ok().and_then(|t| {
        t.lines().enumerate().find(|(_, l)| !l.trim().is_empty()).map(|(i, l)| (i + 1, l.trim().to_string()))
    });
    match line {
        Some((n, l)) => format!("{} line {n} ({l})", file.display()),
        None => format!("the first ground-truth box ({},{},{},{})", parsed[0], parsed[1], parsed[2], parsed[3]),
    }
}

/// A run's error, with a refused init box quoted as `sources[target]` gave it
/// (`--init 0,0,1e7,1e7`).
fn quote_init(e: tracking::TrackError, sources: &[String]) -> anyhow::Error {
    match e {
        tracking::TrackError::Tracker { label, target, source: prl_runtime::Error::InitBox { problem, .. } } => {
            anyhow::anyhow!("{}: {problem} (on {label})", sources.get(target).map_or("the init box", |s| s.as_str()))
        }
        e => e.into(),
    }
}

/// Most targets one run tracks (each holds its own template features and state).
const MAX_TARGETS: usize = 64;

/// The initial boxes given: `--init`s, then the lines of `--targets FILE`, each with how errors
/// quote it (`--init 1,2,3,4`, `FILE line 2 (1,2,3,4)`).
fn given_boxes(a: &TrackArgs) -> anyhow::Result<Vec<(BBox, String)>> {
    let mut given: Vec<(BBox, String)> = a.init.iter().map(|b| (b.bbox(), format!("--init {}", b.text))).collect();
    if let Some(path) = &a.targets {
        let text = prl_track::read_text_bounded(path, 64 * 1024, "a targets file")?;
        for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let b = prl_track::parse_box(line).map_err(|m| InputError::new(path, format!("line {}: {m}", i + 1)))?;
            let bbox = BBox { x: b[0], y: b[1], w: b[2], h: b[3] };
            given.push((bbox, format!("{} line {} ({})", path.display(), i + 1, line.trim())));
        }
        anyhow::ensure!(given.len() > a.init.len(), "{}: no box in it (one x,y,w,h line per target)", path.display());
    }
    anyhow::ensure!(given.len() <= MAX_TARGETS, "{} targets: at most {MAX_TARGETS} are tracked at once", given.len());
    Ok(given)
}

/// The result file of target `k` (0-based) of `n`: `path` itself for one target, else
/// `NAME_<k+1>.EXT`.
fn target_path(path: &Path, k: usize, n: usize) -> PathBuf {
    if n == 1 {
        return path.to_path_buf();
    }
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let ext = path.extension().map(|e| format!(".{}", e.to_string_lossy())).unwrap_or_default();
    path.with_file_name(format!("{stem}_{}{ext}", k + 1))
}

/// Spread `targets` over the `threads` asked for (default: all cores): the jobs that run
/// targets side by side, and each job's threads (for the network, set process-wide, and for
/// the long-term mode's region crops).
fn spread_threads(threads: Option<usize>, targets: usize) -> (usize, usize) {
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())).max(1);
    let jobs = threads.min(targets).max(1);
    let per_job = (threads / jobs).max(1);
    set_threads(per_job);
    (jobs, per_job)
}

/// Per-stage times of a run and how the boxes compare with ground truth (`--json` writes it).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Summary {
    /// Frames tracked (the first included).
    pub frames: usize,
    /// Frames per second of the whole loop, frame decoding included.
    pub fps: f64,
    /// Median ms per frame the loop waited for its frame: decoding it, or, with frames read ahead
    /// on a thread of their own, what of the decoding did not overlap the tracking.
    pub decode_ms: f64,
    /// Crop and resize.
    pub crop_ms: f64,
    /// The search network.
    pub network_ms: f64,
    /// Decoding of the outputs and the state update.
    pub post_ms: f64,
    /// Mean IoU with the ground truth, when known.
    pub mean_iou: Option<f64>,
    /// Peak resident memory of the process, MB.
    pub peak_rss_mb: Option<f64>,
}

impl Summary {
    pub fn of(run: &TrackRun, groundtruth: Option<&[[f64; 4]]>) -> Summary {
        Summary {
            frames: run.boxes.len(),
            fps: run.boxes.len() as f64 / run.total.as_secs_f64(),
            decode_ms: run.median_ms(|t| t.decode),
            crop_ms: run.median_ms(|t| t.crop),
            network_ms: run.median_ms(|t| t.network),
            post_ms: run.median_ms(|t| t.post),
            mean_iou: groundtruth.and_then(|g| run.mean_iou(g)),
            peak_rss_mb: super::peak_rss_mb(),
        }
    }

    /// The summary as printed, line by line.
    pub fn lines(&self) -> Vec<String> {
        let mut l = vec![
            format!("frames: {}   FPS: {:.1} (whole loop, frame decoding included)", self.frames, self.fps),
            format!(
                "ms per frame (median): frame wait {:.1}, crop {:.1}, network {:.1}, post-processing {:.2}",
                self.decode_ms, self.crop_ms, self.network_ms, self.post_ms
            ),
        ];
        if let Some(iou) = self.mean_iou {
            l.push(format!("mean IoU with the ground truth: {iou:.3}"));
        }
        if let Some(mb) = self.peak_rss_mb {
            l.push(format!("peak resident memory: {mb:.0} MB"));
        }
        l
    }

    /// Print [`Summary::lines`] on standard output.
    pub fn print(&self) {
        self.lines().into_iter().for_each(|l| println!("{l}"));
    }
}

/// [`prl_track::tracking::track`] behind a progress bar.
pub fn track_with_progress(
    tracker: &mut Tracker,
    frames: impl Frames + Send,
    init: BBox,
    mut on_frame: impl FnMut(usize, &Frame, &Prediction) -> anyhow::Result<()>,
) -> Result<TrackRun, tracking::TrackError> {
    let runs = targets_with_progress(std::slice::from_mut(tracker), 1, frames, true, &[init], |i, f, p| {
        on_frame(i, f, &p[0])
    })?;
    Ok(runs.into_iter().next().expect("one run per tracker"))
}

/// [`prl_track::tracking::track_targets`] through frame files, behind a progress bar; `ahead`:
/// each frame decoded while the one before is tracked ([`tracking::read_ahead`]).
fn targets_with_progress<F: Frames + Send>(
    trackers: &mut [Tracker],
    jobs: usize,
    frames: F,
    ahead: bool,
    inits: &[BBox],
    mut on_frame: impl FnMut(usize, &Frame, &[Prediction]) -> anyhow::Result<()>,
) -> Result<Vec<TrackRun>, tracking::TrackError> {
    let n = frames.len();
    let pb = indicatif::ProgressBar::new(n as u64);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta}")
            .expect("static template"),
    );
    let step = |i: usize, f: &Frame, p: &[Prediction]| {
        pb.inc(1);
        on_frame(i, f, p).map_err(|e| format!("{e:#}"))
    };
    let runs = if ahead {
        tracking::read_ahead(frames, |stream| tracking::track_targets(trackers, jobs, stream, inits, n, step))
    } else {
        tracking::track_targets(trackers, jobs, tracking::in_order(frames), inits, n, step)
    };
    pb.finish_and_clear();
    runs
}

/// The frame as an RGB image with the ground-truth boxes `gt` (red, where known) and every box of
/// `preds` (green) drawn.
fn with_boxes(f: &Frame, preds: &[Prediction], gt: &[[f64; 4]]) -> image::RgbImage {
    let mut img = f.to_rgb_image();
    for g in gt.iter().filter(|g| g.iter().all(|v| v.is_finite())) {
        draw_rect(&mut img, *g, [255, 40, 40]);
    }
    for p in preds {
        draw_rect(&mut img, [p.bbox.x, p.bbox.y, p.bbox.w, p.bbox.h], [40, 255, 40]);
    }
    img
}

/// Draw `preds` (green) and `gt` (red) on a copy of the frame and save it as JPEG.
pub fn save_vis(dir: &Path, i: usize, f: &Frame, preds: &[Prediction], gt: &[[f64; 4]]) -> anyhow::Result<()> {
    let path = dir.join(format!("{:06}.jpg", i + 1));
    with_boxes(f, preds, gt).save(&path).with_context(|| format!("{}: cannot write", path.display()))
}

fn draw_rect(img: &mut image::RgbImage, b: [f64; 4], color: [u8; 3]) {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let (x0, y0) = (b[0].round() as i64, b[1].round() as i64);
    let (x1, y1) = ((b[0] + b[2]).round() as i64, (b[1] + b[3]).round() as i64);
    let mut put = |x: i64, y: i64| {
        if (0..w).contains(&x) && (0..h).contains(&y) {
            img.put_pixel(x as u32, y as u32, image::Rgb(color));
        }
    };
    for t in 0..2 {
        for x in x0..=x1 {
            put(x, y0 + t);
            put(x, y1 - t);
        }
        for y in y0..=y1 {
            put(x0 + t, y);
            put(x1 - t, y);
        }
    }
}

pub fn run(a: TrackArgs) -> anyhow::Result<()> {
    let given = given_boxes(&a)?;
    if let Some(src) = &a.video {
        anyhow::ensure!(!given.is_empty(), "--video needs --init x,y,w,h or --targets FILE");
        let (jobs, per_job) = spread_threads(a.threads, given.len());
        return run_video(&a, src, &given, jobs, per_job);
    }
    // Each target's ground truth, where the sequence has it (one file per target).
    let (mut frames, gt, inits): (_, Vec<Vec<[f64; 4]>>, _) = match (&a.sequence, &a.frames) {
        (Some(dir), _) => {
            let seq = Sequence::open(dir)?;
            let inits = if !given.is_empty() {
                given
            } else if seq.targets.is_empty() {
                let msg = "no ground truth (groundtruth_rect.txt, or groundtruth_rect.<N>.txt per target): give --init x,y,w,h";
                return Err(InputError::new(dir, msg).into());
            } else {
                let first = |t: &prl_track::GroundTruth| t.boxes[0];
                seq.targets
                    .iter()
                    .map(|t| (init_box_from_groundtruth(first(t)), first_box_as_written(&t.file, first(t))))
                    .collect()
            };
            (seq.frames, seq.targets.into_iter().map(|t| t.boxes).collect(), inits)
        }
        (None, Some(dir)) if !given.is_empty() => (Sequence::list_frames(dir)?, vec![], given),
        _ => anyhow::bail!("give --sequence DIR, or --frames DIR with --init x,y,w,h (or --targets FILE)"),
    };
    let (jobs, per_job) = spread_threads(a.threads, inits.len());
    if let Some(n) = a.max_frames {
        frames.truncate(n.max(1));
    }
    if let Some(dir) = &a.vis {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    // With --jsonl, standard output carries the per-frame objects only.
    let say = |line: String| if a.jsonl { eprintln!("{line}") } else { println!("{line}") };
    let mut trackers = open_trackers(&a.plan, inits.len(), a.long_term.then_some(per_job), say)?;
    let damaged = if a.strict { Damaged::Refuse } else { Damaged::Warn };
    let files = tracking::FrameFiles { paths: &frames, damaged };
    let boxes: Vec<BBox> = inits.iter().map(|i| i.0).collect();
    let several = boxes.len() > 1;
    let runs = targets_with_progress(&mut trackers, jobs, files, !a.no_read_ahead, &boxes, |i, f, ps| {
        if a.jsonl {
            ps.iter().enumerate().for_each(|(k, p)| println!("{}", frame_json(i, None, several.then_some(k + 1), p)));
        }
        match &a.vis {
            Some(dir) => save_vis(dir, i, f, ps, &gt.iter().filter_map(|g| g.get(i).copied()).collect::<Vec<_>>()),
            None => Ok(()),
        }
    })
    .map_err(|e| quote_init(e, &inits.iter().map(|i| i.1.clone()).collect::<Vec<_>>()))?;
    if let Some(path) = &a.results {
        for (k, run) in runs.iter().enumerate() {
            let path = target_path(path, k, runs.len());
            write_results(&path, run)?;
            say(format!("results: {} (confidences in {})", path.display(), longterm::confidence_path(&path).display()));
        }
    }
    let summary = Summary::of(&runs[0], gt.first().map(|g| g.as_slice()));
    if let Some(path) = &a.json {
        write_atomically(path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    }
    let mut lines = summary.lines();
    if several {
        lines.insert(1, targets_line(&runs, jobs, &gt));
    }
    lines.into_iter().for_each(say);
    Ok(())
}

/// With several targets: how many, on how many threads, each one's frames lost and, when every
/// target has its ground truth in `gt`, each one's mean IoU.
fn targets_line(runs: &[TrackRun], jobs: usize, gt: &[Vec<[f64; 4]>]) -> String {
    let lost: Vec<String> = runs
        .iter()
        .enumerate()
        .map(|(k, r)| {
            format!("{}: {}", k + 1, r.states.iter().filter(|&&s| s == prl_runtime::TargetState::Lost).count())
        })
        .collect();
    let mut line = format!(
        "targets: {} on {jobs} thread(s) (stage times below are target 1's); frames lost per target: {}",
        runs.len(),
        lost.join(", ")
    );
    if gt.len() == runs.len() {
        let ious: Vec<String> = runs
            .iter()
            .zip(gt)
            .enumerate()
            .map(|(k, (r, g))| format!("{}: {}", k + 1, r.mean_iou(g).map_or("-".into(), |v| format!("{v:.3}"))))
            .collect();
        line += &format!("; mean IoU per target: {}", ious.join(", "));
    }
    line
}

/// One frame's `--jsonl` object: frame number, target (when there are several), time (video),
/// box, score, confidence, state.
fn frame_json(frame: usize, time_s: Option<f64>, target: Option<usize>, p: &Prediction) -> serde_json::Value {
    let b = p.bbox;
    let mut o = serde_json::json!({ "frame": frame });
    if let Some(k) = target {
        o["target"] = k.into();
    }
    if let Some(t) = time_s {
        o["time_s"] = t.into();
    }
    o["box"] = serde_json::json!([b.x, b.y, b.w, b.h]);
    o["score"] = p.score.into();
    o["confidence"] = p.confidence.into();
    o["state"] = p.state.name().into();
    o
}

/// The tracker of the plan in `dir`, with its own settings; `say` prints the line about the plan
/// (a plan of random weights is noted on standard error).
fn open_tracker(dir: &Path, say: impl Fn(String)) -> anyhow::Result<Tracker> {
    let t = Instant::now();
    let plan = Plan::load(dir)?;
    let m = plan.manifest();
    say(format!(
        "plan: {} ({}, {}), loaded in {} ms",
        dir.display(),
        m.precision,
        m.weights.note,
        t.elapsed().as_millis()
    ));
    if m.weights.kind == "random" {
        eprintln!("note: {} holds RANDOM weights: it runs, but it cannot track", dir.display());
    }
    let config = m.tracker.clone();
    Ok(Tracker::new(plan, config))
}

/// `n` trackers of the plan in `dir` (one plan, loaded once); in the long-term mode when
/// `long_term` gives the threads its region crops are searched on.
fn open_trackers(dir: &Path, n: usize, long_term: Option<usize>, say: impl Fn(String)) -> anyhow::Result<Vec<Tracker>> {
    let first = open_tracker(dir, say)?;
    let (plan, config) = (first.plan().clone(), first.plan().manifest().tracker.clone());
    let mut trackers = vec![first];
    trackers.extend((1..n).map(|_| Tracker::new(plan.clone(), config.clone())));
    for t in &mut trackers {
        t.set_long_term(long_term.is_some());
        t.set_region_threads(long_term.unwrap_or(1));
    }
    Ok(trackers)
}

/// `prl track --video SRC`: decode with FFmpeg and track every frame (or the newest, `--live`).
fn run_video(a: &TrackArgs, src: &str, given: &[(BBox, String)], jobs: usize, per_job: usize) -> anyhow::Result<()> {
    use prl_track::video::{Pacing, VideoSource};
    use std::cell::RefCell;
    // With --jsonl, standard output carries the per-frame objects only.
    let say = |line: String| if a.jsonl { eprintln!("{line}") } else { println!("{line}") };
    // The plan first (a bad plan fails before a camera starts), then the source.
    let mut trackers = open_trackers(&a.plan, given.len(), a.long_term.then_some(per_job), say)?;
    let mut video = VideoSource::open(src, if a.live { Pacing::Live } else { Pacing::Every }, a.init_frame)?;
    let (w, h) = video.size();
    say(format!("video: {src}, {w}x{h}, {}", if a.live { "live (newest frame)" } else { "every frame" }));
    // Ctrl-C (or SIGTERM) ends the run at the next frame with its results written: a camera or
    // a stream has no end of its own. A second Ctrl-C quits at once.
    let stop = video.stop_flag();
    let on_signal = std::sync::Arc::clone(&stop);
    let handler = ctrlc::set_handler(move || {
        if on_signal.swap(true, std::sync::atomic::Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("stopping at the next frame, results written (Ctrl-C again: quit at once)");
    });
    if let Err(e) = handler {
        eprintln!("note: Ctrl-C will not end this run cleanly: {e}");
    }
    if let Some(dir) = &a.vis {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    let mut writer = match &a.vis_video {
        Some(p) => Some(prl_track::video::VideoWriter::create(p, w, h, if a.live { 10.0 } else { 25.0 })?),
        None => None,
    };
    // Frame number and time of every frame tracked.
    let stamps: RefCell<Vec<(usize, f64)>> = RefCell::new(vec![]);
    let limit = a.max_frames.unwrap_or(usize::MAX).max(1);
    let frames = VideoFrames { video: &mut video, src, stamps: &stamps, limit };
    let boxes: Vec<BBox> = given.iter().map(|g| g.0).collect();
    let several = boxes.len() > 1;
    let runs = tracking::track_targets(&mut trackers, jobs, frames, &boxes, 0, |i, f, ps| {
        let (index, time) = stamps.borrow()[i];
        if a.jsonl {
            ps.iter()
                .enumerate()
                .for_each(|(k, p)| println!("{}", frame_json(index, Some(time), several.then_some(k + 1), p)));
        }
        if let Some(wr) = writer.as_mut() {
            wr.write(Frame::from_rgb_image(&with_boxes(f, ps, &[])).bgr()).map_err(|e| e.to_string())?;
        }
        match &a.vis {
            Some(dir) => save_vis(dir, index, f, ps, &[]).map_err(|e| format!("{e:#}")),
            None => Ok(()),
        }
    })
    .map_err(|e| quote_init(e, &given.iter().map(|g| g.1.clone()).collect::<Vec<_>>()))?;
    if let Some(wr) = writer {
        wr.finish()?;
        say(format!("video with boxes: {}", a.vis_video.as_ref().expect("set with the writer").display()));
    }
    anyhow::ensure!(!runs[0].boxes.is_empty(), "{src}: no frame at or after frame {} to start on", a.init_frame);
    let stamps = stamps.into_inner();
    if let Some(path) = &a.results {
        for (k, run) in runs.iter().enumerate() {
            let path = target_path(path, k, runs.len());
            // Every frame: pysot's one line a frame, and the confidences beside. Live: the frame
            // number first, frames were dropped.
            if a.live {
                let text: String = run
                    .xywh()
                    .iter()
                    .zip(&stamps)
                    .map(|(b, (n, _))| format!("{n},{},{},{},{}\n", b[0], b[1], b[2], b[3]))
                    .collect();
                write_atomically(&path, text.as_bytes())?;
            } else {
                write_results(&path, run)?;
            }
            say(format!("results: {}", path.display()));
        }
    }
    let summary = Summary::of(&runs[0], None);
    if let Some(path) = &a.json {
        write_atomically(path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    }
    if several {
        say(targets_line(&runs, jobs, &[]));
    }
    say(format!(
        "frames: {} tracked, {} dropped   FPS: {:.1}   ms per frame (median): frame wait {:.1}, crop {:.1}, network {:.1}",
        summary.frames,
        video.dropped(),
        summary.fps,
        summary.decode_ms,
        summary.crop_ms,
        summary.network_ms
    ));
    if stop.load(std::sync::atomic::Ordering::SeqCst) {
        say("stopped on request (Ctrl-C or SIGTERM): the results cover the frames tracked until then".into());
    }
    Ok(())
}

/// A video's frames for the tracking loop, each one's number and time noted in `stamps`.
struct VideoFrames<'a> {
    video: &'a mut prl_track::video::VideoSource,
    src: &'a str,
    stamps: &'a std::cell::RefCell<Vec<(usize, f64)>>,
    /// Frames to track at most.
    limit: usize,
}

impl tracking::FrameStream for VideoFrames<'_> {
    fn next_frame(&mut self) -> Result<Option<Frame>, tracking::TrackError> {
        if self.stamps.borrow().len() >= self.limit {
            return Ok(None);
        }
        let Some(vf) = self.video.next_frame()? else { return Ok(None) };
        self.stamps.borrow_mut().push((vf.index, vf.time.as_secs_f64()));
        Ok(Some(vf.frame))
    }
    fn label(&self) -> String {
        let last = self.stamps.borrow().last().map_or(0, |s| s.0);
        format!("{} frame {last}", self.src)
    }
}
