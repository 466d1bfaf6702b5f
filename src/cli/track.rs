//! `prl track`: run a plan over a frame sequence.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use prl_runtime::{set_threads, BBox, Frame, Plan, Prediction, Tracker};
use prl_track::{init_box_from_groundtruth, iou, load_frame, InputError, Sequence};

use super::write_atomically;

#[derive(Args)]
pub struct TrackArgs {
    /// Plan directory written by `prl compile`.
    #[arg(long, default_value = "models/prl-track/plan")]
    plan: PathBuf,
    /// OTB/UAV123-style sequence folder (`img/`, `groundtruth_rect.txt`); init from its first box.
    #[arg(long, value_name = "DIR", required_unless_present = "frames", conflicts_with = "frames")]
    sequence: Option<PathBuf>,
    /// A bare folder of frames (needs --init).
    #[arg(long, value_name = "DIR", requires = "init")]
    frames: Option<PathBuf>,
    /// Initial box `x,y,w,h` in the first frame (0-based pixels).
    #[arg(long, value_name = "X,Y,W,H", value_parser = parse_init, allow_hyphen_values = true)]
    init: Option<[f64; 4]>,
    /// Write one `x,y,w,h` line per frame here (pysot format; first line the init box).
    #[arg(long, value_name = "FILE")]
    results: Option<PathBuf>,
    /// Write each frame with its box drawn (ground truth too, when known) into this folder.
    #[arg(long, value_name = "DIR")]
    vis: Option<PathBuf>,
    /// Threads for the network (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Track only the first N frames.
    #[arg(long, value_name = "N")]
    max_frames: Option<usize>,
}

fn parse_init(s: &str) -> Result<[f64; 4], String> {
    prl_track::parse_box(s)
}

/// Per-stage times of a run and how the boxes compare with ground truth.
pub struct Summary {
    pub frames: usize,
    pub total: Duration,
    pub decode: Vec<Duration>,
    pub crop: Vec<Duration>,
    pub network: Vec<Duration>,
    pub post: Vec<Duration>,
    pub mean_iou: Option<f64>,
}

fn median_ms(v: &[Duration]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut ms: Vec<f64> = v.iter().map(|d| d.as_secs_f64() * 1e3).collect();
    ms.sort_by(f64::total_cmp);
    ms[ms.len() / 2]
}

impl Summary {
    pub fn print(&self) {
        println!(
            "frames: {}   FPS: {:.1} (whole loop, frame decoding included)",
            self.frames,
            self.frames as f64 / self.total.as_secs_f64()
        );
        println!(
            "ms per frame (median): decode {:.1}, crop {:.1}, network {:.1}, post-processing {:.2}",
            median_ms(&self.decode),
            median_ms(&self.crop),
            median_ms(&self.network),
            median_ms(&self.post)
        );
        if let Some(iou) = self.mean_iou {
            println!("mean IoU with the ground truth: {iou:.3}");
        }
        if let Some(mb) = super::peak_rss_mb() {
            println!("peak resident memory: {mb:.0} MB");
        }
    }
}

/// Track `count` frames given by `frame(i)` from `init`; returns one box per frame (the init
/// box first) and the summary. `label(i)` names frame `i` in errors; `on_frame` sees each frame
/// and its box (for drawing).
pub fn track_frames(
    tracker: &mut Tracker,
    count: usize,
    mut frame: impl FnMut(usize) -> anyhow::Result<Frame>,
    label: impl Fn(usize) -> String,
    init: BBox,
    groundtruth: Option<&[[f64; 4]]>,
    mut on_frame: impl FnMut(usize, &Frame, &BBox) -> anyhow::Result<()>,
) -> anyhow::Result<(Vec<BBox>, Summary)> {
    let pb = indicatif::ProgressBar::new(count as u64);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta}")
            .expect("static template"),
    );
    let start = Instant::now();
    let mut s = Summary {
        frames: count,
        total: Duration::ZERO,
        decode: vec![],
        crop: vec![],
        network: vec![],
        post: vec![],
        mean_iou: None,
    };
    let mut boxes = Vec::with_capacity(count);
    let mut size = (0, 0);
    for i in 0..count {
        let t = Instant::now();
        let f = frame(i)?;
        s.decode.push(t.elapsed());
        if i == 0 {
            size = (f.width(), f.height());
            tracker.init(&f, init).with_context(|| label(i))?;
            boxes.push(init);
        } else {
            if (f.width(), f.height()) != size {
                anyhow::bail!(
                    "{}: frame is {}x{}, the first frame {}x{}: frames of one sequence must have one size",
                    label(i),
                    f.width(),
                    f.height(),
                    size.0,
                    size.1
                );
            }
            let Prediction { bbox, .. } = tracker.track(&f).with_context(|| label(i))?;
            let t = tracker.last_timings();
            s.crop.push(t.crop);
            s.network.push(t.network);
            s.post.push(t.post);
            boxes.push(bbox);
        }
        on_frame(i, &f, boxes.last().expect("pushed"))?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    s.total = start.elapsed();
    if let Some(gt) = groundtruth {
        let ious: Vec<f64> = boxes
            .iter()
            .zip(gt)
            .filter(|(_, g)| g[2] > 0.0 && g[3] > 0.0)
            .map(|(b, g)| iou([b.x, b.y, b.w, b.h], *g))
            .collect();
        s.mean_iou = (!ious.is_empty()).then(|| ious.iter().sum::<f64>() / ious.len() as f64);
    }
    Ok((boxes, s))
}

/// Results in pysot's format: one `x,y,w,h` line per frame.
pub fn results_text(boxes: &[BBox]) -> String {
    boxes.iter().map(|b| format!("{},{},{},{}\n", b.x, b.y, b.w, b.h)).collect()
}

/// Draw `pred` (green) and `gt` (red) on a copy of the frame and save it as JPEG.
pub fn save_vis(dir: &Path, i: usize, f: &Frame, pred: &BBox, gt: Option<[f64; 4]>) -> anyhow::Result<()> {
    let rgb: Vec<u8> = f.bgr().chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect();
    let mut img = image::RgbImage::from_raw(f.width() as u32, f.height() as u32, rgb).expect("frame size");
    if let Some(g) = gt.filter(|g| g.iter().all(|v| v.is_finite())) {
        draw_rect(&mut img, g, [255, 40, 40]);
    }
    draw_rect(&mut img, [pred.x, pred.y, pred.w, pred.h], [40, 255, 40]);
    let path = dir.join(format!("{:06}.jpg", i + 1));
    img.save(&path).with_context(|| format!("{}: cannot write", path.display()))
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
    set_threads(a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())));
    let (mut frames, gt, init) = match (&a.sequence, &a.frames, a.init) {
        (Some(dir), _, init) => {
            let seq = Sequence::open(dir)?;
            let init = match (init, &seq.groundtruth) {
                (Some(b), _) => BBox { x: b[0], y: b[1], w: b[2], h: b[3] },
                (None, Some(gt)) => init_box_from_groundtruth(gt[0]),
                (None, None) => return Err(InputError::new(dir, "no groundtruth_rect.txt: give --init x,y,w,h").into()),
            };
            (seq.frames, seq.groundtruth, init)
        }
        (None, Some(dir), Some(b)) => (Sequence::list_frames(dir)?, None, BBox { x: b[0], y: b[1], w: b[2], h: b[3] }),
        _ => anyhow::bail!("give --sequence DIR, or --frames DIR with --init x,y,w,h"),
    };
    if let Some(n) = a.max_frames {
        frames.truncate(n.max(1));
    }
    if let Some(dir) = &a.vis {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    let t = Instant::now();
    let plan = Plan::load(&a.plan)?;
    let m = plan.manifest();
    println!(
        "plan: {} ({}, {}), loaded in {} ms",
        a.plan.display(),
        m.precision,
        m.weights.note,
        t.elapsed().as_millis()
    );
    if plan.manifest().weights.kind == "random" {
        eprintln!("note: {} holds RANDOM weights: it runs, but it cannot track", a.plan.display());
    }
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    let load = |i: usize| -> anyhow::Result<Frame> { Ok(load_frame(&frames[i])?) };
    let label = |i: usize| frames[i].display().to_string();
    let (boxes, summary) =
        track_frames(&mut tracker, frames.len(), load, label, init, gt.as_deref(), |i, f, b| match &a.vis {
            Some(dir) => save_vis(dir, i, f, b, gt.as_ref().and_then(|g| g.get(i).copied())),
            None => Ok(()),
        })?;
    if let Some(path) = &a.results {
        write_atomically(path, results_text(&boxes).as_bytes())?;
        println!("results: {}", path.display());
    }
    summary.print();
    Ok(())
}
